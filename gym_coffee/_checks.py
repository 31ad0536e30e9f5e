"""Argument checks shared by the env's constructor, ``reset`` options and ``step``: one clear
``ValueError`` naming the argument and what was expected, before any work starts."""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["check_bool", "check_choice", "check_int", "check_real", "check_vector"]


def check_choice(name: str, value: Any, choices: Sequence[Any]) -> Any:
    """``value`` if it is one of ``choices``."""
    if not any(value is c or (type(value) is type(c) and value == c) for c in choices):
        raise ValueError(f"{name} must be one of {list(choices)}, got {value!r}")
    return value


def check_bool(name: str, value: Any) -> bool:
    """``value`` as a bool if it is a bool (Python's or numpy's)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def check_int(name: str, value: Any, low: int, high: int) -> int:
    """``value`` as an int if it is an integer (not a bool) in ``[low, high]``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    if not low <= int(value) <= high:
        raise ValueError(f"{name} must be an integer in [{low}, {high}], got {int(value)}")
    return int(value)


def check_real(name: str, value: Any, low: float, high: float, unit: str = "") -> float:
    """``value`` as a float if it is a finite real number in ``[low, high]``."""
    unit = f" {unit}" if unit else ""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a number in [{low}, {high}]{unit}, got {value!r}")
    value = float(value)
    if not (np.isfinite(value) and low <= value <= high):
        raise ValueError(f"{name} must be a finite number in [{low}, {high}]{unit}, got {value!r}")
    return value


def check_vector(name: str, value: Any, sizes: Sequence[int]) -> NDArray[np.float64]:
    """``value`` as a finite float64 vector whose length is one of ``sizes``."""
    expected = " or ".join(f"({n},)" for n in sizes)
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be a vector of shape {expected}, got {type(value).__name__}"
        ) from None
    if array.ndim != 1 or array.shape[0] not in sizes:
        raise ValueError(f"{name} must have shape {expected}, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite (no NaN or inf), got {array.tolist()}")
    return array
