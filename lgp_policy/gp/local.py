"""Local Gaussian processes (paper Sec. II-C, Algorithms 1 and 2, Eqs. 8-9).

:class:`LocalGP` clusters the inputs by covariance (Algorithm 1), fits one exact or
heteroscedastic GP per cluster, and combines the local predictions (Algorithm 2).

Assignment (Algorithm 1). A point ``x`` joins the model whose centre ``c`` has the highest
normalised covariance ``w = k(x, c) / sqrt(k(x, x) k(c, c))`` (for the squared exponential,
``exp(-|x - c|^2 / (2 l^2))``, in ``(0, 1]``) if ``w > threshold``; otherwise it opens a new model
at ``x``. Centres are the running means of their points. The signal part of ``kernel`` with its
*initial* hyperparameters defines ``w``. A model holding ``max_points`` distinct inputs no longer
accepts new inputs (the next one opens a new model). Replicates (the same input in several
demonstrations) are solved exactly on their distinct inputs (see :mod:`lgp_policy.gp.exact`)
and cost nothing extra, so the cap bounds a model's cost at ``O(max_points^3)`` and keeps the
whole fit near-linear in ``n``. Points are visited in the lexicographic order of ``X``
(``order="sorted"``, the default): for the 1-D time input of learning from demonstration this puts
the replicates of all demonstrations at one time step into the same model and makes the models
contiguous time windows; for sorted 1-D inputs and a squared-exponential kernel the assignment runs
in O(n) (same result as the general loop, tested). ``order="given"`` runs Algorithm 1 in the
data's order as in the paper (replicates count once per consecutive run there). All of this runs on
``X / input_scale_`` (see "Input units" below).

Hyperparameters. ``hyperparameters="shared"`` (default): one set of kernel (and z-process)
hyperparameters for all local models, learnt by maximising the *sum* of the log marginal
likelihoods of a few data sets (the product-of-experts likelihood, Deisenroth & Ng 2015): every
local model with all its data where there are at most ``n_shared_models`` of them with at most
``shared_points`` distinct inputs each; otherwise the local models split into
``SHARED_BLOCKS`` (4) contiguous runs (for sorted 1-D inputs: consecutive windows), each run's
data thinned to at most ``shared_points`` distinct inputs (every k-th, with its replicates), so
that learning costs the same for any ``n``. Each run spans several windows: a length scale
longer than one window cannot be identified from that window (learnt from single thinned
windows, LASA handwriting demonstrations in a start-point frame got 0.09 s where the same data
in the world frame got 0.84 s, and the mean followed every demonstration that ended). Every
local model then runs (its heteroscedastic EM) with the hyperparameters fixed, and keeps the
learnt kernel of ``f``: a local EM whose homoscedastic start (another kernel of ``f``) had the
higher objective used to keep that start, and the mixture then compared latent variances under
two priors (see ``_em_models``).
``hyperparameters="local"`` (the paper's choice, Sec. IV: "individual parameterization and
optimization"): every local model maximises its own log marginal likelihood from ``kernel``; with
narrow local windows the individual estimates become unreliable (a window shorter than a length
scale cannot identify it), which is why it is not the default. ``hyperparameters="fixed"``:
``kernel`` as given. The targets are standardised once globally (``normalize_y``), so every local
model has the same zero-mean prior as the global GP.

Combination (Algorithm 2). Local *latent* (noise-free) predictions ``N(mu_l, v_l)`` are combined
and the noise ``r(x)`` is added afterwards. Multiplying the noisy predictive distributions instead
double-counts the noise and gives 95% coverage far below 0.95 (``combine_noisy=True`` reproduces
that behaviour for comparison). Rules:

* ``"product"``: Eqs. (8)-(9), ``v = (sum_l 1/v_l)^-1``, ``mu = v sum_l mu_l / v_l``, over all
  models (a model far from ``x`` contributes its prior; over-confident where models overlap and
  pulled towards the prior by the many far models);
* ``"rbcm"``: robust Bayesian committee machine (Deisenroth & Ng 2015) with
  ``beta_l = (log s_l^2 - log v_l) / 2``, ``s_l^2`` the prior variance; note that with a single
  model it does not reduce to that model (``beta != 1``), and its latent variance is smaller than
  the best model's where ``beta > 1``;
* ``"nearest"`` (default, the calibrated rule): moment-matched mixture of the ``n_neighbors``
  models with the highest ``w(x)``, weights ``pi_l ~ (w_l(x) - w_next(x)) / v_l(x)``, ``w_next``
  the highest ``w`` of the models left out (``_taper``): a model's weight reaches 0 where it
  leaves the selection, so mean and variance are continuous in ``x``; with one model it is that
  model; its cost does not grow with the number of models.

The noise is ``r(x) = sum_l rho_l(x) r_l(x)``: the noise function of the model whose training
inputs surround ``x``, blended with its neighbours over ``NOISE_BLEND`` (a twentieth) of a
window's width beyond its training inputs, each evaluated at the nearest point of its own window
(``LocalGP._noise_weights``). Neighbouring noise functions are estimated from different data
and can disagree at their common edge (on the LASA handwriting set by up to half the data's
range); the blend spreads that over a twentieth of a window instead of one input spacing. On
distinct inputs each noise function is also refitted on the other windows' single-residual
log-noise targets within ``NOISE_SHARE`` (a quarter) of its window beyond its inputs
(``_share_noise_targets``), so that neighbours estimate the noise at their edge from the same
data; a replicated grid keeps each window's own targets.

Length-scale bounds. With the default kernel, a search (the shared one, or each local model's
with ``hyperparameters="local"``) cannot take the squared exponential's length scale below the
median spacing of the inputs that learn it (the thinned subsets, or the model's own inputs):
shorter, it is white noise on those inputs, which cannot identify it, while on the denser full
data it interpolates single points. Nor can it go above half the span of all the training inputs:
longer, the heteroscedastic noise absorbs the mean's motion ("all noise"), every window becomes a
constant and the mean steps between them
(:func:`~lgp_policy.gp.heteroscedastic.bound_length_scale`). An explicit kernel's bounds are
used as given.

Input units (``input_scale``). Everything above runs on ``X / input_scale_`` (one divisor per
feature): the kernel's starting values and bounds, and with them Algorithm 1's radius, are read in
those units. The default kernel's starting length scale 1 assumes inputs on a unit scale; time in
milliseconds made every time step its own local model. ``input_scale="auto"`` (default) rescales
by powers of 1000 (an SI prefix), chosen per feature so that the feature's span
``max(x) - min(x)`` lies in ``UNIT_SPAN = [1000**-0.5, 1000**0.5)`` (about ``[0.032, 31.6)``);
a feature already in that band is used as given (divisor exactly 1: the same bits as without the
rule), as is a constant feature. Inputs in ms, us or ns therefore give the model of the same
inputs in seconds (same local models, same predictions to rounding); rescaling by other factors
within the band (seconds against minutes) still changes the starting point. ``"auto"`` rescales
only with the default kernels (``kernel`` and ``noise_kernel`` ``None``): an explicit kernel's
length scales and bounds are in the input's own units and are used as given (divisor 1). A number
or a per-feature array sets the divisor (``1.0``: the input as given). ``centers_`` and
``X_train_`` are in input units; the local ``models_`` are fitted on ``X / input_scale_``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lgp_policy.gp._base import NoisePredictionsMixin, ParamsMixin
from lgp_policy.gp._threads import with_single_blas_thread
from lgp_policy.gp._validation import check_random_state, check_X_y
from lgp_policy.gp.exact import (
    GaussianProcess,
    Optimizer,
    default_kernel,
    fit_shared_hyperparameters,
    unique_rows,
)
from lgp_policy.gp.heteroscedastic import (
    DEFAULT_METHOD,
    MAX_EM_ITER,
    NOISE_BOUNDS,
    STOPPED_EARLY,
    HeteroscedasticGP,
    _data_scale,
    bound_length_scale,
    check_method,
    check_noise_bounds,
    em_warning,
    fit_noise_model,
    fixed_gp,
    input_span,
    most_likely_em_many,
    signal_kernel,
)
from lgp_policy.gp.kernels import Kernel, SquaredExponential

__all__ = ["COMBINE_RULES", "DEFAULT_COMBINE", "UNIT_SPAN", "LocalGP", "auto_input_scale"]

COMBINE_RULES = ("product", "rbcm", "nearest")

DEFAULT_COMBINE = "nearest"
"""The one default combination rule of :class:`LocalGP`, ``DemonstrationEncoder`` and the GP
policy. Measured (``benchmarks/gp_quality.py``, ``docs/design-gp.md``): on leave-one-
demonstration-out the three rules give the same RMSE and NLPD to within 0.01-0.1, and the
same coverage; ``"nearest"`` is the one whose latent variance is calibrated where models
overlap (``"product"`` is over-confident there, ``"rbcm"`` too where ``beta > 1``), that reduces
to the single model where only one is near, and whose cost does not grow with the number of
models."""

#: Test points farther than this many length scales from a model's data skip that model.
SKIP_DISTANCE = 9.0

#: The local noise functions are blended over this fraction of a model's window (per feature,
#: at least one input spacing) beyond its training inputs (``LocalGP._noise_weights``).
NOISE_BLEND = 0.05

#: A local noise function also learns from the other models' single-residual log-noise targets
#: up to this fraction of its window's width (per feature) beyond its training inputs
#: (``_share_noise_targets``).
NOISE_SHARE = 0.25

#: Where the shared hyperparameters cannot be learnt from every local model with all its data,
#: they are learnt from this many contiguous runs of local models, each thinned
#: (``LocalGP._shared_data``).
SHARED_BLOCKS = 4

#: ``input_scale="auto"`` rescales a feature by powers of this base (an SI prefix step).
INPUT_SCALE_BASE = 1000.0

#: Spans ``max(x) - min(x)`` that ``input_scale="auto"`` uses as given: one factor
#: ``INPUT_SCALE_BASE`` wide, centred (geometrically) on 1; it holds the unit-scale inputs of
#: the package (phase in [0, 1], time in [0, 10] s).
UNIT_SPAN = (INPUT_SCALE_BASE**-0.5, INPUT_SCALE_BASE**0.5)


def auto_input_scale(X: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per-feature divisors of ``input_scale="auto"``: ``INPUT_SCALE_BASE**k`` with the integer
    ``k`` that puts the span ``ptp(X[:, j]) / divisor`` into ``UNIT_SPAN`` (exactly 1 for a span
    already there and for a constant feature). Rescaling ``X`` by a power of the base rescales
    the divisors by it, so that ``X / divisor`` stays the same (to rounding)."""
    span = np.ptp(np.asarray(X, dtype=np.float64), axis=0)
    k = np.zeros(span.shape)
    positive = span > 0.0
    k[positive] = np.floor(np.log10(span[positive]) / math.log10(INPUT_SCALE_BASE) + 0.5)
    return np.power(INPUT_SCALE_BASE, k)


class LocalGP(NoisePredictionsMixin, ParamsMixin):
    """Local (heteroscedastic) GP regression, Algorithms 1 and 2 of the paper.

    Args:
        kernel: kernel of every local model (Eq. 10). Default
            ``SquaredExponential(1, 1) + WhiteNoise(0.1)``. Its signal part, with the initial
            hyperparameters, also defines the assignment weight ``w``. Its length scales are in
            units of ``X / input_scale_`` (the input's own units unless ``input_scale`` is set).
        threshold: minimum weight ``w`` in ``(0, 1)`` for joining an existing model.
        max_points: most distinct training inputs per local model (replicates are free).
        local_model: ``"heteroscedastic"`` (:class:`HeteroscedasticGP`) or ``"exact"``
            (:class:`GaussianProcess`).
        method: how heteroscedastic local models learn their noise, one of
            :data:`lgp_policy.gp.heteroscedastic.METHODS` (``"em"``: most-likely EM, ``"vhgp"``:
            variational bound); default :data:`~lgp_policy.gp.heteroscedastic.DEFAULT_METHOD`.
        combine: ``"product"`` (Eqs. 8-9), ``"rbcm"`` or ``"nearest"`` (see module docstring).
        combine_noisy: combine the noisy predictive distributions (the known trap; for
            comparison only).
        hyperparameters: ``"shared"`` (default), ``"local"`` or ``"fixed"`` (module docstring).
        n_shared_models: most local models that learn shared hyperparameters each with all
            their data; with more models, or more than ``shared_points`` distinct inputs in
            one, :data:`SHARED_BLOCKS` thinned runs of models learn them (module docstring).
        shared_points: most distinct inputs per data set that learns them (every k-th).
        n_neighbors: how many models (highest ``w``) the ``"nearest"`` rule mixes.
        order: ``"sorted"`` or ``"given"``: the order Algorithm 1 visits the points in.
        noise_kernel: z-process kernel of heteroscedastic local models (``None``: the bounded
            default of :func:`~lgp_policy.gp.heteroscedastic.default_noise_kernel`).
        noise_bounds: bounds of the local models' noise std relative to ``std(y)``
            (:data:`~lgp_policy.gp.heteroscedastic.NOISE_BOUNDS`).
        optimizer, n_restarts, max_em_iter: passed to the local models.
        normalize_y: standardise ``y`` globally before fitting.
        input_scale: ``"auto"``, a positive number or ``(n_features,)`` positive numbers: the
            models run on ``X / input_scale_``, and the kernels' length scales (starting values
            and bounds) are read in those units (module docstring, "Input units"). ``"auto"``:
            powers of 1000 that bring each feature's span into :data:`UNIT_SPAN`
            (:func:`auto_input_scale`) with the default kernels, 1 with an explicit ``kernel``
            or ``noise_kernel``.
        random_state: seed for the local models.

    Attributes:
        input_scale_: ``(n_features,)`` the divisors of the inputs (1: used as given).
        centers_: ``(n_models, n_features)`` centres in input units.
        assignments_: ``(n_samples,)`` index of the model each training point belongs to.
        models_: the fitted local models (:class:`GaussianProcess` or
            :class:`HeteroscedasticGP`), fitted to ``X / input_scale_`` and globally
            standardised targets.
        estimators_: ``None``, or for heteroscedastic local models and a 2-D ``y`` one
            independent ``LocalGP`` per target (same ``centers_`` and ``assignments_``);
            ``models_`` is then a list (per target) of lists.
    """

    input_scale_: NDArray[np.float64]
    centers_: NDArray[np.float64]
    assignments_: NDArray[np.int64]
    models_: list[Any]
    estimators_: list[LocalGP] | None
    _assign_kernel: Kernel
    _unit_input: bool
    _X_fit: NDArray[np.float64]
    _centres: NDArray[np.float64]

    def __init__(
        self,
        kernel: Kernel | None = None,
        *,
        threshold: float = 0.5,
        max_points: int = 400,
        local_model: str = "heteroscedastic",
        method: str = DEFAULT_METHOD,
        combine: str = DEFAULT_COMBINE,
        combine_noisy: bool = False,
        hyperparameters: str = "shared",
        n_shared_models: int = 8,
        shared_points: int = 100,
        n_neighbors: int = 3,
        order: str = "sorted",
        noise_kernel: Kernel | None = None,
        noise_bounds: tuple[float, float] = NOISE_BOUNDS,
        optimizer: Optimizer = "L-BFGS-B",
        n_restarts: int = 0,
        max_em_iter: int = MAX_EM_ITER,
        normalize_y: bool = True,
        input_scale: str | float | ArrayLike = "auto",
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.kernel = kernel
        self.threshold = threshold
        self.max_points = max_points
        self.local_model = local_model
        self.method = method
        self.combine = combine
        self.combine_noisy = combine_noisy
        self.hyperparameters = hyperparameters
        self.n_shared_models = n_shared_models
        self.shared_points = shared_points
        self.n_neighbors = n_neighbors
        self.order = order
        self.noise_kernel = noise_kernel
        self.noise_bounds = noise_bounds
        self.optimizer = optimizer
        self.n_restarts = n_restarts
        self.max_em_iter = max_em_iter
        self.normalize_y = normalize_y
        self.input_scale = input_scale
        self.random_state = random_state

    def _check_params(self) -> None:
        if not (np.isscalar(self.threshold) and 0.0 < float(self.threshold) < 1.0):  # type: ignore[arg-type]
            raise ValueError(f"threshold must be in (0, 1), got {self.threshold!r}")
        if not isinstance(self.max_points, (int, np.integer)) or self.max_points < 2:
            raise ValueError(f"max_points must be an int >= 2, got {self.max_points!r}")
        if self.local_model not in ("heteroscedastic", "exact"):
            raise ValueError(
                f"local_model must be 'heteroscedastic' or 'exact', got {self.local_model!r}"
            )
        if self.combine not in COMBINE_RULES:
            raise ValueError(f"combine must be one of {COMBINE_RULES}, got {self.combine!r}")
        if self.hyperparameters not in ("shared", "local", "fixed"):
            raise ValueError(
                "hyperparameters must be 'shared', 'local' or 'fixed', "
                f"got {self.hyperparameters!r}"
            )
        for name in ("shared_points", "n_neighbors"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < (
                2 if name == "shared_points" else 1
            ):
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        if not isinstance(self.n_shared_models, (int, np.integer)) or self.n_shared_models < 1:
            raise ValueError(
                f"n_shared_models must be a positive int, got {self.n_shared_models!r}"
            )
        if self.order not in ("sorted", "given"):
            raise ValueError(f"order must be 'sorted' or 'given', got {self.order!r}")
        check_noise_bounds(self.noise_bounds)
        check_method(self.method)
        self._given_input_scale()

    def _given_input_scale(self) -> NDArray[np.float64] | None:
        """``input_scale`` as a 1-D array of positive divisors, or ``None`` for ``"auto"``."""
        value = self.input_scale
        if isinstance(value, str) and value == "auto":
            return None
        try:
            if isinstance(value, str):
                raise ValueError
            scale = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            scale = np.array([np.nan])
        if scale.ndim > 1 or scale.size == 0 or not np.all(np.isfinite(scale) & (scale > 0.0)):
            raise ValueError(
                "input_scale must be 'auto', a positive number or a 1-D array of positive "
                f"numbers, got {value!r}"
            )
        return scale.reshape(-1)

    def _input_scale(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        """The divisors of the inputs, ``(n_features,)`` (module docstring, "Input units")."""
        d = X.shape[1]
        scale = self._given_input_scale()
        if scale is None:
            if self.kernel is None and self.noise_kernel is None:
                return auto_input_scale(X)
            return np.ones(d)
        if scale.size == 1:
            return np.full(d, scale[0])
        if scale.size != d:
            raise ValueError(f"input_scale has {scale.size} entries but X has {d} features")
        return scale

    def _scaled(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        """``X / input_scale_``: the units the local models and the clustering work in (``X``
        itself where every divisor is 1)."""
        if self._unit_input:
            return X
        return X / self.input_scale_

    # ------------------------------------------------------------- Algorithm 1
    def _weights(self, X: NDArray[np.float64], C: NDArray[np.float64]) -> NDArray[np.float64]:
        """Log of the normalised covariance ``w`` between rows of X and centres C, (n, L)."""
        k = self._assign_kernel
        if isinstance(k, SquaredExponential):
            ls = np.asarray(k.length_scale)
            Xs, Cs = X / ls, C / ls
            d2 = np.sum(Xs**2, 1)[:, None] + np.sum(Cs**2, 1)[None, :] - 2.0 * Xs @ Cs.T
            return -0.5 * np.maximum(d2, 0.0)
        Kxc = k(X, C)
        norm = np.sqrt(np.outer(k.diag(X), k.diag(C)))
        return np.log(np.maximum(Kxc / norm, 1e-300))

    def _assign(self, X: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        n = X.shape[0]
        if self.order == "sorted":
            visit = np.lexsort(X.T[::-1])
        else:
            visit = np.arange(n)
        # Replicates (identical inputs visited consecutively) are assigned as one group: the
        # first joins a model and moves its centre onto x, so the rest follow it (Algorithm 1).
        Xv = X[visit]
        new_group = np.ones(n, dtype=bool)
        new_group[1:] = np.any(Xv[1:] != Xv[:-1], axis=1)
        starts = np.flatnonzero(new_group)
        sizes = np.diff(np.append(starts, n))
        if (
            self.order == "sorted"
            and X.shape[1] == 1
            and isinstance(self._assign_kernel, SquaredExponential)
        ):
            centres_1d, model_of_group = self._assign_sorted_1d(Xv[starts, 0], sizes)
            assignments = np.empty(n, dtype=np.int64)
            assignments[visit] = np.repeat(model_of_group, sizes)
            return centres_1d[:, None], assignments
        log_thr = np.log(self.threshold)
        centres = np.empty((0, X.shape[1]))
        sums: list[NDArray[np.float64]] = []
        counts: list[int] = []
        n_distinct: list[int] = []
        model_of_group = np.empty(starts.shape[0], dtype=np.int64)
        centre_arr = np.empty((max(1, starts.shape[0]), X.shape[1]))
        n_models = 0
        cap = self.max_points
        for g, (s, m) in enumerate(zip(starts, sizes, strict=True)):
            x = Xv[s]
            p = -1
            if n_models:
                centres = centre_arr[:n_models]
                logw = self._weights(x[None, :], centres)[0]  # Algorithm 1, line 6
                full = np.asarray(n_distinct) >= cap  # a full model takes no new input
                logw[full] = -np.inf
                best = int(np.argmax(logw))  # line 10
                if logw[best] > log_thr:  # line 11
                    p = best
            if p < 0:  # lines 17-19: new model at x
                p = n_models
                n_models += 1
                sums.append(np.zeros(X.shape[1]))
                counts.append(0)
                n_distinct.append(0)
            sums[p] = sums[p] + m * x  # line 13
            counts[p] += m
            n_distinct[p] += 1
            centre_arr[p] = sums[p] / counts[p]  # line 15: centre = mean
            model_of_group[g] = p
        assignments = np.empty(n, dtype=np.int64)
        assignments[visit] = np.repeat(model_of_group, sizes)
        return centre_arr[:n_models].copy(), assignments

    def _assign_sorted_1d(
        self, x: NDArray[np.float64], sizes: NDArray[np.int64]
    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Algorithm 1 for increasing 1-D inputs ``x`` (distinct), replicate group ``sizes``.

        Same result as the general loop, in O(n) time: with increasing inputs every centre is
        at most the current input, so a model whose centre lies farther than the threshold
        radius behind it can never be chosen again and is dropped from the candidates.
        """
        ls = float(np.asarray(self._assign_kernel.length_scale).reshape(-1)[0])  # type: ignore[attr-defined]
        radius = float(np.sqrt(-2.0 * np.log(self.threshold))) * ls  # w > threshold inside
        cap = self.max_points
        centres: list[float] = []
        sums: list[float] = []
        counts: list[int] = []
        n_distinct: list[int] = []
        active: list[int] = []  # candidate models, in index order
        model_of_group = np.empty(x.shape[0], dtype=np.int64)
        for g, (xg, m) in enumerate(zip(x.tolist(), sizes.tolist(), strict=True)):
            active = [p for p in active if xg - centres[p] < radius]
            best, best_d = -1, radius
            for p in active:  # Algorithm 1, lines 5-11 (highest w = smallest distance)
                d = xg - centres[p]
                if d < best_d and n_distinct[p] < cap:
                    best, best_d = p, d
            if best < 0:  # lines 17-19: new model at x
                best = len(centres)
                centres.append(xg)
                sums.append(0.0)
                counts.append(0)
                n_distinct.append(0)
                active.append(best)
            sums[best] += m * xg  # line 13
            counts[best] += m
            n_distinct[best] += 1
            centres[best] = sums[best] / counts[best]  # line 15: centre = mean
            model_of_group[g] = best
        return np.asarray(centres), model_of_group

    # ---------------------------------------------------------------- fitting
    @with_single_blas_thread
    def fit(self, X: ArrayLike, y: ArrayLike) -> LocalGP:
        """Cluster (Algorithm 1) and fit one GP per cluster. Returns ``self``.

        ``X (n_samples, n_features)``, ``y (n_samples,)`` or ``(n_samples, n_targets)``.
        """
        X, y = check_X_y(X, y)
        self._check_params()
        self.estimators_ = None
        if self.local_model == "heteroscedastic" and y.ndim == 2:
            # One noise process per output: an independent LocalGP per column (same clusters).
            rng = check_random_state(self.random_state)
            params = {**self.get_params(deep=False), "random_state": rng}
            self.estimators_ = [LocalGP(**params) for _ in range(y.shape[1])]
            if self.method == "em" and self.hyperparameters == "shared" and self.optimizer:
                _fit_columns_in_lockstep(self.estimators_, X, y)
            else:
                for j, e in enumerate(self.estimators_):
                    e.fit(X, y[:, j])
            first: LocalGP = self.estimators_[0]
            self.X_train_, self.y_train_ = X, y
            self.n_features_in_ = X.shape[1]
            self.input_scale_ = first.input_scale_
            self.centers_, self.assignments_ = first.centers_, first.assignments_
            self.models_ = [e.models_ for e in self.estimators_]
            return self
        kernel, Xs, Yn, index_sets, rng = self._begin(X, y)
        # Algorithm 1, lines 22-25: one GP per local data set.
        if self.local_model == "exact":
            self.models_ = self._fit_exact(kernel, Xs, Yn, index_sets, rng)
        else:
            self.models_ = self._fit_heteroscedastic(kernel, Xs, Yn[:, 0], index_sets, rng)
        self._prepare_prediction()
        return self

    def _begin(self, X, y):
        """``fit`` up to the local models: normalisation, Algorithm 1 and the local index sets.
        Returns ``(kernel, Xs, Yn, index_sets, rng)``, ``Xs = X / input_scale_`` (the models'
        inputs)."""
        kernel = default_kernel() if self.kernel is None else self.kernel
        self._assign_kernel = signal_kernel(kernel)
        self._single_target = y.ndim == 1
        Y = y[:, None] if self._single_target else y
        if self.normalize_y:
            self._y_mean = Y.mean(axis=0)
            self._y_std = np.array([_data_scale(Y[:, j]) for j in range(Y.shape[1])])
        else:
            self._y_mean, self._y_std = np.zeros(Y.shape[1]), np.ones(Y.shape[1])
        Yn = (Y - self._y_mean) / self._y_std
        self.X_train_, self.y_train_ = X, y
        self.n_features_in_ = X.shape[1]
        self.input_scale_ = self._input_scale(X)
        self._unit_input = bool(np.all(self.input_scale_ == 1.0))
        Xs = self._X_fit = self._scaled(X)
        self._centres, self.assignments_ = self._assign(Xs)  # Algorithm 1, lines 1-21
        self.centers_ = self._centres if self._unit_input else self._centres * self.input_scale_
        rng = check_random_state(self.random_state)
        n_models = self._centres.shape[0]
        order = np.argsort(self.assignments_, kind="stable")
        splits = np.cumsum(np.bincount(self.assignments_, minlength=n_models))[:-1]
        index_sets = []
        for idx in np.split(order, splits):
            if idx.shape[0] < 2:  # a lone point: duplicate it (an exact replicate)
                idx = np.repeat(idx, 2)
            index_sets.append(idx)
        self._index_sets = index_sets
        return kernel, Xs, Yn, index_sets, rng

    def _shared_data(self, X, index_sets) -> tuple[list[NDArray[np.int64]], bool]:
        """Index sets that learn the shared hyperparameters, and whether they are complete.

        Complete: at most ``n_shared_models`` local models, none with more than
        ``shared_points`` distinct inputs: one set per model, all its data. Otherwise the models
        in :data:`SHARED_BLOCKS` contiguous runs (Algorithm 1's order: consecutive windows of
        sorted 1-D inputs), each run's data thinned to at most ``shared_points`` distinct
        inputs (every k-th, with all its replicates), so that every set spans a stretch of
        several windows and together they span all the data.
        """
        n_models = len(index_sets)
        if n_models <= self.n_shared_models:
            subsets = [np.asarray(idx) for idx in index_sets]
            if all(unique_rows(X[idx])[0].shape[0] <= self.shared_points for idx in subsets):
                return subsets, True
        subsets = []
        for run in np.array_split(np.arange(n_models), min(SHARED_BLOCKS, n_models)):
            idx = np.concatenate([index_sets[i] for i in run])
            _, inverse, _ = unique_rows(X[idx])
            step = int(np.ceil((int(inverse.max()) + 1) / self.shared_points))
            if step > 1:
                keep = (inverse % step) == 0
                idx = idx[keep] if np.count_nonzero(keep) >= 2 else idx
            subsets.append(idx)
        return subsets, False

    def _fit_exact(self, kernel, X, Yn, index_sets, rng) -> list[GaussianProcess]:
        target = (lambda idx: Yn[idx, 0]) if self._single_target else (lambda idx: Yn[idx])
        if self.hyperparameters == "shared" and self.optimizer is not None:
            subsets, _ = self._shared_data(X, index_sets)
            kernel = self._learning_kernel(kernel, [X[i] for i in subsets])
            learners = [
                GaussianProcess(kernel, optimizer=None, normalize_y=False).fit(X[i], target(i))
                for i in subsets
            ]
            fit_shared_hyperparameters(
                learners, optimizer=self.optimizer, n_restarts=self.n_restarts, random_state=rng
            )
            kernel = learners[0].kernel_
        local_opt = self.optimizer if self.hyperparameters == "local" else None
        return [
            GaussianProcess(
                kernel if local_opt is None else self._learning_kernel(kernel, [X[idx]]),
                optimizer=local_opt,
                n_restarts=self.n_restarts,
                normalize_y=False,
                random_state=rng,
            ).fit(X[idx], target(idx))
            for idx in index_sets
        ]

    def _fit_heteroscedastic(self, kernel, X, yn, index_sets, rng) -> list[HeteroscedasticGP]:
        plan = self._em_plan(kernel, X, yn, index_sets, rng)
        learned = None
        if plan["shared"]:
            learned = fit_noise_model(
                plan["subsets"], plan["kernel"], self.noise_kernel, method=self.method, **plan["em"]
            )
        return self._em_models(plan, learned)

    def _em_plan(self, kernel, X, yn, index_sets, rng) -> dict[str, Any]:
        """What the heteroscedastic local models are fitted from: the local data sets, the EM
        options and, for shared hyperparameters, the subsets that learn them (``shared``)."""
        lo, hi = check_noise_bounds(self.noise_bounds)
        log_bounds = (2.0 * math.log(lo), 2.0 * math.log(hi))  # targets are standardised
        plan: dict[str, Any] = {
            "kernel": kernel,
            "datasets": [(X[idx], yn[idx]) for idx in index_sets],
            "em": {
                "optimizer": self.optimizer,
                "n_restarts": self.n_restarts,
                "max_em_iter": self.max_em_iter,
                "random_state": rng,
                "log_noise_bounds": log_bounds,
            },
            "shared": self.hyperparameters == "shared" and self.optimizer is not None,
        }
        if plan["shared"]:
            # Learn the signal, noise and z-process hyperparameters once, on a bounded subset of
            # the data (sum of the subsets' LMLs), then run every model's EM with them fixed.
            subsets, plan["complete"] = self._shared_data(X, index_sets)
            plan["subsets"] = [(X[i], yn[i]) for i in subsets]
            plan["kernel"] = self._learning_kernel(kernel, [X[i] for i in subsets])
        return plan

    def _learning_kernel(self, kernel: Kernel, inputs: list[NDArray[np.float64]]) -> Kernel:
        """The kernel a search starts from: the default kernel with its length scale bounded
        below by the spacing of the ``inputs`` that learn it and above by half the span of all
        the training inputs (``bound_length_scale``); an explicit kernel as given."""
        if self.kernel is not None:
            return kernel
        return bound_length_scale(kernel, inputs, input_span(self._X_fit))

    def _em_models(self, plan: dict[str, Any], learned: Any) -> list[HeteroscedasticGP]:
        """The local models from the plan and the shared EM's result ``learned``."""
        kernel, datasets, em = plan["kernel"], plan["datasets"], plan["em"]
        noise_kernel = self.noise_kernel
        params = {
            "method": self.method,
            "noise_kernel": noise_kernel,
            "noise_bounds": self.noise_bounds,
            "optimizer": None,
            "normalize_y": False,
            "max_em_iter": self.max_em_iter,
        }
        refit_kernel = None
        offset = None
        # One prior for f in every local model: the "nearest" mixture weighs the models by
        # their latent variances. Where the shared EM kept a heteroscedastic iteration, its
        # kernel of f differs from iteration 0's homoscedastic one (on LASA's mixed-shape sets,
        # a signal variance at its 1e-5 bound: "all noise"). A local EM that went back to
        # iteration 0 had that prior and a latent variance far below its neighbours' from a
        # window that knew nothing of f; entering the selection, it took most of the weight
        # within one sample (the mean stepped 7-10x the demonstrations' largest step).
        keep_homoscedastic = True
        statuses: list[str] = []
        if learned is not None:
            statuses.append(learned.status)
            kernel = learned.homoscedastic_kernel
            noise_kernel = learned.noise_kernel
            refit_kernel = learned.signal_kernel
            offset = learned.noise_offset  # one z mean for all models: no jump between them
            params["noise_kernel"] = noise_kernel
            keep_homoscedastic = learned.best_iter == 0
        if learned is not None and plan["complete"]:
            # every model took part with all its data: its result is final
            models = [
                HeteroscedasticGP._from_em(learned, i, Xl, yl, 0.0, 1.0, kernel=kernel, **params)
                for i, (Xl, yl) in enumerate(datasets)
            ]
        else:
            models = []
            for Xl, yl in datasets:
                if self.hyperparameters == "local" and self.optimizer is not None:
                    own = self._learning_kernel(kernel, [Xl])
                    result = fit_noise_model(
                        [(Xl, yl)], own, noise_kernel, method=self.method, **em
                    )
                else:
                    result = fit_noise_model(
                        [(Xl, yl)],
                        kernel,
                        noise_kernel,
                        method=self.method,
                        **{**em, "optimizer": None},
                        learn=False,
                        refit_kernel=refit_kernel,
                        noise_offset=offset,
                        keep_homoscedastic=keep_homoscedastic,
                    )
                statuses.append(result.status)
                models.append(
                    HeteroscedasticGP._from_em(result, 0, Xl, yl, 0.0, 1.0, kernel=kernel, **params)
                )
        self._warn_em(statuses)
        _share_noise_targets(models, datasets)
        return models

    def _warn_em(self, statuses: list[str]) -> None:
        """Record the EM outcomes (``em_status_``) and warn once if any ran out of iterations
        (an EM whose objective decreased has passed its best iteration, which is kept: recorded,
        not warned about)."""
        self.em_status_ = statuses
        stopped = [st for st in statuses if st in STOPPED_EARLY]
        if stopped:
            kinds = ", ".join(f"{stopped.count(k)} {k}" for k in sorted(set(stopped)))
            em_warning(f"{len(stopped)} of {len(statuses)} EM runs: {kinds}", "LocalGP")

    # ------------------------------------------------------------- Algorithm 2
    def _prepare_prediction(self) -> None:
        """Bounding boxes and length scales that let prediction skip far-away models."""
        X = self._X_fit  # the models' units (X_train_ / input_scale_)
        self._boxes = np.stack(
            [np.stack([X[idx].min(axis=0), X[idx].max(axis=0)]) for idx in self._index_sets]
        )  # (L, 2, n_features)
        spacing = []
        for j in range(X.shape[1]):
            u = np.unique(X[:, j])
            spacing.append(np.ptp(u) / (u.size - 1) if u.size > 1 else 1.0)
        self._spacing = np.asarray(spacing)  # mean spacing of distinct inputs, per feature
        width = self._boxes[:, 1] - self._boxes[:, 0]  # (L, d)
        self._blend = np.maximum(self._spacing[None, :], NOISE_BLEND * width)
        self._skip_scale = []
        for model in self.models_:
            k = _latent_model(model).kernel_
            k = signal_kernel(k)
            self._skip_scale.append(
                np.asarray(k.length_scale) if isinstance(k, SquaredExponential) else None
            )

    def _noise_weights(self, X: NDArray[np.float64], relevant: NDArray[np.bool_]):
        """(L, n) weights of the local noise functions ``r_l`` in ``r(x)``.

        ``rho_l ~ exp(-|g_l(x) / h_l|^2 / 2)`` over the ``relevant`` models, ``g_l`` the distance
        from ``x`` to the bounding box of model ``l``'s training inputs (0 inside) and ``h_l``
        per feature ``NOISE_BLEND`` times the box's width, at least the mean spacing of the
        distinct training inputs: the noise is that of the model whose data lie at ``x``,
        blended with a neighbour over a twentieth of a window between two windows (and averaged
        where boxes overlap). With ``h_l`` one input spacing (before), dense distinct inputs
        (the LASA handwriting set: 6000 time stamps, 15 models) switched between neighbouring
        noise functions within one sample, and the std stepped by up to 240x the
        demonstrations' largest step (median over the 30 shapes 21x; 2.8x with this blend, 1.6x
        with the EM's log bias from the data too; a tenth of a window gave 1.7x alone but moved
        the coffee policy's std tables more, see docs/design-gp.md).
        A noise function is an estimate from the model's own data; outside its window it only
        extrapolates (so each is evaluated at the nearest point of its window). Weighting by how
        much a model knows about ``f(x)`` (its precision gain) mixed in those extrapolations
        wherever the signal length scale exceeded a window: on demonstrations that split fast the
        std was 0.3x the demonstrations' spread and jumped at the model boundaries.
        """
        lo, hi = self._boxes[:, 0][:, None, :], self._boxes[:, 1][:, None, :]  # (L, 1, d)
        gap = np.maximum(np.maximum(lo - X[None], X[None] - hi), 0.0) / self._blend[:, None, :]
        logrho = np.where(relevant, -0.5 * np.sum(gap**2, axis=2), -np.inf)
        return _normalized_exp(logrho)

    def _relevant(self, X: NDArray[np.float64], logw: NDArray[np.float64]) -> NDArray[np.bool_]:
        """(L, n) mask of the local models evaluated at each test point.

        ``"nearest"`` uses the ``n_neighbors`` models with the highest ``w`` (part of the rule's
        definition). ``"product"`` and ``"rbcm"`` use every model except those whose training
        inputs are all more than ``SKIP_DISTANCE`` length scales away: such a model's prediction
        equals its prior to within ``exp(-SKIP_DISTANCE^2 / 2)`` (1e-18) relative, and the prior
        is used for it exactly (tested). The nearest-centre model is always evaluated.
        """
        L, n = logw.shape[1], X.shape[0]
        if self.combine == "nearest":
            k = min(self.n_neighbors, L)
            top = np.argpartition(-logw, k - 1, axis=1)[:, :k] if k < L else None
            relevant = np.zeros((L, n), dtype=bool)
            if top is None:
                relevant[:] = True
            else:
                relevant[top.T, np.arange(n)[None, :]] = True
        else:
            relevant = np.ones((L, n), dtype=bool)
            for l in range(L):
                ls = self._skip_scale[l]
                if ls is not None:
                    lo, hi = self._boxes[l]
                    gap = np.maximum(np.maximum(lo - X, X - hi), 0.0) / ls
                    relevant[l] = np.sum(gap**2, axis=1) < SKIP_DISTANCE**2
        relevant[np.argmax(logw, axis=1), np.arange(n)] = True
        return relevant

    def _local_predictions(
        self, X: NDArray[np.float64], relevant: NDArray[np.bool_], noisy: NDArray[np.bool_]
    ):
        """Per model: latent mean, latent var, noise var, prior var; each (L, n, n_targets).

        Where a model is not ``relevant`` its mean is 0 and its variance the prior; its noise is
        evaluated where ``noisy`` (elsewhere 0). One latent solve per model and test point (the
        public ``predict_latent`` and ``noise_variance`` would each repeat it).
        """
        L, n, t = len(self.models_), X.shape[0], self._y_mean.shape[0]
        mu = np.zeros((L, n, t))
        var = np.empty((L, n, t))
        noise = np.zeros((L, n, t))
        prior = np.empty((L, n, t))
        for l, model in enumerate(self.models_):
            gp = _latent_model(model)
            prior_l = (gp.kernel_.diag(X) - gp._noise_level)[:, None]
            prior[l] = prior_l
            var[l] = prior_l
            near = relevant[l]
            if np.any(near):
                m, v = gp._predict_normalized(X[near])  # normalised units (the models' own)
                mu[l, near] = m
                var[l, near] = v[:, None]
            need = noisy[l]
            if np.any(need):  # at the nearest point of its window: no extrapolated noise
                Xn = np.clip(X[need], self._boxes[l, 0], self._boxes[l, 1])
                noise[l, need] = _noise_normalized(model, Xn)[:, None]
        return mu, np.maximum(var, 1e-12), noise, prior

    def _combine(self, X: NDArray[np.float64]):
        logw_nl = self._weights(X, self._centres)  # (n, L)
        relevant = self._relevant(X, logw_nl)
        # Noise r(x), added after combining: the noise of the model whose training inputs
        # surround x (see _noise_weights); a model whose weight underflows to 0 at x adds
        # exactly nothing there and is not evaluated.
        rho = self._noise_weights(X, relevant)
        noisy = np.ones_like(relevant) if self.combine_noisy else rho > 0.0
        mu, var, noise, prior = self._local_predictions(X, relevant, noisy)  # Alg. 2, lines 1-6
        logw = logw_nl.T[:, :, None]  # (L, n, 1)
        r = np.sum(rho[:, :, None] * noise, axis=0)
        if self.combine_noisy:
            var = var + noise
            prior = prior + noise
        if self.combine == "product":  # Algorithm 2, line 7; Eqs. (8)-(9)
            prec = np.sum(1.0 / var, axis=0)
            mean = np.sum(mu / var, axis=0) / prec
            v = 1.0 / prec
        elif self.combine == "rbcm":
            beta = 0.5 * (np.log(prior) - np.log(var))
            rho_w = _normalized_exp(logw)
            prior_var = np.sum(rho_w * prior, axis=0)
            prec = np.sum(beta / var, axis=0) + (1.0 - np.sum(beta, axis=0)) / prior_var
            prec = np.maximum(prec, 1.0 / prior_var)
            mean = np.sum(beta * mu / var, axis=0) / prec
            v = 1.0 / prec
        else:  # "nearest": mixture of the n_neighbors models, weights (w_l - w_next) / v_l
            logpi = np.where(
                relevant[:, :, None], _taper(logw_nl.T, relevant) - np.log(var), -np.inf
            )
            pi = _normalized_exp(logpi)
            mean = np.sum(pi * mu, axis=0)
            v = np.maximum(np.sum(pi * (var + mu**2), axis=0) - mean**2, 1e-12)
        if self.combine_noisy:
            v = np.maximum(v - r, 1e-12)  # report the latent part; noise re-added by callers
        return mean, v, r

    def _check_fitted(self) -> None:
        if not hasattr(self, "models_"):
            raise ValueError("This LocalGP is not fitted yet; call fit(X, y) first")

    def _out(self, a):
        return a[:, 0] if self._single_target else a

    def _predict_normalized(self, X):
        return self._combine(self._scaled(X))

    def log_marginal_likelihood(self, theta: ArrayLike | None = None, eval_gradient: bool = False):
        """Sum of the local models' log marginal likelihoods (standardised targets)."""
        self._check_fitted()
        if theta is not None or eval_gradient:
            raise ValueError("LocalGP.log_marginal_likelihood supports only theta=None")
        if self.estimators_:
            return float(sum(e.log_marginal_likelihood() for e in self.estimators_))
        return float(sum(m.log_marginal_likelihood() for m in self.models_))


def _fit_columns_in_lockstep(columns: list[LocalGP], X, y) -> None:
    """Fit ``columns[j]`` to ``y[:, j]`` as ``columns[j].fit(X, y[:, j])`` would (shared
    hyperparameters, most-likely EM), with the columns' learning EMs run in lockstep
    (:func:`~lgp_policy.gp.heteroscedastic.most_likely_em_many`): the same models to
    rounding, their likelihood evaluations batched."""
    plans = []
    for j, e in enumerate(columns):
        e._check_params()
        e.estimators_ = None
        kernel, Xs, Yn, index_sets, rng = e._begin(X, y[:, j])
        plans.append(e._em_plan(kernel, Xs, Yn[:, 0], index_sets, rng))
    em = plans[0]["em"]
    learned = most_likely_em_many(
        [plan["subsets"] for plan in plans], plans[0]["kernel"], columns[0].noise_kernel, **em
    )
    for e, plan, result in zip(columns, plans, learned, strict=True):
        e.models_ = e._em_models(plan, result)
        e._prepare_prediction()


def _share_noise_targets(models: list[HeteroscedasticGP], datasets) -> None:
    """Refit every local noise function on its own log-noise targets and on the other models'
    single-residual targets (inputs without replicates) within ``NOISE_SHARE`` of its window's
    width (per feature) beyond its training inputs, with its z-process's hyperparameters as
    learnt.

    Each noise function is an estimate from its own window, so at a window's edge it only
    extrapolates its own targets, and on distinct inputs two neighbours disagreed there by up
    to 4x (LASA heee: 6.4 against 1.6 mm where the demonstrations end at different times); the
    std then stepped where ``r(x)`` passes from one to the other. With the targets near the edge
    shared, both estimate the noise there from the same data. Targets of replicated inputs (a
    phase grid: the mean of ``m`` demonstrations' squares at each step) are not shared: there
    the spread is measured at every step of the grid, and sharing it blurred the coffee
    policy's std where the demonstrations' spread drops fast (3 of its 510 target episodes
    lost, two layouts that failed at placing the cup across demonstration draws). The local
    latent models are unchanged. A model whose EM kept its homoscedastic step has no z-process
    and is left as it is (its targets are not shared either)."""
    targets: list[tuple[NDArray[np.float64], ...] | None] = []
    shared: list[tuple[NDArray[np.float64], ...] | None] = []
    for model in models:
        zgp = model.noise_gp_
        if zgp is None:
            targets.append(None)
            shared.append(None)
            continue
        d = zgp._data  # the distinct inputs, their (mean) targets and the known target noise
        noise = zgp._noise_level
        mine = (d.X, d.ybar[:, 0], (noise + zgp._alpha_u) / d.counts - noise)
        targets.append(mine)
        # the z-process sits on the latent GP's distinct inputs, whose replicate counts say
        # which targets are single residuals
        latent = model.gp_._data
        single = (latent.counts == 1) & np.array_equal(latent.X, d.X)
        shared.append(tuple(a[single] for a in mine) if np.any(single) else None)
    if not any(t is not None for t in shared):
        return
    boxes = np.stack([np.stack([X.min(axis=0), X.max(axis=0)]) for X, _ in datasets])
    margin = NOISE_SHARE * (boxes[:, 1] - boxes[:, 0])
    lo, hi = boxes[:, 0] - margin, boxes[:, 1] + margin
    refits: list[GaussianProcess | None] = []
    for l, own in enumerate(targets):
        parts = []
        if own is not None:
            for o, other in enumerate(shared):
                if other is None or o == l:
                    continue
                near = np.all((other[0] >= lo[l]) & (other[0] <= hi[l]), axis=1)
                if np.any(near):
                    parts.append(tuple(a[near] for a in other))
        if own is None or not parts:
            refits.append(None)
            continue
        U, z, var = (np.concatenate([own[i], *(p[i] for p in parts)]) for i in range(3))
        kernel = models[l].noise_gp_.kernel_  # type: ignore[union-attr]
        refits.append(fixed_gp(kernel, alpha=var, collapse_replicates=True).fit(U, z))
    for model, refit in zip(models, refits, strict=True):
        if refit is not None:
            model.noise_gp_ = refit


def _taper(logw: NDArray[np.float64], relevant: NDArray[np.bool_]) -> NDArray[np.float64]:
    """(L, n, 1) log weights of the ``n_neighbors`` selected models that go to 0 continuously as
    a model leaves the selection: ``log(w_l - w_next)``, ``w_next`` the largest weight of the
    models not selected (none: ``w_l`` itself). Every model's mixture weight is then continuous
    in ``x``, so the combined mean and variance are too."""
    out = np.where(relevant, logw, -np.inf)
    if np.all(relevant):
        return out[:, :, None]
    rest = np.max(np.where(relevant, -np.inf, logw), axis=0, keepdims=True)  # (1, n)
    top = np.max(out, axis=0, keepdims=True)
    g = np.exp(out - top) - np.exp(rest - top)  # relative to the best: nothing overflows
    with np.errstate(divide="ignore"):
        logg = np.where(relevant & (g > 0.0), np.log(np.where(g > 0.0, g, 1.0)) + top, -np.inf)
    # exact ties with the best unselected model (equidistant centres): its plain weights
    tie = ~np.any(np.isfinite(logg), axis=0, keepdims=True)
    return np.where(tie, out, logg)[:, :, None]


def _normalized_exp(logw: NDArray[np.float64]) -> NDArray[np.float64]:
    """``exp(logw)`` normalised to sum 1 over axis 0 (a softmax; ``-inf`` entries are 0), with
    the largest entry of each column shifted to 0 first so that nothing overflows. (scipy's
    ``logsumexp`` gave the same weights and cost a fifth of ``LocalGP.predict``.)"""
    top = np.max(logw, axis=0, keepdims=True)
    w = np.exp(logw - np.where(np.isfinite(top), top, 0.0))
    return w / np.sum(w, axis=0, keepdims=True)


def _latent_model(model) -> GaussianProcess:
    return model.gp_ if isinstance(model, HeteroscedasticGP) else model


def _noise_normalized(model, X: NDArray[np.float64]) -> NDArray[np.float64]:
    """Noise variance r(x) of a local model at X in its (normalised) units, (n,)."""
    if isinstance(model, HeteroscedasticGP):
        return np.exp(model._log_noise_normalized(X))
    return np.full(X.shape[0], model._noise_level)
