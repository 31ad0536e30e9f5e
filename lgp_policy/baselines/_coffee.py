"""The coffee task's specifics for the baselines, in one place.

Everything the baselines need to know about ``gym_coffee`` (where the time, the joints and the
object poses are in an observation; how a joint target becomes an action; the default robot
model) goes through this module, so that a baseline itself only sees arrays. ``gym_coffee`` is
imported lazily, as in :mod:`lgp_policy.lfd.policy`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from lgp_policy.lfd.policy import demonstration_frames

__all__ = [
    "CoffeeSpec",
    "coffee_spec",
    "demonstration_frames",
    "layout_features",
]

Frames = dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]


class CoffeeSpec:
    """Observation layout, action scaling and robot model of the coffee task."""

    def __init__(self) -> None:
        from gym_coffee.env import OBS_SLICES
        from gym_coffee.robot import GRIPPER_MAX_OPENING, MAX_JOINT_STEP

        self.slices: dict[str, slice] = dict(OBS_SLICES)
        self.max_joint_step = float(MAX_JOINT_STEP)
        self.gripper_max_opening = float(GRIPPER_MAX_OPENING)
        self.obs_dim = max(s.stop for s in self.slices.values())

    def time(self, obs: NDArray[np.float64]) -> float:
        """Seconds since reset."""
        return float(obs[self.slices["time"]][0])

    def joint_pos(self, obs: NDArray[np.float64]) -> NDArray[np.float64]:
        """Measured arm joint positions ``(7,)``."""
        return np.asarray(obs[self.slices["joint_pos"]], dtype=float)

    def frames(self, obs: NDArray[np.float64]) -> Frames:
        """Object frames ``{name: (origin (3,), rotation (3, 3))}`` of one observation, as the
        GP policy builds them (cup: initial position; machine: position and yaw)."""
        from gym_coffee.env import object_frames

        return object_frames(obs)

    def layout(self, obs: NDArray[np.float64]) -> NDArray[np.float64]:
        """The layout features of one observation (see :func:`layout_features`)."""
        return layout_features(self.frames(obs))

    def action(
        self, q: NDArray[np.float64], q_target: NDArray[np.float64], gripper: float
    ) -> NDArray[np.float32]:
        """The env action that commands ``q_target`` from ``q`` and a gripper opening (m)."""
        from gym_coffee.robot import action_from_targets

        return action_from_targets(q, q_target, gripper)

    def gripper_opening(self, command: NDArray[np.float64]) -> NDArray[np.float64]:
        """Gripper opening (m) of the action's gripper command in ``[-1, 1]``."""
        return (np.asarray(command, dtype=float) + 1.0) / 2.0 * self.gripper_max_opening

    def check_obs(self, observation: Any) -> NDArray[np.float64]:
        """``(OBS_DIM,)`` or ``(n, OBS_DIM)`` as a 2-D float array; a clear error otherwise."""
        obs = np.asarray(observation, dtype=float)
        if obs.ndim not in (1, 2) or obs.shape[-1] != self.obs_dim:
            raise ValueError(
                f"observation must be (OBS_DIM,) or (n_envs, OBS_DIM) with OBS_DIM = "
                f"{self.obs_dim}, got shape {obs.shape}"
            )
        return np.atleast_2d(obs)


def default_robot() -> Any:
    """The Panda's kinematics (``RobotModel``: FK, Jacobian, joint limits)."""
    from gym_coffee.kinematics import PandaKinematics

    return PandaKinematics()


def layout_features(frames: Frames) -> NDArray[np.float64]:
    """A layout as a vector: each object's origin and its yaw ``(cos, sin)`` scaled to metres
    (0.1 m per radian-sized change), objects in name order."""
    parts = []
    for name in sorted(frames):
        origin, rotation = frames[name]
        parts.append(np.asarray(origin, dtype=float))
        parts.append(0.1 * np.asarray(rotation, dtype=float)[:2, 0])
    return np.concatenate(parts)


def coffee_spec() -> CoffeeSpec:
    """The coffee task's :class:`CoffeeSpec`."""
    return CoffeeSpec()
