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


@pytest.mark.parametrize("skip_ungated", [False, True])
def test_potential_shaping_on_real_env_steps(skip_ungated):
    """``gym-coffee finetune``'s default reward on a scripted-teacher episode through the
    fine-tuning wrapper (gate opening mid-episode, so with ``skip_ungated`` early agent steps
    sum many env steps): with gamma = 1 the shaping telescopes, so the episode's agent return is
    the env's event terms plus phi(last) - phi(reset); a wrong ``previous_info`` (a skipped
    step's potential counted twice or not at all) breaks it. And a step that changes nothing
    pays (gamma - 1) * phi, where the env's dense reward paid phi (up to +1 per step for a
    button held pressed)."""
    from gym_coffee.env import OBS_SLICES, REWARD_TERMS
    from lgp_policy.app.finetune_cli import POTENTIAL_TERMS, make_reward_fn
    from lgp_policy.residual.rewards import PotentialShaping

    assert make_reward_fn("env", "sac") is None
    assert make_reward_fn("shaped", "sac").gamma == 0.98
    shaping = PotentialShaping(POTENTIAL_TERMS, gamma=1.0)
    inner = make_coffee()
    env = ResidualWrapper(
        inner,
        TeacherBase(inner),
        gate=PhaseGate(
            start=0.5,
            ramp=0.0,
            source="observation",
            time_index=OBS_SLICES["time"].start,
            time_scale=10.0,
        ),
        residual_dims=range(7),
        skip_ungated=skip_ungated,
        reward_fn=shaping,
    )
    _, reset_info = env.reset(seed=4)
    events = [t for t in REWARD_TERMS if t not in POTENTIAL_TERMS]
    total, event_sum, n_env, n_agent, done = 0.0, 0.0, 0, 0, False
    inner_infos = []
    original_step = inner.step

    def recording_step(action):
        out = original_step(action)
        inner_infos.append(out[4])
        return out

    inner.step = recording_step
    while not done:
        _, reward, terminated, truncated, info = env.step(np.zeros(7, np.float32))
        total += reward
        n_agent += 1
        n_env += info["env_steps"]
        done = terminated or truncated
    env.close()
    assert info["is_success"] and n_env == len(inner_infos)
    assert (n_agent < n_env) == skip_ungated
    event_sum = sum(i[f"reward_{t}"] for i in inner_infos for t in events)
    expected = event_sum + shaping.potential(inner_infos[-1]) - shaping.potential(reset_info)
    assert total == pytest.approx(expected, abs=1e-9)
    assert event_sum == pytest.approx(3.0 + 10.0)  # three stages and the success, once each
    held = dict(inner_infos[-2], reward_press=1.0)  # the button held at the press travel
    shaped = PotentialShaping(POTENTIAL_TERMS, gamma=0.98)(1.0, held, held)
    assert shaped == pytest.approx(-0.02 * shaping.potential(held), abs=1e-9)
    with pytest.raises(KeyError, match="reward_press"):
        shaping(0.0, {"reward_reach": 0.0, "reward_carry": 0.0}, reset_info)
    with pytest.raises(ValueError, match="gamma"):
        PotentialShaping(POTENTIAL_TERMS, gamma=0.0)
