"""Subcommands of ``gym-coffee`` that belong to the learning side: ``fit``, ``evaluate``, ``run``
(and ``finetune``, ``teleop``, ``export`` when their modules are importable).

* ``gym-coffee fit DEMOS --out POLICY.npz``: encode recorded demonstrations into a policy file.
* ``gym-coffee evaluate POLICY --episodes N --seed S [--level easy|hard | --env-id ID]
  [--workers K] [--video out.mp4] [--json out.json] [--backend ray [--address ADDR]]``:
  per-stage success on held-out layouts of one level with 95% Wilson intervals.
* ``gym-coffee run [--out DIR] [--demos 4] [--episodes 50] [--seed S]``: record demonstrations,
  fit, evaluate, and write the policy, ``results.json``, the figures and a rollout video to DIR.

Every command checks all its arguments (numbers, input files, output names, the overwrite rule)
before any work starts; see :mod:`lgp_policy.app._common` for the error path.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path
from typing import Any

import gym_coffee
from lgp_policy._io import atomic_write_text
from lgp_policy.app._common import (
    UsageError,
    add_env_options,
    add_force_option,
    check_output,
    check_output_folder,
    check_seed_room,
    check_video_output,
    demos_int,
    env_id_from_args,
    env_kwargs_from_args,
    finite_float,
    input_file,
    int_range,
    seed_int,
)
from lgp_policy.app.backends import add_backend_arguments

__all__ = ["add_subcommands", "load_policy"]

MAX_WORKERS = 1024
MAX_EPISODES = 10_000_000
EVAL_SEED_OFFSET = 10_000
"""Evaluation layouts use seeds ``10000 + S + i`` (disjoint from demonstration seeds)."""
MODELS = ("local", "heteroscedastic", "exact", "empirical")
COMBINE_RULES = ("product", "nearest", "rbcm")
"""``LocalGP`` combination rules (``lgp_policy.gp.local.COMBINE_RULES``)."""
workers_int = int_range(1, MAX_WORKERS, what="a number of workers")
episodes_int = int_range(1, MAX_EPISODES, what="a number of episodes")


def add_subcommands(subparsers: argparse._SubParsersAction) -> None:
    """Add ``fit``, ``evaluate``, ``run`` and the optional modules' subcommands."""
    p = subparsers.add_parser(
        "fit",
        help="fit a GP policy to recorded demonstrations",
        description="Encode demonstrations (a .npz written by `gym-coffee record`) into a "
        "GPDemonstrationPolicy file.",
    )
    p.add_argument("demos", type=input_file(".npz"), help="demonstrations file (.npz)")
    p.add_argument("--out", type=Path, required=True, help="policy file to write (.npz)")
    _add_policy_options(p)
    add_force_option(p, "policy file")
    p.set_defaults(func=cmd_fit)

    p = subparsers.add_parser(
        "evaluate",
        help="evaluate a policy on held-out layouts (per-stage success)",
        description="Run a policy on layouts from seeds 10000+S.. (disjoint from demonstration "
        "seeds) of one difficulty level and print per-stage success rates with 95% Wilson "
        "intervals. The level and physics default to those of the demonstrations the policy "
        "was fitted on (recorded in the policy file).",
    )
    p.add_argument("policy", type=input_file(".npz"), help="policy file (GP or residual, .npz)")
    add_env_options(p, "the evaluation layouts", from_policy=True)
    p.add_argument("--episodes", type=episodes_int, default=100, help="layouts (default 100)")
    p.add_argument("--seed", type=seed_int, default=0, help="layout seed offset S (default 0)")
    p.add_argument("--workers", type=workers_int, default=1, help="parallel envs (default 1)")
    p.add_argument(
        "--video", type=Path, default=None, help="also record the first layout (.mp4 or .gif)"
    )
    p.add_argument("--json", type=Path, default=None, help="write the full results here (.json)")
    add_backend_arguments(p)
    add_force_option(p, "--json and --video files")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_evaluate)

    p = subparsers.add_parser(
        "run",
        help="demonstrate, fit, evaluate, plot: the whole pipeline in one command",
        description="Record demonstrations with the scripted teacher, fit the local-GP policy, "
        "evaluate it on new layouts and write the policy, results.json, figures (Figs. 1, 2, 4, "
        "5 of the paper) and a rollout video into --out (a new or empty folder; --force "
        "replaces the files of an earlier run there, keeping them aside until the new run "
        "completes, and leaves other files alone).",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=Path("gym-coffee-run"),
        help="output folder (default ./gym-coffee-run)",
    )
    p.add_argument("--demos", type=demos_int, default=4, help="demonstrations (default 4)")
    p.add_argument("--episodes", type=episodes_int, default=50, help="layouts (default 50)")
    p.add_argument("--seed", type=seed_int, default=0, help="seed of demonstrations and layouts")
    p.add_argument("--workers", type=workers_int, default=1, help="parallel envs for evaluation")
    p.add_argument("--no-video", action="store_true", help="skip the rollout video")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    add_env_options(p, "the demonstrations and the evaluation layouts")
    _add_policy_options(p)
    add_force_option(p, "files of an earlier run in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_run)

    for module, name in (
        ("lgp_policy.app.finetune_cli", "add_finetune_subcommand"),  # residual RL (rl extra)
        ("lgp_policy.app.data_commands", "add_subcommands"),  # teleop, export
    ):
        try:
            add = getattr(importlib.import_module(module), name, None)
        except ImportError:  # pragma: no cover - an optional part absent from this install
            continue
        if add is not None:
            add(subparsers)


def _add_policy_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("policy")
    g.add_argument(
        "--model",
        default="local",
        choices=MODELS,
        help="encoder (default: local heteroscedastic GP, as in the paper)",
    )
    g.add_argument(
        "--combine",
        default=None,
        choices=COMBINE_RULES,
        help="LocalGP combination rule (with --model local)",
    )
    g.add_argument(
        "--alpha",
        type=finite_float(0.0, 1.0),
        default=None,
        help="null-space weight in [0, 1] (default 0.5)",
    )
    g.add_argument("--joint-only", action="store_true", help="ignore the object frames (ablation)")


def _policy_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The policy's keyword arguments; raises :class:`UsageError` for inconsistent options."""
    if args.combine is not None and args.model != "local":
        raise UsageError(
            f"argument --combine: applies to --model local only, not --model {args.model}"
        )
    kwargs: dict[str, Any] = {"model": args.model}
    if args.combine is not None:
        kwargs["combine"] = args.combine
    if args.alpha is not None:
        kwargs["alpha"] = args.alpha
    if args.joint_only:
        kwargs["frames"] = ()
    return kwargs


def load_policy(path: str | Path) -> Any:
    """Open a GP policy ``.npz`` or a residual policy file (dispatching on its ``kind``)."""
    from lgp_policy.residual import load_any_policy

    return load_any_policy(path)


def cmd_fit(args: argparse.Namespace) -> int:
    from gym_coffee.demonstrations import DemonstrationSet
    from lgp_policy.lfd.policy import GPDemonstrationPolicy

    out = check_output("--out", args.out, force=args.force, suffixes=(".npz",), inputs=[args.demos])
    kwargs = _policy_kwargs(args)
    demos = DemonstrationSet.load(args.demos)
    policy = GPDemonstrationPolicy(**kwargs)
    print(f"fitting {len(demos)} demonstrations ({args.model}) ...", flush=True)
    policy.fit(demos, progress=True)
    path = policy.save(out, overwrite=args.force)
    print(f"fitted in {policy.fit_time_:.1f} s; wrote {path}")
    for iv in policy.constraints_["intervals"]:
        print(f"  tight: {iv['label']}")
    return 0


def _check_evaluate(args: argparse.Namespace) -> str:
    """Check every ``evaluate`` argument before any work; return the env id to evaluate on."""
    env_id = env_id_from_args(args)
    check_seed_room(args.seed, EVAL_SEED_OFFSET + args.episodes, "--episodes", args.episodes)
    outputs = {}
    if args.json is not None:
        outputs["--json"] = check_output(
            "--json", args.json, force=args.force, suffixes=(".json",), inputs=[args.policy]
        )
    if args.video is not None:
        outputs["--video"] = check_video_output("--video", args.video, force=args.force)
    if len({p.absolute() for p in outputs.values()}) < len(outputs):
        raise UsageError("argument --video: the same file as --json")
    if args.chunk_size is not None and args.chunk_size < 1:
        raise UsageError(f"argument --chunk-size: expected an integer >= 1, got {args.chunk_size}")
    if args.address is not None and args.backend != "ray":
        raise UsageError("argument --address: needs --backend ray")
    if args.backend == "ray" and importlib.util.find_spec("ray") is None:
        raise UsageError("argument --backend: ray is not installed (pip install 'gym-coffee[ray]')")
    return env_id


def evaluation_env(
    args: argparse.Namespace, policy: Any, given: str
) -> tuple[str, dict[str, Any], str]:
    """The env ``evaluate`` runs: ``--level``/``--env-id`` and ``--physics`` where given (``given``
    is the checked id, or the default id), else those of the demonstrations the policy was
    fitted on (``demonstrations_env_``, of a residual policy's base too), else the defaults.
    Returns ``(env id, env kwargs, note)``; ``note`` says where a choice differs from the
    demonstrations' env (evaluating elsewhere is allowed: it tests transfer)."""
    recorded = getattr(policy, "demonstrations_env_", None) or getattr(
        getattr(policy, "base", None), "demonstrations_env_", None
    )
    if recorded is None or recorded["env_id"] not in gym_coffee.ENV_IDS:
        return given, env_kwargs_from_args(args), ""
    env_id = given if args.level is not None or args.env_id is not None else recorded["env_id"]
    physics = recorded["env_kwargs"].get("physics") or "default"
    if physics not in gym_coffee.PHYSICS_PRESETS:  # not one this version has: the task's own
        physics = "default"
    env_kwargs = env_kwargs_from_args(args, default=physics)
    theirs = env_text(recorded["env_id"], {} if physics == "default" else {"physics": physics})
    note = f"the policy was fitted on demonstrations of {theirs}"
    return env_id, env_kwargs, "" if theirs == env_text(env_id, env_kwargs) else note


def env_text(env_id: str, env_kwargs: dict[str, Any]) -> str:
    """``"<env id>"``, or ``"<env id> (fast physics)"`` with another physics preset."""
    return f"{env_id} ({env_kwargs['physics']} physics)" if env_kwargs else env_id


def cmd_evaluate(args: argparse.Namespace) -> int:
    from lgp_policy.app.evaluation import evaluate_policy_stages, format_results

    given = _check_evaluate(args)
    try:
        policy = load_policy(args.policy)
    except ValueError as exc:  # a bad file: name the argument, as for the other inputs
        raise UsageError(f"argument POLICY: {exc}") from exc
    env_id, env_kwargs, note = evaluation_env(args, policy, given)
    print(f"evaluating {args.policy} on {env_text(env_id, env_kwargs)}", flush=True)
    if note:
        print(f"note: {note}", file=sys.stderr, flush=True)
    result = evaluate_policy_stages(  # the video is rendered during the evaluation itself
        policy,
        args.episodes,
        seed=args.seed,
        env_id=env_id,
        env_kwargs=env_kwargs,
        workers=args.workers,
        video=args.video,
        progress=not args.no_progress,
        backend=args.backend,
        address=args.address,
        chunk_size=args.chunk_size,
        force=args.force,
    )
    result["env_id"] = env_id
    result["env_kwargs"] = env_kwargs
    print(format_results(result))
    if result.get("video"):
        print(f"video: {result['video']}")
    if args.json is not None:
        atomic_write_text(args.json, json.dumps(result, indent=2), force=args.force)
        print(f"results: {args.json}")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from lgp_policy.app import pipeline

    env_id = env_id_from_args(args)
    stale = check_output_folder("--out", args.out, force=args.force, owned=pipeline.RUN_FILES)
    check_seed_room(args.seed, 100 * args.demos, "--demos", args.demos)
    check_seed_room(args.seed, EVAL_SEED_OFFSET + args.episodes, "--episodes", args.episodes)
    kwargs = _policy_kwargs(args)
    pipeline.run_pipeline(
        args.out,
        n_demos=args.demos,
        n_episodes=args.episodes,
        seed=args.seed,
        workers=args.workers,
        video=not args.no_video,
        plots=not args.no_plots,
        policy_kwargs=kwargs,
        progress=not args.no_progress,
        force=bool(stale),  # the earlier run's files: set aside until this one completes
        env_id=env_id,
        env_kwargs=env_kwargs_from_args(args),
    )
    return 0
