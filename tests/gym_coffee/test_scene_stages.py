"""Stage flags, rewards and termination of CoffeeEnv in scripted situations."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import gym_coffee
from gym_coffee.env import OBS_DIM, OBS_SLICES, REWARD_TERMS, CoffeeEnv, object_frames, obs_part
from gym_coffee.robot import GRIPPER_MAX_OPENING
from gym_coffee.scene import (
    BUTTON_MAX_TRAVEL,
    BUTTON_REST_TRAVEL,
    CUP_REGION_X,
    CUP_REGION_Y,
    MACHINE_REGION_X,
    MACHINE_REGION_Y,
    MACHINE_YAW_NOMINAL,
    MACHINE_YAW_RANGE,
    MIN_CUP_MACHINE_DISTANCE,
)
from gym_coffee.teacher import FINGERTIP_OFFSET, REST_POSTURE, ScriptedTeacher, _hand_rotation

HOLD_OPEN = np.array([0, 0, 0, 0, 0, 0, 0, 1], dtype=np.float32)


@pytest.fixture
def env():
    env = CoffeeEnv()
    yield env
    env.close()


def hold(env, n):
    for _ in range(n):
        out = env.step(HOLD_OPEN)
    return out


def drive(env, position, rotation, n_steps, opening=0.0):
    """Track a grasp-point pose for ``n_steps`` with the env's own IK (joint targets, env.step
    semantics), returning the last info."""
    from gym_coffee.robot import MAX_JOINT_STEP

    info = {}
    for _ in range(n_steps):
        q, _ = env.robot.joint_states()
        q_target = env.kinematics.ik_step(
            q, position, rotation, REST_POSTURE, max_step=MAX_JOINT_STEP
        )
        env.robot.command(q_target, opening)
        env._simulate()
        info, _ = env._evaluate()
    return info


def press_button(env, depth, direction=None, approach=0.06):
    """Press the button with the closed fingertips along ``direction`` (default: its axis) to
    ``depth`` (m) past its face."""
    points = env.task_points()
    axis = points["button_axis"]
    direction = axis if direction is None else direction
    rotation = _hand_rotation(direction, False)
    tip = points["button_pos"] - FINGERTIP_OFFSET * direction
    drive(env, tip - approach * direction, rotation, 60)
    return drive(env, tip + depth * direction, rotation, 30)


def check_reward_terms(reward, info):
    assert reward == pytest.approx(sum(info[f"reward_{name}"] for name in REWARD_TERMS), abs=1e-12)


def test_observation_layout_and_frames(env):
    obs, info = env.reset(seed=0)
    assert obs.shape == (OBS_DIM,) and obs.dtype == np.float32
    assert sum(s.stop - s.start for s in OBS_SLICES.values()) == OBS_DIM
    points = env.task_points()
    np.testing.assert_allclose(obs_part(obs, "cup_pos"), points["cup_pos"], atol=1e-6)
    np.testing.assert_allclose(obs_part(obs, "cup_init_pos"), points["cup_pos"], atol=1e-6)
    assert obs_part(np.stack([obs, obs]), "joint_pos").shape == (2, 7)
    frames = object_frames(obs)
    _, rot = frames["machine"]
    np.testing.assert_allclose(rot[:, 0], points["button_axis"], atol=1e-6)
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-6)
    assert set(info) >= {"is_success", *gym_coffee.STAGES, "stage", "layout"}
    assert obs_part(obs, "gripper")[0] == pytest.approx(GRIPPER_MAX_OPENING, abs=1e-6)
    np.testing.assert_allclose(obs_part(obs, "ee_pos"), env.robot.ee_position(), atol=1e-5)


def test_layouts_stay_in_their_regions(env):
    for seed in range(30):
        obs, _ = env.reset(seed=seed)
        cup = obs_part(obs, "cup_init_pos")
        machine = obs_part(obs, "machine_pos")
        yaw = obs_part(obs, "machine_yaw")[0]
        assert CUP_REGION_X[0] <= cup[0] <= CUP_REGION_X[1]
        assert CUP_REGION_Y[0] <= cup[1] <= CUP_REGION_Y[1]
        assert MACHINE_REGION_X[0] <= machine[0] <= MACHINE_REGION_X[1]
        assert MACHINE_REGION_Y[0] <= machine[1] <= MACHINE_REGION_Y[1]
        assert abs(yaw - MACHINE_YAW_NOMINAL) <= MACHINE_YAW_RANGE + 1e-6
        assert np.linalg.norm(cup[:2] - machine[:2]) >= MIN_CUP_MACHINE_DISTANCE


@pytest.mark.parametrize("reward_type", ["dense", "sparse"])
def test_reward_is_the_sum_of_its_terms(reward_type):
    env = CoffeeEnv(reward_type=reward_type)
    env.reset(seed=4)
    rng = np.random.default_rng(0)
    for _ in range(30):
        _, reward, _, _, info = env.step(rng.uniform(-1, 1, 8).astype(np.float32))
        check_reward_terms(reward, info)
    env.close()


def test_lifted_cup_is_grasped_and_not_placed():
    env = gym.make(gym_coffee.ENV_ID)
    teacher = ScriptedTeacher(env, rng=0)
    obs, info = env.reset(seed=5)
    assert not info["cup_grasped"]
    grasped_at = None
    for k in range(200):
        obs, reward, _, _, info = env.step(teacher.act(obs))
        check_reward_terms(reward, info)
        if info["cup_grasped"]:
            grasped_at = k
            break
    assert grasped_at is not None
    assert obs_part(obs, "cup_pos")[2] > 0.002  # off the table
    assert not info["cup_placed"] and not info["is_success"] and info["stage"] == 1
    env.close()


def test_cup_in_the_air_without_fingers_is_not_grasped(env):
    env.reset(seed=6)
    cup = env.task_points()["cup_pos"]
    env.sim.set_base_pose("cup", cup + np.array([0, 0, 0.1]), (0, 0, 0, 1))
    _, _, _, _, info = env.step(HOLD_OPEN)
    assert not info["cup_grasped"]


def test_cup_on_the_tray_counts_only_under_the_spout(env):
    env.reset(seed=7)
    points = env.task_points()
    # Dropped beside the machine, on the table: not placed.
    axis = points["button_axis"]
    beside = points["place_pos"] - 0.2 * axis
    beside[2] = 0.0
    env.sim.set_base_pose("cup", beside, (0, 0, 0, 1))
    _, _, terminated, _, info = hold(env, 10)
    assert not info["cup_placed"] and not terminated
    # On the tray but off the spout axis by more than the tolerance: not placed.
    side = np.cross([0, 0, 1], axis)
    env.sim.set_base_pose("cup", points["place_pos"] + 0.04 * side, (0, 0, 0, 1))
    _, _, _, _, info = hold(env, 10)
    assert not info["cup_placed"]
    # Under the spout: placed, but never grasped, so no stage and no success.
    env.sim.set_base_pose("cup", points["place_pos"] + [0, 0, 0.001], (0, 0, 0, 1))
    _, _, _, _, info = hold(env, 10)
    assert info["cup_placed"] and not info["cup_grasped"]
    assert info["stage"] == 0 and not info["is_success"]


def test_button_pressed_without_the_cup_is_not_success():
    env = gym.make(gym_coffee.ENV_ID)
    teacher = ScriptedTeacher(env, rng=1)
    obs, _ = env.reset(seed=8)
    action = teacher.act(obs)  # plans for the cup where it stands now
    # Move the cup out of the way: the teacher grasps air, "places" nothing and presses the button.
    env.unwrapped.sim.set_base_pose("cup", [-0.2, -0.4, 0.0], (0, 0, 0, 1))
    pressed = False
    for _ in range(env.spec.max_episode_steps):
        obs, reward, terminated, truncated, info = env.step(action)
        action = teacher.act(obs)
        check_reward_terms(reward, info)
        pressed |= info["button_pressed"]
        if terminated or truncated:
            break
    assert pressed and info["button_pressed"]
    assert not info["cup_grasped"] and not info["cup_placed"] and not info["is_success"]
    env.close()


def test_button_springs_back_and_latches(env):
    env.reset(seed=9)
    info = press_button(env, depth=0.007)
    assert info["button_pressed"] and not info["is_success"]
    obs, _, _, _, info = hold(env, 5)
    assert obs_part(obs, "button_travel")[0] < 0.002  # the spring pushed it back
    assert info["button_pressed"]  # latched


@pytest.mark.parametrize(
    ("position", "quat"),
    [
        ([0.5, -0.15, 0.03], (0.0, np.sqrt(0.5), 0.0, np.sqrt(0.5))),  # lying on its side
        ([0.5, -0.75, 0.3], (0.0, 0.0, 0.0, 1.0)),  # beyond the table's edge
    ],
)
def test_failures_terminate_with_a_penalty(env, position, quat):
    env.reset(seed=10)
    env.sim.set_base_pose("cup", position, quat)
    _, reward, terminated, truncated, info = env.step(HOLD_OPEN)
    assert terminated and not truncated and not info["is_success"]
    assert info["reward_failure"] < 0
    check_reward_terms(reward, info)


def test_rgb_array_render():
    env = CoffeeEnv(render_mode="rgb_array", width=160, height=120)
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    assert frame.std() > 10  # not a blank image
    env.close()
    env.close()  # idempotent


def test_sideways_swipe_across_the_button_is_not_a_press(env):
    """The fingertips swept across the button 4 mm past its face push it in by ~7 mm, but not
    along its axis: not pressed."""
    env.reset(seed=0)
    points = env.task_points()
    axis, button = points["button_axis"], points["button_pos"]
    side = np.cross([0.0, 0.0, 1.0], axis)
    rotation = _hand_rotation(axis, False)
    start = button + 0.004 * axis - 0.04 * side - FINGERTIP_OFFSET * axis
    drive(env, start - 0.06 * axis, rotation, 60)
    drive(env, start, rotation, 40)
    most = 0.0
    for k in range(30):
        info = drive(env, start + (k + 1) / 30 * 0.08 * side, rotation, 1)
        most = max(most, env.scene.button_travel())
    assert most > 0.005  # the button did go in past the threshold
    assert not info["button_pressed"]
    # The same button pressed along its axis counts.
    info = press_button(env, depth=0.007)
    assert info["button_pressed"]


@pytest.mark.parametrize("depth", [0.007, 0.03])
def test_button_stops_hard_at_8_mm(env, depth):
    env.reset(seed=1)
    points = env.task_points()
    axis = points["button_axis"]
    rotation = _hand_rotation(axis, False)
    tip = points["button_pos"] - FINGERTIP_OFFSET * axis
    drive(env, tip - 0.06 * axis, rotation, 60)
    travels = []
    for _ in range(30):  # a push far past the stop, at full speed
        info = drive(env, tip + depth * axis, rotation, 1)
        travels.append(env.scene.button_travel())
    assert max(travels) <= BUTTON_MAX_TRAVEL + 1e-9
    assert info["button_pressed"]
    if depth > BUTTON_MAX_TRAVEL:
        assert max(travels) > 0.0075  # it went to the stop


def test_cup_still_moving_or_tilted_on_the_tray_is_not_placed(env):
    env.reset(seed=7)
    place = env.task_points()["place_pos"]
    env.sim.set_base_pose("cup", place + np.array([0, 0, 0.001]), (0, 0, 0, 1))
    _, _, _, _, info = hold(env, 10)
    assert info["cup_placed"]
    # Sliding at 5 cm/s: not at rest.
    cup = env.sim.bodies["cup"]
    env.sim.p.resetBaseVelocity(cup, [0.05, 0.0, 0.0], [0.0, 0.0, 0.0])
    assert not env._evaluate()[0]["cup_placed"]
    # Wobbling (angular velocity only, standing where it should).
    env.sim.set_base_pose("cup", place + np.array([0, 0, 0.001]), (0, 0, 0, 1))
    env.sim.p.resetBaseVelocity(cup, [0.0, 0.0, 0.0], [0.5, 0.0, 0.0])
    assert not env._evaluate()[0]["cup_placed"]
    # Tilted by 7 degrees, at rest.
    half = np.deg2rad(7.0) / 2
    tilted = (np.sin(half), 0.0, 0.0, np.cos(half))
    env.sim.set_base_pose("cup", place + np.array([0, 0, 0.004]), tilted)
    assert not env._evaluate()[0]["cup_placed"]


def test_button_past_its_stop_is_set_back_and_its_spring_returns_it(env):
    """The stop (enforced after every physics step) and the spring (set once per reset) hold in
    every episode, also after a reset that reused the world."""
    for seed in (0, 1):
        env.reset(seed=seed)
        env.sim.p.resetJointState(env.sim.bodies["machine"], 0, BUTTON_MAX_TRAVEL + 0.002, 0.0)
        hold(env, 1)
        travels = [env.scene.button_travel()]
        assert travels[0] <= BUTTON_MAX_TRAVEL
        for _ in range(12):
            hold(env, 1)
            travels.append(env.scene.button_travel())
        assert travels[-1] < BUTTON_REST_TRAVEL  # pushed back out by the spring
        assert max(travels[1:]) <= travels[0]
