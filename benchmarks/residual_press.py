"""Residual-RL fine-tuning of the button press under a calibration error: base vs fine-tuned.

Prints, for held-out layouts (seeds ``EVAL_SEED_OFFSET + i``, the ``gym-coffee evaluate`` layouts;
the learning curve uses the disjoint seeds ``CURVE_SEED_OFFSET + i``):

- the base GP policy's per-stage success on the plain env and under the calibration bias (the
  env's ``calibration_bias``, default 2 mm: per episode, the observed cup positions are off by
  that length in one random 3-D direction and the observed machine position in another; the
  policy cannot observe it. The button's face has a 12 mm radius, so only the offset's
  component along the button's axis matters for the press: for a random direction it is
  uniform in [-2, 2] mm, and a press the base ends a millimetre or two short of 5 mm of travel
  does not count);
- per training seed: the fine-tuned policy's per-stage success (incl. ``cup_placed_at_end``: no
  stage lost), env steps, wall and CPU time of training;
- the targets: fine-tuned press >= 95% on every seed, no stage below the base's.

Every rate comes with its 95% Wilson interval.

Usage::

    python benchmarks/residual_press.py                       # 3 seeds x 50k env steps, 100 layouts
    python benchmarks/residual_press.py --quick               # 1 seed x 10k env steps, 20 layouts
    python benchmarks/residual_press.py --seeds 1 2 --policy runs/residual_press/base_policy.npz
    python benchmarks/residual_press.py --backend ray         # seeds as Ray tasks
    python benchmarks/residual_press.py --policy base.npz --runs ft/   # evaluate only: the
        # seeds ft/seedS/ written by `gym-coffee finetune base.npz --out ft/ --seeds S ...`

The base policy is fitted here from 4 teacher demonstrations (seeds 0-3) unless ``--policy`` names
a file. Everything goes to ``--out`` (default ``runs/residual_press``): the base policy, per seed
the fine-tuned policy with its learning curve and checkpoints, ``results-<seeds>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")

from lgp_policy._io import atomic_write_text  # after the thread variables

STAGES = ("cup_grasped", "cup_placed", "cup_placed_at_end", "button_pressed", "is_success")


def _fit_base(out: Path, n_demos: int) -> Path:
    import gymnasium as gym

    import gym_coffee
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    path = out / "base_policy.npz"
    if path.exists():
        return path
    env = gym.make(gym_coffee.ENV_ID)
    t0 = time.perf_counter()
    demos = gym_coffee.collect_demonstrations(env, n=n_demos, seed=0, progress=True)
    env.close()
    GPDemonstrationPolicy.fit(demos).save(path)
    print(f"base policy: {n_demos} demonstrations, fitted in {time.perf_counter() - t0:.1f} s")
    return path


def _cached_eval(out: Path, base_path: Path, bias: float, seeds: list[int], base) -> dict:
    """The base policy's evaluation, reused from ``out/base_eval.json`` for the same policy file,
    bias and layouts (so ``--seeds 1 2`` later does not redo it)."""
    import hashlib

    from lgp_policy.app.finetune_cli import build_env_fn, evaluate_stages

    digest = hashlib.sha256(base_path.read_bytes()).hexdigest()
    key = f"{digest}|calibration_bias={bias}|{seeds[0]}|{len(seeds)}"
    cache_path = out / "base_eval.json"
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    if key not in cache:
        cache[key] = evaluate_stages(base, build_env_fn(bias), seeds)
        atomic_write_text(cache_path, json.dumps(cache, indent=2), force=True)  # a cache
    return cache[key]


def _cell(rate: float, n: int) -> str:
    """``rate`` in percent with its 95% Wilson interval."""
    from lgp_policy.app.evaluation import wilson_interval

    lo, hi = wilson_interval(round(rate * n), n)
    return f"{100 * rate:.0f} [{100 * lo:.0f}, {100 * hi:.0f}]"


def _table(rows: dict[str, dict[str, float]], n: int) -> str:
    columns = list(rows)
    head = f"{'stage':<19}" + "".join(f"{c:>16}" for c in columns)
    lines = [head, "-" * len(head)]
    for stage in STAGES:
        lines.append(f"{stage:<19}" + "".join(f"{_cell(rows[c][stage], n):>16}" for c in columns))
    lines.append(
        f"(% of {n} held-out layouts [95% Wilson interval]; a stage counts if reached at any step)"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 seed, 10k steps, 20 layouts")
    ap.add_argument("--seeds", type=int, nargs="+", default=None)
    ap.add_argument("--timesteps", type=int, default=None, help="env-step budget per seed")
    ap.add_argument("--episodes", type=int, default=None, help="held-out layouts (default 100)")
    ap.add_argument("--algo", choices=("sac", "td3", "ppo"), default="sac")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--reward", choices=("shaped", "env"), default="shaped")
    ap.add_argument("--gate-start", type=float, default=None)
    ap.add_argument("--calibration-bias", type=float, default=0.002, metavar="M")
    ap.add_argument("--policy", type=Path, default=None, help="base policy file (else fitted)")
    ap.add_argument("--demos", type=int, default=4)
    ap.add_argument("--curve-episodes", type=int, default=10)
    ap.add_argument("--eval-freq", type=int, default=10_000)
    ap.add_argument(
        "--keep-best",
        action="store_true",
        help="keep each seed's policy of its best learning-curve point (the curve layouts are "
        "disjoint from the held-out layouts of the table)",
    )
    ap.add_argument("--backend", choices=("local", "ray"), default="local")
    ap.add_argument("--out", type=Path, default=Path("runs/residual_press"))
    ap.add_argument(
        "--force",
        action="store_true",
        help="replace the seeds' runs and results file of an earlier run in --out",
    )
    ap.add_argument(
        "--runs",
        type=Path,
        default=None,
        help="evaluate the seeds already fine-tuned in RUNS/seedS (gym-coffee finetune --out "
        "RUNS) instead of training; needs --policy (their base)",
    )
    args = ap.parse_args(argv)
    if args.runs is not None and args.policy is None:
        ap.error("argument --runs: needs --policy (the base the runs were fine-tuned from)")

    seeds = args.seeds or ([0] if args.quick else [0, 1, 2])
    budget = args.timesteps or (10_000 if args.quick else 50_000)
    n_eval = args.episodes or (20 if args.quick else 100)
    finished: dict[int, dict] = {}  # --runs: each seed's learning_curve.json, checked before work
    for seed in seeds if args.runs is not None else []:
        curve_file = args.runs / f"seed{seed}" / "learning_curve.json"
        if not (curve_file.is_file() and curve_file.with_name("residual_policy.npz").is_file()):
            ap.error(f"argument --runs: no finished run {curve_file.parent}")
        finished[seed] = json.loads(curve_file.read_text())
        if finished[seed]["algo"] != args.algo:
            ap.error(f"argument --runs: {curve_file.parent} is a {finished[seed]['algo']} run")
    bias = args.calibration_bias
    results_file = args.out / f"results-{'-'.join(map(str, seeds))}.json"
    earlier = [results_file] if results_file.exists() else []
    if args.runs is None:
        runs_dir = args.out / f"bias{bias * 1e3:g}mm-{args.algo}"
        earlier += [runs_dir / f"seed{s}" for s in seeds if (runs_dir / f"seed{s}").exists()]
    if earlier and not args.force:
        ap.error(f"argument --out: {earlier[0]} exists (an earlier run); --force replaces it")

    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    threadpool_limits(1)

    from lgp_policy.app.evaluation import EVAL_SEED_OFFSET
    from lgp_policy.app.finetune_cli import (
        FinetuneJob,
        build_env_fn,
        evaluate_stages,
        make_gate,
        run_jobs,
    )
    from lgp_policy.lfd.policy import GPDemonstrationPolicy
    from lgp_policy.residual import ResidualPolicy

    args.out.mkdir(parents=True, exist_ok=True)
    base_path = args.policy or _fit_base(args.out, args.demos)
    base = GPDemonstrationPolicy.load(base_path)
    test_seeds = [EVAL_SEED_OFFSET + i for i in range(n_eval)]
    print(f"base policy {base_path}; gate {make_gate(base, args.gate_start).to_config()}")
    t0 = time.perf_counter()
    plain = _cached_eval(args.out, base_path, 0.0, test_seeds, base)["rates"]
    biased = _cached_eval(args.out, base_path, bias, test_seeds, base)["rates"]
    print(f"base evaluated in {time.perf_counter() - t0:.0f} s")
    rows = {"base plain": plain, f"base {bias * 1e3:g}mm": biased}
    print(_table(rows, n_eval))

    if args.runs is not None:
        runs, summaries = args.runs, finished
    else:
        settings = {
            "algo": args.algo,
            "timesteps": budget,
            "scale": args.scale,
            "gate_start": args.gate_start,
            "eval_episodes": args.curve_episodes,
            "eval_freq": args.eval_freq,
            "keep_best": args.keep_best,
            "checkpoint_freq": max(budget // 2, 1),
            "n_envs": 1,
            "calibration_bias": bias,
            "reward": args.reward,
            "progress": args.backend == "local",
        }
        jobs = [FinetuneJob(base_path.read_bytes(), seed, settings) for seed in seeds]
        t0 = time.perf_counter()
        runs = runs_dir
        summaries = run_jobs(jobs, runs, backend=args.backend)
        print(f"fine-tuned {len(seeds)} seed(s) in {time.perf_counter() - t0:.0f} s wall")
    results: dict[str, object] = {
        "base_policy": str(base_path),
        "calibration_bias_m": bias,
        "algo": args.algo,
        "scale": args.scale,
        "budget_env_steps": budget,
        "runs": str(runs),
        "episodes": n_eval,
        "base_plain": plain,
        "base": biased,
        "seeds": {},
    }
    ok = True
    env_fn = build_env_fn(bias)
    for seed in seeds:
        summary = summaries[seed]
        path = runs / f"seed{seed}" / "residual_policy.npz"
        t1, c1 = time.perf_counter(), time.process_time()
        rates = evaluate_stages(ResidualPolicy.load(path), env_fn, test_seeds)["rates"]
        rows[f"seed {seed}"] = rates
        results["seeds"][str(seed)] = {  # type: ignore[index]
            "rates": rates,
            "budget_env_steps": summary["total_env_steps"],
            "scale": summary["scale"],
            "env_steps": summary["env_steps"],
            "agent_steps": summary["agent_steps"],
            "train_wall_time_s": summary["wall_time_s"],
            "train_cpu_time_s": summary["cpu_time_s"],
            "eval_wall_time_s": time.perf_counter() - t1,
            "eval_cpu_time_s": time.process_time() - c1,
            "curve": summary["curve"],
        }
        lost = [k for k in STAGES[:3] if rates[k] < biased[k]]
        met = rates["button_pressed"] >= 0.95 and not lost
        ok = ok and met
        print(
            f"seed {seed}: press {rates['button_pressed']:.2f} (target >= 0.95), stages below "
            f"the base's: {lost or 'none'}, "
            f"{summary['env_steps']} env steps, {summary['wall_time_s'] / 60:.1f} min wall, "
            f"{summary['cpu_time_s'] / 60:.1f} min CPU -> {'met' if met else 'MISSED'}"
        )
    print(f"\n=== summary: {args.algo}, calibration bias {bias * 1e3:g} mm, {n_eval} layouts")
    print(_table(rows, n_eval))
    # --force was checked before the work; the file may have appeared since (another run)
    atomic_write_text(results_file, json.dumps(results, indent=2), force=args.force)
    print(f"wrote {results_file}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
