"""One BLAS thread for the GP layer's small matrices (threadpoolctl).

The GPs factorise many small matrices (a local model holds at most a few hundred distinct
inputs). Multi-threaded BLAS on such matrices only adds synchronisation: measured on the 2-core
CI machine, one heteroscedastic test took 95 s with default threads and 7.9 s with one, and a
300-point heteroscedastic fit 35 s against 1.3 s (see ``docs/design-gp.md``). Every public
``fit``/``predict`` of the GP layer therefore runs under :func:`single_blas_thread`, whatever
the user's environment variables say; nested calls enter the limit once.
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

from threadpoolctl import ThreadpoolController

__all__ = ["single_blas_thread", "with_single_blas_thread"]

_state = threading.local()
_controller: ThreadpoolController | None = None
_lock = threading.Lock()

F = TypeVar("F", bound=Callable[..., Any])


def _get_controller() -> ThreadpoolController:
    global _controller
    with _lock:
        if _controller is None:  # the BLAS libraries numpy and scipy loaded
            _controller = ThreadpoolController()
        return _controller


@contextmanager
def single_blas_thread() -> Iterator[None]:
    """Limit BLAS to one thread inside the block (re-entrant; thread-local nesting)."""
    depth = getattr(_state, "depth", 0)
    if depth:
        _state.depth = depth + 1
        try:
            yield
        finally:
            _state.depth = depth
        return
    _state.depth = 1
    try:
        with _get_controller().limit(limits=1, user_api="blas"):
            yield
    finally:
        _state.depth = 0


def with_single_blas_thread(func: F) -> F:
    """Decorator: run ``func`` under :func:`single_blas_thread`."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with single_blas_thread():
            return func(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
