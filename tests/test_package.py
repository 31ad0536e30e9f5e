import gymnasium as gym

import gym_coffee
import lgp_policy


def test_versions_match():
    assert gym_coffee.__version__ == lgp_policy.__version__


def test_env_ids_registered():
    for env_id in gym_coffee.ENV_IDS:
        assert env_id in gym.registry
