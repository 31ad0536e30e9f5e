"""Most-likely heteroscedastic GP on Goldberg et al.'s synthetic set."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from lgp_policy.gp._base import ConvergenceWarning
from lgp_policy.gp.exact import GaussianProcess
from lgp_policy.gp.heteroscedastic import HeteroscedasticGP


def goldberg(n: int, rng: np.random.Generator):
    """x ~ U[0, 1], f = 2 sin(2 pi x), noise sd 0.5 + x (Goldberg et al. 1997)."""
    x = rng.uniform(0.0, 1.0, n)
    return x[:, None], 2.0 * np.sin(2.0 * np.pi * x) + (0.5 + x) * rng.standard_normal(n)


def nlpd(y, mean, std):
    return float(np.mean(0.5 * np.log(2 * np.pi * std**2) + 0.5 * (y - mean) ** 2 / std**2))


@pytest.fixture(scope="module")
def fitted():
    rng = np.random.default_rng(1)
    X, y = goldberg(300, rng)
    X_test, y_test = goldberg(3000, rng)
    with warnings.catch_warnings():
        # an EM that passed its best iteration is recorded (em_status_), not warned about
        warnings.simplefilter("error", ConvergenceWarning)
        het = HeteroscedasticGP(random_state=0).fit(X, y)
    hom = GaussianProcess().fit(X, y)
    return het, hom, X_test, y_test


def test_noise_tracks_truth(fitted):
    het, _, _, _ = fitted
    grid = np.linspace(0.1, 0.9, 9)[:, None]
    sd = np.sqrt(het.noise_variance(grid))
    truth = 0.5 + grid[:, 0]
    np.testing.assert_allclose(sd, truth, rtol=0.25)
    # The z-process is an Ornstein-Uhlenbeck (exponential-kernel) GP, whose posterior mean is
    # rougher than a squared exponential's on this smooth noise (correlation 0.886 against
    # > 0.9), the price of never overshooting a step in the noise (see test_local.py).
    assert np.corrcoef(sd, truth)[0, 1] > 0.85
    # The EM stops at its fixed point: converged, or an oscillation there (measured with the
    # OU z-process: objective -279.8, -242.0, -241.6, -242.9; iteration 2 is kept). It must
    # neither run out of iterations nor fail to improve on the homoscedastic GP.
    assert het.em_status_ in ("converged", "objective decreased"), het.em_status_
    assert het.n_iter_ < het.max_em_iter
    assert het.em_objective_[het.em_best_iter_] > het.em_objective_[0] + 10.0


def test_beats_homoscedastic_nlpd(fitted):
    het, hom, X_test, y_test = fitted
    nlpd_het = nlpd(y_test, *het.predict(X_test, return_std=True))
    nlpd_hom = nlpd(y_test, *hom.predict(X_test, return_std=True))
    assert nlpd_het < nlpd_hom - 0.02
    mean, std = het.predict(X_test, return_std=True)
    coverage = np.mean(np.abs(y_test - mean) < 1.96 * std)
    assert 0.92 < coverage < 0.98


def test_std_is_eq6(fitted):
    het, _, X_test, _ = fitted
    X = X_test[:50]
    _, std = het.predict(X, return_std=True)
    _, std_f = het.predict_latent(X)
    np.testing.assert_allclose(std**2, std_f**2 + het.noise_variance(X), rtol=1e-10)  # Eq. (6)


def test_kersting_sample_estimator_is_deterministic_and_biased_low():
    rng = np.random.default_rng(2)
    X, y = goldberg(300, rng)
    a = HeteroscedasticGP(n_samples=50, random_state=5).fit(X, y)
    b = HeteroscedasticGP(n_samples=50, random_state=5).fit(X, y)
    grid = np.linspace(0.1, 0.9, 9)[:, None]
    np.testing.assert_array_equal(a.noise_variance(grid), b.noise_variance(grid))
    ratio = np.sqrt(a.noise_variance(grid)) / (0.5 + grid[:, 0])
    # Kersting's estimator averaged in the log domain underestimates r(x) (documented).
    assert 0.6 < np.exp(np.mean(np.log(ratio))) < 1.0
    default = HeteroscedasticGP(random_state=5).fit(X, y)
    assert np.mean(default.noise_variance(grid)) > np.mean(a.noise_variance(grid))


def test_multi_target_fits_each_column():
    rng = np.random.default_rng(3)
    X, y = goldberg(80, rng)
    Y = np.column_stack([y, 0.1 * y])
    model = HeteroscedasticGP(random_state=0).fit(X, Y)
    grid = np.linspace(0.0, 1.0, 5)[:, None]
    mean, std = model.predict(grid, return_std=True)
    assert mean.shape == std.shape == model.noise_variance(grid).shape == (5, 2)
    single = HeteroscedasticGP(random_state=model.estimators_[0].random_state).fit(X, y)
    assert single.predict(grid).shape == (5,)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"max_em_iter": 0}, "max_em_iter"), ({"tol": -1.0}, "tol"), ({"n_samples": 0}, "n_samples")],
)
def test_bad_parameters(kwargs, match):
    X, y = goldberg(20, np.random.default_rng(0))
    with pytest.raises(ValueError, match=match):
        HeteroscedasticGP(**kwargs).fit(X, y)
    with pytest.raises(ValueError, match="X contains NaN"):
        HeteroscedasticGP().fit(np.full((3, 1), np.nan), np.zeros(3))


def test_em_searches_stop_at_search_ftol(monkeypatch):
    """Every hyperparameter search of the EM (a global model and a LocalGP's lockstep) runs
    L-BFGS-B with SEARCH_FTOL; the exact GP keeps scipy's default."""
    from lgp_policy.gp import _lbfgsb, exact, heteroscedastic
    from lgp_policy.gp.local import LocalGP

    seen = []
    original = exact.minimize_many

    def spy(evaluate, x0s, bounds, max_iter=200, ftol=_lbfgsb.FTOL):
        seen.append(ftol)
        return original(evaluate, x0s, bounds, max_iter, ftol)

    monkeypatch.setattr(exact, "minimize_many", spy)
    rng = np.random.default_rng(3)
    X = np.sort(rng.uniform(0.0, 1.0, 120))[:, None]
    y = np.sin(6.0 * X[:, 0]) + (0.05 + 0.2 * X[:, 0]) * rng.standard_normal(120)
    HeteroscedasticGP(max_em_iter=2).fit(X, y)
    LocalGP(max_points=40, max_em_iter=2).fit(X, np.c_[y, -y])
    assert seen and set(seen) == {heteroscedastic.SEARCH_FTOL}
    seen.clear()
    GaussianProcess().fit(X, y)
    assert seen == [_lbfgsb.FTOL]


def test_default_kernel_length_scale_is_floored_at_the_input_spacing():
    """With the default kernel the length scale cannot go below the median spacing of the
    inputs (shorter, a squared exponential is white noise on them: on a LASA handwriting set the
    search stopped at 3.4e-5 s against a 6 ms spacing and the mean stepped 3x further than any
    demonstration); an explicit kernel's bounds are kept."""
    from lgp_policy.gp.heteroscedastic import signal_kernel
    from lgp_policy.gp.kernels import SquaredExponential, WhiteNoise

    rng = np.random.default_rng(0)
    X = np.sort(rng.uniform(0.0, 3.0, 300))[:, None]
    y = np.sin(3.0 * X[:, 0]) + 0.1 * rng.standard_normal(300)
    gp = HeteroscedasticGP(random_state=0).fit(X, y)
    floor = float(np.median(np.diff(np.unique(X[:, 0]))))
    se = signal_kernel(gp.gp_.kernel_)
    assert se.length_scale_bounds[0] == pytest.approx(floor)
    assert se.length_scale >= floor
    explicit = SquaredExponential(1.0, 1.0) + WhiteNoise(0.1)
    gp = HeteroscedasticGP(explicit, random_state=0).fit(X, y)
    assert signal_kernel(gp.gp_.kernel_).length_scale_bounds == (1e-5, 1e5)


def test_single_residual_log_bias_is_estimated_from_the_residuals():
    """The log bias of single squared residuals: the Gaussian value 1.27 for Gaussian draws, ~0
    for residuals of one magnitude (persistent offsets of demonstrations), never beyond [0, 1.27]
    (zero residuals, whose logs sit at the floor, do not push it up)."""
    from lgp_policy.gp.heteroscedastic import _single_residual_log_bias

    rng = np.random.default_rng(0)
    gaussian = rng.standard_normal(20000) ** 2
    assert _single_residual_log_bias(gaussian, -30.0, 10.0) == pytest.approx(1.27, abs=0.05)
    offsets = np.repeat([0.9, 1.0, 1.1], 100) ** 2
    assert _single_residual_log_bias(offsets, -30.0, 10.0) < 0.05
    with_zeros = np.r_[np.zeros(50), gaussian[:50]]
    assert 0.0 <= _single_residual_log_bias(with_zeros, -13.8, 4.6) <= 1.2704


@pytest.mark.parametrize("local", [False, True])
def test_noise_of_offset_demonstrations_on_their_own_stamps_matches_their_spread(local):
    """Six demonstrations that each keep their own offset from the mean (growing with t), each
    on its own time stamps: the predicted noise std is their spread about the mean. With the
    Gaussian log bias of a single residual (1.27 nats) it came out 1.7-1.8x too wide. One
    global model pools the trend into its estimate of the bias (1.3x); LocalGP's windows hold
    little of it."""
    from lgp_policy.gp.local import LocalGP

    rng = np.random.default_rng(3)
    offsets = np.array([-1.2, -0.9, -0.7, 0.8, 1.0, 1.1])
    t = np.concatenate([np.sort(rng.uniform(0.0, 1.0, 150)) for _ in offsets])
    spread = 0.02 + 0.2 * t
    y = np.sin(2 * np.pi * t) + np.repeat(offsets, 150) * spread + 0.002 * rng.standard_normal(900)
    model = (LocalGP if local else HeteroscedasticGP)(random_state=0).fit(t[:, None], y)
    grid = np.linspace(0.1, 0.9, 9)
    ratio = np.sqrt(model.noise_variance(grid[:, None])) / (np.std(offsets) * (0.02 + 0.2 * grid))
    if local:
        np.testing.assert_allclose(ratio, 1.0, rtol=0.3)
    else:
        assert np.all((ratio > 1.0) & (ratio < 1.45)), ratio
