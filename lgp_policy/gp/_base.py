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

__all__ = ["ConvergenceWarning", "ParamsMixin"]


class ConvergenceWarning(UserWarning):
    """An iterative fit stopped without meeting its tolerance (like scikit-learn's)."""


class ParamsMixin:
    """``get_params`` / ``set_params`` from the ``__init__`` signature (scikit-learn's rules)."""

    @classmethod
    def _param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return sorted(
            p.name
            for p in sig.parameters.values()
            if p.name != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        )

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
