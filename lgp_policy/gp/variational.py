"""Variational heteroscedastic GP (VHGP; Lazaro-Gredilla & Titsias 2011), the principled
alternative to the most-likely EM of :mod:`lgp_policy.gp.heteroscedastic`.

Model: ``y_i = f(x_i) + eps_i``, ``eps_i ~ N(0, exp(g(x_i)))``, ``f ~ GP(0, k_f)``,
``g ~ GP(mu_0, k_g)``. The posterior of ``g`` is approximated by ``q(g) = N(mu, Sigma)`` and ``f``
is integrated out exactly, which gives the *marginal variational bound* (their Eq. 5)

    F = log N(y | 0, K_f + R) - 1/4 sum_i Sigma_ii - KL(q(g) || p(g)),
    R = diag(exp(mu_i - Sigma_ii / 2)),

a lower bound on ``log p(y)`` of the heteroscedastic model. At its stationary points
``Sigma = (K_g^-1 + Lambda)^-1`` and ``mu = mu_0 + K_g (Lambda - c / 2)`` with ``Lambda``
diagonal (``c``: the number of replicates at each distinct input, 1 in the paper), so the
bound is maximised over the ``m`` entries of ``Lambda`` (one per distinct input, as
``log Lambda``) and the hyperparameters of ``k_f``, ``k_g`` and ``mu_0`` jointly, with
L-BFGS-B and the analytic gradients below (derived here; ``beta_u = r_u dF/dr_u`` summed over
the replicates at ``u``):

* ``dF/dLambda = (K_g + Sigma o Sigma / 2) (beta - Lambda + c / 2)`` (zero at the fixed point
  ``Lambda = c / 2 + beta`` of the paper);
* ``dF/dmu_0 = sum beta``; ``dF/dtheta_f``: the usual ``1/2 tr((a a^T - K_y^-1) dK_f)``;
* ``dF/dK_g = sym(beta a^T) + P diag(-beta / 2 - c / 4) P^T - W K_g W / 2 - a a^T / 2`` with
  ``a = Lambda - c / 2``, ``W = (K_g + Lambda^-1)^-1`` and ``P = I - W K_g``.

The posterior of ``g`` is a GP on the pseudo-targets ``(K_g + Lambda^-1) a`` with observation
noise ``Lambda^-1``, so the z-process is an ordinary
:class:`~lgp_policy.gp.exact.GaussianProcess` and the result is an
:class:`~lgp_policy.gp.heteroscedastic.EMResult` that :class:`HeteroscedasticGP` and the local
models use unchanged. The predictive noise is ``E[exp(g*)] = exp(mu* + s*^2 / 2)`` (their
Eq. 9), the f-posterior's noise ``R``.

Well-posedness is the same as the EM's: ``log r`` is clipped to ``log_noise_bounds`` (the
data-scaled floor and ceiling; the bound's gradient is zero where the clip is active), the
z-kernel is :func:`~lgp_policy.gp.heteroscedastic.default_noise_kernel` (bounded
hyperparameters) and ``Lambda`` lies in ``[LAMBDA_BOUNDS]``. The homoscedastic GP of the
initialisation is kept when its exact log marginal likelihood exceeds the bound (evidence
against input-dependent noise), so a constant-noise set loses nothing.

Cost: ``O(m^3)`` per bound evaluation (about six ``m x m`` products) for ``m`` distinct inputs,
times at most ``max_iter`` L-BFGS iterations; ``m`` is limited to :data:`MAX_VHGP_INPUTS`.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import scipy.linalg
import scipy.optimize
from numpy.typing import NDArray

from lgp_policy.gp.exact import (
    GaussianProcess,
    Optimizer,
    _cholesky_inverse,
    _Replicates,
    cholesky_with_jitter,
    fit_shared_hyperparameters,
)
from lgp_policy.gp.heteroscedastic import (
    LOG_NOISE_BOUNDS,
    OBJECTIVE_TOL,
    EMResult,
    _signal_length_scale,
    _with_noise_bounds,
    default_noise_kernel,
    fixed_gp,
    signal_kernel,
)
from lgp_policy.gp.kernels import Kernel

__all__ = ["LAMBDA_BOUNDS", "MAX_VHGP_INPUTS", "variational_heteroscedastic"]

#: Bounds of the variational parameters ``Lambda`` (precision of a pseudo-observation of g).
LAMBDA_BOUNDS = (1e-6, 1e6)

#: Most distinct inputs per data set (the bound costs O(m^3) per evaluation, m parameters).
MAX_VHGP_INPUTS = 2000

#: Converged when the bound rose by less than OBJECTIVE_TOL nats per sample over this many
#: L-BFGS iterations.
FLAT_WINDOW = 10

_LOG_2PI = math.log(2.0 * math.pi)


class _Set:
    """One data set on its distinct inputs: ``U``, counts ``c``, means ``ybar``, ``scatter``."""

    def __init__(self, X: NDArray[np.float64], y: NDArray[np.float64]) -> None:
        d = _Replicates(X, y[:, None], collapse=True)
        self.U, self.inverse, self.c = d.X, d.inverse, d.counts
        self.ybar, self.scatter = d.ybar[:, 0], d.scatter[:, 0]
        self.m = self.U.shape[0]
        if self.m > MAX_VHGP_INPUTS:
            raise ValueError(
                f"X has {self.m} distinct inputs; the variational heteroscedastic GP is limited "
                f"to {MAX_VHGP_INPUTS} (O(m^3) per bound evaluation). Use LocalGP or "
                "method='em'."
            )


def _bound(
    s: _Set,
    Kf: NDArray[np.float64],
    dKf: NDArray[np.float64] | None,
    Kg: NDArray[np.float64],
    dKg: NDArray[np.float64] | None,
    mu0: float,
    loglam: NDArray[np.float64],
    lo: float,
    hi: float,
    grad: bool,
):
    """The bound F of one data set and its gradients (log Lambda, theta_f, theta_g, mu_0).

    Also returns ``log r`` at the distinct inputs (clipped) for the final model.
    """
    m, c = s.m, s.c
    lam = np.exp(loglam)
    a = lam - 0.5 * c
    mu = mu0 + Kg @ a
    sq = np.sqrt(lam)
    B = np.eye(m) + sq[:, None] * Kg * sq[None, :]
    LB, _ = cholesky_with_jitter(B)
    V = scipy.linalg.solve_triangular(LB, sq[:, None] * Kg, lower=True, check_finite=False)
    Sigma = Kg - V.T @ V
    dS = np.diag(Sigma)
    raw = mu - 0.5 * dS
    log_r = np.clip(raw, lo, hi)
    inside = (raw > lo) & (raw < hi)
    r = np.exp(log_r)
    Ky = Kf.copy()
    Ky[np.diag_indices_from(Ky)] += r / c
    L, _ = cholesky_with_jitter(Ky)
    alpha = scipy.linalg.cho_solve((L, True), s.ybar, check_finite=False)
    # log N(y | 0, K_f + R) of all samples, through the distinct inputs (replicates exact)
    l1 = (
        -0.5 * float(s.ybar @ alpha)
        - float(np.sum(np.log(np.diag(L))))
        - 0.5 * m * _LOG_2PI
        + float(
            np.sum(-0.5 * (c - 1.0) * (_LOG_2PI + log_r) - 0.5 * np.log(c) - 0.5 * s.scatter / r)
        )
    )
    LBinv = scipy.linalg.lapack.dtrtri(LB, lower=1)[0]
    kl = 0.5 * (
        float(np.sum(LBinv**2))  # tr(B^-1) = tr(K_g^-1 Sigma)
        + float(a @ (Kg @ a))
        - m
        + 2.0 * float(np.sum(np.log(np.diag(LB))))  # log|B| = log|K_g| - log|Sigma|
    )
    F = l1 - 0.25 * float(c @ dS) - kl
    if not grad:
        return F, log_r
    Kinv = _cholesky_inverse(L)
    dl1_dr = 0.5 * (alpha**2 - np.diag(Kinv)) / c - 0.5 * (c - 1.0) / r + 0.5 * s.scatter / r**2
    beta = np.where(inside, r * dl1_dr, 0.0)
    S2 = Sigma * Sigma
    g_lam = (Kg + 0.5 * S2) @ (beta - lam + 0.5 * c) * lam  # w.r.t. log Lambda
    g_mu0 = float(np.sum(beta))
    g_f = np.zeros(0)
    if dKf is not None:
        A = np.outer(alpha, alpha) - Kinv
        g_f = 0.5 * np.einsum("ij,ijk->k", A, dKf)
    g_g = np.zeros(0)
    if dKg is not None:
        W = sq[:, None] * (LBinv.T @ LBinv) * sq[None, :]  # (K_g + Lambda^-1)^-1
        P = np.eye(m) - W @ Kg
        cd = -0.5 * beta - 0.25 * c
        G = 0.5 * (np.outer(beta, a) + np.outer(a, beta))
        G += (P * cd[None, :]) @ P.T
        G -= 0.5 * (W @ Kg @ W + np.outer(a, a))
        g_g = np.einsum("ij,ijk->k", G, dKg)
    return F, log_r, g_lam, g_f, g_g, g_mu0


def variational_heteroscedastic(
    datasets: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    kernel: Kernel,
    noise_kernel: Kernel | None,
    *,
    learn: bool = True,
    optimizer: Optimizer = "L-BFGS-B",
    n_restarts: int = 0,
    max_iter: int = 200,
    collapse_replicates: bool = True,
    random_state: int | np.random.Generator | None = None,
    refit_kernel: Kernel | None = None,
    log_noise_bounds: tuple[float, float] = LOG_NOISE_BOUNDS,
    noise_offset: float | None = None,
    keep_homoscedastic: bool = True,
    **_em_only: Any,
) -> EMResult:
    """VHGP on one or more data sets (module docstring); the same contract as
    :func:`~lgp_policy.gp.heteroscedastic.most_likely_em`.

    With several data sets the hyperparameters (``k_f``, ``k_g``, ``mu_0``) are shared and the
    summed bound is maximised; every data set has its own ``Lambda``. ``learn=False`` keeps the
    kernels (``refit_kernel`` for ``f``) and, if given, ``noise_offset`` fixed and maximises the
    bound over ``Lambda`` only. ``max_iter`` bounds the L-BFGS-B iterations over the bound
    (the EM's ``max_em_iter``, ``tol`` and ``n_samples`` do not apply and are ignored).

    ``objective`` is ``[homoscedastic log marginal likelihood, bound]``; ``best_iter`` is 1 when
    the heteroscedastic model is kept (bound above the homoscedastic evidence, or always with
    ``keep_homoscedastic=False``), else 0.
    ``status``: ``"converged"``, ``"max_iter reached"`` or the optimiser's message.
    """
    lo, hi = (float(b) for b in log_noise_bounds)
    sets = [_Set(X, y) for X, y in datasets]

    make = functools.partial(fixed_gp, collapse_replicates=collapse_replicates)

    # Initialisation: the homoscedastic GP (its noise within the bounds), as the EM's step 1.
    kernel = _with_noise_bounds(kernel, lo, hi)
    hom = [make(kernel).fit(X, y) for X, y in datasets]
    if learn:
        fit_shared_hyperparameters(
            hom,
            optimizer=optimizer,
            n_restarts=n_restarts,
            random_state=random_state,
            max_iter=max_iter,
        )
    homoscedastic_kernel = hom[0].kernel_.clone()
    hom_lml = float(sum(gp.log_marginal_likelihood_value_ for gp in hom))
    sig = signal_kernel(homoscedastic_kernel) if refit_kernel is None else refit_kernel.clone()
    if noise_kernel is None:
        zk = default_noise_kernel(_signal_length_scale(homoscedastic_kernel), (lo, hi))
    else:
        zk = noise_kernel.clone()
    mu0_init = float(np.clip(math.log(max(hom[0]._noise_level, 1e-300)), lo, hi))
    learn_mu0 = noise_offset is None
    mu0_fixed = mu0_init if noise_offset is None else float(noise_offset)

    nf, ng = (sig.n_dims, zk.n_dims) if learn else (0, 0)
    sizes = [s.m for s in sets]
    lam_lo, lam_hi = (math.log(b) for b in LAMBDA_BOUNDS)
    x0 = np.concatenate(
        [
            sig.theta if learn else np.zeros(0),
            zk.theta if learn else np.zeros(0),
            [mu0_init] if learn_mu0 else np.zeros(0),
            *[np.log(np.clip(0.5 * s.c, *LAMBDA_BOUNDS)) for s in sets],
        ]
    )
    bounds = np.concatenate(
        [
            sig.bounds if learn else np.zeros((0, 2)),
            zk.bounds if learn else np.zeros((0, 2)),
            np.array([[lo, hi]]) if learn_mu0 else np.zeros((0, 2)),
            np.tile([lam_lo, lam_hi], (sum(sizes), 1)),
        ]
    )
    fixed_f = None if learn else [sig(s.U) for s in sets]
    fixed_g = None if learn else [zk(s.U) for s in sets]

    def unpack(x):
        i = 0
        tf = x[i : i + nf]
        i += nf
        tg = x[i : i + ng]
        i += ng
        mu0 = float(x[i]) if learn_mu0 else mu0_fixed
        i += int(learn_mu0)
        lams = np.split(x[i:], np.cumsum(sizes)[:-1])
        return tf, tg, mu0, lams

    def total(x, grad: bool = True):
        tf, tg, mu0, lams = unpack(x)
        kf = sig.clone_with_theta(tf) if learn else sig
        kg = zk.clone_with_theta(tg) if learn else zk
        F = 0.0
        g_f, g_g, g_mu, g_l = np.zeros(nf), np.zeros(ng), 0.0, []
        logs = []
        for j, s in enumerate(sets):
            if learn:
                Kf, dKf = kf(s.U, eval_gradient=True)
                Kg, dKg = kg(s.U, eval_gradient=True)
            else:
                assert fixed_f is not None and fixed_g is not None
                Kf, dKf, Kg, dKg = fixed_f[j], None, fixed_g[j], None
            out = _bound(
                s, Kf, dKf if grad else None, Kg, dKg if grad else None, mu0, lams[j], lo, hi, grad
            )
            F += out[0]
            logs.append(out[1])
            if grad:
                g_l.append(out[2])
                if learn:
                    g_f += out[3]
                    g_g += out[4]
                g_mu += out[5]
        if not grad:
            return F, logs
        g = np.concatenate([g_f, g_g, [g_mu] if learn_mu0 else np.zeros(0), *g_l])
        return F, g

    def objective(x):
        try:
            F, g = total(x)
        except np.linalg.LinAlgError:
            return 1e25, np.zeros_like(x)
        if not np.isfinite(F):
            return 1e25, np.zeros_like(x)
        return -F, -g

    n_total = sum(X.shape[0] for X, _ in datasets)
    history: list[float] = []

    def stop_when_flat(intermediate_result: scipy.optimize.OptimizeResult) -> None:
        # The bound's gradient in Lambda is ill-conditioned (by K_g): L-BFGS creeps for
        # hundreds of iterations after the bound has settled (Goldberg: 600 iterations to
        # ftol 1e-7, for 0.5 nats and an NLPD change of 0.003). Stop on the EM's tolerance.
        history.append(-float(intermediate_result.fun))
        if len(history) > FLAT_WINDOW and (
            history[-1] - history[-1 - FLAT_WINDOW] < OBJECTIVE_TOL * n_total
        ):
            raise StopIteration

    res = scipy.optimize.minimize(
        objective,
        x0,
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        callback=stop_when_flat,
        options={"maxiter": int(max_iter), "ftol": 1e-9, "gtol": 1e-5},
    )
    flat = res.status == 99  # stopped by stop_when_flat
    x = np.clip(res.x, bounds[:, 0], bounds[:, 1])
    F, logs = total(x, grad=False)
    tf, tg, mu0, lams = unpack(x)
    if learn:
        sig = sig.clone_with_theta(tf)
        zk = zk.clone_with_theta(tg)
    if res.success or flat:
        status, converged = "converged", True
    elif res.status == 1:
        status, converged = "max_iter reached", False
    else:
        status, converged = f"optimiser stopped: {res.message}", False
    objective_values = [hom_lml, float(F)]
    if F > hom_lml or not keep_homoscedastic:
        gps = [
            make(sig, alpha=np.exp(lr)[s.inverse]).fit(X, y)
            for lr, s, (X, y) in zip(logs, sets, datasets, strict=True)
        ]
        noise_gps: list[GaussianProcess | None] = []
        for s, ll in zip(sets, lams, strict=True):
            lam = np.exp(ll)
            Kg = zk(s.U)
            a = lam - 0.5 * s.c
            t = Kg @ a + a / lam  # pseudo-targets (K_g + Lambda^-1) a
            if s.m == 1:  # a GP needs two samples: two replicates of twice the noise
                noise_gps.append(
                    make(zk, alpha=np.repeat(2.0 / lam, 2)).fit(
                        np.repeat(s.U, 2, 0), np.repeat(t, 2)
                    )
                )
            else:
                noise_gps.append(make(zk, alpha=1.0 / lam).fit(s.U, t))
        best_iter, offset = 1, mu0
    else:
        gps, noise_gps, best_iter = hom, [None] * len(hom), 0
        offset = mu0_init
        sig = signal_kernel(homoscedastic_kernel)
    return EMResult(
        gps,
        noise_gps,
        offset,
        homoscedastic_kernel,
        sig,
        zk,
        int(res.nit),
        converged,
        (lo, hi),
        objective_values,
        best_iter,
        status,
        lognormal_noise=True,
    )
