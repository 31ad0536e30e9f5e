"""Export speed: 200 demonstrations to robomimic HDF5 and Minari (target: each <= 5 s).

Records ``--recorded`` real teacher demonstrations once (``gym_coffee.collect_demonstrations``,
seeds 0, 1, ...; cached as ``.npz`` under ``--cache``, default ``/tmp``) and repeats them to
``--demos`` demonstrations (same arrays, seeds renumbered): the exported data have exactly the
shapes, dtypes and lengths of real teacher episodes without recording 200 of them (about 4 s of
CPU each). Then times, in one process, wall clock and CPU seconds of:

* ``DemonstrationSet.save`` / ``load`` (the project's own ``.npz``, for comparison),
* ``export_robomimic`` and ``import_robomimic`` (checked: the import equals the set),
* ``export_minari`` and ``minari.load_dataset`` + reading every episode (checked: equal arrays).

Usage:
    python benchmarks/export_speed.py [--demos 200] [--recorded 8] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym
import numpy as np

import gym_coffee
from gym_coffee.datasets import export_minari, export_robomimic, import_robomimic
from gym_coffee.demonstrations import Demonstration, DemonstrationSet, collect_demonstrations

TARGET_S = 5.0


def recorded(n: int, cache: Path) -> DemonstrationSet:
    """``n`` real teacher demonstrations, recorded once and cached."""
    path = cache / f"gym_coffee_export_speed_{n}.npz"
    if path.exists():
        return DemonstrationSet.load(path)
    env = gym.make(gym_coffee.ENV_ID)
    try:
        demos = collect_demonstrations(env, n=n, seed=0, progress=True)
    finally:
        env.close()
    demos.save(path)
    return demos


def tiled(demos: DemonstrationSet, n: int) -> DemonstrationSet:
    """``n`` demonstrations cycling through ``demos`` (arrays shared, seeds renumbered)."""
    out = []
    for i in range(n):
        d = demos[i % len(demos)]
        fields = {k: getattr(d, k) for k in Demonstration.__dataclass_fields__}
        out.append(Demonstration(**{**fields, "seed": i}))
    meta = {**demos.metadata, "seeds": list(range(n))}
    return DemonstrationSet(out, meta)


def timed(
    fn: Callable[[], Any], repeat: int, reset: Callable[[], None]
) -> tuple[float, float, Any]:
    """Best wall and CPU seconds over ``repeat`` runs (``reset`` before each)."""
    best_wall = best_cpu = float("inf")
    result = None
    for _ in range(repeat):
        reset()
        w0, c0 = time.perf_counter(), time.process_time()
        result = fn()
        best_wall = min(best_wall, time.perf_counter() - w0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return best_wall, best_cpu, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demos", type=int, default=200)
    parser.add_argument("--recorded", type=int, default=8)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()))
    args = parser.parse_args()

    base = recorded(args.recorded, args.cache)
    demos = tiled(base, args.demos)
    steps = sum(d.n_steps for d in demos)
    print(
        f"{len(demos)} demonstrations ({args.recorded} real teacher episodes repeated), "
        f"{steps} states, {np.mean([d.n_steps for d in demos]):.0f} per demonstration, "
        f"obs_dim {demos[0].obs_dim}, action_type {demos.action_type}"
    )
    rows = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        npz, h5 = tmp / "d.npz", tmp / "d.hdf5"
        root = tmp / "minari"

        def clear() -> None:
            for p in (npz, h5):
                p.unlink(missing_ok=True)
            if root.exists():
                import shutil

                shutil.rmtree(root)

        def keep() -> None:
            pass

        wall, cpu, _ = timed(lambda: demos.save(npz), args.repeat, clear)
        rows.append(("npz save (DemonstrationSet.save)", wall, cpu, npz.stat().st_size, ""))
        wall, cpu, back = timed(lambda: DemonstrationSet.load(npz), args.repeat, keep)
        rows.append(("npz load", wall, cpu, None, "equal" if back == demos else "DIFFERENT"))

        wall, cpu, _ = timed(lambda: export_robomimic(demos, h5), args.repeat, clear)
        rows.append(("robomimic export", wall, cpu, h5.stat().st_size, _verdict(wall)))
        wall, cpu, back = timed(lambda: import_robomimic(h5), args.repeat, keep)
        rows.append(("robomimic import", wall, cpu, None, "equal" if back == demos else "DIFF"))

        wall, cpu, folder = timed(
            lambda: export_minari(demos, "coffee/speed-v0", root=root), args.repeat, clear
        )
        size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
        rows.append(("minari export", wall, cpu, size, _verdict(wall)))
        os.environ["MINARI_DATASETS_PATH"] = str(root)
        import minari

        def read_all() -> bool:
            dataset = minari.load_dataset("coffee/speed-v0")
            return all(
                np.array_equal(ep.observations, d.observations)
                and np.array_equal(ep.actions, d.actions[:-1])
                for ep, d in zip(dataset.iterate_episodes(), demos, strict=True)
            )

        wall, cpu, same = timed(read_all, args.repeat, keep)
        rows.append(("minari load_dataset + read", wall, cpu, None, "equal" if same else "DIFF"))

    print(f"\nbest of {args.repeat}; target: each export <= {TARGET_S:g} s\n")
    print("| step | wall (s) | CPU (s) | size (MB) | check |")
    print("|---|---:|---:|---:|---|")
    for name, wall, cpu, size, note in rows:
        mb = "" if size is None else f"{size / 1e6:.1f}"
        print(f"| {name} | {wall:.2f} | {cpu:.2f} | {mb} | {note} |")


def _verdict(wall: float) -> str:
    return "meets target" if wall <= TARGET_S else "ABOVE TARGET"


if __name__ == "__main__":
    main()
