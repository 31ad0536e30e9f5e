"""The coffee adapter's cup frame: rotated by the layout, the same online and from recordings."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import gym_coffee
from gym_coffee.env import OBS_SLICES
from lgp_policy.lfd.adapters.coffee import CoffeeAdapter, cup_rotation, to_trajectories


@pytest.fixture(scope="module")
def short_hard_demos():
    """Short hard-level recordings (a few teacher steps each), the machine on both sides."""
    env = gym.make(gym_coffee.LEVELS["hard"], max_episode_steps=4)
    try:
        demos = gym_coffee.collect_demonstrations(env, n=8, seed=0, keep_failed=True)
    finally:
        env.close()
    sides = {bool(d.object_pos["machine"][0, 1] > 0.0) for d in demos}
    assert sides == {True, False}, "seeds 0-7 should put the machine on both sides"
    return demos


def _x_axis(R):
    return np.asarray(R)[..., :, 0]


def test_recorded_cup_frame_equals_online(short_hard_demos):
    trajs = to_trajectories(short_hard_demos)
    adapter = CoffeeAdapter()
    for demo, traj in zip(short_hard_demos, trajs, strict=True):
        observed = adapter.read(np.asarray(demo.observations, dtype=float))
        p_online, R_online = observed.frames["cup"]
        p_rec, R_rec = traj.frames["cup"]
        np.testing.assert_allclose(p_rec, p_online, atol=1e-6)
        np.testing.assert_allclose(R_rec, R_online, atol=1e-6)
        # The machine frame agrees too (yaw from the recorded quaternion vs the observed angle).
        np.testing.assert_allclose(
            traj.frames["machine"][1], observed.frames["machine"][1], atol=1e-6
        )


def test_cup_frame_x_axis_is_horizontal_across_the_radial_towards_the_machine(short_hard_demos):
    for traj, demo in zip(to_trajectories(short_hard_demos), short_hard_demos, strict=True):
        R = traj.frames["cup"][1][0]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        x = _x_axis(R)
        cup = demo.object_pos["cup"][0]
        assert abs(x[2]) < 1e-12  # horizontal
        assert abs(x[:2] @ cup[:2]) < 1e-9  # across the line from the robot base to the cup
        towards_machine = demo.object_pos["machine"][0, :2] - cup[:2]
        assert x[:2] @ towards_machine > 0.0


def test_cup_frame_flips_with_the_machine_side(short_hard_demos):
    """Mirroring the layout in the robot's xz-plane mirrors the cup frame's x axis: the approach
    direction in the cup frame is the same whichever side the machine stands on."""
    obs = np.stack([np.asarray(d.observations[0], dtype=float) for d in short_hard_demos])
    mirrored = obs.copy()
    for name in ("cup_pos", "cup_init_pos", "machine_pos"):
        mirrored[:, OBS_SLICES[name].start + 1] *= -1.0
    mirrored[:, OBS_SLICES["machine_yaw"]] *= -1.0
    adapter = CoffeeAdapter()
    x = _x_axis(adapter.read(obs).frames["cup"][1])
    x_m = _x_axis(adapter.read(mirrored).frames["cup"][1])
    np.testing.assert_allclose(x_m, x * np.array([1.0, -1.0, 1.0]), atol=1e-9)
    # The machine's side decides: the same cup, the machine (and its place point) mirrored through
    # the cup, turns the frame around.
    cup = obs[:, OBS_SLICES["cup_pos"]]
    machine = obs[:, OBS_SLICES["machine_pos"]]
    yaw = obs[:, OBS_SLICES["machine_yaw"]][:, 0]
    x_here = _x_axis(cup_rotation(cup, machine, yaw))
    x_there = _x_axis(cup_rotation(cup, 2.0 * cup - machine, yaw + np.pi))
    np.testing.assert_allclose(x_there, -x_here, atol=1e-9)
