"""Variational heteroscedastic GP (``HeteroscedasticGP(method="vhgp")``)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from lgp_policy.gp import variational
from lgp_policy.gp.exact import GaussianProcess
from lgp_policy.gp.heteroscedastic import HeteroscedasticGP
from lgp_policy.gp.kernels import Exponential, SquaredExponential


def noisy_set(n: int, seed: int, sd=lambda x: 0.05 + 0.6 * x**2):
    """A set that is not one of the benchmark's: f = cos(5x), noise sd growing as x^2."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, 1.0, n)
    return x[:, None], np.cos(5.0 * x) + sd(x) * rng.standard_normal(n)


def nlpd(y, mean, std):
    return float(np.mean(0.5 * np.log(2 * np.pi * std**2) + 0.5 * (y - mean) ** 2 / std**2))


def test_bound_gradients_match_finite_differences():
    rng = np.random.default_rng(0)
    X = np.r_[np.tile(np.linspace(0, 1, 8), 2), rng.uniform(0, 1, 6)][:, None]  # replicates too
    y = np.sin(6 * X[:, 0]) + (0.1 + X[:, 0]) * rng.standard_normal(X.shape[0])
    s = variational._Set(X, y)
    kf, kg = SquaredExponential(1.0, 0.3), Exponential(2.0, 0.5)
    loglam = np.log(s.c * 0.5 * rng.uniform(0.8, 1.25, s.m))

    def bound(tf, tg, mu0, ll):
        Kf, dKf = kf.clone_with_theta(tf)(s.U, eval_gradient=True)
        Kg, dKg = kg.clone_with_theta(tg)(s.U, eval_gradient=True)
        return variational._bound(s, Kf, dKf, Kg, dKg, mu0, ll, -20.0, 20.0, True)

    tf, tg, mu0 = kf.theta, kg.theta, -3.0
    _, _, g_lam, g_f, g_g, g_mu = bound(tf, tg, mu0, loglam)
    eps = 1e-6

    def fd(i, which):
        args = [tf.copy(), tg.copy(), mu0, loglam.copy()]
        plus, minus = [a.copy() if isinstance(a, np.ndarray) else a for a in args], list(args)
        minus = [a.copy() if isinstance(a, np.ndarray) else a for a in args]
        if which == 2:
            plus[2], minus[2] = mu0 + eps, mu0 - eps
        else:
            plus[which][i] += eps
            minus[which][i] -= eps
        return (bound(*plus)[0] - bound(*minus)[0]) / (2 * eps)

    np.testing.assert_allclose([fd(i, 3) for i in range(s.m)], g_lam, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose([fd(i, 0) for i in range(2)], g_f, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose([fd(i, 1) for i in range(2)], g_g, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(fd(0, 2), g_mu, rtol=1e-5)


def test_recovers_a_noise_profile_better_than_a_homoscedastic_gp():
    X, y = noisy_set(150, seed=3)
    Xt, yt = noisy_set(2000, seed=4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # converges on its stated tolerance: no warning
        het = HeteroscedasticGP(method="vhgp", random_state=0).fit(X, y)
    hom = GaussianProcess().fit(X, y)
    assert het.em_status_ == "converged" and het.em_best_iter_ == 1
    assert het.em_objective_[1] > het.em_objective_[0]  # bound above the homoscedastic evidence
    grid = np.linspace(0.05, 0.95, 19)[:, None]
    truth = 0.05 + 0.6 * grid[:, 0] ** 2
    err_het = np.abs(np.log(np.sqrt(het.noise_variance(grid)) / truth))
    err_hom = np.abs(np.log(np.sqrt(hom.noise_variance(grid)) / truth))
    assert np.mean(err_het) < 0.5 * np.mean(err_hom), (np.mean(err_het), np.mean(err_hom))
    assert (
        nlpd(yt, *het.predict(Xt, return_std=True))
        < nlpd(yt, *hom.predict(Xt, return_std=True)) - 0.2
    )
    _, std = het.predict(grid, return_std=True)
    _, std_f = het.predict_latent(grid)
    np.testing.assert_allclose(std**2, std_f**2 + het.noise_variance(grid), rtol=1e-10)


def test_constant_noise_costs_nothing():
    X, y = noisy_set(120, seed=5, sd=lambda x: 0.3 + 0.0 * x)
    Xt, yt = noisy_set(2000, seed=6, sd=lambda x: 0.3 + 0.0 * x)
    het = HeteroscedasticGP(method="vhgp", random_state=0).fit(X, y)
    hom = GaussianProcess().fit(X, y)
    loss = nlpd(yt, *het.predict(Xt, return_std=True)) - nlpd(yt, *hom.predict(Xt, return_std=True))
    assert loss < 0.01, loss


def test_vhgp_is_an_option_with_the_estimator_contract():
    from sklearn.base import clone

    est = HeteroscedasticGP(method="vhgp", max_iter=100, noise_bounds=(1e-2, 5.0))
    twin = clone(est)
    assert twin.get_params(deep=False)["method"] == "vhgp"
    assert est.get_params()["method"] == "vhgp" and "method" in HeteroscedasticGP().get_params()
    X, y = noisy_set(40, seed=7)
    Y = np.column_stack([y, 1e3 * y])
    model = twin.fit(X, Y)
    mean, std = model.predict(X[:5], return_std=True)
    assert mean.shape == std.shape == (5, 2)
    np.testing.assert_allclose(std[:, 1], 1e3 * std[:, 0], rtol=1e-3)
    with pytest.raises(ValueError, match="method must be one of"):
        HeteroscedasticGP(method="laplace").fit(X, y)


def test_input_cap_is_stated(monkeypatch):
    monkeypatch.setattr(variational, "MAX_VHGP_INPUTS", 30)
    X, y = noisy_set(31, seed=8)
    with pytest.raises(ValueError, match=r"31 distinct inputs.*limited to 30"):
        HeteroscedasticGP(method="vhgp").fit(X, y)
