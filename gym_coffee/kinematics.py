"""Pure-numpy kinematics of the Franka Panda arm (no PyBullet).

The chain is the one of ``franka_panda/panda.urdf`` in ``pybullet_data``: seven revolute joints,
then the fixed flange (``panda_joint8``, 0.107 m), the hand (rotated by -pi/4 about z) and the grasp
target between the fingertips (0.105 m further along the hand's z axis, link ``panda_grasptarget``).
The end-effector point of gym-coffee is that grasp target, the same point as ``ee_pos`` in the
observations.

:class:`PandaKinematics` satisfies the ``RobotModel`` protocol of ``docs/CONTRACTS.md``:
``n_joints``, ``forward_kinematics(q) -> (3,)``, ``position_jacobian(q) -> (3, 7)``,
``joint_lower``, ``joint_upper``. The Jacobian is the exact geometric one (``z_i x (p_ee - p_i)``),
not a finite difference.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "GRASP_OFFSET",
    "JOINT_LOWER",
    "JOINT_UPPER",
    "JOINT_VELOCITY_LIMIT",
    "PandaKinematics",
]

# URDF joint origins of panda_joint1..7: translation (m) and roll (rad); pitch and yaw are zero.
_JOINT_XYZ = np.array(
    [
        [0.0, 0.0, 0.333],
        [0.0, 0.0, 0.0],
        [0.0, -0.316, 0.0],
        [0.0825, 0.0, 0.0],
        [-0.0825, 0.384, 0.0],
        [0.0, 0.0, 0.0],
        [0.088, 0.0, 0.0],
    ]
)
_HALF_PI_URDF = 1.57079632679  # the URDF's literal value
_JOINT_ROLL = np.array(
    [
        0.0,
        -_HALF_PI_URDF,
        _HALF_PI_URDF,
        _HALF_PI_URDF,
        -_HALF_PI_URDF,
        _HALF_PI_URDF,
        _HALF_PI_URDF,
    ]
)
#: Distance (m) from the link-7 frame to the grasp point along link 7's z axis (flange 0.107 +
#: 0.105).
GRASP_OFFSET = 0.107 + 0.105
_HAND_YAW = -0.785398163397  # panda_hand_joint rpy (rad)

#: Joint limits (rad) of panda_joint1..7 from the URDF.
JOINT_LOWER = np.array([-2.9671, -1.8326, -2.9671, -3.1416, -2.9671, -0.0873, -2.9671])
JOINT_UPPER = np.array([2.9671, 1.8326, 2.9671, 0.0, 2.9671, 3.8223, 2.9671])
#: Joint velocity limits (rad/s) from the URDF.
JOINT_VELOCITY_LIMIT = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])


_XYZ = [tuple(row) for row in _JOINT_XYZ.tolist()]
_EYE6, _EYE7 = np.eye(6), np.eye(7)
_ROLL_CS = [(float(np.cos(r)), float(np.sin(r))) for r in _JOINT_ROLL]
_HAND_CS = (float(np.cos(_HAND_YAW)), float(np.sin(_HAND_YAW)))


class PandaKinematics:
    """Forward kinematics and Jacobians of the Panda's grasp point, in the world frame.

    Args:
        base_position: world position (m) of the robot base (``panda_link0``); the base is not
        rotated.

    Results for the last joint vector are cached, so calling :meth:`forward_kinematics` and
    :meth:`position_jacobian` with the same ``q`` computes the chain once;
    :meth:`pose_and_jacobian` returns the pose and the Jacobian of one pass without the cache.

    Example:
        >>> kin = PandaKinematics()
        >>> q = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
        >>> kin.forward_kinematics(q).shape, kin.position_jacobian(q).shape
        ((3,), (3, 7))
    """

    n_joints: int = 7

    def __init__(self, base_position: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        self.base_position = np.asarray(base_position, dtype=np.float64).reshape(3)
        self.joint_lower = JOINT_LOWER.copy()
        self.joint_upper = JOINT_UPPER.copy()
        self._q: NDArray[np.float64] | None = None
        self._pos = np.zeros(3)
        self._rot = np.eye(3)
        self._jac = np.zeros((6, 7))

    def _walk(
        self,
        q: NDArray[np.float64],
        axes: list[tuple[float, float, float]] | None = None,
        origins: list[tuple[float, float, float]] | None = None,
    ) -> tuple[float, ...]:
        """Walk the chain in plain floats (columns x, y, z of the current frame's rotation and its
        origin p; for 3-vectors several times faster than numpy). Returns the last frame's
        ``x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2``; appends each joint's axis and origin to
        ``axes`` and ``origins`` when given (the Jacobian's columns)."""
        if q.shape != (7,):
            raise ValueError(f"q must have shape (7,), got {q.shape}")
        cos, sin = np.cos(q).tolist(), np.sin(q).tolist()
        x0, x1, x2 = 1.0, 0.0, 0.0
        y0, y1, y2 = 0.0, 1.0, 0.0
        z0, z1, z2 = 0.0, 0.0, 1.0
        p0, p1, p2 = self.base_position.tolist()
        for i in range(7):
            t0, t1, t2 = _XYZ[i]
            p0 += t0 * x0 + t1 * y0 + t2 * z0
            p1 += t0 * x1 + t1 * y1 + t2 * z1
            p2 += t0 * x2 + t1 * y2 + t2 * z2
            cr, sr = _ROLL_CS[i]
            if sr != 0.0:  # R @ Rx(roll)
                y0, y1, y2, z0, z1, z2 = (
                    cr * y0 + sr * z0,
                    cr * y1 + sr * z1,
                    cr * y2 + sr * z2,
                    cr * z0 - sr * y0,
                    cr * z1 - sr * y1,
                    cr * z2 - sr * y2,
                )
            c, s = cos[i], sin[i]  # R @ Rz(q_i)
            x0, x1, x2, y0, y1, y2 = (
                c * x0 + s * y0,
                c * x1 + s * y1,
                c * x2 + s * y2,
                c * y0 - s * x0,
                c * y1 - s * x1,
                c * y2 - s * x2,
            )
            if axes is not None and origins is not None:
                axes.append((z0, z1, z2))
                origins.append((p0, p1, p2))
        return x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2

    def _chain(
        self, q: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """One pass of the chain: grasp point (3,), hand rotation (3, 3), geometric Jacobian
        (6, 7)."""
        axes: list[tuple[float, float, float]] = []
        origins: list[tuple[float, float, float]] = []
        x0, x1, x2, y0, y1, y2, z0, z1, z2, p0, p1, p2 = self._walk(q, axes, origins)
        d = GRASP_OFFSET
        e0, e1, e2 = p0 + d * z0, p1 + d * z1, p2 + d * z2
        j0: list[float] = []
        j1: list[float] = []
        j2: list[float] = []
        for (a0, a1, a2), (o0, o1, o2) in zip(axes, origins, strict=True):  # z_i x (p_ee - p_i)
            r0, r1, r2 = e0 - o0, e1 - o1, e2 - o2
            j0.append(a1 * r2 - a2 * r1)
            j1.append(a2 * r0 - a0 * r2)
            j2.append(a0 * r1 - a1 * r0)
        w0, w1, w2 = zip(*axes, strict=True)
        ch, sh = _HAND_CS  # hand frame = R @ Rz(hand yaw)
        rot = np.array(
            [
                [ch * x0 + sh * y0, ch * y0 - sh * x0, z0],
                [ch * x1 + sh * y1, ch * y1 - sh * x1, z1],
                [ch * x2 + sh * y2, ch * y2 - sh * x2, z2],
            ]
        )
        return np.array([e0, e1, e2]), rot, np.array([j0, j1, j2, w0, w1, w2])

    def _position(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        """The grasp point (3,) alone: :meth:`_chain`'s walk without the Jacobian and the hand
        rotation (the same bits; the env needs only the point at every step)."""
        *_, z0, z1, z2, p0, p1, p2 = self._walk(q)
        d = GRASP_OFFSET
        return np.array([p0 + d * z0, p1 + d * z1, p2 + d * z2])

    def _update(self, q: ArrayLike) -> None:
        q = np.asarray(q, dtype=np.float64)
        if self._q is not None and np.array_equal(q, self._q):
            return
        self._pos, self._rot, self._jac = self._chain(q)
        self._q = q.copy()

    def pose_and_jacobian(
        self, q: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """:meth:`forward_pose` and :meth:`jacobian` in one pass of the chain (new arrays; the
        cache is neither read nor written)."""
        return self._chain(np.asarray(q, dtype=np.float64))

    def forward_kinematics(self, q: ArrayLike) -> NDArray[np.float64]:
        """Grasp-point position (3,) in the world frame for joint positions ``q`` (7,)."""
        q = np.asarray(q, dtype=np.float64)
        if self._q is not None and np.array_equal(q, self._q):
            return self._pos.copy()
        return self._position(q)

    def forward_pose(self, q: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Grasp-point position (3,) and hand orientation (3, 3) (columns: hand x, y, z axes).

        The hand's z axis points from the wrist through the fingertips; the fingers close along its
        y axis.
        """
        self._update(q)
        return self._pos.copy(), self._rot.copy()

    def position_jacobian(self, q: ArrayLike) -> NDArray[np.float64]:
        """Position Jacobian (3, 7) of the grasp point: column i is ``z_i x (p_ee - p_i)``."""
        self._update(q)
        return self._jac[:3].copy()

    def jacobian(self, q: ArrayLike) -> NDArray[np.float64]:
        """Geometric Jacobian (6, 7): position rows, then angular-velocity rows (the joint axes)."""
        self._update(q)
        return self._jac.copy()

    def ik_step(
        self,
        q: NDArray[np.float64],
        position: NDArray[np.float64],
        rotation: NDArray[np.float64],
        rest: NDArray[np.float64],
        *,
        max_step: float,
        iterations: int = 2,
        damping: float = 0.03,
        orientation_weight: float = 0.3,
        null_space_gain: float = 0.05,
        keep_direction: bool = False,
    ) -> NDArray[np.float64]:
        """Joint targets that move the grasp point towards ``position`` (3,) and the hand towards
        ``rotation`` (3, 3), from the measured joint positions ``q`` (7,).

        ``iterations`` damped-least-squares steps on the 6-D pose error (orientation errors, in rad,
        weighted by ``orientation_weight`` against position errors in m), each with a null-space
        pull of ``null_space_gain`` towards the posture ``rest``. The change from ``q`` is limited
        to ``max_step`` rad per joint: clipped joint by joint, or, with ``keep_direction``, scaled
        as a whole (the hand then moves along the commanded direction, only slower); the result is
        clipped to the joint limits. The scripted teacher and the env's end-effector action modes
        share it.
        """
        q_target = q.copy()
        eye6, eye7 = _EYE6, _EYE7
        for _ in range(iterations):
            pos, rot = self.forward_pose(q_target)
            err_p = position - pos
            # 1/2 sum_i rot[:, i] x rotation[:, i], written out: each component of the three
            # cross products is np.cross's a1 b2 - a2 b1 (no fused multiply-add), summed in the
            # order of three np.cross calls (the same bits, without np.cross's axis handling).
            cx = rot[1] * rotation[2] - rot[2] * rotation[1]
            cy = rot[2] * rotation[0] - rot[0] * rotation[2]
            cz = rot[0] * rotation[1] - rot[1] * rotation[0]
            err_o = 0.5 * np.array(
                [cx[0] + cx[1] + cx[2], cy[0] + cy[1] + cy[2], cz[0] + cz[1] + cz[2]]
            )
            jac = self.jacobian(q_target)
            jac[3:] *= orientation_weight
            err = np.concatenate([err_p, orientation_weight * err_o])
            jjt = jac @ jac.T + damping**2 * eye6
            dq = jac.T @ np.linalg.solve(jjt, err)
            pinv = jac.T @ np.linalg.solve(jjt, jac)
            dq += (eye7 - pinv) @ (null_space_gain * (rest - q_target))
            q_target = q_target + dq
        step = q_target - q
        largest = float(np.max(np.abs(step)))
        if keep_direction and largest > max_step:
            step *= max_step / largest
        else:
            step = np.clip(step, -max_step, max_step)
        return np.clip(q + step, self.joint_lower, self.joint_upper)
