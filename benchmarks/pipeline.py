"""CPU seconds per stage of ``gym-coffee run``, where the evaluation's time goes, and the
parallel evaluation's speed-up.

    python benchmarks/pipeline.py [--episodes 50] [--demos 4] [--breakdown 5] [--speedup 12]

1. ``gym-coffee run --out TMP`` in a subprocess with **no thread variables set** (the
   ``*_NUM_THREADS`` variables are removed from its environment, as in a fresh venv) and the
   packages' bytecode compiled first (``compileall``, as ``pip install`` does for an installed
   package; an editable install compiles on the first import, or on every import where
   ``PYTHONDONTWRITEBYTECODE`` is set: ~0.2 CPU s of ``run`` on this machine): wall and
   CPU seconds per stage from its ``results.json`` (the stages of
   ``lgp_policy.app.pipeline.PIPELINE_STAGES``; the evaluation workers' CPU included), and the
   whole process's CPU seconds (imports included) against the 30 CPU s target.
2. The evaluation stage taken apart on ``--breakdown`` layouts of that run's policy, in this
   process: CPU seconds in ``env.reset``, ``policy.predict``, ``env.step``, and ``env.render``
   per frame of the video.
3. ``--speedup N``: the same N layouts with 1 and with 2 worker processes (the local backend):
   identical records, the wall-clock speed-up, and the CPU-normalised speed-up ``serial CPU /
   busiest worker's CPU`` (what 2 idle cores would give when the driver's share is negligible;
   on a machine shared with other jobs the wall-clock figure is not a measure of the code, so
   the load average is printed next to it).
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import gym_coffee

ROOT = Path(__file__).resolve().parents[1]
THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)
TARGET_CPU_S = 30.0


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_cli(
    out: Path,
    episodes: int,
    demos: int,
    workers: int,
    level: str = "easy",
    physics: str = "default",
) -> tuple[dict, float, float]:
    """``gym-coffee run --physics PHYSICS`` in a subprocess with no thread variables; (results,
    wall, CPU)."""
    for package in ("gym_coffee", "lgp_policy"):
        compileall.compile_dir(ROOT / package, quiet=1)
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    cmd = [sys.executable, "-m", "lgp_policy.app.cli", "run", "--out", str(out)]
    cmd += ["--episodes", str(episodes), "--demos", str(demos), "--workers", str(workers)]
    cmd += ["--level", level, "--physics", physics]
    cpu, wall = _children_cpu(), time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall, cpu = time.perf_counter() - wall, _children_cpu() - cpu
    return json.loads((out / "results.json").read_text()), wall, cpu


class _Timed:
    """Accumulates the CPU seconds spent in a callable."""

    def __init__(self, fn):
        self.fn, self.cpu, self.calls = fn, 0.0, 0

    def __call__(self, *args, **kwargs):
        t = time.process_time()
        try:
            return self.fn(*args, **kwargs)
        finally:
            self.cpu += time.process_time() - t
            self.calls += 1


def breakdown(
    policy_path: Path, n: int, env_id: str, env_kwargs: dict
) -> list[tuple[str, float, int]]:
    """CPU seconds in reset / predict / step (over ``n`` layouts) and render (one layout)."""
    import gymnasium as gym

    from lgp_policy.app.evaluation import EVAL_FLAGS, EVAL_SEED_OFFSET, VIDEO_EVERY
    from lgp_policy.lfd.policy import GPDemonstrationPolicy
    from lgp_policy.rollout import run_episode

    policy = GPDemonstrationPolicy.load(policy_path)
    t = time.process_time()
    env = gym.make(env_id, **env_kwargs)
    make = time.process_time() - t
    reset, step, predict = _Timed(env.reset), _Timed(env.step), _Timed(policy.predict)
    env.reset, env.step, policy.predict = reset, step, predict  # type: ignore[method-assign]
    t = time.process_time()
    for i in range(n):
        run_episode(policy, env, EVAL_SEED_OFFSET + i, flags=EVAL_FLAGS)
    total = time.process_time() - t
    env.close()
    renv = gym.make(env_id, render_mode="rgb_array", **env_kwargs)
    render = _Timed(renv.render)
    renv.render = render  # type: ignore[method-assign]
    t = time.process_time()
    run_episode(
        GPDemonstrationPolicy.load(policy_path),
        renv,
        EVAL_SEED_OFFSET,
        flags=EVAL_FLAGS,
        render=True,
        render_every=VIDEO_EVERY,
    )
    rendered = time.process_time() - t
    renv.close()
    rest = total - reset.cpu - step.cpu - predict.cpu
    return [
        ("make the env (once)", make, 1),
        ("env.reset", reset.cpu, reset.calls),
        ("policy.predict", predict.cpu, predict.calls),
        ("env.step", step.cpu, step.calls),
        ("episode loop itself", rest, n),
        ("first layout with rendering (whole episode)", rendered, 1),
        ("env.render (frames of that episode)", render.cpu, render.calls),
    ]


def speedup(policy_path: Path, n: int) -> dict:
    from lgp_policy.app.evaluation import evaluate_policy_stages
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    policy = GPDemonstrationPolicy.load(policy_path)
    runs = {}
    for w in (1, 2):
        c = time.process_time()
        r = evaluate_policy_stages(policy, n, workers=w, progress=False)
        r["driver_cpu_s"] = time.process_time() - c
        runs[w] = r
    serial_cpu = sum(runs[1]["worker_cpu_s"].values())
    busiest = max(runs[2]["worker_cpu_s"].values())
    return {
        "identical": runs[1]["episodes"] == runs[2]["episodes"],
        "serial_cpu": serial_cpu,
        "worker_cpu": sorted(runs[2]["worker_cpu_s"].values()),
        "driver_cpu_2": runs[2]["driver_cpu_s"],
        "cpu_speedup": serial_cpu / busiest,
        "wall_1": runs[1]["wall_time_s"],
        "wall_2": runs[2]["wall_time_s"],
    }


def _table(title: str, header: tuple[str, ...], rows: list[tuple]) -> None:
    """Print a titled Markdown table (first column left-aligned, the others right-aligned)."""
    print()
    print(title)
    print("| " + " | ".join(header) + " |")
    print("|---|" + "---:|" * (len(header) - 1))
    for row in rows:
        print("| " + " | ".join(str(v) for v in row) + " |")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--episodes", type=int, default=50, help="evaluation layouts of the run")
    p.add_argument("--demos", type=int, default=4)
    p.add_argument("--workers", type=int, default=1, help="--workers of the run")
    p.add_argument("--breakdown", type=int, default=5, help="layouts for the breakdown (0: skip)")
    p.add_argument("--speedup", type=int, default=0, help="layouts for the 1 vs 2 workers check")
    p.add_argument("--level", default="easy", choices=["easy", "hard"], help="--level of the run")
    p.add_argument(
        "--physics",
        default="default",
        choices=list(gym_coffee.PHYSICS_PRESETS),
        help="the env's physics preset (gym_coffee.PHYSICS_PRESETS)",
    )
    p.add_argument("--keep", default=None, help="keep the run's folder here")
    args = p.parse_args(argv)

    from threadpoolctl import threadpool_limits

    from lgp_policy.app.pipeline import PIPELINE_STAGES

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.keep) if args.keep else Path(tmp) / "run"
        load0 = os.getloadavg()[0]
        results, wall, cpu = run_cli(
            out, args.episodes, args.demos, args.workers, args.level, args.physics
        )
        t = results["timings"]
        print(
            f"gym-coffee run --episodes {args.episodes} --demos {args.demos} --workers "
            f"{args.workers} --level {args.level} (physics {args.physics}); no thread "
            f"variables; load average {load0:.1f} -> "
            f"{os.getloadavg()[0]:.1f} (2 cores shared)"
        )
        print()
        print("| stage | wall s | CPU s | share of CPU |")
        print("|---|---:|---:|---:|")
        for name, _ in PIPELINE_STAGES:
            if name in t:
                s = t[name]
                print(f"| {name} | {s['wall_s']:.1f} | {s['cpu_s']:.1f} | {s['cpu_s'] / cpu:.0%} |")
        start = cpu - t["total"]["cpu_s"]
        print(f"| imports and start-up | | {start:.1f} | {start / cpu:.0%} |")
        status = "meets" if cpu <= TARGET_CPU_S else "misses"
        print(f"| **end to end** | {wall:.1f} | **{cpu:.1f}** | {status} <= {TARGET_CPU_S:.0f} |")
        ev = results["evaluation"]
        print()
        print(
            f"evaluation: {ev['n_episodes']} layouts, mean length "
            f"{ev['episode_length']['mean']:.0f} steps, success "
            f"{ev['stages']['is_success']['rate']:.0%}"
        )
        with threadpool_limits(limits=1, user_api="blas"):
            if args.breakdown > 0:
                rows = breakdown(
                    out / "policy.npz",
                    args.breakdown,
                    results["env_id"],
                    results.get("env_kwargs", {}),
                )
                _table(
                    f"where the evaluation's time goes ({args.breakdown} layouts, this process)",
                    ("part", "CPU s", "calls", "ms per call"),
                    [
                        (name, f"{sec:.2f}", calls, f"{1000 * sec / max(calls, 1):.2f}")
                        for name, sec, calls in rows
                    ],
                )
            if args.speedup > 0:
                r = speedup(out / "policy.npz", args.speedup)
                workers = ", ".join(f"{c:.1f}" for c in r["worker_cpu"])
                _table(
                    f"parallel evaluation, {args.speedup} layouts (local backend)",
                    ("quantity", "value"),
                    [
                        ("records identical, 1 vs 2 workers", r["identical"]),
                        ("serial CPU s", f"{r['serial_cpu']:.1f}"),
                        ("2 workers: CPU s per worker", workers),
                        ("2 workers: driver CPU s", f"{r['driver_cpu_2']:.2f}"),
                        ("CPU-normalised speed-up", f"{r['cpu_speedup']:.2f}x"),
                        (
                            f"wall speed-up (load {os.getloadavg()[0]:.1f})",
                            f"{r['wall_1'] / r['wall_2']:.2f}x",
                        ),
                    ],
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
