"""Algorithm 3 (batched) on a small 4-joint arm defined here, and its one-pass form against a
frame-by-frame reference (random states; the coffee Panda's task points)."""

from __future__ import annotations

import numpy as np
import pytest

from lgp_policy.lfd.reproduction import (
    MIN_VARIANCE,
    FrameStack,
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
        stack = None
        if frames:
            o, R, m, v = (
                np.stack([f[i] if i < 2 else f[i][t + 1] for f in frames]) for i in range(4)
            )
            stack = FrameStack(o[None], R[None], m[None], v[None])
        dq, _ = reproduction_step(q[None], q_hat[t + 1][None], q_var[t + 1][None], x, J, stack)
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
    tgt = FrameStack(
        (x + 0.01)[:, None],
        np.broadcast_to(np.eye(3), (6, 1, 3, 3)),
        np.zeros((6, 1, 3)),
        np.full((6, 1, 3), 1e-4),
    )
    batch, cov = reproduction_step(qs, q_hat, var, x, J, tgt, return_cov=True)
    for i in range(6):
        one, c1 = reproduction_step(
            qs[i], q_hat[i], var[i], x[i], J[i], FrameStack(*(a[i] for a in tgt)), return_cov=True
        )
        np.testing.assert_allclose(batch[i], one, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(cov[i], c1, rtol=1e-9, atol=1e-12)


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
    tgt = FrameStack(
        x[None, None], np.eye(3)[None, None], np.zeros((1, 1, 3)), np.full((1, 1, 3), 1e-8)
    )
    var = np.full((1, 4), 1e6)  # an uninformative joint estimate: only the null-space term can pull
    J = arm.jacobian(q)[None]
    kw = {"null_space_std": 0.01}
    d0, _ = reproduction_step(q[None], q_hat[None], var, x[None], J, tgt, alpha=0.0, **kw)
    d1, _ = reproduction_step(q[None], q_hat[None], var, x[None], J, tgt, alpha=0.5, **kw)
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


# ------------------------------------------------- the one-pass form against the plain one


def _reference_step(q, q_hat, var, x, J, frames, *, alpha, null_space_std, damping, ridge):
    """Algorithm 3 for one robot written as the module docstring states it, frame by frame:
    explicit damped pseudo-inverse, world targets and precisions, the Gaussian product by
    inverting the summed precision. Returns ``(dq, cov)``."""
    k = q.shape[0]
    lam = 1.0 / np.maximum(var, MIN_VARIANCE)
    de = q_hat - q
    J_pinv = J.T @ np.linalg.inv(J @ J.T + damping**2 * np.eye(J.shape[0]))
    N = np.eye(k) - J_pinv @ J
    null_prec = N @ np.diag(lam) @ N if null_space_std is None else N / null_space_std**2
    Lam = np.diag(lam) + ridge * np.eye(k)
    eta = np.diag(lam) @ de
    for origin, R, mean, fvar in zip(*frames, strict=True):
        d = origin.shape[0]
        points = mean.reshape(-1, d)
        target = np.concatenate([origin + R @ pt for pt in points])
        W = np.zeros((len(target), len(target)))
        for j, v in enumerate(np.maximum(fvar, MIN_VARIANCE).reshape(-1, d)):
            W[j * d : (j + 1) * d, j * d : (j + 1) * d] = R @ np.diag(1.0 / v) @ R.T
        mean_j = J_pinv @ (target - x) + alpha * N @ de
        P = J.T @ W @ J + null_prec
        Lam = Lam + P
        eta = eta + P @ mean_j
    cov = np.linalg.inv(0.5 * (Lam + Lam.T))
    return cov @ eta, cov


def _random_problem(rng, n, k, d, b, m):
    from scipy.spatial.transform import Rotation

    p = b * d
    q = rng.uniform(-1.0, 1.0, (n, k))
    q_hat = q + rng.normal(0.0, 0.05, (n, k))
    var = np.exp(rng.uniform(np.log(1e-6), np.log(1e-1), (n, k)))
    x = rng.normal(0.0, 0.3, (n, p))
    J = rng.normal(0.0, 0.3, (n, p, k))
    R = Rotation.random(n * m, random_state=rng).as_matrix()
    if d == 2:
        R = R[:, :2, :2] / np.linalg.norm(R[:, :2, :1], axis=1, keepdims=True)
        R[:, :, 1] = np.stack([-R[:, 1, 0], R[:, 0, 0]], axis=1)
    frames = FrameStack(
        rng.normal(0.0, 0.3, (n, m, d)),
        R.reshape(n, m, d, d),
        rng.normal(0.0, 0.1, (n, m, p)),
        np.exp(rng.uniform(np.log(1e-6), np.log(1e-1), (n, m, p))),
    )
    return q, q_hat, var, x, J, frames


@pytest.mark.parametrize(
    ("k", "d", "b", "m", "null_space_std"),
    [
        (7, 3, 2, 2, None),
        (7, 3, 2, 2, 0.3),
        (7, 3, 1, 3, None),
        (4, 3, 1, 1, None),
        (3, 2, 1, 2, 0.5),
    ],
)
def test_one_pass_step_matches_the_frame_by_frame_reference(k, d, b, m, null_space_std):
    """One robot (2-D arrays, Cholesky), a batch of one and a batch of five give the reference's
    increment and covariance to 1e-10 of their size; a 1% change of the damping is detected."""
    rng = np.random.default_rng(k * 100 + m * 10 + b)
    kw = {"alpha": 0.4, "null_space_std": null_space_std, "damping": 1e-2, "ridge": 1e-9}
    q, q_hat, var, x, J, frames = _random_problem(rng, 5, k, d, b, m)
    batch, batch_cov = reproduction_step(q, q_hat, var, x, J, frames, return_cov=True, **kw)
    batch_dq, none = reproduction_step(q, q_hat, var, x, J, frames, **kw)
    assert none is None
    for i in range(5):
        args = (q[i], q_hat[i], var[i], x[i], J[i], FrameStack(*(a[i] for a in frames)))
        ref, ref_cov = _reference_step(*args, **kw)
        tol, cov_tol = 1e-10 * np.abs(ref).max(), 1e-10 * np.abs(ref_cov).max()
        one, one_cov = reproduction_step(*args, return_cov=True, **kw)
        one_dq, _ = reproduction_step(*args, **kw)
        first, _ = reproduction_step(
            *(a[None] for a in args[:5]), FrameStack(*(a[i : i + 1] for a in frames)), **kw
        )
        for got in (one, one_dq, first[0], batch[i], batch_dq[i]):
            np.testing.assert_allclose(got, ref, rtol=0, atol=tol)
        for got in (one_cov, batch_cov[i]):
            np.testing.assert_allclose(got, ref_cov, rtol=0, atol=cov_tol)
        off, _ = reproduction_step(*args, **{**kw, "damping": 1.01e-2})
        assert np.abs(off - ref).max() > 10 * tol


def test_without_frames_each_joint_follows_its_estimate():
    rng = np.random.default_rng(5)
    q, q_hat, var, *_ = _random_problem(rng, 3, 7, 3, 2, 1)
    for args in ((q, q_hat, var), (q[0], q_hat[0], var[0])):
        dq, cov = reproduction_step(*args, return_cov=True)
        lam = 1.0 / args[2]
        np.testing.assert_allclose(dq, (args[1] - args[0]) * lam / (lam + 1e-9), rtol=1e-12)
        np.testing.assert_allclose(np.diagonal(cov, axis1=-2, axis2=-1), 1.0 / (lam + 1e-9))


def test_coffee_panda_task_points_one_pass_equal_the_batch_and_finite_differences():
    """The Panda's pose and Jacobian of one pass of the chain (one state) give the same task
    vector (grasp point and the approach point 0.1 m behind it) and Jacobian as the batched
    chain (the chain bit for bit), and the Jacobian is the task vector's derivative."""
    from lgp_policy.lfd.adapters.coffee import PandaModel
    from lgp_policy.lfd.policy import hand_points

    robot = PandaModel(base_position=(0.05, -0.1, 0.02))
    rng = np.random.default_rng(3)
    qs = rng.uniform(robot.joint_lower, robot.joint_upper, (6, 7))
    xb, Jb = hand_points(robot, qs, 0.1)
    pose = robot.pose_and_jacobian(qs)
    for i, q in enumerate(qs):
        for one, batch in zip(robot._one.pose_and_jacobian(q), pose, strict=True):
            np.testing.assert_array_equal(one, batch[i])
        x1, J1 = hand_points(robot, q, 0.1)
        np.testing.assert_allclose(x1, xb[i], rtol=0, atol=1e-14)
        np.testing.assert_allclose(J1, Jb[i], rtol=0, atol=1e-14)
        eps = 1e-6
        fd = np.stack(
            [
                (hand_points(robot, q + eps * e, 0.1)[0] - hand_points(robot, q - eps * e, 0.1)[0])
                / (2 * eps)
                for e in np.eye(7)
            ],
            axis=1,
        )
        np.testing.assert_allclose(J1, fd, atol=1e-8)


def test_one_row_limit_and_action_equal_the_batch():
    """The step limit and the joint-delta action map of one row (on floats) give the batch's
    rows bit for bit: within and beyond the limit, clipped actions, a NaN (all NaN after the
    limit, as the batch does)."""
    from lgp_policy.lfd.robots import GripperSpec, JointDeltaAction

    rng = np.random.default_rng(7)
    dq = rng.normal(0.0, 0.05, (40, 7))
    dq[3, 2] = np.nan
    dq[5] = 0.0
    gripper = rng.uniform(-0.01, 0.09, 40)
    limited = limit_step(dq, 0.05)
    action_map = JointDeltaAction(0.04, GripperSpec(closed=0.0, open=0.08))
    actions = action_map(dq, limited, gripper)
    assert np.all(np.isnan(limited[3])) and np.any(np.abs(actions) == 1.0)
    for i in range(len(dq)):
        one = limit_step(dq[i : i + 1], 0.05)
        np.testing.assert_array_equal(one, limited[i : i + 1])
        np.testing.assert_array_equal(
            action_map(dq[i : i + 1], one, gripper[i : i + 1]), actions[i : i + 1]
        )
