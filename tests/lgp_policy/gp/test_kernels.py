"""Kernels: values, log-space hyperparameters, analytic gradients, input checks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from lgp_policy.gp.kernels import SEPARABLE_RANGE, Exponential, SquaredExponential, Sum, WhiteNoise


@pytest.fixture
def X():
    return np.random.default_rng(0).uniform(-2.0, 2.0, (7, 2))


KERNELS = [
    SquaredExponential(1.7, 0.6),
    SquaredExponential(0.8, [0.5, 2.0]),
    WhiteNoise(0.3),
    SquaredExponential(1.2, 0.9) + WhiteNoise(0.05),
    Exponential(1.7, 0.6),
    Exponential(0.8, [0.5, 2.0]),
]


def test_squared_exponential_value(X):
    k = SquaredExponential(2.0, 0.7)
    d2 = np.sum((X[:, None, :] - X[None, :, :]) ** 2, axis=2)
    np.testing.assert_allclose(k(X), 2.0 * np.exp(-d2 / (2 * 0.7**2)), rtol=1e-12)  # Eq. (3)
    ard = SquaredExponential(2.0, [0.7, 0.7])
    np.testing.assert_allclose(ard(X), k(X), rtol=1e-12)


def test_exponential_equals_scikit_learn_matern_half(X):
    from sklearn.gaussian_process.kernels import Matern

    ours = Exponential(2.0, [0.7, 1.3])
    ref = 2.0 * Matern(length_scale=[0.7, 1.3], nu=0.5)
    np.testing.assert_allclose(ours(X), ref(X), rtol=1e-12)
    np.testing.assert_allclose(ours(X, X[:3]), ref(X, X[:3]), rtol=1e-12)
    assert not isinstance(ours, SquaredExponential)  # LocalGP's assignment tests for the SE


def test_eq10_white_noise_only_on_the_training_set(X):
    k = SquaredExponential(1.0, 1.0) + WhiteNoise(0.25)
    np.testing.assert_allclose(k(X) - SquaredExponential(1.0, 1.0)(X), 0.25 * np.eye(7))
    np.testing.assert_allclose(k(X, X[:3]), SquaredExponential(1.0, 1.0)(X, X[:3]))
    np.testing.assert_allclose(k.diag(X), np.full(7, 1.25))


@pytest.mark.parametrize("kernel", KERNELS, ids=repr)
def test_gradient_matches_finite_differences(kernel, X):
    K, G = kernel(X, eval_gradient=True)
    assert G.shape == (*K.shape, kernel.n_dims)
    np.testing.assert_allclose(np.diag(K), kernel.diag(X), rtol=1e-12)
    for i, j in [(0, 0), (1, 4), (6, 2)]:

        def entry(theta, i=i, j=j):
            return kernel.clone_with_theta(theta)(X)[i, j]

        num = approx_fprime(kernel.theta, entry, 1e-7)
        np.testing.assert_allclose(G[i, j], num, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("kernel", KERNELS, ids=repr)
def test_theta_is_log_and_round_trips(kernel):
    theta = kernel.theta + 0.3
    k2 = kernel.clone_with_theta(theta)
    np.testing.assert_allclose(k2.theta, theta)
    assert kernel.theta[0] == pytest.approx(theta[0] - 0.3)  # original untouched
    assert kernel.bounds.shape == (kernel.n_dims, 2)
    assert len(kernel.hyperparameter_names) == kernel.n_dims


def test_sum_concatenates_theta():
    k = SquaredExponential(2.0, 3.0) + WhiteNoise(0.5)
    assert isinstance(k, Sum)
    np.testing.assert_allclose(k.theta, np.log([2.0, 3.0, 0.5]))
    assert [leaf.is_noise for leaf in k.leaves()] == [False, True]


@pytest.mark.parametrize(
    ("factory", "name"),
    [
        (lambda: SquaredExponential(0.0, 1.0), "variance"),
        (lambda: SquaredExponential(-1.0, 1.0), "variance"),
        (lambda: SquaredExponential(1.0, 0.0), "length_scale"),
        (lambda: SquaredExponential(1.0, [1.0, -2.0]), "length_scale"),
        (lambda: SquaredExponential(1.0, np.nan), "length_scale"),
        (lambda: WhiteNoise(0.0), "noise_level"),
        (lambda: WhiteNoise(np.inf), "noise_level"),
        (
            lambda: SquaredExponential(1.0, 1.0, length_scale_bounds=(0.0, 1.0)),
            "length_scale_bounds",
        ),
    ],
)
def test_non_positive_hyperparameters_raise(factory, name):
    with pytest.raises(ValueError, match=name):
        factory()


def test_ard_length_scale_must_match_features(X):
    with pytest.raises(ValueError, match="length_scale"):
        SquaredExponential(1.0, [1.0, 1.0, 1.0])(X)


def test_clone_is_independent_and_equal():
    k = SquaredExponential(2.0, np.array([0.5, 1.5])) + WhiteNoise(0.1)
    c = k.clone()
    assert repr(c) == repr(k) and c.get_params(deep=True).keys() == k.get_params(deep=True).keys()
    c.theta = c.theta + 1.0
    c.k1.length_scale[0] = 9.0  # an array attribute is copied, not shared
    np.testing.assert_allclose(k.theta, np.log([2.0, 0.5, 1.5, 0.1]))


@pytest.mark.parametrize("n_features", [1, 2])
def test_cached_distance_forms_equal_the_kernels(n_features):
    X = np.random.default_rng(0).uniform(0.0, 3.0, (12, n_features))
    d2 = np.sum((X[:, None, :] - X[None, :, :]) ** 2, axis=2)
    theta = np.log([1.7, 0.6])
    for kernel, form, dist in (
        (SquaredExponential, SquaredExponential.from_sqdist, d2),
        (Exponential, Exponential.from_dist, np.sqrt(d2)),
    ):
        K, G = kernel(1.7, 0.6)(X, eval_gradient=True)
        K2, G2 = form(theta, dist, True)
        np.testing.assert_allclose(K2, K, rtol=1e-12)
        np.testing.assert_allclose(np.stack(G2, axis=2), G, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(form(theta, dist, False), K, rtol=1e-12)


@pytest.mark.parametrize("length_scale", [0.05, 0.7, 40.0])
def test_exponential_of_1d_inputs_as_a_product_equals_the_direct_formula(length_scale):
    """k(X, Y) and from_dist(..., x=) of 1-D inputs use exp(-|x - y| / l) =
    min(e^-u e^v, e^u e^-v) within SEPARABLE_RANGE length scales, the direct formula beyond."""
    rng = np.random.default_rng(3)
    x = np.sort(rng.uniform(0.0, 3.0, 40))
    y = np.concatenate([[x[5]], rng.uniform(-0.5, 3.5, 25)])  # one equal input: k = variance
    k = Exponential(1.3, length_scale)
    direct = 1.3 * np.exp(-np.abs(x[:, None] - y[None, :]) / length_scale)
    assert (np.ptp(np.r_[x, y]) / length_scale <= SEPARABLE_RANGE) == (length_scale > 0.1)
    np.testing.assert_allclose(k(x[:, None], y[:, None]), direct, rtol=5e-14, atol=0)
    dist = np.abs(x[:, None] - x[None, :])
    theta = np.log([1.3, length_scale])
    K, G = Exponential.from_dist(theta, lambda: dist, True, x=x)
    K0, G0 = k(x[:, None], eval_gradient=True)
    np.testing.assert_allclose(K, K0, rtol=5e-14, atol=0)
    np.testing.assert_allclose(np.stack(G, axis=2), G0, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(Exponential.from_dist(theta, dist, False, x=x), K0, rtol=5e-14)
    np.testing.assert_allclose(np.diag(k(x[:, None])), 1.3, rtol=1e-15)
