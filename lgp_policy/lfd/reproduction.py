"""Reproduction of a demonstrated task: Algorithm 3 of Schneider & Ertel (IROS 2010).

At every step the joint-space estimate ``theta_hat`` and, for every detected object ``m``, the
task-space estimate ``x_hat^(m)`` (end-effector position relative to the object's initial pose) are
turned into joint increments and fused by their uncertainty:

* per object (Algorithm 3, lines 14-17):
  ``dx^(m) = o^(m) + x_hat^(m) - x_t``,
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

Everything here is plain numpy and needs only a robot model with
``forward_kinematics(q) -> (3,)`` and ``position_jacobian(q) -> (3, n_joints)`` (the ``RobotModel``
protocol of ``docs/CONTRACTS.md``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "DEFAULT_ALPHA",
    "FrameEstimate",
    "Reproduction",
    "RobotModel",
    "damped_pseudoinverse",
    "frame_estimate",
    "fuse_information",
    "limit_step",
    "reproduce",
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


class RobotModel(Protocol):
    """What the reproduction needs from a robot (``docs/CONTRACTS.md``)."""

    n_joints: int
    joint_lower: NDArray[np.float64]
    joint_upper: NDArray[np.float64]

    def forward_kinematics(self, q: NDArray[np.float64]) -> NDArray[np.float64]: ...

    def position_jacobian(self, q: NDArray[np.float64]) -> NDArray[np.float64]: ...


@dataclass(frozen=True)
class FrameEstimate:
    """One object's task-space estimate at one time step, already in world coordinates.

    Attributes:
        position: ``o^(m) + R^(m) x_hat^(m)``, the end-effector position the frame asks for,
            ``(3,)``.
        covariance: ``R^(m) Sigma_x^(m) R^(m)^T``, its covariance, ``(3, 3)``.
    """

    position: NDArray[np.float64]
    covariance: NDArray[np.float64]
    precision: NDArray[np.float64] | None = None
    """Optional ``covariance^-1`` when the caller has it in closed form (saves a solve)."""


@dataclass(frozen=True)
class Reproduction:
    """A trajectory reproduced open loop by Algorithm 3.

    Attributes:
        joint_pos: ``theta_t``, ``(T, n_joints)``.
        ee_pos: ``x_t = DK(theta_t)``, ``(T, 3)``.
        joint_std: std of the fused increment at each step (remaining uncertainty),
            ``(T, n_joints)``.
        frame_targets: per frame, the world position it asked for at each step, ``(T, 3)``.
    """

    joint_pos: NDArray[np.float64]
    ee_pos: NDArray[np.float64]
    joint_std: NDArray[np.float64]
    frame_targets: dict[str, NDArray[np.float64]]


def damped_pseudoinverse(
    jacobian: NDArray[np.float64], damping: float = DEFAULT_DAMPING
) -> NDArray:
    """``J^T (J J^T + damping^2 I)^-1`` for ``J (p, k)``, ``p <= k``; returns ``(k, p)``."""
    J = np.asarray(jacobian, dtype=float)
    JJt = J @ J.T
    JJt[np.diag_indices_from(JJt)] += damping**2
    return np.linalg.solve(JJt, J).T


def fuse_information(
    means: Sequence[NDArray[np.float64]], precisions: Sequence[NDArray[np.float64]], ridge: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Gaussian product ``prod_i N(mean_i, precision_i^-1)`` in information form.

    Args:
        means: ``(k,)`` each.
        precisions: ``(k, k)`` each, positive semi-definite; their sum plus ``ridge I`` must be
            definite.
        ridge: added to the diagonal of the summed precision.

    Returns:
        ``(mean (k,), covariance (k, k))`` of the product.
    """
    k = means[0].shape[0]
    Lam = np.zeros((k, k))
    eta = np.zeros(k)
    for mu, P in zip(means, precisions, strict=True):
        Lam += P
        eta += P @ mu
    Lam[np.diag_indices(k)] += ridge
    Lam = 0.5 * (Lam + Lam.T)
    try:
        np.linalg.cholesky(Lam)  # a cheap check that the product is a proper Gaussian
    except np.linalg.LinAlgError as exc:  # pragma: no cover - guarded by the ridge
        raise np.linalg.LinAlgError(
            "The fused precision of Algorithm 3 is not positive definite. Increase 'ridge' or the "
            "variance floor of the joint-space estimate."
        ) from exc
    cov = np.linalg.inv(Lam)  # k x k (7 x 7): one call, well conditioned thanks to the ridge
    return cov @ eta, cov


def reproduction_step(
    robot: RobotModel,
    q: NDArray[np.float64],
    joint_target: NDArray[np.float64],
    joint_var: NDArray[np.float64],
    frames: Sequence[FrameEstimate] = (),
    *,
    alpha: float = DEFAULT_ALPHA,
    null_space_std: float | None = None,
    damping: float = DEFAULT_DAMPING,
    ridge: float = DEFAULT_RIDGE,
    ee_pos: NDArray[np.float64] | None = None,
    jacobian: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """One iteration of Algorithm 3's loop (lines 6-19) from the joint configuration ``q``.

    The task vector has ``p`` elements (line 7): by default the end-effector position (``p = 3``,
    ``robot.forward_kinematics`` / ``robot.position_jacobian``); pass ``ee_pos (p,)`` and
    ``jacobian (p, k)`` for another task vector (e.g. two points on the hand, ``p = 6``), with
    every frame's ``position (p,)`` and ``covariance (p, p)`` to match.

    Args:
        robot: kinematics (``RobotModel``).
        q: ``theta_t``, ``(k,)``.
        joint_target: ``theta_hat_{t+1}``, the joint-space GP mean at the next step, ``(k,)``.
        joint_var: its predicted variance, ``(k,)``.
        frames: one :class:`FrameEstimate` per *detected* object (footnote 2: a missing object is
            simply left out).
        alpha: weight of the null-space term (line 16).
        null_space_std: ``None`` (default): a frame's null-space information is the joint-space
            estimate's, projected; a float (rad): a fixed std instead (see the module docstring).
        damping: damping of the pseudo-inverse (m).
        ridge: added to the fused precision.
        ee_pos: ``x_t``; computed by forward kinematics when omitted.
        jacobian: ``J(theta_t)``; ``robot.position_jacobian(q)`` when omitted.

    Returns:
        ``(dtheta (k,), covariance (k, k))``: the fused increment and its covariance.
    """
    q = np.asarray(q, dtype=float)
    de = np.asarray(joint_target, dtype=float) - q  # line 15
    prec_theta = np.diag(1.0 / np.maximum(np.asarray(joint_var, dtype=float), MIN_VARIANCE))
    means = [de]
    precisions = [prec_theta]
    if frames:
        J = np.asarray(robot.position_jacobian(q) if jacobian is None else jacobian, dtype=float)
        # line 8 (p x k)
        J_pinv = damped_pseudoinverse(J, damping)  # line 10
        N = np.eye(q.shape[0]) - J_pinv @ J
        x = np.asarray(robot.forward_kinematics(q) if ee_pos is None else ee_pos, dtype=float)
        null_term = alpha * (N @ de)
        if null_space_std is None:
            null_prec = N @ prec_theta @ N
        else:
            null_prec = N / null_space_std**2
        for frame in frames:
            dx = np.asarray(frame.position, dtype=float) - x  # line 14 (o + x_hat already summed)
            means.append(J_pinv @ dx + null_term)  # line 16
            # line 17 in information form: pinv(J^+ Sigma_x J^+^T) = J^T Sigma_x^-1 J, regularised
            if frame.precision is not None:
                P = np.asarray(frame.precision, dtype=float)
                precisions.append(J.T @ P @ J + null_prec)
            else:
                cov = np.asarray(frame.covariance, dtype=float)
                cov = cov + MIN_VARIANCE * np.eye(cov.shape[0])
                precisions.append(J.T @ np.linalg.solve(cov, J) + null_prec)
    return fuse_information(means, precisions, ridge)  # line 19


def frame_estimate(
    origin: NDArray[np.float64],
    rotation: NDArray[np.float64],
    mean: NDArray[np.float64],
    var: NDArray[np.float64],
) -> FrameEstimate:
    """World-frame target of a frame: ``o + R x_hat`` with covariance ``R diag(var) R^T``."""
    R = np.asarray(rotation, dtype=float)
    return FrameEstimate(
        position=np.asarray(origin, dtype=float) + R @ np.asarray(mean, dtype=float),
        covariance=(R * np.asarray(var, dtype=float)) @ R.T,
    )


def limit_step(dq: NDArray[np.float64], max_joint_step: float) -> NDArray[np.float64]:
    """Scale ``dq`` so that ``max |dq_j| <= max_joint_step``, keeping its direction."""
    peak = float(np.max(np.abs(dq)))
    return dq * (max_joint_step / peak) if peak > max_joint_step else dq


def reproduce(
    robot: RobotModel,
    joint_mean: NDArray[np.float64],
    joint_var: NDArray[np.float64],
    frame_means: Mapping[str, NDArray[np.float64]] | None = None,
    frame_vars: Mapping[str, NDArray[np.float64]] | None = None,
    frames: Mapping[str, tuple[NDArray[np.float64], NDArray[np.float64]]] | None = None,
    *,
    q0: NDArray[np.float64] | None = None,
    alpha: float = DEFAULT_ALPHA,
    null_space_std: float | None = None,
    damping: float = DEFAULT_DAMPING,
    ridge: float = DEFAULT_RIDGE,
    clip_to_limits: bool = True,
    max_joint_step: float | None = None,
) -> Reproduction:
    """Algorithm 3 open loop over a whole time grid of ``T`` steps.

    Args:
        robot: kinematics.
        joint_mean: ``theta_hat``, ``(T, k)``.
        joint_var: ``Sigma_theta`` (diagonal), ``(T, k)``.
        frame_means: per object name, ``x_hat^(m)`` in the object's frame, ``(T, 3)``.
        frame_vars: per object name, the diagonal of ``Sigma_x^(m)`` in the object's frame,
            ``(T, 3)``.
        frames: per *detected* object name, ``(origin (3,), rotation (3, 3))``; objects with a GP
            but no entry here are skipped (footnote 2).
        q0: start configuration; ``theta_hat_0`` when omitted (line 4).
        alpha, null_space_std, damping, ridge: see :func:`reproduction_step`.
        clip_to_limits: clip each ``theta_t`` to the robot's joint limits.
        max_joint_step: if given (rad), an increment whose largest joint change exceeds it is scaled
            down as a whole (keeps its direction), as a position-controlled robot would limit it.

    Returns:
        A :class:`Reproduction`.
    """
    joint_mean = np.asarray(joint_mean, dtype=float)
    joint_var = np.asarray(joint_var, dtype=float)
    T, k = joint_mean.shape
    frame_means = dict(frame_means or {})
    frame_vars = dict(frame_vars or {})
    frames = dict(frames or {})
    names = [name for name in frame_means if name in frames]
    q = joint_mean[0].copy() if q0 is None else np.asarray(q0, dtype=float).copy()  # line 4
    lower = getattr(robot, "joint_lower", None)
    upper = getattr(robot, "joint_upper", None)
    joint_pos = np.empty((T, k))
    ee_pos = np.empty((T, 3))
    joint_std = np.empty((T, k))
    targets = {name: np.empty((T, 3)) for name in names}
    joint_pos[0] = q
    ee_pos[0] = robot.forward_kinematics(q)
    joint_std[0] = np.sqrt(joint_var[0])
    for name in names:
        o, R = frames[name]
        targets[name][0] = frame_estimate(o, R, frame_means[name][0], frame_vars[name][0]).position
    for t in range(T - 1):  # line 5
        estimates = []
        for name in names:
            o, R = frames[name]
            est = frame_estimate(o, R, frame_means[name][t + 1], frame_vars[name][t + 1])
            targets[name][t + 1] = est.position
            estimates.append(est)
        dq, cov = reproduction_step(
            robot,
            q,
            joint_mean[t + 1],
            joint_var[t + 1],
            estimates,
            alpha=alpha,
            null_space_std=null_space_std,
            damping=damping,
            ridge=ridge,
            ee_pos=ee_pos[t],
        )
        if max_joint_step is not None:
            dq = limit_step(dq, max_joint_step)
        q = q + dq  # line 19
        if clip_to_limits and lower is not None and upper is not None:
            q = np.clip(q, lower, upper)
        joint_pos[t + 1] = q
        ee_pos[t + 1] = robot.forward_kinematics(q)  # line 21
        joint_std[t + 1] = np.sqrt(np.diag(cov))
    return Reproduction(
        joint_pos=joint_pos, ee_pos=ee_pos, joint_std=joint_std, frame_targets=targets
    )
