"""The ``gym-coffee run`` pipeline: record, fit, evaluate, plot, video, into one folder.

:data:`PIPELINE_STAGES` is the one list of stages: the progress lines (``[i/n] stage: ...``), the
timings in ``results.json`` (wall and CPU seconds per stage, the evaluation workers' CPU included)
and ``benchmarks/pipeline.py`` all come from it. ``results.json`` is written (atomically) after
every stage, so a run that is interrupted keeps what finished: ``"status"`` says
``"running"``, ``"interrupted"`` (with the stage) or ``"complete"``. With ``force``, the files of
an earlier run in the folder are moved into a hidden ``.previous-run-*`` subfolder first and
deleted only when the new run completes: an interrupted run loses nothing (``results.json``'s
``"previous_run"`` names the subfolder), and the folder never mixes two runs.

Each evaluation layout is rolled out once: the first layout's observations (for Fig. 5) and
frames (for the video) are kept from the evaluation roll-out itself. The whole run limits BLAS to
one thread (the GPs' matrices are small; more threads only spin).
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from lgp_policy._io import atomic_write_text
from lgp_policy.app._common import set_aside

__all__ = ["PIPELINE_STAGES", "RUN_FILES", "run_pipeline"]

PIPELINE_STAGES: tuple[tuple[str, str], ...] = (
    ("record", "recording demonstrations with the scripted teacher"),
    ("fit", "fitting the local heteroscedastic GPs"),
    ("evaluate", "evaluating on new layouts"),
    ("plots", "plotting Figs. 1, 2, 4, 5"),
    ("video", "writing the rollout video of the first layout"),
)
"""``(name, what it does)`` in order; ``plots`` and ``video`` can be switched off."""

RUN_FILES = (
    "demonstrations.npz",
    "policy.npz",
    "constraints.json",
    "results.json",
    "fig1_heteroscedastic.png",
    "fig2_clustering.png",
    "fig4_constraints.png",
    "fig5_reproduction.png",
    "rollout.gif",
)
"""The files ``run`` writes into its folder (``gym-coffee run --force`` removes these first)."""


def _cpu_seconds() -> float:
    """CPU seconds of this process and of its finished children (evaluation workers)."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


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
    force: bool = False,
    env_id: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Record, fit, evaluate, plot; write everything into ``out``; return ``results.json``.

    Args:
        out: the output folder (created if missing).
        n_demos: demonstrations recorded with the scripted teacher (seeds ``seed, seed+1..``).
        n_episodes: evaluation layouts (seeds ``EVAL_SEED_OFFSET + seed + i``).
        seed: seed of demonstrations and layouts.
        workers: evaluation worker processes.
        video, plots: write ``rollout.gif`` / the figures.
        policy_kwargs: keywords of :class:`~lgp_policy.lfd.policy.GPDemonstrationPolicy`.
        progress: progress bars.
        force: replace files of an earlier run (:data:`RUN_FILES`) in ``out`` (set aside until
            this run completes, see above); without it they are an error, raised before any work.
        env_id: the task: a registered id or a level name of ``gym_coffee.LEVELS`` (default
            ``gym_coffee.ENV_ID``, the easy level); demonstrations and evaluation use it, and
            ``results.json`` records it.
        env_kwargs: constructor keywords of the env (e.g. ``{"physics": "fast"}``), for the
            demonstrations and the evaluation alike; ``results.json`` records them.

    Raises:
        FileExistsError: ``out`` holds a file of :data:`RUN_FILES` and ``force`` is false.
        ValueError: ``env_id`` is neither a level name nor a registered id, or the env refuses
            ``env_kwargs`` (its error, naming the argument).
    """
    import gymnasium as gym
    from threadpoolctl import threadpool_limits

    import gym_coffee
    from lgp_policy.app.evaluation import (
        evaluate_policy_stages,
        format_results,
        write_episode_video,
    )
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    if env_id is None:
        env_id = gym_coffee.ENV_ID
    elif isinstance(env_id, str):
        env_id = gym_coffee.LEVELS.get(env_id, env_id)
    if not isinstance(env_id, str) or env_id not in gym.registry:
        raise ValueError(
            f"env_id must be a level of gym_coffee.LEVELS {sorted(gym_coffee.LEVELS)} or a "
            f"registered id, got {env_id!r}"
        )
    out = Path(out)
    present = [n for n in RUN_FILES if os.path.lexists(out / n)]
    if present and not force:
        raise FileExistsError(
            f"{out} holds files of an earlier run ({', '.join(present)}); pass force=True "
            "(--force) to replace them, or choose a new folder"
        )
    # The env of the demonstrations, made before any work: it checks env_kwargs.
    record_env = gym.make(env_id, **(env_kwargs or {}))
    out.mkdir(parents=True, exist_ok=True)
    # force: the earlier run's files move aside (not deleted) until this run completes, so an
    # interrupted run loses nothing and the folder never mixes two runs.
    aside = set_aside([out / n for n in present], out)
    stages = [(n, what) for n, what in PIPELINE_STAGES if (n != "plots" or plots)]
    stages = [(n, what) for n, what in stages if (n != "video" or video)]
    results: dict[str, Any] = {
        "status": "running",
        "env_id": env_id,
        "env_kwargs": dict(env_kwargs or {}),
        "stages": [n for n, _ in stages],
        "done": [],
        "timings": {},
        "files": {},
    }

    def save() -> None:
        atomic_write_text(out / "results.json", json.dumps(results, indent=2), force=True)

    @contextmanager
    def stage(name: str, detail: str = "") -> Iterator[None]:
        i = [n for n, _ in stages].index(name) + 1
        what = dict(stages)[name]
        print(f"[{i}/{len(stages)}] {name}: {what}{detail}", flush=True)
        wall, cpu = time.perf_counter(), _cpu_seconds()
        try:
            yield
        except BaseException:
            results["status"] = "interrupted"
            results["interrupted_in"] = name
            if aside is not None:
                results["previous_run"] = str(aside)
                print(f"the earlier run's files are in {aside}", file=sys.stderr, flush=True)
            save()
            raise
        results["timings"][name] = {
            "wall_s": time.perf_counter() - wall,
            "cpu_s": _cpu_seconds() - cpu,
        }
        results["done"].append(name)
        save()

    t0, cpu0 = time.perf_counter(), _cpu_seconds()
    with threadpool_limits(limits=1, user_api="blas"):
        with stage("record", f" ({n_demos}, seeds {seed}..{seed + n_demos - 1})"):
            try:
                demos = gym_coffee.collect_demonstrations(
                    record_env, n=n_demos, seed=seed, progress=progress
                )
            finally:
                record_env.close()
            demos.save(out / "demonstrations.npz", overwrite=True)
            results["demonstrations"] = {"n": len(demos), "seeds": demos.seeds}
            results["files"]["demonstrations"] = str(out / "demonstrations.npz")

        with stage("fit"):
            policy = GPDemonstrationPolicy(**(policy_kwargs or {})).fit(demos, progress=progress)
            policy_path = policy.save(out / "policy.npz", overwrite=True)
            report = policy.constraints_
            atomic_write_text(out / "constraints.json", json.dumps(report, indent=2), force=True)
            results["policy"] = {"params": policy.get_params(), "fit_time_s": policy.fit_time_}
            results["constraints"] = report
            results["files"].update(
                policy=str(policy_path), constraints=str(out / "constraints.json")
            )
            print(f"      fitted in {policy.fit_time_:.1f} s -> {policy_path}", flush=True)
            for iv in report["intervals"]:
                print(f"      tight: {iv['label']}")
            for c in report["checks"]:
                status = "ok" if c["tight"] else "NOT tight"
                frame = c["expected_frame"]
                print(f"      {c['stage']} at t {c['phase']:.2f}: {frame} frame {status}")

        with stage("evaluate", f" ({n_episodes} layouts, {workers} worker(s))"):
            result = evaluate_policy_stages(
                policy,
                n_episodes,
                seed=seed,
                workers=workers,
                progress=progress,
                env_id=env_id,
                env_kwargs=env_kwargs,
                keep_first=True,
                render_first=video,
            )
            first = result.pop("first_episode")
            results["evaluation"] = result
            print(format_results(result), flush=True)

        if plots:
            with stage("plots"):
                from lgp_policy.app import plots as _plots

                results["files"].update(_plots.make_all(policy, out, episode=first, force=True))
        if video:
            with stage("video"):
                try:
                    path = write_episode_video(first, out / "rollout.gif", force=True)
                    results["files"]["video"] = str(path)
                    results["evaluation"]["video"] = str(path)
                except (ImportError, OSError, ValueError) as exc:  # video is a nice-to-have
                    print(f"      video skipped: {exc}", file=sys.stderr)
    results["timings"]["total"] = {
        "wall_s": time.perf_counter() - t0,
        "cpu_s": _cpu_seconds() - cpu0,
    }
    results["status"] = "complete"
    save()
    if aside is not None:
        shutil.rmtree(aside)
    total = results["timings"]["total"]
    print(
        f"done in {total['wall_s']:.0f} s ({total['cpu_s']:.0f} CPU s); "
        f"results in {out / 'results.json'}",
        flush=True,
    )
    return results
