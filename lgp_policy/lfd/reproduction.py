"""Reproduction of a demonstrated task: Algorithm 3 of Schneider & Ertel (IROS 2010), batched.

At every step the joint-space estimate ``theta_hat`` and, for every object ``m``, the task-space
estimate ``x_hat^(m)`` (the hand relative to the object's frame) are turned into joint increments
and fused by their uncertainty:

* per object (Algorithm 3, lines 14-17):
  ``dx^(m) = o^(m) + R^(m) x_hat^(m) - x_t``,
  ``dtheta^(m) = J^+ dx^(m) + alpha (I - J^+ J) (theta_hat - theta_t)``,
  ``Sigma^(m) = J^+ Sigma_x^(m) J^+^T``;
* the Gaussian product of all ``N(dtheta^(m), Sigma^(m))`` and
  ``N(theta_hat - theta_t, Sigma_theta)`` (line 19).

**Information form and regularisation.** With a 7-joint arm and a 3-D position,
``J^+ Sigma_x J^+^T`` has rank 3: it carries no information about the 4-D null space of ``J``, so it
cannot be inverted and the product of line 19 cannot be written with covariances. We write it with
precisions instead. For a full-row-rank ``J`` the pseudo-inverse of ``J^+ Sigma_x J^+^T`` is exactly
``J^T Sigma_x^-1 J`` (the information a Cartesian measurement with covariance ``Sigma_x`` gives
about a joint increment). We regularise each frame's joint-space covariance by giving its null-space
part finite information::

    Lambda^(m) = J^T Sigma_x^-1 J + Lambda_N,
    Lambda_N   = N Sigma_theta^-1 N        (default, null_space_std=None)
               = N / s_N^2                 (null_space_std=s_N)

with ``N = I - J^+ J``, so that the null-space term ``alpha N (theta_hat - theta_t)`` of line 16
keeps its meaning. By default a frame's opinion in the null space is exactly as certain as the
joint-space estimate it comes from: where the demonstrations disagree in joint space (large
``Sigma_theta``) the null-space pull is weak, where they agree it is strong. (A fixed ``s_N``
lets an uncertain joint-space mean drive large null-space motions; measured on demonstrations
whose wrist postures differ by radians.) Then fuse::

    Lambda = Lambda_theta + sum_m Lambda^(m) + eps I
    dtheta = Lambda^-1 (Lambda_theta (theta_hat - theta_t) + sum_m Lambda^(m) dtheta^(m))

with ``Lambda_theta = Sigma_theta^-1`` (diagonal: one GP per joint) and a tiny ``eps`` (``ridge``)
that only matters when every input is uninformative. ``Lambda^-1`` is the remaining joint-space
covariance (the shaded band of Fig. 5b). Near kinematic singularities ``J^+`` is the damped
pseudo-inverse ``J^T (J J^T + lambda^2 I)^-1``.

Every function works on a batch of ``n`` robots at once (one vectorised pass; the policy's
``predict`` on ``n`` observations) and needs only plain arrays: the task vector ``x (n, p)`` and its
Jacobian ``J (n, p, k)`` come from a :class:`~lgp_policy.lfd.robots.RobotModel`.
:func:`reproduction_step` sums the frames in one pass over all of them (:class:`FrameStack`) and
runs one robot (the common control loop) on 2-D arrays with a Cholesky solver.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg.lapack import dposv as _dposv

__all__ = [
    "DEFAULT_ALPHA",
    "DEFAULT_DAMPING",
    "DEFAULT_RIDGE",
    "MIN_VARIANCE",
    "FrameEstimate",
    "FrameStack",
    "damped_pseudoinverse",
    "frame_estimate",
    "frame_targets",
    "limit_step",
    "reproduction_step",
]

DEFAULT_ALPHA = 0.5
"""Weight of the null-space term towards the joint-space estimate (Algorithm 3, line 2)."""
DEFAULT_DAMPING = 1e-3
"""m; damping ``lambda`` of the pseudo-inverse, negligible away from singularities."""
DEFAULT_RIDGE = 1e-9
"""rad^-2; added to the fused precision so it is always invertible."""
MIN_VARIANCE = 1e-10
"""Floor on every predicted variance (rad^2 or m^2), keeps precisions finite."""
_MIN_VARIANCE = np.array(MIN_VARIANCE)  # as an array: cheaper in a ufunc than a Python float


_EYES: dict[int, NDArray[np.float64]] = {}


def _eye(k: int) -> NDArray[np.float64]:
    """The read-only identity ``(k, k)`` (made once per size)."""
    eye = _EYES.get(k)
    if eye is None:
        eye = _EYES[k] = np.eye(k)
        eye.setflags(write=False)
    return eye


_DAMPED: dict[tuple[int, float], NDArray[np.float64]] = {}


def _damped_eye(p: int, damping: float) -> NDArray[np.float64]:
    """The read-only ``damping^2 I`` ``(p, p)`` (made once per size and damping)."""
    key = (p, damping)
    eye = _DAMPED.get(key)
    if eye is None:
        eye = _DAMPED[key] = damping**2 * np.eye(p)
        eye.setflags(write=False)
    return eye


def damped_pseudoinverse(
    jacobian: ArrayLike, damping: float = DEFAULT_DAMPING
) -> NDArray[np.float64]:
    """``J^T (J J^T + damping^2 I)^-1`` for ``J (..., p, k)``; returns ``(..., k, p)``."""
    J = np.asarray(jacobian, dtype=float)
    JJt = J @ J.mT
    JJt = JJt + damping**2 * _eye(J.shape[-2])
    return np.linalg.solve(JJt, J).mT


def frame_targets(
    origin: NDArray[np.float64],
    rotation: NDArray[np.float64],
    mean: NDArray[np.float64],
    var: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """World targets of one frame for a batch: ``o + R x_hat`` per point, with their precision.

    Args:
        origin: ``(n, d)``; rotation: ``(n, d, d)``.
        mean: ``(n, b d)``, ``b`` points on the hand in the frame's axes; var: ``(n, b d)``.

    Returns:
        ``(position (n, b d), precision (n, b d, b d))``: block diagonal ``R diag(1/var) R^T``.
    """
    n, d = origin.shape
    b = mean.shape[1] // d
    m = mean.reshape(n, b, d)
    Rt = rotation.mT
    pos = (origin[:, None, :] + m @ Rt).reshape(n, b * d)
    inv = 1.0 / np.maximum(var, MIN_VARIANCE)
    prec = np.zeros((n, b * d, b * d))
    for j in range(b):
        blk = slice(j * d, (j + 1) * d)
        prec[:, blk, blk] = (rotation * inv[:, None, blk]) @ Rt
    return pos, prec


@dataclass(frozen=True)
class FrameEstimate:
    """One frame's world target for one robot: ``position`` ``o + R x_hat (p,)`` and its
    ``precision`` ``(p, p)``."""

    position: NDArray[np.float64]
    precision: NDArray[np.float64]


def frame_estimate(
    origin: ArrayLike, rotation: ArrayLike, mean: ArrayLike, var: ArrayLike
) -> FrameEstimate:
    """:func:`frame_targets` for one robot."""
    o = np.asarray(origin, dtype=float)
    pos, prec = frame_targets(
        o[None],
        np.asarray(rotation, dtype=float)[None],
        np.asarray(mean, dtype=float).reshape(1, -1),
        np.asarray(var, dtype=float).reshape(1, -1),
    )
    return FrameEstimate(pos[0], prec[0])


class FrameStack(NamedTuple):
    """The frames of Algorithm 3 for a batch of ``n`` robots, stacked over the ``m`` frames.

    Attributes:
        origin: ``(n, m, d)`` frame positions; rotation: ``(n, m, d, d)`` (columns: the frame's
            axes in the world).
        mean: ``(n, m, b d)``, the hand's ``b`` task points predicted in each frame's axes;
            var: ``(n, m, b d)``, their predicted variances (per axis of the frame).

    The world target of frame ``j`` is ``o_j + R_j mean_j`` per point, with the precision
    ``R_j diag(1 / var_j) R_j^T`` per point (:func:`frame_targets`).
    """

    origin: NDArray[np.float64]
    rotation: NDArray[np.float64]
    mean: NDArray[np.float64]
    var: NDArray[np.float64]


def reproduction_step(
    q: NDArray[np.float64],
    joint_target: NDArray[np.float64],
    joint_var: NDArray[np.float64],
    task_pos: NDArray[np.float64] | None = None,
    jacobian: NDArray[np.float64] | None = None,
    frames: FrameStack | None = None,
    *,
    alpha: float = DEFAULT_ALPHA,
    null_space_std: float | None = None,
    damping: float = DEFAULT_DAMPING,
    ridge: float = DEFAULT_RIDGE,
    return_cov: bool = False,
) -> tuple[NDArray[Any], NDArray[Any] | None]:
    """One iteration of Algorithm 3's loop (lines 6-19) for a batch of ``n`` robots.

    Args:
        q: ``theta_t``, ``(n, k)``, or ``(k,)`` for one robot (then every argument drops its
            leading ``n``; a batch of one is run that way too).
        joint_target: ``theta_hat_{t+1}``, the joint-space GP mean, ``(n, k)``.
        joint_var: its predicted variance, ``(n, k)``.
        task_pos: ``x_t``, the task vector (``p`` entries: one or more points on the hand),
            ``(n, p)``; needed with ``frames``.
        jacobian: ``J(theta_t)``, ``(n, p, k)``; needed with ``frames``.
        frames: the frames' poses and the task-space GPs' predictions (:class:`FrameStack`), or
            ``None`` (the joint-space estimate alone).
        alpha: weight of the null-space term (line 16).
        null_space_std: ``None`` (default): a frame's null-space information is the joint-space
            estimate's, projected; a float (rad): a fixed std instead (see the module docstring).
        damping: damping of the pseudo-inverse (m).
        ridge: added to the fused precision.
        return_cov: also return the fused covariance ``(n, k, k)``.

    Returns:
        ``(dtheta (n, k), covariance (n, k, k) or None)``.

    The frames are summed in one pass over all of them (equal to the frame-by-frame form up to
    rounding; tested against it): with ``dtheta_j = J^+ dx_j + t`` (line 16, ``t`` the
    null-space term), ``Lambda^(j) = J^T W_j J + L_N`` and ``Y`` stacking ``R_j^T J`` per frame
    and point (the frame's own axes, where ``W_j = diag(1 / var_j)``)::

        sum_j Lambda^(j)            = Y^T W Y + m L_N
        sum_j Lambda^(j) dtheta_j   = Y^T W [Y_j dtheta_j]_j + L_N sum_j dtheta_j

    ``J^+ = Z^T`` with ``Z = (J J^T + lambda^2 I)^-1 J`` (a solve, no explicit inverse). One robot
    (``q (k,)`` or a batch of one) runs on 2-D arrays with LAPACK's Cholesky solver.
    """
    if frames is not None and (task_pos is None or jacobian is None):
        raise ValueError("frames need task_pos and jacobian")
    args = (alpha, null_space_std, damping, ridge, return_cov)
    if q.ndim == 1:
        return _step_one(q, joint_target, joint_var, task_pos, jacobian, frames, *args)
    if q.shape[0] == 1:  # a batch of one: the one-robot path
        dq, cov = _step_one(
            q[0],
            joint_target[0],
            joint_var[0],
            None if task_pos is None else task_pos[0],
            None if jacobian is None else jacobian[0],
            None if frames is None else FrameStack(*(a[0] for a in frames)),
            *args,
        )
        return dq[None], None if cov is None else cov[None]
    return _step(q, joint_target, joint_var, task_pos, jacobian, frames, *args)


def _spd_solve(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """``A^-1 B`` for a symmetric positive definite ``A (k, k)`` (LAPACK's Cholesky solver, which
    reads the upper triangle); the general solver if ``A`` is not numerically positive definite."""
    _c, x, info = _dposv(A, B)
    if info != 0:
        return np.asarray(np.linalg.solve(0.5 * (A + A.T), B))
    return np.asarray(x)


def _step_one(
    q: NDArray[np.float64],
    joint_target: NDArray[np.float64],
    joint_var: NDArray[np.float64],
    task_pos: NDArray[np.float64] | None,
    J: NDArray[np.float64] | None,
    frames: FrameStack | None,
    alpha: float,
    null_space_std: float | None,
    damping: float,
    ridge: float,
    return_cov: bool,
) -> tuple[NDArray[Any], NDArray[Any] | None]:
    """:func:`_step` for one robot: ``q (k,)``, ``J (p, k)``, frames ``(m, ...)``; the same
    arithmetic on 2-D arrays (``ndarray.dot``: fewer and cheaper calls than ``matmul``) with a
    Cholesky solver."""
    k = q.shape[0]
    de = joint_target - q  # line 15
    if frames is None or task_pos is None or J is None:
        lam_theta = np.reciprocal(np.maximum(joint_var, _MIN_VARIANCE))
        eta = lam_theta * de
        Lam = np.zeros((k, k))
    else:
        origin, rotation, mean, var = frames
        # the precisions of the joint estimate and of every frame's points at once
        prec = np.reciprocal(np.maximum(np.concatenate((joint_var, var), axis=None), _MIN_VARIANCE))
        lam_theta = prec[:k]
        eta = lam_theta * de
        m, d = origin.shape
        p = J.shape[0]
        b = p // d
        A = J.dot(J.T)
        A += _damped_eye(p, damping)
        Z = _spd_solve(A, J)  # J^+ = Z^T (line 10)
        N = _eye(k) - Z.T.dot(J)
        if null_space_std is None:
            null_prec = (N * lam_theta).dot(N)
        else:
            null_prec = N / null_space_std**2
        Rt = rotation.transpose(0, 2, 1)
        target = np.matmul(mean.reshape(m, b, d), Rt)
        target += origin[:, None, :]
        dx = target.reshape(m, p)
        dx -= task_pos
        dtheta = dx.dot(Z)
        dtheta += alpha * N.dot(de)
        Y = np.matmul(Rt[:, None], J.reshape(b, d, k)).reshape(m, p, k)
        u = np.matvec(Y, dtheta).reshape(m * p)
        Y = Y.reshape(m * p, k)
        YtW = Y.T * prec[k:]
        Lam = YtW.dot(Y)
        Lam += m * null_prec
        eta += YtW.dot(u)
        eta += null_prec.dot(dtheta.sum(axis=0))
    Lam.reshape(k * k)[:: k + 1] += lam_theta + ridge
    if return_cov:  # line 19
        cov = _spd_solve(Lam, _eye(k))
        return cov.dot(eta), cov
    return _spd_solve(Lam, eta), None


def _step(
    q: NDArray[np.float64],
    joint_target: NDArray[np.float64],
    joint_var: NDArray[np.float64],
    task_pos: NDArray[np.float64] | None,
    J: NDArray[np.float64] | None,
    frames: FrameStack | None,
    alpha: float,
    null_space_std: float | None,
    damping: float,
    ridge: float,
    return_cov: bool,
) -> tuple[NDArray[Any], NDArray[Any] | None]:
    """:func:`reproduction_step` for a batch ``(n, k)`` (see its docstring for the sums)."""
    n, k = q.shape
    de = joint_target - q  # line 15
    lam_theta = 1.0 / np.maximum(joint_var, MIN_VARIANCE)
    eta = lam_theta * de
    if frames is None or task_pos is None or J is None:
        Lam = np.zeros((n, k, k))
    else:
        origin, rotation, mean, var = frames
        m, d = origin.shape[1:]
        p = J.shape[1]
        b = p // d
        Jt = J.mT
        Z = np.linalg.solve(J @ Jt + _damped_eye(p, damping), J)  # J^+ = Z^T (line 10)
        N = _eye(k) - Z.mT @ J
        if null_space_std is None:
            null_prec = (N * lam_theta[:, None, :]) @ N
        else:
            null_prec = N / null_space_std**2
        t = alpha * np.matvec(N, de)
        # per frame: dx = o + R x_hat - x_t (line 14), dtheta = J^+ dx + t (line 16), (n, m, k)
        Rt = rotation.mT
        target = origin[:, :, None, :] + mean.reshape(n, m, b, d) @ Rt
        dtheta = (target.reshape(n, m, p) - task_pos[:, None, :]) @ Z
        dtheta += t[:, None, :]
        # J^T W J and J^T W J dtheta in each frame's axes: Y = R^T J per point, W = diag(1/var)
        Jb = J.reshape(n, b, d, k).transpose(0, 2, 1, 3).reshape(n, d, b * k)  # points side by side
        Y = (Rt.reshape(n, m * d, d) @ Jb).reshape(n, m, d, b, k)  # one product per robot
        Y = Y.transpose(0, 1, 3, 2, 4).reshape(n, m * p, k)
        u = np.matvec(Y.reshape(n, m, p, k), dtheta).reshape(n, m * p)
        YtW = Y.mT * (1.0 / np.maximum(var, MIN_VARIANCE)).reshape(n, 1, m * p)
        Lam = YtW @ Y  # sum of the frames' Lambda^(j) (line 17, information form)
        Lam += m * null_prec
        eta += np.matvec(YtW, u)
        eta += np.matvec(null_prec, dtheta.sum(axis=1))
    Lam.reshape(n, k * k)[:, :: k + 1] += lam_theta + ridge
    if return_cov:  # line 19
        cov = _solve(Lam, _eye(k))
        return np.matvec(cov, eta), cov
    return _solve(Lam, eta[:, :, None])[:, :, 0], None


def _solve(A: NDArray[np.float64], B: NDArray[np.float64]) -> NDArray[np.float64]:
    """``A^-1 B`` for a stack ``(n, k, k)`` of symmetric positive definite matrices (LU of the
    symmetrised matrices); ``B`` ``(n, k, r)`` or ``(k, r)``."""
    B = np.broadcast_to(B, A.shape[:-2] + B.shape[-2:])
    return np.asarray(np.linalg.solve(0.5 * (A + A.mT), B))


def limit_step(dq: NDArray[np.float64], max_step: float) -> NDArray[np.float64]:
    """Scale each row of ``dq (n, k)`` so that ``max |dq_j| <= max_step``, keeping its direction."""
    if dq.shape[0] == 1:  # the same arithmetic on floats
        values = dq[0].tolist()
        peak = math.nan if any(map(math.isnan, values)) else max(map(abs, values))
        return dq * min(max_step / max(peak, 1e-300), 1.0)  # (a NaN stays NaN)
    peak = np.abs(dq).max(axis=-1, keepdims=True)
    return dq * np.minimum(1.0, max_step / np.maximum(peak, 1e-300))
