"""Difficulty levels, the layout option and ``info["layout"]``."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import gym_coffee
from gym_coffee.env import CoffeeEnv, obs_part
from gym_coffee.scene import LEVEL_SPECS, MACHINE_YAW_NOMINAL, MIN_CUP_MACHINE_DISTANCE, Layout
from gym_coffee.teacher import ScriptedTeacher


def test_levels_are_registered_ids():
    assert gym_coffee.LEVELS == {"easy": gym_coffee.ENV_ID, "hard": "gym_coffee/CoffeeTaskHard-v0"}
    assert gym_coffee.ENV_IDS == list(gym_coffee.LEVELS.values())
    for level, env_id in gym_coffee.LEVELS.items():
        env = gym.make(env_id)
        try:
            assert env.unwrapped.level == level
        finally:
            env.close()


def test_easy_layouts_are_unchanged():
    """The easy level draws the same layouts as before the levels existed (values measured
    with the code of commit 0f9433e)."""
    before = {
        0: ([0.5019138699714327, -0.20604265724722595], [0.4561460285904292, 0.30132221084228233],
            1.7348242404715455),
        1: ([0.4818914599520411, -0.06990726073481293], [0.47162394190794504, 0.3758919557709795],
            1.472271505461477),
        2: ([0.44185794147989066, -0.20030177131717536], [0.572133861089142, 0.30735327537080775],
            1.6232088396272588),
    }  # fmt: skip
    for seed, (cup, machine, yaw) in before.items():
        layout = Layout.sample(np.random.default_rng(seed), "easy")
        np.testing.assert_array_equal(layout.cup_pos[:2], cup)
        np.testing.assert_array_equal(layout.machine_pos[:2], machine)
        assert layout.machine_yaw == yaw


def test_hard_layouts_put_the_machine_on_both_sides_within_their_regions():
    spec = LEVEL_SPECS["hard"]
    sides = []
    for seed in range(200):
        layout = Layout.sample(np.random.default_rng(seed), "hard")
        side = np.sign(layout.machine_pos[1])
        sides.append(side)
        cup, machine = layout.cup_pos, layout.machine_pos
        assert spec.cup_x[0] <= cup[0] <= spec.cup_x[1]
        assert spec.cup_y[0] <= side * cup[1] <= spec.cup_y[1]  # on the other side
        assert spec.machine_x[0] <= machine[0] <= spec.machine_x[1]
        assert spec.machine_y[0] <= side * machine[1] <= spec.machine_y[1]
        assert abs(layout.machine_yaw - side * MACHINE_YAW_NOMINAL) <= spec.yaw_range
        assert np.linalg.norm(cup[:2] - machine[:2]) >= MIN_CUP_MACHINE_DISTANCE
    assert 70 <= sides.count(1.0) <= 130  # about half on each side


def _side(env):
    return np.sign(env.unwrapped.task_points()["place_pos"][1])


@pytest.mark.parametrize("seed", [0, 2])  # machine on the robot's right (0) and left (2)
def test_teacher_solves_the_hard_level(seed):
    env = gym.make(gym_coffee.LEVELS["hard"])
    try:
        obs, info = env.reset(seed=seed)
        assert _side(env) == {0: -1, 2: 1}[seed]
        teacher = ScriptedTeacher(env, rng=[1, seed])
        for _ in range(env.spec.max_episode_steps):
            obs, _, terminated, truncated, info = env.step(teacher.act(obs))
            if terminated or truncated:
                break
        assert info["is_success"], info
    finally:
        env.close()


def test_layout_option_round_trip():
    env = CoffeeEnv(level="hard")
    try:
        obs_a, info_a = env.reset(seed=1)
        layout = info_a["layout"]
        assert set(layout) == {"cup_pos", "machine_pos", "machine_yaw"}
        obs_b, info_b = env.reset(seed=50, options={"layout": layout})
        assert info_b["layout"] == layout
        for name in ("cup_init_pos", "cup_pos", "machine_pos", "machine_yaw"):
            np.testing.assert_array_equal(obs_part(obs_a, name), obs_part(obs_b, name))
        # Every step reports it too; the same seed and layout give the same episode.
        info_c = env.step(env.action_space.sample())[-1]
        assert info_c["layout"] == layout
        # Some keys only: the others are drawn as usual.
        _, info_d = env.reset(seed=50, options={"layout": {"machine_yaw": 2.0}})
        assert info_d["layout"]["machine_yaw"] == 2.0
        _, info_f = env.reset(seed=50)
        assert info_d["layout"]["cup_pos"] == info_f["layout"]["cup_pos"]
        obs_e, _ = env.reset(seed=3, options={"layout": {"cup_pos": [0.45, -0.2]}})
        np.testing.assert_allclose(obs_part(obs_e, "cup_init_pos"), [0.45, -0.2, 0.0], atol=1e-6)
        np.testing.assert_allclose(env.task_points()["cup_pos"], [0.45, -0.2, 0.0], atol=1e-6)
    finally:
        env.close()


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"layout": {"cup": [0.5, 0.0]}}, r"unknown key\(s\) \['cup'\]"),
        ({"layout": {"cup_pos": [0.5]}}, r"\['cup_pos'\] must have shape \(2,\) or \(3,\)"),
        ({"layout": {"cup_pos": [0.5, np.nan]}}, r"\['cup_pos'\] must be finite"),
        ({"layout": {"cup_pos": [0.5, -0.2, 0.1]}}, r"\['cup_pos'\] must stand on the table"),
        ({"layout": {"machine_pos": [3.0, 0.0]}}, r"\['machine_pos'\] must be on the table"),
        ({"layout": {"machine_yaw": "north"}}, r"\['machine_yaw'\] must be a number"),
        ({"layout": {"machine_yaw": 7.0}}, r"\['machine_yaw'\] must be a finite number"),
        ({"layout": {"cup_pos": [0.5, 0.3], "machine_pos": [0.5, 0.35]}}, r"at least 0.28 m"),
        ({"layout": [0.5, 0.3]}, r"options\['layout'\] must be a dict"),
        ({"layuot": {}}, r"options must be None or a dict"),
    ],
)
def test_bad_layout_options_name_the_key(options, match):
    env = CoffeeEnv()
    try:
        with pytest.raises(ValueError, match=match):
            env.reset(seed=0, options=options)
        env.reset(seed=0)  # still usable
    finally:
        env.close()
