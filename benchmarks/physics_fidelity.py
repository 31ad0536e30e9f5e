"""Physics presets against a fine reference: what ``gym_coffee.PHYSICS_PRESETS`` cost and change.

The scripted teacher runs closed loop on the same layouts under every preset and under a
reference physics (1 ms physics steps, 100 solver iterations: 40 per 40 ms control step), and
the script prints, per level and preset:

- CPU ms per ``env.step`` (``time.process_time``; the teacher's own time excluded);
- teacher success and mean episode length (control steps);
- the deepest contact penetration seen (mm; ``getContactPoints`` distance after every step);
- how far the grasp moves the cup (mm, horizontally, from the moment the fingers start to close
  until the cup counts as grasped; mean over the episodes): a sloppier contact solution pushes
  the cup aside more;
- against the reference on the same layout: the median over the episode of the largest joint
  difference (rad), the cup's final position difference (mm) and the largest difference of the
  episode length (steps).

The joints' position controller has the same time constant under every setting
(``Simulation.control_joints`` converts its gain to the physics step), so the differences are
the integration's and the contact solver's.

``--residual T ...`` adds rows of the default preset with other solver residual thresholds
(``Simulation.solver_residual``: where the constraint solver stops its sweeps early).

Usage:
    OMP_NUM_THREADS=1 python benchmarks/physics_fidelity.py [--episodes 8] [--levels easy,hard]
        [--residual 1e-7 1e-4 1e-3]
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym
import numpy as np

import gym_coffee
from gym_coffee.demonstrations import _make_teacher
from gym_coffee.env import obs_part
from gym_coffee.teacher import ScriptedTeacher

#: The reference physics: (physics time step (s), physics steps per control step, iterations).
REFERENCE = (0.001, 40, 100, 1e-7)
#: Gripper opening (m) below which the fingers count as closing on the cup (fully open: 0.08).
GRIPPER_CLOSING = 0.079


def run_level(level: str, setting: tuple[float, int, int, float], episodes: int, seed: int) -> dict:
    """Teacher episodes on ``level`` with the physics ``setting``; per-episode records."""
    env = gym.make(gym_coffee.LEVELS[level])
    sim = env.unwrapped.sim
    timestep, n_substeps, iterations, residual = setting
    sim.set_physics(
        timestep=timestep,
        n_substeps=n_substeps,
        solver_iterations=iterations,
        solver_residual=residual,
    )
    records: list[dict[str, Any]] = []
    cpu, steps = 0.0, 0
    for episode in range(episodes):
        obs, info = env.reset(seed=seed + episode)
        teacher = _make_teacher(ScriptedTeacher, env, seed + episode, {})
        joints, deepest, closing, shift = [], 0.0, None, np.nan
        while True:
            action = teacher.act(obs)
            t0 = time.process_time()
            obs, _, terminated, truncated, info = env.step(action)
            cpu += time.process_time() - t0
            steps += 1
            joints.append(obs_part(obs, "joint_pos").copy())
            cup = np.asarray(sim.p.getBasePositionAndOrientation(sim.bodies["cup"])[0])
            if closing is None and obs_part(obs, "gripper")[0] < GRIPPER_CLOSING:
                closing = cup
            if closing is not None and np.isnan(shift) and info["cup_grasped"]:
                shift = 1e3 * float(np.linalg.norm((cup - closing)[:2]))
            contacts = sim.p.getContactPoints()
            if contacts:
                deepest = min(deepest, min(c[8] for c in contacts))
            if terminated or truncated:
                break
        cup = np.asarray(sim.p.getBasePositionAndOrientation(sim.bodies["cup"])[0])
        records.append(
            {
                "success": bool(info.get("is_success", False)),
                "joints": np.asarray(joints),
                "cup": cup,
                "penetration": -deepest,
                "grasp_shift": shift,
            }
        )
    env.close()
    return {"records": records, "ms_per_step": 1e3 * cpu / max(steps, 1)}


def compare(run: dict, reference: dict) -> tuple[float, float, int]:
    """(median joint difference rad, final cup difference mm, largest length difference)."""
    joint, cup, length = [], [], 0
    for mine, ref in zip(run["records"], reference["records"], strict=True):
        n = min(len(mine["joints"]), len(ref["joints"]))
        joint.append(np.median(np.abs(mine["joints"][:n] - ref["joints"][:n]).max(axis=1)))
        cup.append(1e3 * np.linalg.norm(mine["cup"] - ref["cup"]))
        length = max(length, abs(len(mine["joints"]) - len(ref["joints"])))
    return float(np.mean(joint)), float(np.mean(cup)), length


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=8, help="layouts per level")
    p.add_argument("--levels", default=",".join(gym_coffee.LEVELS))
    p.add_argument("--seed", type=int, default=500, help="first layout seed")
    p.add_argument(
        "--residual",
        type=float,
        nargs="*",
        default=[],
        help="also the default preset with these solver residual thresholds (Simulation's "
        "solver_residual, PyBullet's solverResidualThreshold)",
    )
    args = p.parse_args(argv)
    levels = args.levels.split(",")
    bad = [lv for lv in levels if lv not in gym_coffee.LEVELS]
    if bad or args.episodes < 1 or not all(0.0 < r < 1.0 for r in args.residual):
        p.error(
            f"--levels must name levels of {list(gym_coffee.LEVELS)}, --episodes >= 1, "
            "--residual values in (0, 1)"
        )
    settings = {"reference (1 ms x 40, 100 it.)": REFERENCE}
    for name, setting in gym_coffee.PHYSICS_PRESETS.items():
        dt, n, iterations, residual = setting
        settings[f"{name} ({1e3 * dt:g} ms x {n}, {iterations} it., res. {residual:g})"] = setting
    dt, n, iterations = gym_coffee.PHYSICS_PRESETS["default"][:3]
    for residual in args.residual:
        settings[f"default, res. {residual:g}"] = (dt, n, iterations, residual)
    print(f"scripted teacher, {args.episodes} layouts per level from seed {args.seed}")
    print()
    print(
        "| level | physics | env.step ms | success | mean length | deepest contact mm "
        "| cup moved by the grasp mm | joints vs ref. (median, rad) | final cup vs ref. mm "
        "| length vs ref. (max) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for level in levels:
        runs = {name: run_level(level, s, args.episodes, args.seed) for name, s in settings.items()}
        reference = next(iter(runs.values()))
        for name, run in runs.items():
            recs = run["records"]
            success = sum(r["success"] for r in recs)
            length = np.mean([len(r["joints"]) for r in recs])
            deepest = max(r["penetration"] for r in recs) * 1e3
            shift = np.nanmean([r["grasp_shift"] for r in recs])
            row = f"| {level} | {name} | {run['ms_per_step']:.2f} | {success}/{len(recs)} | "
            row += f"{length:.0f} | {deepest:.1f} | {shift:.1f} | "
            if run is reference:
                row += "- | - | - |"
            else:
                joint, cup, steps = compare(run, reference)
                row += f"{joint:.4f} | {cup:.1f} | {steps} |"
            print(row, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
