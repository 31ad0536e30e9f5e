"""Residual reinforcement learning for the button press (the paper's future work, Sec. VI).

The paper's robot "was not able to press the tiny button and stopped a few millimeters in front of
it or [did not] press it deep enough" (Sec. IV). A learned residual corrects the demonstration
policy where it matters, and nowhere else::

    applied = clip(base + scale * gate * residual, low, high)

- ``base``: any SB3 ``PolicyPredictor``, normally a
  :class:`~lgp_policy.lfd.policy.GPDemonstrationPolicy`, always asked deterministically;
- ``gate`` (:mod:`~lgp_policy.residual.gates`): in ``[0, 1]``, a function of the base's phase;
- ``residual``: the action of an unmodified stable-baselines3 agent (SAC, TD3, PPO) whose
  actor's last layer starts at zero (:mod:`~lgp_policy.residual.models`), so fine-tuning starts
  exactly at the base policy.

Modules, by job: :mod:`~lgp_policy.residual.gates` (where the residual acts),
:mod:`~lgp_policy.residual.wrapper` (the agent's env), :mod:`~lgp_policy.residual.rewards` (the
agent's reward from the env's reward terms), :mod:`~lgp_policy.residual.models` (SB3:
the optional dependency, hyperparameters, zero start), :mod:`~lgp_policy.residual.policy` (the
fine-tuned policy, save/load), :mod:`~lgp_policy.residual.files` (the file format, bounded and
validated reading), :mod:`~lgp_policy.residual.train` (:func:`finetune`). Episodes are rolled out
by the application layer (:mod:`lgp_policy.app.evaluation`), which also draws the plots.

Only numpy and gymnasium are imported here: everything but training and loading works without the
``rl`` extra; those raise an :class:`ImportError` that says ``pip install "gym-coffee[rl]"``.
"""

from __future__ import annotations

from lgp_policy.residual.files import RESIDUAL_POLICY_KIND, ResidualPolicyFormatError
from lgp_policy.residual.gates import PhaseGate, gate_from_config
from lgp_policy.residual.models import (
    ALGOS,
    DEFAULT_HYPERPARAMETERS,
    RL_EXTRA_HINT,
    require_rl,
    zero_init_residual_actor,
)
from lgp_policy.residual.policy import ObsNormalizer, ResidualPolicy, load_any_policy
from lgp_policy.residual.rewards import PotentialShaping
from lgp_policy.residual.train import FinetuneResult, finetune
from lgp_policy.residual.wrapper import ResidualWrapper

__all__ = [
    "ALGOS",
    "DEFAULT_HYPERPARAMETERS",
    "RESIDUAL_POLICY_KIND",
    "RL_EXTRA_HINT",
    "FinetuneResult",
    "ObsNormalizer",
    "PhaseGate",
    "PotentialShaping",
    "ResidualPolicy",
    "ResidualPolicyFormatError",
    "ResidualWrapper",
    "finetune",
    "gate_from_config",
    "load_any_policy",
    "require_rl",
    "zero_init_residual_actor",
]
