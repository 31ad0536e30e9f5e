"""The examples run end to end at a small size (the full figures: run the scripts)."""

from __future__ import annotations

import importlib.util
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"_example_{name}", EXAMPLES / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_plain_arrays_2d_learns_the_task_from_arrays():
    ex = _load("plain_arrays_2d")
    from lgp_policy.gp import ConvergenceWarning
    from lgp_policy.lfd.demonstrations import TrajectorySet
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    demos = TrajectorySet([ex.record(i) for i in range(3)])
    assert all(d.success for d in demos)
    with warnings.catch_warnings():
        # the defaults fit it without a warning (the EM of one frame needs 12 iterations)
        warnings.simplefilter("error", ConvergenceWarning)
        policy = GPDemonstrationPolicy(adapter=ex.make_adapter(), n_steps=80).fit(demos)
    assert policy.frame_names_ == ["joint", "goal", "object"]
    assert policy.mean_["object"].shape[1] == 2  # 2-D frames, no padding
    tight = {iv["frame"] for iv in policy.constraint_intervals()}
    assert tight == {"object", "goal"}
    assert ex.evaluate(policy, 6, 10_000) >= 5 / 6


def test_panda_gym_pick_and_place():
    pytest.importorskip("panda_gym")
    ex = _load("panda_gym_pick_and_place")
    result = ex.run(n_demos=4, n_episodes=5)
    assert result["expert"] == 1.0
    assert result["policy"] >= 0.8


def test_an_adapter_that_drops_a_frame_is_an_error():
    """A fitted frame the adapter no longer returns is an error, never silently dropped."""
    ex = _load("plain_arrays_2d")
    from lgp_policy.lfd.adapters import ArrayAdapter
    from lgp_policy.lfd.demonstrations import TrajectorySet
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    adapter = ex.make_adapter()
    demos = TrajectorySet([ex.record(i) for i in range(2)])
    policy = GPDemonstrationPolicy(adapter=adapter, n_steps=30, n_grid=50).fit(demos)
    policy.adapter_ = ArrayAdapter(
        ex.OBS_DIM,
        state=slice(1, 3),
        frames={"goal": (slice(7, 9), None)},
        robot=adapter.robot,
        action_map=adapter.action_map,
        gripper=adapter.gripper,
        control_dt=ex.DT,
    )
    obs = ex.PickPlace2D().reset(0)
    with pytest.raises(ValueError, match="no frame 'object'"):
        policy.predict(obs, episode_start=np.array([True]))
