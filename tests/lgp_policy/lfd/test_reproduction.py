"""Algorithm 3 on a small 4-joint arm defined here (no gym_coffee needed)."""

from __future__ import annotations

import numpy as np
import pytest

from lgp_policy.lfd.reproduction import (
    FrameEstimate,
    damped_pseudoinverse,
    frame_estimate,
    fuse_information,
    reproduce,
    reproduction_step,
)


class FourJointArm:
    """Base yaw plus three pitch joints; links 0.4, 0.3, 0.2 m. A redundant 3-D position arm."""

    n_joints = 4
    joint_lower = np.full(4, -np.pi)
    joint_upper = np.full(4, np.pi)
    links = np.array([0.4, 0.3, 0.2])

    def forward_kinematics(self, q):
        q = np.asarray(q, dtype=float)
        pitch = np.cumsum(q[1:])
        r = np.sum(self.links * np.cos(pitch))
        z = np.sum(self.links * np.sin(pitch))
        return np.array([r * np.cos(q[0]), r * np.sin(q[0]), z])

    def position_jacobian(self, q):
        q = np.asarray(q, dtype=float)
        eps = 1e-7
        J = np.empty((3, 4))
        for j in range(4):
            dq = np.zeros(4)
            dq[j] = eps
            J[:, j] = (self.forward_kinematics(q + dq) - self.forward_kinematics(q - dq)) / (
                2 * eps
            )
        return J


@pytest.fixture
def arm():
    return FourJointArm()


def _trajectories(T=60):
    s = np.linspace(0.0, 1.0, T)[:, None]
    q_start = np.array([0.0, 0.3, 0.5, 0.2])
    q_end = np.array([0.8, 0.1, 0.9, -0.3])
    return q_start + s * (q_end - q_start)


def test_pseudoinverse_information_identity(arm):
    """pinv(J^+ S J^+^T) == J^T S^-1 J for a full-row-rank J (the regularised product uses it)."""
    J = arm.position_jacobian(np.array([0.2, 0.4, 0.6, -0.2]))
    S = np.diag([1e-4, 4e-4, 9e-4])
    Jp = damped_pseudoinverse(J, damping=0.0)
    np.testing.assert_allclose(Jp, np.linalg.pinv(J), atol=1e-10)
    np.testing.assert_allclose(
        np.linalg.pinv(Jp @ S @ Jp.T), J.T @ np.linalg.solve(S, J), rtol=1e-6
    )


def test_fuse_information_matches_covariance_form():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3))
    B = rng.normal(size=(3, 3))
    Sa, Sb = A @ A.T + np.eye(3), B @ B.T + np.eye(3)
    ma, mb = rng.normal(size=3), rng.normal(size=3)
    mean, cov = fuse_information([ma, mb], [np.linalg.inv(Sa), np.linalg.inv(Sb)], ridge=0.0)
    expected_cov = np.linalg.inv(np.linalg.inv(Sa) + np.linalg.inv(Sb))
    np.testing.assert_allclose(cov, expected_cov, rtol=1e-10)
    np.testing.assert_allclose(
        mean, expected_cov @ (np.linalg.solve(Sa, ma) + np.linalg.solve(Sb, mb)), rtol=1e-10
    )


def test_no_frames_follows_joint_estimate(arm):
    q_hat = _trajectories()
    rep = reproduce(arm, q_hat, np.full_like(q_hat, 1e-4))
    np.testing.assert_allclose(rep.joint_pos, q_hat, atol=1e-9)


def test_tight_frame_dominates(arm):
    """A frame with std 1 mm beats a joint estimate with std 0.3 rad, and vice versa."""
    q_hat = _trajectories()
    T = len(q_hat)
    ee_hat = np.array([arm.forward_kinematics(q) for q in q_hat])
    offset = np.array([0.012, -0.01, 0.008])  # the object moved: the frame asks for a shifted path
    origin, rotation = offset, np.eye(3)
    frame_mean = ee_hat  # relative to the object: the same path, so the world target is shifted
    tight = reproduce(
        arm,
        q_hat,
        np.full((T, 4), 0.3**2),
        {"cup": frame_mean},
        {"cup": np.full((T, 3), 1e-3**2)},
        {"cup": (origin, rotation)},
        max_joint_step=0.05,
    )
    # the first steps close a 2 cm gap with limited linearised (Jacobian) steps; then it tracks
    err_tight = np.linalg.norm(tight.ee_pos[10:] - (ee_hat[10:] + offset), axis=1)
    assert err_tight.max() < 2e-3
    loose = reproduce(
        arm,
        q_hat,
        np.full((T, 4), 1e-3**2),
        {"cup": frame_mean},
        {"cup": np.full((T, 3), 0.3**2)},
        {"cup": (origin, rotation)},
    )
    np.testing.assert_allclose(loose.joint_pos, q_hat, atol=5e-3)


def test_tightest_of_two_frames_wins_and_rotation_is_used(arm):
    q_hat = _trajectories()
    T = len(q_hat)
    ee_hat = np.array([arm.forward_kinematics(q) for q in q_hat])
    yaw = 0.3
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    o_machine = np.array([0.02, 0.03, -0.01])
    o_cup = np.array([-0.04, 0.0, 0.02])
    # relative paths chosen so that both frames reproduce their own world path
    world_machine = ee_hat + np.array([0.03, -0.02, 0.01])
    rel_machine = (world_machine - o_machine) @ R  # R^T (x - o), row-wise
    rel_cup = ee_hat - o_cup
    var_tight = np.full((T, 3), 1e-3**2)
    var_loose = np.full((T, 3), 0.1**2)
    rep = reproduce(
        arm,
        q_hat,
        np.full((T, 4), 0.2**2),
        {"cup": rel_cup, "machine": rel_machine},
        {"cup": var_loose, "machine": var_tight},
        {"cup": (o_cup, np.eye(3)), "machine": (o_machine, R)},
    )
    assert np.linalg.norm(rep.ee_pos[3:] - world_machine[3:], axis=1).max() < 2e-3
    np.testing.assert_allclose(rep.frame_targets["machine"], world_machine, atol=1e-12)


def test_undetected_object_drops_out(arm):
    q_hat = _trajectories()
    T = len(q_hat)
    ee_hat = np.array([arm.forward_kinematics(q) for q in q_hat])
    var = np.full((T, 3), 1e-6)
    without = reproduce(arm, q_hat, np.full((T, 4), 0.01), {"cup": ee_hat + 0.05}, {"cup": var}, {})
    plain = reproduce(arm, q_hat, np.full((T, 4), 0.01))
    np.testing.assert_allclose(without.joint_pos, plain.joint_pos)
    assert without.frame_targets == {}


def test_null_space_term_pulls_towards_joint_estimate(arm):
    """With the task fixed by a tight frame, alpha > 0 moves redundant joints towards theta_hat."""
    q = np.array([0.1, 0.2, 0.4, 0.1])
    target = arm.forward_kinematics(q)
    q_hat = q + np.array([0.0, 0.3, -0.3, 0.2])
    frame = FrameEstimate(position=target, covariance=np.eye(3) * 1e-8)
    var = np.full(4, 1e6)  # an uninformative joint estimate: only the null-space term can pull
    d0, _ = reproduction_step(arm, q, q_hat, var, [frame], alpha=0.0, null_space_std=0.01)
    d1, _ = reproduction_step(arm, q, q_hat, var, [frame], alpha=0.5, null_space_std=0.01)
    assert np.linalg.norm(d0) < 1e-6
    J = arm.position_jacobian(q)
    assert np.linalg.norm(J @ d1) < 1e-4  # stays on the task
    assert np.dot(d1, q_hat - q) > 0  # but moves towards theta_hat in the null space


def test_frame_estimate_rotates_covariance():
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    est = frame_estimate(np.ones(3), R, np.array([1.0, 0.0, 0.0]), np.array([4.0, 1.0, 9.0]))
    np.testing.assert_allclose(est.position, [1.0, 2.0, 1.0])
    np.testing.assert_allclose(est.covariance, np.diag([1.0, 4.0, 9.0]), atol=1e-12)
