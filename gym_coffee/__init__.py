"""gym-coffee: a PyBullet Gymnasium version of the coffee task of Schneider & Ertel (IROS 2010).

``import gym_coffee`` registers the environments listed in :data:`ENV_IDS`.
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

ENV_IDS: list[str] = ["gym_coffee/CoffeeTask-v0"]

if "gym_coffee/CoffeeTask-v0" not in registry:
    register(
        id="gym_coffee/CoffeeTask-v0",
        entry_point="gym_coffee.env:CoffeeEnv",
        max_episode_steps=400,
    )

__all__ = ["ENV_IDS", "__version__"]
