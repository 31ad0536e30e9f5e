"""The ``gym-coffee run`` pipeline: record, fit, evaluate, plot, video, into one folder."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["run_pipeline"]


def run_pipeline(
    out: str | Path,
    *,
    n_demos: int = 4,
    n_episodes: int = 50,
    seed: int = 0,
    workers: int = 1,
    video: bool = True,
    plots: bool = True,
    policy_kwargs: dict[str, Any] | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Record, fit, evaluate, plot; write everything into ``out``; return ``results.json``."""
    import gymnasium as gym

    import gym_coffee
    from lgp_policy.app.evaluation import evaluate_policy_stages, format_results, record_rollout
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    timings: dict[str, float] = {}

    print(f"[1/5] recording {n_demos} demonstrations (seeds {seed}..)", flush=True)
    env = gym.make("gym_coffee/CoffeeTask-v0")
    try:
        demos = gym_coffee.collect_demonstrations(env, n=n_demos, seed=seed, progress=progress)
    finally:
        env.close()
    demos.save(out / "demonstrations.npz", overwrite=True)
    timings["record_s"] = time.perf_counter() - t0

    print("[2/5] fitting the local heteroscedastic GPs", flush=True)
    t = time.perf_counter()
    policy = GPDemonstrationPolicy(**(policy_kwargs or {})).fit(demos, progress=progress)
    policy_path = policy.save(out / "policy.npz", overwrite=True)
    timings["fit_s"] = time.perf_counter() - t
    print(f"      fitted in {policy.fit_time_:.1f} s -> {policy_path}", flush=True)
    report = policy.constraints_
    (out / "constraints.json").write_text(json.dumps(report, indent=2))
    for iv in report["intervals"]:
        print(f"      tight: {iv['label']}")
    for c in report["checks"]:
        status = "ok" if c["tight"] else "NOT tight"
        print(f"      {c['stage']} at t {c['phase']:.2f}: {c['expected_frame']} frame {status}")

    print(f"[3/5] evaluating on {n_episodes} new layouts", flush=True)
    t = time.perf_counter()
    result = evaluate_policy_stages(
        policy, n_episodes, seed=seed, workers=workers, progress=progress
    )
    timings["evaluate_s"] = time.perf_counter() - t
    print(format_results(result), flush=True)

    files: dict[str, str] = {
        "policy": str(policy_path),
        "constraints": str(out / "constraints.json"),
        "demonstrations": str(out / "demonstrations.npz"),
    }
    if plots:
        print("[4/5] plotting", flush=True)
        t = time.perf_counter()
        from lgp_policy.app import plots as _plots

        files.update(_plots.make_all(policy, demos, out, seed=result["seeds"][0]))
        timings["plots_s"] = time.perf_counter() - t
    if video:
        print("[5/5] recording a rollout video", flush=True)
        t = time.perf_counter()
        try:
            rec = record_rollout(policy, out / "rollout.gif", result["seeds"][0])
            files["video"] = rec["video"]
        except (ImportError, OSError, ValueError) as exc:  # video is a nice-to-have
            print(f"      video skipped: {exc}", file=sys.stderr)
        timings["video_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t0
    results = {
        "demonstrations": {"n": len(demos), "seeds": demos.seeds},
        "policy": {"params": policy.get_params(), "fit_time_s": policy.fit_time_},
        "constraints": report,
        "evaluation": result,
        "files": files,
        "timings": timings,
    }
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"done in {timings['total_s']:.0f} s; results in {out / 'results.json'}", flush=True)
    return results
