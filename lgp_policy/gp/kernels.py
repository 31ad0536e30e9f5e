"""Covariance functions (kernels) with log-space hyperparameters and analytic gradients.

Kernels are small composable value objects in the style of scikit-learn's
``sklearn.gaussian_process.kernels``:

* ``theta``: the hyperparameters in log space, a flat array (what the optimiser sees);
* ``bounds``: ``(n_theta, 2)`` log-space bounds;
* ``k(X, Y=None, eval_gradient=False)``: the covariance matrix, and with ``eval_gradient`` (only
  for ``Y=None``) its derivative with respect to ``theta``, shape ``(n, n, n_theta)``;
* ``k.diag(X)``: the diagonal of ``k(X)`` without building the matrix.

``SquaredExponential(...) + WhiteNoise(...)`` builds Eq. (10) of the paper. A kernel only says
*what* the covariance is; how the linear algebra is done is the job of
:class:`lgp_policy.gp.GaussianProcess` (tinygp's split of kernel and solver).

Like scikit-learn's ``WhiteKernel``, :class:`WhiteNoise` contributes only to ``k(X)`` (the
Kronecker delta of Eq. (10) between a training set and itself), never to ``k(X, Y)``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lgp_policy.gp._base import ParamsMixin
from lgp_policy.gp._validation import check_positive

__all__ = ["Exponential", "Kernel", "SquaredExponential", "Sum", "WhiteNoise"]

Bounds = tuple[float, float]


def _check_bounds(bounds: Any, name: str) -> NDArray[np.float64]:
    arr = np.asarray(bounds, dtype=np.float64)
    if arr.shape != (2,) or not np.all(np.isfinite(arr)) or arr[0] <= 0 or arr[0] > arr[1]:
        raise ValueError(f"{name} must be a pair (low, high) with 0 < low <= high, got {bounds!r}")
    return arr


def _as_2d(X: ArrayLike, name: str) -> NDArray[np.float64]:
    arr = np.asarray(X, dtype=np.float64)
    if arr.ndim != 2:
        raise ValueError(
            f"{name} must be 2-D with shape (n_samples, n_features), got ndim={arr.ndim}"
        )
    return arr


class Kernel(ParamsMixin, ABC):
    """Base class: a covariance function with hyperparameters ``theta`` in log space."""

    #: True for kernels that model observation noise (a Kronecker delta); the GP treats them
    #: as the noise term sigma_n^2 of Eqs. (1)-(4) rather than as part of the latent f.
    is_noise: bool = False

    @property
    @abstractmethod
    def theta(self) -> NDArray[np.float64]:
        """Log-transformed hyperparameters, a flat array."""

    @theta.setter
    @abstractmethod
    def theta(self, value: ArrayLike) -> None: ...

    @property
    @abstractmethod
    def bounds(self) -> NDArray[np.float64]:
        """Log-space bounds of ``theta``, shape ``(n_theta, 2)``."""

    @property
    @abstractmethod
    def hyperparameter_names(self) -> list[str]:
        """One name per entry of ``theta``."""

    @abstractmethod
    def __call__(
        self, X: ArrayLike, Y: ArrayLike | None = None, eval_gradient: bool = False
    ) -> NDArray[np.float64] | tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Covariance ``k(X, Y)`` (n_X, n_Y); with ``eval_gradient`` also ``dK/dtheta``."""

    @abstractmethod
    def diag(self, X: ArrayLike) -> NDArray[np.float64]:
        """``diag(k(X))``, shape ``(n_samples,)``."""

    @property
    def n_dims(self) -> int:
        return int(self.theta.shape[0])

    def leaves(self) -> list[Kernel]:
        """The non-composite kernels in ``theta`` order."""
        return [self]

    def clone_with_theta(self, theta: ArrayLike) -> Kernel:
        """A copy of this kernel with hyperparameters ``theta`` (log space)."""
        new = self.clone()
        new.theta = theta
        return new

    def clone(self) -> Kernel:
        """An independent copy (the same constructor arguments, nested kernels cloned).

        Copies the attributes directly instead of calling the constructor again: the arguments
        were validated when this kernel was made, and solvers clone kernels in their inner loops
        (reading the constructor's signature each time cost more than the linear algebra on
        the small matrices of local models)."""
        new = object.__new__(type(self))
        for k, v in self.__dict__.items():
            if isinstance(v, Kernel):
                v = v.clone()
            elif isinstance(v, np.ndarray):
                v = v.copy()
            new.__dict__[k] = v
        return new

    def __add__(self, other: Kernel) -> Sum:
        if not isinstance(other, Kernel):
            return NotImplemented
        return Sum(self, other)

    def __repr__(self) -> str:
        args = ", ".join(
            f"{k}={v!r}" for k, v in self.get_params(deep=False).items() if "bounds" not in k
        )
        return f"{type(self).__name__}({args})"


class _Stationary(Kernel):
    """Shared part of the stationary kernels ``variance * g(|x_p - x_q| / l)``: parameters,
    ``theta``, bounds, scaled distances and the diagonal (arguments: see SquaredExponential)."""

    def __init__(
        self,
        variance: float = 1.0,
        length_scale: float | ArrayLike = 1.0,
        *,
        variance_bounds: Bounds = (1e-5, 1e5),
        length_scale_bounds: Bounds = (1e-5, 1e5),
    ) -> None:
        # Arguments are checked here and stored unchanged (scikit-learn's clone contract).
        check_positive(variance, "variance")
        if np.ndim(variance) != 0:
            raise ValueError(f"variance must be a scalar, got {variance!r}")
        if check_positive(length_scale, "length_scale").ndim > 1:
            raise ValueError(f"length_scale must be a float or a 1-D array, got {length_scale!r}")
        _check_bounds(variance_bounds, "variance_bounds")
        _check_bounds(length_scale_bounds, "length_scale_bounds")
        self.variance = variance
        self.length_scale = length_scale
        self.variance_bounds = variance_bounds
        self.length_scale_bounds = length_scale_bounds

    @property
    def anisotropic(self) -> bool:
        return np.ndim(self.length_scale) == 1

    @property
    def theta(self) -> NDArray[np.float64]:
        if np.ndim(self.length_scale) == 0:  # (the same array, without hstack's overhead)
            return np.log(np.array([self.variance, self.length_scale], dtype=np.float64))
        return np.log(np.hstack([self.variance, np.atleast_1d(self.length_scale)]))

    @theta.setter
    def theta(self, value: ArrayLike) -> None:
        value = np.asarray(value, dtype=np.float64).reshape(-1)
        if value.shape[0] != self.n_dims:
            raise ValueError(f"theta must have {self.n_dims} entries, got {value.shape[0]}")
        self.variance = float(np.exp(value[0]))
        self.length_scale = np.exp(value[1:]) if self.anisotropic else float(np.exp(value[1]))

    @property
    def n_dims(self) -> int:
        return 1 + int(np.size(self.length_scale))

    @property
    def bounds(self) -> NDArray[np.float64]:
        n_ls = np.size(self.length_scale)
        rows = [self.variance_bounds] + [self.length_scale_bounds] * n_ls
        return np.log(np.asarray(rows, dtype=np.float64))

    @property
    def hyperparameter_names(self) -> list[str]:
        if self.anisotropic:
            return ["variance"] + [f"length_scale[{i}]" for i in range(np.size(self.length_scale))]
        return ["variance", "length_scale"]

    def _scaled(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        ls = np.asarray(self.length_scale)
        if self.anisotropic and ls.shape[0] != X.shape[1]:
            raise ValueError(
                f"length_scale has {ls.shape[0]} entries but X has {X.shape[1]} features"
            )
        return X / ls

    def _sqdist(self, X, Y):
        """Scaled inputs of ``X`` and squared scaled distances between ``X`` and ``Y``."""
        X = _as_2d(X, "X")
        Xs = self._scaled(X)
        Ys = Xs if Y is None else self._scaled(_as_2d(Y, "Y"))
        if Xs.shape[1] == 1:  # 1-D inputs (time): a broadcast difference is exact and fast
            d2 = np.subtract(Xs[:, 0][:, None], Ys[:, 0][None, :])
            np.multiply(d2, d2, out=d2)  # (the same bits as ** 2, without a second array)
        else:
            d2 = np.sum(Xs**2, axis=1)[:, None] + np.sum(Ys**2, axis=1)[None, :] - 2.0 * Xs @ Ys.T
            np.maximum(d2, 0.0, out=d2)
            if Y is None:
                np.fill_diagonal(d2, 0.0)  # exact zeros (the expansion leaves rounding errors)
        return Xs, d2

    def _dist(self, X, Y):
        """Scaled inputs of ``X`` and scaled distances between ``X`` and ``Y``."""
        X = _as_2d(X, "X")
        if X.shape[1] == 1:  # 1-D: |x - y| directly (no square and root)
            Xs = self._scaled(X)
            Ys = Xs if Y is None else self._scaled(_as_2d(Y, "Y"))
            d = np.subtract(Xs[:, 0][:, None], Ys[:, 0][None, :])
            return Xs, np.abs(d, out=d)
        Xs, d2 = self._sqdist(X, Y)
        return Xs, np.sqrt(d2)

    def diag(self, X):
        X = _as_2d(X, "X")
        return np.full(X.shape[0], self.variance)


class SquaredExponential(_Stationary):
    """Squared-exponential kernel, Eq. (3): ``variance * exp(-|x_p - x_q|^2 / (2 l^2))``.

    Args:
        variance: signal variance sigma_f^2 (> 0).
        length_scale: characteristic length scale l (> 0); a float for an isotropic kernel or an
            array with one entry per input feature (automatic relevance determination).
        variance_bounds: ``(low, high)`` for ``variance`` during optimisation.
        length_scale_bounds: ``(low, high)`` for every length scale.

    ``theta = log([variance, *length_scale])``.
    """

    def __call__(self, X, Y=None, eval_gradient=False):
        if eval_gradient and Y is not None:
            raise ValueError("eval_gradient is only supported when Y is None")
        Xs, d2 = self._sqdist(X, Y)
        if not eval_gradient:  # Eq. (3) in place in the (fresh) distance array, the same bits
            np.multiply(d2, -0.5, out=d2)
            np.exp(d2, out=d2)
            d2 *= self.variance
            return d2
        K = self.variance * np.exp(-0.5 * d2)  # Eq. (3)
        if self.anisotropic:
            # d/d log l_d of -(x_d - y_d)^2 / (2 l_d^2) = (x_d - y_d)^2 / l_d^2
            per_dim = (Xs[:, None, :] - Xs[None, :, :]) ** 2
            grad = np.concatenate([K[:, :, None], K[:, :, None] * per_dim], axis=2)
        else:
            grad = np.stack([K, K * d2], axis=2)
        return K, grad

    @staticmethod
    def from_sqdist(theta: NDArray[np.float64], sqdist: NDArray[np.float64], eval_gradient: bool):
        """Isotropic ``k`` from unscaled squared distances and ``theta = log([variance, l])``.

        Lets a solver cache the distances of its training inputs across hyperparameter values.
        With ``eval_gradient`` returns ``(K, [dK/dtheta_0, dK/dtheta_1])`` (a list of matrices).
        """
        if not eval_gradient:
            K = np.multiply(sqdist, -0.5 * np.exp(-2.0 * theta[1]))
            np.exp(K, out=K)
            K *= np.exp(theta[0])  # Eq. (3)
            return K
        d2 = sqdist * np.exp(-2.0 * theta[1])
        K = np.multiply(d2, -0.5)
        np.exp(K, out=K)
        K *= np.exp(theta[0])  # Eq. (3)
        d2 *= K
        return K, [K, d2]


#: Widest range of 1-D inputs, in length scales, over which the exponential kernel is
#: evaluated as a product of exponentials (:func:`_exp_neg_abs_diff`).
SEPARABLE_RANGE = 32.0


def _exp_neg_abs_diff(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """``exp(-|x_i - y_j|)`` for 1-D scaled inputs, or ``None`` where their joint range
    exceeds :data:`SEPARABLE_RANGE` (or an input is empty).

    ``exp(-|x_i - y_j|) = min(e^-u_i e^v_j, e^u_i e^-v_j)`` with ``u = x - c``, ``v = y - c``
    and ``c`` the middle of the range: the product with the right sign is at most 1 and the
    other its reciprocal. That is ``n + m`` exponentials instead of ``n m`` (the exponential is
    most of a kernel evaluation's cost). Relative error: a few ulp times the range (below
    1e-14; the direct formula's is about one ulp).
    """
    if x.size == 0 or y.size == 0:
        return None
    lo, hi = min(float(x.min()), float(y.min())), max(float(x.max()), float(y.max()))
    if not hi - lo <= SEPARABLE_RANGE:
        return None
    c = 0.5 * (lo + hi)
    u, v = x - c, y - c
    return separable_exp_neg_abs_diff(np.exp(u), np.exp(-u), np.exp(v), np.exp(-v))


def separable_exp_neg_abs_diff(
    exp_u: NDArray[np.float64],
    exp_neg_u: NDArray[np.float64],
    exp_v: NDArray[np.float64],
    exp_neg_v: NDArray[np.float64],
) -> NDArray[np.float64]:
    """``exp(-|u_i - v_j|) = min(e^-u_i e^v_j, e^u_i e^-v_j)`` from the four exponentials of
    centred, scaled 1-D inputs ``u`` (..., n) and ``v`` (..., m); leading axes are batch axes.
    Returns (..., n, m). Where :func:`_exp_neg_abs_diff` and the stacked likelihood of
    :mod:`lgp_policy.gp.exact` evaluate the exponential kernel as a product."""
    K = exp_neg_u[..., :, None] * exp_v[..., None, :]
    np.minimum(K, exp_u[..., :, None] * exp_neg_v[..., None, :], out=K)
    return K


class Exponential(_Stationary):
    """Exponential (Matern-1/2, Ornstein-Uhlenbeck) kernel: ``variance exp(-|x_p - x_q| / l)``.

    In one dimension it is a first-order Markov process: the posterior mean at ``x`` is a
    *non-negatively* weighted combination of the observations and the prior mean (the equivalent
    kernel of a scalar AR(1) smoother is positive), so it cannot overshoot a step in the data
    the way the squared exponential's ringing interpolant does. This is why the z-process of
    :mod:`lgp_policy.gp.heteroscedastic` uses it.

    Arguments and ``theta`` as for :class:`SquaredExponential`.
    """

    def __call__(self, X, Y=None, eval_gradient=False):
        if eval_gradient and Y is not None:
            raise ValueError("eval_gradient is only supported when Y is None")
        if not eval_gradient and not self.anisotropic and _as_2d(X, "X").shape[1] == 1:
            xs = self._scaled(_as_2d(X, "X"))[:, 0]
            ys = xs if Y is None else self._scaled(_as_2d(Y, "Y"))[:, 0]
            K = _exp_neg_abs_diff(xs, ys)
            if K is not None:
                K *= self.variance
                return K
        Xs, d = self._dist(X, Y)
        if not eval_gradient:  # in place in the (fresh) distance array, the same bits
            np.negative(d, out=d)
            np.exp(d, out=d)
            d *= self.variance
            return d
        K = self.variance * np.exp(-d)
        if self.anisotropic:
            # d/d log l_k of -d = (x_k - y_k)^2 / (l_k^2 d); 0 on the diagonal (d = 0)
            per_dim = (Xs[:, None, :] - Xs[None, :, :]) ** 2
            inv_d = np.divide(1.0, d, out=np.zeros_like(d), where=d > 0)
            grad = np.concatenate([K[:, :, None], (K * inv_d)[:, :, None] * per_dim], axis=2)
        else:
            grad = np.stack([K, K * d], axis=2)
        return K, grad

    @staticmethod
    def from_dist(
        theta: NDArray[np.float64],
        dist: NDArray[np.float64] | Callable[[], NDArray[np.float64]],
        eval_gradient: bool,
        x: NDArray[np.float64] | None = None,
    ):
        """Isotropic ``k`` from unscaled distances and ``theta = log([variance, l])``.

        Lets a solver cache the distances of its training inputs across hyperparameter values.
        With ``eval_gradient`` returns ``(K, [dK/dtheta_0, dK/dtheta_1])`` (a list of matrices).
        ``dist`` may be a function returning them (called only where needed); ``x``: the 1-D
        inputs the distances are between, if any: ``K`` then comes from
        :func:`_exp_neg_abs_diff` where their range allows.
        """
        if x is not None:
            xs = x * np.exp(-theta[1])
            K = _exp_neg_abs_diff(xs, xs)
            if K is not None:
                K *= np.exp(theta[0])
                if not eval_gradient:
                    return K
                d = (dist() if callable(dist) else dist) * np.exp(-theta[1])
                d *= K
                return K, [K, d]
        if callable(dist):
            dist = dist()
        d = dist * np.exp(-theta[1])
        K = np.negative(d) if eval_gradient else np.multiply(dist, -np.exp(-theta[1]))
        np.exp(K, out=K)
        K *= np.exp(theta[0])
        if not eval_gradient:
            return K
        d *= K
        return K, [K, d]


class WhiteNoise(Kernel):
    """White-noise kernel, the ``delta_pq sigma_n^2`` term of Eq. (10).

    Args:
        noise_level: noise variance sigma_n^2 (> 0).
        noise_level_bounds: ``(low, high)`` for ``noise_level`` during optimisation.

    ``theta = log([noise_level])``. ``k(X)`` is ``noise_level * I``; ``k(X, Y)`` is zero.
    """

    is_noise = True

    def __init__(
        self, noise_level: float = 1.0, *, noise_level_bounds: Bounds = (1e-8, 1e5)
    ) -> None:
        if np.ndim(noise_level) != 0:
            raise ValueError(f"noise_level must be a scalar, got {noise_level!r}")
        check_positive(noise_level, "noise_level")
        _check_bounds(noise_level_bounds, "noise_level_bounds")
        self.noise_level = noise_level
        self.noise_level_bounds = noise_level_bounds

    @property
    def theta(self) -> NDArray[np.float64]:
        return np.log(np.array([self.noise_level]))

    @theta.setter
    def theta(self, value: ArrayLike) -> None:
        value = np.asarray(value, dtype=np.float64).reshape(-1)
        if value.shape[0] != 1:
            raise ValueError(f"theta must have 1 entry, got {value.shape[0]}")
        self.noise_level = float(np.exp(value[0]))

    @property
    def n_dims(self) -> int:
        return 1

    @property
    def bounds(self) -> NDArray[np.float64]:
        return np.log(np.asarray([self.noise_level_bounds], dtype=np.float64))

    @property
    def hyperparameter_names(self) -> list[str]:
        return ["noise_level"]

    def __call__(self, X, Y=None, eval_gradient=False):
        X = _as_2d(X, "X")
        if Y is not None:
            if eval_gradient:
                raise ValueError("eval_gradient is only supported when Y is None")
            return np.zeros((X.shape[0], _as_2d(Y, "Y").shape[0]))
        K = self.noise_level * np.eye(X.shape[0])  # Eq. (10), Kronecker delta term
        if eval_gradient:
            return K, K[:, :, None].copy()
        return K

    def diag(self, X):
        X = _as_2d(X, "X")
        return np.full(X.shape[0], self.noise_level)


class Sum(Kernel):
    """``k1 + k2``; ``theta`` is ``theta`` of ``k1`` followed by that of ``k2``."""

    def __init__(self, k1: Kernel, k2: Kernel) -> None:
        if not isinstance(k1, Kernel) or not isinstance(k2, Kernel):
            raise ValueError("k1 and k2 must be Kernel instances")
        self.k1 = k1
        self.k2 = k2

    @property
    def theta(self) -> NDArray[np.float64]:
        return np.hstack([self.k1.theta, self.k2.theta])

    @theta.setter
    def theta(self, value: ArrayLike) -> None:
        value = np.asarray(value, dtype=np.float64).reshape(-1)
        if value.shape[0] != self.n_dims:
            raise ValueError(f"theta must have {self.n_dims} entries, got {value.shape[0]}")
        n1 = self.k1.n_dims
        self.k1.theta = value[:n1]
        self.k2.theta = value[n1:]

    @property
    def bounds(self) -> NDArray[np.float64]:
        return np.vstack([self.k1.bounds, self.k2.bounds])

    @property
    def hyperparameter_names(self) -> list[str]:
        return [f"k1__{n}" for n in self.k1.hyperparameter_names] + [
            f"k2__{n}" for n in self.k2.hyperparameter_names
        ]

    @property
    def n_dims(self) -> int:
        return self.k1.n_dims + self.k2.n_dims

    def leaves(self) -> list[Kernel]:
        return self.k1.leaves() + self.k2.leaves()

    def __call__(self, X, Y=None, eval_gradient=False):
        if eval_gradient:
            K1, G1 = self.k1(X, Y, eval_gradient=True)
            K2, G2 = self.k2(X, Y, eval_gradient=True)
            return K1 + K2, np.concatenate([G1, G2], axis=2)
        return self.k1(X, Y) + self.k2(X, Y)

    def diag(self, X):
        return self.k1.diag(X) + self.k2.diag(X)

    def __repr__(self) -> str:
        return f"{self.k1!r} + {self.k2!r}"
