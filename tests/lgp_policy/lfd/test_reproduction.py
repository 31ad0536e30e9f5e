"""Algorithm 3 (batched) on a small 4-joint arm defined here (no gym_coffee needed)."""

from __future__ import annotations

import numpy as np
import pytest

from lgp_policy.lfd.reproduction import (
    damped_pseudoinverse,
    frame_estimate,
    frame_targets,
    limit_step,
    reproduction_step,
)


class FourJointArm:
    """Base yaw plus three pitch joints; links 0.4, 0.3, 0.2 m. A redundant 3-D position arm."""

    links = np.array([0.4, 0.3, 0.2])

    def position(self, q):
        q = np.asarray(q, dtype=float)
        pitch = np.cumsum(q[1:])
        r = np.sum(self.links * np.cos(pitch))
        z = np.sum(self.links * np.sin(pitch))
        return np.array([r * np.cos(q[0]), r * np.sin(q[0]), z])

    def jacobian(self, q):
        eps = 1e-7
        J = np.empty((3, 4))
        for j in range(4):
            dq = np.zeros(4)
            dq[j] = eps
            J[:, j] = (self.position(q + dq) - self.position(q - dq)) / (2 * eps)
        return J


@pytest.fixture
def arm():
    return FourJointArm()


def _trajectories(T=60):
    s = np.linspace(0.0, 1.0, T)[:, None]
    q_start = np.array([0.0, 0.3, 0.5, 0.2])
    q_end = np.array([0.8, 0.1, 0.9, -0.3])
    return q_start + s * (q_end - q_start)


def _reproduce(arm, q_hat, q_var, frames=(), max_step=None):
    """Closed loop over the time grid: frames = [(origin, R, rel_mean (T, 3), var (T, 3))]."""
    q = q_hat[0].copy()
    out = [arm.position(q)]
    for t in range(len(q_hat) - 1):
        x, J = arm.position(q)[None], arm.jacobian(q)[None]
        targets = [
            frame_targets(o[None], R[None], m[t + 1][None], v[t + 1][None]) for o, R, m, v in frames
        ]
        dq, _ = reproduction_step(q[None], q_hat[t + 1][None], q_var[t + 1][None], x, J, targets)
        if max_step is not None:
            dq = limit_step(dq, max_step)
        q = q + dq[0]
        out.append(arm.position(q))
    return q, np.array(out)


def test_pseudoinverse_information_identity(arm):
    """pinv(J^+ S J^+^T) == J^T S^-1 J for a full-row-rank J (the regularised product uses it)."""
    J = arm.jacobian(np.array([0.2, 0.4, 0.6, -0.2]))
    S = np.diag([1e-4, 4e-4, 9e-4])
    Jp = damped_pseudoinverse(J, damping=0.0)
    np.testing.assert_allclose(Jp, np.linalg.pinv(J), atol=1e-10)
    np.testing.assert_allclose(
        np.linalg.pinv(Jp @ S @ Jp.T), J.T @ np.linalg.solve(S, J), rtol=1e-6
    )


def test_fused_increment_matches_covariance_form_without_frames():
    """Joint estimate only: the product is N(theta_hat - theta, Sigma_theta) itself."""
    rng = np.random.default_rng(0)
    q, q_hat, var = rng.normal(size=(3, 5, 4))
    var = var**2 + 0.1
    dq, cov = reproduction_step(q, q_hat, var, return_cov=True)
    np.testing.assert_allclose(dq, q_hat - q, rtol=1e-6)
    np.testing.assert_allclose(np.diagonal(cov, axis1=1, axis2=2), var, rtol=1e-6)


def test_batch_equals_one_at_a_time(arm):
    rng = np.random.default_rng(1)
    qs = rng.uniform(-0.5, 0.5, (6, 4)) + np.array([0.0, 0.3, 0.5, 0.2])
    q_hat = qs + rng.normal(0, 0.05, qs.shape)
    var = rng.uniform(1e-3, 1e-1, qs.shape)
    x = np.stack([arm.position(q) for q in qs])
    J = np.stack([arm.jacobian(q) for q in qs])
    tgt = (x + 0.01, np.broadcast_to(np.eye(3) * 1e4, (6, 3, 3)).copy())
    batch, cov = reproduction_step(qs, q_hat, var, x, J, [tgt], return_cov=True)
    for i in range(6):
        one, c1 = reproduction_step(
            qs[i : i + 1],
            q_hat[i : i + 1],
            var[i : i + 1],
            x[i : i + 1],
            J[i : i + 1],
            [(tgt[0][i : i + 1], tgt[1][i : i + 1])],
            return_cov=True,
        )
        np.testing.assert_allclose(batch[i], one[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(cov[i], c1[0], rtol=1e-9, atol=1e-12)


def test_no_frames_follows_joint_estimate(arm):
    q_hat = _trajectories()
    q, _ = _reproduce(arm, q_hat, np.full_like(q_hat, 1e-4))
    np.testing.assert_allclose(q, q_hat[-1], atol=1e-9)


def test_tight_frame_dominates(arm):
    """A frame with std 1 mm beats a joint estimate with std 0.3 rad, and vice versa."""
    q_hat = _trajectories()
    T = len(q_hat)
    ee_hat = np.array([arm.position(q) for q in q_hat])
    offset = np.array([0.012, -0.01, 0.008])  # the object moved: the frame asks for a shifted path
    frame = (offset, np.eye(3), ee_hat, np.full((T, 3), 1e-3**2))
    _, path = _reproduce(arm, q_hat, np.full((T, 4), 0.3**2), [frame], max_step=0.05)
    # the first steps close a 2 cm gap with limited linearised (Jacobian) steps; then it tracks
    assert np.linalg.norm(path[10:] - (ee_hat[10:] + offset), axis=1).max() < 2e-3
    loose = (offset, np.eye(3), ee_hat, np.full((T, 3), 0.3**2))
    q, _ = _reproduce(arm, q_hat, np.full((T, 4), 1e-3**2), [loose])
    np.testing.assert_allclose(q, q_hat[-1], atol=5e-3)


def test_tightest_of_two_frames_wins_and_rotation_is_used(arm):
    q_hat = _trajectories()
    T = len(q_hat)
    ee_hat = np.array([arm.position(q) for q in q_hat])
    yaw = 0.3
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    o_machine = np.array([0.02, 0.03, -0.01])
    o_cup = np.array([-0.04, 0.0, 0.02])
    world_machine = ee_hat + np.array([0.03, -0.02, 0.01])
    rel_machine = (world_machine - o_machine) @ R  # R^T (x - o), row-wise
    rel_cup = ee_hat - o_cup
    frames = [
        (o_cup, np.eye(3), rel_cup, np.full((T, 3), 0.1**2)),
        (o_machine, R, rel_machine, np.full((T, 3), 1e-3**2)),
    ]
    _, path = _reproduce(arm, q_hat, np.full((T, 4), 0.2**2), frames)
    assert np.linalg.norm(path[3:] - world_machine[3:], axis=1).max() < 2e-3


def test_null_space_term_pulls_towards_joint_estimate(arm):
    """With the task fixed by a tight frame, alpha > 0 moves redundant joints towards theta_hat."""
    q = np.array([0.1, 0.2, 0.4, 0.1])
    x = arm.position(q)
    q_hat = q + np.array([0.0, 0.3, -0.3, 0.2])
    tgt = (x[None], np.eye(3)[None] * 1e8)
    var = np.full((1, 4), 1e6)  # an uninformative joint estimate: only the null-space term can pull
    J = arm.jacobian(q)[None]
    kw = {"null_space_std": 0.01}
    d0, _ = reproduction_step(q[None], q_hat[None], var, x[None], J, [tgt], alpha=0.0, **kw)
    d1, _ = reproduction_step(q[None], q_hat[None], var, x[None], J, [tgt], alpha=0.5, **kw)
    assert np.linalg.norm(d0) < 1e-6
    assert np.linalg.norm(J[0] @ d1[0]) < 1e-4  # stays on the task
    assert np.dot(d1[0], q_hat - q) > 0  # but moves towards theta_hat in the null space


def test_frame_targets_rotate_and_stack_points():
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    est = frame_estimate(np.ones(3), R, np.array([1.0, 0.0, 0.0]), np.array([4.0, 1.0, 9.0]))
    np.testing.assert_allclose(est.position, [1.0, 2.0, 1.0])
    np.testing.assert_allclose(np.linalg.inv(est.precision), np.diag([1.0, 4.0, 9.0]), atol=1e-12)
    pos, prec = frame_targets(
        np.zeros((1, 2)), np.eye(2)[None], np.array([[1.0, 2.0, 3.0, 4.0]]), np.ones((1, 4))
    )
    np.testing.assert_allclose(pos, [[1.0, 2.0, 3.0, 4.0]])
    np.testing.assert_allclose(prec[0], np.eye(4))


def test_limit_step_keeps_direction():
    dq = np.array([[0.2, -0.1], [0.01, 0.0]])
    out = limit_step(dq, 0.05)
    np.testing.assert_allclose(out, [[0.05, -0.025], [0.01, 0.0]])
