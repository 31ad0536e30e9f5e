"""Most-likely heteroscedastic Gaussian process (paper Sec. II-B, Eqs. 5-7; Kersting et al. 2007).

The noise variance is a function ``r(x) = exp(z(x))`` of the input, with ``z`` the mean of a second
GP (the z-process, Goldberg et al. 1997). Following Kersting et al.'s most-likely EM:

1. fit a homoscedastic GP ``G1`` to ``(X, y)``;
2. estimate the noise at every training input from the posterior of ``f``;
3. fit the z-process ``G2`` to the log of these estimates;
4. refit the GP with input-dependent noise ``R = diag(exp(z(x_i)))`` (Eq. 5) and go to 2 until
   ``log r`` at the training inputs changes by less than ``tol``.

Step 2, default (``n_samples=None``): under the current model the residual ``y_i - mu_i`` has
variance ``r_i - var_f(x_i)``, so ``e_i = (y_i - mu_i)^2 / (1 - var_f(x_i) / r_i)`` is an unbiased
``r(x_i) chi2_1`` draw. The ``m`` replicates at one input are averaged, and the log is corrected
for the bias of the log of a ``chi2_m / m`` variable, ``psi(m/2) - log(m/2)`` (-1.27 for
``m = 1``). Without these two corrections ``r(x)`` comes out biased (measured on Goldberg's set:
about 1.4x too large when the posterior variance is added to the squared residual, about 3.6x too
small without the log correction). ``n_samples=s`` uses Kersting et al.'s sample estimator
verbatim, ``mean_j (y_i - t_ij)^2 / 2`` with ``t_ij`` drawn from the current predictive
distribution (no log correction); it is kept for comparison.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.special
from numpy.typing import ArrayLike, NDArray

from lgp_policy.gp._base import ConvergenceWarning, NoisePredictionsMixin, ParamsMixin
from lgp_policy.gp._threads import with_single_blas_thread
from lgp_policy.gp._validation import check_random_state, check_X_y
from lgp_policy.gp.exact import (
    GaussianProcess,
    Optimizer,
    default_kernel,
    fit_shared_hyperparameters_many,
)
from lgp_policy.gp.kernels import Exponential, Kernel, SquaredExponential

#: Floor of ``1 - var_f / r`` in the leverage correction of squared residuals.
MIN_RESIDUAL_FRACTION = 0.05

#: The EM has converged when its objective changes by less than this many nats per sample.
OBJECTIVE_TOL = 1e-3
#: Default limit of EM iterations (``max_em_iter``); see docs/design-gp.md for why 20.
MAX_EM_ITER = 20

SEARCH_FTOL = 1e-7
"""Relative tolerance on ``-LML`` at which the EM's hyperparameter searches stop (L-BFGS-B's
``ftol``; scipy's default is 2.2e-9). A search is re-run from its optimum in every iteration,
and the EM itself stops at changes of ``OBJECTIVE_TOL`` nats per sample: at 1e-7 a search stops
where one more step gains less than 1e-7 of the likelihood (a few 1e-5 nats on a local model's
few hundred samples), a ten-thousandth of what the EM resolves. Measured: 11% fewer likelihood
evaluations in ``LocalGP.fit`` at n = 2000, ``benchmarks/gp_quality.py --quick`` unchanged in
every printed digit; at 1e-6, 18% fewer but some figures moved in their last digit (a step ratio
0.87 -> 0.90, two NLPDs by 0.001-0.002), so not that far."""

NOISE_BOUNDS = (1e-3, 10.0)
"""Default bounds of the noise standard deviation ``sqrt(r(x))``, relative to the standard
deviation of the training targets. The lower end is the floor that keeps the noise model
well posed where demonstrations coincide exactly (zero spread: the squared residuals are 0 and
their log is ``-inf``); the upper end keeps ``exp(z)`` finite wherever the z-process goes."""
LOG_NOISE_BOUNDS = (2 * math.log(NOISE_BOUNDS[0]), 2 * math.log(NOISE_BOUNDS[1]))
""":data:`NOISE_BOUNDS` as bounds of ``log r`` (the noise variance), in the targets' units."""

__all__ = [
    "DEFAULT_METHOD",
    "MAX_EM_ITER",
    "METHODS",
    "NOISE_BOUNDS",
    "STOPPED_EARLY",
    "EMResult",
    "HeteroscedasticGP",
    "default_noise_kernel",
    "fit_noise_model",
    "most_likely_em",
    "most_likely_em_many",
    "signal_kernel",
]

METHODS = ("em", "vhgp")
"""How the noise model is learnt: ``"em"`` most-likely EM (Kersting et al. 2007,
:func:`most_likely_em`), ``"vhgp"`` the variational heteroscedastic GP (Lazaro-Gredilla &
Titsias 2011, :func:`lgp_policy.gp.variational.variational_heteroscedastic`)."""

DEFAULT_METHOD = "em"
"""The default of :data:`METHODS`, chosen on the measurements in ``docs/design-gp.md``."""

#: Single-residual log-noise targets of one data set needed to estimate their log bias from the
#: data (``_single_residual_log_bias``; with Gaussian residuals the estimate's std is about
#: 2.2 / sqrt(n), 0.22 nats at 100); with fewer, the Gaussian value is used.
MIN_SMEARING_TARGETS = 100

#: EM / bound statuses that mean "stopped at an iteration cap" (a ConvergenceWarning).
STOPPED_EARLY = ("max_em_iter reached", "max_iter reached")


def signal_kernel(kernel: Kernel) -> Kernel:
    """``kernel`` without its :class:`~lgp_policy.gp.kernels.WhiteNoise` terms (a copy)."""
    parts = [leaf.clone() for leaf in kernel.leaves() if not leaf.is_noise]
    if not parts:
        raise ValueError("kernel has no signal (non-noise) term")
    out = parts[0]
    for p in parts[1:]:
        out = out + p
    return out


def _log_mean_chi2_bias(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """``E[log(chi2_m / m)] = psi(m/2) - log(m/2)``: bias of the log of a mean of m squares."""
    return scipy.special.digamma(m / 2.0) - np.log(m / 2.0)


def _single_residual_log_bias(e: NDArray[np.float64], lo: float, hi: float) -> float:
    """How far the mean log of single squared residuals ``e`` lies below the log of their mean
    (Duan's smearing estimate of the log bias), between 0 and the Gaussian value
    ``-E[log chi2_1] = 1.27``; the logs clipped to ``[lo, hi]`` first (a zero residual).

    A residual that is one Gaussian draw has ``E[log e] = log r - 1.27``, the correction of
    :func:`_log_mean_chi2_bias` for ``m = 1``. Demonstrations on their own time stamps are no such
    draws: each deviates from the mean smoothly, so the residuals at nearby inputs are a few
    persistent offsets whose logs spread far less (on the LASA handwriting set the gap was 0.3
    nats where 1.27 was assumed, and the noise came out 2.6x the mean squared residual). The
    estimate pools one data set: a trend in the noise across it widens the logs' spread and
    moves the estimate towards the Gaussian value, never past it. Taking the trend out with the
    EM's current noise estimate was tried and biased it low (that estimate has absorbed part of
    the residuals' own spread: Goldberg's noise came out 26% low)."""
    logs = np.clip(np.log(np.maximum(e, 1e-300)), lo, hi)
    gap = math.log(max(float(np.mean(e)), 1e-300)) - float(np.mean(logs))
    return min(max(gap, 0.0), GAUSSIAN_SINGLE_LOG_BIAS)


#: ``-E[log chi2_1] = log 2 - psi(1/2) = 1.27``: the log bias of one Gaussian squared residual.
GAUSSIAN_SINGLE_LOG_BIAS = float(-_log_mean_chi2_bias(np.ones(1))[0])


def _log_mean_chi2_var(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """``Var[log(chi2_m / m)] = psi'(m/2)``: the known noise of a log-noise target (4.93 for
    ``m = 1``, 0.64 for ``m = 4``). It is the z-process's observation noise, so that noise
    cannot collapse to zero (the failure of a learnt white-noise term)."""
    return scipy.special.polygamma(1, m / 2.0)


def default_noise_kernel(
    signal_length_scale: float = 1.0, log_noise_bounds: tuple[float, float] = (-13.8, 4.6)
) -> Kernel:
    """z-process kernel: :class:`~lgp_policy.gp.kernels.Exponential` (Ornstein-Uhlenbeck)
    whose hyperparameters cannot collapse.

    Exponential, not squared exponential: where demonstrations coincide and then split, the
    log-noise targets step by ~9 nats within a few samples; a squared-exponential z-process
    rang over that step (Gibbs-like overshoot, multiplied by ``exp``), and the predicted std
    overshot the demonstrations' spread by up to 6x, up to the noise ceiling. The exponential
    kernel's posterior mean is a non-negative average of the targets and the mean: it cannot
    overshoot. (It is rougher on smooth noise: on Goldberg's set the correlation of the noise
    std with the truth is 0.89 instead of above 0.9.)

    * length scale at least ``signal_length_scale`` (the fitted length scale of ``f``): the
      noise varies no faster than the function, so the noise model cannot resolve single samples
      (which made ``r(x)`` piecewise constant and the predictions jump);
    * variance in ``[1e-2, (width / 2)^2]`` with ``width`` the range of ``log r`` allowed by
      ``log_noise_bounds``: the z-process cannot swing further than the bounds allow.
    """
    lo, hi = log_noise_bounds
    ls = float(signal_length_scale)
    return Exponential(
        1.0,
        ls,
        variance_bounds=(1e-2, max(1e-2, ((hi - lo) / 2.0) ** 2)),
        length_scale_bounds=(ls, max(ls, 1e5)),
    )


def _with_noise_bounds(kernel: Kernel, log_lo: float, log_hi: float) -> Kernel:
    """A copy of ``kernel`` whose WhiteNoise levels stay within ``exp([log_lo, log_hi])``."""
    out = kernel.clone()
    lo, hi = math.exp(log_lo), math.exp(log_hi)
    for leaf in out.leaves():
        if leaf.is_noise:
            b = np.asarray(leaf.noise_level_bounds, dtype=np.float64)  # type: ignore[attr-defined]
            new = (max(float(b[0]), lo), min(float(b[1]), hi))
            if new[0] > new[1]:
                new = (lo, hi)
            leaf.noise_level_bounds = new  # type: ignore[attr-defined]
            leaf.noise_level = float(np.clip(leaf.noise_level, *new))  # type: ignore[attr-defined]
    return out


def fixed_gp(k: Kernel, alpha: Any = 0.0, *, collapse_replicates: bool) -> GaussianProcess:
    """A GP with the kernel's hyperparameters as given (no optimiser) on targets as they are: the
    building block of the noise models' steps (their hyperparameters are learnt jointly)."""
    return GaussianProcess(
        k, optimizer=None, normalize_y=False, alpha=alpha, collapse_replicates=collapse_replicates
    )


def _fit_z(
    make, zk: Kernel, U, z, var, prepare: bool = False, template=None, shared=None
) -> GaussianProcess:
    """The z-process on the distinct inputs ``U`` with known target noise ``var``.

    A single distinct input is given as two exact replicates of twice the noise (the same
    information), since a GP needs two samples; the replicates are collapsed exactly.
    ``template``: the z-process of an earlier EM iteration on the same inputs and noise, whose
    grouping and distances are reused (only the targets change); ``shared``: see
    :meth:`GaussianProcess._derive`.
    """
    if U.shape[0] == 1:
        z = np.repeat(z, 2)
    if template is not None:
        gp = template._derive(zk, y=z, shared=shared)
        if not prepare:
            gp._solve()
        return gp
    if U.shape[0] == 1:
        gp = make(zk, alpha=np.repeat(2.0 * var, 2))
        U = np.repeat(U, 2, axis=0)
    else:
        gp = make(zk, alpha=var)
    gp._shared = shared
    return (gp._prepare if prepare else gp.fit)(U, z)


def _signal_length_scale(kernel: Kernel) -> float:
    ls = [
        np.min(leaf.length_scale)
        for leaf in kernel.leaves()
        if isinstance(leaf, SquaredExponential)
    ]
    return float(min(ls)) if ls else 1.0


RESCUE_LENGTH_SCALES = (1.0 / 3.0, 1.0 / 10.0)
"""Starts of the searches that re-learn a collapsed step 1 (:func:`_rescue_collapsed_search`):
signal length scales as fractions of the inputs' extent per feature."""


#: With the default kernel, the squared-exponential length scale stays below this fraction of
#: the inputs' span (``bound_length_scale``); the encoder's kernel uses the same bound on its
#: phase range.
MAX_LENGTH_SCALE_FRACTION = 0.5


def bound_length_scale(
    kernel: Kernel, inputs: list[NDArray[np.float64]], span: float | None = None
) -> Kernel:
    """A copy of ``kernel`` whose squared-exponential length scales stay between the inputs'
    spacing and ``MAX_LENGTH_SCALE_FRACTION`` of ``span`` (the data's largest per-feature
    range; ``None`` or 0: no ceiling). Used with the default kernel only: an explicit kernel's
    bounds are the user's.

    Floor: the median, over the arrays in ``inputs`` and their features, of the median gap
    between consecutive distinct values. A shorter length scale is white noise on the inputs that
    learn it, so they cannot identify it, and on denser inputs it interpolates every point
    (measured on the LASA handwriting set Multi_Models_1: ``LocalGP``'s shared search on thinned
    subsets stopped at 1.1e-4 s against their 2.6e-3 s spacing, and the mean stepped 119x further
    than any demonstration between two samples; one global ``HeteroscedasticGP`` on every tenth
    sample stopped at 3.4e-5 s, a step of 3.1x).

    Ceiling: the opposite degenerate optimum, "all noise": where demonstrations spread widely
    around a slowly moving mean, the heteroscedastic noise absorbs the mean's motion and the
    length scale runs away (LASA Sharpc, one fold: 68 s on 4.5 s of data). Every local window,
    a fraction of the span, is then a constant, neighbouring constants differ, and the mean
    steps where the mixture passes from one to the next (3.3x the demonstrations' largest step;
    0.95x with the ceiling, the held-out likelihood unchanged)."""
    gaps = []
    for Xs in inputs:
        for j in range(Xs.shape[1]):
            u = np.unique(Xs[:, j])
            if u.size > 1:
                gaps.append(float(np.median(np.diff(u))))
    floor = float(np.median(gaps)) if gaps else 0.0
    ceiling = MAX_LENGTH_SCALE_FRACTION * span if span else math.inf
    if floor == 0.0 and math.isinf(ceiling):
        return kernel
    out = kernel.clone()
    for leaf in out.leaves():
        if isinstance(leaf, SquaredExponential):
            low, high = (float(b) for b in leaf.length_scale_bounds)
            low = min(max(low, floor), high)
            high = max(min(high, ceiling), low)
            leaf.length_scale_bounds = (low, high)
            leaf.length_scale = np.clip(leaf.length_scale, low, high)
    return out


def input_span(X: NDArray[np.float64]) -> float:
    """The largest range ``max - min`` of a feature of ``X`` (the ``span`` of
    :func:`bound_length_scale`)."""
    return float(np.max(np.ptp(X, axis=0))) if X.size else 0.0


def _collapsed(kernel: Kernel) -> bool:
    """Whether a squared-exponential length scale of ``kernel`` sits at its lower bound."""
    for leaf in kernel.leaves():
        if isinstance(leaf, SquaredExponential):
            low = float(leaf.length_scale_bounds[0])
            if np.any(np.asarray(leaf.length_scale) <= low * (1.0 + 1e-6)):
                return True
    return False


def _rescue_collapsed_search(gps: list[GaussianProcess], kernel: Kernel, learn_all) -> None:
    """Re-learn step 1 of the EM where its search ended at a collapsed length scale.

    From the neutral start (length scale 1 on standardised targets) a single outlier makes the
    gradient of the homoscedastic likelihood point steeply towards short length scales; the
    first L-BFGS-B step can then reach the length scale's lower bound, where a squared
    exponential is white noise on any inputs further apart than the bound, its gradient in the
    length scale vanishes, and the search stops. That point has the likelihood of a model
    without signal (``-n/2 log(2 pi e)`` on standardised targets), usually far below the
    smooth fit; every later EM step starts from it, and ``LocalGP`` hands it to all its local
    models (the signal dropped, predictions at the mean).

    Here, and only here (a search that did not end on the lower bound is left alone, bit for
    bit), the same search runs again from :data:`RESCUE_LENGTH_SCALES` times the inputs'
    extent, and the result with the highest likelihood (the objective of step 1) is kept:
    the collapsed one where it is really the best.
    """
    if not _collapsed(gps[0].kernel_):
        return
    X_all = np.concatenate([gp._data.X for gp in gps])
    span = np.ptp(X_all, axis=0)
    span = np.where(span > 0, span, 1.0)
    y_var = float(np.mean([np.var(gp.y_train_) for gp in gps]))
    candidates = []
    for frac in RESCUE_LENGTH_SCALES:
        k = kernel.clone()
        for leaf in k.leaves():
            if leaf.is_noise:
                low, high = (float(b) for b in leaf.noise_level_bounds)  # type: ignore[attr-defined]
                leaf.noise_level = float(np.clip(0.5 * y_var, low, high))  # type: ignore[attr-defined]
            elif isinstance(leaf, SquaredExponential):
                low, high = (float(b) for b in leaf.variance_bounds)
                leaf.variance = float(np.clip(0.5 * y_var, low, high))
                low, high = (float(b) for b in leaf.length_scale_bounds)
                ls = np.clip(frac * span, low, high)
                leaf.length_scale = ls if leaf.anisotropic else float(np.min(ls))
        candidates.append([gp._derive(k) for gp in gps])
    learn_all(candidates)
    best = float(sum(gp.log_marginal_likelihood_value_ for gp in gps))
    best_theta = None
    for cand in candidates:
        value = float(sum(gp.log_marginal_likelihood_value_ for gp in cand))
        if value > best:
            best, best_theta = value, cand[0].kernel_.theta
    if best_theta is not None:
        for gp in gps:
            gp._set_theta(best_theta)


@dataclass
class EMResult:
    """Output of :func:`most_likely_em`: one entry per data set in the lists.

    ``noise_gps[i]`` is ``None`` where the homoscedastic model (iteration 0) was kept; the log
    noise is then the constant ``noise_offset``. ``objective`` holds the EM objective (the sum
    over data sets of ``log p(y | X, R)``, Eq. 4 with ``R = diag(r(x_i))``) after every
    iteration, iteration 0 being the homoscedastic GP; ``best_iter`` is the iteration kept.
    """

    gps: list[GaussianProcess]
    noise_gps: list[GaussianProcess | None]
    noise_offset: float
    homoscedastic_kernel: Kernel
    signal_kernel: Kernel
    noise_kernel: Kernel
    n_iter: int
    converged: bool
    log_noise_bounds: tuple[float, float]
    objective: list[float] = field(default_factory=list)
    best_iter: int = 0
    status: str = ""
    lognormal_noise: bool = False
    """Predict the noise as ``E[exp(z*)] = exp(mean + var / 2)`` of the z-posterior (VHGP)
    instead of ``exp(mean)`` (the most-likely EM's point estimate)."""


def most_likely_em(
    datasets: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    kernel: Kernel,
    noise_kernel: Kernel | None,
    *,
    learn: bool = True,
    optimizer: Optimizer = "L-BFGS-B",
    n_restarts: int = 0,
    max_em_iter: int = MAX_EM_ITER,
    tol: float = 0.05,
    n_samples: int | None = None,
    collapse_replicates: bool = True,
    max_iter: int = 200,
    random_state: int | np.random.Generator | None = None,
    refit_kernel: Kernel | None = None,
    log_noise_bounds: tuple[float, float] = LOG_NOISE_BOUNDS,
    noise_offset: float | None = None,
    keep_homoscedastic: bool = True,
) -> EMResult:
    """Most-likely heteroscedastic EM (Kersting et al. 2007) on one or more data sets.

    With several data sets (the local models of :class:`~lgp_policy.gp.local.LocalGP`) the
    hyperparameters are shared: each learning step maximises the *sum* of the data sets' log
    marginal likelihoods, and the z-processes share one constant mean ``noise_offset`` (the mean
    of all log-noise targets, unless given), so that neighbouring local models agree on the noise
    where they have no data. ``learn=False`` keeps ``kernel`` and ``noise_kernel`` as given.

    Well-posedness: ``log r`` is kept within ``log_noise_bounds`` everywhere (targets, z at the
    training inputs, predictions), the WhiteNoise of step 1 is bounded the same way, the
    z-process's observation noise is the known variance of a log mean of squares
    (:func:`_log_mean_chi2_var`) and its kernel has bounded hyperparameters
    (:func:`default_noise_kernel`).

    Objective: ``sum_i log p(y_i | X_i, R_i)`` (Eq. 4 with the noise ``R`` of the current
    iteration; iteration 0 is the homoscedastic GP). The EM keeps the iteration with the best
    objective and stops when ``log r`` changes by less than ``tol`` or the objective by less than
    :data:`OBJECTIVE_TOL` nats per sample ("converged"), when the objective decreases by more
    ("objective decreased"), or after ``max_em_iter`` ("max_em_iter reached"); ``status`` says
    which.

    Args:
        datasets: ``[(X (n_i, d), y (n_i,)), ...]``, targets already standardised.
        kernel: homoscedastic kernel of step 1 (with a WhiteNoise term).
        noise_kernel: z-process kernel; ``None``: :func:`default_noise_kernel` from step 1.
        refit_kernel: kernel of ``f`` in step 4 (default: ``kernel`` without its noise term).
        log_noise_bounds: ``(low, high)`` bounds of ``log r`` in the units of the targets.
        noise_offset: fixed constant mean of the z-processes (``None``: learnt).
        keep_homoscedastic: whether iteration 0 (the homoscedastic GP) can be the iteration kept.
            ``False`` keeps the best heteroscedastic iteration (>= 1) even where the homoscedastic
            GP's objective is higher: :class:`~lgp_policy.gp.local.LocalGP`'s local models with
            shared hyperparameters, which must all have the shared prior of ``f`` (see there).
    """
    return most_likely_em_many(
        [datasets],
        kernel,
        noise_kernel,
        learn=learn,
        optimizer=optimizer,
        n_restarts=n_restarts,
        max_em_iter=max_em_iter,
        tol=tol,
        n_samples=n_samples,
        collapse_replicates=collapse_replicates,
        max_iter=max_iter,
        random_state=random_state,
        refit_kernel=refit_kernel,
        log_noise_bounds=log_noise_bounds,
        noise_offset=noise_offset,
        keep_homoscedastic=keep_homoscedastic,
    )[0]


def most_likely_em_many(
    problems: list[list[tuple[NDArray[np.float64], NDArray[np.float64]]]],
    kernel: Kernel,
    noise_kernel: Kernel | None,
    *,
    learn: bool = True,
    optimizer: Optimizer = "L-BFGS-B",
    n_restarts: int = 0,
    max_em_iter: int = MAX_EM_ITER,
    tol: float = 0.05,
    n_samples: int | None = None,
    collapse_replicates: bool = True,
    max_iter: int = 200,
    random_state: int | np.random.Generator | None = None,
    refit_kernel: Kernel | None = None,
    log_noise_bounds: tuple[float, float] = LOG_NOISE_BOUNDS,
    noise_offset: float | None = None,
    keep_homoscedastic: bool = True,
) -> list[EMResult]:
    """Independent :func:`most_likely_em` runs, one per entry of ``problems`` (each a list of
    data sets that share hyperparameters: the local models of one output), in lockstep.

    Every learning step of the problems still running is one
    :func:`~lgp_policy.gp.exact.fit_shared_hyperparameters_many` (their searches in lockstep,
    the likelihoods of one round in one batched pass); each problem stops by its own rule.
    Each result equals that of :func:`most_likely_em` on the problem alone, to rounding, when
    nothing is drawn at random (``n_restarts=0``, ``n_samples=None``); otherwise the problems
    draw from ``random_state`` in turn. Arguments: see :func:`most_likely_em`.
    """
    rng = check_random_state(random_state)
    lo, hi = (float(b) for b in log_noise_bounds)
    make = functools.partial(fixed_gp, collapse_replicates=collapse_replicates)
    cache: dict[Any, Any] = {}  # distances of the fixed inputs, shared by every learning step

    def learn_all(groups: list[list[GaussianProcess]]) -> None:
        fit_shared_hyperparameters_many(
            groups,
            optimizer=optimizer,
            n_restarts=n_restarts,
            random_state=rng,
            max_iter=max_iter,
            cache=cache,
            ftol=SEARCH_FTOL,
        )

    # Step 1: homoscedastic GP G1, its noise kept within the bounds.
    kernel = _with_noise_bounds(kernel, lo, hi)
    if learn:
        step1 = [[make(kernel)._prepare(X, y) for X, y in datasets] for datasets in problems]
        learn_all(step1)
        for gps in step1:
            _rescue_collapsed_search(gps, kernel, learn_all)
    else:
        step1 = [[make(kernel).fit(X, y) for X, y in datasets] for datasets in problems]
    runs = [
        _EMRun(datasets, gps, lo, hi, refit_kernel, noise_kernel, keep_homoscedastic)
        for datasets, gps in zip(problems, step1, strict=True)
    ]
    for _ in range(max_em_iter):
        active = [run for run in runs if run.running]
        if not active:
            break
        # Steps 2-3: noise estimates and the z-processes on their logs.
        for run in active:
            run.noise_targets(make, n_samples, rng, noise_offset, prepare=learn)
        if learn:
            learn_all([run.noise_gps for run in active])
        # Step 4: GP with R = diag(r(x_i)), Eq. (5), on the inputs and groups of step 1.
        for run in active:
            run.refit(solve=not learn)
        if learn:
            learn_all([run.gps for run in active])
        for run in active:
            run.end_iteration(tol)
    return [run.result() for run in runs]


class _EMRun:
    """The state of one problem's most-likely EM (:func:`most_likely_em_many`)."""

    def __init__(
        self, datasets, gps, lo, hi, refit_kernel, noise_kernel, keep_homoscedastic=True
    ) -> None:
        self.datasets, self.gps, self.lo, self.hi = datasets, gps, lo, hi
        self.homoscedastic_kernel = gps[0].kernel_.clone()
        self.groups = []  # the GP's own distinct inputs: X, inverse, counts, log bias, log var
        for gp in gps:
            d = gp._data
            self.groups.append(
                (
                    d.X,
                    d.inverse,
                    d.counts,
                    _log_mean_chi2_bias(d.counts),
                    _log_mean_chi2_var(d.counts),
                )
            )
        self.base = gps  # inputs, replicate groups and distances of every later step's GPs
        self.z_templates: Sequence[GaussianProcess | None] = [None] * len(gps)
        log_r0 = float(np.clip(math.log(gps[0]._noise_level), lo, hi))
        self.log_r = [np.full(X.shape[0], log_r0) for X, _ in datasets]
        k0 = self.homoscedastic_kernel
        self.sig = signal_kernel(k0) if refit_kernel is None else refit_kernel.clone()
        if noise_kernel is None:
            self.zk = default_noise_kernel(_signal_length_scale(k0), (lo, hi))
        else:
            self.zk = noise_kernel.clone()
        lml0 = float(sum(gp.log_marginal_likelihood_value_ for gp in gps))
        self.n_total = sum(X.shape[0] for X, _ in datasets)
        self.objective = [lml0]
        # without keep_homoscedastic, iteration 1 replaces iteration 0 whatever its objective
        self.best_obj = lml0 if keep_homoscedastic else -math.inf
        self.best: tuple[Any, ...] = (gps, [None] * len(gps), log_r0, self.sig, self.zk, 0)
        self.status, self.converged, self.n_iter = "max_em_iter reached", False, 0
        self.running = True
        # With fixed hyperparameters every z-process of a data set has the same K_y and every
        # refit of f the same signal matrix: kept here between iterations (cleared at the end).
        self.z_shared: list[dict[Any, Any]] = [{} for _ in gps]
        self.f_shared: list[dict[Any, Any]] = [{} for _ in gps]

    def noise_targets(self, make, n_samples, rng, noise_offset, prepare: bool) -> None:
        """Steps 2-3: the log-noise targets and the z-processes on them (``noise_gps``)."""
        self.n_iter += 1
        lo, hi = self.lo, self.hi
        targets = []
        for gp, (X, y), (U, inverse, counts, bias, _), lr in zip(
            self.gps, self.datasets, self.groups, self.log_r, strict=True
        ):
            mu_u, var_u = gp._latent_at_training()  # at the distinct inputs, then per sample
            mu, var_f = mu_u[inverse, 0], var_u[inverse]
            if n_samples is None:
                # Squared residual over its expectation r - var_f (leverage-corrected): an
                # unbiased r(x_i) * chi2_1 draw; averaged over replicates, log-bias removed.
                frac = np.maximum(1.0 - var_f * np.exp(-lr), MIN_RESIDUAL_FRACTION)
                e = (y - mu) ** 2 / frac
                e_u = np.bincount(inverse, weights=e, minlength=U.shape[0]) / counts
                z = np.log(np.maximum(e_u, 1e-300)) - bias
                single = counts == 1
                if np.count_nonzero(single) >= MIN_SMEARING_TARGETS:  # log bias from the data
                    gap = _single_residual_log_bias(e_u[single], lo, hi)
                    z[single] = np.log(np.maximum(e_u[single], 1e-300)) + gap
            else:
                # Kersting et al.'s estimator: 0.5 (y_i - t_ij)^2, t_ij from the predictive
                # distribution of the current GP (including its noise).
                scale = np.sqrt(var_f + np.exp(lr))
                t = mu[:, None] + scale[:, None] * rng.standard_normal((X.shape[0], n_samples))
                e = np.mean(0.5 * (y[:, None] - t) ** 2, axis=1)
                e_u = np.bincount(inverse, weights=e, minlength=U.shape[0]) / counts
                z = np.log(np.maximum(e_u, 1e-300))
            targets.append(np.clip(z, lo, hi))  # a zero residual means "at the floor"
        # Step 3: z-process G2 on the log noise, one shared constant mean.
        if noise_offset is None:
            self.off = float(np.mean(np.concatenate(targets)))
        else:
            self.off = float(noise_offset)
        self.noise_gps = [
            _fit_z(
                make,
                self.zk,
                g[0],
                z - self.off,
                g[4],
                prepare=prepare,
                template=t,
                shared=None if prepare else zs,
            )
            for g, z, t, zs in zip(
                self.groups, targets, self.z_templates, self.z_shared, strict=True
            )
        ]
        self.z_templates = self.noise_gps

    def refit(self, solve: bool) -> None:
        """Step 4 with the (learnt) z-processes: ``gps`` prepared (or solved)."""
        self.zk = self.noise_gps[0].kernel_.clone()
        self.new_log_r_u = [  # z at the distinct training inputs (the z-process's own inputs)
            np.clip(zgp._latent_mean_at_training()[:, 0] + self.off, self.lo, self.hi)
            for zgp in self.noise_gps
        ]
        self.gps = [
            b._derive(self.sig, alpha=np.exp(lr), shared=fs if solve else None)
            for b, lr, fs in zip(self.base, self.new_log_r_u, self.f_shared, strict=True)
        ]
        if solve:
            for gp in self.gps:
                gp._solve()

    def end_iteration(self, tol: float) -> None:
        """The objective, the best iteration and the stopping rule (see most_likely_em)."""
        self.sig = self.gps[0].kernel_.clone()
        new_log_r = [lr[g[1]] for lr, g in zip(self.new_log_r_u, self.groups, strict=True)]
        obj = float(sum(gp.log_marginal_likelihood_value_ for gp in self.gps))
        self.objective.append(obj)
        change = max(
            float(np.max(np.abs(a - b))) for a, b in zip(new_log_r, self.log_r, strict=True)
        )
        self.log_r = new_log_r
        if obj > self.best_obj:
            self.best_obj = obj
            self.best = (self.gps, self.noise_gps, self.off, self.sig, self.zk, self.n_iter)
        step = obj - self.objective[-2]
        if change < tol or abs(step) < OBJECTIVE_TOL * self.n_total:
            self.status, self.converged, self.running = "converged", True, False
        elif step < 0:
            self.status, self.running = "objective decreased", False

    def result(self) -> EMResult:
        for cache in [*self.z_shared, *self.f_shared]:
            cache.clear()  # the fitted GPs keep no copies of intermediate matrices
        gps_b, noise_b, off_b, sig_b, zk_b, it_b = self.best
        return EMResult(
            gps_b,
            noise_b,
            off_b,
            self.homoscedastic_kernel,
            sig_b,
            zk_b,
            self.n_iter,
            self.converged,
            (self.lo, self.hi),
            self.objective,
            it_b,
            self.status,
        )


def check_method(method: Any) -> str:
    """``method`` if it is one of :data:`METHODS`, or a ValueError naming it."""
    if not isinstance(method, str) or method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return method


def fit_noise_model(
    datasets: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    kernel: Kernel,
    noise_kernel: Kernel | None,
    *,
    method: str = DEFAULT_METHOD,
    **kwargs: Any,
) -> EMResult:
    """Learn the heteroscedastic model of one or more data sets with ``method``
    (:data:`METHODS`): :func:`most_likely_em` or
    :func:`~lgp_policy.gp.variational.variational_heteroscedastic`, which take the same
    arguments (``kwargs``) and return the same :class:`EMResult`."""
    if check_method(method) == "vhgp":
        from lgp_policy.gp.variational import variational_heteroscedastic

        return variational_heteroscedastic(datasets, kernel, noise_kernel, **kwargs)
    return most_likely_em(datasets, kernel, noise_kernel, **kwargs)


CONSTANT_SCALE = 4.0 * float(np.finfo(np.float64).eps)
"""Scale of a constant output relative to its magnitude (:func:`_data_scale`): a few units in
the last place of the values, the finest variation they can carry. Rounding (a mean of many
copies of 0.35 is off by one ulp, and ``np.std`` is then 1.1e-16, not 0) stays below it, so a
constant gets this scale however its values were computed."""
MIN_DATA_SCALE = 1e-150
"""Smallest scale of an output (a column of zeros gets it): tiny, yet the square of a std
1e-3 of it (the noise floor, :data:`NOISE_BOUNDS`) is still a normal float (1e-306), so
variances and precisions derived from it stay finite and > 0."""


def _data_scale(y: NDArray[np.float64]) -> float:
    """Standard deviation of ``y``, or for a constant ``y`` a scale at its float precision.

    ``max(std(y), CONSTANT_SCALE * max|y|, MIN_DATA_SCALE)``: for a constant output the scale
    does not depend on its value beyond the values' own precision (a std proportional to the
    value, the earlier rule, gave ``c = 1e6`` a predicted std of 1.6e3 and ``c = 0`` one of
    1.4e-3, while ``1000 + 1e-3 y`` got 1e-4); any output that varies by more than a few ulps
    keeps its standard deviation.
    """
    std = float(np.std(y)) if y.size else 0.0
    mag = float(np.max(np.abs(y))) if y.size else 0.0
    return max(std, CONSTANT_SCALE * mag, MIN_DATA_SCALE)


def check_noise_bounds(noise_bounds: Any) -> tuple[float, float]:
    """``noise_bounds`` as a pair ``0 < low <= high`` of finite floats, or a ValueError."""
    try:
        lo, hi = (float(b) for b in noise_bounds)
    except (TypeError, ValueError):
        raise ValueError(
            f"noise_bounds must be a pair (low, high) of relative standard deviations, "
            f"got {noise_bounds!r}"
        ) from None
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
        raise ValueError(f"noise_bounds must satisfy 0 < low <= high, got {noise_bounds!r}")
    return lo, hi


def em_warning(status: str, where: str) -> None:
    """Emit the :class:`ConvergenceWarning` of an EM that stopped without converging."""
    warnings.warn(
        f"{where}: the heteroscedastic EM stopped without converging ({status}); the model of "
        "the iteration with the best objective (log p(y | X, R)) is kept. Raise max_em_iter or "
        "tol (method='em'), or max_iter (method='vhgp'), to silence this.",
        ConvergenceWarning,
        stacklevel=3,
    )


class HeteroscedasticGP(NoisePredictionsMixin, ParamsMixin):
    """GP with input-dependent noise ``r(x)`` learnt by most-likely EM (Kersting et al. 2007).

    Args:
        kernel: kernel of the first (homoscedastic) GP, e.g. Eq. (10); its WhiteNoise terms are
            dropped once ``R`` takes over. Default ``SquaredExponential(1, 1) + WhiteNoise(0.1)``.
        method: how the noise model is learnt, one of :data:`METHODS`: ``"em"`` (the
            most-likely EM below) or ``"vhgp"`` (the variational bound of Lazaro-Gredilla &
            Titsias 2011, :mod:`lgp_policy.gp.variational`; ``max_iter`` then bounds its
            L-BFGS iterations and ``max_em_iter``, ``tol``, ``n_samples`` are unused). Default
            :data:`DEFAULT_METHOD`.
        noise_kernel: kernel of the z-process (log noise). Default
            (``None``): :func:`default_noise_kernel`, built from the fitted signal length scale.
        noise_bounds: ``(low, high)`` bounds of the noise standard deviation ``sqrt(r(x))``
            relative to the standard deviation of ``y`` (default :data:`NOISE_BOUNDS`). Every
            predicted std therefore lies in ``[low, sqrt(v_max + high^2)]`` times ``std(y)``,
            ``v_max`` the upper bound of the signal variance (normalised units).
        optimizer, n_restarts, max_iter, collapse_replicates: as in
            :class:`~lgp_policy.gp.GaussianProcess`, for both GPs.
        normalize_y: standardise ``y`` first; ``r(x)`` is reported in units of ``y``.
        max_em_iter: most EM iterations (step 2-4 above).
        tol: stop when ``max |delta log r(x_i)|`` falls below this.
        n_samples: ``None`` (default): leverage-corrected squared residuals (module docstring);
            an int: Kersting et al.'s estimator with that many samples from ``random_state``.
        random_state: seed for restarts and samples.

    ``optimizer=None`` keeps both kernels as given (no hyperparameter learning in the EM).
    Duplicated inputs are replicates (see :class:`~lgp_policy.gp.GaussianProcess`); the noise
    estimate at an input averages its replicates. Multiple targets are fitted as independent
    models (one noise process each), kept in ``estimators_`` (``None`` for a single target).
    An EM that stops without converging keeps its best iteration and records why in
    ``em_status_``: "objective decreased" (it has passed its best iteration, the usual end of
    this non-monotone EM) or "max_em_iter reached", which also emits a
    :class:`ConvergenceWarning`.

    Attributes:
        gp_: final GP of ``f`` with ``alpha = r(x_i)`` (normalised units); the homoscedastic GP
            of step 1 when no EM iteration improved on it.
        noise_gp_: the z-process, fitted to ``log r - noise_offset_`` (``None`` when the
            homoscedastic GP was kept: ``r`` is then the constant ``exp(noise_offset_)``).
        homoscedastic_kernel_: the kernel of step 1 after fitting.
        n_iter_, converged_: EM iterations run and whether ``tol`` was met.
        em_objective_: the objective after each iteration (index 0: homoscedastic GP).
        em_best_iter_: the iteration kept. ``em_status_``: why the EM stopped.
        log_noise_bounds_: bounds of ``log r`` in normalised units.
    """

    estimators_: list[HeteroscedasticGP] | None

    def __init__(
        self,
        kernel: Kernel | None = None,
        *,
        method: str = DEFAULT_METHOD,
        noise_kernel: Kernel | None = None,
        noise_bounds: tuple[float, float] = NOISE_BOUNDS,
        optimizer: Optimizer = "L-BFGS-B",
        n_restarts: int = 0,
        normalize_y: bool = True,
        max_em_iter: int = MAX_EM_ITER,
        tol: float = 0.05,
        n_samples: int | None = None,
        collapse_replicates: bool = True,
        max_iter: int = 200,
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.kernel = kernel
        self.method = method
        self.noise_kernel = noise_kernel
        self.noise_bounds = noise_bounds
        self.optimizer = optimizer
        self.n_restarts = n_restarts
        self.normalize_y = normalize_y
        self.max_em_iter = max_em_iter
        self.tol = tol
        self.n_samples = n_samples
        self.collapse_replicates = collapse_replicates
        self.max_iter = max_iter
        self.random_state = random_state

    def _check_params(self) -> None:
        if not isinstance(self.max_em_iter, (int, np.integer)) or self.max_em_iter < 1:
            raise ValueError(f"max_em_iter must be a positive int, got {self.max_em_iter!r}")
        if not np.isfinite(self.tol) or self.tol <= 0:
            raise ValueError(f"tol must be positive, got {self.tol!r}")
        if self.n_samples is not None and (
            not isinstance(self.n_samples, (int, np.integer)) or self.n_samples < 1
        ):
            raise ValueError(f"n_samples must be None or a positive int, got {self.n_samples!r}")
        check_noise_bounds(self.noise_bounds)
        check_method(self.method)

    @with_single_blas_thread
    def fit(self, X: ArrayLike, y: ArrayLike) -> HeteroscedasticGP:
        """Fit to ``X (n_samples, n_features)``, ``y (n_samples,)`` or ``(n_samples, n_targets)``.

        Returns:
            self
        """
        X, y = check_X_y(X, y)
        self._check_params()
        self.n_features_in_ = X.shape[1]
        self.X_train_, self.y_train_ = X, y
        rng = check_random_state(self.random_state)
        self._single_target = y.ndim == 1
        if y.ndim == 2 and y.shape[1] > 1:
            params = self.get_params(deep=False)
            self.estimators_ = []
            for j in range(y.shape[1]):
                params["random_state"] = rng
                self.estimators_.append(HeteroscedasticGP(**params).fit(X, y[:, j]))
            return self
        self.estimators_ = None
        self._fit_single(X, y.reshape(-1), rng)
        return self

    def _fit_single(self, X, y, rng: np.random.Generator) -> None:
        scale = _data_scale(y)
        if self.normalize_y:
            self._y_mean, self._y_std, work = float(y.mean()), scale, 1.0
        else:
            self._y_mean, self._y_std, work = 0.0, 1.0, scale
        yn = (y - self._y_mean) / self._y_std
        lo, hi = check_noise_bounds(self.noise_bounds)
        if self.kernel is None:  # length scale between the spacing and half the span of X
            kernel = bound_length_scale(default_kernel(), [X], input_span(X))
        else:
            kernel = self.kernel
        result = fit_noise_model(
            [(X, yn)],
            kernel,
            self.noise_kernel,
            method=self.method,
            learn=self.optimizer is not None,
            optimizer=self.optimizer,
            n_restarts=self.n_restarts,
            max_em_iter=self.max_em_iter,
            tol=self.tol,
            n_samples=self.n_samples,
            collapse_replicates=self.collapse_replicates,
            max_iter=self.max_iter,
            random_state=rng,
            log_noise_bounds=(2 * math.log(lo * work), 2 * math.log(hi * work)),
        )
        self._set_state(result, 0)
        if result.status in STOPPED_EARLY:
            em_warning(result.status, type(self).__name__)

    def _set_state(self, result: EMResult, index: int) -> None:
        self.gp_ = result.gps[index]
        self.noise_gp_ = result.noise_gps[index]
        self.noise_offset_ = float(result.noise_offset)
        self.homoscedastic_kernel_ = result.homoscedastic_kernel
        self.n_iter_ = result.n_iter
        self.converged_ = result.converged
        self.em_objective_ = list(result.objective)
        self.em_best_iter_ = result.best_iter
        self.em_status_ = result.status
        self.log_noise_bounds_ = result.log_noise_bounds
        self._lognormal_noise = result.lognormal_noise

    @classmethod
    def _from_em(
        cls, result: EMResult, index: int, X, y, y_mean: float, y_std: float, **params: Any
    ) -> HeteroscedasticGP:
        """A fitted instance from group EM output (used by LocalGP)."""
        model = cls(**params)
        model.n_features_in_ = X.shape[1]
        model.X_train_, model.y_train_ = X, y
        model._single_target = True
        model.estimators_ = None
        model._y_mean, model._y_std = y_mean, y_std
        model._set_state(result, index)
        return model

    # ---------------------------------------------------------------- inference
    def _check_fitted(self) -> None:
        if not hasattr(self, "estimators_"):
            raise ValueError(f"This {type(self).__name__} is not fitted yet; call fit(X, y) first")

    def _log_noise_normalized(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        """``log r(X)`` in normalised units, within ``log_noise_bounds_`` (never overflows)."""
        if self.noise_gp_ is None:
            return np.full(X.shape[0], self.noise_offset_)
        if getattr(self, "_lognormal_noise", False):  # E[exp(z*)], z* ~ N(mean, var)
            mean, std = self.noise_gp_.predict(X, return_std=True)
            z = mean + 0.5 * std**2
        else:
            z = self.noise_gp_.predict(X)
        return np.clip(z + self.noise_offset_, *self.log_noise_bounds_)

    def _predict_normalized(self, X: NDArray[np.float64]):
        """Latent mean ``(n,)``, latent variance ``(n,)`` and r(x) ``(n,)``, normalised units."""
        mean, var = self.gp_._predict_normalized(X)
        return mean[:, 0], var, np.exp(self._log_noise_normalized(X))

    def log_marginal_likelihood(self, theta: ArrayLike | None = None, eval_gradient: bool = False):
        """Eq. (4) of the final GP (signal hyperparameters ``theta``, noise ``R`` fixed)."""
        self._check_fitted()
        if self.estimators_:
            if theta is not None or eval_gradient:
                raise ValueError("theta/eval_gradient need a single-target model")
            return float(sum(e.log_marginal_likelihood() for e in self.estimators_))
        return self.gp_.log_marginal_likelihood(theta, eval_gradient)

    @property
    def kernel_(self) -> Kernel:
        """The fitted signal kernel of ``f`` (single target)."""
        self._check_fitted()
        if self.estimators_:
            raise AttributeError("kernel_ is per target: see estimators_[j].kernel_")
        return self.gp_.kernel_
