"""How the baselines read a task: through the GP policy's observation adapter, in one place.

A baseline is fitted on a :class:`~lgp_policy.lfd.demonstrations.TrajectorySet` (a
``gym_coffee`` ``DemonstrationSet`` is converted by the adapter's ``to_trajectories``) and reads
observations with the adapter's ``read`` (time, robot state, frames); actions come from its
``action_map``. The default adapter is gym-coffee's
(:class:`lgp_policy.lfd.adapters.coffee.CoffeeAdapter`) with the cup frame at the cup's pose at
reset (``track_cup=False``): the baselines keep no state between steps, so they cannot hold on to
the cup's last pose once the gripper hides it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["default_adapter", "layout_features", "read_batch", "to_trajectories"]

Frames = dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]


def default_adapter() -> Any:
    """gym-coffee's adapter, cup frame at its pose at reset."""
    from lgp_policy.lfd.adapters.coffee import CoffeeAdapter

    return CoffeeAdapter(track_cup=False)


def to_trajectories(adapter: Any, demos: Any) -> Any:
    """``demos`` as a ``TrajectorySet`` (converted by the adapter unless it already is one);
    a clear error for an empty set."""
    from lgp_policy.lfd.demonstrations import TrajectorySet

    if not isinstance(demos, TrajectorySet):
        demos = list(demos)
    if len(demos) == 0:
        raise ValueError("demos: need at least one demonstration, got none")
    return demos if isinstance(demos, TrajectorySet) else adapter.to_trajectories(demos)


def read_batch(adapter: Any, observation: ArrayLike) -> tuple[Any, bool]:
    """``(Observed, single)`` for ``(obs_dim,)`` or ``(n, obs_dim)``; a clear error otherwise."""
    obs = np.asarray(observation, dtype=float)
    if obs.ndim not in (1, 2) or obs.shape[-1] != adapter.obs_dim:
        raise ValueError(
            f"observation must be (obs_dim,) or (n_envs, obs_dim) with obs_dim = "
            f"{adapter.obs_dim}, got shape {obs.shape}"
        )
    observed = adapter.read(np.atleast_2d(obs))
    if observed.time is None:
        raise ValueError("the baselines are time-indexed: the adapter must read a clock")
    return observed, obs.ndim == 1


def frames_at(observed: Any, row: int) -> Frames:
    """The frames of one row of an ``Observed``."""
    return {name: (p[row], R[row]) for name, (p, R) in observed.frames.items()}


def layout_features(frames: Frames) -> NDArray[np.float64]:
    """A layout as a vector: each frame's origin and its rotation's first column scaled to
    0.1 m, frames in name order."""
    parts = []
    for name in sorted(frames):
        origin, rotation = frames[name]
        parts.append(np.asarray(origin, dtype=float))
        parts.append(0.1 * np.asarray(rotation, dtype=float)[:, 0])
    return np.concatenate(parts)
