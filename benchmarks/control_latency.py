"""Control latency of GPDemonstrationPolicy on the coffee task: fit, one observation, a batch.

Targets (issue 12): one observation <= 0.15 ms; a batch of 1000 observations in one vectorised
pass <= 20 us per observation. CPU time (``time.process_time``), BLAS pinned to one thread.

    python benchmarks/control_latency.py [--demos 4] [--steps 2000] [--batch 1000]

Records demonstrations with the scripted teacher (seeds 0..), fits the policy, rolls it out once
on a held-out layout (seed 10000) and times ``predict`` on those observations: one at a time
(the policy's own memory: online frame filter and phase), and as one batch of ``--batch`` rows
(``episode_start`` all true, as many environments at once).
"""

from __future__ import annotations

import argparse
import os
import platform
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

import gym_coffee  # noqa: E402
from lgp_policy.lfd.policy import GPDemonstrationPolicy  # noqa: E402


def _cpu_per_call(fn, repeats: int) -> float:
    start = time.process_time()
    for _ in range(repeats):
        fn()
    return (time.process_time() - start) / repeats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--demos", type=int, default=4)
    ap.add_argument("--steps", type=int, default=2000, help="single-observation calls to time")
    ap.add_argument("--batch", type=int, default=1000, help="rows of the batched call")
    ap.add_argument("--model", default="local")
    args = ap.parse_args()
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
    rollout = np.asarray(observations)

    single = np.empty(args.steps)
    for i in range(args.steps):
        o = rollout[i % len(rollout)]
        start_i = time.process_time()
        policy.predict(o, episode_start=np.array([i % len(rollout) == 0]))
        single[i] = time.process_time() - start_i
    # process_time has a coarse tick on some systems: also the mean over a tight loop
    k = [0]

    def one() -> None:
        policy.predict(rollout[k[0] % len(rollout)])
        k[0] += 1

    single_mean = _cpu_per_call(one, args.steps)
    batch = rollout[np.arange(args.batch) % len(rollout)]
    starts = np.ones(args.batch, dtype=bool)
    policy.predict(batch, episode_start=starts)  # warm-up
    batch_s = _cpu_per_call(lambda: policy.predict(batch, episode_start=starts), 20)
    loop_s = _cpu_per_call(
        lambda: [policy.predict(o, episode_start=np.array([True])) for o in batch[:100]], 3
    )

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
        f"model={args.model}, {args.demos} demonstrations; CPU time, 1 BLAS thread"
    )
    rows = [
        ("fit, all GPs", f"{fit_s:.2f} s", "-", None),
        (
            "predict, 1 observation (mean)",
            f"{single_mean * 1e3:.3f} ms",
            "<= 0.15 ms",
            single_mean <= 0.15e-3,
        ),
        ("predict, 1 observation (median)", f"{np.median(single) * 1e3:.3f} ms", "", None),
        (
            f"predict, batch of {args.batch} / row",
            f"{batch_s / args.batch * 1e6:.1f} us",
            "<= 20 us",
            batch_s / args.batch <= 20e-6,
        ),
        ("same rows one by one / row", f"{loop_s / 100 * 1e6:.1f} us", "", None),
    ]
    print(f"{'quantity':<38}{'measured':>12}{'target':>12}{'ok':>5}")
    for name, value, target, ok in rows:
        flag = "" if ok is None else ("yes" if ok else "NO")
        print(f"{name:<38}{value:>12}{target:>12}{flag:>5}")


if __name__ == "__main__":
    main()
