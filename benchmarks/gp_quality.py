"""GP quality on demonstration data: leave-one-demonstration-out against a ProMP and the exact GP.

Part 1, multi-demonstration sets (each fold fits on all demonstrations but one and predicts the
held-out one at its own time stamps):

* ``coffee/<frame>``: the coffee task's scripted teacher, recorded once with
  ``gym_coffee.collect_demonstrations`` (cached under ``/tmp``) and resampled exactly as
  ``GPDemonstrationPolicy.fit`` does (``DemonstrationEncoder.data_``), in every frame the policy
  encodes (joint, cup, machine); one model per output dimension.
* ``shapes-<grid>``: synthetic 2-D shapes whose demonstrations share their start and end
  points exactly (zero spread there), ``grid`` ``shared`` (one time grid, replicated inputs) or
  ``own`` (each demonstration on its own time stamps, distinct inputs).
* ``lasa/<shape>`` (with ``--lasa DIR``): real human demonstrations, the LASA Handwriting
  Dataset (Khansari-Zadeh & Billard 2011): 30 shapes drawn on a tablet, 7 demonstrations of
  1000 samples each (2-D positions in mm, each on its own time stamps), every demonstration
  ending at exactly (0, 0). Read from the dataset's ``.mat`` files in ``DIR`` (its
  ``DataSet`` folder; nothing is downloaded) and resampled on normalised time as
  ``DemonstrationEncoder.fit`` does (``resample``). Summarised in a table of their own.

Methods: ``local-<rule>`` (``LocalGP`` as the encoder builds it,
``DemonstrationEncoder._make_model``, with each combination rule), ``exact`` (the homoscedastic
``GaussianProcess`` with the same kernel) and ``promp``
(``movement_primitives.promp.ProMP``, ``N_WEIGHTS`` Gaussian basis functions per dimension; its
predictive variance is that of the learnt weight distribution, which models the variation
between demonstrations).

Metrics, per held-out demonstration and output dimension, in units of that dimension's std over
the training demonstrations: RMSE of the mean; NLPD (Gaussian, nats per point); coverage of the
95% interval; largest step of the predicted mean (and of the predicted std) between consecutive
time stamps divided by the largest step in the training demonstrations; CPU seconds of fit +
predict; and ``bad``: the number of folds with a non-finite, zero or > 100 x std prediction.

Methods ``het-<noise model>``: one global ``HeteroscedasticGP`` per noise model (``"em"``, the
most-likely EM, and ``"vhgp"``, the variational heteroscedastic GP), also calibrated, so that
the two noise models are compared side by side on the same folds.

Part 2, generated heteroscedastic regression sets (Goldberg et al. 1997, Yuan & Wahba 2004,
Williams 1996, and a homoscedastic control): NLPD of ``HeteroscedasticGP`` with each noise
model and of the homoscedastic ``GaussianProcess`` on a large test set; the gain is
homoscedastic minus heteroscedastic (positive: the heteroscedastic GP is better). The *oracle
gain* is what the true noise model gains over the best constant noise on the same test set
(true ``f`` in both): the largest gain any heteroscedastic model can reach there (about 0.09
nats on Goldberg's set, whose noise std only doubles over the input range). With
``--hetero-csv FILE ...``, also real heteroscedastic sets read from CSV files (the last two
columns x and y; nothing is downloaded), e.g. the motorcycle crash data (Silverman 1985; R's
``MASS::mcycle``, Rdatasets' ``MASS/mcycle.csv``): 5-fold cross-validation on 3 shuffles,
standardised on each training fold, with ``LocalGP()`` next to the global models.

Part 4 (``--part lasa-raw``, with ``--lasa DIR``): ``LocalGP()`` with its default settings, as
a user would call it, on each LASA shape's demonstrations on their own time stamps in seconds
(all 1000 samples: 6000 distinct inputs per fold, about 15 local models), leave one
demonstration out, per output dimension: the largest step of the predicted mean and std against
the demonstrations' largest step, and the bad folds. No calibration and no time alignment (the
demonstrations last 2.5-5 s), so RMSE and coverage are not comparable with part 1's. With
``--lasa-time normalised`` each demonstration's stamps are divided by its duration (``t /
t_end``: every demonstration starting at 0 and ending at 1; LASA samples each demonstration at
a fixed rate, so this is one grid of 1000 points with 6 replicates, up to rounding), and
a ProMP and ``LocalGP()`` with the new-demonstration factor run on the same folds. With
``--lasa-frame start`` each demonstration is expressed relative to its own first sample (a
start-point frame: no spread at t = 0, and the demonstrations end at different points).

Part 3 (``--part coverage``), coverage of held-out demonstrations over many generated sets
(``smooth_deviations``; not the sets above): separates the calibration mechanism from the
sampling spread of a single set of 4-5 demonstrations, next to a reference without a GP on the
same folds (``textbook_interval``: the Student-t prediction interval of a new sample per time
step).

Usage::

    python benchmarks/gp_quality.py --quick    # a few output dimensions, 1 seed (~1-2 min)
    python benchmarks/gp_quality.py            # every dimension, 3 seeds
    python benchmarks/gp_quality.py --part loo --lasa LASAHandwritingDataset/DataSet
    python benchmarks/gp_quality.py --part hetero --hetero-csv mcycle.csv
"""

from __future__ import annotations

import argparse
import functools
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from lgp_policy.gp.exact import GaussianProcess
from lgp_policy.gp.heteroscedastic import DEFAULT_METHOD, METHODS, HeteroscedasticGP
from lgp_policy.gp.local import COMBINE_RULES, LocalGP
from lgp_policy.lfd.encoding import DemonstrationEncoder, new_demonstration_scale

N_WEIGHTS = 25
CACHE = Path("/tmp/gym_coffee_gp_quality")
N_DEMOS = 4


# ----------------------------------------------------------------------------- data
def coffee_sets(n_steps: int, max_dims: int | None) -> dict[str, np.ndarray]:
    """``{"coffee/<frame>": (n_demos, n_steps, d)}`` from the teacher's demonstrations."""
    import gymnasium as gym

    import gym_coffee
    from gym_coffee.demonstrations import DemonstrationSet, collect_demonstrations
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    CACHE.mkdir(exist_ok=True)
    path = CACHE / f"teacher_{N_DEMOS}.npz"
    if path.exists():
        demos = DemonstrationSet.load(path)
    else:
        env = gym.make(gym_coffee.ENV_ID)
        try:
            demos = collect_demonstrations(env, N_DEMOS, seed=0)
        finally:
            env.close()
        demos.save(path, overwrite=True)
    policy = GPDemonstrationPolicy(model="empirical", n_steps=n_steps).fit(demos)
    data = policy.encoder_.data_
    return {f"coffee/{k}": v[:, :, :max_dims] for k, v in data.items()}


def lasa_shapes(folder: Path, quick: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{shape: (T (7, 1000) s, Y (7, 1000, 2) mm)}`` from the LASA Handwriting Dataset's
    ``.mat`` files in ``folder`` (``demos{i}.t``, ``demos{i}.pos``): each demonstration on its
    own time stamps. ``quick``: every third shape."""
    from scipy.io import loadmat

    files = sorted(Path(folder).glob("*.mat"))
    if not files:
        raise SystemExit(
            f"--lasa: no .mat files in {folder} (expected the dataset's DataSet folder)"
        )
    shapes = {}
    for path in files[::3] if quick else files:
        demos = loadmat(path, simplify_cells=True)["demos"]
        T = np.stack([np.asarray(d["t"], float) for d in demos])
        shapes[path.stem] = (T, np.stack([np.asarray(d["pos"], float).T for d in demos]))
    return shapes


def lasa_sets(folder: Path, n_steps: int, quick: bool) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{"lasa/<shape>": (T, Y)}``: each of a shape's demonstrations (:func:`lasa_shapes`)
    resampled to ``n_steps`` points on normalised time (``resample``), ``T`` the shared phase
    grid."""
    from lgp_policy.lfd.encoding import resample

    sets = {}
    for name, (T, Y) in lasa_shapes(folder, quick).items():
        Yr = np.stack([resample(t, y, n_steps) for t, y in zip(T, Y, strict=True)])
        sets[f"lasa/{name}"] = (np.tile(np.linspace(0.0, 1.0, n_steps), (len(Yr), 1)), Yr)
    return sets


def _time_grid(grid: str, n_steps: int, rng: np.random.Generator) -> np.ndarray:
    """One demonstration's time stamps on [0, 1]: ``"shared"`` (one grid for all) or ``"own"``
    (random stamps between the fixed ends)."""
    if grid == "shared":
        return np.linspace(0.0, 1.0, n_steps)
    return np.sort(np.r_[0.0, 1.0, rng.uniform(0.0, 1.0, n_steps - 2)])


def shapes(grid: str, n_demos: int = 5, n_steps: int = 150, seed: int = 0):
    """2-D shapes from a common start to a common end (zero spread at both)."""
    rng = np.random.default_rng(seed)
    Ts, Ys = [], []
    for _ in range(n_demos):
        t = _time_grid(grid, n_steps, rng)
        bend = np.sin(np.pi * t)  # 0 at both ends
        a, b, c = rng.normal(0.0, [0.25, 0.25, 0.15])
        x = t + a * bend + c * np.sin(3 * np.pi * t) * bend
        y = np.sin(2 * np.pi * t) * 0.5 + b * bend**2
        Ts.append(t)
        Ys.append(np.column_stack([x, y]))
    return np.stack(Ts), np.stack(Ys)


def smooth_deviations(seed: int, n_demos: int, grid: str, n_steps: int = 100):
    """Calibration sets (not the benchmark's LOO sets): ``cos(3t)`` plus a smooth GP draw per
    demonstration (length scale 0.15) of std ``0.02 + 0.3 sin^2(pi t)``; ``grid`` as
    :func:`shapes`."""
    rng = np.random.default_rng(1000 + seed)
    Ts, Ys = [], []
    for _ in range(n_demos):
        t = _time_grid(grid, n_steps, rng)
        K = np.exp(-0.5 * (t[:, None] - t[None, :]) ** 2 / 0.15**2) + 1e-8 * np.eye(n_steps)
        sd = 0.02 + 0.3 * np.sin(np.pi * t) ** 2
        Ts.append(t)
        Ys.append(np.cos(3 * t) + sd * (np.linalg.cholesky(K) @ rng.standard_normal(n_steps)))
    return np.stack(Ts), np.stack(Ys)


def textbook_interval(
    T_train: np.ndarray, Y_train: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The textbook 95% prediction interval of a new sample, per time step, as a reference that
    involves no GP: the ``n`` training demonstrations linearly interpolated to the times ``t``,
    their mean and unbiased std ``s``, half-width ``t_{n-1}(0.975) s sqrt(1 + 1/n)`` (exact for
    independent Gaussian demonstrations). Returns (mean, half-width)."""
    from scipy.special import stdtrit

    Yi = np.stack([np.interp(t, tt, yy) for tt, yy in zip(T_train, Y_train, strict=True)])
    n = Yi.shape[0]
    half = stdtrit(n - 1, 0.975) * Yi.std(axis=0, ddof=1) * np.sqrt(1.0 + 1.0 / n)
    return Yi.mean(axis=0), half


def coverage_table(n_sets: int, n_steps: int) -> list[str]:
    """95% coverage of held-out demonstrations over ``n_sets`` generated sets per row: its mean,
    spread over sets, the share of sets inside [0.90, 0.97], the mean with an extra factor
    ``sqrt(1 + 1/n)`` (the variance of a mean of n training demonstrations), and the same for
    the textbook interval (:func:`textbook_interval`) on the same folds: how far single sets
    spread even for an interval that is calibrated by construction."""
    lines = [
        "| demonstrations | grid | mean coverage | sd over sets | min - max | "
        "sets in [0.90, 0.97] | mean cov. with sqrt(1 + 1/n) | textbook: mean cov. | "
        "textbook: sd over sets | textbook: sets in [0.90, 0.97] |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    enc = DemonstrationEncoder(n_steps=n_steps, model="local")
    for n_demos in (4, 5):
        for grid in ("shared", "own"):
            cov, cov_n, cov_t = [], [], []
            for seed in range(n_sets):
                T, Y = smooth_deviations(seed, n_demos, grid, n_steps)
                per, per_n, per_t = [], [], []
                for k in range(n_demos):
                    keep = np.arange(n_demos) != k
                    mean, std = fit_predict_gp(enc._make_model(), T[keep], Y[keep], T[k])
                    std = std * new_demonstration_scale(n_demos - 1)
                    err = np.abs(Y[k] - mean)
                    per.append(np.mean(err <= 1.96 * std))
                    per_n.append(np.mean(err <= 1.96 * std * np.sqrt(1 + 1 / (n_demos - 1))))
                    t_mean, t_half = textbook_interval(T[keep], Y[keep], T[k])
                    per_t.append(np.mean(np.abs(Y[k] - t_mean) <= t_half))
                cov.append(np.mean(per))
                cov_n.append(np.mean(per_n))
                cov_t.append(np.mean(per_t))
            c, ct = np.array(cov), np.array(cov_t)
            inside = np.mean((c >= 0.90) & (c <= 0.97))
            inside_t = np.mean((ct >= 0.90) & (ct <= 0.97))
            lines.append(
                f"| {n_demos} | {grid} | {c.mean():.3f} | {c.std():.3f} | "
                f"{c.min():.3f} - {c.max():.3f} | {inside:.0%} | {np.mean(cov_n):.3f} | "
                f"{ct.mean():.3f} | {ct.std():.3f} | {inside_t:.0%} |"
            )
    return lines


# -------------------------------------------------------------------------- methods
def fit_predict_gp(model: Any, t_tr, y_tr, t_te):
    X = t_tr.reshape(-1, 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(X, y_tr.reshape(-1))
    return model.predict(t_te[:, None], return_std=True)


def make_methods(
    n_steps: int, rules: tuple[str, ...]
) -> dict[str, Callable[[np.ndarray, np.ndarray, np.ndarray], Any]]:
    """The compared methods. GP stds are scaled by ``new_demonstration_scale`` as the encoder
    does (``calibrate=True``); ``<method>-raw`` rows show the same fits without it."""

    def gp(model: str, **kw: Any):
        enc = DemonstrationEncoder(n_steps=n_steps, model=model, **kw)
        memo: dict[int, Any] = {}

        def run(t_tr, y_tr, t_te, raw: bool = False):
            key = hash((t_tr.tobytes(), y_tr.tobytes(), t_te.tobytes()))
            if key not in memo:
                memo[key] = fit_predict_gp(enc._make_model(), t_tr, y_tr, t_te)
            mean, std = memo[key]
            return mean, std * (1.0 if raw else new_demonstration_scale(t_tr.shape[0]))

        return run

    def promp(t_tr, y_tr, t_te):
        from movement_primitives.promp import ProMP

        p = ProMP(n_dims=1, n_weights_per_dim=N_WEIGHTS)
        p.imitate(t_tr, y_tr[:, :, None])
        mean = p.mean_trajectory(t_te)[:, 0]
        var = p.var_trajectory(t_te)[:, 0]
        return mean, np.sqrt(np.maximum(var, 0.0))

    methods: dict[str, Callable[..., Any]] = {}
    for rule in rules:
        f = gp("local", combine=rule)
        methods[f"local-{rule}"] = f
        methods[f"local-{rule}-raw"] = lambda a, b, c, f=f: f(a, b, c, raw=True)
    if "method" in LocalGP().get_params():  # LocalGP with the non-default noise model
        other = next(m for m in METHODS if m != DEFAULT_METHOD)
        methods[f"local-{other}"] = gp("local", model_kwargs={"method": other})
    for method in METHODS:  # one global heteroscedastic GP per noise model (EM vs VHGP)
        methods[f"het-{method}"] = gp("heteroscedastic", model_kwargs={"method": method})
    methods["exact"] = gp("exact")
    methods["promp"] = promp
    return methods


def loo_table(
    sets: dict[str, tuple[np.ndarray, np.ndarray]], methods: dict[str, Callable[..., Any]]
) -> dict[str, list[dict[str, float]]]:
    """Leave one demonstration out of every set with every method, one printed row each;
    returns ``{method: [loo result per set]}``."""
    print(
        "| set | method | RMSE | NLPD | 95% cov. | max step ratio | max std step ratio | CPU s "
        "| bad folds |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    summary: dict[str, list[dict[str, float]]] = {m: [] for m in methods}
    for name, (T, Y) in sets.items():
        for m, fn in methods.items():
            r = loo(T, Y, fn)
            summary[m].append(r)
            print(
                f"| {name} (d={Y.shape[2]}) | {m} | {r['rmse']:.3f} | {r['nlpd']:.2f} | "
                f"{r['cov']:.3f} | {r['step']:.2f} | {r['std_step']:.2f} | {r['cpu']:.2f} | "
                f"{r['bad']}/{r['folds']} |",
                flush=True,
            )
    return summary


def loo(Ts: np.ndarray, Ys: np.ndarray, method) -> dict[str, float]:
    """Leave-one-demonstration-out over every output dimension; averaged metrics."""
    rows = []
    bad = 0
    cpu = 0.0
    for k in range(Ts.shape[0]):
        keep = np.arange(Ts.shape[0]) != k
        fold_bad = False
        for j in range(Ys.shape[2]):
            # copies: movement_primitives' ProMP normalises the time arrays it gets in place
            y_tr, t_tr = Ys[keep, :, j].copy(), Ts[keep].copy()
            y_te, t_te = Ys[k, :, j].copy(), Ts[k].copy()
            scale = float(np.std(y_tr))
            scale = scale if scale > 0 else 1.0
            c0 = time.process_time()
            mean, std = method(t_tr, y_tr, t_te)
            cpu += time.process_time() - c0
            mean, std = np.asarray(mean, float), np.asarray(std, float)
            if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(std))) or (
                np.any(std <= 0) or np.any(std > 100 * scale)
            ):
                fold_bad = True
                std = np.where(np.isfinite(std) & (std > 0), std, np.nan)
            z = (y_te - mean) / scale
            s = std / scale
            nlpd = 0.5 * np.log(2 * np.pi * s**2) + 0.5 * (z / s) ** 2
            demo_step = max(float(np.max(np.abs(np.diff(y)))) for y in y_tr)
            rows.append(
                (
                    float(np.sqrt(np.mean(z**2))),
                    float(np.nanmean(nlpd)),
                    float(np.nanmean(np.abs(z) <= 1.96 * s)),
                    float(np.max(np.abs(np.diff(mean)))) / max(demo_step, 1e-12),
                    float(np.nanmax(np.abs(np.diff(std)))) / max(demo_step, 1e-12),
                )
            )
        bad += fold_bad
    r = np.array(rows)
    return {
        "rmse": float(np.mean(r[:, 0])),
        "nlpd": float(np.mean(r[:, 1])),
        "cov": float(np.mean(r[:, 2])),
        "step": float(np.max(r[:, 3])),
        "std_step": float(np.max(r[:, 4])),
        "cpu": cpu,
        "bad": bad,
        "folds": Ts.shape[0],
    }


# ---------------------------------------------------------------- heteroscedastic sets
def hetero_sets():
    """(name, x range, f, noise sd) of the classic generated heteroscedastic sets."""
    return [
        ("goldberg", (0.0, 1.0), lambda x: 2 * np.sin(2 * np.pi * x), lambda x: 0.5 + x),
        (
            "yuan",
            (0.0, 1.0),
            lambda x: 2 * (np.exp(-30 * (x - 0.25) ** 2) + np.sin(np.pi * x**2)) - 2,
            lambda x: np.exp(np.sin(2 * np.pi * x)),
        ),
        (
            "williams",
            (0.0, np.pi),
            lambda x: np.sin(2.5 * x) * np.sin(1.5 * x),
            lambda x: 0.01 + 0.25 * (1 - np.sin(2.5 * x)) ** 2,
        ),
        ("homoscedastic", (0.0, 1.0), lambda x: 2 * np.sin(2 * np.pi * x), lambda x: 0.5 + 0 * x),
    ]


def regression_models() -> dict[str, Callable[[], Any]]:
    """The homoscedastic GP (``"hom"``) and ``HeteroscedasticGP`` with every noise model."""
    models: dict[str, Callable[[], Any]] = {"hom": GaussianProcess}
    for method in METHODS:
        models[method] = functools.partial(HeteroscedasticGP, method=method, random_state=0)
    return models


def hetero_table(seeds: list[int], n_train: int = 200, n_test: int = 2000) -> list[str]:
    """NLPD of the homoscedastic GP and of ``HeteroscedasticGP`` with every noise model
    (``METHODS``), the gain of each, the oracle gain and CPU seconds (fit + predict)."""
    gains = " | ".join(f"gain {m}" for m in METHODS)
    cpus = " | ".join(f"CPU s {m}" for m in METHODS)
    nlpds = " | ".join(f"NLPD {m}" for m in METHODS)
    ncol = 4 + 3 * len(METHODS)
    lines = [
        f"| set | NLPD hom. | {nlpds} | {gains} | oracle gain | CPU s hom. | {cpus} |",
        "|" + "---|" * ncol,
    ]
    for name, (a, b), f, sd in hetero_sets():
        models = regression_models()
        nl: dict[str, list[float]] = {k: [] for k in models}
        cpu = dict.fromkeys(models, 0.0)
        oracle: list[float] = []
        for seed in seeds:
            rng = np.random.default_rng(seed)
            x = rng.uniform(a, b, n_train)
            y = f(x) + sd(x) * rng.standard_normal(n_train)
            xt = rng.uniform(a, b, n_test)
            yt = f(xt) + sd(xt) * rng.standard_normal(n_test)
            # the gain of the true noise model: true f with the true noise against true f with
            # the best constant noise (what a perfect heteroscedastic model gains at most)
            r2 = (yt - f(xt)) ** 2
            het_o = np.mean(0.5 * np.log(2 * np.pi * sd(xt) ** 2) + 0.5 * r2 / sd(xt) ** 2)
            oracle.append(float(0.5 * np.log(2 * np.pi * np.mean(r2)) + 0.5 - het_o))
            for key, make in models.items():
                model = make()
                c0 = time.process_time()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    model.fit(x[:, None], y)
                m, s = model.predict(xt[:, None], return_std=True)
                cpu[key] += time.process_time() - c0
                nl[key].append(
                    float(np.mean(0.5 * np.log(2 * np.pi * s**2) + 0.5 * ((yt - m) / s) ** 2))
                )
        hom = float(np.mean(nl["hom"]))
        row = [name, f"{hom:.3f}"]
        row += [f"{np.mean(nl[m]):.3f}" for m in METHODS]
        row += [f"{hom - np.mean(nl[m]):+.3f}" for m in METHODS]
        row += [f"{np.mean(oracle):+.3f}", f"{cpu['hom'] / len(seeds):.2f}"]
        row += [f"{cpu[m] / len(seeds):.2f}" for m in METHODS]
        lines.append("| " + " | ".join(row) + " |")
    return lines


def read_xy_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)`` from a CSV with one header row whose last two columns are the input and the
    output (Rdatasets' ``MASS/mcycle.csv``: row name, ``times``, ``accel``); at most 100 000
    rows are read. Raises ``ValueError`` naming what is wrong."""
    if not path.is_file():
        raise ValueError(f"{path} is not a file")
    data = np.genfromtxt(path, delimiter=",", skip_header=1, max_rows=100_000)
    if data.ndim != 2 or data.shape[1] < 2 or data.shape[0] < 20:
        raise ValueError(f"{path}: expected a header row and >= 20 rows of >= 2 columns")
    x, y = data[:, -2], data[:, -1]
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError(f"{path}: the last two columns must be numbers")
    return x, y


def real_hetero_table(
    sets: dict[str, tuple[np.ndarray, np.ndarray]], seeds: list[int], k: int = 5
) -> list[str]:
    """Real heteroscedastic regression sets: ``k``-fold cross-validation per seed (a shuffle),
    inputs and outputs standardised on each training fold; NLPD of the homoscedastic GP, of
    ``HeteroscedasticGP`` with every noise model and of ``LocalGP()``, their gain over the
    homoscedastic GP (mean over all folds), the worst fold's gain and the folds lost by more
    than 0.1 nats; ``bad``: folds with a non-finite, zero or > 100 x std prediction, any
    model."""
    models = {**regression_models(), "local": functools.partial(LocalGP, random_state=0)}
    het = [m for m in models if m != "hom"]
    lines = [
        "| set | n | folds | NLPD hom. | "
        + " | ".join(f"NLPD {m} | gain {m} | worst fold {m} | lost {m}" for m in het)
        + " | bad |",
        "|" + "---|" * (5 + 4 * len(het)),
    ]
    for name, (x, y) in sets.items():
        nl: dict[str, list[float]] = {m: [] for m in models}
        bad = 0
        for seed in seeds:
            perm = np.random.default_rng(seed).permutation(x.shape[0])
            for test in np.array_split(perm, k):
                train = np.setdiff1d(perm, test)
                mx, sx = x[train].mean(), x[train].std()
                my, sy = y[train].mean(), y[train].std()
                X, Y = ((x - mx) / sx)[:, None], (y - my) / sy
                for m, make in models.items():
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        mean, std = make().fit(X[train], Y[train]).predict(X[test], return_std=True)
                    ok = np.all(np.isfinite(mean)) and np.all(np.isfinite(std))
                    bad += int(not ok or np.any(std <= 0) or np.any(std > 100.0))  # Y: std 1
                    z = (Y[test] - mean) / std
                    nl[m].append(float(np.mean(0.5 * np.log(2 * np.pi * std**2) + 0.5 * z**2)))
        hom = np.asarray(nl["hom"])
        row = [name, str(x.shape[0]), str(hom.shape[0]), f"{hom.mean():.3f}"]
        for m in het:
            gain = hom - np.asarray(nl[m])
            row += [
                f"{np.mean(nl[m]):.3f}",
                f"{gain.mean():+.3f}",
                f"{gain.min():+.3f}",
                str(int(np.sum(gain < -0.1))),
            ]
        lines.append("| " + " | ".join(row) + f" | {bad} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="2 dims per frame, 1 seed")
    parser.add_argument("--n-steps", type=int, default=100, help="resampled points per demo")
    parser.add_argument(
        "--rules",
        nargs="+",
        default=list(COMBINE_RULES),
        choices=COMBINE_RULES,
        help="LocalGP combination rules to compare",
    )
    parser.add_argument(
        "--part",
        choices=("all", "loo", "hetero", "coverage", "lasa-raw"),
        default="all",
        help="one part: leave-one-demonstration-out, heteroscedastic sets, or the coverage "
        "study on generated smoothly deviating demonstrations (not part of 'all')",
    )
    parser.add_argument("--coverage-sets", type=int, default=12, help="sets per coverage row")
    parser.add_argument(
        "--lasa",
        type=Path,
        default=None,
        metavar="DIR",
        help="also leave-one-out on the LASA Handwriting Dataset's .mat files in DIR (real "
        "human demonstrations; its DataSet folder)",
    )
    parser.add_argument(
        "--hetero-csv",
        type=Path,
        nargs="+",
        default=[],
        metavar="FILE",
        help="also real heteroscedastic regression sets, each a CSV whose last two columns are "
        "x and y (e.g. Rdatasets' MASS/mcycle.csv, the motorcycle crash data), in the "
        "heteroscedastic part: 5-fold cross-validation",
    )
    parser.add_argument(
        "--lasa-time",
        choices=("seconds", "normalised"),
        default="seconds",
        help="time axis of --part lasa-raw: the stamps in seconds, or each demonstration's "
        "divided by its duration (then also RMSE, NLPD and coverage against a ProMP)",
    )
    parser.add_argument(
        "--lasa-frame",
        choices=("world", "start"),
        default="world",
        help="coordinates of --part lasa-raw: the dataset's own (every demonstration ends at "
        "the origin), or each demonstration relative to its first sample",
    )
    args = parser.parse_args(argv)
    real_sets = {}
    for path in args.hetero_csv:  # read before any work: a bad file fails at once
        try:
            real_sets[path.stem] = read_xy_csv(path)
        except ValueError as err:
            parser.error(f"--hetero-csv: {err}")
    if real_sets and args.part not in ("all", "hetero"):
        parser.error("--hetero-csv belongs to the heteroscedastic part: --part hetero or all")
    if args.part == "coverage":
        print(f"## Coverage over {args.coverage_sets} generated sets per row (LocalGP)\n")
        for line in coverage_table(args.coverage_sets, args.n_steps):
            print(line, flush=True)
        return
    if args.part == "lasa-raw":
        if args.lasa is None:
            parser.error("--part lasa-raw needs --lasa DIR")
        lasa_raw_table(args.lasa, args.quick, args.lasa_time, args.lasa_frame)
        return
    if args.part != "loo":
        print("## Generated heteroscedastic sets (200 train, 2000 test points)\n")
        for line in hetero_table([0] if args.quick else [0, 1, 2]):
            print(line, flush=True)
        if real_sets:
            print("\n## Real heteroscedastic sets (5-fold cross-validation, standardised)\n")
            for line in real_hetero_table(real_sets, [0] if args.quick else [0, 1, 2]):
                print(line, flush=True)
        if args.part == "hetero":
            return
        print()
    max_dims = 2 if args.quick else None
    methods = make_methods(args.n_steps, tuple(args.rules))
    sets: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, Y in coffee_sets(args.n_steps, max_dims).items():
        T = np.tile(np.linspace(0.0, 1.0, Y.shape[1]), (Y.shape[0], 1))
        sets[name] = (T, Y)
    for grid in ("shared", "own"):
        sets[f"shapes-{grid}"] = shapes(grid, n_steps=args.n_steps)
    if args.lasa is not None:
        sets.update(lasa_sets(args.lasa, args.n_steps, args.quick))
    print(f"## Leave-one-demonstration-out (n_steps={args.n_steps}, ProMP {N_WEIGHTS} weights)\n")
    summary = loo_table(sets, methods)
    groups = {"teacher and synthetic sets": [n for n in sets if not n.startswith("lasa/")]}
    if args.lasa is not None:
        groups["LASA, real human demonstrations"] = [n for n in sets if n.startswith("lasa/")]
    names = list(sets)
    for title, members in groups.items():
        print(f"\n{title} ({len(members)} sets)")
        print_summary({m: [rs[names.index(n)] for n in members] for m, rs in summary.items()})


def lasa_raw_table(
    folder: Path, quick: bool, time_axis: str = "seconds", frame: str = "world"
) -> None:
    """Part 4: ``LocalGP()`` defaults on the LASA shapes' own time stamps (see the module
    docstring); ``time_axis="normalised"``: each demonstration's stamps divided by its duration
    (``t / t_end``: one grid on [0, 1] up to rounding), with a ProMP on the same folds and
    ``LocalGP()``'s std also times ``new_demonstration_scale`` (``-cal``) for RMSE, NLPD and
    coverage. ``frame="start"``: each demonstration relative to its own first sample (a
    start-point frame: no spread at t = 0; the demonstrations then end at different points)."""
    promp = make_methods(100, ())["promp"]

    def default_local(t_tr, y_tr, t_te):
        return fit_predict_gp(LocalGP(), t_tr, y_tr, t_te)

    def calibrated(t_tr, y_tr, t_te):
        mean, std = default_local(t_tr, y_tr, t_te)
        return mean, std * new_demonstration_scale(t_tr.shape[0])

    methods: dict[str, Callable[..., Any]] = {"local": default_local}
    if time_axis == "normalised":
        methods.update({"local-cal": calibrated, "promp": promp})
    unit = "s" if time_axis == "seconds" else "t / t_end"
    where = ", start-point frame" if frame == "start" else ""
    print(f"## LocalGP() on the LASA demonstrations' own stamps ({unit}{where}), all samples\n")
    shapes = lasa_shapes(folder, quick)
    if frame == "start":
        shapes = {n: (T, Y - Y[:, :1]) for n, (T, Y) in shapes.items()}
    if time_axis == "normalised":
        shapes = {n: ((T - T[:, :1]) / (T[:, -1:] - T[:, :1]), Y) for n, (T, Y) in shapes.items()}
    rows = loo_table(shapes, methods)
    for m, rs in rows.items():
        steps = np.array([r["step"] for r in rs])
        std_steps = np.array([r["std_step"] for r in rs])
        line = (
            f"\n{m}, {len(rs)} shapes: largest step ratio {steps.max():.2f} (median "
            f"{np.median(steps):.2f}, {int(np.sum(steps > 2))} shapes above 2); std "
            f"{std_steps.max():.2f} (median {np.median(std_steps):.2f}, "
            f"{int(np.sum(std_steps > 2))} above 2); bad folds {sum(r['bad'] for r in rs)}"
        )
        if "promp" in rows:
            pairs = list(zip(rs, rows["promp"], strict=True))
            covs = [r["cov"] for r in rs]
            line += (
                f"; RMSE / ProMP {np.mean([r['rmse'] / q['rmse'] for r, q in pairs]):.3f}, "
                f"NLPD - ProMP {np.mean([r['nlpd'] - q['nlpd'] for r, q in pairs]):+.2f}, "
                f"coverage {np.mean(covs):.3f} (per shape {min(covs):.3f}-{max(covs):.3f})"
            )
        print(line)


def print_summary(summary: dict[str, list[dict[str, float]]]) -> None:
    """Per method: means over the sets, the worst step ratio, the bad folds, the range of the
    per-set coverage, and the RMSE ratio / NLPD difference to the ProMP on the same sets."""
    print(
        "\n| method | mean RMSE | mean NLPD | mean cov. | cov. per set | worst step | "
        "worst std step | bad folds | RMSE / ProMP | NLPD - ProMP |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    ref = summary["promp"]
    for m, rs in summary.items():
        rm = np.mean([r["rmse"] for r in rs])
        nl = np.mean([r["nlpd"] for r in rs])
        covs = [r["cov"] for r in rs]
        ratio = np.mean([r["rmse"] / p["rmse"] for r, p in zip(rs, ref, strict=True)])
        dn = np.mean([r["nlpd"] - p["nlpd"] for r, p in zip(rs, ref, strict=True)])
        print(
            f"| {m} | {rm:.3f} | {nl:.2f} | {np.mean(covs):.3f} | "
            f"{min(covs):.3f} - {max(covs):.3f} | {max(r['step'] for r in rs):.2f} | "
            f"{max(r['std_step'] for r in rs):.2f} | {sum(r['bad'] for r in rs)} | "
            f"{ratio:.2f} | {dn:+.2f} |"
        )


if __name__ == "__main__":
    main()
