"""Evaluation: Wilson intervals, held-out seeds, the one episode loop, and results that are
bit-identical however the episodes are split (serial, process pool, chunk sizes, first layout
rolled out here with rendering)."""

from __future__ import annotations

import functools

import gymnasium as gym
import numpy as np
import pytest

import gym_coffee
from lgp_policy.app.backends import EnvFactory, chunk_seeds
from lgp_policy.app.evaluation import (
    EVAL_FLAGS,
    EVAL_SEED_OFFSET,
    evaluate_policy_stages,
    format_results,
    wilson_interval,
)
from lgp_policy.rollout import run_episode

SHORT = {"max_episode_steps": 20, "width": 64, "height": 48}


def test_wilson_interval_equals_scipy_binomtest():
    """The closed form gives scipy.stats.binomtest's Wilson interval to the last bit."""
    from scipy.stats import binomtest

    for confidence in (0.95, 0.9, 0.99):
        for n in (1, 2, 7, 50, 173):
            for k in range(n + 1):
                ci = binomtest(k, n).proportion_ci(confidence, method="wilson")
                assert wilson_interval(k, n, confidence) == (float(ci.low), float(ci.high))
    with pytest.raises(ValueError, match="confidence"):
        wilson_interval(3, 10, 1.0)


def test_wilson_interval_known_values():
    lo, hi = wilson_interval(5, 10)
    assert lo == pytest.approx(0.2366, abs=1e-4) and hi == pytest.approx(0.7634, abs=1e-4)
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = wilson_interval(50, 50)
    assert hi == 1.0 and lo == pytest.approx(0.9287, abs=1e-4)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError):
        wilson_interval(11, 10)


class ScriptedPolicy:
    """Moves joint 1 and opens/closes the gripper with time: deterministic, batch-aware."""

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        obs = np.atleast_2d(observation)
        t = obs[:, 0]
        a = np.zeros((len(obs), 8), dtype=np.float32)
        a[:, 0] = 0.5 * np.sin(3 * t)
        a[:, 1] = 0.3 * np.cos(2 * t)
        a[:, 7] = np.where(t < 0.5, 1.0, -1.0)
        return (a if np.ndim(observation) == 2 else a[0]), state


class BatchOnlyPolicy(ScriptedPolicy):
    """Answers every observation with a batch of one (some SB3 wrappers do)."""

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        a, state = super().predict(np.atleast_2d(observation), state, episode_start)
        return a, state


class MemoryPolicy(ScriptedPolicy):
    """A policy with memory updated in place (like the GP policy's frame filter): its action
    depends on the steps since ``episode_start``; the big array goes through Ray's object store
    zero-copy (read-only)."""

    def __init__(self):
        self.memory = np.zeros(200_000)

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        if episode_start is not None and np.any(episode_start):
            self.memory[:] = 0.0
        self.memory[:2] += 1.0
        a, _ = super().predict(observation, state, episode_start)
        a = np.array(a)
        a[..., 2] = 0.05 * np.sin(self.memory[0])
        return a, state


def test_run_episode_records_what_happened():
    env = gym.make(gym_coffee.ENV_ID, **SHORT)
    try:
        rewards = []
        ep = run_episode(
            ScriptedPolicy(),
            env,
            11,
            flags=EVAL_FLAGS,
            keep_observations=True,
            on_step=lambda obs, a, r, info: rewards.append(r),
        )
        again = run_episode(BatchOnlyPolicy(), env, 11, flags=EVAL_FLAGS)
    finally:
        env.close()
    assert ep.seed == 11 and ep.length == 20 and not ep.terminated
    assert ep.total_reward == pytest.approx(sum(rewards))
    assert ep.observations is not None and ep.observations.shape[0] == ep.length + 1
    assert set(ep.reached) == set(gym_coffee.STAGES) | {"is_success"}  # what the env reports
    assert ep.record(EVAL_FLAGS) == again.record(EVAL_FLAGS)  # same episode from the same seed
    with pytest.raises(ValueError, match="render_every"):
        run_episode(ScriptedPolicy(), env, 0, render_every=0)


def test_results_identical_however_the_episodes_are_split(tmp_path):
    kw = {"env_kwargs": SHORT, "progress": False}
    n = 4
    serial = evaluate_policy_stages(ScriptedPolicy(), n, seed=7, workers=1, **kw)
    assert serial["seeds"] == [EVAL_SEED_OFFSET + 7 + i for i in range(n)]
    assert [e["seed"] for e in serial["episodes"]] == serial["seeds"]
    returns = {e["return"] for e in serial["episodes"]}
    assert len(returns) == n  # different layouts, different episodes: the comparison can fail
    splits = [
        {"workers": 2, "chunk_size": 1},
        {"workers": 2, "chunk_size": 3},
        # the first layout here, rendered, with a video; the others in the pool
        {"workers": 2, "video": tmp_path / "first.gif", "keep_first": True},
    ]
    for split in splits:
        other = evaluate_policy_stages(ScriptedPolicy(), n, seed=7, **kw, **split)
        assert other["episodes"] == serial["episodes"], split
        assert other["stages"] == serial["stages"]
    # a policy with memory (reset by episode_start) gives its own episodes, in any split too
    memory = evaluate_policy_stages(MemoryPolicy(), n, seed=7, **kw)
    assert memory["episodes"] != serial["episodes"]
    split = evaluate_policy_stages(MemoryPolicy(), n, seed=7, workers=2, chunk_size=3, **kw)
    assert split["episodes"] == memory["episodes"]
    assert other["video"] == str(tmp_path / "first.gif")
    assert (tmp_path / "first.gif").stat().st_size > 0
    first = other["first_episode"]
    assert first.record(EVAL_FLAGS) == serial["episodes"][0]
    assert len(first.frames) == 1 + first.length // 3 + (first.length % 3 > 0)
    assert set(serial["stages"]) == set(EVAL_FLAGS)
    for v in serial["stages"].values():
        assert 0.0 <= v["ci_low"] <= v["rate"] <= v["ci_high"] <= 1.0
    text = format_results(serial)
    assert "button_pressed" in text and "Wilson" in text
    with pytest.raises(FileExistsError):  # no overwrite without force, before any work
        evaluate_policy_stages(ScriptedPolicy(), 1, video=tmp_path / "first.gif", **kw)


def test_any_env_factory():
    calls = []

    def factory(**extra):
        calls.append(extra)
        return gym.make(gym_coffee.ENV_ID, max_episode_steps=5, **extra)

    res = evaluate_policy_stages(ScriptedPolicy(), 2, env_factory=factory, progress=False)
    assert res["episode_length"]["max"] == 5 and calls == [{}]
    same = evaluate_policy_stages(
        ScriptedPolicy(),
        2,
        env_factory=functools.partial(EnvFactory(gym_coffee.ENV_ID), max_episode_steps=5),
        progress=False,
    )
    assert same["episodes"] == res["episodes"]


def test_chunk_seeds_cover_every_seed_once():
    for n in range(1, 12):
        for k in range(1, 6):
            chunks = chunk_seeds(range(n), k)
            assert [s for c in chunks for s in c] == list(range(n))
            assert len(chunks) == min(n, k) and all(chunks)
            assert max(map(len, chunks)) - min(map(len, chunks)) <= 1


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_episodes": 0}, "n_episodes"),
        ({"n_episodes": 2, "workers": 0}, "workers"),
        ({"n_episodes": 2, "backend": "dask"}, "backend"),
        ({"n_episodes": 2, "chunk_size": 0}, "chunk_size"),
        ({"n_episodes": 2, "confidence": 1.5}, "confidence"),
        ({"n_episodes": 2, "video": "x.avi"}, "video"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        evaluate_policy_stages(ScriptedPolicy(), progress=False, **kwargs)


def _square(x):
    return x * x


def test_map_tasks_keeps_the_order():
    from lgp_policy.app.backends import map_tasks

    items = list(range(7))
    assert map_tasks(_square, items, workers=2) == [x * x for x in items]
    assert map_tasks(_square, items) == [x * x for x in items]
    with pytest.raises(ValueError, match="backend"):
        map_tasks(_square, items, backend="spark")


def test_levels_and_perturbations_are_seeded():
    kw = {
        "env_id": "hard",  # a level name of gym_coffee.LEVELS
        "env_kwargs": {"obs_noise": 0.01, "calibration_bias": 0.01, "max_episode_steps": 10},
        "progress": False,
    }
    serial = evaluate_policy_stages(ScriptedPolicy(), 2, **kw)
    split = evaluate_policy_stages(ScriptedPolicy(), 2, workers=2, **kw)
    assert split["episodes"] == serial["episodes"]
    env = EnvFactory(kw["env_id"], kw["env_kwargs"])()
    try:  # the level and the keywords reach the env
        assert env.spec.id == gym_coffee.LEVELS["hard"]
        assert env.unwrapped.obs_noise == 0.01
    finally:
        env.close()
