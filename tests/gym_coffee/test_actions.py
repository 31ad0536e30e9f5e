"""Action modes (joint, end-effector, end-effector with rotation), action checks and constructor
argument checks of CoffeeEnv."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import gym_coffee
from gym_coffee.env import CoffeeEnv, obs_part
from gym_coffee.robot import ACTION_TYPES, MAX_EE_ROT_STEP, MAX_EE_STEP

EE_TYPES = ["ee", "ee_rot"]


@pytest.mark.parametrize("action_type", EE_TYPES)
def test_end_effector_modes_pass_both_checkers_without_warnings(action_type):
    from gymnasium.utils.env_checker import check_env

    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = gym.make(gym_coffee.ENV_ID, render_mode="rgb_array", action_type=action_type)
        try:
            assert env.action_space.shape == (ACTION_TYPES[action_type],)
            check_env(env.unwrapped)
            sb3_checker.check_env(env, warn=True, skip_render_check=False)
        finally:
            env.close()


@pytest.mark.parametrize("action_type", EE_TYPES)
def test_cartesian_action_moves_the_grasp_point_along_the_command(action_type):
    env = CoffeeEnv(action_type=action_type)
    try:
        obs, _ = env.reset(seed=0)
        for direction in ([0.5, 0.0, 0.0], [0.0, 0.0, -0.5], [0.0, 0.5, 0.0]):
            action = np.zeros(ACTION_TYPES[action_type], dtype=np.float32)
            action[:3], action[-1] = direction, 1.0
            start = obs_part(obs, "ee_pos").copy()
            for _ in range(8):
                obs = env.step(action)[0]
            moved = obs_part(obs, "ee_pos") - start
            commanded = 8 * MAX_EE_STEP * np.array(direction)
            # Along the command (the last step is still being tracked), hardly across it.
            assert 0.7 < moved @ commanded / (commanded @ commanded) < 1.1, moved
            across = moved - (moved @ commanded) / (commanded @ commanded) * commanded
            assert np.linalg.norm(across) < 0.1 * np.linalg.norm(commanded), moved
    finally:
        env.close()


def test_ee_keeps_the_hand_orientation_and_ee_rot_turns_it():
    for action_type, turn in [("ee", None), ("ee_rot", 5)]:
        env = CoffeeEnv(action_type=action_type)
        try:
            obs, _ = env.reset(seed=1)
            kin = env.kinematics
            start = kin.forward_pose(obs_part(obs, "joint_pos"))[1]
            action = np.zeros(ACTION_TYPES[action_type], dtype=np.float32)
            action[0], action[-1] = 0.3, 1.0
            if turn is not None:
                action[turn] = 1.0  # yaw about the world z axis
            for _ in range(10):
                obs = env.step(action)[0]
            end = kin.forward_pose(obs_part(obs, "joint_pos"))[1]
            rotvec = Rotation.from_matrix(end @ start.T).as_rotvec()
            if turn is None:
                assert np.linalg.norm(rotvec) < 0.02
            else:
                np.testing.assert_allclose(rotvec, [0, 0, 10 * MAX_EE_ROT_STEP], atol=0.03)
        finally:
            env.close()


BAD_ACTIONS = ["nan", "inf", "-inf", "one more", "one less", "2-d", "scalar", "text"]


def _bad_action(kind: str, n: int) -> object:
    if kind in ("nan", "inf", "-inf"):
        action = np.zeros(n, dtype=np.float32)
        action[1] = float(kind)
        return action
    return {
        "one more": np.zeros(n + 1),
        "one less": np.zeros(n - 1),
        "2-d": np.zeros((1, n)),
        "scalar": 0.5,
        "text": "forward",
    }[kind]


@pytest.mark.parametrize("action_type", list(ACTION_TYPES))
def test_bad_actions_raise_one_clear_error(action_type):
    n = ACTION_TYPES[action_type]
    env = CoffeeEnv(action_type=action_type)
    try:
        obs, _ = env.reset(seed=0)
        for kind in BAD_ACTIONS:
            with pytest.raises(ValueError, match=rf"^action .*(\({n},\)|finite)") as error:
                env.step(_bad_action(kind, n))
            assert action_type in str(error.value), error.value
        # Nothing happened: the episode goes on from where it was.
        after = env.step(np.zeros(n, dtype=np.float32))[0]
        assert np.isfinite(after).all() and after[0] == pytest.approx(obs[0] + env.sim.dt)
    finally:
        env.close()


def test_finite_actions_out_of_range_are_clipped():
    rng = np.random.default_rng(0)
    actions = rng.uniform(-3, 3, (10, 8))
    runs = []
    for scale in (None, "clip"):
        env = CoffeeEnv()
        try:
            obs = [env.reset(seed=2)[0]]
            for a in actions:
                obs.append(env.step(a if scale is None else np.clip(a, -1, 1))[0])
        finally:
            env.close()
        runs.append(np.array(obs))
    np.testing.assert_array_equal(runs[0], runs[1])


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"render_mode": "rgb_array", "width": -5}, "width"),
        ({"render_mode": "rgb_array", "width": 0}, "width"),
        ({"render_mode": "rgb_array", "height": 10**6}, "height"),
        ({"render_mode": "rgb_array", "width": 320.5}, "width"),
        ({"render_mode": "rgb_array", "width": "320"}, "width"),
        ({"render_mode": "rgb_array", "height": True}, "height"),
        ({"render_mode": "rgb"}, "render_mode"),
        ({"reward_type": "shaped"}, "reward_type"),
        ({"render_shadows": "no"}, "render_shadows"),
        ({"exact_reset": 1}, "exact_reset"),
        ({"action_type": "cartesian"}, "action_type"),
        ({"action_type": None}, "action_type"),
        ({"physics": "slow"}, "physics"),
    ],
)
@pytest.mark.filterwarnings("ignore:.*render_mode:UserWarning")
def test_bad_constructor_arguments_raise_before_any_work(kwargs, name):
    with pytest.raises(ValueError, match=rf"^{name} must"):
        CoffeeEnv(**kwargs)
    with pytest.raises(ValueError, match=rf"^{name} must"):
        gym.make(gym_coffee.ENV_ID, **kwargs)


def test_fast_physics_preset_keeps_the_control_period():
    """``physics="fast"``: 5 physics steps of 8 ms with 20 solver iterations (the same 40 ms per
    step); the default env is unchanged."""
    from gym_coffee.env import CONTROL_DT

    fast, default = CoffeeEnv(physics="fast"), CoffeeEnv()
    try:
        assert (fast.sim.n_substeps, fast.sim.solver_iterations) == (5, 20)
        assert (default.sim.n_substeps, default.sim.solver_iterations) == (10, 50)
        assert fast.sim.dt == pytest.approx(CONTROL_DT) and default.sim.dt == CONTROL_DT
        obs = []
        for env in (fast, default):
            env.reset(seed=0)
            obs.append(env.step(np.zeros(8, dtype=np.float32))[0])
        assert not np.array_equal(obs[0], obs[1])  # other physics, other trajectories
    finally:
        fast.close()
        default.close()


def test_solver_residual_reaches_the_solver():
    """``Simulation.solver_residual`` is PyBullet's early stop of the constraint solver: set
    (``set_physics``) before a reset, a coarse one (1e-2) gives other joint positions within a
    few control steps than the preset's, and the preset's value again gives the preset's episode
    bit for bit."""
    env = CoffeeEnv()
    preset = gym_coffee.PHYSICS_PRESETS["default"][3]
    action = np.array([1, -1, 1, 0, 0, 0, 0, 1], dtype=np.float32)
    try:
        assert env.sim.solver_residual == preset
        runs = []
        for residual in (preset, 1e-2, preset):
            env.sim.set_physics(solver_residual=residual)
            env.reset(seed=5)
            runs.append(np.stack([env.step(action)[0] for _ in range(5)]))
        np.testing.assert_array_equal(runs[0], runs[2])
        assert np.abs(runs[1] - runs[0]).max() > 1e-6
    finally:
        env.close()


def test_joint_response_per_control_step_does_not_depend_on_the_physics_step():
    """The position controller's gain is set per 4 ms of simulated time, so 5 physics steps of
    8 ms move the joints about as far per control step as 10 of 4 ms (0.015 rad apart after a
    0.05 rad step on every joint; 0.053 with PyBullet's gain per physics step unconverted)."""
    moved = []
    for physics in ("default", "fast"):
        env = CoffeeEnv(physics=physics)
        try:
            q0 = obs_part(env.reset(seed=3)[0], "joint_pos")
            step = np.array([1, -1, 1, -1, 1, -1, 1, 1], dtype=np.float32)
            hold = np.array([0, 0, 0, 0, 0, 0, 0, 1], dtype=np.float32)
            path = [obs_part(env.step(a)[0], "joint_pos") - q0 for a in (step, step, hold, hold)]
            moved.append(np.array(path))
        finally:
            env.close()
    assert np.abs(moved[0][1]).max() > 0.09  # the joints did move two steps of 0.05 rad
    assert np.abs(moved[0] - moved[1]).max() < 0.025


def test_small_and_odd_render_sizes_work():
    env = CoffeeEnv(render_mode="rgb_array", width=1, height=3)
    try:
        env.reset(seed=0)
        assert env.render().shape == (3, 1, 3)
    finally:
        env.close()
