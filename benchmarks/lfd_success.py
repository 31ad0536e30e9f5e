"""Learning-from-demonstration success: methods x levels x perturbations x demonstrations x draws.

    python benchmarks/lfd_success.py --out results/lfd            # targets first, then coverage
    python benchmarks/lfd_success.py --out results/lfd --quick    # smoke run, ~2 CPU minutes
    python benchmarks/lfd_success.py --out results/lfd --resume   # continue an interrupted run
    python benchmarks/lfd_success.py --out results/lfd --report   # only rewrite the tables

Every cell is one method fitted from ``n`` demonstrations of one *draw*, evaluated on held-out
layouts of one level under one perturbation:

* methods (``METHODS``): ``gp`` (``GPDemonstrationPolicy``, the paper's local heteroscedastic
  GPs), ``promp`` (a ProMP per frame, ``lgp_policy.baselines.ProMPPolicy``), ``objrel`` (ONE
  demonstration's hand path relative to the cup, then the machine, tracked with IK:
  ``ObjectRelativeReplay``; it uses the draw's first demonstration whatever ``n``, so it runs at
  ``n = 1`` only), ``nearest`` (``NearestDemonstrationReplay``); ablations of the GP policy
  (``gp-calibrated``, ``gp-exact``, ``gp-joint``, ``gp-p3``, ``gp-noalign``) on request
  (``--methods``);
* levels: ``gym_coffee.LEVELS`` (only the easy level where the env has no levels);
* perturbations (``PERTURBATIONS``, env keywords on every level): none, the cup pushed 3-5 cm
  during the approach, 5 mm per-step observation noise, a 2 mm calibration bias, actuation noise;
  a perturbation the installed env does not accept is reported as unavailable;
* draws: draw ``k`` records its demonstrations from seeds ``1000 (k + 1)`` on (the teacher's
  failures are skipped, so a draw uses a few more seeds than demonstrations; draws never share a
  seed); the ``n``-demonstration set of a draw is its first ``n`` demonstrations;
* evaluation layouts: ``evaluate_policy_stages(seed=0)``, i.e. seeds ``10000 ...``, the same for
  every cell (paired comparison) and disjoint from every demonstration seed (checked).

The plan (``plan``, ``--part``) measures the issue's targets with many episodes and covers the
rest cheaply:

==========  ================================================================  ===========
part        cells                                                             episodes
==========  ================================================================  ===========
targets     hard, none: ``gp`` n = 8 and ``objrel``, 3 draws                   30 / draw
            easy, none: ``gp`` n = 4, 5 draws                                  30 / draw
            easy, cup push and 5 mm noise: ``gp`` n = 4, 3 draws                30 / draw
coverage    every level, every perturbation: every method at n = 4, 3 draws    10 / draw
sweep       every level, none: every method, n = 1, 2, 4, 8, 3 draws            10 / draw
==========  ================================================================  ===========

Cells that two parts plan are run once, with the larger number of episodes. Each result row
gives the success over all draws pooled with a 95% Wilson interval
(``scipy.stats.binomtest(...).proportion_ci(method="wilson")``), the range of the per-draw rates
(the spread between demonstration sets), the per-stage rates and the CPU seconds spent fitting
and evaluating. ``--out DIR`` gets ``results.json`` (every cell, written after each one, with
the commit of the measured code; ``--resume`` skips finished cells and continues a cell of the
same committed code on its missing layouts only) and ``results.md`` (the tables: methods x
demonstrations per level, the README's headline, levels x perturbations, the targets). BLAS is
pinned to one thread; ``--jobs`` runs fit-and-evaluate units in that many processes (on a
loaded 2-core machine, 1 or 2).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

import gym_coffee

ROOT = Path(__file__).resolve().parents[1]
MEASURED_CODE = (
    "gym_coffee",
    "lgp_policy",
    ":(exclude)lgp_policy/app",
    "lgp_policy/app/evaluation.py",
    "lgp_policy/app/backends.py",
)
"""Git pathspec of the code a cell measures (the env, the teacher, the policies, the episode
loop); its last commit is each row's ``code``, with ``+dirty`` for uncommitted changes there."""
DRAW_SEED_STRIDE = 1000
"""Draw ``k`` records demonstrations from seed ``DRAW_SEED_STRIDE * (k + 1)`` on."""
EVAL_SEED = 0
"""``evaluate_policy_stages(seed=EVAL_SEED)``: layouts ``EVAL_SEED_OFFSET + EVAL_SEED + i``."""
N_DEMOS = (1, 2, 4, 8)
COVERAGE_EPISODES = 10
TARGET_EPISODES = 30
COVERAGE_DRAWS = 3
STAGE_KEYS = (*gym_coffee.STAGES, "is_success")

#: Perturbation name -> env keyword arguments (the env's documented perturbation options).
PERTURBATIONS: dict[str, dict[str, Any]] = {
    "none": {},
    "cup_push": {"cup_push": (0.03, 0.05)},
    "obs_noise_5mm": {"obs_noise": 0.005},
    "calib_2mm": {"calibration_bias": 0.002},
    "actuation": {"actuation_noise": 0.01},
}
PERTURBATION_LABELS = {
    "none": "none",
    "cup_push": "cup pushed 3-5 cm",
    "obs_noise_5mm": "obs. noise 5 mm",
    "calib_2mm": "calib. bias 2 mm",
    "actuation": "actuation noise 0.01 rad",
}


def _gp(**kwargs: Any) -> Callable[[], Any]:
    def make() -> Any:
        from lgp_policy.lfd.policy import GPDemonstrationPolicy

        return GPDemonstrationPolicy(**kwargs)

    return make


def _baseline(name: str) -> Callable[[], Any]:
    def make() -> Any:
        import lgp_policy.baselines as baselines

        return getattr(baselines, name)()

    return make


#: Method name -> (description, policy factory). The policy is fitted with ``fit(demos)``.
METHODS: dict[str, tuple[str, Callable[[], Any]]] = {
    "gp": ("GP policy (local heteroscedastic GPs, Alg. 3)", _gp()),
    "promp": ("ProMP per frame + Alg. 3", _baseline("ProMPPolicy")),
    "objrel": ("object-relative replay of 1 demo (IK)", _baseline("ObjectRelativeReplay")),
    "nearest": ("nearest-demonstration joint replay", _baseline("NearestDemonstrationReplay")),
    "gp-calibrated": ("GP policy, calibrated LocalGP combination", _gp(combine="calibrated")),
    "gp-exact": ("GP policy, one exact homoscedastic GP", _gp(model="exact")),
    "gp-joint": ("GP policy, joint frame only", _gp(frames=())),
    "gp-p3": ("GP policy, grasp point only (p = 3)", _gp(approach_offset=None)),
    "gp-noalign": ("GP policy, plain normalised time", _gp(align=None)),
}
MAIN_METHODS = ("gp", "promp", "objrel", "nearest")
SINGLE_DEMO_METHODS = frozenset({"objrel"})


def levels() -> dict[str, str]:
    """Level name -> env id: ``gym_coffee.LEVELS`` where the env has levels."""
    return dict(getattr(gym_coffee, "LEVELS", {"easy": gym_coffee.ENV_ID}))


@dataclass(frozen=True)
class Cell:
    method: str
    level: str
    perturbation: str
    n_demos: int
    draw: int

    @property
    def key(self) -> str:
        return f"{self.method}|{self.level}|{self.perturbation}|{self.n_demos}|{self.draw}"


@dataclass
class Unit:
    """One fit (method, level, n, draw) and its evaluations (perturbation -> episodes)."""

    method: str
    level: str
    n_demos: int
    draw: int
    episodes: dict[str, int] = field(default_factory=dict)
    extend: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Perturbation -> a finished row of the same code: only its missing layouts are run."""


# ---------------------------------------------------------------------------------------- plan
PARTS = ("targets", "coverage", "sweep")


def plan(
    *,
    quick: bool,
    methods: Sequence[str],
    level_names: Sequence[str],
    perturbations: Sequence[str],
    parts: Sequence[str] = PARTS,
    target_episodes: int = TARGET_EPISODES,
    coverage_episodes: int = COVERAGE_EPISODES,
    draws: int = COVERAGE_DRAWS,
) -> dict[Cell, int]:
    """Cells to run and their episodes per draw (in the order of ``PARTS``).

    ``targets``: the issue's targets (fixed draws, ``target_episodes``); ``coverage``: every
    method, level and perturbation at n = 4; ``sweep``: every method and level without
    perturbation at n = 1, 2, 4, 8. Both with ``draws`` draws and ``coverage_episodes``.
    """
    cells: dict[Cell, int] = {}

    def add(method: str, level: str, pert: str, n: int, draw_ids: Iterable[int], eps: int) -> None:
        if method not in methods or level not in level_names or pert not in perturbations:
            return
        if method in SINGLE_DEMO_METHODS:
            n = 1
        for k in draw_ids:
            c = Cell(method, level, pert, n, k)
            cells[c] = max(cells.get(c, 0), eps)

    if quick:
        for m in methods:
            add(m, level_names[0], "none", 2, range(COVERAGE_DRAWS), 2)
        return cells
    if "targets" in parts:
        t = target_episodes
        add("gp", "hard", "none", 8, range(3), t)
        add("objrel", "hard", "none", 1, range(3), t)
        add("gp", "easy", "none", 4, range(5), t)
        add("gp", "easy", "cup_push", 4, range(3), t)
        add("gp", "easy", "obs_noise_5mm", 4, range(3), t)
    c = coverage_episodes
    if "coverage" in parts:
        for level in level_names:
            for pert in perturbations:
                for m in methods:
                    add(m, level, pert, 4, range(draws), c)
    if "sweep" in parts:
        for level in level_names:
            for n in N_DEMOS:
                for m in methods:
                    add(m, level, "none", n, range(draws), c)
    return cells


def units(
    cells: Mapping[Cell, int], extend: Mapping[Cell, dict[str, Any]] | None = None
) -> list[Unit]:
    """Group cells sharing one fit, in the order of their first cell; ``extend``: finished rows
    that the cells continue (their layouts are not run again)."""
    out: dict[tuple[str, str, int, int], Unit] = {}
    for c, eps in cells.items():
        key = (c.method, c.level, c.n_demos, c.draw)
        unit = out.setdefault(key, Unit(c.method, c.level, c.n_demos, c.draw))
        unit.episodes[c.perturbation] = eps
        if extend and c in extend:
            unit.extend[c.perturbation] = extend[c]
    return list(out.values())


def code_version() -> str:
    """The last commit of :data:`MEASURED_CODE` (``+dirty`` with uncommitted changes there), or
    ``"unknown"`` outside a git checkout."""
    import subprocess

    try:

        def git(*args: str) -> str:
            done = subprocess.run(
                ["git", *args, "--", *MEASURED_CODE],
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=60,
                check=True,
            )
            return done.stdout.strip()

        commit = git("log", "-1", "--format=%h")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if not commit:
        return "unknown"
    return commit + ("+dirty" if dirty else "")


def can_extend(row: Mapping[str, Any] | None, code: str) -> bool:
    """Whether a finished row can be continued by running only its missing layouts: measured
    on the same committed code (a fit is deterministic given the demonstrations)."""
    from lgp_policy.app.evaluation import EVAL_SEED_OFFSET

    return (
        row is not None
        and row.get("status") == "ok"
        and row.get("code") == code
        and "unknown" not in code
        and "dirty" not in code
        and row.get("eval_seeds", [None])[0] == EVAL_SEED_OFFSET + EVAL_SEED
    )


# --------------------------------------------------------------------------------------- demos
def demo_path(out: Path, level: str, draw: int) -> Path:
    return out / "demos" / f"{level}-draw{draw}.npz"


def record_demos(out: Path, level: str, env_id: str, draw: int, n: int) -> Any:
    """The draw's first ``n`` demonstrations (recorded once, then read from ``out/demos``)."""
    import gymnasium as gym

    from gym_coffee.demonstrations import DemonstrationSet

    path = demo_path(out, level, draw)
    if path.exists():
        demos = DemonstrationSet.load(path)
        if len(demos) >= n:
            return demos
    env = gym.make(env_id)
    try:
        demos = gym_coffee.collect_demonstrations(env, n=n, seed=DRAW_SEED_STRIDE * (draw + 1))
    finally:
        env.close()
    seeds = demos.metadata["seeds"] + demos.metadata["failed_seeds"]
    if max(seeds) >= DRAW_SEED_STRIDE * (draw + 2):
        raise RuntimeError(f"draw {draw} ran into the next draw's seeds: {seeds}")
    path.parent.mkdir(parents=True, exist_ok=True)
    demos.save(path, overwrite=True)
    return demos


# ---------------------------------------------------------------------------------------- run
def _cpu() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def env_accepts(env_id: str, kwargs: Mapping[str, Any]) -> str | None:
    """``None`` if ``gym.make(env_id, **kwargs)`` works, else why not."""
    import gymnasium as gym

    try:
        gym.make(env_id, **kwargs).close()
    except (TypeError, ValueError) as exc:
        return f"{type(exc).__name__}: {exc}"
    return None


def run_unit(unit: Unit, out: Path, workers: int, code: str = "unknown") -> list[dict[str, Any]]:
    """Fit one policy and evaluate it under each of the unit's perturbations (for a row in
    ``unit.extend``, only on the layouts it lacks, and add them to it)."""
    from threadpoolctl import threadpool_limits

    from lgp_policy.app.evaluation import EVAL_SEED_OFFSET, evaluate_policy_stages

    threadpool_limits(1)
    env_id = levels()[unit.level]
    demos = record_demos(out, unit.level, env_id, unit.draw, max(N_DEMOS))[: unit.n_demos]
    demo_seeds = [int(d.seed) for d in demos]
    t0 = _cpu()
    policy = METHODS[unit.method][1]().fit(demos)
    fit_cpu = _cpu() - t0
    rows = []
    for pert, eps in unit.episodes.items():
        base = {
            "method": unit.method,
            "level": unit.level,
            "env_id": env_id,
            "perturbation": pert,
            "env_kwargs": PERTURBATIONS[pert],
            "n_demos": unit.n_demos,
            "draw": unit.draw,
            "demo_seeds": demo_seeds,
            "code": code,
            "fit_cpu_s": round(fit_cpu, 2),
        }
        why = env_accepts(env_id, PERTURBATIONS[pert])
        if why is not None:
            rows.append({**base, "status": f"unavailable ({why})"})
            continue
        old = unit.extend.get(pert)
        if old is not None and old["demo_seeds"] != demo_seeds:
            raise RuntimeError(f"{_row_key(old)}: its demonstrations changed; run it anew")
        first = 0 if old is None else int(old["episodes"])
        eval_seeds = [EVAL_SEED_OFFSET + EVAL_SEED + i for i in range(eps)]
        if set(eval_seeds) & set(demo_seeds) or min(eval_seeds) <= max(demo_seeds):
            raise RuntimeError("evaluation layouts overlap the demonstration seeds")
        t0 = _cpu()
        res = evaluate_policy_stages(
            policy,
            eps - first,
            seed=EVAL_SEED + first,
            workers=workers,
            progress=False,
            env_id=env_id,
            env_kwargs=PERTURBATIONS[pert],
        )
        n_new = int(res["n_episodes"])
        row: dict[str, Any] = {
            **base,
            "status": "ok",
            "episodes": n_new,
            "eval_seeds": [min(eval_seeds), max(eval_seeds)],
            "successes": {k: int(res["stages"][k]["successes"]) for k in STAGE_KEYS},
            "failed_seeds": [int(e["seed"]) for e in res["episodes"] if not e["is_success"]],
            "episode_length_mean": float(res["episode_length"]["mean"]),
            "eval_cpu_s": round(_cpu() - t0, 2),
        }
        if old is not None:  # the same policy on the earlier layouts: add them up
            n_all = first + n_new
            row.update(
                episodes=n_all,
                successes={k: row["successes"][k] + old["successes"][k] for k in STAGE_KEYS},
                failed_seeds=sorted({*old.get("failed_seeds", []), *row["failed_seeds"]}),
                episode_length_mean=(
                    first * old["episode_length_mean"] + n_new * row["episode_length_mean"]
                )
                / n_all,
                eval_cpu_s=round(old["eval_cpu_s"] + row["eval_cpu_s"], 2),
                extended_from=first,
            )
            if "failed_seeds" not in old:  # a row from before the field: not known in full
                del row["failed_seeds"]
        rows.append(row)
    return rows


# ------------------------------------------------------------------------------------ results
def _atomic_write(path: Path, text: str) -> None:
    """Replace ``path`` atomically (the project's one file helper, ``lgp_policy._io``)."""
    from lgp_policy._io import atomic_write_text

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text, force=True)


def load_results(out: Path) -> dict[str, dict[str, Any]]:
    path = out / "results.json"
    if not path.exists():
        return {}
    data = json.loads(path.read_text())
    return {_row_key(r): r for r in data.get("cells", [])}


def _row_key(r: Mapping[str, Any]) -> str:
    return Cell(r["method"], r["level"], r["perturbation"], r["n_demos"], r["draw"]).key


def wilson(k: int, n: int) -> tuple[float, float]:
    """95% Wilson score interval of ``k`` successes in ``n`` trials (scipy)."""
    from scipy.stats import binomtest

    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def aggregate(rows: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Pool the draws of every (method, level, perturbation, n)."""
    groups: dict[tuple[str, str, str, int], list[Mapping[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["method"], r["level"], r["perturbation"], r["n_demos"]), []).append(r)
    out = []
    for (method, level, pert, n), rs in groups.items():
        ok = [r for r in rs if r["status"] == "ok"]
        agg: dict[str, Any] = {
            "method": method,
            "level": level,
            "perturbation": pert,
            "n_demos": n,
            "draws": sorted(r["draw"] for r in ok),
        }
        if not ok:
            agg["status"] = rs[0]["status"]
            out.append(agg)
            continue
        episodes = sum(r["episodes"] for r in ok)
        stages = {}
        for k in STAGE_KEYS:
            succ = sum(r["successes"][k] for r in ok)
            lo, hi = wilson(succ, episodes)
            stages[k] = {"successes": succ, "rate": succ / episodes, "ci_low": lo, "ci_high": hi}
        per_draw = [r["successes"]["is_success"] / r["episodes"] for r in ok]
        agg.update(
            status="ok",
            episodes=episodes,
            episodes_per_draw=sorted({r["episodes"] for r in ok}),
            stages=stages,
            success_per_draw=per_draw,
            success_mean_over_draws=float(np.mean(per_draw)),
            success_range=[min(per_draw), max(per_draw)],
            fit_cpu_s=float(np.mean([r["fit_cpu_s"] for r in ok])),
            eval_cpu_s_per_episode=sum(r["eval_cpu_s"] for r in ok) / episodes,
        )
        out.append(agg)
    order = {m: i for i, m in enumerate(METHODS)}
    return sorted(
        out,
        key=lambda a: (
            a["level"],
            list(PERTURBATIONS).index(a["perturbation"]),
            order.get(a["method"], 99),
            a["n_demos"],
        ),
    )


def _pct(x: float) -> str:
    return f"{100 * x:.0f}"


def _cell_text(a: Mapping[str, Any] | None) -> str:
    if a is None:
        return "not run"
    if a["status"] != "ok":
        return "n/a"
    s = a["stages"]["is_success"]
    lo, hi = a["success_range"]
    spread = f"; draws {_pct(lo)}-{_pct(hi)}" if len(a["draws"]) > 1 else ""
    return f"{_pct(s['rate'])} [{_pct(s['ci_low'])}, {_pct(s['ci_high'])}]{spread}"


TARGETS = (
    # (text, method, level, perturbation, n, statistic, comparison, threshold)
    ("hard: GP from 8 demos >= 90%", "gp", "hard", "none", 8, "pooled", ">=", 0.90),
    (
        "hard: 1-demo object-relative replay <= 70%",
        "objrel",
        "hard",
        "none",
        1,
        "pooled",
        "<=",
        0.70,
    ),
    ("cup pushed 3-5 cm: GP (4 demos) >= 95%", "gp", "easy", "cup_push", 4, "pooled", ">=", 0.95),
    (
        "obs. noise 5 mm: GP (4 demos) >= 95%",
        "gp",
        "easy",
        "obs_noise_5mm",
        4,
        "pooled",
        ">=",
        0.95,
    ),
    ("easy: GP 4 demos >= 98%, mean of 5 draws", "gp", "easy", "none", 4, "mean5", ">=", 0.98),
)


def markdown(aggs: Sequence[Mapping[str, Any]], meta: Mapping[str, Any]) -> str:
    """The tables: headline, targets, and every pooled cell."""
    by = {(a["method"], a["level"], a["perturbation"], a["n_demos"]): a for a in aggs}
    lines = [
        "# LfD success benchmark",
        "",
        f"`{meta['command']}`; {meta['date']}; gym-coffee {gym_coffee.__version__}. "
        "Success (task completed) in %, pooled over demonstration draws, with the 95% Wilson "
        "interval and the range of the per-draw rates. Evaluation layouts: seeds "
        f"{meta['eval_seeds']}; demonstration draws: seeds {meta['demo_seeds']}.",
        "",
    ]
    levels_run = sorted({a["level"] for a in aggs}, key=lambda x: (x != "easy", x))
    perts_run = [p for p in PERTURBATIONS if any(a["perturbation"] == p for a in aggs)]
    # Headline: methods x number of demonstrations, per level, without perturbation.
    for lv in levels_run:
        ns = sorted(
            {a["n_demos"] for a in aggs if a["level"] == lv and a["perturbation"] == "none"}
        )
        if len(ns) < 2:
            continue
        rows_m = [m for m in METHODS if any((m, lv, "none", n) in by for n in ns)]
        lines += [f"## Demonstrations: {lv} level, no perturbation", ""]
        lines.append(
            "Success % [95% Wilson interval] pooled over the draws; the range of the per-draw "
            "rates; (episodes = draws x layouts)."
        )
        header = " | ".join(f"{n} demo{'s' if n > 1 else ''}" for n in ns)
        lines += ["", f"| method | {header} |"]
        lines.append("|---|" + "---|" * len(ns))
        for m in rows_m:
            cells_m = []
            for n in ns:
                a = by.get((m, lv, "none", n))
                if a is None and m in SINGLE_DEMO_METHODS and n > 1:
                    cells_m.append("(uses 1 demo)")
                    continue
                text = _cell_text(a)
                if a is not None and a["status"] == "ok":
                    text += f" ({len(a['draws'])} x {'/'.join(map(str, a['episodes_per_draw']))})"
                cells_m.append(text)
            lines.append(f"| {m} | " + " | ".join(cells_m) + " |")
        lines.append("")
    # Methods at their main n, every level x perturbation.
    head_rows = []
    for m in MAIN_METHODS:
        ns = sorted({a["n_demos"] for a in aggs if a["method"] == m})
        wanted = [n for n in (8, 4) if n in ns] if m == "gp" else [n for n in (4,) if n in ns]
        head_rows += [(m, n) for n in (wanted or ns[-1:])]
    cols = [(lv, p) for lv in levels_run for p in perts_run]
    cols = [c for c in cols if any((m, *c, n) in by for m, n in head_rows)]
    lines += ["## Levels and perturbations", ""]
    lines.append(
        "| method | demos | "
        + " | ".join(f"{lv}: {PERTURBATION_LABELS[p]}" for lv, p in cols)
        + " |"
    )
    lines.append("|---|---:|" + "---|" * len(cols))
    for m, n in head_rows:
        if not any((m, *c, n) in by for c in cols):
            continue
        cells = [_cell_text(by.get((m, *c, n))) for c in cols]
        lines.append(f"| {m} | {n} | " + " | ".join(cells) + " |")
    lines += ["", "## Targets (issue 11)", ""]
    lines += ["| target | measured | episodes | draws | verdict |", "|---|---|---:|---:|---|"]
    for text, m, lv, p, n, stat, cmp, thr in TARGETS:
        a = by.get((m, lv, p, n))
        if a is None or a["status"] != "ok":
            lines.append(f"| {text} | {'not run' if a is None else a['status']} | | | |")
            continue
        if stat == "mean5":
            value = a["success_mean_over_draws"]
            shown = f"mean over draws {100 * value:.1f}% ({_cell_text(a)})"
            enough = len(a["draws"]) >= 5
        else:
            value = a["stages"]["is_success"]["rate"]
            shown = _cell_text(a)
            enough = True
        met = value >= thr if cmp == ">=" else value <= thr
        verdict = ("met" if met else "MISSED") + ("" if enough else " (fewer than 5 draws)")
        lines.append(f"| {text} | {shown} | {a['episodes']} | {len(a['draws'])} | {verdict} |")
    lines += ["", "## All cells", ""]
    lines.append(
        "| level | perturbation | method | demos | success % [95% CI] | per-draw range | "
        "grasp % | place % | press % | episodes | fit CPU s | eval CPU s/episode |"
    )
    lines.append("|---|---|---|---:|---|---|---:|---:|---:|---:|---:|---:|")
    for a in aggs:
        if a["status"] != "ok":
            lines.append(
                f"| {a['level']} | {a['perturbation']} | {a['method']} | {a['n_demos']} | "
                f"{a['status']} | | | | | | | |"
            )
            continue
        st = a["stages"]
        s = st["is_success"]
        lo, hi = a["success_range"]
        lines.append(
            f"| {a['level']} | {a['perturbation']} | {a['method']} | {a['n_demos']} | "
            f"{100 * s['rate']:.1f} [{100 * s['ci_low']:.1f}, {100 * s['ci_high']:.1f}] | "
            f"{_pct(lo)}-{_pct(hi)} ({len(a['draws'])}) | "
            + " | ".join(f"{100 * st[k]['rate']:.0f}" for k in gym_coffee.STAGES)
            + f" | {a['episodes']} | {a['fit_cpu_s']:.1f} | {a['eval_cpu_s_per_episode']:.2f} |"
        )
    lines += ["", "Methods:", ""]
    lines += [f"* `{m}`: {METHODS[m][0]}" for m in sorted({a["method"] for a in aggs})]
    lines += ["", "Perturbations (env keywords):", ""]
    lines += [f"* `{p}`: `{PERTURBATIONS[p]}`" for p in perts_run]
    return "\n".join(lines) + "\n"


def write_results(out: Path, rows: Mapping[str, Mapping[str, Any]], meta: dict[str, Any]) -> None:
    cells = sorted(rows.values(), key=_row_key)
    seeds = [s for r in cells for s in r["demo_seeds"]]
    evals = [s for r in cells if r["status"] == "ok" for s in r["eval_seeds"]]
    meta = {
        **meta,
        "demo_seeds": f"{min(seeds)}-{max(seeds)}" if seeds else "-",
        "eval_seeds": f"{min(evals)}-{max(evals)}" if evals else "-",
    }
    aggs = aggregate(cells)
    _atomic_write(
        out / "results.json",
        json.dumps({"meta": meta, "cells": cells, "pooled": aggs}, indent=1) + "\n",
    )
    _atomic_write(out / "results.md", markdown(aggs, meta))


# --------------------------------------------------------------------------------------- main
def _run_one(args: tuple[Unit, str, int, str]) -> list[dict[str, Any]]:
    unit, out, workers, code = args
    return run_unit(unit, Path(out), workers, code)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="directory for results.json/.md")
    ap.add_argument("--quick", action="store_true", help="smoke run: n = 2, 2 episodes per draw")
    ap.add_argument(
        "--resume",
        action="store_true",
        help="skip cells already in results.json; a cell with fewer episodes than planned runs "
        "only its missing layouts if it was measured on the same committed code (else anew)",
    )
    ap.add_argument("--report", action="store_true", help="only rewrite results.md from the JSON")
    ap.add_argument(
        "--force",
        action="store_true",
        help="start anew in an --out that has a results.json (its cells are replaced)",
    )
    ap.add_argument(
        "--merge",
        type=Path,
        nargs="*",
        default=[],
        help="with --report: also take the cells of these output directories (runs split over "
        "processes or machines; a cell present twice keeps the one with more episodes)",
    )
    ap.add_argument("--methods", default=",".join(MAIN_METHODS), help="comma-separated")
    ap.add_argument("--levels", default=None, help="comma-separated (default: every level)")
    ap.add_argument("--perturbations", default=",".join(PERTURBATIONS), help="comma-separated")
    ap.add_argument(
        "--part",
        choices=("all", *PARTS),
        default="all",
        help="targets: the issue's targets; coverage: every perturbation at n = 4; sweep: "
        "n = 1, 2, 4, 8 without perturbation",
    )
    ap.add_argument(
        "--draws", type=int, default=COVERAGE_DRAWS, help="demonstration draws (coverage, sweep)"
    )
    ap.add_argument("--target-episodes", type=int, default=TARGET_EPISODES, help="per draw")
    ap.add_argument("--coverage-episodes", type=int, default=COVERAGE_EPISODES, help="per draw")
    ap.add_argument("--jobs", type=int, default=1, help="processes running fit+evaluate units")
    ap.add_argument("--workers", type=int, default=1, help="env processes per evaluation")
    ap.add_argument("--max-units", type=int, default=None, help="stop after this many units")
    args = ap.parse_args(argv)

    methods = [m for m in args.methods.split(",") if m]
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        ap.error(f"--methods: unknown {unknown}; known: {list(METHODS)}")
    perts = [p for p in args.perturbations.split(",") if p]
    if set(perts) - set(PERTURBATIONS):
        ap.error(f"--perturbations: known are {list(PERTURBATIONS)}")
    known_levels = levels()
    level_names = list(known_levels) if args.levels is None else args.levels.split(",")
    if set(level_names) - set(known_levels):
        ap.error(f"--levels: this gym_coffee has {list(known_levels)}")
    if min(args.jobs, args.workers, args.target_episodes, args.coverage_episodes, args.draws) < 1:
        ap.error(
            "--jobs, --workers, --target-episodes, --coverage-episodes and --draws must be >= 1"
        )

    out: Path = args.out
    if (out / "results.json").exists() and not (args.resume or args.report or args.force):
        ap.error(
            f"--out: {out}/results.json exists; --resume continues it, --report rewrites its "
            "tables, --force starts anew"
        )
    rows = load_results(out) if (args.resume or args.report) else {}
    meta: dict[str, Any] = {
        "command": "python benchmarks/lfd_success.py "
        + " ".join(a for a in (argv if argv is not None else sys.argv[1:])),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "levels": known_levels,
        "code": code_version(),
    }
    saved = out / "results.json"
    old_meta = json.loads(saved.read_text()).get("meta", {}) if rows and saved.exists() else {}
    if args.report:
        meta = {**meta, **old_meta}
        for other in args.merge:
            for key, row in load_results(other).items():
                if row.get("episodes", -1) > rows.get(key, {}).get("episodes", -1):
                    rows[key] = row
        write_results(out, rows, meta)
        print((out / "results.md").read_text())
        return
    if old_meta.get("command"):  # --resume: the tables come from several runs
        meta["command"] = f"{old_meta['command']}`, then `{meta['command']}"
    cells = plan(
        quick=args.quick,
        methods=methods,
        level_names=level_names,
        perturbations=perts,
        parts=PARTS if args.part == "all" else (args.part,),
        target_episodes=args.target_episodes,
        coverage_episodes=args.coverage_episodes,
        draws=args.draws,
    )
    todo = {c: e for c, e in cells.items() if rows.get(c.key, {}).get("episodes", -1) < e}
    extend = {c: rows[c.key] for c in todo if can_extend(rows.get(c.key), meta["code"])}
    if "hard" not in known_levels:
        print("note: this gym_coffee has no hard level; its cells are skipped")
    work = units(todo, extend)[: args.max_units]
    n_eps = sum(e - (extend[c]["episodes"] if c in extend else 0) for c, e in todo.items())
    print(
        f"{len(cells)} cells planned, {len(todo)} to run ({len(extend)} of them continued) in "
        f"{len(work)} fit units ({n_eps} episodes); code {meta['code']}; writing "
        f"{out}/results.json",
        flush=True,
    )

    def done(unit: Unit, new_rows: list[dict[str, Any]]) -> None:
        for r in new_rows:
            rows[_row_key(r)] = r
            if r["status"] == "ok":
                s = r["successes"]["is_success"]
                print(
                    f"{r['method']:>8} {r['level']:>5} {r['perturbation']:>14} n={r['n_demos']} "
                    f"draw {r['draw']}: {s}/{r['episodes']} success "
                    f"(fit {r['fit_cpu_s']:.0f} s, eval {r['eval_cpu_s']:.0f} s CPU)",
                    flush=True,
                )
            else:
                print(f"{_row_key(r)}: {r['status']}", flush=True)
        write_results(out, rows, meta)

    jobs = [(u, str(out), args.workers, str(meta["code"])) for u in work]
    if args.jobs == 1:
        for job in jobs:
            done(job[0], _run_one(job))
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(args.jobs, mp_context=mp.get_context("spawn")) as pool:
            futures = {pool.submit(_run_one, job): job[0] for job in jobs}
            for fut in as_completed(futures):
                done(futures[fut], fut.result())
    write_results(out, rows, meta)
    print((out / "results.md").read_text())


if __name__ == "__main__":
    main()
