"""Demonstrations as plain arrays, the input of
:class:`~lgp_policy.lfd.policy.GPDemonstrationPolicy`.

A :class:`Trajectory` is one demonstration of ``n`` steps:

* ``time (n,)``: seconds (or steps) since the start, strictly increasing;
* ``state (n, k)``: the robot state the policy steers (joint positions of an arm, the
  end-effector position of a point robot, see :mod:`lgp_policy.lfd.robots`);
* ``gripper (n,)``: the *commanded* gripper (a named part of the command; optional);
* ``frames``: ``{name: (position (n, d) or (d,), rotation (n, d, d) or (d, d))}``, any number of
  named object frames (``d`` = 2 or 3). Rotations may also be given as a
  ``scipy.spatial.transform.Rotation`` (3-D). The policy learns the hand relative to each frame's
  pose at the first step;
* ``events``: optional ``{name: (n,) bool}`` flags (e.g. ``"cup_grasped"``): the phase at which
  each first becomes true is kept, and an event-driven phase waits for them;
* ``success``: whether the demonstration succeeded (failed ones are refused by ``fit`` unless
  ``allow_failed=True``).

A :class:`TrajectorySet` is a list of trajectories naming the same frames.

Example (2-D, plain numpy)::

    t = np.arange(50) * 0.1
    path = np.linspace([0.0, 0.0], [1.0, 0.5], 50)
    demo = Trajectory(t, path, frames={"goal": ([1.0, 0.5], np.eye(2))})

This module imports only numpy and scipy.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

__all__ = [
    "FrameLike",
    "Trajectory",
    "TrajectorySet",
    "as_rotation_matrices",
    "check_finite",
    "check_time_stamps",
    "real_array",
]

FrameLike = tuple[ArrayLike, ArrayLike | Rotation]
"""A frame as given: ``(position, rotation)``, per step or constant."""


def real_array(value: Any, where: str) -> NDArray[np.float64]:
    """``value`` as a float array, or a ValueError naming ``where``."""
    try:
        raw = np.asarray(value)
        if raw.dtype.kind not in "biuf":
            raise TypeError(f"dtype {raw.dtype}")
        return np.asarray(raw, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where} must be an array of real numbers ({exc})") from None


def check_finite(a: NDArray[np.float64], where: str) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        at = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(
            f"{where} contains NaN or infinity (first at index {at[0] if len(at) == 1 else at})"
        )


def check_time_stamps(value: Any, where: str) -> NDArray[np.float64]:
    """One demonstration's time stamps: 1-D, at least 2, finite, strictly increasing; a
    ValueError names ``where`` (e.g. ``times[2]``) and the offending stamps."""
    t = real_array(value, where)
    if t.ndim != 1:
        raise ValueError(f"{where} must be 1-D, (n,) time stamps, got shape {t.shape}")
    if t.size < 2:
        raise ValueError(f"{where} needs at least 2 time stamps, got {t.size}")
    check_finite(t, where)
    step = np.diff(t)
    if np.any(step <= 0):
        k = int(np.argmax(step <= 0))
        raise ValueError(
            f"{where} must be strictly increasing, but {where}[{k + 1}] = {float(t[k + 1])!r} "
            f"follows {where}[{k}] = {float(t[k])!r}"
        )
    if not np.isfinite(t[-1] - t[0]):
        raise ValueError(
            f"{where} spans {float(t[0])!r} to {float(t[-1])!r}: its duration is not finite"
        )
    return t


def as_rotation_matrices(rotation: ArrayLike | Rotation, n: int, d: int, name: str) -> NDArray:
    """Rotation matrices ``(n, d, d)`` from a constant ``(d, d)``, per-step ``(n, d, d)`` or a
    scipy ``Rotation`` (one or ``n``); checked to be orthonormal with determinant 1."""
    if isinstance(rotation, Rotation):
        if d != 3:
            raise ValueError(f"frame {name!r}: a scipy Rotation needs 3-D positions, got d={d}")
        R = rotation.as_matrix()
    else:
        R = np.asarray(rotation, dtype=float)
    if R.shape == (d, d):
        R = np.broadcast_to(R, (n, d, d))
    if R.shape != (n, d, d):
        raise ValueError(
            f"frame {name!r}: rotation must be ({d}, {d}) or ({n}, {d}, {d}), got {R.shape}"
        )
    if not np.all(np.isfinite(R)):
        raise ValueError(f"frame {name!r}: rotation contains NaN or inf")
    err = np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(d)).max()
    if err > 1e-5 or np.any(np.linalg.det(R) < 0):
        raise ValueError(f"frame {name!r}: rotation is not a proper rotation (orthonormal, det 1)")
    return np.ascontiguousarray(R)


@dataclass
class Trajectory:
    """One demonstration as plain arrays (see the module docstring).

    Args:
        time: ``(n,)`` strictly increasing.
        state: ``(n, k)`` robot state.
        frames: ``{name: (position, rotation)}``; position ``(d,)`` or ``(n, d)``.
        gripper: ``(n,)`` commanded gripper, or ``None``.
        actions: ``(n, a)`` the actions taken (kept for replay baselines; not used by the GP).
        events: ``{name: (n,) bool}``.
        success: whether the demonstration succeeded.

    Attributes are stored converted: ``frames[name] = (position (n, d), rotation (n, d, d))``.
    """

    time: NDArray[Any]
    state: NDArray[Any]
    frames: dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]] = field(default_factory=dict)
    gripper: NDArray[Any] | None = None
    actions: NDArray[Any] | None = None
    events: dict[str, NDArray[np.bool_]] = field(default_factory=dict)
    success: bool = True

    def __post_init__(self) -> None:
        t = check_time_stamps(self.time, "time")
        n = t.size
        self.time = t
        self.state = _steps("state", self.state, n)
        if self.gripper is not None:
            self.gripper = _steps("gripper", self.gripper, n, vector=True)
        if self.actions is not None:
            self.actions = _steps("actions", self.actions, n)
        frames = {}
        if not isinstance(self.frames, Mapping):
            raise TypeError(
                "frames must be a mapping name -> (position, rotation), got "
                f"{type(self.frames).__name__}"
            )
        for name, frame in self.frames.items():
            if not isinstance(name, str) or not name:
                raise ValueError(f"frame names must be non-empty strings, got {name!r}")
            try:
                pos, rot = frame
            except (TypeError, ValueError):
                raise ValueError(f"frame {name!r} must be (position, rotation)") from None
            p = np.asarray(pos, dtype=float)
            if p.ndim == 1:
                p = np.broadcast_to(p, (n, p.size))
            if p.ndim != 2 or p.shape[0] != n or p.shape[1] not in (2, 3):
                raise ValueError(
                    f"frame {name!r}: position must be (d,) or ({n}, d) with d 2 or 3, got "
                    f"{np.shape(pos)}"
                )
            if not np.all(np.isfinite(p)):
                raise ValueError(f"frame {name!r}: position contains NaN or inf")
            frames[name] = (np.ascontiguousarray(p), as_rotation_matrices(rot, n, p.shape[1], name))
        self.frames = frames
        self.events = {
            str(k): _steps(f"events[{k!r}]", v, n, vector=True, dtype=bool)
            for k, v in dict(self.events).items()
        }
        self.success = bool(self.success)

    def __len__(self) -> int:
        return int(self.time.size)

    @property
    def frame_names(self) -> list[str]:
        """The frames' names, sorted."""
        return sorted(self.frames)

    def initial_frames(self) -> dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]:
        """Each frame's pose at the first step: ``{name: (position (d,), rotation (d, d))}``."""
        return {k: (p[0], R[0]) for k, (p, R) in self.frames.items()}

    def event_times(self) -> dict[str, float | None]:
        """Time at which each event first became true (``None`` if never)."""
        out: dict[str, float | None] = {}
        for k, flags in self.events.items():
            idx = np.flatnonzero(flags)
            out[k] = float(self.time[idx[0]]) if idx.size else None
        return out


def _steps(
    name: str, value: Any, n: int, *, vector: bool = False, dtype: Any = float
) -> NDArray[Any]:
    a = np.asarray(value, dtype=dtype)
    ok = a.shape == (n,) if vector else (a.ndim == 2 and a.shape[0] == n and a.shape[1] >= 1)
    if not ok:
        want = f"({n},)" if vector else f"({n}, k)"
        raise ValueError(f"{name} must have shape {want} (one row per time step), got {a.shape}")
    if dtype is float and not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or inf")
    return a


class TrajectorySet(Sequence[Trajectory]):
    """Demonstrations that name the same frames, with consistent shapes.

    Args:
        trajectories: at least one :class:`Trajectory`.
        metadata: free-form information (e.g. the environment id).
    """

    def __init__(
        self, trajectories: Iterable[Trajectory], metadata: Mapping[str, Any] | None = None
    ) -> None:
        items = list(trajectories)
        if not items:
            raise ValueError("need at least one demonstration")
        for i, tr in enumerate(items):
            if not isinstance(tr, Trajectory):
                raise TypeError(f"item {i} is a {type(tr).__name__}, not a Trajectory")
        first = items[0]
        for i, tr in enumerate(items[1:], start=1):
            if tr.frame_names != first.frame_names:
                raise ValueError(
                    f"demonstration {i} names the frames {tr.frame_names}, "
                    f"demonstration 0 names {first.frame_names}"
                )
            if tr.state.shape[1] != first.state.shape[1]:
                raise ValueError(
                    f"demonstration {i} has a {tr.state.shape[1]}-D state, "
                    f"demonstration 0 a {first.state.shape[1]}-D one"
                )
            if (tr.gripper is None) != (first.gripper is None):
                raise ValueError("either every demonstration has a gripper command or none has")
            for k in first.frame_names:
                if tr.frames[k][0].shape[1] != first.frames[k][0].shape[1]:
                    raise ValueError(f"frame {k!r} changes dimension between demonstrations")
        self._items = items
        self.metadata = dict(metadata or {})

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return TrajectorySet(self._items[i], self.metadata)
        return self._items[i]

    def __iter__(self) -> Iterator[Trajectory]:
        return iter(self._items)

    @property
    def frame_names(self) -> list[str]:
        """The frames every demonstration names, sorted."""
        return self._items[0].frame_names

    @property
    def state_dim(self) -> int:
        """``k``, the robot state's length."""
        return int(self._items[0].state.shape[1])

    def __repr__(self) -> str:
        return f"TrajectorySet({len(self)} demonstrations, frames={self.frame_names})"
