"""Shared test set-up: headless plotting and one torch thread (2-core CI machines)."""

from __future__ import annotations

import os

os.environ.setdefault("MPLBACKEND", "Agg")

try:  # torch is optional (the ``rl`` extra)
    import torch

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover - depends on the install
    pass
