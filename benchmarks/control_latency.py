"""Control latency of GPDemonstrationPolicy on the coffee task: one observation, a batch.

Targets (issue 12): one observation <= 0.15 ms; a batch of 1000 observations in one vectorised
pass <= 20 us per observation. CPU time (``time.process_time``), BLAS pinned to one thread.

    python benchmarks/control_latency.py [--demos 4] [--steps 1000] [--batch 1000] [--rounds 5]
                                         [--baseline REV]

Records demonstrations with the scripted teacher (seeds 0..), fits the policy, rolls it out once
on a held-out layout (seed 10000) and times ``predict`` on those observations: one at a time
(the policy's own memory: online frame filter and phase, a new episode at the rollout's start),
and as one batch of ``--batch`` rows (``episode_start`` all true, as many environments at once).

``--baseline REV`` (a git revision of this repository, e.g. ``main``) times the code of that
revision side by side: each implementation runs in its own process on the same policy file and
observations, and the processes take turns, ``--rounds`` rounds each, so both see the same load;
the table gives the median over rounds. It also replays the rollout through both and prints the
largest difference between their actions.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _cpu_per_call(fn, repeats: int) -> float:
    start = time.process_time()
    for _ in range(repeats):
        fn()
    return (time.process_time() - start) / repeats


# ------------------------------------------------------------------------------- worker
def _worker(args: argparse.Namespace) -> None:
    """Load the policy and the observations, then answer ``round`` / ``actions`` on stdin."""
    from threadpoolctl import threadpool_limits

    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    threadpool_limits(1)
    policy = GPDemonstrationPolicy.load(args.policy)
    rollout = np.load(args.rollout)
    starts = [np.array([i == 0]) for i in range(len(rollout))]
    batch = rollout[np.arange(args.batch) % len(rollout)]
    batch_starts = np.ones(args.batch, dtype=bool)

    def replay(steps: int, times: list[float] | None = None) -> list[np.ndarray]:
        out = []
        for i in range(steps):
            j = i % len(rollout)
            start = time.process_time()
            action, _ = policy.predict(rollout[j], episode_start=starts[j])
            if times is not None:
                times.append(time.process_time() - start)
            out.append(action)
        return out

    replay(len(rollout))  # warm-up
    policy.predict(batch, episode_start=batch_starts)
    print("ready", flush=True)
    counter = [0]

    def one() -> None:
        j = counter[0] % len(rollout)
        policy.predict(rollout[j], episode_start=starts[j])
        counter[0] += 1

    for line in sys.stdin:
        command = line.strip()
        if command == "round":
            per_call: list[float] = []
            replay(args.steps, per_call)
            counter[0] = 0
            result = {
                "single_mean": _cpu_per_call(one, args.steps),
                "single_median": float(np.median(per_call)),
                "batch_row": _cpu_per_call(
                    lambda: policy.predict(batch, episode_start=batch_starts), 5
                )
                / args.batch,
            }
            print(json.dumps(result), flush=True)
        elif command == "actions":
            acts = np.asarray(replay(len(rollout)))
            print(json.dumps(acts.tolist()), flush=True)
        else:
            break


# ------------------------------------------------------------------------------- parent
class _Worker:
    def __init__(self, name: str, tree: Path, args: argparse.Namespace, files: dict) -> None:
        self.name = name
        env = dict(os.environ, PYTHONPATH=str(tree))
        cmd = [
            sys.executable,
            str(Path(__file__).resolve()),
            "--worker",
            "--policy",
            files["policy"],
            "--rollout",
            files["rollout"],
            "--steps",
            str(args.steps),
            "--batch",
            str(args.batch),
        ]
        self.proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=tree
        )
        line = self._read()
        if line != "ready":
            raise RuntimeError(f"{name} worker did not start: {line!r}")

    def _read(self) -> str:
        assert self.proc.stdout is not None
        return self.proc.stdout.readline().strip()

    def ask(self, command: str) -> object:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        return json.loads(self._read())

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


def _export(rev: str, dest: Path) -> str:
    """The files of revision ``rev`` of this repository under ``dest``; returns its commit."""
    commit = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", rev],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", "--format=tar", rev], check=True, capture_output=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return commit


def _prepare(args: argparse.Namespace, tmp: Path) -> tuple[dict, float]:
    import gymnasium as gym
    from threadpoolctl import threadpool_limits

    import gym_coffee
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    threadpool_limits(1)
    env = gym.make(gym_coffee.ENV_ID)
    demos = gym_coffee.collect_demonstrations(env, n=args.demos, seed=0)
    start = time.process_time()
    policy = GPDemonstrationPolicy(model=args.model).fit(demos)
    fit_s = time.process_time() - start
    obs, _ = env.reset(seed=10_000)
    observations, done, first = [], False, True
    while not done:
        observations.append(obs)
        action, _ = policy.predict(obs, episode_start=np.array([first]))
        first = False
        obs, _r, terminated, truncated, _info = env.step(action)
        done = terminated or truncated
    env.close()
    files = {"policy": str(tmp / "policy.npz"), "rollout": str(tmp / "rollout.npy")}
    policy.save(files["policy"])
    np.save(files["rollout"], np.asarray(observations))
    return files, fit_s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--demos", type=int, default=4)
    ap.add_argument("--steps", type=int, default=1000, help="single-observation calls per round")
    ap.add_argument("--batch", type=int, default=1000, help="rows of the batched call")
    ap.add_argument("--rounds", type=int, default=5, help="timing rounds per implementation")
    ap.add_argument("--model", default="local")
    ap.add_argument("--baseline", default=None, help="git revision to time side by side")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--policy", help=argparse.SUPPRESS)
    ap.add_argument("--rollout", help=argparse.SUPPRESS)
    args = ap.parse_args()
    for name in ("demos", "steps", "batch", "rounds"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be >= 1")
    if args.worker:
        _worker(args)
        return

    with tempfile.TemporaryDirectory(prefix="control_latency_") as tmp_name:
        tmp = Path(tmp_name)
        files, fit_s = _prepare(args, tmp)
        trees = {"this tree": ROOT}
        if args.baseline is not None:
            base = tmp / "baseline"
            base.mkdir()
            trees = {f"baseline {_export(args.baseline, base)}": base, **trees}
        workers = [_Worker(name, tree, args, files) for name, tree in trees.items()]
        try:
            rounds: dict[str, list[dict]] = {w.name: [] for w in workers}
            for _ in range(args.rounds):
                for w in workers:
                    rounds[w.name].append(w.ask("round"))  # type: ignore[arg-type]
            actions = {w.name: np.asarray(w.ask("actions")) for w in workers}
        finally:
            for w in workers:
                w.close()

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load "
        f"{os.getloadavg()[0]:.1f}; model={args.model}, {args.demos} demonstrations; CPU time, "
        f"1 BLAS thread; median of {args.rounds} rounds"
    )
    print(f"fit, all GPs (this tree): {fit_s:.2f} s")
    names = list(rounds)
    med = {n: {k: float(np.median([r[k] for r in rounds[n]])) for k in rounds[n][0]} for n in names}
    rows = [
        ("predict, 1 observation (mean)", "single_mean", 1e3, "ms", 0.15e-3, "<= 0.15 ms"),
        ("predict, 1 observation (median)", "single_median", 1e3, "ms", None, ""),
        (f"predict, batch of {args.batch} / row", "batch_row", 1e6, "us", 20e-6, "<= 20 us"),
    ]
    head = f"{'quantity':<36}" + "".join(f"{n:>18}" for n in names)
    if len(names) == 2:
        head += f"{'ratio':>8}"
    print(head + f"{'target':>12}{'ok':>5}")
    for label, key, scale, unit, target, text in rows:
        line = f"{label:<36}" + "".join(
            f"{med[n][key] * scale:>15.3f} {unit}"
            if unit == "ms"
            else f"{med[n][key] * scale:>15.1f} {unit}"
            for n in names
        )
        if len(names) == 2:
            line += f"{med[names[0]][key] / med[names[1]][key]:>7.2f}x"
        ok = "" if target is None else ("yes" if med[names[-1]][key] <= target else "NO")
        print(line + f"{text:>12}{ok:>5}")
    if len(names) == 2:
        diff = np.abs(actions[names[0]] - actions[names[1]]).max()
        print(
            f"largest action difference over the rollout's {len(actions[names[0]])} steps: "
            f"{diff:.3g}"
        )


if __name__ == "__main__":
    main()
