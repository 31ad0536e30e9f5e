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
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "DEFAULT_ALPHA",
    "DEFAULT_DAMPING",
    "DEFAULT_RIDGE",
    "MIN_VARIANCE",
    "FrameEstimate",
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


_EYES: dict[int, NDArray[np.float64]] = {}


def _eye(k: int) -> NDArray[np.float64]:
    """The read-only identity ``(k, k)`` (made once per size)."""
    eye = _EYES.get(k)
    if eye is None:
        eye = _EYES[k] = np.eye(k)
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


def reproduction_step(
    q: NDArray[np.float64],
    joint_target: NDArray[np.float64],
    joint_var: NDArray[np.float64],
    task_pos: NDArray[np.float64] | None = None,
    jacobian: NDArray[np.float64] | None = None,
    targets: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]] = (),
    *,
    alpha: float = DEFAULT_ALPHA,
    null_space_std: float | None = None,
    damping: float = DEFAULT_DAMPING,
    ridge: float = DEFAULT_RIDGE,
    return_cov: bool = False,
) -> tuple[NDArray[Any], NDArray[Any] | None]:
    """One iteration of Algorithm 3's loop (lines 6-19) for a batch of ``n`` robots.

    Args:
        q: ``theta_t``, ``(n, k)``.
        joint_target: ``theta_hat_{t+1}``, the joint-space GP mean, ``(n, k)``.
        joint_var: its predicted variance, ``(n, k)``.
        task_pos: ``x_t``, the task vector (``p`` entries: one or more points on the hand),
            ``(n, p)``; needed with ``targets``.
        jacobian: ``J(theta_t)``, ``(n, p, k)``; needed with ``targets``.
        targets: per frame, ``(position (n, p), precision (n, p, p))`` (see
            :func:`frame_targets`).
        alpha: weight of the null-space term (line 16).
        null_space_std: ``None`` (default): a frame's null-space information is the joint-space
            estimate's, projected; a float (rad): a fixed std instead (see the module docstring).
        damping: damping of the pseudo-inverse (m).
        ridge: added to the fused precision.
        return_cov: also return the fused covariance ``(n, k, k)``.

    Returns:
        ``(dtheta (n, k), covariance (n, k, k) or None)``.
    """
    n, k = q.shape
    de = joint_target - q  # line 15
    lam_theta = 1.0 / np.maximum(joint_var, MIN_VARIANCE)
    Lam = np.zeros((n, k, k))
    Lam.reshape(n, k * k)[:, :: k + 1] = lam_theta + ridge  # the diagonals
    eta = lam_theta * de
    if targets:
        if task_pos is None or jacobian is None:
            raise ValueError("frame targets need task_pos and jacobian")
        J = jacobian
        Jt = J.mT
        J_pinv = damped_pseudoinverse(J, damping)  # line 10
        N = _eye(k) - J_pinv @ J
        null_term = alpha * (N @ de[:, :, None])[:, :, 0]
        if null_space_std is None:
            null_prec = (N * lam_theta[:, None, :]) @ N
        else:
            null_prec = N / null_space_std**2
        for pos, prec in targets:
            dx = pos - task_pos  # line 14
            mean = (J_pinv @ dx[:, :, None])[:, :, 0] + null_term  # line 16
            P = Jt @ prec @ J + null_prec  # line 17, information form
            Lam += P
            eta += (P @ mean[:, :, None])[:, :, 0]
    Lam = 0.5 * (Lam + Lam.mT)
    if return_cov:
        cov = np.linalg.inv(Lam)
        dq: NDArray[Any] = (cov @ eta[:, :, None])[:, :, 0]  # line 19
        return dq, cov
    dq = np.linalg.solve(Lam, eta[:, :, None])[:, :, 0]
    return dq, None


def limit_step(dq: NDArray[np.float64], max_step: float) -> NDArray[np.float64]:
    """Scale each row of ``dq (n, k)`` so that ``max |dq_j| <= max_step``, keeping its direction."""
    peak = np.abs(dq).max(axis=-1, keepdims=True)
    return dq * np.minimum(1.0, max_step / np.maximum(peak, 1e-300))
