"""lgp_policy: Gaussian-process learning from demonstration (Schneider & Ertel, IROS 2010).

Layers, each importing only the ones above it in this list:

* :mod:`lgp_policy.gp`: GP estimators on plain arrays (kernels, exact, heteroscedastic, local).
* :mod:`lgp_policy.lfd`: learning from demonstration (encoding, reproduction, the policy, robot
  models); it knows a task only through an adapter (:mod:`lgp_policy.lfd.adapters`).
* :mod:`lgp_policy.residual`: residual reinforcement learning on top of any base policy.
* :mod:`lgp_policy.app`: the ``gym-coffee`` command line, the pipeline, evaluation and plots.

Public names are imported lazily, so ``import lgp_policy`` stays cheap and never imports torch or
stable-baselines3.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "SquaredExponential": "lgp_policy.gp.kernels",
    "WhiteNoise": "lgp_policy.gp.kernels",
    "GaussianProcess": "lgp_policy.gp.exact",
    "HeteroscedasticGP": "lgp_policy.gp.heteroscedastic",
    "LocalGP": "lgp_policy.gp.local",
    "DemonstrationEncoder": "lgp_policy.lfd.encoding",
    "GPDemonstrationPolicy": "lgp_policy.lfd.policy",
    "evaluate_policy_stages": "lgp_policy.app.evaluation",
    "ResidualWrapper": "lgp_policy.residual",
    "ResidualPolicy": "lgp_policy.residual",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'lgp_policy' has no attribute {name!r}")
