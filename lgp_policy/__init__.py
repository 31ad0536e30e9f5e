"""lgp_policy: Gaussian-process learning from demonstration (Schneider & Ertel, IROS 2010).

The GP layer (:mod:`lgp_policy.kernels`, :mod:`lgp_policy.gp`, :mod:`lgp_policy.heteroscedastic`,
:mod:`lgp_policy.local`) and the encoding work on plain arrays. Public names are imported lazily, so
``import lgp_policy`` stays cheap and never imports torch or stable-baselines3.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "SquaredExponential": "lgp_policy.kernels",
    "WhiteNoise": "lgp_policy.kernels",
    "GaussianProcess": "lgp_policy.gp",
    "HeteroscedasticGP": "lgp_policy.heteroscedastic",
    "LocalGP": "lgp_policy.local",
    "DemonstrationEncoder": "lgp_policy.encoding",
    "GPDemonstrationPolicy": "lgp_policy.policy",
    "evaluate_policy_stages": "lgp_policy.evaluation",
    "ResidualWrapper": "lgp_policy.residual",
    "ResidualPolicy": "lgp_policy.residual",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'lgp_policy' has no attribute {name!r}")
