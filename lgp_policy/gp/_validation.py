"""Input checking shared by the GP estimators.

Every check raises a :class:`ValueError` whose message names the offending argument, so a
caller sees *what* is wrong and *where* (scikit-learn's ``check_array`` habit).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Largest magnitude accepted in ``X`` and ``y``: the GPs square deviations and distances in
#: float64 (largest finite value 1.8e308), so larger values would overflow to inf and NaN.
MAX_ABS_VALUE = 1e100

#: Training inputs whose values of a feature lie within this fraction of that feature's range
#: (``max - min``) of each other, and within ``REPLICATE_ULPS`` float64 spacings of its largest
#: magnitude, are one input: :func:`snap_near_replicates`.
REPLICATE_RTOL = 1e-10
REPLICATE_ULPS = 1024

__all__ = [
    "MAX_ABS_VALUE",
    "REPLICATE_RTOL",
    "REPLICATE_ULPS",
    "check_X",
    "check_X_y",
    "check_positive",
    "check_random_state",
    "snap_near_replicates",
]


def check_X(
    X: ArrayLike,
    *,
    name: str = "X",
    n_features: int | None = None,
    min_samples: int = 1,
) -> NDArray[np.float64]:
    """Return ``X`` as a finite float64 array of shape ``(n_samples, n_features)``.

    Raises:
        ValueError: if ``X`` is not 2-D, is empty, has fewer than ``min_samples`` rows, holds
            NaN or infinity, or has a number of columns other than ``n_features``.
    """
    try:
        arr = np.asarray(X, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array, got {type(X).__name__}") from exc
    if arr.ndim != 2:
        hint = " Reshape 1-D data with X.reshape(-1, 1)." if arr.ndim == 1 else ""
        raise ValueError(
            f"{name} must be 2-D with shape (n_samples, n_features), got ndim={arr.ndim}.{hint}"
        )
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"{name} is empty: shape {arr.shape}")
    if arr.shape[0] < min_samples:
        raise ValueError(
            f"{name} has {arr.shape[0]} sample(s); at least {min_samples} are required"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinity")
    _check_magnitude(arr, name)
    if n_features is not None and arr.shape[1] != n_features:
        raise ValueError(
            f"{name} has {arr.shape[1]} features, but the model was fitted with {n_features}"
        )
    return arr


def check_X_y(
    X: ArrayLike, y: ArrayLike, *, min_samples: int = 2
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Validate training data.

    Returns:
        ``X (n_samples, n_features)`` and ``y`` as float64, ``y`` of shape ``(n_samples,)`` or
        ``(n_samples, n_targets)`` exactly as given; inputs equal up to rounding made equal
        (:func:`snap_near_replicates`).

    Raises:
        ValueError: naming ``X`` or ``y`` for NaN/inf, wrong ndim, empty input, fewer than
            ``min_samples`` samples, or mismatched lengths.
    """
    X_arr = check_X(X, name="X", min_samples=1)
    try:
        y_arr = np.asarray(y, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"y must be a numeric array, got {type(y).__name__}") from exc
    if y_arr.ndim not in (1, 2):
        raise ValueError(
            f"y must have shape (n_samples,) or (n_samples, n_targets), got ndim={y_arr.ndim}"
        )
    if y_arr.size == 0:
        raise ValueError(f"y is empty: shape {y_arr.shape}")
    if y_arr.shape[0] != X_arr.shape[0]:
        raise ValueError(
            f"X and y have mismatched lengths: X has {X_arr.shape[0]} samples, "
            f"y has {y_arr.shape[0]}"
        )
    if not np.all(np.isfinite(y_arr)):
        raise ValueError("y contains NaN or infinity")
    _check_magnitude(y_arr, "y")
    if X_arr.shape[0] < min_samples:
        raise ValueError(
            f"X and y have {X_arr.shape[0]} sample(s); at least {min_samples} are required "
            "to fit a Gaussian process"
        )
    return snap_near_replicates(X_arr), y_arr


def snap_near_replicates(X: NDArray[np.float64]) -> NDArray[np.float64]:
    """``X`` with each feature's values that lie within the feature's rounding tolerance of the
    next smaller value replaced by the smallest value of their run; ``X`` itself (not a copy)
    where there are none. The tolerance is ``REPLICATE_RTOL`` times the feature's range or
    ``REPLICATE_ULPS`` float64 spacings (``eps``) of its largest magnitude, whichever is smaller.

    Rounding is not data. Demonstrations sampled at a fixed rate but of different durations
    share one grid of normalised time ``t / t_end`` only up to rounding: on the LASA
    handwriting set, 1000 grid points became 2121 "distinct" inputs 1e-16 apart, so the
    replicate groups (exact sufficient statistics, pooled noise targets) depended on the last
    bit of a division, and the length-scale floor (the median spacing of distinct inputs,
    :func:`~lgp_policy.gp.heteroscedastic.bound_length_scale`) fell from 1e-3 to 1.1e-16.
    Snapped, they are 1000 inputs with 6 replicates each, as on an exact grid. Both bounds keep
    data apart: 1e-10 of the range is far below any sampling interval (it would take 1e10
    samples), and 1024 spacings of the largest magnitude (2.3e-13 of it) stop a wild value,
    which widens the range, from merging the rest.
    """
    out = None
    for j in range(X.shape[1]):
        ordered = np.sort(X[:, j])
        gaps = np.diff(ordered)
        biggest = max(abs(ordered[0]), abs(ordered[-1]))
        tol = min(
            REPLICATE_RTOL * (ordered[-1] - ordered[0]),
            REPLICATE_ULPS * np.finfo(np.float64).eps * biggest,
        )
        if not np.any((gaps > 0.0) & (gaps <= tol)):  # (the common case: nothing to snap)
            continue
        values, inverse = np.unique(X[:, j], return_inverse=True)
        close = np.diff(values) <= tol
        first = np.concatenate([[True], ~close])  # where a run of close values starts
        snapped = values[first][np.cumsum(first) - 1]
        if out is None:
            out = X.copy()
        out[:, j] = snapped[inverse.reshape(-1)]
    return X if out is None else out


def _check_magnitude(arr: NDArray[np.float64], name: str) -> None:
    big = float(np.max(np.abs(arr)))
    if big > MAX_ABS_VALUE:
        raise ValueError(
            f"{name} has values up to {big:.3g} in magnitude; the GP squares them in float64, "
            f"so |{name}| must stay below {MAX_ABS_VALUE:g}. Rescale {name} (e.g. to SI units "
            "or by its standard deviation)."
        )


def check_positive(value: Any, name: str) -> NDArray[np.float64]:
    """Return ``value`` as a float array after checking that it is finite and > 0."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0 or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError(f"{name} must be finite and positive, got {value!r}")
    return arr


def check_random_state(random_state: Any) -> np.random.Generator:
    """Turn ``None``, an int seed or a ``Generator`` into a ``numpy.random.Generator``."""
    if isinstance(random_state, np.random.Generator):
        return random_state
    if random_state is None or isinstance(random_state, (int, np.integer)):
        return np.random.default_rng(random_state)
    if isinstance(random_state, np.random.RandomState):
        return np.random.default_rng(random_state.randint(0, 2**31 - 1))
    raise ValueError(
        f"random_state must be None, an int or a numpy Generator, got {type(random_state)}"
    )
