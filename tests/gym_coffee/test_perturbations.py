"""Perturbations: what each one changes, and that each is seeded (same seed, same episode, also in
another process)."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from gym_coffee.env import CUP_PUSH_STEPS, PERTURBED_OBS, CoffeeEnv, obs_part
from gym_coffee.scene import MIN_CUP_MACHINE_DISTANCE

PERTURBATIONS = {
    "obs_noise": {"obs_noise": 0.005},
    "calibration_bias": {"calibration_bias": 0.002},
    "actuation_noise": {"actuation_noise": 0.01},
    "cup_push": {"cup_push": (0.03, 0.05)},
}
N_STEPS = CUP_PUSH_STEPS[1] + 5


def rollout(kwargs: dict, seed: int, n_steps: int = N_STEPS) -> tuple[np.ndarray, list[np.ndarray]]:
    """Observations (n_steps + 1, OBS_DIM) of a seeded rollout and the true cup positions."""
    env = CoffeeEnv(**kwargs)
    try:
        actions = np.random.default_rng(seed).uniform(-0.3, 0.3, (n_steps, 8)).astype(np.float32)
        actions[:, 7] = 1.0  # gripper open
        observations = [env.reset(seed=seed)[0]]
        cups = [env.task_points()["cup_pos"]]
        for action in actions:
            observations.append(env.step(action)[0])
            cups.append(env.task_points()["cup_pos"])
        return np.array(observations), cups
    finally:
        env.close()


def digest(kwargs: dict, seed: int) -> str:
    observations, _ = rollout(kwargs, seed)
    return hashlib.sha256(np.ascontiguousarray(observations).tobytes()).hexdigest()


def test_each_perturbation_is_seeded_and_reproducible_across_processes():
    here = {name: digest(kwargs, seed=4) for name, kwargs in PERTURBATIONS.items()}
    plain = digest({}, seed=4)
    for name, kwargs in PERTURBATIONS.items():
        assert here[name] != plain, name  # it does something
        assert digest(kwargs, seed=5) != here[name], name  # and depends on the seed
    code = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from test_perturbations import PERTURBATIONS, digest
        for name, kwargs in PERTURBATIONS.items():
            print(name, digest(kwargs, seed=4))
        """
    )
    env = {**os.environ, "PYTHONHASHSEED": "99", "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300
    )
    assert result.returncode == 0, result.stderr
    there = dict(line.split() for line in result.stdout.splitlines() if line.count(" ") == 1)
    assert there == here


def test_obs_noise_perturbs_only_the_observed_object_positions():
    plain, _ = rollout({}, seed=1)
    noisy, _ = rollout({"obs_noise": 0.005}, seed=1)
    mask = np.zeros(plain.shape[1], dtype=bool)
    for name in PERTURBED_OBS:
        part = np.arange(plain.shape[1])[obs_part(np.arange(plain.shape[1]), name)]
        mask[part] = True
    # The simulation is untouched: everything else is bit-identical.
    np.testing.assert_array_equal(noisy[:, ~mask], plain[:, ~mask])
    diff = (noisy - plain)[:, mask]
    assert 0.004 < diff.std() < 0.006 and abs(diff.mean()) < 0.001


def test_calibration_bias_is_constant_within_an_episode_and_drawn_per_episode():
    plain, _ = rollout({}, seed=2, n_steps=10)
    biased, _ = rollout({"calibration_bias": 0.002}, seed=2, n_steps=10)
    offsets = {name: obs_part(biased, name) - obs_part(plain, name) for name in PERTURBED_OBS}
    for offset in offsets.values():
        np.testing.assert_allclose(offset, np.broadcast_to(offset[0], offset.shape), atol=2e-6)
        np.testing.assert_allclose(np.linalg.norm(offset[0]), 0.002, rtol=1e-3)
    np.testing.assert_allclose(offsets["cup_pos"][0], offsets["cup_init_pos"][0], atol=2e-6)
    assert np.linalg.norm(offsets["cup_pos"][0] - offsets["machine_pos"][0]) > 1e-4
    other, _ = rollout({"calibration_bias": 0.002}, seed=3, n_steps=0)
    plain_other, _ = rollout({}, seed=3, n_steps=0)
    assert (
        np.linalg.norm(obs_part(other[0] - plain_other[0], "cup_pos") - offsets["cup_pos"][0])
        > 1e-4
    )


def test_actuation_noise_moves_the_arm_differently():
    plain, _ = rollout({}, seed=3, n_steps=20)
    noisy, _ = rollout({"actuation_noise": 0.01}, seed=3, n_steps=20)
    deviation = np.abs(obs_part(noisy, "joint_pos") - obs_part(plain, "joint_pos"))[1:]
    assert 1e-3 < deviation.mean() < 0.05


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cup_push_moves_the_standing_cup_once_during_the_approach(seed):
    observations, cups = rollout({"cup_push": (0.03, 0.05), "level": "hard"}, seed=seed)
    moves = [t for t in range(1, len(cups)) if np.linalg.norm(cups[t] - cups[t - 1]) > 0.01]
    assert len(moves) == 1 and CUP_PUSH_STEPS[0] <= moves[0] <= CUP_PUSH_STEPS[1]
    moved = cups[-1] - cups[0]
    assert 0.029 < np.linalg.norm(moved[:2]) < 0.051 and abs(moved[2]) < 1e-3
    # What the policy sees: the new position in cup_pos, the reset position in cup_init_pos.
    np.testing.assert_allclose(obs_part(observations[-1], "cup_pos"), cups[-1], atol=1e-5)
    np.testing.assert_allclose(obs_part(observations[-1], "cup_init_pos"), cups[0], atol=1e-6)
    machine = obs_part(observations[-1], "machine_pos")
    assert np.linalg.norm(cups[-1][:2] - machine[:2]) >= MIN_CUP_MACHINE_DISTANCE - 1e-6


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"obs_noise": -0.001}, "obs_noise"),
        ({"obs_noise": np.nan}, "obs_noise"),
        ({"calibration_bias": 1.0}, "calibration_bias"),
        ({"actuation_noise": "0.01"}, "actuation_noise"),
        ({"cup_push": 0.03}, "cup_push"),
        ({"cup_push": (0.05, 0.03)}, "cup_push"),
        ({"cup_push": (0.03, np.inf)}, "cup_push"),
        ({"level": "medium"}, "level"),
    ],
)
def test_bad_perturbation_arguments(kwargs, name):
    with pytest.raises(ValueError, match=rf"^{name} must"):
        CoffeeEnv(**kwargs)
