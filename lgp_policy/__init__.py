"""lgp_policy: Gaussian-process learning from demonstration (Schneider & Ertel, IROS 2010)."""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["__version__"]
