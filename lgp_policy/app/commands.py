"""Subcommands of ``gym-coffee`` that belong to the learning side: ``fit``, ``evaluate``, ``run``
(and ``finetune``, added by :mod:`lgp_policy.app.finetune_cli` when it is importable).

* ``gym-coffee fit DEMOS --out POLICY.npz``: encode recorded demonstrations into a policy file.
* ``gym-coffee evaluate POLICY --episodes N --seed S [--workers K] [--video out.mp4]
  [--json out.json]``: per-stage success on held-out layouts with 95% Wilson intervals.
* ``gym-coffee run [--out DIR] [--demos 4] [--episodes 50] [--seed S]``: record demonstrations,
  fit, evaluate, and write the policy, ``results.json``, the figures and a rollout video to DIR.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

__all__ = ["add_subcommands", "load_policy"]


def add_subcommands(subparsers: argparse._SubParsersAction) -> None:
    """Add ``fit``, ``evaluate``, ``run`` and ``finetune`` to the ``gym-coffee`` parser."""
    p = subparsers.add_parser(
        "fit",
        help="fit a GP policy to recorded demonstrations",
        description="Encode demonstrations (a .npz written by `gym-coffee record`) into a "
        "GPDemonstrationPolicy file.",
    )
    p.add_argument("demos", help="demonstrations file (.npz)")
    p.add_argument("--out", required=True, help="policy file to write (.npz)")
    _add_policy_options(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing policy file")
    p.set_defaults(func=cmd_fit)

    p = subparsers.add_parser(
        "evaluate",
        help="evaluate a policy on held-out layouts (per-stage success)",
        description="Run a policy on layouts from seeds 10000+S.. (disjoint from demonstration "
        "seeds) and print per-stage success rates with 95%% Wilson intervals.",
    )
    p.add_argument("policy", help="policy file (GP policy .npz or residual policy)")
    p.add_argument("--episodes", type=int, default=100, help="number of layouts (default 100)")
    p.add_argument("--seed", type=int, default=0, help="layout seed offset S (default 0)")
    p.add_argument("--workers", type=int, default=1, help="parallel environments (default 1)")
    p.add_argument("--video", default=None, help="also record the first layout (.mp4 or .gif)")
    p.add_argument("--json", default=None, help="write the full results as JSON here")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_evaluate)

    p = subparsers.add_parser(
        "run",
        help="demonstrate, fit, evaluate, plot: the whole pipeline in one command",
        description="Record demonstrations with the scripted teacher, fit the local-GP policy, "
        "evaluate it on new layouts and write the policy, results.json, figures (Figs. 1, 2, 4, "
        "5 of the paper) and a rollout video into --out.",
    )
    p.add_argument(
        "--out", default="gym-coffee-run", help="output folder (default ./gym-coffee-run)"
    )
    p.add_argument("--demos", type=int, default=4, help="number of demonstrations (default 4)")
    p.add_argument("--episodes", type=int, default=50, help="evaluation layouts (default 50)")
    p.add_argument("--seed", type=int, default=0, help="seed of demonstrations and layouts")
    p.add_argument("--workers", type=int, default=1, help="parallel environments for evaluation")
    p.add_argument("--no-video", action="store_true", help="skip the rollout video")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    _add_policy_options(p)
    p.set_defaults(func=cmd_run)

    try:  # the residual-RL subcommand lives in its own module (optional extra)
        from lgp_policy.app.finetune_cli import add_finetune_subcommand
    except ImportError:  # pragma: no cover - depends on the checkout
        pass
    else:
        add_finetune_subcommand(subparsers)


def _add_policy_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("policy")
    g.add_argument(
        "--model",
        default="local",
        choices=("local", "heteroscedastic", "exact", "empirical"),
        help="encoder (default: local heteroscedastic GP, as in the paper)",
    )
    g.add_argument(
        "--combine", default=None, help="LocalGP combination rule (product, nearest, rbcm)"
    )
    g.add_argument("--alpha", type=float, default=None, help="null-space weight (default 0.5)")
    g.add_argument("--joint-only", action="store_true", help="ignore the object frames (ablation)")


def _policy_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    kwargs: dict[str, Any] = {"model": args.model}
    if args.combine is not None:
        kwargs["combine"] = args.combine
    if args.alpha is not None:
        kwargs["alpha"] = args.alpha
    if args.joint_only:
        kwargs["frames"] = ()
    return kwargs


def load_policy(path: str | Path) -> Any:
    """Open a GP policy ``.npz`` or any other policy kind this project writes (residual)."""
    try:
        from lgp_policy.residual.core import load_any_policy
    except ImportError:
        load_any_policy = None
    if load_any_policy is not None:
        return load_any_policy(path)
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    return GPDemonstrationPolicy.load(path)


def cmd_fit(args: argparse.Namespace) -> int:
    from gym_coffee.demonstrations import DemonstrationSet
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    demos = DemonstrationSet.load(args.demos)
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        print(f"error: {out} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    print(f"fitting {len(demos)} demonstrations ({args.model}) ...", flush=True)
    policy = GPDemonstrationPolicy(**_policy_kwargs(args)).fit(demos, progress=True)
    path = policy.save(out, overwrite=args.overwrite)
    print(f"fitted in {policy.fit_time_:.1f} s; wrote {path}")
    for iv in policy.constraints_["intervals"]:
        print(f"  tight: {iv['label']}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from lgp_policy.app.evaluation import evaluate_policy_stages, format_results

    policy = load_policy(args.policy)
    result = evaluate_policy_stages(
        policy,
        args.episodes,
        seed=args.seed,
        workers=args.workers,
        video=args.video,
        progress=not args.no_progress,
    )
    print(format_results(result))
    if result.get("video"):
        print(f"video: {result['video']}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=2))
        print(f"results: {args.json}")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from lgp_policy.app.pipeline import run_pipeline

    run_pipeline(
        args.out,
        n_demos=args.demos,
        n_episodes=args.episodes,
        seed=args.seed,
        workers=args.workers,
        video=not args.no_video,
        plots=not args.no_plots,
        policy_kwargs=_policy_kwargs(args),
    )
    return 0
