"""The lockstep L-BFGS-B driver takes the steps scipy.optimize.minimize takes."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize

from lgp_policy.gp import _lbfgsb
from lgp_policy.gp._lbfgsb import minimize_many


def _problem(rng):
    A = rng.standard_normal((3, 3))
    H = A @ A.T + 0.1 * np.eye(3)
    c = rng.standard_normal(3)

    def f(x):
        return float(0.5 * x @ H @ x - c @ x + np.sum(np.cos(3.0 * x))), H @ x - c - 3.0 * np.sin(
            3.0 * x
        )

    return f


@pytest.mark.parametrize("max_iter", [200, 3])
def test_lockstep_results_equal_scipy_minimize(max_iter):
    """Several bounded, non-convex problems at once (some stopping at the bounds, some at the
    iteration limit): each ends exactly where scipy.optimize.minimize ends, and each round
    hands over only the problems still searching."""
    rng = np.random.default_rng(0)
    funcs = [_problem(rng) for _ in range(12)]
    bounds = [np.array([[-1.0, 2.0], [-0.5, 0.5], [-3.0, 3.0]])] * len(funcs)
    x0s = [rng.uniform(-1.0, 0.5, 3) for _ in funcs]
    rounds = []

    def evaluate(indices, xs):
        rounds.append(list(indices))
        return [funcs[i](x) for i, x in zip(indices, xs, strict=True)]

    results = minimize_many(evaluate, x0s, bounds, max_iter)
    for f, x0, b, (x, value) in zip(funcs, x0s, bounds, results, strict=True):
        ref = scipy.optimize.minimize(
            f, x0, jac=True, method="L-BFGS-B", bounds=b, options={"maxiter": max_iter}
        )
        np.testing.assert_array_equal(x, ref.x)
        assert value == ref.fun
    assert rounds[0] == list(range(len(funcs)))
    assert len(rounds[-1]) < len(funcs)  # the problems do not all take as many evaluations


def test_fallback_without_the_routine_gives_the_same(monkeypatch):
    rng = np.random.default_rng(1)
    funcs = [_problem(rng) for _ in range(3)]
    bounds = [np.array([[-1.0, 2.0]] * 3)] * 3
    x0s = [np.zeros(3)] * 3

    def evaluate(indices, xs):
        return [funcs[i](x) for i, x in zip(indices, xs, strict=True)]

    direct = minimize_many(evaluate, x0s, bounds)
    monkeypatch.setattr(_lbfgsb, "_driver_ok", False)
    fallback = minimize_many(evaluate, x0s, bounds)
    for (a, fa), (b, fb) in zip(direct, fallback, strict=True):
        np.testing.assert_array_equal(a, b)
        assert fa == fb


def test_the_self_check_passes_on_a_checked_scipy():
    """On the scipy versions the driver was checked on, the routine is found and passes."""
    if _lbfgsb._scipy_version() not in _lbfgsb.CHECKED_SCIPY:
        assert _lbfgsb._SETULB is None
        return
    assert _lbfgsb._SETULB is not None
    assert _lbfgsb._self_check()


@pytest.mark.parametrize("kind", ["raises", "junk"])
def test_a_changed_routine_fails_the_self_check_and_the_results_stay(monkeypatch, kind):
    """A private routine that raises, or that runs but ends elsewhere (another scipy's
    semantics), is detected on first use; every problem then goes through minimize."""

    def routine(*args):
        if kind == "raises":
            raise ValueError("failed in converting 12th argument")
        x, task = args[1], args[11]
        x[:] = 0.0  # "converged" at a point that is not scipy's answer
        task[:] = (4, 0)

    rng = np.random.default_rng(2)
    funcs = [_problem(rng) for _ in range(2)]
    bounds = [np.array([[-1.0, 2.0]] * 3)] * 2
    x0s = [np.full(3, 0.5)] * 2

    def evaluate(indices, xs):
        return [funcs[i](x) for i, x in zip(indices, xs, strict=True)]

    monkeypatch.setattr(_lbfgsb, "_SETULB", routine)
    monkeypatch.setattr(_lbfgsb, "_driver_ok", None)
    results = minimize_many(evaluate, x0s, bounds)
    assert _lbfgsb._driver_ok is False
    for f, x0, b, (x, value) in zip(funcs, x0s, bounds, results, strict=True):
        ref = scipy.optimize.minimize(f, x0, jac=True, method="L-BFGS-B", bounds=b)
        np.testing.assert_array_equal(x, ref.x)
        assert value == ref.fun


@pytest.mark.parametrize("path", ["direct", "fallback"])
def test_ftol_is_scipys_ftol(monkeypatch, path):
    """A looser ``ftol`` (the EM's searches) ends where ``minimize`` with that option ends,
    with the direct driver (where this scipy has it: see
    ``test_the_self_check_passes_on_a_checked_scipy``; else the fallback again) and with the
    fallback, and stops sooner than the default."""
    monkeypatch.setattr(_lbfgsb, "_driver_ok", path == "direct" and _lbfgsb._SETULB is not None)
    rng = np.random.default_rng(5)
    funcs = [_problem(rng) for _ in range(6)]
    bounds = [np.array([[-1.0, 2.0], [-0.5, 0.5], [-3.0, 3.0]])] * len(funcs)
    x0s = [rng.uniform(-1.0, 0.5, 3) for _ in funcs]
    counts = {}
    for ftol in (_lbfgsb.FTOL, 1e-4):
        n = [0]

        def evaluate(indices, xs, n=n):
            n[0] += len(indices)
            return [funcs[i](x) for i, x in zip(indices, xs, strict=True)]

        results = minimize_many(evaluate, x0s, bounds, ftol=ftol)
        counts[ftol] = n[0]
        for f, x0, b, (x, value) in zip(funcs, x0s, bounds, results, strict=True):
            ref = scipy.optimize.minimize(
                f, x0, jac=True, method="L-BFGS-B", bounds=b, options={"ftol": ftol}
            )
            np.testing.assert_array_equal(x, ref.x)
            assert value == ref.fun
    assert counts[1e-4] < counts[_lbfgsb.FTOL]
