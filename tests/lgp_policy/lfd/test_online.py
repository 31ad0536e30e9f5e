"""Online adaptation on plain arrays (the 2-D example task): frame filter, jumps, held frames,
the event-driven phase, and the plain-array API's validation."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from lgp_policy.lfd.demonstrations import Trajectory, TrajectorySet
from lgp_policy.lfd.policy import GPDemonstrationPolicy, PolicyState
from lgp_policy.lfd.robots import CartesianPointRobot, GripperSpec

EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "plain_arrays_2d.py"


@pytest.fixture(scope="module")
def ex():
    spec = importlib.util.spec_from_file_location("_example_plain_arrays_2d_online", EXAMPLE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def policy(ex):
    demos = TrajectorySet([ex.record(i) for i in range(3)])
    return GPDemonstrationPolicy(adapter=ex.make_adapter(), n_steps=60, n_grid=200).fit(demos)


def _obs(ex, seed=0):
    return ex.PickPlace2D().reset(seed)


def test_noisy_frame_observations_are_averaged(policy, ex):
    rng = np.random.default_rng(0)
    obs = _obs(ex)
    true = obs[5:7].copy()
    state = None
    errors = []
    for i in range(40):
        o = obs.copy()
        o[5:7] = true + rng.normal(0.0, 0.005, 2)
        _a, state = policy.predict(o, state=state, episode_start=np.array([i == 0]))
        errors.append(np.linalg.norm(state.position["object"][0] - true))
    assert np.mean(errors[-10:]) < 0.5 * 0.005 * np.sqrt(2)  # well below one observation's error


def test_a_moved_object_is_followed_and_a_held_one_frozen(policy, ex):
    obs = _obs(ex)
    _a, state = policy.predict(obs, episode_start=np.array([True]))
    moved = obs.copy()
    moved[5:7] += [0.04, -0.03]  # pushed 5 cm
    for _ in range(3):
        _a, state = policy.predict(moved, state=state)
    np.testing.assert_allclose(state.position["object"][0], moved[5:7], atol=1e-9)
    held = moved.copy()
    held[4] = 1.0  # holding: the object moves with the hand, its frame stays where it was
    held[5:7] += [0.2, 0.2]
    for _ in range(3):
        _a, state = policy.predict(held, state=state)
    np.testing.assert_allclose(state.position["object"][0], moved[5:7], atol=1e-9)


def test_the_phase_waits_for_the_hand_before_a_gripper_event(policy, ex):
    """A hand that cannot move: the clock stops before the closing event, then gives up."""
    obs = _obs(ex)
    s_close = policy.landmarks_[0][0]
    state = None
    clocks = []
    for i in range(int(s_close * policy.duration_ / ex.DT) + 40):
        o = obs.copy()
        o[0] = i * ex.DT
        _a, state = policy.predict(o, state=state, episode_start=np.array([i == 0]))
        clocks.append(state.clock[0])
    waited = float(state.waited[0])
    assert waited == pytest.approx(policy.max_wait, abs=ex.DT + 1e-9)
    plateau = np.flatnonzero(np.diff(clocks) == 0)
    assert plateau.size >= int(policy.max_wait / ex.DT) - 1
    assert clocks[plateau[0]] / policy.duration_ <= s_close


def test_the_policy_state_follows_the_batch(policy, ex):
    obs = np.stack([_obs(ex, s) for s in range(3)])
    _a, state = policy.predict(obs, episode_start=np.ones(3, bool))
    assert isinstance(state, PolicyState) and len(state) == 3
    with pytest.raises(ValueError, match="episode_start"):
        policy.predict(obs, state=state, episode_start=np.ones(2, bool))


def test_trajectory_validation():
    t = np.arange(5) * 0.1
    x = np.zeros((5, 2))
    with pytest.raises(ValueError, match="strictly increasing"):
        Trajectory(t[::-1], x)
    with pytest.raises(ValueError, match="state"):
        Trajectory(t, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="proper rotation"):
        Trajectory(t, x, frames={"goal": (np.zeros(2), 2 * np.eye(2))})
    with pytest.raises(ValueError, match="NaN"):
        Trajectory(t, x, frames={"goal": (np.array([np.nan, 0.0]), np.eye(2))})
    a = Trajectory(t, x, frames={"goal": (np.zeros(2), np.eye(2))})
    b = Trajectory(t, x, frames={"other": (np.zeros(2), np.eye(2))})
    with pytest.raises(ValueError, match="names the frames"):
        TrajectorySet([a, b])
    with pytest.raises(ValueError, match="dim"):
        CartesianPointRobot(4)
    with pytest.raises(ValueError, match="distinct"):
        GripperSpec(1.0, 1.0)


def test_the_robot_must_match_the_demonstrations(ex):
    demos = TrajectorySet([ex.record(0)])
    from lgp_policy.lfd.adapters import ArrayAdapter

    adapter = ex.make_adapter()
    three_d = ArrayAdapter(
        ex.OBS_DIM,
        state=slice(0, 3),
        frames={"object": (slice(4, 7), None), "goal": (slice(6, 9), None)},
        robot=CartesianPointRobot(3),
        action_map=adapter.action_map,
        gripper=adapter.gripper,
        control_dt=ex.DT,
    )
    with pytest.raises(ValueError, match="2 entries, the robot"):
        GPDemonstrationPolicy(adapter=three_d, n_steps=20, n_grid=20).fit(demos)


def test_one_observation_matches_the_batch_path(policy, ex, single_matches_batch):
    """Noise, a pushed object (gate, then jump), a held object, a hand that cannot move (the
    waits) and a reset in the middle of the episode."""
    rng = np.random.default_rng(1)
    obs = _obs(ex)
    rows, starts = [], []
    for i in range(int(policy.duration_ / ex.DT) + 20):
        o = obs.copy()
        o[0] = i * ex.DT
        o[5:7] += rng.normal(0.0, 0.005, 2) + (0.05 if i > 30 else 0.0)
        if 60 < i < 70:
            o[4] = 1.0
        rows.append(o)
        starts.append(i in (0, 90))
    state = None
    for o, first in zip(rows, starts, strict=True):
        _a, state = policy.predict(o, state=state, episode_start=np.array([first]))
    single_matches_batch(policy, rows, starts)


def test_a_point_robot_keeps_one_joint_model(policy, ex):
    """Posture clusters are for a redundant arm's null space; a point robot's state trajectories
    differ by the layout itself, so even a tiny posture_distance leaves one joint model."""
    assert policy.posture_labels_ is None
    demos = TrajectorySet([ex.record(i) for i in range(3)])
    tight = GPDemonstrationPolicy(
        adapter=ex.make_adapter(), n_steps=20, n_grid=50, posture_distance=1e-6
    ).fit(demos)
    assert tight.posture_labels_ is None and tight.posture_mean_ == []
