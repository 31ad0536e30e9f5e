"""Scripted teacher: success per stage over many seeded layouts, episode length, a video.

Runs :class:`gym_coffee.teacher.ScriptedTeacher` on the layouts of seeds ``--seed`` ...
``--seed + --seeds - 1`` of each difficulty level (``gym_coffee.LEVELS``, ``--levels``) through
:func:`gym_coffee.collect_demonstrations` (``keep_failed=True``, so the same code path as
``gym-coffee record``), and prints, for each stage, the fraction of episodes that reached it with
a 95% Wilson interval, how the failed episodes ended, the episode length and the CPU time.
Target: full success >= 95% on every level.

``--video`` replays one successful demonstration in an ``rgb_array`` env and writes it (``.mp4``
or ``.gif``); ``--frames DIR`` also saves a few PNG stills of it (start, grasp, placed, press, end).

Usage:
    OMP_NUM_THREADS=1 python benchmarks/teacher.py [--seeds 200] [--levels easy hard]
        [--video teacher.mp4] [--physics fast]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym
import numpy as np

import gym_coffee
from gym_coffee.demonstrations import STAGE_NAMES, Demonstration, collect_demonstrations

TARGET_SUCCESS = 0.95


def wilson_interval(successes: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """95% Wilson score interval of a binomial proportion (Wilson 1927)."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def outcome(demo: Demonstration, max_steps: int | None) -> str:
    """How an episode ended: success, failure (terminated without success) or time limit."""
    if demo.success:
        return "success"
    n_env_steps = demo.n_steps - 1
    if max_steps is not None and n_env_steps >= max_steps:
        return "time limit"
    return "failure (cup tipped / off table)"


def _level_path(save: Path, level: str) -> Path:
    """``--save``'s file for one level: ``NAME_<level>.npz``."""
    return save.with_name(f"{save.stem}_{level}{save.suffix}")


def save_frames(env_id: str, demo: Demonstration, folder: Path) -> list[Path]:
    """PNG stills of ``demo`` replayed: start, grasped, placed, pressed, end."""
    import imageio.v3 as iio

    stages = demo.stages
    first = {name: int(np.argmax(stages[:, i])) for i, name in enumerate(STAGE_NAMES)}
    wanted = {"0_start": 0}
    for i, name in enumerate(STAGE_NAMES):
        if stages[:, i].any():
            wanted[f"{i + 1}_{name}"] = first[name]
    wanted["4_end"] = demo.n_steps - 1
    # A frame half-way between grasp and placement shows the carry.
    if "1_cup_grasped" in wanted and "2_cup_placed" in wanted:
        wanted["1b_carry"] = (wanted["1_cup_grasped"] + wanted["2_cup_placed"]) // 2
    folder.mkdir(parents=True, exist_ok=True)
    env = gym.make(env_id, render_mode="rgb_array", width=480, height=360)
    paths = []
    try:
        env.reset(seed=demo.seed)
        by_step = {step: name for name, step in wanted.items()}
        for t in range(demo.n_steps):
            if t in by_step:
                path = folder / f"teacher_seed{demo.seed}_{by_step[t]}_t{t}.png"
                iio.imwrite(path, np.asarray(env.render()))
                paths.append(path)
            if t < demo.n_steps - 1:
                env.step(demo.actions[t])
    finally:
        env.close()
    return paths


def report(level: str, env_id: str, args: argparse.Namespace) -> tuple[list[Demonstration], float]:
    """Run the teacher on ``args.seeds`` layouts of ``level``, print its table; the demos and the
    success rate."""
    env = gym.make(env_id, physics=args.physics)
    max_steps = env.spec.max_episode_steps if env.spec is not None else None
    cpu0 = time.process_time()
    try:
        demos = collect_demonstrations(
            env, n=args.seeds, seed=args.seed, progress=False, keep_failed=True
        )
    finally:
        env.close()
    cpu = time.process_time() - cpu0
    n = len(demos)
    if args.save is not None:
        demos.save(_level_path(args.save, level), overwrite=args.force)

    reached = np.array([d.stages.any(axis=0) for d in demos])  # (n, 3) stage ever reached
    success = np.array([d.success for d in demos])
    lengths = np.array([d.n_steps - 1 for d in demos])  # env steps
    dt = float(demos[0].time[1] - demos[0].time[0]) if demos[0].n_steps > 1 else float("nan")

    print(
        f"\nlevel {level!r} ({env_id}): teacher on {n} layouts (seeds {args.seed}.."
        f"{args.seed + n - 1}), {cpu:.0f} CPU s"
    )
    print("| stage | reached | rate | 95% Wilson interval |")
    print("|---|---|---|---|")
    rows = [(name, int(reached[:, i].sum())) for i, name in enumerate(STAGE_NAMES)]
    rows.append(("is_success (all three)", int(success.sum())))
    for name, k in rows:
        lo, hi = wilson_interval(k, n)
        print(f"| {name} | {k}/{n} | {k / n:.1%} | [{lo:.1%}, {hi:.1%}] |")
    ok = lengths[success]
    print(
        f"\nepisode length (env steps): all {lengths.mean():.1f} +- {lengths.std():.1f}; "
        f"successful {ok.mean() if ok.size else float('nan'):.1f} +- "
        f"{ok.std() if ok.size else float('nan'):.1f} "
        f"(= {ok.mean() * dt if ok.size else float('nan'):.1f} s at {dt:.3f} s/step), "
        f"min {lengths.min()}, max {lengths.max()}"
    )
    ends: dict[str, list[int]] = {}
    for d in demos:
        ends.setdefault(outcome(d, max_steps), []).append(d.seed)
    for what, seeds in sorted(ends.items()):
        shown = seeds if len(seeds) <= 20 else [*seeds[:20], "..."]
        print(f"  {what}: {len(seeds)}" + ("" if what == "success" else f" (seeds {shown})"))
    lo, _ = wilson_interval(int(success.sum()), n)
    rate = float(success.mean())
    print(
        f"target full success >= {TARGET_SUCCESS:.0%}: {rate:.1%} -> "
        f"{'met' if rate >= TARGET_SUCCESS else 'MISSED'} (Wilson lower bound {lo:.1%})"
    )
    return list(demos), rate


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=200, help="number of layouts per level")
    parser.add_argument("--seed", type=int, default=0, help="first layout seed")
    parser.add_argument(
        "--levels",
        nargs="+",
        choices=list(gym_coffee.LEVELS),
        default=list(gym_coffee.LEVELS),
        help="difficulty levels (default: all)",
    )
    parser.add_argument(
        "--physics",
        choices=list(gym_coffee.PHYSICS_PRESETS),
        default="default",
        help="the env's physics preset (gym_coffee.PHYSICS_PRESETS)",
    )
    parser.add_argument("--video", type=Path, default=None, help="write one demo (.mp4/.gif)")
    parser.add_argument("--frames", type=Path, default=None, help="folder for PNG stills")
    parser.add_argument(
        "--save", type=Path, default=None, help="also save all episodes (.npz, one per level)"
    )
    parser.add_argument("--force", action="store_true", help="overwrite --save/--video/--frames")
    args = parser.parse_args(argv)
    existing = [args.video] if args.video is not None and args.video.exists() else []
    if args.save is not None:
        existing += [p for level in args.levels if (p := _level_path(args.save, level)).exists()]
    if args.frames is not None and args.frames.is_dir():
        existing += sorted(args.frames.glob("teacher_seed*.png"))[:1]
    if existing and not args.force:
        parser.error(f"{existing[0]} exists; pass --force to overwrite")

    rates = {}
    first: tuple[str, list[Demonstration]] | None = None
    for level in args.levels:
        env_id = gym_coffee.LEVELS[level]
        demos, rates[level] = report(level, env_id, args)
        first = first or (env_id, demos)
    print("\n| level | teacher success |")
    print("|---|---|")
    for level, rate in rates.items():
        print(f"| {level} | {rate:.1%} |")

    assert first is not None
    env_id, demos = first
    if args.video is not None or args.frames is not None:
        good = [d for d in demos if d.success] or list(demos)
        demo = good[0]
        if args.video is not None:
            from lgp_policy.app.cli import record_video

            path = record_video(env_id, demo, args.video, overwrite=args.force)
            print(f"wrote {path} (replay of seed {demo.seed}, {demo.n_steps} steps)")
        if args.frames is not None:
            for path in save_frames(env_id, demo, args.frames):
                print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
