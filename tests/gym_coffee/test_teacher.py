"""The scripted teacher solves the task, deterministically, with human-like variation."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import gym_coffee
from gym_coffee.env import obs_part
from gym_coffee.teacher import ScriptedTeacher


def run_episode(env, teacher, seed):
    obs, info = env.reset(seed=seed)
    teacher.reset(seed=seed)
    actions, observations = [], [obs]
    done = False
    while not done:
        action = teacher.act(obs)
        assert env.action_space.contains(action)
        obs, _, terminated, truncated, info = env.step(action)
        actions.append(action)
        observations.append(obs)
        done = terminated or truncated
    return np.array(actions), np.array(observations), info


@pytest.fixture(scope="module")
def env():
    env = gym.make(gym_coffee.ENV_ID)
    yield env
    env.close()


@pytest.mark.parametrize("seed", [0, 7, 1234])
def test_teacher_succeeds(env, seed):
    teacher = ScriptedTeacher(env)
    _, observations, info = run_episode(env, teacher, seed)
    assert info["is_success"], info
    assert info["cup_grasped"] and info["cup_placed"] and info["button_pressed"]
    assert len(observations) - 1 < env.spec.max_episode_steps


def test_teacher_is_deterministic_and_varies(env):
    teacher = ScriptedTeacher(env)
    a1, o1, _ = run_episode(env, teacher, 3)
    a2, o2, _ = run_episode(env, teacher, 3)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(o1, o2)
    # Same layout, different teacher seed: a different (human-like) demonstration.
    obs, _ = env.reset(seed=3)
    teacher.reset(obs, seed=99)
    first = teacher.duration
    teacher.reset(obs, seed=3)
    assert teacher.duration != first
    ee_a = teacher.target(2.0)[0]
    teacher.reset(obs, seed=99)
    assert np.linalg.norm(teacher.target(2.0)[0] - ee_a) > 1e-3


def test_teacher_replans_on_a_new_episode(env):
    teacher = ScriptedTeacher(env, rng=0)
    obs, _ = env.reset(seed=1)
    teacher.act(obs)
    cup_1 = obs_part(obs, "cup_init_pos").copy()
    obs, _ = env.reset(seed=2)
    teacher.act(obs)  # time went back to 0: plans for the new layout
    grasp = next(s for s in teacher.segments if s.name == "reach").p1
    assert np.linalg.norm(grasp[:2] - obs_part(obs, "cup_init_pos")[:2]) < 0.02
    assert np.linalg.norm(grasp[:2] - cup_1[:2]) > 1e-3
