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
#: Difficulty levels and their registered ids (``CoffeeEnv``'s ``level`` argument; see its
#: docstring): the same task, the hard level with the machine on either side and wider regions.
LEVELS: dict[str, str] = {"easy": ENV_ID, "hard": "gym_coffee/CoffeeTaskHard-v0"}
#: Every registered id.
ENV_IDS: list[str] = list(LEVELS.values())
#: The task's stages in order: the ``info`` flags an episode reaches one after the other.
#: ``info["is_success"]`` is the whole task (pressed while the cup stands placed).
STAGES: tuple[str, ...] = ("cup_grasped", "cup_placed", "button_pressed")
#: ``physics`` presets of ``CoffeeEnv``: (physics time step (s), physics steps per control step,
#: solver iterations, solver residual threshold: ``Simulation``'s ``solver_residual``, PyBullet's
#: ``solverResidualThreshold``, the squared velocity correction below which the solver stops
#: iterating early). ``"default"`` is the task's physics: 10 steps of 4 ms, at most 50 solver
#: iterations, stopping once the largest correction of a sweep is below 1.7 cm/s (3e-4); ``"fast"``
#: (5 physics steps of 8 ms, 20 solver iterations; the same 40 ms control period) makes
#: ``env.step`` ~40% cheaper but gives other trajectories (see docs/design-env.md, "Physics
#: settings").
PHYSICS_PRESETS: dict[str, tuple[float, int, int, float]] = {
    "default": (1.0 / 250.0, 10, 50, 3e-4),
    "fast": (1.0 / 125.0, 5, 20, 1e-7),
}

for _level, _env_id in LEVELS.items():
    if _env_id not in registry:
        register(
            id=_env_id,
            entry_point="gym_coffee.env:CoffeeEnv",
            max_episode_steps=400,  # gym_coffee.env.MAX_EPISODE_STEPS (not imported: no PyBullet)
            kwargs={"level": _level},
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

__all__ = ["ENV_ID", "ENV_IDS", "LEVELS", "PHYSICS_PRESETS", "STAGES", "__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'gym_coffee' has no attribute {name!r}")
