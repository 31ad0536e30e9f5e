"""LocalGP does not depend on the input's units (``input_scale``, docs/design-gp.md "Input units").

The default kernel's starting values (length scale 1) and bounds, and with them Algorithm 1's
clustering radius, are read in units of ``X / input_scale_``; ``"auto"`` takes the power of 1000
(an SI prefix) that puts each feature's span into ``[1000**-0.5, 1000**0.5)``. Time in
milliseconds or microseconds (or in mega-seconds) gives the seconds' model: the same number of
local models and the same predictions to rounding. Inputs already in that band are used as given
(bit-identical to the fit before the rule).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from lgp_policy.gp.kernels import SquaredExponential, WhiteNoise
from lgp_policy.gp.local import LocalGP, auto_input_scale

RTOL = 1e-7  # rescaled inputs: equal to rounding (measured: means 2e-12 absolute, stds 1e-8)


def period_data(seed=0):
    """The audit's data: 4 noisy demonstrations of one sine period over 5 s, 500 steps each."""
    t = np.tile(np.linspace(0.0, 5.0, 500), 4)
    y = np.sin(2 * np.pi * t / 5.0) + 0.05 * np.random.default_rng(seed).standard_normal(t.size)
    return t, y


T_TEST = np.linspace(0.0, 5.0, 377)


def truth(t):
    return np.sin(2 * np.pi * t / 5.0)


def fit_timed(X, y, **kw):
    start = time.perf_counter()
    model = LocalGP(random_state=0, **kw).fit(X, y)
    return model, time.perf_counter() - start


def assert_same_model(a, b, Xa, Xb):
    """Same clustering and the same predictions (mean, std, latent std, noise) to rounding."""
    assert len(a.models_) == len(b.models_)
    np.testing.assert_array_equal(a.assignments_, b.assignments_)
    mean_a, std_a = a.predict(Xa, return_std=True)
    mean_b, std_b = b.predict(Xb, return_std=True)
    np.testing.assert_allclose(mean_b, mean_a, rtol=RTOL, atol=RTOL * np.ptp(mean_a))
    np.testing.assert_allclose(std_b, std_a, rtol=RTOL)
    latent_a, latent_b = a.predict_latent(Xa)[1], b.predict_latent(Xb)[1]
    # Latent variances: near 0 (a noise-free target) a difference of O(1) terms, so absolute.
    np.testing.assert_allclose(latent_b**2, latent_a**2, rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(b.noise_variance(Xb), a.noise_variance(Xa), rtol=RTOL)


@pytest.fixture(scope="module")
def seconds():
    t, y = period_data()
    model, fit_s = fit_timed(t[:, None], y)
    return t, y, model, fit_s


def test_seconds_reference_is_accurate(seconds):
    _, _, model, _ = seconds
    np.testing.assert_array_equal(model.input_scale_, [1.0])
    assert len(model.models_) == 3
    rmse = np.sqrt(np.mean((model.predict(T_TEST[:, None]) - truth(T_TEST)) ** 2))
    assert rmse < 0.01


def test_milliseconds_give_the_seconds_model(seconds):
    t, y, ref, ref_s = seconds
    model, fit_s = fit_timed(1000.0 * t[:, None], y)
    np.testing.assert_array_equal(model.input_scale_, [1000.0])
    assert_same_model(ref, model, T_TEST[:, None], 1000.0 * T_TEST[:, None])
    # Attributes in input units.
    np.testing.assert_allclose(model.centers_, 1000.0 * ref.centers_, rtol=1e-12)
    np.testing.assert_array_equal(model.X_train_, 1000.0 * t[:, None])
    # Before the rule: 500 local models (one per time step), 10x the fit time, RMSE 0.58.
    assert fit_s < 3.0 * ref_s + 0.5


@pytest.mark.parametrize("factor", [1e6, 1e-6, 1e-3, 1e9])
def test_micro_and_mega_units_give_the_seconds_model(seconds, factor):
    t, y, ref, _ = seconds
    model, _ = fit_timed(factor * t[:, None], y)
    np.testing.assert_allclose(model.input_scale_, [factor], rtol=1e-15)
    assert_same_model(ref, model, T_TEST[:, None], factor * T_TEST[:, None])


def test_offset_inputs(seconds):
    t, y, ref, _ = seconds
    # An offset does not change the span: used as given, the same model up to the rounding of
    # the shifted inputs.
    shifted, _ = fit_timed(t[:, None] + 1e4, y)
    np.testing.assert_array_equal(shifted.input_scale_, [1.0])
    assert_same_model(ref, shifted, T_TEST[:, None], T_TEST[:, None] + 1e4)
    # Milliseconds since some start time: rescaled by the span, not by the magnitude.
    ms, _ = fit_timed(1000.0 * t[:, None] + 1e4, y)
    np.testing.assert_array_equal(ms.input_scale_, [1000.0])
    assert_same_model(ref, ms, T_TEST[:, None], 1000.0 * T_TEST[:, None] + 1e4)


def test_multi_target_and_two_features(seconds):
    t, y, _, _ = seconds
    Y = np.stack([y, np.cos(2 * np.pi * t / 5.0)], axis=1)
    ref = LocalGP(random_state=0).fit(t[:, None], Y)
    ms = LocalGP(random_state=0).fit(1000.0 * t[:, None], Y)
    np.testing.assert_array_equal(ms.input_scale_, [1000.0])
    assert all(e.input_scale_[0] == 1000.0 for e in ms.estimators_)
    for a, b in zip(ref.estimators_, ms.estimators_, strict=True):
        assert_same_model(a, b, T_TEST[:, None], 1000.0 * T_TEST[:, None])
    # Per feature: time in ms next to a unit-scale feature.
    rng = np.random.default_rng(1)
    X = np.stack([t[::8], rng.uniform(0.0, 2.0, t[::8].size)], axis=1)
    y2 = truth(X[:, 0]) + 0.3 * X[:, 1]
    Xq = np.stack([T_TEST, np.linspace(0.0, 2.0, T_TEST.size)], axis=1)
    a = LocalGP(random_state=0).fit(X, y2)
    b = LocalGP(random_state=0).fit(X * [1000.0, 1.0], y2)
    np.testing.assert_array_equal(b.input_scale_, [1000.0, 1.0])
    assert_same_model(a, b, Xq, Xq * [1000.0, 1.0])


def test_auto_rule():
    band = (1000.0**-0.5, 1000.0**0.5)
    for span, scale in [
        (1.0, 1.0),
        (10.0, 1.0),
        (0.04, 1.0),
        (30.0, 1.0),
        (0.02, 1e-3),
        (40.0, 1e3),
        (5000.0, 1e3),
        (5e6, 1e6),
        (5e-6, 1e-6),
        (0.0, 1.0),  # a constant feature
    ]:
        X = np.array([[3.0], [3.0 + span]])
        got = auto_input_scale(X)
        np.testing.assert_allclose(got, [scale], rtol=1e-15, err_msg=f"span {span}")
        if span:
            assert band[0] <= span / got[0] < band[1]
    # Exactly 1 inside the band (the inputs are then used as given).
    X = np.random.default_rng(0).uniform(0.0, 1.0, (50, 3)) * [1.0, 10.0, 0.1]
    assert auto_input_scale(X).tolist() == [1.0, 1.0, 1.0]


def test_explicit_kernels_and_input_scale():
    t, y = period_data()
    X = 1000.0 * t[:, None]
    # An explicit kernel's hyperparameters are in the input's units: used as given.
    explicit = LocalGP(SquaredExponential(1.0, 1000.0) + WhiteNoise(0.1), random_state=0)
    assert explicit.fit(X, y).input_scale_.tolist() == [1.0]
    assert len(explicit.models_) == 3
    # input_scale given: the same model as "auto" where they agree; 1.0 is the input as given.
    auto = LocalGP(random_state=0).fit(X, y)
    given = LocalGP(input_scale=1000.0, random_state=0).fit(X, y)
    assert_same_model(auto, given, X[:50], X[:50])
    assert LocalGP(input_scale=[1.0], random_state=0).fit(X[::20], y[::20]).input_scale_ == [1.0]


@pytest.mark.parametrize("value", [0.0, -1.0, np.nan, np.inf, "seconds", [1.0, 2.0], [[1.0]]])
def test_bad_input_scale(value):
    t, y = period_data()
    with pytest.raises(ValueError, match="input_scale"):
        LocalGP(input_scale=value).fit(t[:40, None], y[:40])
