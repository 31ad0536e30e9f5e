"""L-BFGS-B for the many small hyperparameter searches of the GP layer, several in lockstep.

``scipy.optimize.minimize(method="L-BFGS-B")`` wraps the L-BFGS-B routine (which asks for the
objective by reverse communication) in a driver whose own work, about 1-2 ms per search on
these 2-3 parameter problems, exceeded the likelihood evaluations of the small local models
of the heteroscedastic EM. :func:`minimize_many` drives the same routine with scipy's default
options directly, for one or several independent problems at once: each problem takes exactly
the steps ``scipy.optimize.minimize`` would take (the routine is the same and sees the same
values; tested), and the evaluations the problems ask for in one round are handed to the
caller together, so that they can be computed in one batched pass.

The routine is scipy's (``scipy.optimize._lbfgsb.setulb``, the C version of scipy >= 1.15), a
private module: it is used only on the scipy versions it was checked on (:data:`CHECKED_SCIPY`,
1.17.1 at the time of writing) and only after a self-check on first use (a small bounded problem
must end exactly where ``scipy.optimize.minimize`` ends). Otherwise, or on any error in that
check, every problem runs through ``scipy.optimize.minimize`` one after another (same results,
without the saving).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import scipy
import scipy.optimize
from numpy.typing import NDArray

__all__ = ["minimize_many"]

#: scipy versions (major, minor) whose C routine has the signature and task codes used here.
CHECKED_SCIPY = ((1, 15), (1, 16), (1, 17))


def _scipy_version() -> tuple[int, int]:
    major, minor = scipy.__version__.split(".")[:2]
    return int(major), int("".join(ch for ch in minor if ch.isdigit()) or 0)


_SETULB: Callable[..., None] | None = None
if _scipy_version() in CHECKED_SCIPY:
    try:  # scipy >= 1.15: the C routine with integer task codes
        from scipy.optimize import _lbfgsb as _routine

        _SETULB = getattr(_routine, "setulb", None)
    except ImportError:  # pragma: no cover - depends on the installed scipy
        _SETULB = None

#: scipy.optimize.minimize's L-BFGS-B defaults.
MAXCOR = 10
FTOL = 2.2204460492503131e-09
GTOL = 1e-5
MAXLS = 20
MAXFUN = 15000

_FG, _NEW_X, _STOP = 3, 1, 5  # task codes of the C routine
_driver_ok: bool | None = None if _SETULB is not None else False
"""Whether the direct driver is used: ``None`` until the self-check has run."""

Evaluate = Callable[[list[int], list[NDArray[np.float64]]], list[tuple[float, NDArray[np.float64]]]]


class _Search:
    """The state of one problem's L-BFGS-B (the arrays scipy's driver allocates)."""

    def __init__(
        self,
        x0: NDArray[np.float64],
        bounds: NDArray[np.float64],
        max_iter: int,
        ftol: float = FTOL,
    ):
        n = x0.shape[0]
        lo, hi = bounds[:, 0], bounds[:, 1]
        self.x = np.clip(np.asarray(x0, dtype=np.float64), lo, hi).copy()
        self.low = np.where(np.isfinite(lo), lo, 0.0)
        self.high = np.where(np.isfinite(hi), hi, 0.0)
        # nbd: 0 unbounded, 1 lower only, 2 both, 3 upper only
        self.nbd = (np.isfinite(lo) * 1 + np.isfinite(hi) * 3).astype(np.int32)
        self.nbd[self.nbd == 4] = 2
        m = MAXCOR
        self.f = 0.0
        self.g = np.zeros(n)
        self.wa = np.zeros(2 * m * n + 5 * n + 11 * m * m + 8 * m)
        self.iwa = np.zeros(3 * n, dtype=np.int32)
        self.task = np.zeros(2, dtype=np.int32)
        self.ln_task = np.zeros(2, dtype=np.int32)
        self.lsave = np.zeros(4, dtype=np.int32)
        self.isave = np.zeros(44, dtype=np.int32)
        self.dsave = np.zeros(29)
        self.max_iter = max_iter
        self.factr = ftol / np.finfo(float).eps
        self.n_iter = 0
        self.n_fev = 0
        self.done = False

    def advance(self) -> bool:
        """Run the routine until it asks for an evaluation (True) or stops (False)."""
        assert _SETULB is not None
        factr = self.factr
        while True:
            _SETULB(
                MAXCOR,
                self.x,
                self.low,
                self.high,
                self.nbd,
                self.f,
                self.g,
                factr,
                GTOL,
                self.wa,
                self.iwa,
                self.task,
                self.lsave,
                self.isave,
                self.dsave,
                MAXLS,
                self.ln_task,
            )
            if self.task[0] == _FG:
                return True
            if self.task[0] != _NEW_X:
                self.done = True
                return False
            self.n_iter += 1
            if self.n_iter >= self.max_iter:
                self.task[:] = (_STOP, 504)
            elif self.n_fev > MAXFUN:
                self.task[:] = (_STOP, 502)


def minimize_many(
    evaluate: Evaluate,
    x0s: Sequence[NDArray[np.float64]],
    bounds: Sequence[NDArray[np.float64]],
    max_iter: int = 200,
    ftol: float = FTOL,
) -> list[tuple[NDArray[np.float64], float]]:
    """Minimise independent problems ``i`` by L-BFGS-B (scipy's defaults), in lockstep.

    Args:
        evaluate: ``evaluate(indices, xs)`` returns ``[(f_i(x), grad f_i(x)), ...]`` for the
            problems ``indices`` at the points ``xs`` (one round's requests, together).
        x0s: start of each problem (clipped to its bounds).
        bounds: ``(n_i, 2)`` bounds of each problem.
        max_iter: iteration limit per problem (``options={"maxiter": ...}``).
        ftol: relative decrease of ``f`` below which a search stops (``options={"ftol":
            ...}``; default scipy's).

    Returns:
        ``[(x_i, f_i), ...]``: what ``scipy.optimize.minimize`` returns as ``res.x`` and
        ``res.fun`` for each problem.
    """
    global _driver_ok
    if _driver_ok is None:
        _driver_ok = _self_check()
    if _driver_ok:
        return _lockstep(evaluate, x0s, bounds, max_iter, ftol)
    return _one_by_one(evaluate, x0s, bounds, max_iter, ftol)


def _one_by_one(evaluate: Evaluate, x0s, bounds, max_iter: int, ftol: float = FTOL):
    out = []
    for i, (x0, b) in enumerate(zip(x0s, bounds, strict=True)):

        def fun(x, i=i):
            f, g = evaluate([i], [np.asarray(x, dtype=np.float64)])[0]
            return f, g

        res = scipy.optimize.minimize(
            fun,
            x0,
            jac=True,
            method="L-BFGS-B",
            bounds=b,
            options={"maxiter": max_iter, "ftol": ftol},
        )
        out.append((np.asarray(res.x, dtype=np.float64), float(res.fun)))
    return out


def _lockstep(evaluate: Evaluate, x0s, bounds, max_iter: int, ftol: float = FTOL):
    searches = [
        _Search(
            np.asarray(x0, dtype=np.float64).ravel(),
            np.asarray(b, dtype=np.float64),
            max_iter,
            ftol,
        )
        for x0, b in zip(x0s, bounds, strict=True)
    ]
    waiting = [i for i, s in enumerate(searches) if s.advance()]
    while waiting:
        values = evaluate(waiting, [searches[i].x.copy() for i in waiting])
        for i, (f, g) in zip(waiting, values, strict=True):
            s = searches[i]
            s.f = float(f)
            s.g = np.asarray(g, dtype=np.float64).reshape(-1).copy()
            s.n_fev += 1
        waiting = [i for i in waiting if searches[i].advance()]
    return [(s.x, float(s.f)) for s in searches]


def _self_check() -> bool:
    """Whether the direct driver ends where ``scipy.optimize.minimize`` ends, bit for bit, on a
    small bounded non-convex problem (one bound active); ``False`` on any error."""

    def f(x: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        c = np.array([1.5, -0.4])
        value = float(0.5 * x @ x - c @ x + np.sum(np.cos(3.0 * x)))
        return value, x - c - 3.0 * np.sin(3.0 * x)

    x0, bounds = np.array([0.3, 0.2]), np.array([[-1.0, 1.0], [-0.5, 0.5]])

    def evaluate(indices, xs):
        return [f(x) for x in xs]

    try:
        ((x, value),) = _lockstep(evaluate, [x0], [bounds], 200)
        ref = scipy.optimize.minimize(f, x0, jac=True, method="L-BFGS-B", bounds=bounds)
        return bool(np.array_equal(x, ref.x) and value == float(ref.fun))
    except Exception:  # any failure of a private routine means: do not use it
        return False
