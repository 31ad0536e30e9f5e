"""Evaluation: Wilson intervals, held-out seeds, serial vs vectorised workers agree."""

from __future__ import annotations

import numpy as np
import pytest

from lgp_policy.app.evaluation import (
    EVAL_SEED_OFFSET,
    STAGES,
    evaluate_policy_stages,
    format_results,
    wilson_interval,
)


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
        a[:, 0] = 0.5 * np.sin(t)
        a[:, 7] = np.where(t < 2.0, 1.0, -1.0)
        return (a if np.ndim(observation) == 2 else a[0]), state


def test_serial_and_vectorised_give_the_same_episodes():
    kw = {"env_kwargs": {"max_episode_steps": 40}, "progress": False}
    serial = evaluate_policy_stages(ScriptedPolicy(), 3, seed=7, workers=1, **kw)
    parallel = evaluate_policy_stages(ScriptedPolicy(), 3, seed=7, workers=2, **kw)
    assert serial["seeds"] == [EVAL_SEED_OFFSET + 7 + i for i in range(3)]
    assert serial["episodes"] == parallel["episodes"]
    assert set(serial["stages"]) == set(STAGES)
    assert serial["episode_length"]["max"] == 40
    for v in serial["stages"].values():
        assert 0.0 <= v["ci_low"] <= v["rate"] <= v["ci_high"] <= 1.0
    text = format_results(serial)
    assert "button_pressed" in text and "Wilson" in text


def test_bad_arguments():
    with pytest.raises(ValueError):
        evaluate_policy_stages(ScriptedPolicy(), 0)
    with pytest.raises(ValueError):
        evaluate_policy_stages(ScriptedPolicy(), 2, workers=0)
