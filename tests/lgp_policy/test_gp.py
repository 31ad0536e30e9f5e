"""Exact GP: agreement with scikit-learn, analytic gradients, replicates, input checks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from lgp_policy.gp import GaussianProcess
from lgp_policy.kernels import SquaredExponential, WhiteNoise


@pytest.fixture
def data():
    rng = np.random.default_rng(0)
    x = np.sort(rng.uniform(0.0, 5.0, 40))
    X = np.tile(x, 3)[:, None]  # three "demonstrations" on one grid: replicated inputs
    y = np.sin(X[:, 0]) + 0.2 * rng.standard_normal(X.shape[0])
    return X, y


def _kernel():
    return SquaredExponential(1.3, 0.7) + WhiteNoise(0.05)


@pytest.mark.parametrize("collapse", [True, False])
def test_matches_sklearn(data, collapse):
    sk_gp = pytest.importorskip("sklearn.gaussian_process")
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    X, y = data
    gp = GaussianProcess(_kernel(), optimizer=None, collapse_replicates=collapse).fit(X, y)
    sk = sk_gp.GaussianProcessRegressor(
        ConstantKernel(1.3) * RBF(0.7) + WhiteKernel(0.05),
        optimizer=None,
        normalize_y=True,
        alpha=0.0,
    ).fit(X, y)
    Xs = np.linspace(-1.0, 6.0, 57)[:, None]
    m, s = gp.predict(Xs, return_std=True)
    m_sk, s_sk = sk.predict(Xs, return_std=True)
    np.testing.assert_allclose(m, m_sk, atol=1e-6, rtol=0)
    np.testing.assert_allclose(s, s_sk, atol=1e-6, rtol=0)
    assert gp.log_marginal_likelihood() == pytest.approx(
        sk.log_marginal_likelihood_value_, abs=1e-6
    )


@pytest.mark.parametrize("collapse", [True, False])
def test_lml_gradient(data, collapse):
    X, y = data
    gp = GaussianProcess(_kernel(), optimizer=None, collapse_replicates=collapse).fit(X, y)
    theta = gp.kernel_.theta + np.array([0.2, -0.3, 0.4])
    _, grad = gp.log_marginal_likelihood(theta, eval_gradient=True)
    num = approx_fprime(theta, lambda t: gp.log_marginal_likelihood(t), 1e-6)
    np.testing.assert_allclose(grad, num, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("optimizer", ["L-BFGS-B", "CG"])
def test_fit_improves_lml(data, optimizer):
    X, y = data
    fixed = GaussianProcess(_kernel(), optimizer=None).fit(X, y)
    fitted = GaussianProcess(_kernel(), optimizer=optimizer).fit(X, y)
    assert fitted.log_marginal_likelihood() > fixed.log_marginal_likelihood() + 1.0
