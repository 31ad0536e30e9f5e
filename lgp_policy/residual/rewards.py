"""The reward the residual trains on: an env's event terms as they are, its dense terms as a
potential (potential-based shaping, Ng, Harada and Russell, ICML 1999)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["PotentialShaping"]


class PotentialShaping:
    """``reward_fn(env_reward, info, previous_info)`` for :class:`~.wrapper.ResidualWrapper`.

    The env's reward is split by the terms it reports in ``info`` (``info[prefix + name]``):
    the ``potential_terms`` (dense terms that describe a state, such as minus a distance or a
    button's travel) form a potential ``phi(s) = sum of those terms``, every other term of the
    reward (events: a stage reached or lost, success, failure) is kept as it is. The agent gets::

        env_reward - phi(s') + gamma * phi(s') - phi(s)

    (``s`` the state before the step, from ``previous_info``; ``s'`` after it, from ``info``).
    With ``gamma`` the agent's discount the shaping term ``gamma * phi(s') - phi(s)`` leaves the
    optimal policy of the event reward unchanged, while it still pays every step for moving
    towards a better state. A dense term paid as it is, every step, does not: a reward of "button
    travel as a fraction of the press travel" pays up to +1 per step for holding the button just
    short of the press, which under a discount of 0.98 is worth about 50, against the 11 a press
    pays once before the episode ends (measured: SAC on it learned to stop pressing).

    Raises ``KeyError`` naming the term if an ``info`` lacks one (the reset's ``info`` is the
    first ``previous_info``, so the env must report its terms there too).
    """

    def __init__(
        self, potential_terms: Sequence[str], gamma: float, *, prefix: str = "reward_"
    ) -> None:
        terms = tuple(str(t) for t in potential_terms)
        if not terms or len(set(terms)) != len(terms):
            raise ValueError(f"potential_terms must be distinct names, got {potential_terms!r}")
        gamma = float(gamma)
        if not (math.isfinite(gamma) and 0.0 < gamma <= 1.0):
            raise ValueError(f"gamma must be in (0, 1], got {gamma!r}")
        self.keys = tuple(prefix + t for t in terms)
        self.gamma = gamma

    def potential(self, info: Mapping[str, Any]) -> float:
        """``phi``: the sum of the potential terms in ``info``."""
        missing = [k for k in self.keys if k not in info]
        if missing:
            raise KeyError(f"info has no reward term {missing[0]!r} (PotentialShaping needs it)")
        return float(sum(float(info[k]) for k in self.keys))

    def __call__(
        self, reward: float, info: Mapping[str, Any], previous_info: Mapping[str, Any]
    ) -> float:
        phi = self.potential(info)
        return float(reward) - phi + self.gamma * phi - self.potential(previous_info)

    def __repr__(self) -> str:
        return f"PotentialShaping(keys={list(self.keys)}, gamma={self.gamma})"
