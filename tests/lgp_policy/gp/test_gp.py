"""Exact GP: agreement with scikit-learn, analytic gradients, replicates, input checks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from lgp_policy.gp.exact import GaussianProcess, _StackedLML, fit_shared_hyperparameters
from lgp_policy.gp.heteroscedastic import HeteroscedasticGP
from lgp_policy.gp.kernels import Exponential, SquaredExponential, WhiteNoise
from lgp_policy.gp.local import LocalGP


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


def test_replicates_collapsed_equal_dense_after_fitting(data):
    X, y = data
    a = GaussianProcess(_kernel(), collapse_replicates=True).fit(X, y)
    b = GaussianProcess(_kernel(), collapse_replicates=False).fit(X, y)
    assert a._data.X.shape[0] == 40 and b._data.X.shape[0] == 120  # the claim is tested
    np.testing.assert_allclose(a.kernel_.theta, b.kernel_.theta, rtol=1e-5, atol=1e-6)
    Xs = np.linspace(-1.0, 6.0, 31)[:, None]
    b_fixed = GaussianProcess(a.kernel_, optimizer=None, collapse_replicates=False).fit(X, y)
    pa, pb = a.predict(Xs, return_std=True), b_fixed.predict(Xs, return_std=True)
    np.testing.assert_allclose(pa, pb, atol=1e-9)
    np.testing.assert_allclose(a.predict_latent(Xs), b_fixed.predict_latent(Xs), atol=1e-9)
    assert a.log_marginal_likelihood() == pytest.approx(b_fixed.log_marginal_likelihood(), abs=1e-8)


def test_std_splits_into_latent_and_noise(data):
    X, y = data
    gp = GaussianProcess(_kernel()).fit(X, y)
    Xs = np.linspace(0.0, 5.0, 9)[:, None]
    mean, std = gp.predict(Xs, return_std=True)
    mean_f, std_f = gp.predict_latent(Xs)
    np.testing.assert_allclose(mean, mean_f)
    np.testing.assert_allclose(std**2, std_f**2 + gp.noise_variance(Xs), rtol=1e-12)
    assert np.all(std_f < std)
    assert gp.noise_variance(Xs).shape == (9,)


def test_interpolates_without_noise():
    X = np.linspace(0.0, 3.0, 8)[:, None]
    y = np.cos(2.0 * X[:, 0])
    gp = GaussianProcess(SquaredExponential(1.0, 0.5), optimizer=None).fit(X, y)
    mean, std = gp.predict(X, return_std=True)
    np.testing.assert_allclose(mean, y, atol=1e-6)
    assert np.all(std < 1e-3)


def test_multi_target_shares_hyperparameters(data):
    X, y = data
    Y = np.column_stack([y, 3.0 * y + 1.0])
    gp = GaussianProcess(_kernel()).fit(X, Y)
    Xs = np.linspace(0.0, 5.0, 11)[:, None]
    mean, std = gp.predict(Xs, return_std=True)
    assert mean.shape == std.shape == gp.noise_variance(Xs).shape == (11, 2)
    np.testing.assert_allclose(mean[:, 1], 3.0 * mean[:, 0] + 1.0, atol=1e-8)
    np.testing.assert_allclose(std[:, 1], 3.0 * std[:, 0], rtol=1e-8)
    single = GaussianProcess(gp.kernel_, optimizer=None).fit(X, y)
    np.testing.assert_allclose(single.predict(Xs), mean[:, 0], atol=1e-10)


def test_restarts_deterministic_and_no_worse(data):
    X, y = data
    runs = [GaussianProcess(_kernel(), n_restarts=2, random_state=3).fit(X, y) for _ in range(2)]
    np.testing.assert_array_equal(runs[0].kernel_.theta, runs[1].kernel_.theta)
    single = GaussianProcess(_kernel()).fit(X, y)
    assert runs[0].log_marginal_likelihood() >= single.log_marginal_likelihood() - 1e-6


class _Negative(SquaredExponential):
    def __call__(self, X, Y=None, eval_gradient=False):
        return -super().__call__(X, Y, eval_gradient)


def test_not_positive_definite_names_the_remedy(data):
    X, y = data
    from lgp_policy.gp.exact import NotPositiveDefiniteError

    with pytest.raises(NotPositiveDefiniteError, match="WhiteNoise"):
        GaussianProcess(_Negative(1.0, 1.0), optimizer=None).fit(X, y)


def test_jitter_rescues_near_singular_matrix():
    X = np.vstack([np.linspace(0, 1, 30)[:, None]] * 2)  # replicates, no noise term
    y = np.tile(np.sin(np.linspace(0, 1, 30)), 2)
    gp = GaussianProcess(SquaredExponential(1.0, 0.3), optimizer=None).fit(X, y)
    assert gp.jitter_ > 0
    np.testing.assert_allclose(gp.predict(X), y, atol=1e-3)


@pytest.mark.parametrize(
    ("X", "y", "match"),
    [
        (np.array([[0.0], [np.nan], [1.0]]), np.zeros(3), "X contains NaN"),
        (np.array([[0.0], [1.0], [2.0]]), np.array([0.0, np.inf, 1.0]), "y contains NaN"),
        (np.zeros((3, 1)), np.zeros(4), "mismatched lengths"),
        (np.zeros(3), np.zeros(3), "X must be 2-D"),
        (np.zeros((3, 1, 1)), np.zeros(3), "X must be 2-D"),
        (np.zeros((3, 1)), np.zeros((3, 1, 1)), "y must have shape"),
        (np.zeros((0, 1)), np.zeros(0), "X is empty"),
        (np.zeros((1, 1)), np.zeros(1), "at least 2"),
    ],
)
def test_bad_input_raises_value_error(X, y, match):
    with pytest.raises(ValueError, match=match):
        GaussianProcess(_kernel()).fit(X, y)


def test_bad_arguments_raise(data):
    X, y = data
    with pytest.raises(ValueError, match="optimizer"):
        GaussianProcess(optimizer="BFGS").fit(X, y)
    with pytest.raises(ValueError, match="alpha"):
        GaussianProcess(alpha=np.ones(3)).fit(X, y)
    with pytest.raises(ValueError, match="alpha"):
        GaussianProcess(alpha=-1.0).fit(X, y)
    with pytest.raises(ValueError, match="n_restarts"):
        GaussianProcess(n_restarts=-1).fit(X, y)
    gp = GaussianProcess(_kernel(), optimizer=None).fit(X, y)
    with pytest.raises(ValueError, match="features"):
        gp.predict(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="theta"):
        gp.log_marginal_likelihood(np.zeros(5))
    with pytest.raises(ValueError, match="not fitted"):
        GaussianProcess().predict(np.zeros((2, 1)))


@pytest.mark.parametrize("collapse", [True, False])
def test_latent_at_training_shortcut_equals_prediction(data, collapse):
    X, y = data
    gp = GaussianProcess(_kernel(), alpha=0.01, collapse_replicates=collapse).fit(X, y)
    mean, var = gp._latent_at_training()
    ref_mean, ref_var = gp._predict_normalized(gp._data.X)
    np.testing.assert_allclose(mean, ref_mean, atol=1e-9)
    np.testing.assert_allclose(var, ref_var, atol=1e-9)


def test_refuses_data_it_cannot_represent():
    """Finite but huge values would overflow when squared: one clear error naming the argument."""
    X = np.linspace(0.0, 1.0, 10)[:, None]
    y = np.sin(X[:, 0])
    for model in (GaussianProcess(), HeteroscedasticGP(), LocalGP()):
        with pytest.raises(
            ValueError, match=r"^y has values up to 8.41e\+299.*must stay below 1e\+100"
        ):
            model.fit(X, y * 1e300)
        with pytest.raises(ValueError, match=r"^X has values up to"):
            model.fit(X * 1e200, y)
        with pytest.raises(ValueError, match=r"^y contains NaN"):
            model.fit(X, np.where(X[:, 0] > 0.5, np.nan, y))
        with pytest.raises(ValueError, match=r"^X contains NaN"):
            model.fit(np.where(X > 0.5, np.inf, X), y)
    gp = GaussianProcess().fit(X, y)
    with pytest.raises(ValueError, match=r"^X contains NaN"):
        gp.predict(np.array([[np.nan]]))


def test_exact_gp_refuses_more_inputs_than_it_can_hold_and_points_to_local_gp(monkeypatch):
    import lgp_policy.gp.exact as exact

    monkeypatch.setattr(exact, "MAX_EXACT_INPUTS", 50)
    X = np.linspace(0.0, 1.0, 51)[:, None]
    with pytest.raises(ValueError, match=r"51 distinct inputs.*limited to 50.*LocalGP"):
        GaussianProcess().fit(X, np.sin(X[:, 0]))
    # replicates are free: 4 x 50 samples on 50 distinct inputs are accepted
    X4 = np.tile(np.linspace(0.0, 1.0, 50), 4)[:, None]
    GaussianProcess(optimizer=None).fit(X4, np.sin(X4[:, 0]))


def test_estimators_follow_the_scikit_learn_contract():
    from sklearn.base import clone

    for est in (
        GaussianProcess(SquaredExponential(2.0, [0.5, 1.0]) + WhiteNoise(0.1), n_restarts=2),
        HeteroscedasticGP(noise_bounds=(1e-2, 5.0), max_em_iter=3),
        LocalGP(max_points=50, combine="product"),
    ):
        twin = clone(est)
        assert type(twin) is type(est)
        p, q = est.get_params(deep=False), twin.get_params(deep=False)
        assert p.keys() == q.keys()
        for k in p:
            if hasattr(p[k], "get_params"):
                assert repr(p[k]) == repr(q[k]) and p[k] is not q[k]
            else:
                assert p[k] is q[k] or p[k] == q[k]
    gp = GaussianProcess(SquaredExponential(1.0, 1.0) + WhiteNoise(0.1))
    deep = gp.get_params(deep=True)
    assert deep["kernel__k1__length_scale"] == 1.0
    gp.set_params(kernel__k1__length_scale=0.3, n_restarts=1)
    assert gp.kernel.k1.length_scale == 0.3 and gp.n_restarts == 1
    with pytest.raises(ValueError, match="Invalid parameter 'nope'"):
        gp.set_params(nope=1)


@pytest.mark.parametrize(
    "kernel, per_sample_noise",
    [
        (SquaredExponential(1.0, 0.3) + WhiteNoise(0.1), False),
        (Exponential(1.0, 0.5), True),  # the z-process: known noise, no WhiteNoise term
        (SquaredExponential(2.0, 0.2), True),  # the refit of f with R = diag(r(x_i))
    ],
)
def test_stacked_lml_equals_the_sum_of_the_models(kernel, per_sample_noise):
    """The batched sum of local models' Eq. (4) (padded blocks) is the sum of their _lml,
    value and gradient, for models of different sizes with and without replicates."""
    rng = np.random.default_rng(1)
    gps = []
    for n, reps in ((30, 5), (17, 0), (25, 12)):
        x = np.sort(rng.uniform(0.0, 1.0, n))
        idx = np.concatenate([np.arange(n), np.arange(reps), np.arange(reps)])
        X = x[idx][:, None]
        y = np.sin(6.0 * X[:, 0]) + 0.1 * rng.standard_normal(X.shape[0])
        alpha = np.exp(rng.uniform(-4.0, -1.0, n))[idx] if per_sample_noise else 0.0
        gps.append(
            GaussianProcess(kernel, optimizer=None, normalize_y=False, alpha=alpha).fit(X, y)
        )
    stacked = _StackedLML.build(gps)
    assert stacked is not None
    for shift in (0.0, 0.4, -0.7):
        theta = kernel.theta + shift
        value, grad = stacked(theta)
        parts = [gp._lml(theta, eval_gradient=True) for gp in gps]
        assert value == pytest.approx(sum(p[0] for p in parts), rel=1e-12, abs=1e-10)
        np.testing.assert_allclose(grad, np.sum([p[1] for p in parts], axis=0), atol=1e-9)


@pytest.mark.parametrize(
    "kernel, per_sample_noise",
    [
        (SquaredExponential(1.0, 0.1) + WhiteNoise(0.1), False),  # step 1 of the EM
        (Exponential(1.0, 0.2), False),  # the z-process: the same known noise everywhere
    ],
)
def test_stacked_lml_shares_the_factorisation_of_equal_windows(kernel, per_sample_noise):
    """Windows of one time grid (replicated, as demonstrations are) have the same K_y up to the
    last bits of their distances: they are one problem with the windows' targets side by side,
    and the kernel is evaluated on the grid's distinct distances; the value and the gradient
    are still the sum of the windows' _lml."""
    rng = np.random.default_rng(3)
    grid = np.linspace(0.0, 1.0, 200)
    gps = []
    for lo, hi in ((0, 46), (46, 92), (92, 138), (138, 150)):  # three equal windows, one short
        X = np.tile(grid[lo:hi], 4)[:, None]
        y = np.sin(6.0 * X[:, 0]) + 0.1 * rng.standard_normal(X.shape[0])
        alpha = 0.0 if kernel.leaves()[-1].is_noise else 0.3
        gps.append(
            GaussianProcess(kernel, optimizer=None, normalize_y=False, alpha=alpha).fit(X, y)
        )
    stacked = _StackedLML.build(gps)
    assert stacked is not None
    assert stacked.Y.shape[0] == 2  # the three equal windows are one problem
    assert set(stacked.distinct) == {type(leaf).__name__ for leaf in kernel.leaves()} - {
        "WhiteNoise"
    }  # the kernel is evaluated on the grid's distinct distances
    for shift in (0.0, 0.5, -0.8):
        theta = kernel.theta + shift
        value, grad = stacked(theta)
        parts = [gp._lml(theta, eval_gradient=True) for gp in gps]
        assert value == pytest.approx(sum(p[0] for p in parts), rel=1e-11)
        np.testing.assert_allclose(
            grad, np.sum([p[1] for p in parts], axis=0), rtol=1e-9, atol=1e-8
        )


def test_derived_gp_equals_a_prepared_one(data):
    """_derive (the EM's later steps on the same inputs) gives the GP _prepare would."""
    X, y = data
    kernel = SquaredExponential(1.3, 0.7)
    base = GaussianProcess(_kernel(), optimizer=None, normalize_y=False).fit(X, y)
    alpha_u = np.exp(np.sin(3.0 * base._data.X[:, 0]) - 2.0)  # per distinct input
    y2 = np.cos(X[:, 0])
    derived = base._derive(kernel, alpha=alpha_u, y=y2)
    derived._solve()
    fresh = GaussianProcess(
        kernel, optimizer=None, normalize_y=False, alpha=alpha_u[base._data.inverse]
    ).fit(X, y2)
    assert derived._data.collapsed and fresh._data.collapsed
    np.testing.assert_array_equal(derived.alpha_, fresh.alpha_)
    np.testing.assert_array_equal(derived.L_, fresh.L_)
    assert derived.log_marginal_likelihood_value_ == fresh.log_marginal_likelihood_value_
    Xs = np.linspace(0.0, 5.0, 7)[:, None]
    np.testing.assert_array_equal(derived.predict(Xs), fresh.predict(Xs))
    with pytest.raises(ValueError, match="normalize_y"):
        GaussianProcess(_kernel(), optimizer=None).fit(X, y)._derive(kernel)


def test_shared_hyperparameters_same_with_and_without_stacking(data, monkeypatch):
    X, y = data
    parts = [(X[i::3], y[i::3]) for i in range(3)]

    def learn():
        gps = [GaussianProcess(_kernel(), optimizer=None).fit(Xp, yp) for Xp, yp in parts]
        return fit_shared_hyperparameters(gps)

    stacked = learn()
    monkeypatch.setattr(_StackedLML, "build", classmethod(lambda cls, gps, cache=None: None))
    np.testing.assert_allclose(learn(), stacked, atol=1e-5)


def test_prepared_gps_learn_the_same_as_fitted_ones(data):
    """``_prepare`` skips only the factorisation that fit_shared_hyperparameters redoes."""
    X, y = data
    parts = [(X[i::3], y[i::3]) for i in range(3)]
    fitted = [GaussianProcess(_kernel(), optimizer=None).fit(Xp, yp) for Xp, yp in parts]
    prepared = [GaussianProcess(_kernel(), optimizer=None)._prepare(Xp, yp) for Xp, yp in parts]
    assert not hasattr(prepared[0], "alpha_")
    np.testing.assert_allclose(
        fit_shared_hyperparameters(prepared), fit_shared_hyperparameters(fitted), atol=1e-10
    )
    Xs = np.linspace(0.0, 5.0, 7)[:, None]
    for a, b in zip(prepared, fitted, strict=True):
        np.testing.assert_allclose(a.predict(Xs, return_std=True), b.predict(Xs, return_std=True))
        np.testing.assert_allclose(a._latent_mean_at_training(), a._latent_at_training()[0])


def test_stacked_owners_evaluate_each_owners_sum():
    """Several owners (outputs, each with its local models and its own theta) in one stack:
    any subset of them evaluated together gives each owner's own sum of _lml."""
    rng = np.random.default_rng(5)
    kernel = SquaredExponential(1.0, 0.1)
    owners = []
    for o in range(3):
        gps = []
        for lo, hi in ((0, 30), (30, 60), (60, 70)):
            x = np.linspace(0.0, 1.0, 100)[lo:hi]
            X = np.tile(x, 3)[:, None]
            y = np.sin((3 + o) * X[:, 0]) + 0.1 * rng.standard_normal(X.shape[0])
            alpha = np.tile(np.exp(rng.uniform(-4.0, -1.0, hi - lo)), 3)
            gps.append(
                GaussianProcess(kernel, optimizer=None, normalize_y=False, alpha=alpha).fit(X, y)
            )
        owners.append(gps)
    stacked = _StackedLML.build_many(owners)
    assert stacked is not None
    thetas = [kernel.theta + np.array([0.3 * o, -0.2 * o]) for o in range(3)]
    for subset in ([0, 1, 2], [2], [0, 2]):
        results = stacked.evaluate(subset, [thetas[o] for o in subset])
        for o, res in zip(subset, results, strict=True):
            assert res is not None
            parts = [gp._lml(thetas[o], eval_gradient=True) for gp in owners[o]]
            assert res[0] == pytest.approx(sum(p[0] for p in parts), rel=1e-11)
            np.testing.assert_allclose(res[1], np.sum([p[1] for p in parts], axis=0), rtol=1e-9)


def test_stacked_set_theta_equals_each_gps_own():
    """The batched set-up after a lockstep search (one factorisation per problem, shared by
    equal windows) leaves every GP as its own _set_theta would, to rounding."""
    from lgp_policy.gp.exact import fit_shared_hyperparameters_many

    rng = np.random.default_rng(6)
    grid = np.linspace(0.0, 1.0, 100)
    groups = []
    for o in range(3):
        gps = []
        for lo, hi in ((0, 30), (30, 60), (60, 70)):
            X = np.tile(grid[lo:hi], 3)[:, None]
            y = np.sin((3 + o) * X[:, 0]) + 0.1 * rng.standard_normal(X.shape[0])
            gps.append(GaussianProcess(_kernel(), optimizer=None, normalize_y=False)._prepare(X, y))
        groups.append(gps)
    thetas = fit_shared_hyperparameters_many(groups)
    Xs = np.linspace(0.0, 1.0, 9)[:, None]
    for gps, theta in zip(groups, thetas, strict=True):
        for gp in gps:
            ref = GaussianProcess(_kernel(), optimizer=None, normalize_y=False)._prepare(
                gp.X_train_, gp.y_train_
            )
            ref._set_theta(theta)
            np.testing.assert_allclose(gp.kernel_.theta, theta)
            np.testing.assert_allclose(gp.L_, ref.L_, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(gp.alpha_, ref.alpha_, rtol=1e-9, atol=1e-10)
            assert gp.log_marginal_likelihood_value_ == pytest.approx(
                ref.log_marginal_likelihood_value_, rel=1e-11
            )
            np.testing.assert_allclose(gp.predict(Xs), ref.predict(Xs), rtol=1e-9, atol=1e-10)


def test_one_group_in_lockstep_equals_fit_shared_hyperparameters():
    """A single group (a single-output LocalGP's learning steps) takes the lockstep path and
    its batched set-up: the same theta and the same fitted GPs as fit_shared_hyperparameters,
    on distinct inputs (one problem per GP) and on replicated ones (equal windows)."""
    from lgp_policy.gp.exact import fit_shared_hyperparameters, fit_shared_hyperparameters_many

    rng = np.random.default_rng(8)
    for replicated in (False, True):
        data = []
        for lo in (0.0, 0.3, 0.6):
            t = np.linspace(lo, lo + 0.3, 25)
            X = (np.tile(t, 3) if replicated else np.sort(rng.uniform(lo, lo + 0.3, 75)))[:, None]
            data.append((X, np.sin(5 * X[:, 0]) + 0.1 * rng.standard_normal(75)))

        many, one = (
            [
                GaussianProcess(_kernel(), optimizer=None, normalize_y=False)._prepare(X, y)
                for X, y in data
            ]
            for _ in range(2)
        )
        (theta,) = fit_shared_hyperparameters_many([many])
        ref = fit_shared_hyperparameters(one)
        np.testing.assert_allclose(theta, ref, rtol=1e-10, atol=1e-12)
        assert sum(gp.n_lml_evaluations_ for gp in many) == sum(gp.n_lml_evaluations_ for gp in one)
        Xs = np.linspace(0.0, 0.9, 7)[:, None]
        for a, b in zip(many, one, strict=True):
            assert a.log_marginal_likelihood_value_ == pytest.approx(
                b.log_marginal_likelihood_value_, rel=1e-11
            )
            np.testing.assert_allclose(
                a.predict(Xs, return_std=True), b.predict(Xs, return_std=True), rtol=1e-9
            )


def test_stacked_exponential_of_1d_inputs_is_separable_and_equals_the_sum(monkeypatch):
    """The z-process's exponential kernel on 1-D distinct inputs is evaluated as a product of
    exponentials (2 m per problem instead of m^2) while every problem's range is within
    SEPARABLE_RANGE length scales, and directly beyond; both equal the sum of the models'
    _lml (value and gradient)."""
    from lgp_policy.gp.kernels import SEPARABLE_RANGE

    rng = np.random.default_rng(4)
    kernel = Exponential(1.0, 0.5)
    gps = []
    for lo, n in ((0.0, 40), (1.0, 23), (2.0, 31)):
        X = np.sort(rng.uniform(lo, lo + 1.0, n))[:, None]
        y = np.sin(6.0 * X[:, 0]) + 0.1 * rng.standard_normal(n)
        alpha = np.exp(rng.uniform(-4.0, -1.0, n))
        gps.append(
            GaussianProcess(kernel, optimizer=None, normalize_y=False, alpha=alpha).fit(X, y)
        )
    stacked = _StackedLML.build(gps)
    assert stacked is not None and stacked.centred is not None
    widest = max(float(np.ptp(gp._data.X)) for gp in gps)
    calls = []
    original = np.minimum

    def minimum(*args, **kwargs):  # the separable form's min(e^-u e^v, e^u e^-v)
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(np, "minimum", minimum)
    for log_l, separable in ((np.log(0.5), True), (np.log(widest / SEPARABLE_RANGE) - 0.1, False)):
        theta = np.array([0.3, log_l])
        calls.clear()
        value, grad = stacked(theta)
        assert bool(calls) == separable
        parts = [gp._lml(theta, eval_gradient=True) for gp in gps]
        assert value == pytest.approx(sum(p[0] for p in parts), rel=1e-12, abs=1e-10)
        np.testing.assert_allclose(grad, np.sum([p[1] for p in parts], axis=0), atol=1e-9)
