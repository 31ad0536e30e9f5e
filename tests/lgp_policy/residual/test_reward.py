"""The reward the residual trains on, measured on real coffee-env steps."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from residual_helpers import TeacherBase, make_coffee

from lgp_policy.residual import PhaseGate, ResidualWrapper, finetune


def _fine_tuning_env_rollout(seed, knock_at_stage=None):
    """Agent rewards and env infos of a scripted-teacher episode in the fine-tuning wrapper,
    with the reward :func:`finetune` trains on by default; optionally the placed cup is knocked
    8 cm off its place the step after ``info["stage"]`` first reaches ``knock_at_stage``."""
    from gym_coffee.env import OBS_SLICES

    reward_fn = inspect.signature(finetune).parameters["reward_fn"].default
    inner = make_coffee()
    env = ResidualWrapper(
        inner,
        TeacherBase(inner),
        gate=PhaseGate(
            start=0.0, ramp=0.0, source="observation", time_index=OBS_SLICES["time"].start
        ),
        residual_dims=range(7),
        reward_fn=reward_fn,
    )
    env.reset(seed=seed)
    steps, knocked, done = [], False, False
    while not done:
        _, reward, terminated, truncated, info = env.step(np.zeros(7, np.float32))
        steps.append((reward, info))
        done = terminated or truncated
        if knock_at_stage is not None and not knocked and info["stage"] == knock_at_stage:
            sim = env.unwrapped.sim
            pos, quat = sim.get_base_pose("cup")
            sim.set_base_pose("cup", pos + np.array([0.0, -0.08, 0.0]), quat)
            knocked = True
    env.close()
    return steps


@pytest.mark.parametrize("knock", [None, 2])
def test_fine_tuning_reward_pays_each_stage_change_once_from_real_env_steps(knock):
    """Reaching a stage pays +1 once, losing one (the placed cup knocked away) costs 1.

    The env pays its stage bonus only on a stage change; the reward the residual trains on must
    keep that meaning (an earlier reward divided it by the stage again and paid +1 for losing
    a stage).
    """
    from gym_coffee.env import STAGE_BONUS

    steps = _fine_tuning_env_rollout(seed=4, knock_at_stage=knock)
    stage_terms, previous = [], 0
    for reward, info in steps:
        terms = {k: v for k, v in info.items() if k.startswith("reward_")}
        stage_term = reward - (sum(terms.values()) - terms["reward_stage"])
        assert stage_term == pytest.approx(STAGE_BONUS * (info["stage"] - previous), abs=1e-9)
        if info["stage"] != previous:
            stage_terms.append((previous, info["stage"], round(stage_term, 9)))
        previous = info["stage"]
    if knock is None:  # the teacher succeeds: grasp, place, press, each paid +1
        assert stage_terms == [(0, 1, 1.0), (1, 2, 1.0), (2, 3, 1.0)]
        assert steps[-1][1]["is_success"]
    else:  # placed, then knocked away: the lost stage costs what reaching it paid
        assert stage_terms[:3] == [(0, 1, 1.0), (1, 2, 1.0), (2, 1, -1.0)]
        assert not steps[-1][1]["is_success"]
