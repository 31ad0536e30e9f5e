"""Fig. 6 of the paper: training and prediction time of the exact and the local GP against n.

Data: 4 trajectory-like demonstrations on one time grid of [0, 10] s (``n / 4`` steps each), a
smooth mean trajectory plus heteroscedastic noise (large while the demonstrations "start
anywhere", small at "constraints"). Prediction: 2000 time points; accuracy is measured there
against the true mean (RMSE) and against a held-out fifth demonstration on the same 2000 time
points (NLPD, 95% coverage of the predictive interval including the noise).

Methods (all fit their hyperparameters by maximising the log marginal likelihood):

* ``exact``: :class:`lgp_policy.GaussianProcess` with ``collapse_replicates=False`` (dense
  ``O(n^3)`` Cholesky on all n points);
* ``exact-grid``: the same GP on the replicate-averaged grid (``n / 4`` unique times, noise / 4),
  posterior identical to ``exact`` (tested in ``tests/lgp_policy/test_gp.py``);
* ``sklearn``: ``GaussianProcessRegressor(C * RBF + WhiteKernel, normalize_y=True)``;
* ``local-<rule>``: :class:`lgp_policy.LocalGP` of heteroscedastic local GPs (the paper's model),
  one fit, predictions combined by each rule; ``local-product-noisy`` multiplies the *noisy*
  local predictions (the known trap);
* ``celerite2``: O(n) solver for 1-D inputs with an SHO kernel (Q = 1/sqrt(2), a smooth kernel but
  not the squared exponential), hyperparameters by L-BFGS-B on its likelihood.

Inputs (``--inputs``): ``replicated`` (the demonstrations on one time grid) and ``distinct`` (each
demonstration on its own time stamps, as real demonstrations are); a second table puts the two
side by side for every n and method.

Where ``exact`` and ``sklearn`` would take too long (n above ``--max-exact``), their fit time is
extrapolated as (measured time of ONE likelihood+gradient evaluation at that n) x (number of
evaluations the optimiser needed at the largest n run in full), and their prediction time as the
largest measured one scaled by n^2; such rows are marked ``extrap.``. With
``--max-extrapolate`` below n (no evaluation at that n either), the target check scales
scikit-learn's measured cost at its largest n by n^3 and says that it is an estimate. Threads:
BLAS is pinned to one thread with threadpoolctl.

The figures in ``docs/design-gp.md``::

    python benchmarks/gp_scaling.py --sizes 2000 8000 --max-exact 2000 --max-extrapolate 2000 \
        --no-celerite

Usage::

    python benchmarks/gp_scaling.py            # full run (several minutes)
    python benchmarks/gp_scaling.py --quick    # smoke run (seconds)
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")

import numpy as np
import scipy.optimize

from lgp_policy._io import atomic_write_bytes, atomic_write_text, check_output_path
from lgp_policy.gp.exact import GaussianProcess
from lgp_policy.gp.kernels import SquaredExponential, WhiteNoise
from lgp_policy.gp.local import DEFAULT_COMBINE, LocalGP

N_DEMOS = 4
N_PREDICT = 2000
DURATION_S = 10.0
RULES = ("product", "rbcm", "nearest")
CALIBRATED_RULE = DEFAULT_COMBINE  # LocalGP's one default rule
Z95 = 1.959964


def truth(t: np.ndarray) -> np.ndarray:
    """Mean trajectory (rad): a slow swing, a fast transfer at t = 5 s and a drift."""
    return 0.5 * np.sin(0.8 * t) + 0.3 * np.tanh(2.0 * (t - 5.0)) + 0.1 * t


def noise_sd(t: np.ndarray) -> np.ndarray:
    """Spread between demonstrations (rad): wide early, tight at t ~ 5 s and at the end."""
    return (
        0.02 + 0.15 * np.exp(-(((t - 2.0) / 1.5) ** 2)) + 0.08 * np.exp(-(((t - 7.5) / 0.8) ** 2))
    )


def make_data(n: int, seed: int, inputs: str = "replicated"):
    """``N_DEMOS`` demonstrations of ``n / N_DEMOS`` steps: on one time grid (``replicated``)
    or each on its own time stamps (``distinct``: the grid jittered by up to half a step)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, DURATION_S, n // N_DEMOS)
    if inputs == "distinct":
        h = t[1] - t[0]
        jitter = rng.uniform(-0.5 * h, 0.5 * h, (N_DEMOS, t.shape[0]))
        X = np.clip(t[None, :] + jitter, 0.0, DURATION_S).reshape(-1, 1)
    else:
        X = np.tile(t, N_DEMOS)[:, None]
    y = truth(X[:, 0]) + noise_sd(X[:, 0]) * rng.standard_normal(X.shape[0])
    t_test = np.linspace(0.0, DURATION_S, N_PREDICT)
    y_test = truth(t_test) + noise_sd(t_test) * np.random.default_rng(seed + 1).standard_normal(
        N_PREDICT
    )
    return X, y, t_test[:, None], y_test


def kernel():
    return SquaredExponential(1.0, 1.0) + WhiteNoise(0.01)


def scores(mean, std, X_test, y_test) -> dict[str, float]:
    rmse = float(np.sqrt(np.mean((mean - truth(X_test[:, 0])) ** 2)))
    nlpd = float(np.mean(0.5 * np.log(2 * np.pi * std**2) + 0.5 * (y_test - mean) ** 2 / std**2))
    cov = float(np.mean(np.abs(y_test - mean) < Z95 * std))
    return {"rmse": rmse, "nlpd": nlpd, "cov95": cov}


def timed(fn: Callable, *args, **kwargs):
    """``(fn(...), CPU seconds)``: CPU time travels across loaded machines, wall time does not."""
    start = time.process_time()
    out = fn(*args, **kwargs)
    return out, time.process_time() - start


class CountingLBFGSB:
    """scikit-learn ``optimizer`` callable that counts likelihood evaluations."""

    def __init__(self) -> None:
        self.nfev = 0

    def __call__(self, obj_func, initial_theta, bounds):
        def f(theta):
            self.nfev += 1
            return obj_func(theta, eval_gradient=True)

        res = scipy.optimize.minimize(f, initial_theta, jac=True, method="L-BFGS-B", bounds=bounds)
        return res.x, res.fun


def sklearn_model(optimizer):
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    k = ConstantKernel(1.0, (1e-5, 1e5)) * RBF(1.0, (1e-5, 1e5)) + WhiteKernel(0.01, (1e-8, 1e5))
    return GaussianProcessRegressor(k, optimizer=optimizer, normalize_y=True, alpha=0.0)


def run_celerite(X, y, X_test):
    import celerite2
    from celerite2 import terms

    t = X[:, 0]
    order = np.argsort(t, kind="stable")
    t, yy = t[order], y[order]
    mu, sd = yy.mean(), yy.std()
    yn = (yy - mu) / sd

    def build(p):
        gp = celerite2.GaussianProcess(
            terms.SHOTerm(sigma=math.exp(p[0]), rho=math.exp(p[1]), Q=1 / math.sqrt(2))
        )
        gp.compute(t, diag=math.exp(p[2]), quiet=True)
        return gp

    def nll(p):
        value = -build(p).log_likelihood(yn)
        return value if np.isfinite(value) else 1e25

    start = time.perf_counter()
    res = scipy.optimize.minimize(
        nll, np.log([1.0, 3.0, 0.01]), method="L-BFGS-B", bounds=[(-10, 10), (-10, 10), (-20, 5)]
    )
    gp = build(res.x)
    fit_s = time.perf_counter() - start
    start = time.perf_counter()
    mean, var = gp.predict(yn, t=X_test[:, 0], return_var=True)
    pred_s = time.perf_counter() - start
    mean = mean * sd + mu
    std = np.sqrt(var + math.exp(res.x[2])) * sd
    return mean, std, fit_s, pred_s


def one_lml_eval_time(model_factory, X, y) -> float:
    """Seconds for one log-likelihood + gradient evaluation at the initial hyperparameters."""
    model = model_factory()
    if isinstance(model, GaussianProcess):
        model.fit(X, y)  # optimizer=None: one factorisation
        _, seconds = timed(model.log_marginal_likelihood, model.kernel_.theta, True)
        return seconds
    model.fit(X, y)
    _, seconds = timed(model.log_marginal_likelihood, model.kernel_.theta, True)
    return seconds


def benchmark(args) -> list[dict]:
    rows: list[dict] = []
    nfev_at: dict[str, tuple[int, int, float]] = {}  # method -> (n, nfev, predict_s)

    inputs = "replicated"

    def add(n, method, fit_s, pred_s, sc=None, note=""):
        row = {"n": n, "method": method, "fit_s": fit_s, "predict_s": pred_s, "note": note}
        row["inputs"] = inputs
        row.update(sc or {"rmse": math.nan, "nlpd": math.nan, "cov95": math.nan})
        rows.append(row)
        print(
            f"  {method:<22s} {inputs:<10s} n={n:6d}  fit {fit_s:9.3f} s  predict {pred_s:7.3f} s  "
            f"rmse {row['rmse']:.4f}  nlpd {row['nlpd']:7.3f}  cov95 {row['cov95']:.3f}  {note}",
            flush=True,
        )

    # warm-up (imports, first-call overheads) so that the first size is not penalised
    Xw, yw, Xw_test, _ = make_data(200, args.seed)
    LocalGP(kernel(), random_state=0).fit(Xw, yw).predict(Xw_test, return_std=True)
    GaussianProcess(kernel()).fit(Xw, yw).predict(Xw_test, return_std=True)

    for n, inputs in [(n, kind) for n in args.sizes for kind in args.inputs]:
        X, y, X_test, y_test = make_data(n, args.seed, inputs)
        print(f"n = {n}, {inputs} inputs", flush=True)
        # --- LocalGP (heteroscedastic local models), all combination rules from one fit
        best = None
        for _ in range(args.repeat):
            lgp = LocalGP(
                kernel(), threshold=args.threshold, max_points=args.max_points, random_state=0
            )
            _, fit_s = timed(lgp.fit, X, y)
            best = fit_s if best is None else min(best, fit_s)
        fit_s = best
        for rule in RULES:
            lgp.combine, lgp.combine_noisy = rule, False
            (mean, std), pred_s = timed(lgp.predict, X_test, return_std=True)
            add(
                n,
                f"local-{rule}",
                fit_s,
                pred_s,
                scores(mean, std, X_test, y_test),
                f"{len(lgp.models_)} models",
            )
        lgp.combine, lgp.combine_noisy = "product", True
        (mean, std), pred_s = timed(lgp.predict, X_test, return_std=True)
        add(n, "local-product-noisy", fit_s, pred_s, scores(mean, std, X_test, y_test), "trap")

        # --- exact GP on the replicate-averaged grid
        if n <= args.max_grid and inputs == "replicated":
            gp = GaussianProcess(kernel())
            _, fit_s = timed(gp.fit, X, y)
            (mean, std), pred_s = timed(gp.predict, X_test, return_std=True)
            add(
                n,
                "exact-grid",
                fit_s,
                pred_s,
                scores(mean, std, X_test, y_test),
                f"{gp.n_lml_evaluations_} LML evals",
            )

        # --- dense exact GP and scikit-learn
        if n <= args.max_exact:
            gp = GaussianProcess(kernel(), collapse_replicates=False)
            _, fit_s = timed(gp.fit, X, y)
            (mean, std), pred_s = timed(gp.predict, X_test, return_std=True)
            add(
                n,
                "exact",
                fit_s,
                pred_s,
                scores(mean, std, X_test, y_test),
                f"{gp.n_lml_evaluations_} LML evals",
            )
            nfev_at[f"exact/{inputs}"] = (n, gp.n_lml_evaluations_, pred_s)
            if not args.no_sklearn:
                opt = CountingLBFGSB()
                sk = sklearn_model(opt)
                _, fit_s = timed(sk.fit, X, y)
                (mean, std), pred_s = timed(sk.predict, X_test, return_std=True)
                add(
                    n,
                    "sklearn",
                    fit_s,
                    pred_s,
                    scores(mean, std, X_test, y_test),
                    f"{opt.nfev} LML evals",
                )
                nfev_at[f"sklearn/{inputs}"] = (n, opt.nfev, pred_s)
        elif n <= args.max_extrapolate:
            factories = {
                "exact": lambda: GaussianProcess(
                    kernel(), optimizer=None, collapse_replicates=False
                )
            }
            if not args.no_sklearn:
                factories["sklearn"] = lambda: sklearn_model(None)
            for name, factory in factories.items():
                if f"{name}/{inputs}" not in nfev_at:
                    continue
                n_ref, nfev, pred_ref = nfev_at[f"{name}/{inputs}"]
                per_eval = one_lml_eval_time(factory, X, y)
                add(
                    n,
                    name,
                    per_eval * nfev,
                    pred_ref * (n / n_ref) ** 2,
                    None,
                    f"extrap.: {per_eval:.2f} s/eval x {nfev} evals (n={n_ref})",
                )

        # --- celerite2 (O(n), different kernel)
        if not args.no_celerite:
            try:
                mean, std, fit_s, pred_s = run_celerite(X, y, X_test)
                add(n, "celerite2", fit_s, pred_s, scores(mean, std, X_test, y_test), "SHO kernel")
            except ImportError:
                if n == args.sizes[0]:
                    print("  celerite2 not installed: pip install 'gym-coffee[bench]'")
    return rows


def print_table(rows: list[dict]) -> None:
    print()
    print(
        "| n | inputs | method | fit (CPU s) | predict 2000 (CPU s) | RMSE vs truth | NLPD | "
        "95% cov. | note |"
    )
    print("|---:|---|---|---:|---:|---:|---:|---:|---|")
    for r in sorted(rows, key=lambda r: (r["n"], r["method"], r["inputs"])):
        acc = (
            f"{r['rmse']:.4f} | {r['nlpd']:.3f} | {r['cov95']:.3f}"
            if np.isfinite(r["rmse"])
            else "- | - | -"
        )
        print(
            f"| {r['n']} | {r['inputs']} | {r['method']} | {r['fit_s']:.3f} | "
            f"{r['predict_s']:.3f} | {acc} | {r['note']} |"
        )


def print_side_by_side(rows: list[dict]) -> None:
    """One row per (n, method): replicated and distinct inputs next to each other."""
    cells: dict[tuple[int, str], dict[str, dict]] = {}
    for r in rows:
        cells.setdefault((r["n"], r["method"]), {})[r["inputs"]] = r

    def part(r: dict | None) -> str:
        if r is None:
            return "- | - | - | -"
        acc = (
            f"{r['rmse']:.4f} | {r['nlpd']:.3f} | {r['cov95']:.3f}"
            if np.isfinite(r["rmse"])
            else "- | - | -"
        )
        mark = " (extrap.)" if "extrap" in r["note"] else ""
        return f"{r['fit_s'] + r['predict_s']:.3f}{mark} | {acc}"

    print("\nSide by side: fit + predict 2000 points (CPU s), RMSE vs truth, NLPD, 95% coverage")
    print(
        "| n | method | replicated: CPU s | RMSE | NLPD | cov. | distinct: CPU s | RMSE | NLPD "
        "| cov. |"
    )
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for (n, method), by in sorted(cells.items()):
        print(f"| {n} | {method} | {part(by.get('replicated'))} | {part(by.get('distinct'))} |")


def check_targets(rows: list[dict], top: int = 8000) -> None:
    print("\nTargets, distinct inputs (each demonstration on its own time stamps)")
    check_targets_for(rows, "distinct", top)
    print("\nTargets, replicated inputs (one time grid)")
    check_targets_for(rows, "replicated", top)


def check_targets_for(rows: list[dict], inputs: str, top: int) -> None:
    def get(n, method):
        for r in rows:
            if r["n"] == n and r["method"] == method and r["inputs"] == inputs:
                return r
        return None

    local2k, exact2k = get(2000, f"local-{CALIBRATED_RULE}"), get(2000, "exact")
    if local2k is not None and exact2k is not None:
        ratio = (exact2k["fit_s"] + exact2k["predict_s"]) / (
            local2k["fit_s"] + local2k["predict_s"]
        )
        print(
            f"  speed-up vs the exact GP at n=2000 ({exact2k['note']}): {ratio:.0f}x "
            f"(target >= 50x): {'met' if ratio >= 50 else 'MISSED'}"
        )
    local = get(top, f"local-{CALIBRATED_RULE}")
    if local is None:
        print(f"  (n = {top} not in this run)")
        return
    total = local["fit_s"] + local["predict_s"]
    print(
        f"  LocalGP fit + predict at n={top}: {total:.2f} s (target <= 2 s): "
        f"{'met' if total <= 2 else 'MISSED'}"
    )
    sk = get(top, "sklearn")
    if sk is not None:
        speedup = (sk["fit_s"] + sk["predict_s"]) / total
        print(
            f"  speed-up vs scikit-learn ({sk['note'] or 'measured'}): {speedup:.0f}x "
            f"(target >= 200x): {'met' if speedup >= 200 else 'MISSED'}"
        )
    else:  # scikit-learn measured at a smaller n only: scale its cost by n^3 (an estimate)
        measured = [r for r in rows if r["method"] == "sklearn" and r["inputs"] == inputs]
        measured = [r for r in measured if "extrap" not in r["note"]]
        if measured:
            ref = max(measured, key=lambda r: r["n"])
            est = (ref["fit_s"] + ref["predict_s"]) * (top / ref["n"]) ** 3
            print(
                f"  speed-up vs scikit-learn, its n={ref['n']} cost scaled by n^3 to n={top} "
                f"(~{est:.0f} s, an estimate): {est / total:.0f}x (target >= 200x): "
                f"{'met' if est / total >= 200 else 'MISSED'}"
            )
    exact = get(top, "exact-grid")  # same posterior as the dense exact GP
    if exact is not None:
        for rule in RULES:
            r = get(top, f"local-{rule}")
            ratio = r["rmse"] / exact["rmse"]
            print(
                f"  RMSE local-{rule} / exact GP at n={top}: {ratio:.2f} (target <= 1.3): "
                f"{'met' if ratio <= 1.3 else 'MISSED'}"
            )
    for n in (1000, 8000, 32000):
        r = get(n, f"local-{CALIBRATED_RULE}")
        if r is not None:
            ok = 0.93 <= r["cov95"] <= 0.97
            print(
                f"  95% coverage local-{CALIBRATED_RULE} at n={n}: {r['cov95']:.3f} "
                f"(target [0.93, 0.97]): {'met' if ok else 'MISSED'}"
            )
    big = get(4 * top, f"local-{CALIBRATED_RULE}")
    if big is not None:
        ratio = (big["fit_s"] + big["predict_s"]) / total
        print(
            f"  cost n={4 * top} / n={top}: {ratio:.2f} (target <= 4): "
            f"{'met' if ratio <= 4 else 'MISSED'}"
        )


def plot(rows: list[dict], path: Path, *, force: bool = False) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    methods = ["exact", "sklearn", "exact-grid", f"local-{CALIBRATED_RULE}", "celerite2"]
    for ax, key, title in zip(
        axes,
        ["fit_s", "predict_s"],
        ["training (with hyperparameters)", "prediction (2000 points)"],
        strict=True,
    ):
        for method in methods:
            pts = [r for r in rows if r["method"] == method]
            if not pts:
                continue
            meas = [(r["n"], r[key]) for r in pts if "extrap" not in r["note"]]
            extra = [(r["n"], r[key]) for r in pts if "extrap" in r["note"]]
            (line,) = ax.loglog(*zip(*meas, strict=True), "o-", label=method) if meas else (None,)
            if extra:
                color = line.get_color() if line is not None else None
                last = meas[-1:] if meas else []
                ax.loglog(*zip(*(last + extra), strict=True), "o--", mfc="none", color=color)
        ax.set_xlabel("training points n")
        ax.set_ylabel("seconds")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("GP scaling (cf. paper Fig. 6c/6d); hollow dashed = extrapolated", fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    atomic_write_bytes(path, buf.getvalue(), force=force)
    print(f"\nwrote {path}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small sizes, seconds")
    parser.add_argument("--sizes", type=int, nargs="+", default=None)
    parser.add_argument(
        "--max-exact",
        type=int,
        default=4000,
        help="largest n for which exact/sklearn are run in full",
    )
    parser.add_argument(
        "--max-extrapolate",
        type=int,
        default=8000,
        help="largest n for which exact/sklearn are extrapolated",
    )
    parser.add_argument(
        "--max-grid", type=int, default=8000, help="largest n for the replicate-averaged exact GP"
    )
    parser.add_argument("--threshold", type=float, default=0.5)
    parser.add_argument("--max-points", type=int, default=400, help="distinct inputs per model")
    parser.add_argument("--repeat", type=int, default=1, help="LocalGP fits per size (min)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--inputs",
        nargs="+",
        default=["replicated", "distinct"],
        choices=["replicated", "distinct"],
        help="demonstrations on one time grid and/or each on its own time stamps",
    )
    parser.add_argument("--no-sklearn", action="store_true")
    parser.add_argument("--no-celerite", action="store_true")
    parser.add_argument("--png", type=Path, default=None, help="also plot the timings here")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    parser.add_argument("--force", action="store_true", help="overwrite --png / --json")
    args = parser.parse_args(argv)
    for option, path, suffix in (("--png", args.png, ".png"), ("--json", args.json, ".json")):
        if path is not None:
            try:
                check_output_path(path, force=args.force, suffixes=(suffix,))
            except (ValueError, FileExistsError) as exc:
                parser.error(f"argument {option}: {exc}")
    if args.sizes is None:
        args.sizes = (
            [100, 400, 1000]
            if args.quick
            else [100, 250, 500, 1000, 2000, 4000, 8000, 16000, 32000]
        )
    if args.quick:
        args.max_exact = min(args.max_exact, 1000)

    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        rows = benchmark(args)
    print_table(rows)
    print_side_by_side(rows)
    check_targets(rows, top=8000 if 8000 in args.sizes else max(args.sizes))
    if args.json is not None:
        atomic_write_text(args.json, json.dumps(rows, indent=1), force=args.force)
    if args.png is not None:
        plot(rows, args.png, force=args.force)
    return 0


if __name__ == "__main__":
    sys.exit(main())
