"""Control latency of GPDemonstrationPolicy: fit time and per-step predict time (printed).

Targets (issue 4): fit (all GPs) <= 10 s for 4 demonstrations, ``predict`` <= 1 ms per step.

    python benchmarks/control_latency.py [--demos 4] [--steps 2000] [--model local]

Records demonstrations with the scripted teacher (seeds 0..), fits the policy, then times
``predict`` on the observations of a closed-loop rollout (single observations, and a batch of 8).
BLAS is pinned to one thread (threadpoolctl, if installed) so the numbers are per core.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import gymnasium as gym
import numpy as np

import gym_coffee
from lgp_policy.lfd.policy import GPDemonstrationPolicy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--demos", type=int, default=4)
    ap.add_argument("--steps", type=int, default=2000, help="predict calls to time")
    ap.add_argument("--model", default="local")
    ap.add_argument("--repeats", type=int, default=3, help="fits to time (median reported)")
    args = ap.parse_args()
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:
        pass

    env = gym.make(gym_coffee.ENV_IDS[0])
    demos = gym_coffee.collect_demonstrations(env, n=args.demos, seed=0)
    fits = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        policy = GPDemonstrationPolicy(model=args.model).fit(demos)
        fits.append(time.perf_counter() - t)

    obs, _ = env.reset(seed=10_000)
    observations = []
    done = False
    while not done:
        observations.append(obs)
        action, _ = policy.predict(obs)
        obs, _r, terminated, truncated, _info = env.step(action)
        done = terminated or truncated
    env.close()
    observations = np.asarray(observations)
    for o in observations[:50]:  # warm-up
        policy.predict(o)
    times = np.empty(args.steps)
    for i in range(args.steps):
        o = observations[i % len(observations)]
        t = time.perf_counter()
        policy.predict(o)
        times[i] = time.perf_counter() - t
    batch = observations[:8]
    tb = time.perf_counter()
    for _ in range(200):
        policy.predict(batch)
    batch_ms = (time.perf_counter() - tb) / 200 * 1e3

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
        f"model={args.model}, {args.demos} demonstrations, T={policy.n_steps}"
    )
    print(f"{'quantity':<34}{'measured':>12}{'target':>10}{'ok':>5}")
    med_fit = float(np.median(fits))
    label = f"fit, all GPs (median of {len(fits)})"
    print(f"{label:<34}{med_fit:>10.2f} s{'<= 10 s':>10}{'yes' if med_fit <= 10 else 'NO':>5}")
    for name, q in (("predict, median", 50), ("predict, 99th percentile", 99)):
        v = float(np.percentile(times, q)) * 1e3
        print(f"{name:<34}{v:>9.3f} ms{'<= 1 ms':>10}{'yes' if v <= 1 else 'NO':>5}")
    print(f"{'predict, batch of 8 (per call)':<34}{batch_ms:>9.3f} ms")


if __name__ == "__main__":
    main()
