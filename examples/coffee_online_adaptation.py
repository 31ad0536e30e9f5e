"""Online adaptation on the coffee task: the cup pushed during the approach, noisy observations.

Fits the GP policy on teacher demonstrations (seeds 0..) and evaluates it on held-out layouts
(seeds >= 10000) with the env's perturbations (``cup_push``, ``obs_noise``,
``calibration_bias``), once as the paper's controller (the cup frame at its pose at reset, every
observation trusted, the phase from the clock) and once online (the cup frame follows the cup
until it is held, frame observations filtered, the phase waits for the hand and for the grasp):

    python examples/coffee_online_adaptation.py [--demos 4] [--episodes 30]
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Any

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import gymnasium as gym  # noqa: E402

import gym_coffee  # noqa: E402
from lgp_policy.app.evaluation import evaluate_policy_stages  # noqa: E402
from lgp_policy.lfd.adapters.coffee import CoffeeAdapter  # noqa: E402
from lgp_policy.lfd.policy import GPDemonstrationPolicy  # noqa: E402

PERTURBATIONS: dict[str, dict[str, Any]] = {
    "clean": {},
    "cup pushed 3-5 cm": {"cup_push": (0.03, 0.05)},
    "obs noise 5 mm": {"obs_noise": 0.005},
    "calibration bias 2 mm": {"calibration_bias": 0.002},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--demos", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=30)
    ap.add_argument("--only", default=None, help="one perturbation name")
    args = ap.parse_args()
    for name in ("demos", "episodes"):
        if getattr(args, name) < 1:
            ap.error(f"argument --{name}: expected an integer >= 1, got {getattr(args, name)}")
    env = gym.make(gym_coffee.ENV_ID)
    demos = gym_coffee.collect_demonstrations(env, n=args.demos, seed=0)
    env.close()
    online = GPDemonstrationPolicy().fit(demos)
    paper = GPDemonstrationPolicy(
        adapter=CoffeeAdapter(track_cup=False), frame_noise=0.0, max_wait=0.0
    )
    paper.fit(demos)
    print(f"{'perturbation':<24}{'paper (reset pose, clock)':>28}{'online':>10}{'CPU s':>8}")
    for name, kwargs in PERTURBATIONS.items():
        if args.only and name != args.only:
            continue
        start = time.process_time()
        rates = []
        for policy in (paper, online):
            r = evaluate_policy_stages(
                policy, args.episodes, seed=0, progress=False, env_kwargs=kwargs
            )
            rates.append(r["stages"]["is_success"]["rate"])
        print(
            f"{name:<24}{rates[0]:>28.0%}{rates[1]:>10.0%}{time.process_time() - start:>8.0f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
