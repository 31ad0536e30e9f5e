"""PandaKinematics (pure numpy) against PyBullet, and the action scaling of the robot."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gym_coffee.kinematics import PandaKinematics
from gym_coffee.robot import (
    EE_LINK,
    GRIPPER_MAX_OPENING,
    MAX_JOINT_STEP,
    Panda,
    action_from_targets,
)
from gym_coffee.simulation import Simulation


@pytest.fixture(scope="module")
def panda():
    sim = Simulation()
    robot = Panda(sim)
    robot.load()
    yield robot
    sim.close()


def test_forward_kinematics_matches_pybullet(panda):
    rng = np.random.default_rng(0)
    kin = PandaKinematics()
    for _ in range(25):
        q = rng.uniform(kin.joint_lower, kin.joint_upper)
        panda.reset(q)
        pos, quat = panda.sim.get_link_pose(panda.name, EE_LINK)
        rot = Rotation.from_quat(quat).as_matrix()
        pos_np, rot_np = kin.forward_pose(q)
        np.testing.assert_allclose(kin.forward_kinematics(q), pos, atol=1e-6)
        np.testing.assert_allclose(pos_np, pos, atol=1e-6)
        np.testing.assert_allclose(rot_np, rot, atol=1e-6)


def test_jacobian_matches_pybullet_and_finite_differences(panda):
    rng = np.random.default_rng(1)
    kin = PandaKinematics()
    p = panda.sim.p
    for _ in range(10):
        q = rng.uniform(kin.joint_lower, kin.joint_upper)
        lin, ang = p.calculateJacobian(
            panda.sim.bodies[panda.name],
            EE_LINK,
            [0.0, 0.0, 0.0],
            [*q, 0.02, 0.02],
            [0.0] * 9,
            [0.0] * 9,
        )
        np.testing.assert_allclose(kin.position_jacobian(q), np.array(lin)[:, :7], atol=1e-9)
        np.testing.assert_allclose(kin.jacobian(q)[3:], np.array(ang)[:, :7], atol=1e-9)
        eps = 1e-6
        fd = np.column_stack(
            [
                (kin.forward_kinematics(q + eps * e) - kin.forward_kinematics(q - eps * e))
                / (2 * eps)
                for e in np.eye(7)
            ]
        )
        np.testing.assert_allclose(kin.position_jacobian(q), fd, atol=1e-7)


def test_robot_model_protocol_and_cache():
    kin = PandaKinematics()
    assert kin.n_joints == 7
    assert kin.joint_lower.shape == kin.joint_upper.shape == (7,)
    assert np.all(kin.joint_lower < kin.joint_upper)
    q = np.zeros(7)
    a = kin.forward_kinematics(q)
    a[:] = 99.0  # returned arrays are copies
    np.testing.assert_array_equal(
        kin.forward_kinematics(q), PandaKinematics().forward_kinematics(q)
    )
    with pytest.raises(ValueError, match="shape"):
        kin.forward_kinematics(np.zeros(6))


def test_base_position_shifts_the_grasp_point():
    q = np.array([0.0, -0.6, 0.0, -2.4, 0.0, 1.85, 0.785])
    shifted = PandaKinematics(base_position=(0.1, -0.2, 0.3))
    np.testing.assert_allclose(
        shifted.forward_kinematics(q),
        PandaKinematics().forward_kinematics(q) + np.array([0.1, -0.2, 0.3]),
    )


def test_action_from_targets_inverts_the_scaling(panda):
    rng = np.random.default_rng(2)
    q = np.array([0.0, -0.6, 0.0, -2.4, 0.0, 1.85, 0.785])
    delta = rng.uniform(-1, 1, 7) * MAX_JOINT_STEP
    action = action_from_targets(q, q + delta, 0.03)
    assert action.shape == (8,) and action.dtype == np.float32
    np.testing.assert_allclose(action[:7] * MAX_JOINT_STEP, delta, atol=1e-7)
    np.testing.assert_allclose((action[7] + 1) / 2 * GRIPPER_MAX_OPENING, 0.03, atol=1e-7)
    assert np.all(np.abs(action_from_targets(q, q + 1.0, 1.0)) <= 1.0)
    batch = action_from_targets(np.tile(q, (4, 1)), np.tile(q + delta, (4, 1)), np.full(4, 0.03))
    assert batch.shape == (4, 8)
    np.testing.assert_allclose(batch, np.tile(action, (4, 1)))


def test_pose_and_jacobian_is_one_pass_of_the_same_chain():
    """pose_and_jacobian gives exactly forward_pose and jacobian (new arrays, cache untouched)."""
    rng = np.random.default_rng(4)
    kin = PandaKinematics(base_position=(0.1, -0.2, 0.3))
    other = PandaKinematics(base_position=(0.1, -0.2, 0.3))
    q0 = np.zeros(7)
    cached = kin.jacobian(q0)
    for _ in range(10):
        q = rng.uniform(kin.joint_lower, kin.joint_upper)
        pos, rot, jac = kin.pose_and_jacobian(q)
        assert pos.shape == (3,) and rot.shape == (3, 3) and jac.shape == (6, 7)
        p2, r2 = other.forward_pose(q)
        np.testing.assert_array_equal(pos, p2)
        np.testing.assert_array_equal(rot, r2)
        np.testing.assert_array_equal(jac, other.jacobian(q))
        jac[:] = 0.0  # the caller's own arrays
    np.testing.assert_array_equal(kin.jacobian(q0), cached)
    with pytest.raises(ValueError, match="shape"):
        kin.pose_and_jacobian(np.zeros(6))


def test_forward_kinematics_alone_gives_the_bits_of_the_full_chain():
    """The position-only pass (what the env computes every step) equals the position of the full
    chain bit for bit, with and without a cached pose of the same joints."""
    rng = np.random.default_rng(5)
    kin = PandaKinematics(base_position=(0.1, -0.2, 0.3))
    for _ in range(50):
        q = rng.uniform(kin.joint_lower, kin.joint_upper)
        pos, _, _ = kin.pose_and_jacobian(q)
        np.testing.assert_array_equal(PandaKinematics((0.1, -0.2, 0.3)).forward_kinematics(q), pos)
        kin.jacobian(q)  # fills the cache for q
        np.testing.assert_array_equal(kin.forward_kinematics(q), pos)


def test_ik_step_orientation_error_has_the_bits_of_three_cross_products():
    """ik_step writes the orientation error out (for speed); its targets equal, bit for bit,
    those of the textbook form 1/2 sum_i r_i x d_i with np.cross (demonstrations stay the same)."""
    rng = np.random.default_rng(6)
    kin = PandaKinematics()

    def reference(q, position, rotation, rest, max_step):
        q_target = q.copy()
        for _ in range(2):
            pos, rot = kin.forward_pose(q_target)
            err_o = 0.5 * (
                np.cross(rot[:, 0], rotation[:, 0])
                + np.cross(rot[:, 1], rotation[:, 1])
                + np.cross(rot[:, 2], rotation[:, 2])
            )
            jac = kin.jacobian(q_target)
            jac[3:] *= 0.3
            err = np.concatenate([position - pos, 0.3 * err_o])
            jjt = jac @ jac.T + 0.03**2 * np.eye(6)
            dq = jac.T @ np.linalg.solve(jjt, err)
            pinv = jac.T @ np.linalg.solve(jjt, jac)
            dq += (np.eye(7) - pinv) @ (0.05 * (rest - q_target))
            q_target = q_target + dq
        step = np.clip(q_target - q, -max_step, max_step)
        return np.clip(q + step, kin.joint_lower, kin.joint_upper)

    for _ in range(20):
        q = rng.uniform(kin.joint_lower, kin.joint_upper)
        rest = rng.uniform(kin.joint_lower, kin.joint_upper)
        position = kin.forward_kinematics(q) + rng.normal(0.0, 0.05, 3)
        rotation = Rotation.random(random_state=rng).as_matrix()
        got = kin.ik_step(q, position, rotation, rest, max_step=0.05)
        np.testing.assert_array_equal(got, reference(q, position, rotation, rest, 0.05))
