"""Degenerate demonstration data: the noise model stays well posed (issue: zero spread).

Sets of demonstrations that coincide exactly somewhere (start, end, mid-way, over an interval),
constant outputs, replicated / near-replicated / distinct time grids, 2-D and 3-D outputs and
outputs of very different scale. Each prediction must be finite, its std within
``[NOISE_BOUNDS[0], 100] x std(y)``, and the mean must stay with the data.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from lgp_policy.gp.heteroscedastic import HeteroscedasticGP
from lgp_policy.gp.local import LocalGP

N_DEMOS, N_STEPS = 4, 40
FLOOR = 1e-3  # NOISE_BOUNDS[0]: the noise std floor relative to std(y)


def demos(grid: str, pinch: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``N_DEMOS`` noisy-shaped trajectories on [0, 1] that coincide exactly where ``pinch`` says.

    grid: ``"replicated"`` (one shared time grid), ``"near"`` (the shared grid + 1e-9 jitter) or
    ``"distinct"`` (each demonstration on its own time stamps, ends included).
    pinch: ``"start"``, ``"end"``, ``"both"``, ``"mid"`` (t = 0.5) or ``"interval"`` (zero spread
    for t in [0.3, 0.6]).
    """
    rng = np.random.default_rng(seed)
    X, y = [], []
    for _ in range(N_DEMOS):
        if grid == "distinct":
            t = np.sort(np.r_[0.0, 0.5, 1.0, rng.uniform(0.0, 1.0, N_STEPS - 3)])
        else:
            t = np.linspace(0.0, 1.0, N_STEPS)
            if grid == "near":
                t = np.clip(t + rng.uniform(-1e-9, 1e-9, t.shape), 0.0, 1.0)
        a, b = rng.normal(0.0, 0.4, 2)
        bump = {
            "start": t,
            "end": 1.0 - t,
            "both": np.sin(np.pi * t),
            "mid": np.abs(np.sin(2.0 * np.pi * t)),
            "interval": np.clip(np.abs(t - 0.45) - 0.15, 0.0, None),
        }[pinch]
        shape = np.sin(2.0 * np.pi * t) + 0.5 * t
        # the pinched values are exactly equal across demonstrations (no rounding noise)
        y.append(np.where(bump == 0.0, shape, shape + bump * (a + b * np.cos(3.0 * t))))
        X.append(t)
    return np.concatenate(X)[:, None], np.concatenate(y)


def check_prediction(mean, std, y, t_test) -> None:
    """Finite, std within [FLOOR, 100] x std(y), and inside [0, 1] the mean stays with the data."""
    scale = np.std(y)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(std))
    assert np.all(std >= 0.99 * FLOOR * scale), std.min() / scale
    assert np.all(std <= 100.0 * scale), std.max() / scale
    lo, hi = y.min() - 0.5 * scale, y.max() + 0.5 * scale
    inside = (t_test[:, 0] >= 0.0) & (t_test[:, 0] <= 1.0)
    assert np.all((mean[inside] > lo) & (mean[inside] < hi)), "the mean left the data"


def spread_at(X, y, t0: float) -> float:
    near = np.abs(X[:, 0] - t0) < 1e-6
    return float(np.ptp(y[near])) if np.any(near) else np.nan


MODELS = {
    "heteroscedastic": lambda: HeteroscedasticGP(random_state=0),
    "vhgp": lambda: HeteroscedasticGP(method="vhgp", random_state=0),
    "local": lambda: LocalGP(max_points=25, random_state=0),
}


@pytest.mark.parametrize("model", sorted(MODELS))
@pytest.mark.parametrize("grid", ["replicated", "near", "distinct"])
@pytest.mark.parametrize("pinch", ["start", "end", "both", "mid", "interval"])
def test_coinciding_demonstrations_give_bounded_finite_predictions(model, grid, pinch):
    X, y = demos(grid, pinch)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = MODELS[model]().fit(X, y)
    t = np.linspace(-0.2, 1.2, 141)[:, None]  # includes extrapolation on both sides
    mean, std = gp.predict(t, return_std=True)
    check_prediction(mean, std, y, t)
    assert np.all(np.isfinite(gp.noise_variance(t)))
    # where the demonstrations coincide the model is far more certain than where they spread
    inside = np.linspace(0.0, 1.0, 101)[:, None]
    _, sd_in = gp.predict(inside, return_std=True)
    pinch_t = {"start": 0.0, "end": 1.0, "both": 0.0, "mid": 0.5, "interval": 0.45}[pinch]
    at = int(np.argmin(np.abs(inside[:, 0] - pinch_t)))
    assert sd_in[at] < 0.3 * np.max(sd_in)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_constant_output_is_reproduced_with_a_small_finite_std(model):
    X = np.tile(np.linspace(0.0, 1.0, 30), 3)[:, None]
    y = np.full(X.shape[0], 2.5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = MODELS[model]().fit(X, y)
    mean, std = gp.predict(np.linspace(-0.5, 1.5, 21)[:, None], return_std=True)
    np.testing.assert_allclose(mean, 2.5, atol=1e-6)
    assert np.all(np.isfinite(std)) and np.all(std > 0) and np.all(std < 0.1 * 2.5)


@pytest.mark.parametrize("model", sorted(MODELS))
@pytest.mark.parametrize("value", [0.0, 3.0, 1000.0, 1e6, -0.35])
def test_a_constant_output_has_the_same_tiny_std_whatever_its_value(model, value):
    """Shifting a constant does not change its std beyond the values' float precision: the
    std is finite, > 0 and a few ulps of the value (c = 1000 had 1.64, c = 1e6 1.6e3)."""
    X = np.tile(np.linspace(0.0, 1.0, 30), 3)[:, None]
    y = np.full(X.shape[0], value)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = MODELS[model]().fit(X, y)
    mean, std = gp.predict(np.linspace(-0.5, 1.5, 21)[:, None], return_std=True)
    np.testing.assert_allclose(mean, value, rtol=1e-12, atol=1e-300)
    assert np.all(np.isfinite(std)) and np.all(std > 0)
    assert np.all(std <= 1e-12 * abs(value) + 1e-100), std.max()
    assert np.all(np.isfinite(gp.noise_variance(X)))


def test_data_scale_is_the_std_or_an_offset_free_float_precision_scale():
    from lgp_policy.gp.heteroscedastic import MIN_DATA_SCALE, _data_scale

    y = np.sin(np.linspace(0.0, 6.0, 50))
    assert _data_scale(y) == np.std(y)
    assert _data_scale(1000.0 + 1e-3 * y) == np.std(1000.0 + 1e-3 * y)
    assert _data_scale(1e-9 * y) == np.std(1e-9 * y)
    for c in (3.0, 1000.0, 1e6, -2.5, 1 / 3):
        scale = _data_scale(np.full(90, c))
        assert 0 < scale <= 1e-14 * abs(c)
        # rounding-level variation of a constant gets the same scale
        assert _data_scale(c + np.spacing(c) * (np.arange(90) % 2)) == pytest.approx(
            scale, rel=1e-12
        )
    assert _data_scale(np.zeros(10)) == MIN_DATA_SCALE
    assert _data_scale(np.zeros(0)) == MIN_DATA_SCALE
    assert 0 < MIN_DATA_SCALE <= 1e-100 and np.isfinite((1e-3 * MIN_DATA_SCALE) ** 2 * 1e300)


@pytest.mark.parametrize("model", sorted(MODELS))
@pytest.mark.parametrize("n_outputs", [2, 3])
def test_multi_output_of_wildly_different_scales(model, n_outputs):
    """Columns of scale 1e6, 1e-6 (and 1): each is modelled on its own scale."""
    X, y1 = demos("distinct", "both", seed=1)
    scales = [1e6, 1e-6, 1.0][:n_outputs]
    Y = np.column_stack([s * np.roll(y1, k) for k, s in enumerate(scales)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = MODELS[model]().fit(X, Y)
    t = np.linspace(0.0, 1.0, 51)[:, None]
    mean, std = gp.predict(t, return_std=True)
    assert mean.shape == std.shape == (51, n_outputs)
    for j in range(n_outputs):
        check_prediction(mean[:, j], std[:, j], Y[:, j], t)
    # the tiny column is not swamped by the huge one: relative predictions agree
    _, std1 = MODELS[model]().fit(X, Y[:, 1]).predict(t, return_std=True)
    np.testing.assert_allclose(std[:, 1], std1, rtol=1e-6)


def test_em_records_its_objective_and_warns_when_stopped_early():
    X, y = demos("distinct", "both", seed=2)
    with pytest.warns(UserWarning, match="stopped without converging"):
        gp = HeteroscedasticGP(max_em_iter=1, tol=1e-12, random_state=0).fit(X, y)
    assert gp.converged_ is False and gp.em_status_ == "max_em_iter reached"
    assert len(gp.em_objective_) == 2
    assert gp.em_objective_[gp.em_best_iter_] == max(gp.em_objective_)
    gp = HeteroscedasticGP(random_state=0).fit(X, y)
    # the kept model is never worse than the homoscedastic GP it starts from (iteration 0)
    assert gp.em_objective_[gp.em_best_iter_] >= gp.em_objective_[0]


def test_noise_bounds_are_validated():
    X, y = demos("replicated", "both")
    for bad in [(0.0, 1.0), (1.0, 0.5), (np.nan, 1.0), "ab"]:
        with pytest.raises(ValueError, match="noise_bounds"):
            HeteroscedasticGP(noise_bounds=bad).fit(X, y)


def test_snap_near_replicates_merges_rounding_not_data():
    from lgp_policy.gp._validation import REPLICATE_RTOL, snap_near_replicates

    grid = np.linspace(0.0, 1.0, 11)
    rounded = np.nextafter(np.nextafter(grid, 2.0), 2.0)  # the same grid, two ulps off
    X = np.c_[np.r_[grid, rounded], np.r_[grid, grid + 10.0 * REPLICATE_RTOL]]
    before = X.copy()
    out = snap_near_replicates(X)
    np.testing.assert_array_equal(X, before)  # the caller's array is not changed
    np.testing.assert_array_equal(out[:11, 0], out[11:, 0])  # rounding: one input
    assert np.unique(out[:, 0]).size == 11
    assert np.max(np.abs(out[:, 0] - X[:, 0])) < 1e-15
    np.testing.assert_array_equal(out[:, 1], X[:, 1])  # 10x the tolerance apart: data
    distinct = np.linspace(0.0, 1.0, 50)[:, None]
    assert snap_near_replicates(distinct) is distinct
    # a wild value widens the range 1e8-fold; samples 1 ms apart stay apart
    wild = np.r_[np.arange(0.0, 10.0, 1e-3), 1e9][:, None]
    assert snap_near_replicates(wild) is wild


@pytest.mark.parametrize("model", [LocalGP, HeteroscedasticGP])
def test_normalised_time_of_demonstrations_of_different_durations_is_a_replicated_grid(model):
    """Demonstrations sampled at a fixed number of steps but of different durations give
    ``t / t_end`` on one grid up to rounding. The fit must be the fit on the exact grid: before,
    the rounding split replicate groups and the length-scale floor (the median spacing of
    distinct inputs) fell to 1e-16, and the std stepped between split and unsplit inputs."""
    n = 120
    rng = np.random.default_rng(3)
    X_round, X_exact, y = [], [], []
    for duration in (2.1, 2.7, 3.3, 3.9, 4.6):
        t = np.arange(n) * (duration / 7.0 / (n - 1)) * 7.0  # seconds, with rounding
        s = (t - t[0]) / (t[-1] - t[0])
        g = np.arange(n) / (n - 1)  # the exact grid
        X_round.append(s)
        X_exact.append(g)
        y.append(np.sin(5.0 * g) + rng.normal(0.0, 0.3) * g * (1.0 - g) * 4.0)
    X_round_a, X_exact_a = np.concatenate(X_round)[:, None], np.concatenate(X_exact)[:, None]
    y_a = np.concatenate(y)
    assert np.unique(X_round_a).size > n  # the rounding did split the grid
    t_test = np.linspace(0.0, 1.0, 401)[:, None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m_round, s_round = model().fit(X_round_a, y_a).predict(t_test, return_std=True)
        m_exact, s_exact = model().fit(X_exact_a, y_a).predict(t_test, return_std=True)
    np.testing.assert_allclose(m_round, m_exact, rtol=0, atol=1e-6 * np.std(y_a))
    np.testing.assert_allclose(s_round, s_exact, rtol=1e-6)
