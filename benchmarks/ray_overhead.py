"""Ray's per-task overhead against an episode's cost, and a scaling curve computed from them.

    python benchmarks/ray_overhead.py [--policy POLICY.npz] [--cpus 2] [--episodes 6] [--tasks 40]

Measured in one run, on a local Ray instance with ``--cpus`` CPUs:

1. ``c_ep``: CPU seconds of one evaluation episode of the policy, in this process (the one
   episode loop, BLAS at one thread), mean over ``--episodes`` layouts; ``c_env``: making the env.
2. ``o``: Ray's per-task overhead for the very task the ``ray`` backend sends
   (``lgp_policy.app.backends._ray_chunk`` with the policy and env factory as object-store
   references, fetched once per worker), on warm workers with an empty chunk: (a) the round
   trip of one task at a time, (b) the wall time per task when ``--tasks`` are in flight at
   once, times the CPUs (the cost a task adds to a busy cluster), and the driver's CPU seconds
   per task.
3. The overhead ratio ``o / (k c_ep)`` for ``k`` episodes per task (the ``--chunk-size``), and the
   backend's own records against the local backend on the same seeds (identical).
4. A simulated scaling curve for ``--sim-episodes`` layouts on 1, 2, 4, ... workers: the
   backend's default chunks (about 4 tasks per worker, sizes differing by at most one), each
   costing ``k c_ep + o`` (``o`` the larger of 2a and 2b), handed to the worker that is free
   first after making its env (``c_env``); against ``c_env + n c_ep`` serially.
   It assumes a worker per core and no other limit (the driver and the object store are not
   modelled beyond ``o``); it is arithmetic on measured figures, not a measurement on a cluster.

Without ``--policy`` it records 4 demonstrations and fits the default policy first. On a shared
machine the wall-clock figures (2b) are inflated by the other jobs; the load average is printed.
"""

from __future__ import annotations

import argparse
import heapq
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _policy(path: str | None):
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    if path is not None:
        return GPDemonstrationPolicy.load(path)
    import gymnasium as gym

    import gym_coffee

    env = gym.make(gym_coffee.ENV_ID)
    try:
        demos = gym_coffee.collect_demonstrations(env, n=4, seed=0, progress=False)
    finally:
        env.close()
    return GPDemonstrationPolicy().fit(demos, progress=False)


def simulate(n: int, w: int, c_ep: float, c_env: float, o: float) -> tuple[float, list[int]]:
    """Makespan of ``n`` equal episodes on ``w`` workers with the backend's default chunks
    (``chunk_seeds``), each task going to the worker that is free first; and the chunk sizes."""
    from lgp_policy.app.backends import CHUNKS_PER_WORKER, chunk_seeds

    sizes = [len(c) for c in chunk_seeds(range(n), CHUNKS_PER_WORKER * w)]
    free = [c_env] * w  # every worker makes its env first
    heapq.heapify(free)
    for k in sizes:
        heapq.heappush(free, heapq.heappop(free) + k * c_ep + o)
    return max(free), sizes


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", default=None, help="a policy file (default: fit one)")
    p.add_argument("--cpus", type=int, default=2, help="CPUs of the local Ray instance")
    p.add_argument("--episodes", type=int, default=6, help="episodes for c_ep (and the check)")
    p.add_argument("--tasks", type=int, default=40, help="empty tasks for the overhead")
    p.add_argument("--sim-episodes", type=int, nargs="+", default=[50, 10_000])
    args = p.parse_args(argv)

    import ray
    from threadpoolctl import threadpool_limits

    import gym_coffee
    from lgp_policy.app import backends
    from lgp_policy.app.evaluation import EVAL_FLAGS, EVAL_SEED_OFFSET, evaluate_policy_stages
    from lgp_policy.rollout import run_episode

    threadpool_limits(limits=1, user_api="blas")
    policy = _policy(args.policy)
    factory = backends.EnvFactory(gym_coffee.ENV_ID)
    seeds = [EVAL_SEED_OFFSET + i for i in range(args.episodes)]

    t = time.process_time()
    env = factory()
    c_env = time.process_time() - t
    costs = []
    for s in seeds:
        t = time.process_time()
        run_episode(policy, env, s, flags=EVAL_FLAGS)
        costs.append(time.process_time() - t)
    env.close()
    c_ep = float(np.mean(costs))

    ray.init(
        num_cpus=args.cpus,
        include_dashboard=False,
        log_to_driver=False,
        runtime_env={"env_vars": {"PYTHONPATH": str(ROOT)}},
    )
    try:
        remote = ray.remote(num_cpus=1)(backends._ray_chunk)
        refs = [ray.put(policy), ray.put(factory)]
        # warm every worker (imports, env made and cached)
        ray.get([remote.remote(refs, [], EVAL_FLAGS) for _ in range(4 * args.cpus)])
        t = time.perf_counter()
        for _ in range(args.tasks):
            ray.get(remote.remote(refs, [], EVAL_FLAGS))
        o_latency = (time.perf_counter() - t) / args.tasks
        t, c = time.perf_counter(), time.process_time()
        ray.get([remote.remote(refs, [], EVAL_FLAGS) for _ in range(args.tasks)])
        o_busy = (time.perf_counter() - t) / args.tasks * args.cpus
        o_driver = (time.process_time() - c) / args.tasks

        local = evaluate_policy_stages(policy, args.episodes, progress=False)
        on_ray = evaluate_policy_stages(
            policy, args.episodes, backend="ray", chunk_size=1, progress=False
        )
        identical = on_ray["episodes"] == local["episodes"]
    finally:
        ray.shutdown()

    load = os.getloadavg()
    print(
        f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}; Ray {ray.__version__}; "
        f"local instance with {args.cpus} CPUs; python {sys.version.split()[0]}"
    )
    print()
    print("| quantity | value |")
    print("|---|---:|")
    print(f"| c_ep: CPU s per episode (mean of {len(costs)}) | {c_ep:.3f} |")
    print(f"| c_env: CPU s to make the env (once per worker) | {c_env:.3f} |")
    print(f"| o (a): round trip of one task, warm worker (s) | {o_latency:.4f} |")
    print(f"| o (b): wall per task x CPUs, {args.tasks} in flight (s) | {o_busy:.4f} |")
    print(f"| driver CPU s per task | {o_driver:.4f} |")
    print(f"| ray records identical to local ({args.episodes} episodes) | {identical} |")
    print()
    print("| episodes per task k | overhead o(a)/(k c_ep) | overhead o(b)/(k c_ep) |")
    print("|---:|---:|---:|")
    for k in (1, 2, 4, 8):
        print(f"| {k} | {100 * o_latency / (k * c_ep):.2f}% | {100 * o_busy / (k * c_ep):.2f}% |")
    o = max(o_latency, o_busy)
    for n in args.sim_episodes:
        print()
        print(f"simulated: {n} episodes, o = {o:.4f} s per task, one worker per core")
        print("| workers | episodes per task | tasks | makespan (s) | speed-up | efficiency |")
        print("|---:|---:|---:|---:|---:|---:|")
        serial = c_env + n * c_ep
        w = 1
        while w <= min(n, 1024):
            makespan, sizes = simulate(n, w, c_ep, c_env, o)
            print(
                f"| {w} | {min(sizes)}-{max(sizes)} | {len(sizes)} | {makespan:.1f} "
                f"| {serial / makespan:.1f}x | {serial / makespan / w:.0%} |"
            )
            w *= 2
    return 0 if identical else 1


if __name__ == "__main__":
    raise SystemExit(main())
