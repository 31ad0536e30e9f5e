"""The gym-coffee task as one adapter, the only module of :mod:`lgp_policy.lfd` that imports
``gym_coffee``.

* :class:`PandaModel`: the coffee env's Panda (``gym_coffee.kinematics.PandaKinematics``) as a
  batched :class:`~lgp_policy.lfd.robots.RobotModel` (7 joints, 3-D, the grasp point);
* :class:`CoffeeAdapter`: reads the env's observation (``gym_coffee.env.OBS_SLICES``): time, the
  7 arm joints, frames ``cup`` (at the cup's base, rotated by the layout: :func:`cup_rotation`) and
  ``machine`` (footprint centre, ``Rz(machine_yaw)``), and the event ``cup_held``; actions are
  joint deltas plus the gripper (``gym_coffee.robot.action_from_targets``'s scaling);
* :func:`to_trajectories`: ``gym_coffee.demonstrations.DemonstrationSet`` ->
  :class:`~lgp_policy.lfd.demonstrations.TrajectorySet` (the gripper command comes from the
  action's gripper entry, ``cup_held`` from the recorded observations).

Online use of the cup (issue 11): the ``cup`` frame is the cup's *current* observed position until
the gripper holds it (``valid["cup"]`` is then false, and the policy freezes its last estimate);
the policy filters the observed positions over time (``frame_noise``).

The cup frame's rotation: the cup is symmetric, but the grasp is not. The teacher approaches the
cup horizontally, across the line from the robot base to the cup, turned towards the side of that
line on which the machine's drip tray stands (``gym_coffee.teacher``). An identity rotation makes
demonstrations with the machine on the left and on the right ask for opposite approach directions
in the cup frame, and the GP averages them (hard level: 22% success from 8 demonstrations).
:func:`cup_rotation` gives the cup frame that direction as its x axis, computed from observed
quantities only (cup position, machine position and yaw), the same way online and from recorded
demonstrations.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

import gym_coffee
from gym_coffee import kinematics as _kin
from gym_coffee.env import OBS_DIM, OBS_SLICES
from gym_coffee.robot import GRIPPER_MAX_OPENING, MAX_JOINT_STEP
from gym_coffee.scene import CUP_HEIGHT, PLACE_OFFSET
from lgp_policy.lfd.adapters import Observed, rotation_about_z, rotation_from_angle
from lgp_policy.lfd.demonstrations import Trajectory, TrajectorySet
from lgp_policy.lfd.robots import GripperSpec, JointDeltaAction

__all__ = [
    "HELD_DISTANCE",
    "CoffeeAdapter",
    "PandaModel",
    "cup_held",
    "cup_rotation",
    "to_trajectories",
]

#: m; the cup counts as held when the grasp point is this close to the cup's middle and the
#: fingers are neither open nor shut (they rest on the cup's 6 cm body).
HELD_DISTANCE = 0.03
_HELD_OPENING = (0.04, 0.075)
_CONTROL_DT = 0.04
_CUP, _EE, _GRIPPER = OBS_SLICES["cup_pos"], OBS_SLICES["ee_pos"], OBS_SLICES["gripper"].start
_HALF_CUP = np.array([0.0, 0.0, 0.5 * CUP_HEIGHT])
_HALF_CUP_Z = float(_HALF_CUP[2])
_PLACE_X, _PLACE_Y = float(PLACE_OFFSET[0]), float(PLACE_OFFSET[1])


# one environment's flags (read-only: the policy copies what it keeps)
_TRUE, _FALSE = np.ones(1, dtype=bool), np.zeros(1, dtype=bool)
_TRUE.setflags(write=False)
_FALSE.setflags(write=False)


class PandaModel:
    """The coffee env's Panda as a batched ``RobotModel`` (grasp point, world frame).

    One state ``(7,)`` goes through ``PandaKinematics`` (a plain-float chain, fastest for one);
    a batch ``(n, 7)`` through the same chain on columns ``(n,)`` of numbers (the same operations
    in the same order, so the same results).
    """

    dim = 3
    n_joints = 7
    has_orientation = True

    def __init__(self, base_position: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        self._one = _kin.PandaKinematics(base_position)
        self.base_position = self._one.base_position
        self.joint_lower = self._one.joint_lower
        self.joint_upper = self._one.joint_upper

    def _chain(self, q: NDArray[np.float64]) -> tuple[NDArray, NDArray, NDArray]:
        """``PandaKinematics``'s chain for a batch ``(n, 7)``: grasp point ``(n, 3)``, hand
        rotation ``(n, 3, 3)`` and geometric Jacobian ``(n, 6, 7)``. Each quantity is a list of
        ``(n,)`` columns: the frame's axes ``x, y, z`` and origin ``p``."""
        n = q.shape[0]
        cos, sin = np.cos(q).T, np.sin(q).T
        zero, one = np.zeros(n), np.ones(n)
        x, y, z = [one, zero, zero], [zero, one, zero], [zero, zero, one]
        p = [np.full(n, v) for v in self.base_position.tolist()]
        J = np.empty((n, 6, 7))
        origins = []
        for i in range(7):
            t0, t1, t2 = _kin._XYZ[i]
            p = [p[a] + (t0 * x[a] + t1 * y[a] + t2 * z[a]) for a in range(3)]
            cr, sr = _kin._ROLL_CS[i]
            if sr != 0.0:  # R @ Rx(roll)
                y, z = (
                    [cr * y[a] + sr * z[a] for a in range(3)],
                    [cr * z[a] - sr * y[a] for a in range(3)],
                )
            c, s = cos[i], sin[i]  # R @ Rz(q_i)
            x, y = [c * x[a] + s * y[a] for a in range(3)], [c * y[a] - s * x[a] for a in range(3)]
            for a in range(3):
                J[:, 3 + a, i] = z[a]
            origins.append(p)
        d = _kin.GRASP_OFFSET
        ee = [p[a] + d * z[a] for a in range(3)]
        for i, o in enumerate(origins):  # z_i x (p_ee - p_i)
            a0, a1, a2 = J[:, 3, i], J[:, 4, i], J[:, 5, i]
            r0, r1, r2 = ee[0] - o[0], ee[1] - o[1], ee[2] - o[2]
            J[:, 0, i] = a1 * r2 - a2 * r1
            J[:, 1, i] = a2 * r0 - a0 * r2
            J[:, 2, i] = a0 * r1 - a1 * r0
        ch, sh = _kin._HAND_CS  # hand frame = R @ Rz(hand yaw)
        R = np.empty((n, 3, 3))
        for a in range(3):
            R[:, a, 0] = ch * x[a] + sh * y[a]
            R[:, a, 1] = ch * y[a] - sh * x[a]
            R[:, a, 2] = z[a]
        return np.stack(ee, axis=1), R, J

    def forward_pose(self, q: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        q = np.asarray(q, dtype=float)
        if q.ndim == 1:
            return self._one.forward_pose(q)
        ee, R, _ = self._chain(q.reshape(-1, 7))
        return ee.reshape(*q.shape[:-1], 3), R.reshape(*q.shape[:-1], 3, 3)

    def jacobian(self, q: ArrayLike) -> NDArray[np.float64]:
        q = np.asarray(q, dtype=float)
        if q.ndim == 1:
            return self._one.jacobian(q)
        _, _, J = self._chain(q.reshape(-1, 7))
        return J.reshape(*q.shape[:-1], 6, 7)

    def pose_and_jacobian(
        self, q: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """``forward_pose`` and ``jacobian`` of one state ``(7,)`` or a batch ``(n, 7)`` in one
        pass of the chain."""
        if q.ndim == 1:
            return self._one.pose_and_jacobian(q)
        if q.shape[0] == 1:  # one pass of the plain-float chain
            p, R, J = self._one.pose_and_jacobian(q[0])
            return p[None], R[None], J[None]
        return self._chain(q)

    def __repr__(self) -> str:
        return f"PandaModel(base_position={self.base_position.tolist()})"


def cup_held(observation: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether the gripper holds the cup, per row of ``(n, OBS_DIM)`` observations: the grasp
    point within :data:`HELD_DISTANCE` of the cup's middle, fingers resting on the cup."""
    obs = np.asarray(observation, dtype=float)
    middle = obs[:, _CUP] + _HALF_CUP
    offset = obs[:, _EE] - middle
    near = np.sqrt(np.add.reduce(offset * offset, axis=1)) < HELD_DISTANCE  # np.linalg.norm
    g = obs[:, _GRIPPER]
    return near & (g > _HELD_OPENING[0]) & (g < _HELD_OPENING[1])


def cup_rotation(
    cup_pos: ArrayLike, machine_pos: ArrayLike, machine_yaw: ArrayLike
) -> NDArray[np.float64]:
    """The cup frame's rotations ``(n, 3, 3)``: about z, the x axis along the grasp approach.

    The x axis is horizontal, perpendicular to the line from the robot base (the world origin) to
    the cup, on the side of that line where the machine's drip tray stands (the place point
    ``machine_pos + Rz(machine_yaw) @ PLACE_OFFSET``): the direction the teacher approaches the
    cup in, so the approach is the same in the cup frame whichever side the machine is on.

    Args:
        cup_pos: ``(n, 3)`` cup base positions, world frame.
        machine_pos: ``(n, 3)`` machine footprint centres.
        machine_yaw: ``(n,)`` machine yaw angles (rad).
    """
    cup = np.asarray(cup_pos, dtype=float).reshape(-1, 3)
    yaw = np.asarray(machine_yaw, dtype=float).reshape(-1)
    c, s = np.cos(yaw), np.sin(yaw)
    place = np.asarray(machine_pos, dtype=float).reshape(-1, 3)[:, :2] + np.stack(
        [c * PLACE_OFFSET[0] - s * PLACE_OFFSET[1], s * PLACE_OFFSET[0] + c * PLACE_OFFSET[1]],
        axis=1,
    )
    side = np.where(cup[:, 0] * place[:, 1] - cup[:, 1] * place[:, 0] >= 0.0, 1.0, -1.0)
    return rotation_from_angle(np.arctan2(cup[:, 1], cup[:, 0]) + side * (0.5 * np.pi), 3)


def _cup_held_one(obs: list[float]) -> bool:
    """:func:`cup_held` of one observation given as floats (the same operations in the same
    order)."""
    c0, c1, c2 = obs[_CUP]
    e0, e1, e2 = obs[_EE]
    o0, o1, o2 = e0 - (c0 + 0.0), e1 - (c1 + 0.0), e2 - (c2 + _HALF_CUP_Z)
    g = obs[_GRIPPER]
    near = math.sqrt(o0 * o0 + o1 * o1 + o2 * o2) < HELD_DISTANCE
    return near and g > _HELD_OPENING[0] and g < _HELD_OPENING[1]


def _cup_angle_one(cx: float, cy: float, mx: float, my: float, yaw: float) -> float:
    """The angle of :func:`cup_rotation` for one layout given as floats (the same operations in
    the same order)."""
    c, s = math.cos(yaw), math.sin(yaw)
    px = mx + (c * _PLACE_X - s * _PLACE_Y)
    py = my + (s * _PLACE_X + c * _PLACE_Y)
    side = 1.0 if cx * py - cy * px >= 0.0 else -1.0
    return math.atan2(cy, cx) + side * (0.5 * math.pi)


class CoffeeAdapter:
    """Reads gym-coffee observations for :class:`~lgp_policy.lfd.policy.GPDemonstrationPolicy`.

    Args:
        track_cup: ``True`` (default): the ``cup`` frame follows the cup's observed position until
            the gripper holds it; ``False``: the cup's pose at reset (``cup_init_pos``, the paper).
    """

    name = "coffee"
    obs_dim = OBS_DIM
    frame_names = ("cup", "machine")
    control_dt = _CONTROL_DT
    gripper = GripperSpec(closed=0.0, open=GRIPPER_MAX_OPENING)
    #: Which frame should be tight when each stage is first reached (the paper's Fig. 4; the
    #: policy's constraint check).
    expected_tight: ClassVar[dict[str, str]] = {
        "cup_grasped": "cup",
        "cup_placed": "machine",
        "button_pressed": "machine",
    }

    def __init__(self, *, track_cup: bool = True) -> None:
        self.track_cup = bool(track_cup)
        self.robot = PandaModel()
        self.action_map = JointDeltaAction(MAX_JOINT_STEP, self.gripper)
        self._time, self._yaw = OBS_SLICES["time"].start, OBS_SLICES["machine_yaw"].start
        self._joints, self._machine = OBS_SLICES["joint_pos"], OBS_SLICES["machine_pos"]
        self._cup, self._cup_init = OBS_SLICES["cup_pos"], OBS_SLICES["cup_init_pos"]

    def read(self, observation: NDArray[np.float64]) -> Observed:
        obs = observation
        if obs.shape[0] == 1:
            return self._read_one(obs)
        held = cup_held(obs)
        cup = obs[:, OBS_SLICES["cup_pos" if self.track_cup else "cup_init_pos"]]
        machine = obs[:, self._machine]
        yaw = obs[:, self._yaw]
        return Observed(
            time=obs[:, self._time],
            state=obs[:, self._joints],
            frames={
                "cup": (cup, cup_rotation(cup, machine, yaw)),
                "machine": (machine, rotation_from_angle(yaw, 3)),
            },
            valid={"cup": ~held} if self.track_cup else {},
            events={"cup_held": held},
        )

    def _read_one(self, obs: NDArray[np.float64]) -> Observed:
        """:meth:`read` of one observation ``(1, OBS_DIM)``, on floats (the control loop)."""
        v = obs[0].tolist()
        held = _cup_held_one(v)
        cup = self._cup if self.track_cup else self._cup_init
        cx, cy, _ = v[cup]
        mx, my, _ = v[self._machine]
        yaw = v[self._yaw]
        not_held = _FALSE if held else _TRUE
        angle = _cup_angle_one(cx, cy, mx, my, yaw)
        return Observed(
            time=obs[:, self._time],
            state=obs[:, self._joints],
            frames={
                "cup": (obs[:, cup], rotation_about_z(angle, 3)),
                "machine": (obs[:, self._machine], rotation_about_z(yaw, 3)),
            },
            valid={"cup": not_held} if self.track_cup else {},
            events={"cup_held": _TRUE if held else _FALSE},
        )

    @staticmethod
    def to_trajectories(demos: Iterable[Any]) -> TrajectorySet:
        """See :func:`to_trajectories`."""
        return to_trajectories(demos)

    def __repr__(self) -> str:
        return f"CoffeeAdapter(track_cup={self.track_cup})"


def _machine_yaw(quat: NDArray[np.float64]) -> NDArray[np.float64]:
    """The machine's yaw (rotation about z only), as the observation reports it."""
    return Rotation.from_quat(quat).as_euler("ZYX")[:, 0]


def to_trajectories(demos: Iterable[Any]) -> TrajectorySet:
    """Convert gym-coffee demonstrations (``DemonstrationSet`` or a sequence of
    ``Demonstration``) into a :class:`TrajectorySet`.

    State: the 7 arm joints; gripper: the commanded opening (m) from the action's gripper entry;
    frames: ``cup`` (position, :func:`cup_rotation` from the recorded cup and machine poses) and
    ``machine`` (position, yaw); events: the env's stage
    flags (``gym_coffee.STAGES``) and ``cup_held`` (from the recorded observations); the
    ``success`` flag is kept.
    """
    items = list(demos)
    out = []
    for d in items:
        actions = np.asarray(d.actions, dtype=float)  # the gripper is the last column in every mode
        stages = np.asarray(d.stages, dtype=bool)
        events = {name: stages[:, j] for j, name in enumerate(gym_coffee.STAGES[: stages.shape[1]])}
        events["cup_held"] = cup_held(np.asarray(d.observations, dtype=float))
        cup, machine = d.object_pos["cup"], d.object_pos["machine"]
        yaw = _machine_yaw(d.object_quat["machine"])
        out.append(
            Trajectory(
                time=d.time,
                state=d.joint_pos,
                gripper=(actions[:, -1] + 1.0) / 2.0 * GRIPPER_MAX_OPENING,
                actions=actions,
                frames={
                    "cup": (cup, cup_rotation(cup, machine, yaw)),
                    "machine": (machine, rotation_from_angle(yaw, 3)),
                },
                events=events,
                success=d.success,
            )
        )
    meta = dict(getattr(demos, "metadata", {}) or {})
    return TrajectorySet(out, meta)
