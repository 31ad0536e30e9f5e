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

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.special
from numpy.typing import ArrayLike, NDArray

from lgp_policy.gp._validation import check_random_state, check_X, check_X_y
from lgp_policy.gp.exact import (
    GaussianProcess,
    Optimizer,
    default_kernel,
    fit_shared_hyperparameters,
)
from lgp_policy.gp.kernels import Kernel, SquaredExponential, WhiteNoise

#: Floor of ``1 - var_f / r`` in the leverage correction of squared residuals.
MIN_RESIDUAL_FRACTION = 0.05

__all__ = [
    "EMResult",
    "HeteroscedasticGP",
    "default_noise_kernel",
    "most_likely_em",
    "signal_kernel",
]


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


def default_noise_kernel() -> Kernel:
    """``SquaredExponential(1, 1) + WhiteNoise(0.5)``: z-process kernel (log noise)."""
    return SquaredExponential(1.0, 1.0) + WhiteNoise(0.5)


@dataclass
class EMResult:
    """Output of :func:`most_likely_em`: one entry per data set in the lists."""

    gps: list[GaussianProcess]
    noise_gps: list[GaussianProcess]
    noise_offsets: list[float]
    homoscedastic_kernel: Kernel
    signal_kernel: Kernel
    noise_kernel: Kernel
    n_iter: int
    converged: bool


def most_likely_em(
    datasets: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    kernel: Kernel,
    noise_kernel: Kernel,
    *,
    learn: bool = True,
    optimizer: Optimizer = "L-BFGS-B",
    n_restarts: int = 0,
    max_em_iter: int = 10,
    tol: float = 0.05,
    n_samples: int | None = None,
    collapse_replicates: bool = True,
    max_iter: int = 200,
    random_state: int | np.random.Generator | None = None,
    refit_kernel: Kernel | None = None,
) -> EMResult:
    """Most-likely heteroscedastic EM (Kersting et al. 2007) on one or more data sets.

    With several data sets (the local models of :class:`~lgp_policy.gp.local.LocalGP`) the
    hyperparameters are shared: each learning step maximises the *sum* of the data sets' log
    marginal likelihoods. Each data set's z-process has its own constant mean (the mean of its
    log-noise targets). ``learn=False`` keeps ``kernel`` and ``noise_kernel`` as given.

    Args:
        datasets: ``[(X (n_i, d), y (n_i,)), ...]``, targets already standardised.
        kernel: homoscedastic kernel of step 1 (with a WhiteNoise term).
        noise_kernel: z-process kernel.
        refit_kernel: kernel of ``f`` in step 4 (default: ``kernel`` without its noise term).
    """
    rng = check_random_state(random_state)
    opt = {"optimizer": optimizer, "n_restarts": n_restarts, "max_iter": max_iter}

    def make(k: Kernel, alpha: Any = 0.0) -> GaussianProcess:
        return GaussianProcess(
            k,
            optimizer=None,
            normalize_y=False,
            alpha=alpha,
            collapse_replicates=collapse_replicates,
        )

    # Step 1: homoscedastic GP G1.
    gps = [make(kernel).fit(X, y) for X, y in datasets]
    if learn:
        fit_shared_hyperparameters(gps, random_state=rng, **opt)
    homoscedastic_kernel = gps[0].kernel_.clone()
    groups = []  # the GP's own distinct inputs (its solve is on them): X, inverse, counts, bias
    for gp in gps:
        d = gp._data
        groups.append((d.X, d.inverse, d.counts, _log_mean_chi2_bias(d.counts)))
    log_r = [np.log(gp.noise_variance(X)) for gp, (X, _) in zip(gps, datasets, strict=True)]
    sig = signal_kernel(homoscedastic_kernel) if refit_kernel is None else refit_kernel.clone()
    zk = noise_kernel.clone()
    converged, n_iter = False, 0
    noise_gps: list[GaussianProcess] = []
    offsets: list[float] = []
    for _ in range(max_em_iter):
        n_iter += 1
        # Step 2: noise estimate at every training input from the posterior of f.
        targets = []
        for gp, (X, y), (U, inverse, counts, bias), lr in zip(
            gps, datasets, groups, log_r, strict=True
        ):
            mu_u, var_u = gp._latent_at_training()  # at the distinct inputs, then per sample
            mu, std_f = mu_u[inverse, 0], np.sqrt(var_u[inverse])
            if n_samples is None:
                # Squared residual over its expectation r - var_f (leverage-corrected): an
                # unbiased r(x_i) * chi2_1 draw; averaged over replicates, log-bias removed.
                r = np.exp(lr)
                e = (y - mu) ** 2 / np.maximum(1.0 - std_f**2 / r, MIN_RESIDUAL_FRACTION)
                e_u = np.bincount(inverse, weights=e, minlength=U.shape[0]) / counts
                targets.append(np.log(np.maximum(e_u, 1e-300)) - bias)
            else:
                # Kersting et al.'s estimator: 0.5 (y_i - t_ij)^2, t_ij from the predictive
                # distribution of the current GP (including its noise).
                scale = np.sqrt(std_f**2 + np.exp(lr))
                t = mu[:, None] + scale[:, None] * rng.standard_normal((X.shape[0], n_samples))
                e = np.mean(0.5 * (y[:, None] - t) ** 2, axis=1)
                e_u = np.bincount(inverse, weights=e, minlength=U.shape[0]) / counts
                targets.append(np.log(np.maximum(e_u, 1e-300)))
        # Step 3: z-process G2 on the log noise.
        offsets = [float(np.mean(z)) for z in targets]
        noise_gps = [
            make(zk).fit(g[0], z - off) for g, z, off in zip(groups, targets, offsets, strict=True)
        ]
        if learn:
            fit_shared_hyperparameters(noise_gps, random_state=rng, **opt)
            zk = noise_gps[0].kernel_.clone()
        new_log_r = [  # z at the training inputs (the z-process's own, distinct inputs)
            zgp._latent_at_training()[0][:, 0][g[1]] + off
            for zgp, g, off in zip(noise_gps, groups, offsets, strict=True)
        ]
        # Step 4: GP with R = diag(r(x_i)), Eq. (5).
        gps = [
            make(sig, alpha=np.exp(lr)).fit(X, y)
            for lr, (X, y) in zip(new_log_r, datasets, strict=True)
        ]
        if learn:
            fit_shared_hyperparameters(gps, random_state=rng, **opt)
            sig = gps[0].kernel_.clone()
        change = max(float(np.max(np.abs(a - b))) for a, b in zip(new_log_r, log_r, strict=True))
        log_r = new_log_r
        if change < tol:
            converged = True
            break
    return EMResult(gps, noise_gps, offsets, homoscedastic_kernel, sig, zk, n_iter, converged)


class HeteroscedasticGP:
    """GP with input-dependent noise ``r(x)`` learnt by most-likely EM (Kersting et al. 2007).

    Args:
        kernel: kernel of the first (homoscedastic) GP, e.g. Eq. (10); its WhiteNoise terms are
            dropped once ``R`` takes over. Default ``SquaredExponential(1, 1) + WhiteNoise(0.1)``.
        noise_kernel: kernel of the z-process (log noise). Default
            ``SquaredExponential(1, 1) + WhiteNoise(0.5)``.
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

    Attributes:
        gp_: final GP of ``f`` with ``alpha = r(x_i)`` (normalised units).
        noise_gp_: the z-process, fitted to ``log r - noise_offset_``.
        homoscedastic_kernel_: the kernel of step 1 after fitting.
        n_iter_, converged_: EM iterations run and whether ``tol`` was met.
    """

    def __init__(
        self,
        kernel: Kernel | None = None,
        *,
        noise_kernel: Kernel | None = None,
        optimizer: Optimizer = "L-BFGS-B",
        n_restarts: int = 0,
        normalize_y: bool = True,
        max_em_iter: int = 10,
        tol: float = 0.05,
        n_samples: int | None = None,
        collapse_replicates: bool = True,
        max_iter: int = 200,
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.kernel = kernel
        self.noise_kernel = noise_kernel
        self.optimizer = optimizer
        self.n_restarts = n_restarts
        self.normalize_y = normalize_y
        self.max_em_iter = max_em_iter
        self.tol = tol
        self.n_samples = n_samples
        self.collapse_replicates = collapse_replicates
        self.max_iter = max_iter
        self.random_state = random_state

    def get_params(self, deep: bool = False) -> dict[str, Any]:
        return {
            "kernel": self.kernel,
            "noise_kernel": self.noise_kernel,
            "optimizer": self.optimizer,
            "n_restarts": self.n_restarts,
            "normalize_y": self.normalize_y,
            "max_em_iter": self.max_em_iter,
            "tol": self.tol,
            "n_samples": self.n_samples,
            "collapse_replicates": self.collapse_replicates,
            "max_iter": self.max_iter,
            "random_state": self.random_state,
        }

    def _gp(self, kernel: Kernel, alpha: Any = 0.0, normalize_y: bool = False, seed=None):
        return GaussianProcess(
            kernel,
            optimizer=self.optimizer,
            n_restarts=self.n_restarts,
            normalize_y=normalize_y,
            alpha=alpha,
            collapse_replicates=self.collapse_replicates,
            max_iter=self.max_iter,
            random_state=seed,
        )

    def fit(self, X: ArrayLike, y: ArrayLike) -> HeteroscedasticGP:
        """Fit to ``X (n_samples, n_features)``, ``y (n_samples,)`` or ``(n_samples, n_targets)``.

        Returns:
            self
        """
        X, y = check_X_y(X, y)
        if not isinstance(self.max_em_iter, (int, np.integer)) or self.max_em_iter < 1:
            raise ValueError(f"max_em_iter must be a positive int, got {self.max_em_iter!r}")
        if not np.isfinite(self.tol) or self.tol <= 0:
            raise ValueError(f"tol must be positive, got {self.tol!r}")
        if self.n_samples is not None and (
            not isinstance(self.n_samples, (int, np.integer)) or self.n_samples < 1
        ):
            raise ValueError(f"n_samples must be None or a positive int, got {self.n_samples!r}")
        self.n_features_in_ = X.shape[1]
        self.X_train_, self.y_train_ = X, y
        rng = check_random_state(self.random_state)
        self._single_target = y.ndim == 1
        if y.ndim == 2 and y.shape[1] > 1:
            params = self.get_params()
            self.estimators_ = []
            for j in range(y.shape[1]):
                params["random_state"] = rng
                self.estimators_.append(HeteroscedasticGP(**params).fit(X, y[:, j]))
            return self
        self.estimators_ = None
        self._fit_single(X, y.reshape(-1), rng)
        return self

    def _fit_single(self, X, y, rng: np.random.Generator) -> None:
        if self.normalize_y:
            self._y_mean = float(y.mean())
            std = float(y.std())
            self._y_std = std if std > 0 else 1.0
        else:
            self._y_mean, self._y_std = 0.0, 1.0
        yn = (y - self._y_mean) / self._y_std
        kernel = default_kernel() if self.kernel is None else self.kernel
        noise_kernel = default_noise_kernel() if self.noise_kernel is None else self.noise_kernel
        result = most_likely_em(
            [(X, yn)],
            kernel,
            noise_kernel,
            learn=self.optimizer is not None,
            optimizer=self.optimizer,
            n_restarts=self.n_restarts,
            max_em_iter=self.max_em_iter,
            tol=self.tol,
            n_samples=self.n_samples,
            collapse_replicates=self.collapse_replicates,
            max_iter=self.max_iter,
            random_state=rng,
        )
        self._set_state(result, 0)

    def _set_state(self, result: EMResult, index: int) -> None:
        self.gp_ = result.gps[index]
        self.noise_gp_ = result.noise_gps[index]
        self.noise_offset_ = float(result.noise_offsets[index])
        self.homoscedastic_kernel_ = result.homoscedastic_kernel
        self.n_iter_ = result.n_iter
        self.converged_ = result.converged

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

    def _stack(self, method: str, X, **kw):
        outs = [getattr(est, method)(X, **kw) for est in self.estimators_]
        if isinstance(outs[0], tuple):
            return tuple(np.stack(parts, axis=1) for parts in zip(*outs, strict=True))
        return np.stack(outs, axis=1)

    def _log_noise_normalized(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.noise_gp_.predict(X) + self.noise_offset_

    def _predict_normalized(self, X: NDArray[np.float64]):
        """Latent mean ``(n,)``, latent variance ``(n,)`` and r(x) ``(n,)``, normalised units."""
        mean, var = self.gp_._predict_normalized(X)
        return mean[:, 0], var, np.exp(self._log_noise_normalized(X))

    def predict(self, X: ArrayLike, return_std: bool = False):
        """Mean (Eq. 5) and, with ``return_std``, the std of Eq. (6): ``sqrt(var_f + r(x))``."""
        self._check_fitted()
        if self.estimators_:
            return self._stack("predict", X, return_std=return_std)
        X = check_X(X, n_features=self.n_features_in_)
        mean, var, r = self._predict_normalized(X)
        mean = mean * self._y_std + self._y_mean
        if not return_std:
            return mean
        return mean, np.sqrt(var + r) * self._y_std  # Eq. (6)

    def predict_latent(self, X: ArrayLike):
        """Mean and noise-free std of ``f(X)``."""
        self._check_fitted()
        if self.estimators_:
            return self._stack("predict_latent", X)
        X = check_X(X, n_features=self.n_features_in_)
        mean, var, _ = self._predict_normalized(X)
        return mean * self._y_std + self._y_mean, np.sqrt(var) * self._y_std

    def noise_variance(self, X: ArrayLike) -> NDArray[np.float64]:
        """r(x) at new inputs (Eq. 6's ``R*``), in units of y^2: ``(n,)`` or ``(n, n_targets)``."""
        self._check_fitted()
        if self.estimators_:
            return self._stack("noise_variance", X)
        X = check_X(X, n_features=self.n_features_in_)
        return np.exp(self._log_noise_normalized(X)) * self._y_std**2

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
