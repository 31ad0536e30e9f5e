"""Replay baselines: what a policy gets without learning from the demonstrations' variation.

* :class:`NearestDemonstrationReplay` replays, in time, the joint trajectory of the demonstration
  whose initial layout is nearest to the episode's (the simplest thing that uses several
  demonstrations).
* :class:`ObjectRelativeReplay` replays ONE demonstration's hand path relative to the objects, with
  the frame switching set by hand: relative to the cup until the demonstration lifted it, then
  (after a short linear blend) relative to the machine. The path is tracked with damped
  least-squares inverse kinematics on two points of the hand (grasp point and a point on the
  approach axis, as the GP policy's task vector), with a null-space pull towards the
  demonstration's joint posture; the gripper is replayed in time.

Both have stable-baselines3's ``predict(observation, state=None, episode_start=None,
deterministic=False)`` and take ``(obs_dim,)`` or ``(n_envs, obs_dim)`` observations. They read the
task through an observation adapter (default: gym-coffee's, see :mod:`._adapter`), are time
indexed (the observation's clock), keep no state between calls and are deterministic.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lgp_policy.baselines._adapter import (
    default_adapter,
    frames_at,
    layout_features,
    read_batch,
    to_trajectories,
)
from lgp_policy.lfd.policy import hand_points
from lgp_policy.lfd.reproduction import DEFAULT_DAMPING, damped_pseudoinverse, limit_step

__all__ = ["NearestDemonstrationReplay", "ObjectRelativeReplay"]


def _interp_rows(t: float, times: NDArray[np.float64], values: NDArray[np.float64]) -> NDArray:
    """``values (n, d)`` linearly interpolated at time ``t`` (held at the ends)."""
    i = int(np.searchsorted(times, t, side="right")) - 1
    if i < 0:
        return values[0].copy()
    if i >= len(times) - 1:
        return values[-1].copy()
    w = (t - times[i]) / (times[i + 1] - times[i])
    return (1.0 - w) * values[i] + w * values[i + 1]


class _TimeIndexedPolicy:
    """Shared ``predict``: the adapter reads the batch, ``_act`` gives one row's step."""

    adapter: Any

    def _check_fitted(self) -> None:
        if not hasattr(self, "adapter_"):
            raise RuntimeError(f"This {type(self).__name__} is not fitted; call fit(demos) first.")

    def _fit_start(self, demos: Any) -> Any:
        self.adapter_ = self.adapter if self.adapter is not None else default_adapter()
        return to_trajectories(self.adapter_, demos)

    def _act(
        self, t: float, q: NDArray[np.float64], frames: dict[str, Any]
    ) -> tuple[NDArray[np.float64], float]:
        """The target state ``(k,)`` and the gripper command for one observation."""
        raise NotImplementedError

    def predict(
        self,
        observation: ArrayLike,
        state: Any = None,
        episode_start: ArrayLike | None = None,
        deterministic: bool = False,
    ) -> tuple[NDArray[np.float32], Any]:
        """The action for an observation (stable-baselines3 ``PolicyPredictor`` protocol).

        Args:
            observation: ``(obs_dim,)`` or ``(n_envs, obs_dim)``.
            state: unused (time-indexed policy); returned unchanged.
            episode_start: unused.
            deterministic: unused (always deterministic).

        Returns:
            ``(action, state)``, ``action`` ``(a,)`` or ``(n_envs, a)`` float32.
        """
        self._check_fitted()
        observed, single = read_batch(self.adapter_, observation)
        q = np.asarray(observed.state, dtype=float)
        targets, grippers = [], []
        for i in range(q.shape[0]):
            target, gripper = self._act(float(observed.time[i]), q[i], frames_at(observed, i))
            targets.append(target)
            grippers.append(gripper)
        am = self.adapter_.action_map
        steps = np.stack(
            [limit_step(x - qi, am.max_step) for x, qi in zip(targets, q, strict=True)]
        )
        actions = am(q, steps, np.asarray(grippers, dtype=float))
        return (actions[0] if single else actions), state


class NearestDemonstrationReplay(_TimeIndexedPolicy):
    """Replay the joint trajectory of the demonstration whose initial layout is nearest.

    Args:
        adapter: how to read the task (default: gym-coffee's, see :mod:`._adapter`).

    The layout distance is Euclidean on the frames' initial origins and rotations (the first
    column, scaled to 0.1 m). At time ``t`` the arm is commanded to the demonstration's commanded
    state at ``t`` (its state plus its action's step, ``actions[:, :k] * action_map.max_step``;
    the state itself where the demonstration has no actions) from the *measured* state, and the
    gripper to its command at ``t``; on the demonstration's own layout this repeats its actions.

    Attributes (after ``fit``):
        layouts_: ``(n_demos, m)`` layout features.
    """

    def __init__(self, adapter: Any = None) -> None:
        self.adapter = adapter

    def fit(self, demos: Sequence[Any]) -> NearestDemonstrationReplay:
        """Store every demonstration's time, commanded states and gripper commands.

        Args:
            demos: a ``TrajectorySet``, or demonstrations the adapter converts (a gym-coffee
                ``DemonstrationSet``).

        Returns:
            ``self``.
        """
        trajs = self._fit_start(demos)
        step = float(self.adapter_.action_map.max_step)
        self.layouts_ = np.stack([layout_features(tr.initial_frames()) for tr in trajs])
        self._times, self._targets, self._grippers = [], [], []
        for tr in trajs:
            k = tr.state.shape[1]
            target = tr.state if tr.actions is None else tr.state + tr.actions[:, :k] * step
            gripper = np.zeros(len(tr)) if tr.gripper is None else tr.gripper
            self._times.append(tr.time)
            self._targets.append(target)
            self._grippers.append(gripper[:, None])
        return self

    def nearest(self, observation: ArrayLike) -> int:
        """Index of the demonstration whose layout is nearest to that of one observation."""
        self._check_fitted()
        observed, _ = read_batch(self.adapter_, observation)
        return self._nearest(frames_at(observed, 0))

    def _nearest(self, frames: dict[str, Any]) -> int:
        d = np.linalg.norm(self.layouts_ - layout_features(frames), axis=1)
        return int(np.argmin(d))

    def _act(
        self, t: float, q: NDArray[np.float64], frames: dict[str, Any]
    ) -> tuple[NDArray[np.float64], float]:
        k = self._nearest(frames)
        target = _interp_rows(t, self._times[k], self._targets[k])
        return target, float(_interp_rows(t, self._times[k], self._grippers[k])[0])


class ObjectRelativeReplay(_TimeIndexedPolicy):
    """Replay one demonstration's hand path relative to the cup, then to the machine.

    Args:
        adapter: how to read the task (default: gym-coffee's, see :mod:`._adapter`); its robot
            needs ``forward_pose`` and ``jacobian``.
        demo_index: which demonstration of ``fit``'s set to replay (default the first).
        frames: the frames in the order the path is relative to them.
        switch_event: the demonstration's event whose first occurrence switches from ``frames[0]``
            to ``frames[1]`` (gym-coffee: ``"cup_grasped"``, the cup lifted between the fingers).
        blend: seconds over which the target moves linearly from the first frame's path to the
            second's after the switch.
        approach_offset: m; the second tracked point lies this far behind the grasp point on the
            hand's approach axis (as the GP policy's ``p = 6`` task vector).
        alpha: gain of the null-space pull towards the demonstration's joint posture.
        lookahead: control steps ahead at which the path is read (compensates tracking lag).

    Attributes (after ``fit``):
        switch_time_: seconds; control_dt_: the demonstration's control period.
    """

    def __init__(
        self,
        adapter: Any = None,
        *,
        demo_index: int = 0,
        frames: tuple[str, str] = ("cup", "machine"),
        switch_event: str = "cup_grasped",
        blend: float = 0.5,
        approach_offset: float = 0.1,
        alpha: float = 0.5,
        lookahead: float = 1.0,
    ) -> None:
        self.adapter = adapter
        self.demo_index = demo_index
        self.frames = frames
        self.switch_event = switch_event
        self.blend = blend
        self.approach_offset = approach_offset
        self.alpha = alpha
        self.lookahead = lookahead

    def fit(self, demos: Sequence[Any]) -> ObjectRelativeReplay:
        """Store the replayed demonstration's hand path in its frames.

        Args:
            demos: a ``TrajectorySet``, or demonstrations the adapter converts; only
                ``demos[demo_index]`` is used.

        Returns:
            ``self``.
        """
        if not (isinstance(self.blend, (int, float)) and self.blend >= 0.0):
            raise ValueError(f"blend must be >= 0 seconds, got {self.blend!r}")
        if len(self.frames) != 2:
            raise ValueError(f"frames must name two frames, got {self.frames!r}")
        trajs = self._fit_start(demos)
        if not -len(trajs) <= self.demo_index < len(trajs):
            raise ValueError(
                f"demo_index must index the {len(trajs)} demonstrations, got {self.demo_index}"
            )
        tr = trajs[self.demo_index]
        missing = [f for f in self.frames if f not in tr.frames]
        if missing:
            raise ValueError(f"frames: the demonstrations have no frame {missing}")
        when = tr.event_times().get(self.switch_event)
        if when is None:
            raise ValueError(
                f"switch_event: the demonstration never has {self.switch_event!r} "
                f"(events: {sorted(tr.events)})"
            )
        robot = self.adapter_.robot
        points = np.stack([hand_points(robot, q, self.approach_offset)[0] for q in tr.state])
        self._rel = {}
        for name in self.frames:
            origin, rotation = tr.initial_frames()[name]
            d = origin.shape[0]
            local = (points.reshape(len(points), -1, d) - origin) @ rotation  # R^T (x - o)
            self._rel[name] = local.reshape(len(points), -1)
        self.switch_time_ = float(when)
        self._times = tr.time
        self._joints = tr.state
        gripper = np.zeros(len(tr)) if tr.gripper is None else tr.gripper
        self._grippers = gripper[:, None]
        self.control_dt_ = float(np.median(np.diff(tr.time)))
        return self

    def _frame_weight(self, t: float) -> float:
        """Weight of the second frame at time ``t`` (0 before the switch, 1 after the blend)."""
        if t < self.switch_time_:
            return 0.0
        if self.blend <= 0.0:
            return 1.0
        return min((t - self.switch_time_) / self.blend, 1.0)

    def _target(self, t: float, frames: dict[str, Any]) -> NDArray[np.float64]:
        world = []
        for name in self.frames:
            origin, rotation = frames[name]
            d = origin.shape[0]
            local = _interp_rows(t, self._times, self._rel[name]).reshape(-1, d)
            world.append((origin + local @ rotation.T).reshape(-1))
        w = self._frame_weight(t)
        return (1.0 - w) * world[0] + w * world[1]

    def target(self, observation: ArrayLike, t: float | None = None) -> NDArray[np.float64]:
        """World targets of the tracked hand points for one observation (at its time, or at
        ``t``)."""
        self._check_fitted()
        observed, _ = read_batch(self.adapter_, observation)
        return self._target(
            float(observed.time[0]) if t is None else float(t), frames_at(observed, 0)
        )

    def _act(
        self, t: float, q: NDArray[np.float64], frames: dict[str, Any]
    ) -> tuple[NDArray[np.float64], float]:
        t_next = t + self.lookahead * self.control_dt_
        x, J = hand_points(self.adapter_.robot, q, self.approach_offset)
        J_pinv = damped_pseudoinverse(J, DEFAULT_DAMPING)
        null = np.eye(q.shape[0]) - J_pinv @ J
        posture = _interp_rows(t_next, self._times, self._joints)
        dq = J_pinv @ (self._target(t_next, frames) - x) + self.alpha * null @ (posture - q)
        return q + dq, float(_interp_rows(t, self._times, self._grippers)[0])
