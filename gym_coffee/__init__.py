"""gym-coffee: a PyBullet Gymnasium version of the coffee task of Schneider & Ertel (IROS 2010).

``import gym_coffee`` registers the environments listed in :data:`ENV_IDS`. The public names below
are imported lazily, so registering the environment does not load PyBullet.
"""

from __future__ import annotations

import importlib
from typing import Any

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

ENV_IDS: list[str] = ["gym_coffee/CoffeeTask-v0"]

if "gym_coffee/CoffeeTask-v0" not in registry:
    register(
        id="gym_coffee/CoffeeTask-v0",
        entry_point="gym_coffee.env:CoffeeEnv",
        max_episode_steps=400,
    )

_LAZY = {
    "CoffeeEnv": "gym_coffee.env",
    "OBS_SLICES": "gym_coffee.env",
    "PandaKinematics": "gym_coffee.kinematics",
    "ScriptedTeacher": "gym_coffee.teacher",
    "Demonstration": "gym_coffee.demonstrations",
    "DemonstrationSet": "gym_coffee.demonstrations",
    "collect_demonstrations": "gym_coffee.demonstrations",
}

__all__ = ["ENV_IDS", "__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'gym_coffee' has no attribute {name!r}")
