"""Local Gaussian processes (paper Sec. II-C, Algorithms 1 and 2, Eqs. 8-9).

:class:`LocalGP` clusters the inputs by covariance (Algorithm 1), fits one exact or
heteroscedastic GP per cluster, and combines the local predictions (Algorithm 2).

Assignment (Algorithm 1). A point ``x`` joins the model whose centre ``c`` has the highest
normalised covariance ``w = k(x, c) / sqrt(k(x, x) k(c, c))`` (for the squared exponential,
``exp(-|x - c|^2 / (2 l^2))``, in ``(0, 1]``) if ``w > threshold``; otherwise it opens a new model
at ``x``. Centres are the running means of their points. The signal part of ``kernel`` with its
*initial* hyperparameters defines ``w``. A model holding ``max_points`` points no longer accepts
points (the next one opens a new model), which caps the cost of a model at ``O(max_points^3)``
and keeps the whole fit near-linear in ``n``. Points are visited in the lexicographic order of
``X`` (``order="sorted"``, the default): for the 1-D time input of learning from demonstration
this puts the replicates of all demonstrations at one time step into the same model and makes
the models contiguous time windows. ``order="given"`` runs Algorithm 1 in the data's order as in
the paper.

Hyperparameters. ``hyperparameters="local"`` (the paper's choice, Sec. IV: "individual
parameterization and optimization"): every local model maximises its own log marginal likelihood,
starting from ``kernel``. ``hyperparameters="fixed"``: all local models use ``kernel`` as given.
The targets are standardised once globally (``normalize_y``), and each local model subtracts the
mean of its own targets (a constant prior mean per model).

Combination (Algorithm 2). Local *latent* (noise-free) predictions ``N(mu_l, v_l)`` are combined
and the noise ``r(x)`` is added afterwards. Multiplying the noisy predictive distributions instead
double-counts the noise and gives 95% coverage far below 0.95 (``combine_noisy=True`` reproduces
that behaviour for comparison). Rules:

* ``"product"``: Eqs. (8)-(9), ``v = (sum_l 1/v_l)^-1``, ``mu = v sum_l mu_l / v_l``;
* ``"rbcm"``: robust Bayesian committee machine (Deisenroth & Ng 2015) with
  ``beta_l = (log s_l^2 - log v_l) / 2``, ``s_l^2`` the model's prior variance;
* ``"nearest"``: moment-matched mixture of the models, weights ``pi_l ~ w_l(x) / v_l(x)``.

The noise is ``r(x) = sum_l rho_l(x) r_l(x)`` with ``rho_l = w_l / sum_k w_k``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import logsumexp

from lgp_policy._validation import check_random_state, check_X, check_X_y
from lgp_policy.gp import GaussianProcess, Optimizer, default_kernel
from lgp_policy.heteroscedastic import HeteroscedasticGP, signal_kernel
from lgp_policy.kernels import Kernel, SquaredExponential

__all__ = ["COMBINE_RULES", "LocalGP"]

COMBINE_RULES = ("product", "rbcm", "nearest")


class LocalGP:
    """Local (heteroscedastic) GP regression, Algorithms 1 and 2 of the paper.

    Args:
        kernel: kernel of every local model (Eq. 10). Default
            ``SquaredExponential(1, 1) + WhiteNoise(0.1)``. Its signal part, with the initial
            hyperparameters, also defines the assignment weight ``w``.
        threshold: minimum weight ``w`` in ``(0, 1)`` for joining an existing model.
        max_points: most training points per local model.
        local_model: ``"heteroscedastic"`` (:class:`HeteroscedasticGP`) or ``"exact"``
            (:class:`GaussianProcess`).
        combine: ``"product"`` (Eqs. 8-9), ``"rbcm"`` or ``"nearest"`` (see module docstring).
        combine_noisy: combine the noisy predictive distributions (the known trap; for
            comparison only).
        hyperparameters: ``"local"`` (each model optimises its own) or ``"fixed"``.
        order: ``"sorted"`` or ``"given"``: the order Algorithm 1 visits the points in.
        noise_kernel: z-process kernel of heteroscedastic local models.
        optimizer, n_restarts, max_em_iter: passed to the local models.
        normalize_y: standardise ``y`` globally before fitting.
        random_state: seed for the local models.

    Attributes:
        centers_: ``(n_models, n_features)`` centres in input units.
        assignments_: ``(n_samples,)`` index of the model each training point belongs to.
        models_: the fitted local models (targets in globally standardised units, minus
            ``offsets_``).
    """

    def __init__(
        self,
        kernel: Kernel | None = None,
        *,
        threshold: float = 0.5,
        max_points: int = 400,
        local_model: str = "heteroscedastic",
        combine: str = "nearest",
        combine_noisy: bool = False,
        hyperparameters: str = "local",
        order: str = "sorted",
        noise_kernel: Kernel | None = None,
        optimizer: Optimizer = "L-BFGS-B",
        n_restarts: int = 0,
        max_em_iter: int = 10,
        normalize_y: bool = True,
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.kernel = kernel
        self.threshold = threshold
        self.max_points = max_points
        self.local_model = local_model
        self.combine = combine
        self.combine_noisy = combine_noisy
        self.hyperparameters = hyperparameters
        self.order = order
        self.noise_kernel = noise_kernel
        self.optimizer = optimizer
        self.n_restarts = n_restarts
        self.max_em_iter = max_em_iter
        self.normalize_y = normalize_y
        self.random_state = random_state

    def get_params(self, deep: bool = False) -> dict[str, Any]:
        return {
            k: getattr(self, k)
            for k in (
                "kernel",
                "threshold",
                "max_points",
                "local_model",
                "combine",
                "combine_noisy",
                "hyperparameters",
                "order",
                "noise_kernel",
                "optimizer",
                "n_restarts",
                "max_em_iter",
                "normalize_y",
                "random_state",
            )
        }

    def _check_params(self) -> None:
        if not (np.isscalar(self.threshold) and 0.0 < float(self.threshold) < 1.0):
            raise ValueError(f"threshold must be in (0, 1), got {self.threshold!r}")
        if not isinstance(self.max_points, (int, np.integer)) or self.max_points < 2:
            raise ValueError(f"max_points must be an int >= 2, got {self.max_points!r}")
        if self.local_model not in ("heteroscedastic", "exact"):
            raise ValueError(
                f"local_model must be 'heteroscedastic' or 'exact', got {self.local_model!r}"
            )
        if self.combine not in COMBINE_RULES:
            raise ValueError(f"combine must be one of {COMBINE_RULES}, got {self.combine!r}")
        if self.hyperparameters not in ("local", "fixed"):
            raise ValueError(
                f"hyperparameters must be 'local' or 'fixed', got {self.hyperparameters!r}"
            )
        if self.order not in ("sorted", "given"):
            raise ValueError(f"order must be 'sorted' or 'given', got {self.order!r}")

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
        log_thr = np.log(self.threshold)
        centres = np.empty((0, X.shape[1]))
        sums: list[NDArray[np.float64]] = []
        counts: list[int] = []
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
                full = np.asarray(counts) + m > cap
                logw[full] = -np.inf
                best = int(np.argmax(logw))  # line 10
                if logw[best] > log_thr:  # line 11
                    p = best
            if p < 0:  # lines 17-19: new model at x
                p = n_models
                n_models += 1
                sums.append(np.zeros(X.shape[1]))
                counts.append(0)
            sums[p] = sums[p] + m * x  # line 13
            counts[p] += m
            centre_arr[p] = sums[p] / counts[p]  # line 15: centre = mean
            model_of_group[g] = p
        assignments = np.empty(n, dtype=np.int64)
        assignments[visit] = np.repeat(model_of_group, sizes)
        return centre_arr[:n_models].copy(), assignments

    # ---------------------------------------------------------------- fitting
    def _make_model(self, kernel: Kernel, seed: np.random.Generator):
        optimizer = None if self.hyperparameters == "fixed" else self.optimizer
        if self.local_model == "exact":
            return GaussianProcess(
                kernel,
                optimizer=optimizer,
                n_restarts=self.n_restarts,
                normalize_y=False,
                random_state=seed,
            )
        return HeteroscedasticGP(
            kernel,
            noise_kernel=self.noise_kernel,
            optimizer=optimizer,
            n_restarts=self.n_restarts,
            normalize_y=False,
            max_em_iter=self.max_em_iter,
            random_state=seed,
        )

    def fit(self, X: ArrayLike, y: ArrayLike) -> LocalGP:
        """Cluster (Algorithm 1) and fit one GP per cluster. Returns ``self``."""
        X, y = check_X_y(X, y)
        self._check_params()
        kernel = default_kernel() if self.kernel is None else self.kernel
        self._assign_kernel = signal_kernel(kernel)
        self._single_target = y.ndim == 1
        Y = y[:, None] if self._single_target else y
        if self.normalize_y:
            self._y_mean = Y.mean(axis=0)
            std = Y.std(axis=0)
            self._y_std = np.where(std > 0, std, 1.0)
        else:
            self._y_mean, self._y_std = np.zeros(Y.shape[1]), np.ones(Y.shape[1])
        Yn = (Y - self._y_mean) / self._y_std
        self.X_train_, self.y_train_ = X, y
        self.n_features_in_ = X.shape[1]
        self.centers_, self.assignments_ = self._assign(X)
        rng = check_random_state(self.random_state)
        self.models_ = []
        offsets = []
        for l in range(self.centers_.shape[0]):
            idx = np.flatnonzero(self.assignments_ == l)
            Yl = Yn[idx]
            off = Yl.mean(axis=0)
            target = (Yl - off)[:, 0] if self._single_target else Yl - off
            if idx.shape[0] < 2:  # a lone point: duplicate it (an exact replicate)
                idx = np.repeat(idx, 2)
                target = np.repeat(target, 2, axis=0)
            self.models_.append(self._make_model(kernel, rng).fit(X[idx], target))
            offsets.append(off)
        self.offsets_ = np.asarray(offsets)  # (n_models, n_targets), standardised units
        return self

    # ------------------------------------------------------------- Algorithm 2
    def _local_predictions(self, X: NDArray[np.float64]):
        """Per model: latent mean, latent var, noise var, prior var; each (L, n, n_targets)."""
        L, n, t = len(self.models_), X.shape[0], self._y_mean.shape[0]
        mu = np.empty((L, n, t))
        var = np.empty((L, n, t))
        noise = np.empty((L, n, t))
        prior = np.empty((L, n, t))
        for l, model in enumerate(self.models_):
            m, s = model.predict_latent(X)
            mu[l] = m.reshape(n, -1) + self.offsets_[l]
            var[l] = (s**2).reshape(n, -1)
            noise[l] = model.noise_variance(X).reshape(n, -1)
            prior[l] = _prior_variance(model, X).reshape(n, -1)
        return mu, np.maximum(var, 1e-12), noise, prior

    def _combine(self, X: NDArray[np.float64]):
        mu, var, noise, prior = self._local_predictions(X)
        logw = self._weights(X, self.centers_).T[:, :, None]  # (L, n, 1)
        rho = np.exp(logw - logsumexp(logw, axis=0, keepdims=True))
        r = np.sum(rho * noise, axis=0)  # noise r(x), added after combining
        if self.combine_noisy:
            var = var + noise
            prior = prior + noise
        if self.combine == "product":  # Eqs. (8)-(9)
            prec = np.sum(1.0 / var, axis=0)
            mean = np.sum(mu / var, axis=0) / prec
            v = 1.0 / prec
        elif self.combine == "rbcm":
            beta = 0.5 * (np.log(prior) - np.log(var))
            prior_var = np.sum(rho * prior, axis=0)
            prior_mean = np.sum(rho * self.offsets_[:, None, :], axis=0)
            prior_w = 1.0 - np.sum(beta, axis=0)
            prec = np.sum(beta / var, axis=0) + prior_w / prior_var
            prec = np.maximum(prec, np.max(1.0 / var, axis=0) * 1e-3)
            mean = (np.sum(beta * mu / var, axis=0) + prior_w * prior_mean / prior_var) / prec
            v = 1.0 / prec
        else:  # "nearest": moment-matched mixture, weights w_l / v_l
            logpi = logw - np.log(var)
            pi = np.exp(logpi - logsumexp(logpi, axis=0, keepdims=True))
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

    def predict(self, X: ArrayLike, return_std: bool = False):
        """Combined mean and, with ``return_std``, std including the noise ``r(x)``."""
        self._check_fitted()
        X = check_X(X, n_features=self.n_features_in_)
        mean, v, r = self._combine(X)
        mean_out = self._out(mean * self._y_std + self._y_mean)
        if not return_std:
            return mean_out
        return mean_out, self._out(np.sqrt(v + r) * self._y_std)

    def predict_latent(self, X: ArrayLike):
        """Combined latent mean and noise-free std."""
        self._check_fitted()
        X = check_X(X, n_features=self.n_features_in_)
        mean, v, _ = self._combine(X)
        return self._out(mean * self._y_std + self._y_mean), self._out(np.sqrt(v) * self._y_std)

    def noise_variance(self, X: ArrayLike) -> NDArray[np.float64]:
        """Noise variance ``r(x)`` blended from the local models, in units of y^2."""
        self._check_fitted()
        X = check_X(X, n_features=self.n_features_in_)
        _, _, r = self._combine(X)
        return self._out(r * self._y_std**2)

    def log_marginal_likelihood(self, theta: ArrayLike | None = None, eval_gradient: bool = False):
        """Sum of the local models' log marginal likelihoods (standardised targets)."""
        self._check_fitted()
        if theta is not None or eval_gradient:
            raise ValueError("LocalGP.log_marginal_likelihood supports only theta=None")
        return float(sum(m.log_marginal_likelihood() for m in self.models_))


def _prior_variance(model, X: NDArray[np.float64]) -> NDArray[np.float64]:
    """Latent prior variance k(x, x) of a local model at X, (n,) or (n, n_targets)."""
    if isinstance(model, HeteroscedasticGP):
        if model.estimators_:
            return np.stack([_prior_variance(e, X) for e in model.estimators_], axis=1)
        return model.gp_.kernel_.diag(X)
    return model.kernel_.diag(X) - model._noise_level
