"""scikit-learn's estimator contract without depending on scikit-learn.

:class:`ParamsMixin` gives ``get_params(deep=True)`` and ``set_params(**params)`` from the
constructor's signature, exactly as ``sklearn.base.BaseEstimator`` does, so that
``sklearn.base.clone``, grid searches and pipelines work on the GP estimators and kernels.
Constructors must store every argument unchanged under its own name (validation happens in
``fit``), which is what ``clone`` checks.
"""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lgp_policy.gp._threads import with_single_blas_thread
from lgp_policy.gp._validation import check_X

__all__ = ["ConvergenceWarning", "ParamsMixin"]


class ConvergenceWarning(UserWarning):
    """An iterative fit stopped without meeting its tolerance (like scikit-learn's)."""


#: Constructor parameter names per class (``ParamsMixin._param_names``).
_PARAM_NAMES: dict[type, list[str]] = {}


class ParamsMixin:
    """``get_params`` / ``set_params`` from the ``__init__`` signature (scikit-learn's rules)."""

    @classmethod
    def _param_names(cls) -> list[str]:
        # Read once per class: inspecting the signature cost more than the algebra of the
        # small GPs an EM builds by the hundred.
        names = _PARAM_NAMES.get(cls)
        if names is None:
            sig = inspect.signature(cls.__init__)
            names = _PARAM_NAMES[cls] = sorted(
                p.name
                for p in sig.parameters.values()
                if p.name != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
            )
        return list(names)

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """Constructor parameters; with ``deep``, also ``name__sub`` of nested estimators."""
        out: dict[str, Any] = {}
        for name in self._param_names():
            value = getattr(self, name)
            if deep and hasattr(value, "get_params") and not isinstance(value, type):
                out.update((f"{name}__{k}", v) for k, v in value.get_params(deep=True).items())
            out[name] = value
        return out

    def set_params(self, **params: Any) -> Any:
        """Set parameters (``name`` or nested ``name__sub``); returns ``self``."""
        valid = self._param_names()
        nested: dict[str, dict[str, Any]] = {}
        for key, value in params.items():
            name, _, sub = key.partition("__")
            if name not in valid:
                raise ValueError(
                    f"Invalid parameter {name!r} for {type(self).__name__}; valid: {valid}"
                )
            if sub:
                nested.setdefault(name, {})[sub] = value
            else:
                setattr(self, name, value)
        for name, sub_params in nested.items():
            getattr(self, name).set_params(**sub_params)
        return self


class NoisePredictionsMixin:
    """``predict``, ``predict_latent`` and ``noise_variance`` of the GPs with a noise model
    (:class:`~lgp_policy.gp.HeteroscedasticGP`, :class:`~lgp_policy.gp.LocalGP`), from one
    ``_predict_normalized(X) -> (latent mean, latent variance, r(x))`` in normalised units.
    A model fitted to several targets delegates to its per-target ``estimators_``."""

    estimators_: Any
    n_features_in_: int
    _y_mean: Any
    _y_std: Any

    def _check_fitted(self) -> None:  # pragma: no cover - every subclass defines it
        raise NotImplementedError

    def _predict_normalized(self, X: NDArray[np.float64]) -> tuple[Any, Any, Any]:
        raise NotImplementedError  # pragma: no cover

    def _out(self, a: Any) -> Any:
        return a

    def _stack(self, method: str, X: ArrayLike, **kw: Any) -> Any:
        outs = [getattr(est, method)(X, **kw) for est in self.estimators_ or []]
        if isinstance(outs[0], tuple):
            return tuple(np.stack(parts, axis=1) for parts in zip(*outs, strict=True))
        return np.stack(outs, axis=1)

    @with_single_blas_thread
    def predict(self, X: ArrayLike, return_std: bool = False) -> Any:
        """Mean (Eq. 5) and, with ``return_std``, the std of Eq. (6): ``sqrt(var_f + r(x))``,
        the noise included."""
        self._check_fitted()
        if self.estimators_:
            return self._stack("predict", X, return_std=return_std)
        X = check_X(X, n_features=self.n_features_in_)
        mean, var, r = self._predict_normalized(X)
        mean_out = self._out(mean * self._y_std + self._y_mean)
        if not return_std:
            return mean_out
        return mean_out, self._out(np.sqrt(var + r) * self._y_std)

    @with_single_blas_thread
    def predict_latent(self, X: ArrayLike) -> Any:
        """Mean and noise-free std of ``f(X)``."""
        self._check_fitted()
        if self.estimators_:
            return self._stack("predict_latent", X)
        X = check_X(X, n_features=self.n_features_in_)
        mean, var, _ = self._predict_normalized(X)
        return self._out(mean * self._y_std + self._y_mean), self._out(np.sqrt(var) * self._y_std)

    @with_single_blas_thread
    def noise_variance(self, X: ArrayLike) -> Any:
        """The noise variance r(x) at new inputs (Eq. 6's ``R*``), in units of y^2."""
        self._check_fitted()
        if self.estimators_:
            return self._stack("noise_variance", X)
        X = check_X(X, n_features=self.n_features_in_)
        _, _, r = self._predict_normalized(X)
        return self._out(r * self._y_std**2)
