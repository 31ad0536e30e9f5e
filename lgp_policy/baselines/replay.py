"""Replay baselines: what a policy gets without learning from the demonstrations' variation.

* :class:`NearestDemonstrationReplay` replays, in time, the joint trajectory of the demonstration
  whose initial layout is nearest to the episode's (the simplest thing that uses several
  demonstrations).
* :class:`ObjectRelativeReplay` replays ONE demonstration's hand path relative to the objects, with
  the frame switching set by hand: relative to the cup until the demonstration grasped it, then
  (after a short linear blend) relative to the machine. The path is tracked with damped
  least-squares inverse kinematics on two points of the hand (grasp point and a point on the
  approach axis, as the GP policy's task vector), with a null-space pull towards the
  demonstration's joint posture; the gripper is replayed in time.

Both have stable-baselines3's ``predict(observation, state=None, episode_start=None,
deterministic=False)`` and take ``(OBS_DIM,)`` or ``(n_envs, OBS_DIM)`` observations. They are time
indexed (the observation's ``time``), keep no state between calls and are deterministic.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lgp_policy.baselines._coffee import (
    CoffeeSpec,
    coffee_spec,
    default_robot,
    demonstration_frames,
    layout_features,
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


def _as_list(demos: Any) -> list[Any]:
    demos = list(demos)
    if not demos:
        raise ValueError("demos: need at least one demonstration, got none")
    return demos


class _TimeIndexedPolicy:
    """Shared ``predict``: one ``_act(obs)`` per row of a batch."""

    spec_: CoffeeSpec

    def _check_fitted(self) -> None:
        if not hasattr(self, "spec_"):
            raise RuntimeError(f"This {type(self).__name__} is not fitted; call fit(demos) first.")

    def _act(self, obs: NDArray[np.float64]) -> NDArray[np.float32]:
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
            observation: ``(OBS_DIM,)`` or ``(n_envs, OBS_DIM)``.
            state: unused (time-indexed policy); returned unchanged.
            episode_start: unused.
            deterministic: unused (always deterministic).

        Returns:
            ``(action, state)``, ``action`` ``(8,)`` or ``(n_envs, 8)`` float32.
        """
        self._check_fitted()
        single = np.ndim(observation) == 1
        obs = self.spec_.check_obs(observation)
        actions = np.stack([self._act(o) for o in obs])
        return (actions[0] if single else actions), state


class NearestDemonstrationReplay(_TimeIndexedPolicy):
    """Replay the joint trajectory of the demonstration whose initial layout is nearest.

    The layout distance is Euclidean on :func:`~lgp_policy.baselines._coffee.layout_features`
    (object positions, and yaw as ``0.1 (cos, sin)``). At time ``t`` the arm is commanded to the
    demonstration's commanded joint target at ``t`` (its joint positions plus its action's joint
    step) from the *measured* joints, and the gripper to its gripper command at ``t``; on the
    demonstration's own layout this repeats the demonstration's actions.

    Attributes (after ``fit``):
        layouts_: ``(n_demos, k)`` layout features; ``seeds_``: the demonstrations' seeds.
    """

    def fit(self, demos: Sequence[Any]) -> NearestDemonstrationReplay:
        """Store every demonstration's time, commanded joint targets and gripper commands.

        Args:
            demos: a ``DemonstrationSet`` or a sequence of ``Demonstration``.

        Returns:
            ``self``.
        """
        demos = _as_list(demos)
        spec = coffee_spec()
        self.layouts_ = np.stack([layout_features(demonstration_frames(d)) for d in demos])
        self.seeds_ = [int(getattr(d, "seed", -1)) for d in demos]
        self._times, self._targets, self._grippers = [], [], []
        for d in demos:
            q = np.asarray(d.joint_pos, dtype=float)
            a = np.asarray(d.actions, dtype=float)
            self._times.append(np.asarray(d.time, dtype=float))
            self._targets.append(q + a[:, :7] * spec.max_joint_step)
            self._grippers.append(spec.gripper_opening(a[:, 7:8]))
        self.spec_ = spec
        return self

    def nearest(self, observation: ArrayLike) -> int:
        """Index of the demonstration whose layout is nearest to that of one observation."""
        self._check_fitted()
        obs = self.spec_.check_obs(observation)[0]
        d = np.linalg.norm(self.layouts_ - self.spec_.layout(obs), axis=1)
        return int(np.argmin(d))

    def _act(self, obs: NDArray[np.float64]) -> NDArray[np.float32]:
        k = self.nearest(obs)
        t = self.spec_.time(obs)
        target = _interp_rows(t, self._times[k], self._targets[k])
        gripper = float(_interp_rows(t, self._times[k], self._grippers[k])[0])
        return self.spec_.action(self.spec_.joint_pos(obs), target, gripper)


class ObjectRelativeReplay(_TimeIndexedPolicy):
    """Replay one demonstration's hand path relative to the cup, then to the machine.

    Args:
        robot: kinematics (``RobotModel`` with ``forward_pose`` and ``jacobian``); default the
            Panda's.
        demo_index: which demonstration of ``fit``'s set to replay (default the first).
        approach_offset: m; the second tracked point lies this far behind the grasp point on the
            hand's approach axis (as the GP policy's ``p = 6`` task vector).
        switch: when the path switches from the cup frame to the machine frame: ``"grasped"``
            (the first step the demonstration's ``cup_grasped`` flag is set: the cup is lifted)
            or ``"gripper"`` (the gripper command closing).
        blend: seconds over which the target moves linearly from the cup-relative to the
            machine-relative path after the switch.
        alpha: gain of the null-space pull towards the demonstration's joint posture.
        lookahead: control steps ahead at which the path is read (compensates tracking lag).

    Attributes (after ``fit``):
        seed_: the replayed demonstration's seed; switch_time_: seconds.
    """

    def __init__(
        self,
        robot: Any = None,
        *,
        demo_index: int = 0,
        approach_offset: float = 0.1,
        switch: str = "grasped",
        blend: float = 0.5,
        alpha: float = 0.5,
        lookahead: float = 1.0,
    ) -> None:
        self.robot = robot
        self.demo_index = demo_index
        self.approach_offset = approach_offset
        self.switch = switch
        self.blend = blend
        self.alpha = alpha
        self.lookahead = lookahead

    def fit(self, demos: Sequence[Any]) -> ObjectRelativeReplay:
        """Store the replayed demonstration's hand path in the cup and machine frames.

        Args:
            demos: a ``DemonstrationSet`` or a sequence of ``Demonstration``; only
                ``demos[demo_index]`` is used.

        Returns:
            ``self``.
        """
        demos = _as_list(demos)
        if not -len(demos) <= self.demo_index < len(demos):
            raise ValueError(
                f"demo_index must index the {len(demos)} demonstrations, got {self.demo_index}"
            )
        if self.switch not in ("grasped", "gripper"):
            raise ValueError(f"switch must be 'grasped' or 'gripper', got {self.switch!r}")
        if not self.blend >= 0.0:
            raise ValueError(f"blend must be >= 0 seconds, got {self.blend!r}")
        demo = demos[self.demo_index]
        spec = coffee_spec()
        self.robot_ = self.robot if self.robot is not None else default_robot()
        times = np.asarray(demo.time, dtype=float)
        joints = np.asarray(demo.joint_pos, dtype=float)
        points = np.stack([hand_points(self.robot_, q, self.approach_offset)[0] for q in joints])
        frames = demonstration_frames(demo)
        self._rel = {}
        for name in ("cup", "machine"):
            origin, rotation = frames[name]
            local = (points.reshape(len(points), -1, 3) - origin) @ rotation  # R^T (x - o)
            self._rel[name] = local.reshape(len(points), -1)
        if self.switch == "grasped":
            grasped = np.flatnonzero(np.asarray(demo.stages, dtype=bool)[:, 0])
            if grasped.size == 0:
                raise ValueError("the demonstration never grasped the cup; cannot switch frames")
            self.switch_time_ = float(times[grasped[0]])
        else:
            from lgp_policy.lfd.policy import gripper_events

            events = gripper_events(demo)
            if events.size == 0:
                raise ValueError("the demonstration never closed the gripper; cannot switch")
            self.switch_time_ = float(events[0])
        self._times = times
        self._joints = joints
        self._grippers = spec.gripper_opening(np.asarray(demo.actions, dtype=float)[:, 7:8])
        self.control_dt_ = float(np.median(np.diff(times)))
        self.seed_ = int(getattr(demo, "seed", -1))
        self.spec_ = spec
        return self

    def _frame_weight(self, t: float) -> float:
        """Weight of the machine frame at time ``t`` (0 before the switch, 1 after the blend)."""
        if t < self.switch_time_:
            return 0.0
        if self.blend <= 0.0:
            return 1.0
        return min((t - self.switch_time_) / self.blend, 1.0)

    def target(self, observation: ArrayLike, t: float | None = None) -> NDArray[np.float64]:
        """World targets ``(6,)`` of the two hand points for one observation (at its time, or
        at ``t``)."""
        self._check_fitted()
        obs = self.spec_.check_obs(observation)[0]
        t = self.spec_.time(obs) if t is None else float(t)
        frames = self.spec_.frames(obs)
        world = {}
        for name, rel in self._rel.items():
            origin, rotation = frames[name]
            local = _interp_rows(t, self._times, rel).reshape(-1, 3)
            world[name] = (origin + local @ rotation.T).reshape(-1)
        w = self._frame_weight(t)
        return (1.0 - w) * world["cup"] + w * world["machine"]

    def _act(self, obs: NDArray[np.float64]) -> NDArray[np.float32]:
        t = self.spec_.time(obs)
        t_next = t + self.lookahead * self.control_dt_
        q = self.spec_.joint_pos(obs)
        x, J = hand_points(self.robot_, q, self.approach_offset)
        J_pinv = damped_pseudoinverse(J, DEFAULT_DAMPING)
        null = np.eye(q.shape[0]) - J_pinv @ J
        posture = _interp_rows(t_next, self._times, self._joints)
        dq = J_pinv @ (self.target(obs, t_next) - x) + self.alpha * null @ (posture - q)
        step = limit_step(dq, self.spec_.max_joint_step)
        gripper = float(_interp_rows(t, self._times, self._grippers)[0])
        return self.spec_.action(q, q + step, gripper)
