"""Environment throughput: steps/s, real-time factor and reset time, next to panda-gym.

Measures, in one process and one run, for ``gym_coffee.ENV_ID`` and panda-gym's
``PandaPickAndPlace-v3`` (when ``panda_gym`` imports; otherwise that column is skipped with a note):

- steps/s and real-time factor (simulated seconds per wall-clock second) with uniformly random
  actions, resetting when an episode ends (reset time excluded);
- steps/s and real-time factor with the scripted teacher (gym-coffee only; includes the
  teacher's own computation);
- mean time of ``reset(seed=...)``;
- mean time of ``render()`` in ``rgb_array`` mode (default image size of each env).

Times are CPU seconds of this process (``time.process_time``; PyBullet's ``DIRECT`` server runs
in it), so that load from other processes on a shared machine does not count; the two envs are
also measured alternately, ``--repeats`` times, and the median is reported. gym-coffee's reset
restores the world as loaded (``exact_reset=True``, the default; loaded without visual meshes
unless rendering); the ``reset, rendering env`` row is the same reset in an env with them.
Targets: real-time factor >= 1.5x panda-gym's, and >= 400 steps/s.

Usage:
    OMP_NUM_THREADS=1 python benchmarks/env_throughput.py [--steps 2000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym
import numpy as np

import gym_coffee

COFFEE_ID = gym_coffee.ENV_ID
PANDA_ID = "PandaPickAndPlace-v3"
TARGET_STEPS_PER_S = 400.0
#: Target: real-time factor (random actions) >= this multiple of panda-gym's.
TARGET_RTF_RATIO = 1.5


def sim_dt(env: gym.Env) -> float:
    """Simulated seconds per env step."""
    unwrapped = env.unwrapped
    if hasattr(unwrapped, "sim") and hasattr(unwrapped.sim, "dt"):  # both envs have sim.dt
        return float(unwrapped.sim.dt)
    from gym_coffee.env import CONTROL_DT

    return float(CONTROL_DT)


def time_random_steps(env: gym.Env, n_steps: int, seed: int) -> float:
    """Wall seconds for ``n_steps`` random-action steps (resets not counted)."""
    env.action_space.seed(seed)
    actions = [env.action_space.sample() for _ in range(n_steps)]
    env.reset(seed=seed)
    elapsed = 0.0
    for action in actions:
        t0 = time.process_time()
        _, _, terminated, truncated, _ = env.step(action)
        elapsed += time.process_time() - t0
        if terminated or truncated:
            env.reset()
    return elapsed


def time_teacher_steps(env: gym.Env, n_steps: int, seed: int) -> tuple[float, float, int]:
    """Wall seconds of (teacher + step, teacher alone) for about ``n_steps`` teacher steps."""
    from gym_coffee.demonstrations import _make_teacher
    from gym_coffee.teacher import ScriptedTeacher

    done_steps, elapsed, acting, episode = 0, 0.0, 0.0, 0
    while done_steps < n_steps:
        obs, _ = env.reset(seed=seed + episode)
        teacher = _make_teacher(ScriptedTeacher, env, seed + episode, {})
        episode += 1
        while done_steps < n_steps:
            t0 = time.process_time()
            action = teacher.act(obs)
            t1 = time.process_time()
            obs, _, terminated, truncated, _ = env.step(action)
            elapsed += time.process_time() - t0
            acting += t1 - t0
            done_steps += 1
            if terminated or truncated:
                break
    return elapsed, acting, done_steps


def time_resets(env: gym.Env, n: int, seed: int) -> float:
    t0 = time.process_time()
    for i in range(n):
        env.reset(seed=seed + i)
    return (time.process_time() - t0) / n


def time_render(env: gym.Env, n: int, seed: int) -> tuple[float, tuple[int, ...]]:
    env.reset(seed=seed)
    frame = env.render()
    t0 = time.process_time()
    for _ in range(n):
        env.step(env.action_space.sample())
        env.render()
    step_and_render = (time.process_time() - t0) / n
    t0 = time.process_time()
    for _ in range(n):
        env.step(env.action_space.sample())
    step_only = (time.process_time() - t0) / n
    return max(step_and_render - step_only, 0.0), tuple(np.asarray(frame).shape)


@contextlib.contextmanager
def quiet_stdout() -> Iterator[None]:
    """Silence C-level stdout (PyBullet prints ``argv[0]=`` on every connect)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def make(env_id: str, **kwargs: Any) -> gym.Env:
    with quiet_stdout():
        return gym.make(env_id, **kwargs)


def measure(env_id: str, args: argparse.Namespace, rep: int, teacher: bool) -> dict[str, Any]:
    env = make(env_id)
    try:
        dt = sim_dt(env)
        wall = time_random_steps(env, args.steps, seed=rep)
        out: dict[str, Any] = {
            "dt": dt,
            "random_sps": args.steps / wall,
            "random_rtf": args.steps * dt / wall,
            "reset_ms": 1e3 * time_resets(env, args.resets, seed=100 + rep),
        }
        if teacher:
            wall, acting, n = time_teacher_steps(env, args.steps, seed=rep * 1000)
            out["teacher_sps"] = n / wall
            out["teacher_rtf"] = n * dt / wall
            out["teacher_act_ms"] = 1e3 * acting / n
            out["teacher_step_ms"] = 1e3 * (wall - acting) / n
    finally:
        env.close()
    if args.render > 0:
        env = make(env_id, render_mode="rgb_array")
        try:
            out["render_reset_ms"] = 1e3 * time_resets(env, max(args.resets // 4, 1), seed=rep)
            render_s, shape = time_render(env, args.render, seed=rep)
            out["render_ms"] = 1e3 * render_s
            out["render_shape"] = shape
        finally:
            env.close()
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2000, help="steps per measurement")
    parser.add_argument("--resets", type=int, default=20, help="resets per measurement")
    parser.add_argument("--render", type=int, default=50, help="rendered steps (0: skip)")
    parser.add_argument("--repeats", type=int, default=3, help="alternating repetitions")
    parser.add_argument("--no-teacher", action="store_true", help="skip the teacher rows")
    args = parser.parse_args(argv)

    columns: dict[str, Callable[[int], dict[str, Any]]] = {
        COFFEE_ID: lambda rep: measure(COFFEE_ID, args, rep, teacher=not args.no_teacher)
    }
    try:
        import panda_gym  # noqa: F401  (registers the Panda envs)
    except Exception as exc:
        print(f"note: panda-gym column skipped (import panda_gym failed: {exc!r})")
    else:
        columns[PANDA_ID] = lambda rep: measure(PANDA_ID, args, rep, teacher=False)

    results: dict[str, list[dict[str, Any]]] = {name: [] for name in columns}
    for rep in range(args.repeats):
        for name, run in columns.items():
            results[name].append(run(rep))
            print(f"  repeat {rep + 1}/{args.repeats} {name}: done", file=sys.stderr)

    rows = [
        ("control period (s/step)", "dt", "{:.3f}"),
        ("random actions: steps/s", "random_sps", "{:.0f}"),
        ("random actions: real-time factor", "random_rtf", "{:.1f}x"),
        ("teacher: steps/s", "teacher_sps", "{:.0f}"),
        ("teacher: real-time factor", "teacher_rtf", "{:.1f}x"),
        ("teacher: act() ms/step", "teacher_act_ms", "{:.2f}"),
        ("teacher: env.step() ms/step", "teacher_step_ms", "{:.2f}"),
        ("reset (ms)", "reset_ms", "{:.1f}"),
        ("reset, rendering env (ms)", "render_reset_ms", "{:.1f}"),
        ("render rgb_array (ms/frame)", "render_ms", "{:.1f}"),
        ("render size (h, w, c)", "render_shape", "{}"),
    ]
    names = list(columns)
    width = max(len(r[0]) for r in rows) + 2
    print(
        f"\nCPU time, median of {args.repeats} alternating repeats, {args.steps} steps each, "
        f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}"
    )
    print("| " + "metric".ljust(width) + " | " + " | ".join(n.ljust(26) for n in names) + " |")
    print("|" + "-" * (width + 2) + "|" + "|".join("-" * 28 for _ in names) + "|")
    for label, key, fmt in rows:
        cells = []
        for name in names:
            values = [r[key] for r in results[name] if key in r]
            if not values:
                cells.append("n/a")
            elif isinstance(values[0], (int, float)):
                cells.append(fmt.format(statistics.median(values)))
            else:
                cells.append(fmt.format(values[0]))
        print("| " + label.ljust(width) + " | " + " | ".join(c.ljust(26) for c in cells) + " |")

    coffee = {k: statistics.median(r[k] for r in results[COFFEE_ID]) for k in ("random_sps",)}
    coffee_rtf = statistics.median(r["random_rtf"] for r in results[COFFEE_ID])
    print()
    ok = coffee["random_sps"] >= TARGET_STEPS_PER_S
    print(
        f"target steps/s >= {TARGET_STEPS_PER_S:.0f} (random actions): "
        f"{coffee['random_sps']:.0f} -> {'met' if ok else 'MISSED'}"
    )
    if PANDA_ID in results:
        panda_rtf = statistics.median(r["random_rtf"] for r in results[PANDA_ID])
        ok = coffee_rtf >= TARGET_RTF_RATIO * panda_rtf
        print(
            f"target real-time factor >= {TARGET_RTF_RATIO}x panda-gym's: {coffee_rtf:.1f}x vs "
            f"{panda_rtf:.1f}x (ratio {coffee_rtf / panda_rtf:.2f}) -> {'met' if ok else 'MISSED'}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
