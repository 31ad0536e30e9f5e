"""A scripted, human-like teacher for the coffee task.

The teacher plans Cartesian waypoints for the grasp point and the hand orientation from the task
points of the episode (``CoffeeEnv.task_points()``), times them with minimum-jerk profiles and
tracks them with damped-least-squares inverse kinematics on
:class:`~gym_coffee.kinematics.PandaKinematics` (6-D pose, with a null-space pull to a comfortable
posture). The motion follows the paper's Fig. 3: approach the cup from the side with the gripper
horizontal, grasp, lift, carry it in front of the machine, slide it onto the drip tray under the
spout, put it down, let go, pull back without touching the cup, close the gripper, move up in front
of the button and press it along its axis.

Human-like variation (from the teacher's own random generator): overall speed and per-segment
durations, via points (arcs of different heights), approach angle, grasp height and depth, press
depth, and a small smooth hand jitter.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from gym_coffee.env import CONTROL_DT, obs_part
from gym_coffee.kinematics import PandaKinematics
from gym_coffee.robot import GRIPPER_MAX_OPENING, MAX_JOINT_STEP, action_from_targets

__all__ = ["ScriptedTeacher"]

#: Grasp height above the cup's base (m) and its jitter.
GRASP_HEIGHT = 0.046
#: The fingertips reach this far (m) beyond the grasp point along the hand's z axis.
FINGERTIP_OFFSET = 0.0072
#: Comfortable posture for a horizontal gripper (null-space target), machine on the robot's left.
REST_POSTURE = np.array([-0.2, 0.9, 0.0, -1.9, 1.4, 1.5, 1.2])
#: Its mirror image in the robot's xz-plane, for a machine on the right (hard level): joints 1, 3,
#: 5 and 7 turn about axes in that plane (negated), 2, 4 and 6 about its normal (kept); the hand
#: sits at -45 degrees on the flange, hence the quarter turn of joint 7.
REST_POSTURE_MIRRORED = REST_POSTURE * np.array([-1, 1, -1, 1, -1, 1, -1]) + np.array(
    [0, 0, 0, 0, 0, 0, np.pi / 2]
)
#: Damping (m) of the damped-least-squares inverse kinematics.
IK_DAMPING = 0.03
#: Weight of orientation (rad) against position (m) errors.
ORIENTATION_WEIGHT = 0.3
#: Gain of the null-space pull towards REST_POSTURE per control step.
NULL_SPACE_GAIN = 0.05


def _min_jerk(tau: float) -> float:
    tau = min(max(tau, 0.0), 1.0)
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)


def _hand_rotation(direction: NDArray[np.float64], flip: bool) -> NDArray[np.float64]:
    """Hand orientation (columns x, y, z) with z along the horizontal ``direction`` and x
    vertical."""
    z = np.array([direction[0], direction[1], 0.0])
    z /= np.linalg.norm(z)
    x = np.array([0.0, 0.0, 1.0 if flip else -1.0])
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


@dataclass
class Segment:
    """One minimum-jerk move of the grasp point (with an arc ``via``) and the hand orientation."""

    t0: float
    t1: float
    p0: NDArray[np.float64]
    p1: NDArray[np.float64]
    r0: NDArray[np.float64]
    r1: NDArray[np.float64]
    grip0: float
    grip1: float
    via: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    name: str = ""

    def __post_init__(self) -> None:
        self._rotvec = Rotation.from_matrix(self.r0.T @ self.r1).as_rotvec()

    def at(self, t: float) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        s = _min_jerk((t - self.t0) / max(self.t1 - self.t0, 1e-9))
        pos = self.p0 + s * (self.p1 - self.p0) + 4.0 * s * (1.0 - s) * self.via
        rot = self.r0 @ Rotation.from_rotvec(s * self._rotvec).as_matrix()
        grip = self.grip0 + s * (self.grip1 - self.grip0)
        return pos, rot, grip


class ScriptedTeacher:
    """Scripted demonstrator for ``CoffeeEnv``.

    Args:
        env: the environment (a ``CoffeeEnv`` or a wrapper around one); the teacher reads its
            ``task_points()`` and ``kinematics`` at the start of each episode.
        rng: seed or ``numpy.random.Generator`` for the human-like variation. Do not pass the
            layout seed itself: ``default_rng(s)`` is the same random stream as the env's
            ``np_random`` after ``reset(seed=s)``, so the variation would copy the layout draws;
            derive it instead, e.g. ``np.random.default_rng([1, s])`` (as
            ``collect_demonstrations`` does with its own constant).
        variation: scale of the variation (0: the same motion for the same layout).

    Call :meth:`act` with each observation; a new episode (observation time 0, or after
    :meth:`reset`) makes the teacher plan anew.

    Example:
        >>> import gymnasium as gym, gym_coffee
        >>> env = gym.make(gym_coffee.ENV_ID)
        >>> import numpy as np
        >>> teacher = ScriptedTeacher(env, rng=np.random.default_rng([1, 0]))
        >>> obs, info = env.reset(seed=0)
        >>> action = teacher.act(obs)
    """

    def __init__(
        self,
        env: Any,
        rng: int | np.random.Generator | None = None,
        *,
        variation: float = 1.0,
    ) -> None:
        self.env = env
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self.variation = float(variation)
        self.kinematics: PandaKinematics = env.unwrapped.kinematics
        self.segments: list[Segment] = []
        self._rest = REST_POSTURE
        self._last_time = np.inf
        self._plan_obs = np.zeros(0)
        self._jitter: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None
        self._jitter = None

    # ------------------------------------------------------------------ public API
    def reset(self, obs: ArrayLike | None = None, seed: int | None = None) -> None:
        """Forget the plan (and re-seed when ``seed`` is given); plan now if ``obs`` is given.

        ``seed`` goes to ``np.random.default_rng``: a different value than the layout seed (see
        ``rng`` in the class docstring).
        """
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        self.segments = []
        self._last_time = np.inf
        if obs is not None:
            self.plan(np.asarray(obs, dtype=np.float64))

    @property
    def duration(self) -> float:
        """Planned duration (s) of the current episode's motion."""
        return self.segments[-1].t1 if self.segments else 0.0

    def act(self, obs: ArrayLike) -> NDArray[np.float32]:
        """The action (8,) for observation ``obs`` (OBS_DIM,)."""
        obs = np.asarray(obs, dtype=np.float64)
        t = float(obs_part(obs, "time")[0])
        new_episode = t < 1e-9 and (t < self._last_time or not np.array_equal(obs, self._plan_obs))
        if not self.segments or new_episode:
            self.plan(obs)
        self._last_time = t
        q = obs_part(obs, "joint_pos")
        pos_d, rot_d, grip = self.target(t + CONTROL_DT)
        q_target = self._ik_step(q, pos_d, rot_d)
        return action_from_targets(q, q_target, grip)

    def __call__(self, obs: ArrayLike) -> NDArray[np.float32]:
        return self.act(obs)

    def target(self, t: float) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        """Desired grasp-point position, hand orientation and gripper opening at time ``t``."""
        seg = self.segments[-1]
        for candidate in self.segments:
            if t <= candidate.t1:
                seg = candidate
                break
        pos, rot, grip = seg.at(t)
        if self._jitter is not None:
            amp, freq, phase = self._jitter
            pos = pos + (amp * np.sin(2.0 * np.pi * freq * t + phase)).sum(axis=0)
        return pos, rot, grip

    # ------------------------------------------------------------------ planning
    def plan(self, obs: NDArray[np.float64]) -> None:
        """Plan the episode's waypoints from the task points and the current observation."""
        rng, var = self.rng, self.variation
        self._plan_obs = obs.copy()
        points = self.env.unwrapped.task_points()
        cup = np.asarray(points["cup_pos"], dtype=np.float64)
        place = np.asarray(points["place_pos"], dtype=np.float64)
        button = np.asarray(points["button_pos"], dtype=np.float64)
        axis = np.asarray(points["button_axis"], dtype=np.float64)
        q = obs_part(obs, "joint_pos")
        p_start, r_start = self.kinematics.forward_pose(q)

        def u(scale: float) -> float:
            return float(rng.uniform(-scale, scale)) * var

        speed = 1.0 + u(0.15)  # overall tempo

        def dur(nominal: float) -> float:
            return nominal * speed * (1.0 + u(0.1))

        # Grasp from the side, the hand pointing roughly across the line from the robot base to the
        # cup (the Panda's wrist handles a horizontal gripper best that way) and towards the
        # machine: turned left when the machine stands to the cup's left, else right.
        machine_side = 1.0 if cup[0] * place[1] - cup[1] * place[0] >= 0.0 else -1.0
        self._rest = REST_POSTURE if machine_side > 0 else REST_POSTURE_MIRRORED
        radial = np.arctan2(cup[1], cup[0])
        grasp_yaw = radial + machine_side * np.pi / 2 + u(np.deg2rad(10.0))
        d_grasp = np.array([np.cos(grasp_yaw), np.sin(grasp_yaw), 0.0])
        flip = False  # hand x down: the posture family of REST_POSTURE
        r_grasp = _hand_rotation(d_grasp, flip)
        grasp = cup + np.array([0.0, 0.0, GRASP_HEIGHT + u(0.004)]) + d_grasp * u(0.004)
        pre_grasp = grasp - (0.11 + u(0.02)) * d_grasp
        # Carry: the hand points along the machine's axis (into the machine).
        r_place = _hand_rotation(axis, flip)
        place_grasp = place + np.array([0.0, 0.0, grasp[2] - cup[2]]) + axis * u(0.005)
        lift = np.array([0.0, 0.0, 0.055 + u(0.01)])
        pre_place = place_grasp + np.array([0.0, 0.0, 0.028]) - (0.13 + u(0.02)) * axis
        above_place = place_grasp + np.array([0.0, 0.0, 0.02])
        retreat = place_grasp - (0.13 + u(0.015)) * axis + np.array([0.0, 0.0, 0.01])
        press_depth = 0.0068 + u(0.0008)
        before_button = button - (0.07 + u(0.015)) * axis - FINGERTIP_OFFSET * axis
        pressed = button + (press_depth - FINGERTIP_OFFSET) * axis
        back_off = button - (0.07 + u(0.01)) * axis

        open_, closed = GRIPPER_MAX_OPENING, 0.0
        side = np.cross(np.array([0.0, 0.0, 1.0]), d_grasp)
        steps: list[
            tuple[str, NDArray[np.float64], NDArray[np.float64], float, float, NDArray[np.float64]]
        ] = [
            # name, position, orientation, gripper, duration, via (arc offset)
            (
                "approach",
                pre_grasp,
                r_grasp,
                open_,
                dur(2.0),
                np.array([0.0, 0.0, 0.06 + u(0.03)]) + side * u(0.04),
            ),
            ("reach", grasp, r_grasp, open_, dur(0.9), np.zeros(3)),
            ("close", grasp, r_grasp, closed, dur(0.6), np.zeros(3)),
            ("lift", grasp + lift, r_grasp, closed, dur(0.7), np.zeros(3)),
            ("carry", pre_place, r_place, closed, dur(2.2), np.array([0.0, 0.0, 0.05 + u(0.03)])),
            ("insert", above_place, r_place, closed, dur(1.0), np.zeros(3)),
            ("put_down", place_grasp, r_place, closed, dur(0.5), np.zeros(3)),
            ("release", place_grasp, r_place, open_, dur(0.5), np.zeros(3)),
            ("retreat", retreat, r_place, open_, dur(0.9), np.zeros(3)),
            ("to_button", before_button, r_place, closed, dur(1.2), -0.03 * axis * (1.0 + u(0.5))),
            ("press", pressed, r_place, closed, dur(0.7), np.zeros(3)),
            ("hold", pressed, r_place, closed, dur(0.3), np.zeros(3)),
            ("back_off", back_off, r_place, closed, dur(0.7), np.zeros(3)),
        ]
        segments = []
        t, p, r = 0.0, p_start, r_start
        g = float(obs_part(obs, "gripper")[0])
        for name, p1, r1, g1, duration, via in steps:
            segments.append(Segment(t, t + duration, p, p1, r, r1, g, g1, via, name))
            t, p, r, g = t + duration, p1, r1, g1
        self.segments = segments
        # Smooth hand jitter: three sinusoids per axis, a millimetre or two in all.
        amp = rng.normal(0.0, 0.0006 * var, size=(3, 3))
        freq = rng.uniform(0.2, 0.9, size=(3, 3))
        phase = rng.uniform(0.0, 2.0 * np.pi, size=(3, 3))
        self._jitter = (amp, freq, phase) if var > 0 else None

    # ------------------------------------------------------------------ control
    def _ik_step(
        self, q: NDArray[np.float64], pos_d: NDArray[np.float64], rot_d: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """Joint targets that move the hand towards the desired pose (damped least squares)."""
        return self.kinematics.ik_step(
            q,
            pos_d,
            rot_d,
            self._rest,
            max_step=MAX_JOINT_STEP,
            damping=IK_DAMPING,
            orientation_weight=ORIENTATION_WEIGHT,
            null_space_gain=NULL_SPACE_GAIN,
        )
