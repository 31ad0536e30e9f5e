"""Shared test set-up: headless plotting, one BLAS thread and one torch thread.

GP work on small matrices loses badly to BLAS thread oversubscription on the 2-core CI machines
(one heteroscedastic test: 95 s with default threads, 7.9 s with one), so BLAS is pinned to one
thread for the whole session with threadpoolctl (a test dependency).
"""

from __future__ import annotations

import os

os.environ.setdefault("MPLBACKEND", "Agg")

from threadpoolctl import threadpool_limits

_BLAS_LIMIT = threadpool_limits(limits=1, user_api="blas")

try:  # torch is optional (the ``rl`` extra)
    import torch

    torch.set_num_threads(1)
except ImportError:  # pragma: no cover - depends on the install
    pass
