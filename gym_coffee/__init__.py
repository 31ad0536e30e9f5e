"""gym-coffee: a PyBullet Gymnasium version of the coffee task of Schneider & Ertel (IROS 2010).

``import gym_coffee`` registers the environments listed in :data:`ENV_IDS`. The public names below
are imported lazily, so registering the environment does not load PyBullet.
"""

from __future__ import annotations

import importlib
from typing import Any

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

#: The default environment id (the easy level). Every module refers to it through this name.
ENV_ID = "gym_coffee/CoffeeTask-v0"
#: Every registered id.
ENV_IDS: list[str] = [ENV_ID]
#: The task's stages in order: the ``info`` flags an episode reaches one after the other.
#: ``info["is_success"]`` is the whole task (pressed while the cup stands placed).
STAGES: tuple[str, ...] = ("cup_grasped", "cup_placed", "button_pressed")

if ENV_ID not in registry:
    register(
        id=ENV_ID,
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

__all__ = ["ENV_ID", "ENV_IDS", "STAGES", "__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'gym_coffee' has no attribute {name!r}")
