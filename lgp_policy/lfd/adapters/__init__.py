"""Observation adapters: how :class:`~lgp_policy.lfd.policy.GPDemonstrationPolicy` reads a task.

An adapter turns a batch of the environment's observations into what the policy needs
(:class:`Observed`: time, robot state, named frames, optional event flags) and carries the robot's
kinematics (:class:`~lgp_policy.lfd.robots.RobotModel`), the action mapping
(:class:`~lgp_policy.lfd.robots.ActionMap`) and the gripper's command range. The policy never
indexes an observation itself.

* :class:`ArrayAdapter`: built from index slices of a flat observation vector (or a function), for
  any environment; see ``examples/plain_arrays_2d.py`` and ``examples/panda_gym_pick_and_place.py``.
* :mod:`lgp_policy.lfd.adapters.coffee`: the gym-coffee task (Panda, joint-delta actions, frames
  ``cup`` and ``machine``), the only module of :mod:`lgp_policy.lfd` that imports ``gym_coffee``.

Frames in an observation: ``Observed.frames[name] = (position (n, d), rotation (n, d, d))`` for
*every* frame the policy was fitted with (a missing one is an error). ``Observed.valid[name]``
``(n,)`` says whether the frame was observed in that row; where it was not (an occluded or
grasped object) the policy keeps its last estimate.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from lgp_policy.lfd.robots import ActionMap, GripperSpec, RobotModel

__all__ = [
    "ArrayAdapter",
    "ObservationAdapter",
    "Observed",
    "rotation_about_z",
    "rotation_from_angle",
]


@dataclass
class Observed:
    """What an adapter reads from a batch of ``n`` observations.

    Attributes:
        time: ``(n,)`` seconds since the episode started, or ``None`` if the observation has no
            clock (the policy then counts control steps itself; pass ``episode_start``).
        state: ``(n, k)`` robot state.
        frames: ``{name: (position (n, d), rotation (n, d, d))}``.
        valid: ``{name: (n,) bool}``; frames not listed are observed in every row.
        events: ``{name: (n,) bool}`` task events seen in this observation (e.g. the cup is held).
    """

    time: NDArray[np.float64] | None
    state: NDArray[np.float64]
    frames: dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]
    valid: dict[str, NDArray[np.bool_]] = field(default_factory=dict)
    events: dict[str, NDArray[np.bool_]] = field(default_factory=dict)


@runtime_checkable
class ObservationAdapter(Protocol):
    """How the policy reads one environment (see the module docstring).

    Attributes:
        name: saved in the policy file (``load`` finds a built-in adapter by it).
        obs_dim: length of one observation vector.
        frame_names: the frames :meth:`read` returns.
        robot: the robot's kinematics.
        action_map: state increment + gripper -> action.
        gripper: the gripper command's range (``None``: no gripper).
        control_dt: seconds per control step.
    """

    name: str
    obs_dim: int
    frame_names: tuple[str, ...]
    robot: RobotModel
    action_map: ActionMap
    gripper: GripperSpec | None
    control_dt: float

    def read(self, observation: NDArray[np.float64]) -> Observed:
        """Read a batch ``(n, obs_dim)`` of observations."""
        ...


_ROTATIONS: dict[tuple[float, int], NDArray[Any]] = {}  # (angle, dim) -> read-only rotation
_MAX_CACHED_ROTATIONS = 16


def rotation_from_angle(angle: NDArray[np.float64], dim: int) -> NDArray[np.float64]:
    """Rotations ``(n, d, d)`` by ``angle (n,)`` about the z axis (``d = 3``) or in the plane
    (read-only), in closed form from ``cos`` and ``sin``.

    One angle is looked up among the last few computed (static objects observed every step)."""
    a = np.asarray(angle, dtype=float).reshape(-1)
    if a.shape == (1,):
        return rotation_about_z(float(a[0]), dim)
    return _rotations(a, dim)


def rotation_about_z(angle: float, dim: int) -> NDArray[np.float64]:
    """:func:`rotation_from_angle` of one angle given as a float, ``(1, d, d)`` (read-only; the
    last few computed are kept: static objects are observed every step)."""
    key = (angle, dim)
    cached = _ROTATIONS.get(key)
    if cached is None:
        c, s = math.cos(angle), math.sin(angle)
        flat = [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0] if dim == 3 else [c, -s, s, c]
        cached = np.array(flat).reshape(1, dim, dim)
        cached.setflags(write=False)
        if len(_ROTATIONS) >= _MAX_CACHED_ROTATIONS:
            _ROTATIONS.clear()
        _ROTATIONS[key] = cached
    return cached


def _rotations(a: NDArray[np.float64], dim: int) -> NDArray[np.float64]:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((a.shape[0], dim, dim))
    R[:, 0, 0] = c
    R[:, 0, 1] = -s
    R[:, 1, 0] = s
    R[:, 1, 1] = c
    if dim == 3:
        R[:, 2, 2] = 1.0
    R.setflags(write=False)
    return R


FrameSpec = tuple[slice, "slice | str | None"]


class ArrayAdapter:
    """An adapter for flat observation vectors, from index slices.

    Args:
        obs_dim: length of an observation.
        state: slice of the robot state.
        frames: ``{name: (position slice, rotation)}`` with rotation ``None`` (identity), a slice
            of one angle (yaw about z, or the planar angle for ``d = 2``) or of a quaternion
            ``(x, y, z, w)`` (4 entries, ``d = 3``).
        robot, action_map, gripper: see :class:`ObservationAdapter`.
        control_dt: seconds per control step.
        time: slice of the observation's clock (seconds since reset), or ``None``.
        events: ``{name: function(obs (n, obs_dim)) -> (n,) bool}``.
        valid: ``{frame name: function(obs) -> (n,) bool}`` (default: always observed).
        name: the adapter's name.

    Example (a 2-D point robot; observation = ``[x, y, goal_x, goal_y]``)::

        adapter = ArrayAdapter(4, state=slice(0, 2), frames={"goal": (slice(2, 4), None)},
                               robot=CartesianPointRobot(2),
                               action_map=CartesianDeltaAction(0.05), control_dt=0.1)
    """

    def __init__(
        self,
        obs_dim: int,
        *,
        state: slice,
        frames: Mapping[str, tuple[slice, slice | None]],
        robot: RobotModel,
        action_map: ActionMap,
        control_dt: float,
        gripper: GripperSpec | None = None,
        time: slice | None = None,
        events: Mapping[str, Callable[[NDArray[np.float64]], NDArray[np.bool_]]] | None = None,
        valid: Mapping[str, Callable[[NDArray[np.float64]], NDArray[np.bool_]]] | None = None,
        name: str = "array",
    ) -> None:
        if not (isinstance(obs_dim, int) and obs_dim > 0):
            raise ValueError(f"obs_dim must be a positive int, got {obs_dim!r}")
        if not (np.isfinite(control_dt) and control_dt > 0):
            raise ValueError(f"control_dt must be finite and > 0, got {control_dt!r}")
        self.obs_dim = obs_dim
        self.name = name
        self.robot = robot
        self.action_map = action_map
        self.gripper = gripper
        self.control_dt = float(control_dt)
        self._time = time
        self._state = state
        k = len(range(*state.indices(obs_dim)))
        if k != robot.n_joints:
            raise ValueError(f"state slice has {k} entries, the robot has {robot.n_joints}")
        self._frames: dict[str, tuple[slice, slice | None]] = {}
        for fname, (pos, rot) in dict(frames).items():
            d = len(range(*pos.indices(obs_dim)))
            if d != robot.dim:
                raise ValueError(
                    f"frame {fname!r}: position slice has {d} entries, need {robot.dim}"
                )
            if rot is not None and len(range(*rot.indices(obs_dim))) not in (1, 4):
                raise ValueError(
                    f"frame {fname!r}: rotation slice must hold an angle or a quaternion"
                )
            self._frames[fname] = (pos, rot)
        self.frame_names = tuple(sorted(self._frames))
        self._events = dict(events or {})
        self._valid = dict(valid or {})
        unknown = sorted(set(self._valid) - set(self._frames))
        if unknown:
            raise ValueError(f"valid names unknown frames {unknown}; frames are {self.frame_names}")

    def read(self, observation: NDArray[np.float64]) -> Observed:
        obs = observation
        n = obs.shape[0]
        d = self.robot.dim
        frames = {}
        for fname, (pos, rot) in self._frames.items():
            if rot is None:
                R = np.broadcast_to(np.eye(d), (n, d, d))
            else:
                r = obs[:, rot]
                if r.shape[1] == 1:
                    R = rotation_from_angle(r[:, 0], d)
                else:
                    from scipy.spatial.transform import Rotation

                    R = Rotation.from_quat(r).as_matrix()
            frames[fname] = (obs[:, pos], R)
        return Observed(
            time=None if self._time is None else obs[:, self._time][:, 0],
            state=obs[:, self._state],
            frames=frames,
            valid={k: np.asarray(f(obs), dtype=bool) for k, f in self._valid.items()},
            events={k: np.asarray(f(obs), dtype=bool) for k, f in self._events.items()},
        )

    def __repr__(self) -> str:
        return (
            f"ArrayAdapter(name={self.name!r}, obs_dim={self.obs_dim}, frames={self.frame_names})"
        )
