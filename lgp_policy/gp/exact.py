"""Exact Gaussian-process regression by Cholesky factorisation (paper Sec. II-A, Eqs. 1, 2, 4).

:class:`GaussianProcess` follows scikit-learn's estimator conventions (``fit`` returns ``self``,
fitted state ends in ``_``) and ``GaussianProcessRegressor``'s numerics, so that with the same data
and hyperparameters the two agree to rounding error.

Replicated inputs (several demonstrations sampled on one time grid) are handled exactly: ``m``
observations ``y_1..y_m`` of the same ``f(x)`` with noise variance ``s`` each carry the same
information about ``f`` as their mean with noise variance ``s / m``. The GP is therefore solved on
the unique inputs (``O(n_unique^3)`` instead of ``O(n^3)``); the posterior of ``f`` is *identical*
to the dense GP's, and the log marginal likelihood of the full data differs from the collapsed one
by the closed-form term ``_replicate_correction`` (within-group scatter and normalisers), which is
added back together with its gradient, so hyperparameter learning is unchanged too. Inputs that
are equal up to rounding (e.g. ``t / t_end`` of demonstrations of different durations sampled at
a fixed rate) are made equal first, by every ``fit``
(:func:`~lgp_policy.gp._validation.snap_near_replicates` says how close that is).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.linalg
import scipy.optimize
from numpy.typing import ArrayLike, NDArray

from lgp_policy.gp._base import ParamsMixin
from lgp_policy.gp._lbfgsb import FTOL, minimize_many
from lgp_policy.gp._threads import with_single_blas_thread
from lgp_policy.gp._validation import check_random_state, check_X, check_X_y
from lgp_policy.gp.kernels import (
    SEPARABLE_RANGE,
    Exponential,
    Kernel,
    SquaredExponential,
    WhiteNoise,
    separable_exp_neg_abs_diff,
)

__all__ = [
    "MAX_EXACT_INPUTS",
    "GaussianProcess",
    "NotPositiveDefiniteError",
    "default_kernel",
    "fit_shared_hyperparameters",
    "fit_shared_hyperparameters_many",
    "maximize_lml",
]

#: Most distinct training inputs the exact GP accepts. Learning holds about seven dense
#: ``n x n`` float64 matrices at once (K_y, its Cholesky factor and inverse, dLML/dK, the cached
#: distances and two kernel gradients): 7 * 8 * n^2 bytes, 3.6 GB at n = 8000 and 9 GB at
#: n = 12 700, and each likelihood evaluation costs O(n^3). Replicated inputs are collapsed first
#: and cost nothing. Larger data sets: :class:`lgp_policy.gp.local.LocalGP`.
MAX_EXACT_INPUTS = 8000

#: Relative jitter (times the mean diagonal of K_y) tried, in order, when Cholesky fails.
JITTER_STEPS = (0.0, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6)

_LOG_2PI = math.log(2.0 * math.pi)

_potrf = scipy.linalg.lapack.dpotrf
_potri = scipy.linalg.lapack.dpotri
_potrs = scipy.linalg.lapack.dpotrs

#: Isotropic kernels whose matrices are built from cached training distances.
_CACHED_KERNELS = (SquaredExponential, Exponential)

Optimizer = str | Callable[..., tuple[NDArray[np.float64], float]] | None


class NotPositiveDefiniteError(np.linalg.LinAlgError, ValueError):
    """K + noise was not positive definite even after adding jitter."""


def default_kernel() -> Kernel:
    """``SquaredExponential(1, 1) + WhiteNoise(0.1)``: Eq. (10) with neutral starting values."""
    return SquaredExponential(1.0, 1.0) + WhiteNoise(0.1)


def cholesky_with_jitter(K: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """Lower Cholesky factor of ``K``, adding growing jitter to the diagonal if needed.

    Returns:
        ``(L, jitter)`` with ``L L^T = K + jitter * I``.

    Raises:
        NotPositiveDefiniteError: if even the largest jitter in ``JITTER_STEPS`` fails.
    """
    if K.size:
        L, info = _potrf(K, lower=1)  # the usual case, without the wrapper's checks
        if info == 0:
            return L, 0.0
    scale = float(np.mean(np.diag(K))) if K.size else 1.0
    scale = scale if np.isfinite(scale) and scale > 0 else 1.0
    for rel in JITTER_STEPS:
        jitter = rel * scale
        try:
            A = K + jitter * np.eye(K.shape[0]) if jitter else K
            return scipy.linalg.cholesky(A, lower=True, check_finite=False), jitter
        except np.linalg.LinAlgError:
            continue
    raise NotPositiveDefiniteError(
        "The kernel matrix K + noise is not positive definite, even with a jitter of "
        f"{JITTER_STEPS[-1]:g} x its mean diagonal. Remedy: add a WhiteNoise term to the kernel "
        "or raise its noise_level (and the lower noise_level_bounds), increase `alpha`, or "
        "check X for (near-)duplicate inputs when no noise term is used."
    )


def _minimize(obj, theta0, bounds, optimizer: Optimizer, max_iter: int, ftol: float = FTOL):
    """Minimise ``obj(theta) -> (value, gradient)``; returns ``(theta, value)``. ``ftol``:
    L-BFGS-B's relative tolerance on the objective (ignored by the other optimisers)."""
    if callable(optimizer):
        theta, val = optimizer(obj, theta0, bounds)
        return np.asarray(theta, dtype=np.float64), float(val)
    if optimizer == "L-BFGS-B":  # scipy's routine and defaults, without scipy's driver
        ((theta, value),) = minimize_many(
            lambda _, thetas: [obj(thetas[0])], [theta0], [bounds], max_iter, ftol
        )
        return theta, value
    if optimizer != "CG":
        raise ValueError(
            f"optimizer must be 'L-BFGS-B', 'CG', None or a callable, got {optimizer!r}"
        )

    # "CG": unconstrained conjugate gradient (the paper's choice); theta is clipped to the
    # bounds and the gradient is zeroed where the clip is active.
    def clipped(theta):
        t = np.clip(theta, bounds[:, 0], bounds[:, 1])
        val, grad = obj(t)
        return val, np.where(t == theta, grad, 0.0)

    res = scipy.optimize.minimize(
        clipped, theta0, jac=True, method="CG", options={"maxiter": max_iter}
    )
    return np.clip(res.x, bounds[:, 0], bounds[:, 1]), float(res.fun)


def _as_loss(
    theta: NDArray[np.float64], value: float, grad: NDArray[np.float64]
) -> tuple[float, NDArray[np.float64]]:
    """What the optimisers minimise: ``-LML`` and its gradient; a failed (non-finite)
    evaluation is a wall of height 1e25 with a zero gradient."""
    if not np.isfinite(value):
        return 1e25, np.zeros_like(theta)
    return -value, -grad


def maximize_lml(
    lml: Callable[[NDArray[np.float64]], tuple[float, NDArray[np.float64]]],
    theta0: ArrayLike,
    bounds: NDArray[np.float64],
    *,
    optimizer: Optimizer = "L-BFGS-B",
    n_restarts: int = 0,
    random_state: int | np.random.Generator | None = None,
    max_iter: int = 200,
    ftol: float = FTOL,
) -> NDArray[np.float64]:
    """Maximise a log marginal likelihood ``lml(theta) -> (value, gradient)`` over ``theta``.

    Runs ``optimizer`` from ``theta0`` and from ``n_restarts`` log-uniform draws within
    ``bounds`` (from ``random_state``) and returns the best ``theta``, clipped to the bounds.
    ``ftol``: L-BFGS-B's relative tolerance on ``-lml`` (default scipy's).
    """
    bounds = np.asarray(bounds, dtype=np.float64)

    def obj(theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        return _as_loss(theta, *lml(theta))

    starts = [np.asarray(theta0, dtype=np.float64)]
    if n_restarts > 0:
        if not np.all(np.isfinite(bounds)):
            raise ValueError("n_restarts > 0 needs finite kernel bounds")
        rng = check_random_state(random_state)
        starts += [rng.uniform(bounds[:, 0], bounds[:, 1]) for _ in range(n_restarts)]
    best_theta, best_val = starts[0], np.inf
    for start in starts:
        theta, val = _minimize(
            obj, np.clip(start, bounds[:, 0], bounds[:, 1]), bounds, optimizer, max_iter, ftol
        )
        if val < best_val:
            best_theta, best_val = theta, val
    return np.clip(best_theta, bounds[:, 0], bounds[:, 1])


def fit_shared_hyperparameters(
    gps: list[GaussianProcess],
    *,
    optimizer: Optimizer = "L-BFGS-B",
    n_restarts: int = 0,
    random_state: int | np.random.Generator | None = None,
    max_iter: int = 200,
    apply_to: list[GaussianProcess] | None = None,
    cache: dict[Any, Any] | None = None,
    ftol: float = FTOL,
) -> NDArray[np.float64]:
    """Learn one ``theta`` for several fitted GPs by maximising the sum of their Eq. (4).

    ``gps`` must be fitted (any hyperparameters), or prepared with ``GaussianProcess._prepare``
    (which skips the factorisation this function would discard), with kernels of the same
    structure. The sum of
    independent data sets' log marginal likelihoods is the likelihood of the product-of-experts
    model of local GPs (Deisenroth & Ng 2015). The result is applied to ``gps`` and to
    ``apply_to`` (default: none besides ``gps``) without further optimisation. ``cache``: a
    dict owned by a caller that learns repeatedly on the same inputs (the EM), in which
    distances are kept between calls (see :meth:`_StackedLML.build_many`). ``ftol``:
    L-BFGS-B's relative tolerance on ``-LML`` (default scipy's).

    Returns:
        the shared ``theta`` (log space).
    """
    kernel = gps[0].kernel_
    stacked = _StackedLML.build(gps, cache)

    def total(theta):
        if stacked is not None:
            out = stacked(theta)
            if out is not None:
                return out
        return _lml_sum(gps, theta)

    theta = maximize_lml(
        total,
        kernel.theta,
        kernel.bounds,
        optimizer=optimizer,
        n_restarts=n_restarts,
        random_state=random_state,
        max_iter=max_iter,
        ftol=ftol,
    )
    if stacked is not None:
        stacked.count_evaluations()
    for gp in [*gps, *(apply_to or [])]:
        gp._set_theta(theta)
    return theta


def _lml_sum(gps: list[GaussianProcess], theta: NDArray[np.float64]):
    values, grads = zip(*(gp._lml(theta, eval_gradient=True) for gp in gps), strict=True)
    return float(np.sum(values)), np.sum(grads, axis=0)


def fit_shared_hyperparameters_many(
    groups: list[list[GaussianProcess]],
    *,
    optimizer: Optimizer = "L-BFGS-B",
    n_restarts: int = 0,
    random_state: int | np.random.Generator | None = None,
    max_iter: int = 200,
    cache: dict[Any, Any] | None = None,
    ftol: float = FTOL,
) -> list[NDArray[np.float64]]:
    """:func:`fit_shared_hyperparameters` for independent groups (one ``theta`` each): the
    outputs of one frame, each with its local models.

    With L-BFGS-B and no restarts the groups' searches run in lockstep
    (:func:`lgp_policy.gp._lbfgsb.minimize_many`) and the likelihoods they ask for in one
    round are evaluated in one batched pass (:class:`_StackedLML`); each group takes exactly
    the steps it would take alone (same search, same values to rounding). Otherwise the
    groups are learnt one after another (restarts draw from ``random_state`` in group order).
    """
    stacked = None
    if optimizer == "L-BFGS-B" and n_restarts == 0 and (len(groups) > 1 or len(groups[0]) > 1):
        # (one group of one GP: its own ``_lml``, as fit_shared_hyperparameters does)
        stacked = _StackedLML.build_many(groups, cache)
    if stacked is None:
        return [
            fit_shared_hyperparameters(
                gps,
                optimizer=optimizer,
                n_restarts=n_restarts,
                random_state=random_state,
                max_iter=max_iter,
                cache=cache,
                ftol=ftol,
            )
            for gps in groups
        ]

    def evaluate(indices, thetas):
        out = []
        for i, theta, res in zip(indices, thetas, stacked.evaluate(indices, thetas), strict=True):
            out.append(_as_loss(theta, *(_lml_sum(groups[i], theta) if res is None else res)))
        return out

    bounds = [np.asarray(gps[0].kernel_.bounds, dtype=np.float64) for gps in groups]
    starts = [
        np.clip(gps[0].kernel_.theta, b[:, 0], b[:, 1])
        for gps, b in zip(groups, bounds, strict=True)
    ]
    results = minimize_many(evaluate, starts, bounds, max_iter, ftol)
    stacked.count_evaluations()
    thetas = [
        np.clip(theta, b[:, 0], b[:, 1]) for b, (theta, _) in zip(bounds, results, strict=True)
    ]
    stacked.set_theta(list(range(len(groups))), thetas)
    return thetas


class _StackedLML:
    """Eq. (4) and its gradient for several groups of GPs ("owners", each the local models of
    one output with one shared ``theta``), each group's sum in one batched pass for all.

    The GPs' (unique-input) problems are stacked into ``(P, m, m)`` arrays, ``m`` the largest;
    a smaller problem is padded with independent unit-variance dummy inputs with target 0
    (identity rows and columns of ``K_y``: their distances to everything are ``PAD_DISTANCE``,
    so every kernel term and its gradient is exactly 0 there), which add exactly 0 to the value
    and the gradient. The kernel matrices, their gradients and the contractions are then one
    numpy operation each for all ``P`` problems (each with its owner's ``theta``), and only the
    factorisation and inversion run per problem (LAPACK, measured faster than numpy's stacked
    routines at these sizes): for the small local models of
    :class:`~lgp_policy.gp.local.LocalGP` the per-GP Python work of
    :meth:`GaussianProcess._lml` cost several times the algebra. Same value and gradient as the
    sum of the GPs' ``_lml`` to rounding (tested); where an owner's ``K_y`` needs jitter its
    result is ``None`` and the caller falls back to that sum.

    Repeated work is done once:

    * GPs of one owner whose ``K_y`` is the same matrix for every ``theta`` (equal training
      distances, replicate counts and ``alpha``: the local models of one time grid in the
      homoscedastic step and in the z-process of the EM) are one problem whose targets are the
      members' targets side by side (a multi-output GP): one factorisation instead of one per
      model;
    * where a problem's distances take few distinct values (a regular grid), the kernel is
      evaluated on those values and gathered.

    Both compare distances to ``2^-40`` relative (those of two equally spaced windows differ in
    their last bits), so the result equals the separate sum to rounding, not bit for bit.

    The exponential kernel of 1-D inputs (the z-process's) is evaluated as
    :class:`~lgp_policy.gp.kernels.Exponential` evaluates it, ``min(e^-u_i e^u_j, e^u_i
    e^-u_j)`` with ``u`` the inputs about the middle of each problem's range in length scales:
    ``2 m`` exponentials per problem instead of ``m^2`` (agrees with ``exp(-d)`` to a few ulp
    times the range; used while every problem's range is within ``SEPARABLE_RANGE``).

    Gradient: with ``W`` the lower triangle of ``K_y^-1`` and ``a = K_y^-1 y``,
    ``dLML/dtheta_j = (a^T G_j a - n_t tr(K_y^-1 G_j)) / 2`` and, ``G_j`` symmetric,
    ``tr(K_y^-1 G_j) = 2 sum(W * G_j) - sum(diag(W) * diag(G_j))``; ``n_t`` is the number of
    target columns a problem's ``K_y`` serves (members times targets).
    """

    #: Distance of a padding input to every input (finite: its products with 0 stay 0).
    PAD_DISTANCE = 1e120

    #: Evaluate the kernel on the distinct distances when there are at most this fraction of
    #: the stacked entries.
    DISTINCT_FRACTION = 0.125

    def __init__(self, owners: list[list[GaussianProcess]], cache: dict[Any, Any]) -> None:
        self.owners = owners
        first = owners[0][0]
        self.parts: list[tuple[str, int]] = []
        start = 0
        for leaf in first.kernel_.leaves():
            self.parts.append(("noise" if leaf.is_noise else type(leaf).__name__, start))
            start += leaf.n_dims
        self.n_theta = start
        kinds = sorted({kind for kind, _ in self.parts if kind != "noise"})
        n_t = first._data.ybar.shape[1]
        # Problems: GPs of one owner whose K_y coincides for every theta share one matrix.
        problems: list[tuple[int, list[GaussianProcess]]] = []
        for o, gps in enumerate(owners):
            mine: list[list[GaussianProcess]] = []
            for gp in gps:
                for members in mine:
                    if _same_covariance(members[0], gp, kinds, cache):
                        members.append(gp)
                        break
                else:
                    mine.append([gp])
            problems += [(o, members) for members in mine]
        sizes = [members[0]._data.X.shape[0] for _, members in problems]
        P, m = len(problems), max(sizes)
        R = n_t * max(len(members) for _, members in problems)
        self.owner = np.array([o for o, _ in problems])
        self.rows = [np.flatnonzero(self.owner == o) for o in range(len(owners))]
        valid = np.zeros((P, m), dtype=bool)
        for p, n in enumerate(sizes):
            valid[p, :n] = True
        # Per kernel kind: the stacked distances (P, m, m), or the distinct distances of every
        # problem side by side with each entry's index into them (and the owner of each value).
        self.dist: dict[str, NDArray[np.float64]] = {}
        self.distinct: dict[str, tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.intp]]]
        self.distinct = {}
        for kind in kinds:
            pad = self.PAD_DISTANCE**2 if kind == "SquaredExponential" else self.PAD_DISTANCE
            per = [_distinct_distances(members[0], kind, cache) for _, members in problems]
            n_values = sum(v.size for v, _ in per) + 1
            if n_values <= self.DISTINCT_FRACTION * P * m * m:
                values = np.concatenate([*(v for v, _ in per), [pad]])
                value_owner = np.concatenate(
                    [*(np.full(v.size, o) for (v, _), o in zip(per, self.owner, strict=True)), [0]]
                )
                index = np.full((P, m, m), n_values - 1, dtype=np.intp)
                offset = 0
                for p, ((v, inv), n) in enumerate(zip(per, sizes, strict=True)):
                    index[p, :n, :n] = inv + offset
                    offset += v.size
                self.distinct[kind] = (values, value_owner, index)
                continue
            D = np.full((P, m, m), pad)
            for p, ((_, members), n) in enumerate(zip(problems, sizes, strict=True)):
                gp = members[0]
                D[p, :n, :n] = (
                    gp._training_sqdist() if kind == "SquaredExponential" else gp._training_dist()
                )
            self.dist[kind] = D
        # 1-D inputs of every problem about the middle of its range (0 at the padding), for
        # the separable exponential kernel; half of each range.
        self.centred: NDArray[np.float64] | None = None
        if "Exponential" in self.dist and first._data.X.shape[1] == 1:
            self.centred = np.zeros((P, m))
            self.half_range = np.zeros(P)
            for p, ((_, members), n) in enumerate(zip(problems, sizes, strict=True)):
                x = members[0]._data.X[:, 0]
                lo, hi = float(np.min(x)), float(np.max(x))
                self.centred[p, :n] = x - 0.5 * (lo + hi)
                self.half_range[p] = 0.5 * (hi - lo)
        self.problems, self.sizes = problems, sizes
        self.Y = np.zeros((P, m, R))
        self.counts = np.ones((P, m))
        self.alpha = np.zeros((P, m))
        self.scatter = np.zeros((P, m))  # summed over members and targets
        self.n_cols = np.zeros(P)  # target columns per problem
        n_inputs = np.zeros(P)  # training inputs (with replicates) per problem, all members
        for p, ((_, members), n) in enumerate(zip(problems, sizes, strict=True)):
            self.counts[p, :n] = members[0]._data.counts
            self.alpha[p, :n] = members[0]._alpha_u
            for k, gp in enumerate(members):
                d = gp._data
                self.Y[p, :n, k * n_t : (k + 1) * n_t] = d.ybar
                self.scatter[p, :n] += np.sum(d.scatter, axis=1)
            self.n_cols[p] = len(members) * n_t
            n_inputs[p] = len(members) * n
        self.valid = valid.astype(np.float64)
        self.weight = self.valid * self.n_cols[:, None]  # target columns at each input
        self.pad = 1.0 - self.valid  # unit diagonal of the padding
        self.n_t = n_t
        # Constant parts of Eq. (4) and of the replicate correction (``_replicate_correction``):
        # per group of c replicates, -(c-1)/2 log(2 pi s) - 1/2 log c - scatter / (2 s) per
        # target column.
        c = self.counts
        self.replicated = bool(np.any(c > 1.0))
        self.inv_counts = self.valid / c
        self.rep_mask = valid & (c > 1.0)
        self.weight_c1 = self.weight * (c - 1.0)
        self.lml_const = -0.5 * n_t * n_inputs * _LOG_2PI - 0.5 * np.sum(
            self.weight * ((c - 1.0) * _LOG_2PI + np.log(c)), axis=1
        )
        self.twice_off_diagonal = 2.0 - np.eye(m)
        self.theta = np.array([gps[0].kernel_.theta for gps in owners])  # last theta per owner
        self.n_evaluations = np.zeros(len(owners), dtype=np.int64)  # (count_evaluations)

    @classmethod
    def build(
        cls, gps: list[GaussianProcess], cache: dict[Any, Any] | None = None
    ) -> _StackedLML | None:
        """A stacked evaluator of the sum over ``gps`` (one owner), or ``None`` where the
        kernels are not all of the supported form (isotropic squared-exponential /
        exponential terms plus white noise). ``cache``: see :meth:`build_many`."""
        if len(gps) < 2:
            return None
        return cls.build_many([gps], cache)

    @classmethod
    def build_many(
        cls, owners: list[list[GaussianProcess]], cache: dict[Any, Any] | None = None
    ) -> _StackedLML | None:
        """A stacked evaluator for several owners (lists of GPs), or ``None`` (see
        :meth:`build`). ``cache``: a dict kept by the caller between builds on the same input
        arrays (the iterations of the EM): distinct distances and which inputs have equal
        distances are stored in it, keyed by the identity of the GPs' input arrays (which it
        keeps alive)."""
        first = owners[0][0]
        kinds = [type(leaf) for leaf in first.kernel_.leaves()]
        for leaf in first.kernel_.leaves():
            if leaf.is_noise:
                if type(leaf) is not WhiteNoise:
                    return None
            elif type(leaf) not in _CACHED_KERNELS or leaf.n_dims != 2:
                return None
        n_t = first._data.ybar.shape[1]
        for gps in owners:
            for gp in gps:
                if [type(leaf) for leaf in gp.kernel_.leaves()] != kinds:
                    return None
                if gp._data.ybar.shape[1] != n_t:
                    return None
            if np.any(np.abs(gps[0].kernel_.bounds) > 50.0):  # keep PAD_DISTANCE products finite
                return None
        return cls(owners, {} if cache is None else cache)

    def __call__(self, theta: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]] | None:
        """Value and gradient of the first owner's sum at ``theta``."""
        return self.evaluate([0], [theta])[0]

    def _kernel(self, kind: str, j: int, theta_p, rows):
        """``(K, dK/dlog l)`` of one stacked isotropic term with each problem's ``theta``
        ``(P, 2)`` (``dK/dlog variance`` is ``K``)."""
        if kind in self.distinct:
            values, value_owner, index = self.distinct[kind]
            t = self.theta[value_owner, j : j + 2]  # every owner's latest theta
            if kind == "SquaredExponential":
                d = values * np.exp(-2.0 * t[:, 1])
                Kv = np.multiply(d, -0.5)
            else:
                d = values * np.exp(-t[:, 1])
                Kv = np.negative(d)
            np.exp(Kv, out=Kv)
            Kv *= np.exp(t[:, 0])
            d *= Kv
            idx = index if rows is None else index[rows]
            return Kv[idx], d[idx]
        D = self.dist[kind] if rows is None else self.dist[kind][rows]
        if kind == "Exponential" and self.centred is not None:
            inv_l = np.exp(-theta_p[:, 1])
            half = self.half_range if rows is None else self.half_range[rows]
            if np.all(2.0 * half * inv_l <= SEPARABLE_RANGE):
                valid = self.valid if rows is None else self.valid[rows]
                u = (self.centred if rows is None else self.centred[rows]) * inv_l[:, None]
                up, down = np.exp(u), np.exp(-u)
                up *= valid  # the padding: zero rows and columns
                down *= valid
                K = separable_exp_neg_abs_diff(up, down, up, down)
                K *= np.exp(theta_p[:, 0])[:, None, None]
                d = D * inv_l[:, None, None]
                d *= K
                return K, d
        if kind == "SquaredExponential":
            d = D * np.exp(-2.0 * theta_p[:, 1])[:, None, None]
            K = np.multiply(d, -0.5)
        else:
            d = D * np.exp(-theta_p[:, 1])[:, None, None]
            K = np.negative(d)
        np.exp(K, out=K)
        K *= np.exp(theta_p[:, 0])[:, None, None]
        d *= K
        return K, d

    def evaluate(
        self, owners: list[int], thetas: list[NDArray[np.float64]]
    ) -> list[tuple[float, NDArray[np.float64]] | None]:
        """``[(value, gradient) or None, ...]`` of the sums of ``owners`` at ``thetas``."""
        sel = list(owners)
        for o, th in zip(sel, thetas, strict=True):
            self.theta[o] = th
            self.n_evaluations[o] += 1
        if sel == list(range(len(self.owners))):
            rows = None
            owner_p = self.owner
        else:
            rows = np.concatenate([self.rows[o] for o in sel])
            owner_p = self.owner[rows]
        ends = np.cumsum([self.rows[o].shape[0] for o in sel])  # each owner's rows, in order
        take = (lambda a: a) if rows is None else (lambda a: a[rows])
        theta_p = self.theta[owner_p]  # (P, n_theta)
        K: NDArray[np.float64] | None = None
        grads: list[tuple[int, NDArray[np.float64]]] = []
        noise = np.zeros(owner_p.shape[0])
        noise_idx: list[int] = []
        for kind, j in self.parts:
            if kind == "noise":
                noise += np.exp(theta_p[:, j])
                noise_idx.append(j)
                continue
            Kl, G1 = self._kernel(kind, j, theta_p[:, j : j + 2], rows)
            K = Kl.copy() if K is None else K + Kl
            grads += [(j, Kl), (j + 1, G1)]
        if K is None:  # pragma: no cover - build() requires a signal term
            return [None] * len(sel)
        P, m = K.shape[0], K.shape[1]
        s = noise[:, None] + take(self.alpha)  # one observation's noise variance per input
        inv_counts = take(self.inv_counts)
        diag = K.reshape(P, -1)[:, :: m + 1]  # a view of the diagonals
        diag += s * inv_counts + take(self.pad)
        # In place, no copies: K[p].T is K[p] (symmetric) in Fortran order; its factor and then
        # the inverse's triangle overwrite it, so W (= K, read in C order) holds one triangle
        # of K_y^-1 and zeros in the other (``clean``).
        failed = np.zeros(P, dtype=bool)
        factors = []
        for p in range(P):
            L, info = _potrf(K[p].T, lower=1, overwrite_a=1, clean=1)
            if info != 0:  # this owner falls back; an identity keeps the rest finite
                failed[p] = True
                K[p] = np.eye(m)
                L = K[p].T
            factors.append(L)
        logdet = np.sum(np.log(diag), axis=1)  # the factors' diagonals
        Y = take(self.Y)
        a = np.empty_like(Y)
        for p, L in enumerate(factors):
            a[p] = _potrs(L, Y[p], lower=1)[0]
            _potri(L, lower=1, overwrite_c=1)
        W = K
        cols = take(self.n_cols)
        value = -0.5 * np.sum(Y * a, axis=(1, 2)) - cols * logdet + take(self.lml_const)
        if self.replicated:
            s_rep = np.where(take(self.rep_mask) & (s > 0), s, 1.0)  # (c - 1 = 0 where s = 0)
            inv_s = 1.0 / s_rep
            scatter, weight_c1 = take(self.scatter), take(self.weight_c1)
            value -= 0.5 * np.sum(weight_c1 * np.log(s_rep) + scatter * inv_s, axis=1)
        W2 = (W * self.twice_off_diagonal).reshape(P, 1, -1)  # tr(K_y^-1 G) = sum(W2 * G)
        grad = np.zeros((P, self.n_theta))
        for j, G in grads:
            quad = np.sum(a * (G @ a), axis=(1, 2))
            trace = np.matmul(W2, G.reshape(P, -1, 1)).reshape(P)
            grad[:, j] = 0.5 * (quad - cols * trace)
        if noise_idx:
            A_diag = np.sum(a * a, axis=2) - cols[:, None] * diag  # 2 diag(dLML/dK_y)
            dnoise = 0.5 * np.sum(inv_counts * A_diag, axis=1)
            if self.replicated:
                dnoise += 0.5 * np.sum(scatter * inv_s * inv_s - weight_c1 * inv_s, axis=1)
            for j in noise_idx:
                grad[:, j] = dnoise * np.exp(theta_p[:, j])
        out: list[tuple[float, NDArray[np.float64]] | None] = []
        any_failed = bool(np.any(failed))
        for stop, start in zip(ends, [0, *ends[:-1]], strict=True):
            if any_failed and np.any(failed[start:stop]):
                out.append(None)
                continue
            lml = float(np.sum(value[start:stop]))
            g = np.sum(grad[start:stop], axis=0)
            finite = math.isfinite(lml) and all(map(math.isfinite, g))
            out.append((lml, g) if finite else None)  # e.g. theta beyond bounds
        return out

    def set_theta(self, owners: list[int], thetas: list[NDArray[np.float64]]) -> None:
        """``gp._set_theta(theta)`` for every GP of ``owners`` (each at its owner's
        ``theta``), with the kernels and factorisations of all of them in one pass and one
        factorisation per problem (its members share it). An owner whose ``K_y`` needs jitter
        is set up by ``_set_theta`` itself."""
        sel = list(owners)
        for o, th in zip(sel, thetas, strict=True):
            self.theta[o] = th
        rows = (
            None
            if sel == list(range(len(self.owners)))
            else np.concatenate([self.rows[o] for o in sel])
        )
        take = (lambda a: a) if rows is None else (lambda a: a[rows])
        owner_p = take(self.owner)
        theta_p = self.theta[owner_p]
        K: NDArray[np.float64] | None = None
        noise = np.zeros(owner_p.shape[0])
        for kind, j in self.parts:
            if kind == "noise":
                noise += np.exp(theta_p[:, j])
                continue
            Kl, _ = self._kernel(kind, j, theta_p[:, j : j + 2], rows)
            K = Kl if K is None else K + Kl
        assert K is not None
        P, m = K.shape[0], K.shape[1]
        s = noise[:, None] + take(self.alpha)
        diag = K.reshape(P, -1)[:, :: m + 1]
        diag += s * take(self.inv_counts) + take(self.pad)
        problem_ids = np.arange(len(self.problems)) if rows is None else rows
        redo: set[int] = set()
        for p, q in enumerate(problem_ids):
            o, members = self.problems[q]
            if o in redo:
                continue
            L, info = _potrf(K[p], lower=1)
            if info != 0:
                redo.add(o)
                continue
            n = self.sizes[q]
            L = np.array(L[:n, :n], order="F")  # the padding's factor is an identity block
            noise_o = float(noise[p])
            for gp in members:
                gp.kernel_.theta = self.theta[o]
                d = gp._data
                s_gp = noise_o + gp._alpha_u
                gp.L_, gp.jitter_ = L, 0.0
                gp._train_noise = s_gp / d.counts
                gp.alpha_ = _potrs(L, d.ybar, lower=1)[0]
                gp._noise_level = noise_o
                n_t = d.ybar.shape[1]
                lml = (
                    -0.5 * float(np.vdot(d.ybar, gp.alpha_))
                    - n_t * float(np.sum(np.log(L.diagonal())))
                    - 0.5 * n_t * n * _LOG_2PI
                )
                if d.collapsed:
                    lml += gp._replicate_correction(s_gp, d.counts, d.scatter)
                gp.log_marginal_likelihood_value_ = float(lml)
        for o in redo:
            for gp in self.owners[o]:
                gp._set_theta(self.theta[o])

    def count_evaluations(self) -> None:
        """Add the evaluations since the last call to the GPs' ``n_lml_evaluations_``."""
        for gps, n in zip(self.owners, self.n_evaluations, strict=True):
            for gp in gps:
                gp.n_lml_evaluations_ = getattr(gp, "n_lml_evaluations_", 0) + int(n)
        self.n_evaluations[:] = 0


def _distinct_distances(
    gp: GaussianProcess, kind: str, cache: dict[Any, Any]
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Distinct training distances of ``gp`` (to ``2^-40``) and each entry's index into them."""
    X = gp._data.X
    key = ("distinct", kind, id(X))
    if key not in cache:
        D = gp._training_sqdist() if kind == "SquaredExponential" else gp._training_dist()
        values, inverse = np.unique(_round_mantissa(D), return_inverse=True)
        cache[key] = (values, inverse.reshape(D.shape).astype(np.intp), X)  # (X: keeps the id)
    values, inverse, _ = cache[key]
    return values, inverse


#: Low mantissa bits ignored when distances are compared (relative 2^-40, about 1e-12).
_DROPPED_BITS = 12


def _round_mantissa(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """``x`` (non-negative) with its lowest ``_DROPPED_BITS`` mantissa bits rounded away."""
    bits = np.ascontiguousarray(x, dtype=np.float64).view(np.int64)
    half = np.int64(1 << (_DROPPED_BITS - 1))
    mask = np.int64(~((1 << _DROPPED_BITS) - 1))
    return ((bits + half) & mask).view(np.float64)


def _same_covariance(
    a: GaussianProcess, b: GaussianProcess, kinds: list[str], cache: dict[Any, Any]
) -> bool:
    """Whether two prepared GPs have the same ``K_y`` at every ``theta``: training distances
    (for the kernel ``kinds``) equal to ``2^-40`` relative, and equal replicate counts and
    fixed noise ``alpha``."""
    da, db = a._data, b._data
    if da.X.shape != db.X.shape:
        return False
    if not (np.array_equal(da.counts, db.counts) and np.array_equal(a._alpha_u, b._alpha_u)):
        return False
    key = ("same", tuple(kinds), id(da.X), id(db.X))
    if key not in cache:
        same = True
        for kind in kinds:
            if kind == "SquaredExponential":
                da_, db_ = a._training_sqdist(), b._training_sqdist()
            else:
                da_, db_ = a._training_dist(), b._training_dist()
            same = same and bool(np.allclose(da_, db_, rtol=2.0**-40, atol=0.0))
        cache[key] = (same, da.X, db.X)  # (the arrays: keeps the ids valid)
    return bool(cache[key][0])


def unique_rows(
    X: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]]:
    """``np.unique(X, axis=0, return_inverse=True, return_counts=True)``, fast for 1 column."""
    if X.shape[1] == 1:
        u, inverse, counts = np.unique(X[:, 0], return_inverse=True, return_counts=True)
        return u[:, None], inverse.reshape(-1), counts
    U, inverse, counts = np.unique(X, axis=0, return_inverse=True, return_counts=True)
    return U, inverse.reshape(-1), counts


def _cholesky_inverse(L: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(L L^T)^{-1}`` from the lower Cholesky factor (LAPACK ``potri``)."""
    inv, info = scipy.linalg.lapack.dpotri(L, lower=1)
    if info != 0:  # pragma: no cover - L comes from a successful factorisation
        return scipy.linalg.cho_solve((L, True), np.eye(L.shape[0]), check_finite=False)
    inv = np.tril(inv)
    return inv + np.tril(inv, -1).T


class _Replicates:
    """Training data grouped by unique input (exact sufficient statistics for a GP).

    Attributes:
        X: unique inputs ``(m, n_features)``; ``counts`` ``(m,)``; ``inverse`` ``(n,)`` maps each
        sample to its row of ``X``; ``ybar`` ``(m, n_targets)`` group means; ``scatter``
        ``(m, n_targets)`` within-group sums of squares ``sum_j (y_j - ybar)^2``.
    """

    def __init__(self, X: NDArray[np.float64], y: NDArray[np.float64], collapse: bool) -> None:
        n = X.shape[0]
        if collapse:
            U, inverse, counts = unique_rows(X)
        if not collapse or U.shape[0] == n:  # nothing to collapse: keep the given order
            U, inverse, counts = X, np.arange(n), np.ones(n, dtype=np.int64)
        self.X = U
        self.inverse = inverse
        self.counts = counts.astype(np.float64)
        self.collapsed = U.shape[0] < n
        self.set_y(y)

    def with_y(self, y: NDArray[np.float64]) -> _Replicates:
        """The same grouping of the same inputs with targets ``y`` ``(n, n_targets)``."""
        new = object.__new__(_Replicates)
        new.X, new.inverse, new.counts, new.collapsed = (
            self.X,
            self.inverse,
            self.counts,
            self.collapsed,
        )
        new.set_y(y)
        return new

    def set_y(self, y: NDArray[np.float64]) -> None:
        m = self.X.shape[0]
        if not self.collapsed:
            self.ybar = y.copy()
            self.scatter = np.zeros_like(y)
            return
        inv = self.inverse
        cols = range(y.shape[1])
        sums = np.stack([np.bincount(inv, weights=y[:, j], minlength=m) for j in cols], axis=1)
        self.ybar = sums / self.counts[:, None]
        sq = (y - self.ybar[inv]) ** 2
        self.scatter = np.stack([np.bincount(inv, weights=sq[:, j], minlength=m) for j in cols], 1)


class GaussianProcess(ParamsMixin):
    """Exact GP regression, ``y = f(x) + eps`` with ``f ~ GP(0, k)`` (Eqs. 1, 2, 4).

    Args:
        kernel: covariance function; noise enters through :class:`~lgp_policy.gp.kernels.WhiteNoise`
            terms (Eq. 10). Default ``SquaredExponential(1, 1) + WhiteNoise(0.1)``.
        optimizer: ``"L-BFGS-B"`` (bounded, default), ``"CG"`` (conjugate gradient as in the
            paper; theta is clipped to the bounds), ``None`` (keep the kernel's hyperparameters),
            or a callable ``optimizer(obj, theta0, bounds) -> (theta, obj_min)`` where
            ``obj(theta) -> (-LML, -gradient)``.
        n_restarts: extra optimiser runs from log-uniform draws within the bounds.
        normalize_y: subtract the mean and divide by the standard deviation of ``y`` (per target)
            before fitting; hyperparameters then refer to the normalised targets.
        alpha: fixed extra noise variance per training sample (scalar or ``(n_samples,)``) in
            normalised units, added to the diagonal like scikit-learn's ``alpha``. Used by
            :class:`~lgp_policy.gp.heteroscedastic.HeteroscedasticGP` for its ``R`` (Eq. 5).
        collapse_replicates: solve on the unique inputs (exact, see module docstring). Falls back
            to the dense solve when ``alpha`` differs between replicates or no noise term exists.
        max_iter: iteration limit passed to scipy's optimiser.
        random_state: seed (int, ``None`` or ``numpy.random.Generator``) for the restarts.

    Multiple targets (``y`` of shape ``(n_samples, n_targets)``) are independent outputs that
    share one set of hyperparameters: the LML is the sum over targets (as in scikit-learn). Fit
    one estimator per column for separate hyperparameters.

    Duplicated inputs are legitimate replicates, not an error: with a noise term (or ``alpha``)
    they are collapsed exactly. Without any noise they make ``K`` singular; growing jitter
    (``JITTER_STEPS``, reported in ``jitter_``) is added to the diagonal, and if that is not
    enough fitting raises :class:`NotPositiveDefiniteError`, which names the remedy.

    Attributes:
        kernel_: the fitted kernel. ``X_train_``, ``y_train_``: the training data.
        L_: lower Cholesky factor of ``K_y`` on the (unique) inputs. ``alpha_``: ``K_y^{-1} y``.
        log_marginal_likelihood_value_: Eq. (4) at ``kernel_.theta`` (normalised targets, the
            full data even when replicates were collapsed). ``n_lml_evaluations_``: how many
            likelihood evaluations fitting used. ``jitter_``: jitter that was needed (0 if none).
    """

    #: Matrices shared by the steps of one EM (:meth:`_derive`); ``None`` outside it.
    _shared: dict[Any, Any] | None = None

    def __init__(
        self,
        kernel: Kernel | None = None,
        *,
        optimizer: Optimizer = "L-BFGS-B",
        n_restarts: int = 0,
        normalize_y: bool = True,
        alpha: float | ArrayLike = 0.0,
        collapse_replicates: bool = True,
        max_iter: int = 200,
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.kernel = kernel
        self.optimizer = optimizer
        self.n_restarts = n_restarts
        self.normalize_y = normalize_y
        self.alpha = alpha
        self.collapse_replicates = collapse_replicates
        self.max_iter = max_iter
        self.random_state = random_state

    # ------------------------------------------------------------------ fitting
    @with_single_blas_thread
    def fit(self, X: ArrayLike, y: ArrayLike) -> GaussianProcess:
        """Fit to ``X (n_samples, n_features)``, ``y (n_samples,)`` or ``(n_samples, n_targets)``.

        Returns:
            self
        """
        self._prepare(X, y)
        if self.optimizer is not None and self.kernel_.n_dims > 0:
            self.kernel_.theta = self._optimize_theta(self.kernel_)
        self._solve()
        return self

    def _derive(
        self,
        kernel: Kernel,
        *,
        alpha: NDArray[np.float64] | None = None,
        y: NDArray[np.float64] | None = None,
        shared: dict[Any, Any] | None = None,
    ) -> GaussianProcess:
        """A GP prepared (as by :meth:`_prepare`) on this prepared GP's training inputs, with
        ``kernel`` and without the checks and grouping ``_prepare`` would repeat.

        For the steps of an iterative fit on fixed inputs (the heteroscedastic EM): the
        replicate grouping and the cached distances are shared. ``alpha``: fixed noise per
        *distinct* input (rows of ``self._data.X``; default this GP's), so it is constant
        within a replicate group by construction; ``y``: ``(n_samples,)`` targets (default
        this GP's). Only for GPs with ``normalize_y=False`` (the targets are used as given).
        ``shared``: a dict the caller owns (and clears when done) in which the GPs derived
        with it keep the signal matrix and factor of their latest ``theta`` and noise, so that
        a step that changes neither reuses them (the EM with fixed hyperparameters).
        """
        if self.normalize_y:
            raise ValueError("_derive needs a GP with normalize_y=False")
        new = object.__new__(type(self))
        new.__dict__.update(self.get_params(deep=False))
        d = self._data
        new.kernel = kernel
        new._alpha_u = self._alpha_u if alpha is None else np.asarray(alpha, dtype=np.float64)
        new.alpha = new._alpha_u[d.inverse] if alpha is not None else self.alpha
        if y is None:
            new._data, new.y_train_ = d, self.y_train_
        else:
            new.y_train_ = y
            new._data = d.with_y(y.reshape(y.shape[0], -1))
        new.X_train_ = self.X_train_
        new.n_features_in_ = self.n_features_in_
        new._single_target = new.y_train_.ndim == 1
        new._y_mean, new._y_std = self._y_mean, self._y_std
        new._sqdist_cache = getattr(self, "_sqdist_cache", None)
        new._dist_cache = getattr(self, "_dist_cache", None)
        new.kernel_ = kernel.clone()
        new.n_lml_evaluations_ = 0
        new._shared = shared
        return new

    def _prepare(self, X: ArrayLike, y: ArrayLike) -> GaussianProcess:
        """``fit`` up to the factorisation: checked data, replicate groups, ``kernel_`` as given.

        For callers that set the hyperparameters next (:func:`fit_shared_hyperparameters`, which
        factorises at the ``theta`` it learns): factorising at the initial ``theta`` first
        would be discarded. Returns ``self``, not usable for prediction until ``_set_theta``.
        """
        X, y = check_X_y(X, y)
        self._check_params(X.shape[0])
        kernel = (default_kernel() if self.kernel is None else self.kernel).clone()
        self._single_target = y.ndim == 1
        Y = y[:, None] if self._single_target else y
        if self.normalize_y:
            self._y_mean = Y.mean(axis=0)
            std = Y.std(axis=0)
            self._y_std = np.where(std > 0, std, 1.0)
        else:
            self._y_mean = np.zeros(Y.shape[1])
            self._y_std = np.ones(Y.shape[1])
        Yn = (Y - self._y_mean) / self._y_std
        self.X_train_ = X
        self.y_train_ = y
        self.n_features_in_ = X.shape[1]

        alpha = np.broadcast_to(np.asarray(self.alpha, dtype=np.float64), (X.shape[0],))
        has_noise = any(leaf.is_noise for leaf in kernel.leaves())
        collapse = bool(self.collapse_replicates and (has_noise or np.all(alpha > 0)))
        self._sqdist_cache: NDArray[np.float64] | None = None
        self._dist_cache: NDArray[np.float64] | None = None
        self._data = _Replicates(X, Yn, collapse)
        if self._data.collapsed:
            a_u = np.zeros(self._data.X.shape[0])
            a_u[self._data.inverse] = alpha
            if np.any(np.abs(alpha - a_u[self._data.inverse]) > 1e-12 * np.abs(alpha)):
                self._data = _Replicates(X, Yn, False)  # alpha differs within a group
                self._sqdist_cache = None
                self._dist_cache = None
                a_u = alpha.copy()
        else:
            a_u = alpha.copy()
        self._alpha_u = a_u
        n_inputs = self._data.X.shape[0]
        if n_inputs > MAX_EXACT_INPUTS:
            gb = 7 * 8 * n_inputs**2 / 1e9
            raise ValueError(
                f"X has {n_inputs} distinct inputs; the exact GaussianProcess is limited to "
                f"{MAX_EXACT_INPUTS} (it would hold ~{gb:.0f} GB of n x n matrices and cost "
                "O(n^3) per likelihood evaluation). Use lgp_policy.gp.local.LocalGP, which "
                "splits the data into local models of bounded size."
            )

        self.kernel_ = kernel
        self.n_lml_evaluations_ = 0
        return self

    def _check_params(self, n_samples: int) -> None:
        if self.optimizer not in ("L-BFGS-B", "CG", None) and not callable(self.optimizer):
            raise ValueError(
                f"optimizer must be 'L-BFGS-B', 'CG', None or a callable, got {self.optimizer!r}"
            )
        if not isinstance(self.n_restarts, (int, np.integer)) or self.n_restarts < 0:
            raise ValueError(f"n_restarts must be a non-negative int, got {self.n_restarts!r}")
        if self.kernel is not None and not isinstance(self.kernel, Kernel):
            raise ValueError(f"kernel must be a lgp_policy Kernel, got {type(self.kernel)}")
        alpha = np.asarray(self.alpha, dtype=np.float64)
        if alpha.ndim > 1 or (alpha.ndim == 1 and alpha.shape[0] != n_samples):
            raise ValueError(
                f"alpha must be a scalar or have shape (n_samples,) = ({n_samples},), "
                f"got shape {alpha.shape}"
            )
        if not np.all(np.isfinite(alpha)) or np.any(alpha < 0):
            raise ValueError("alpha must be finite and non-negative")

    def _optimize_theta(self, kernel: Kernel) -> NDArray[np.float64]:
        return maximize_lml(
            lambda theta: self._lml(theta, eval_gradient=True),
            kernel.theta,
            kernel.bounds,
            optimizer=self.optimizer,
            n_restarts=self.n_restarts,
            random_state=self.random_state,
            max_iter=self.max_iter,
        )

    def _set_theta(self, theta: ArrayLike) -> None:
        """Use hyperparameters ``theta`` (log space) and refactorise; no optimisation."""
        if not hasattr(self, "_data"):  # fitted or prepared (``_prepare``)
            self._check_fitted()
        self.kernel_.theta = theta
        self._solve()

    # ----------------------------------------------------------- linear algebra
    def _noise_and_signal(
        self,
        kernel: Kernel,
        X: NDArray[np.float64],
        eval_gradient: bool,
        theta: NDArray[np.float64] | None = None,
    ):
        """Signal covariance on ``X`` (+ gradient) and the white-noise variance (+ its indices).

        With ``theta`` (log space) the kernel's own hyperparameters are ignored; isotropic
        squared-exponential terms then reuse the cached squared distances of the training inputs.
        """
        K = np.zeros((X.shape[0], X.shape[0]))
        grads: list[tuple[int, NDArray[np.float64]]] = []
        noise = 0.0
        noise_idx: list[int] = []
        start = 0
        for leaf in kernel.leaves():
            p = leaf.n_dims
            sub = None if theta is None else theta[start : start + p]
            if leaf.is_noise:
                noise += float(np.exp(sub[0])) if sub is not None else float(leaf.diag(X[:1])[0])
                noise_idx.extend(range(start, start + p))
            else:
                if sub is not None and type(leaf) in _CACHED_KERNELS and p == 2:
                    if type(leaf) is SquaredExponential:
                        out = leaf.from_sqdist(sub, self._training_sqdist(), eval_gradient)
                    else:
                        out = Exponential.from_dist(
                            sub,
                            self._training_dist,
                            eval_gradient,
                            x=X[:, 0] if X.shape[1] == 1 else None,
                        )
                    Kl = out[0] if eval_gradient else out
                    if eval_gradient:
                        grads.extend((start + j, G) for j, G in enumerate(out[1]))
                else:
                    k = leaf if sub is None else leaf.clone_with_theta(sub)
                    out = k(X, eval_gradient=eval_gradient)
                    Kl = out[0] if eval_gradient else out
                    if eval_gradient:
                        grads.extend((start + j, out[1][:, :, j]) for j in range(p))
                K += Kl
            start += p
        return K, grads, noise, noise_idx

    def _training_sqdist(self) -> NDArray[np.float64]:
        """Squared Euclidean distances between the (unique) training inputs, cached."""
        if getattr(self, "_sqdist_cache", None) is None:
            X = self._data.X
            if X.shape[1] == 1:
                d2 = (X[:, 0][:, None] - X[:, 0][None, :]) ** 2
            else:
                sq = np.sum(X**2, axis=1)
                d2 = np.maximum(sq[:, None] + sq[None, :] - 2.0 * X @ X.T, 0.0)
            self._sqdist_cache = d2
            return d2
        return self._sqdist_cache  # type: ignore[return-value]

    def _training_dist(self) -> NDArray[np.float64]:
        """Euclidean distances between the (unique) training inputs, cached."""
        if getattr(self, "_dist_cache", None) is None:
            X = self._data.X
            if X.shape[1] == 1:
                self._dist_cache = np.abs(X[:, 0][:, None] - X[:, 0][None, :])
            else:
                self._dist_cache = np.sqrt(self._training_sqdist())
        return self._dist_cache  # type: ignore[return-value]

    def _lml(self, theta: NDArray[np.float64], eval_gradient: bool):
        """Eq. (4) of the *full* data at ``theta``, via the unique inputs when collapsed."""
        self.n_lml_evaluations_ = getattr(self, "n_lml_evaluations_", 0) + 1
        theta = np.asarray(theta, dtype=np.float64)
        d = self._data
        K, grads, noise, noise_idx = self._noise_and_signal(self.kernel_, d.X, eval_gradient, theta)
        s = noise + self._alpha_u  # one observation's noise variance at each unique input
        c = d.counts
        K[np.diag_indices_from(K)] += s / c
        try:
            L, _ = cholesky_with_jitter(K)
        except NotPositiveDefiniteError:
            return (-np.inf, np.zeros_like(theta)) if eval_gradient else -np.inf
        Yb = d.ybar
        n_t = Yb.shape[1]
        a = scipy.linalg.cho_solve((L, True), Yb, check_finite=False)
        lml = (
            -0.5 * float(np.sum(Yb * a))
            - n_t * float(np.sum(np.log(np.diag(L))))
            - 0.5 * n_t * K.shape[0] * _LOG_2PI
        )
        if d.collapsed:
            lml += self._replicate_correction(s, c, d.scatter)
        if not eval_gradient:
            return lml
        grad = np.zeros_like(theta)
        Kinv = _cholesky_inverse(L)
        A = a @ a.T - n_t * Kinv  # dLML/dK_y = A / 2
        for j, G in grads:
            grad[j] = 0.5 * float(np.vdot(A, G))
        if noise_idx:
            dnoise = 0.5 * float(np.sum(np.diag(A) / c))
            if d.collapsed:
                dnoise += float(
                    np.sum(-0.5 * n_t * (c - 1.0) / s + 0.5 * np.sum(d.scatter, axis=1) / s**2)
                )
            for j in noise_idx:  # d noise / d log(noise_level_j) = noise_level_j
                grad[j] = dnoise * float(np.exp(theta[j]))
        return lml, grad

    @staticmethod
    def _replicate_correction(s, c, scatter) -> float:
        """log p(y | f) - log p(ybar | f) summed over groups: the LML term collapsing drops.

        For a group of ``c`` replicates with noise variance ``s`` each, ``prod_j N(y_j; f, s)``
        ``= N(ybar; f, s/c) * C`` with
        ``log C = -(c-1)/2 log 2 pi - c/2 log s + 1/2 log(s/c) - scatter / (2 s)``.
        """
        n_t = scatter.shape[1]
        per_group = (
            -0.5 * n_t * (c - 1.0) * _LOG_2PI
            - 0.5 * n_t * (c - 1.0) * np.log(s)
            - 0.5 * n_t * np.log(c)
            - 0.5 * np.sum(scatter, axis=1) / s
        )
        return float(np.sum(per_group))

    def _solve(self) -> None:
        d = self._data
        theta = self.kernel_.theta
        shared: dict[Any, Any] | None = getattr(self, "_shared", None)
        if shared is None:
            K, _, noise, _ = self._noise_and_signal(self.kernel_, d.X, False, theta)
            s = noise + self._alpha_u
            K.flat[:: K.shape[0] + 1] += s / d.counts
            self.L_, self.jitter_ = cholesky_with_jitter(K)  # raises with the remedy
        else:
            # Steps of one EM on the same inputs (``_derive(shared=...)``): the signal matrix
            # at an unchanged theta, and the factor at an unchanged noise too, are the ones
            # computed before (the same arrays, so the same result).
            key = tuple(type(leaf).__name__ for leaf in self.kernel_.leaves())
            entry = shared.get(key)
            if entry is None or not np.array_equal(entry["theta"], theta):
                K, _, noise, _ = self._noise_and_signal(self.kernel_, d.X, False, theta)
                entry = shared[key] = {"theta": theta, "K": K, "noise": noise}
            noise = entry["noise"]
            s = noise + self._alpha_u
            factor = entry.get("factor")
            if factor is not None and np.array_equal(factor[0], s):
                self.L_, self.jitter_ = factor[1], factor[2]
            else:
                K = entry["K"].copy()
                K.flat[:: K.shape[0] + 1] += s / d.counts
                self.L_, self.jitter_ = cholesky_with_jitter(K)  # raises with the remedy
                entry["factor"] = (s, self.L_, self.jitter_)
        self._train_noise = s / d.counts + self.jitter_  # K_y - K on the (unique) inputs
        self.alpha_ = _potrs(self.L_, d.ybar, lower=1)[0]
        self._noise_level = noise
        n_t = d.ybar.shape[1]
        lml = (  # Eq. (4) from this factorisation
            -0.5 * float(np.vdot(d.ybar, self.alpha_))
            - n_t * float(np.sum(np.log(self.L_.diagonal())))
            - 0.5 * n_t * d.X.shape[0] * _LOG_2PI
        )
        if d.collapsed:
            lml += self._replicate_correction(s, d.counts, d.scatter)
        self.log_marginal_likelihood_value_ = float(lml)

    # ---------------------------------------------------------------- inference
    def log_marginal_likelihood(
        self, theta: ArrayLike | None = None, eval_gradient: bool = False
    ) -> float | tuple[float, NDArray[np.float64]]:
        """Log marginal likelihood, Eq. (4), of the (normalised) training targets.

        Args:
            theta: log-space hyperparameters; ``None`` returns the value at ``kernel_.theta``.
            eval_gradient: also return the analytic gradient with respect to ``theta``.
        """
        self._check_fitted()
        if theta is None:
            if eval_gradient:
                return self._lml(self.kernel_.theta, True)
            return self.log_marginal_likelihood_value_
        theta = np.asarray(theta, dtype=np.float64).reshape(-1)
        if theta.shape[0] != self.kernel_.n_dims:
            raise ValueError(f"theta must have {self.kernel_.n_dims} entries, got {theta.shape[0]}")
        return self._lml(theta, eval_gradient)

    def _predict_normalized(self, X: NDArray[np.float64], return_var: bool = True):
        """Latent mean ``(n, n_targets)`` and variance ``(n,)`` in normalised units."""
        Ks = np.asarray(self.kernel_(X, self._data.X))  # WhiteNoise: nothing in k(X*, X)
        mean = Ks @ self.alpha_  # Eq. (1)
        if not return_var:
            return mean, None
        V = scipy.linalg.solve_triangular(self.L_, Ks.T, lower=True, check_finite=False)
        signal_diag = self.kernel_.diag(X) - self._noise_level
        var = signal_diag - np.einsum("ij,ij->j", V, V)  # Eq. (2), diagonal
        return mean, np.maximum(var, 0.0)

    def _latent_at_training(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Latent mean ``(m, n_targets)`` and variance ``(m,)`` at the (unique) training inputs.

        With ``K_y = K + D`` (``D`` diagonal noise): ``K alpha = y - D alpha`` and
        ``diag(K - K K_y^-1 K) = D - D^2 diag(K_y^-1)``, so no kernel evaluation and only a
        triangular inverse are needed. Normalised units; rows follow ``self._data.X``.
        """
        D = self._train_noise
        mean = self._latent_mean_at_training()
        Linv, info = scipy.linalg.lapack.dtrtri(self.L_, lower=1)
        if info != 0:  # pragma: no cover - L_ comes from a successful factorisation
            return self._predict_normalized(self._data.X)
        var = D - D**2 * np.einsum("ij,ij->j", Linv, Linv)
        return mean, np.maximum(var, 0.0)

    def _latent_mean_at_training(self) -> NDArray[np.float64]:
        """The mean of :meth:`_latent_at_training` alone (no triangular inverse)."""
        return self._data.ybar - self._train_noise[:, None] * self.alpha_

    def _out(self, a: NDArray[np.float64]) -> NDArray[np.float64]:
        return a[:, 0] if self._single_target else a

    @with_single_blas_thread
    def predict(self, X: ArrayLike, return_std: bool = False):
        """Predictive mean (and std **including** the noise, like sklearn with a WhiteKernel).

        Returns:
            ``mean`` of shape ``(n,)`` or ``(n, n_targets)``, and ``std`` of the same shape.
        """
        self._check_fitted()
        X = check_X(X, n_features=self.n_features_in_)
        mean_n, var_f = self._predict_normalized(X, return_std)
        mean = self._out(mean_n * self._y_std + self._y_mean)
        if not return_std:
            return mean
        std = np.sqrt(var_f + self._noise_level)[:, None] * self._y_std
        return mean, self._out(std)

    @with_single_blas_thread
    def predict_latent(self, X: ArrayLike):
        """Mean and noise-free standard deviation of the latent ``f(X)``: ``(mean, std_f)``."""
        self._check_fitted()
        X = check_X(X, n_features=self.n_features_in_)
        mean_n, var_f = self._predict_normalized(X, True)
        mean = self._out(mean_n * self._y_std + self._y_mean)
        return mean, self._out(np.sqrt(var_f)[:, None] * self._y_std)

    def noise_variance(self, X: ArrayLike) -> NDArray[np.float64]:
        """Observation-noise variance (the fitted WhiteNoise level) at ``X``, in units of y^2.

        Returns:
            ``(n,)`` for a single target, ``(n, n_targets)`` otherwise.
        """
        self._check_fitted()
        X = check_X(X, n_features=self.n_features_in_)
        var = np.full((X.shape[0], 1), self._noise_level) * self._y_std**2
        return self._out(var)

    def _check_fitted(self) -> None:
        if not hasattr(self, "alpha_"):
            raise ValueError(f"This {type(self).__name__} is not fitted yet; call fit(X, y) first")
