"""Robot models and action mappings: what the reproduction needs to know about a robot.

A :class:`RobotModel` is the kinematics Algorithm 3 steers with: the pose of the point the
demonstrations describe (the end effector's *grasp point*) and its geometric Jacobian, for one
state ``q (k,)`` or a batch ``(n, k)``. An :class:`ActionMap` turns the reproduction's state
increment and gripper command into the environment's action.

Built-ins:

* :class:`CartesianPointRobot`: the state *is* the end-effector position (``d = 2`` or ``3``);
  forward pose = identity, Jacobian = ``I``. For environments with end-effector actions
  (panda-gym, the coffee env's ``action_type="ee"``, a 2-D point mass).
* :class:`CartesianDeltaAction`: ``a = clip(dx / max_step, -1, 1)`` followed by the gripper.
* :class:`JointDeltaAction`: the same for joint deltas (the Panda of the coffee env).

The Panda of the coffee env lives in :mod:`lgp_policy.lfd.adapters.coffee` (``PandaModel``).

This module imports only numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "ActionMap",
    "CartesianDeltaAction",
    "CartesianPointRobot",
    "GripperSpec",
    "JointDeltaAction",
    "RobotModel",
]


@runtime_checkable
class RobotModel(Protocol):
    """Kinematics of the robot whose state the policy steers (batched).

    Attributes:
        n_joints: ``k``, length of the robot state the reproduction steers (joint positions of an
            arm; the end-effector position of a point robot).
        dim: ``d``, dimension of the task space (2 or 3); frames' positions have this length.
        has_orientation: whether :meth:`forward_pose`'s rotation depends on the state (an arm's
            hand); a point robot's does not (then an approach point adds nothing).
        joint_lower, joint_upper: ``(k,)`` limits of the state (``-inf``/``inf`` if none).
    """

    n_joints: int
    dim: int
    has_orientation: bool
    joint_lower: NDArray[np.float64]
    joint_upper: NDArray[np.float64]

    def forward_pose(self, q: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """End-effector position ``(..., d)`` and orientation ``(..., d, d)`` (columns: the
        hand's axes; for ``d = 3`` the last column is the approach axis) for ``q (..., k)``."""
        ...

    def jacobian(self, q: ArrayLike) -> NDArray[np.float64]:
        """Geometric Jacobian ``(..., d + r, k)``: ``d`` position rows, then ``r`` angular rows
        (``r = 3`` for ``d = 3``, ``1`` for ``d = 2``) for ``q (..., k)``."""
        ...


@dataclass(frozen=True)
class GripperSpec:
    """The gripper as a named part of the robot's command.

    Attributes:
        closed, open: the command values of a fully closed and a fully open gripper, in the units
            the demonstrations record it (metres of finger opening for the Panda; panda-gym's
            ``[-1, 1]`` action entry). The midpoint is the closing/opening event used to align
            demonstrations in time.
    """

    closed: float
    open: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.closed) and np.isfinite(self.open)) or self.closed == self.open:
            raise ValueError(
                f"gripper needs finite, distinct closed/open values, got {self.closed}, {self.open}"
            )

    @property
    def midpoint(self) -> float:
        """The command half way between closed and open."""
        return 0.5 * (self.closed + self.open)


class CartesianPointRobot:
    """A robot whose state is its end-effector position (``d = 2`` or ``3``): ``x = q``, ``J = I``.

    Args:
        dim: 2 or 3.
        lower, upper: optional workspace bounds ``(d,)`` (default unbounded).

    Example:
        >>> robot = CartesianPointRobot(2)
        >>> robot.forward_pose(np.zeros((5, 2)))[0].shape, robot.jacobian(np.zeros(2)).shape
        ((5, 2), (3, 2))
    """

    has_orientation = False

    def __init__(
        self, dim: int = 3, lower: ArrayLike | None = None, upper: ArrayLike | None = None
    ) -> None:
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim!r}")
        self.dim = self.n_joints = int(dim)
        self.joint_lower = _bound(lower, -np.inf, dim, "lower")
        self.joint_upper = _bound(upper, np.inf, dim, "upper")
        if np.any(self.joint_lower >= self.joint_upper):
            raise ValueError("lower must be below upper in every dimension")

    def forward_pose(self, q: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        x = _state(q, self.dim)
        return x.copy(), np.broadcast_to(np.eye(self.dim), (*x.shape[:-1], self.dim, self.dim))

    def jacobian(self, q: ArrayLike) -> NDArray[np.float64]:
        x = _state(q, self.dim)
        r = 3 if self.dim == 3 else 1
        J = np.vstack([np.eye(self.dim), np.zeros((r, self.dim))])
        return np.broadcast_to(J, (*x.shape[:-1], *J.shape))

    def __repr__(self) -> str:
        return f"CartesianPointRobot(dim={self.dim})"


def _bound(value: ArrayLike | None, default: float, dim: int, name: str) -> NDArray[np.float64]:
    if value is None:
        return np.full(dim, default)
    b = np.asarray(value, dtype=float).reshape(-1)
    if b.shape != (dim,) or np.any(np.isnan(b)):
        raise ValueError(f"{name} must be {dim} numbers, got {value!r}")
    return b


def _state(q: ArrayLike, k: int) -> NDArray[np.float64]:
    x = np.asarray(q, dtype=float)
    if x.shape[-1:] != (k,):
        raise ValueError(f"q must have shape (..., {k}), got {x.shape}")
    return x


class ActionMap(Protocol):
    """Turns a state increment and a gripper command into the environment's action (batched).

    Attributes:
        max_step: largest change of one state coordinate per control step (rad or m); the
            reproduction scales a larger increment down as a whole (keeping its direction).
    """

    @property
    def max_step(self) -> float: ...

    def __call__(
        self, q: NDArray[np.float64], step: NDArray[np.float64], gripper: NDArray[np.float64]
    ) -> NDArray[np.float32]:
        """``q (n, k)``, ``step (n, k)`` (already limited), ``gripper (n,)`` -> ``(n, a)``."""
        ...


@dataclass(frozen=True)
class _DeltaAction:
    max_step: float
    gripper: GripperSpec | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.max_step) and self.max_step > 0):
            raise ValueError(f"max_step must be finite and > 0, got {self.max_step!r}")

    def __call__(
        self, q: NDArray[np.float64], step: NDArray[np.float64], gripper: NDArray[np.float64]
    ) -> NDArray[np.float32]:
        step = np.asarray(step, dtype=float)
        k = step.shape[-1]
        g = self.gripper
        if step.shape == (1, k):  # one environment: the same arithmetic on floats
            return self._one(step[0].tolist(), gripper)
        out = np.empty((*step.shape[:-1], k + (g is not None)))
        np.divide(step, self.max_step, out=out[..., :k])
        if g is not None:
            arr = np.asarray(gripper, dtype=float)
            grip = float(arr.reshape(-1)[0]) if arr.size == 1 else arr  # one: on a float
            out[..., k] = -1.0 + 2.0 * (grip - g.closed) / (g.open - g.closed)
        return np.minimum(np.maximum(out, -1.0, out=out), 1.0, out=out).astype(np.float32)

    def _one(self, step: list[float], gripper: ArrayLike) -> NDArray[np.float32]:
        g = self.gripper
        out = [v / self.max_step for v in step]
        if g is not None:
            grip = float(np.asarray(gripper).item(0))
            out.append(-1.0 + 2.0 * (grip - g.closed) / (g.open - g.closed))
        return np.array([min(max(v, -1.0), 1.0) for v in out], dtype=np.float32)[None]


class JointDeltaAction(_DeltaAction):
    """Action ``[clip(dq / max_step, -1, 1), gripper]`` for an arm commanded by joint deltas.

    Args:
        max_step: rad per control step at action ``1``.
        gripper: the gripper command's range, mapped to ``[-1 (closed), 1 (open)]``; ``None``:
            no gripper entry.
    """


class CartesianDeltaAction(_DeltaAction):
    """Action ``[clip(dx / max_step, -1, 1), gripper]`` for end-effector delta actions.

    Args:
        max_step: metres per control step at action ``1`` (panda-gym: 0.05).
        gripper: as for :class:`JointDeltaAction`.
    """
