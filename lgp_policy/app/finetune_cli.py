"""``gym-coffee finetune``: residual-RL fine-tuning of the button press.

:func:`lgp_policy.app.commands.add_subcommands` adds it with::

    from lgp_policy.app.finetune_cli import add_finetune_subcommand
    add_finetune_subcommand(subparsers)

This module imports only the standard library at module level: ``gym-coffee --help`` and every
other subcommand work without the ``rl`` extra, and ``finetune`` says which extra to install.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

__all__ = ["add_finetune_subcommand", "build_env_fn", "make_gate", "run_finetune"]

ENV_ID = "gym_coffee/CoffeeTask-v0"
VARIANTS = ("none", "machine-offset")


def add_finetune_subcommand(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``finetune`` to a ``gym-coffee`` sub-parser set; returns the new parser."""
    p = subparsers.add_parser(
        "finetune",
        help="residual-RL fine-tuning of the button press (needs the rl extra)",
        description=(
            "Fine-tune a residual on top of a base policy with an unmodified stable-baselines3 "
            "algorithm: applied action = clip(base + scale * gate * residual). The gate opens "
            "in the press phase only; the residual actor starts at zero, so training starts "
            "from the base policy. Writes DIR/residual_policy.npz (accepted by gym-coffee "
            "evaluate), DIR/learning_curve.png/.json and DIR/checkpoints/. Needs "
            'pip install "gym-coffee[rl]".'
        ),
    )
    p.add_argument("policy", metavar="POLICY", help="base policy file (from gym-coffee fit)")
    p.add_argument("--algo", choices=("sac", "td3", "ppo"), default="sac", help="(default: sac)")
    p.add_argument(
        "--timesteps",
        type=int,
        default=100_000,
        metavar="N",
        help="training budget in env steps (default: 100000)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="(default: 0)")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="output folder (default: runs/finetune-ALGO-seedS)",
    )
    p.add_argument(
        "--scale",
        type=float,
        default=0.5,
        help="largest residual, in action units; 1 action unit = 0.05 rad per step (default 0.5)",
    )
    p.add_argument(
        "--gate-start",
        type=float,
        default=None,
        metavar="PHASE",
        help="phase at which the residual is fully on (default: 0.05 after the phase at which "
        "the demonstrations had placed the cup, from the policy's constraint report)",
    )
    p.add_argument(
        "--eval-episodes",
        type=int,
        default=20,
        metavar="K",
        help="held-out layouts per learning-curve point (default: 20)",
    )
    p.add_argument(
        "--eval-freq", type=int, default=10_000, metavar="N", help="env steps between points"
    )
    p.add_argument(
        "--checkpoint-freq",
        type=int,
        default=25_000,
        metavar="N",
        help="env steps between checkpoints (default: 25000)",
    )
    p.add_argument(
        "--n-envs",
        type=int,
        default=1,
        metavar="K",
        help="training envs; K > 1 runs them in subprocesses (default: 1, best on 2 cores)",
    )
    p.add_argument(
        "--variant",
        choices=VARIANTS,
        default="none",
        help="harder env variant for when the base already presses reliably: 'machine-offset' "
        "shifts the observed machine position a few mm towards its front, so the base aims "
        "short of the button (lgp_policy.residual.core.MachinePoseErrorWrapper; default: none)",
    )
    p.add_argument(
        "--variant-range",
        type=float,
        nargs=2,
        default=(0.002, 0.010),
        metavar=("LOW", "HIGH"),
        help="machine-offset: per-episode offset range in m (default: 0.002 0.010)",
    )
    p.add_argument("--force", action="store_true", help="overwrite an existing DIR")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run_finetune)
    return p


def make_gate(base: Any, start: float | None = None) -> Any:
    """The default gate for ``base``: a :class:`~lgp_policy.residual.core.PhaseGate` on the
    base's own phase when it has ``phase(observation)``, else on the observation's time over
    the base's ``duration`` (seconds) if it has one, else over the env's time limit."""
    from lgp_policy.residual.core import PhaseGate

    if start is None:
        start = _press_phase_start(base)
    if callable(getattr(base, "phase", None)):
        return PhaseGate(start=start, source="policy")
    from gym_coffee.env import CONTROL_DT, MAX_EPISODE_STEPS, OBS_SLICES

    duration = float(getattr(base, "duration", MAX_EPISODE_STEPS * CONTROL_DT))
    return PhaseGate(
        start=start,
        source="observation",
        time_index=OBS_SLICES["time"].start,
        time_scale=duration,
    )


PLACED_MARGIN = 0.05
"""Phase after the demonstrations' mean ``cup_placed`` phase at which the gate is fully open."""


def _press_phase_start(base: Any, default: float = 0.8) -> float:
    """Where the press phase starts, from what the base learned from its demonstrations.

    1. The mean phase at which the demonstrations had placed the cup (the GP policy's
       ``constraint_report()["stage_phases"]["cup_placed"]``) plus :data:`PLACED_MARGIN`: after
       the place, what is left is letting go, pulling back and pressing.
    2. Else the start of the machine frame's last tight interval (Fig. 4b's press constraint).
    3. Else ``default``.

    The machine frame alone is not enough: with the teacher's demonstrations it stays tight
    from the place to the press (one interval, phase 0.52-1.0), which would open the gate while
    the cup is still being carried.
    """
    report_fn = getattr(base, "constraint_report", None)
    if callable(report_fn):
        try:
            placed = report_fn().get("stage_phases", {}).get("cup_placed")
        except Exception:  # a report we do not understand: try the next source
            placed = None
        if placed is not None:
            return float(min(placed + PLACED_MARGIN, 0.95))
    intervals_fn = getattr(base, "constraint_intervals", None)
    if callable(intervals_fn):
        try:
            intervals = [
                iv for iv in intervals_fn() if "machine" in str(iv.get("frame", "")).lower()
            ]
        except Exception:
            intervals = []
        if intervals:
            return float(max(float(iv["start"]) for iv in intervals))
    return default


def build_env_fn(
    variant: str = "none",
    *,
    offset_range: tuple[float, float] = (0.002, 0.010),
    env_kwargs: dict[str, Any] | None = None,
) -> Any:
    """A picklable factory for the training/evaluation env, optionally the harder variant
    ``"machine-offset"`` (:class:`~lgp_policy.residual.core.MachinePoseErrorWrapper`)."""
    return _EnvFactory(variant, (float(offset_range[0]), float(offset_range[1])), env_kwargs)


class _EnvFactory:
    def __init__(
        self,
        variant: str,
        offset_range: tuple[float, float],
        env_kwargs: dict[str, Any] | None,
    ) -> None:
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        self.variant, self.offset_range = variant, offset_range
        self.env_kwargs = dict(env_kwargs or {})

    def __call__(self) -> Any:
        import gymnasium as gym

        import gym_coffee  # noqa: F401  (registers the env)

        env = gym.make(ENV_ID, **self.env_kwargs)
        if self.variant == "machine-offset":
            from lgp_policy.residual.core import MachinePoseErrorWrapper

            low, high = self.offset_range
            env = MachinePoseErrorWrapper(env, low=low, high=high)
        return env


def run_finetune(args: argparse.Namespace) -> int:
    """Entry point of ``gym-coffee finetune``."""
    from lgp_policy.residual.core import require_rl

    try:
        _, torch = require_rl()
    except ImportError as exc:
        print(f"gym-coffee finetune: {exc}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    from lgp_policy.residual.core import finetune, load_any_policy

    base_path = Path(args.policy)
    try:
        base = load_any_policy(base_path)
    except (OSError, ValueError) as exc:
        print(f"gym-coffee finetune: cannot load {base_path}: {exc}", file=sys.stderr)
        return 2
    gate = make_gate(base, args.gate_start)
    env_fn = build_env_fn(args.variant, offset_range=tuple(args.variant_range))
    out = args.out or Path("runs") / f"finetune-{args.algo}-seed{args.seed}"
    try:
        result = finetune(
            base,
            env_fn,
            algo=args.algo,
            total_env_steps=args.timesteps,
            seed=args.seed,
            scale=args.scale,
            gate=gate,
            residual_dims=list(range(7)),
            eval_episodes=args.eval_episodes,
            eval_freq=args.eval_freq,
            checkpoint_freq=args.checkpoint_freq,
            n_envs=args.n_envs,
            out_dir=out,
            overwrite=args.force,
            base_path=base_path,
            progress=not args.no_progress,
        )
    except FileExistsError as exc:
        print(f"gym-coffee finetune: {exc}", file=sys.stderr)
        return 2
    first, last = result.curve[0], result.curve[-1]
    print(
        f"{result.env_steps} env steps ({result.agent_steps} agent steps) in "
        f"{result.wall_time_s:.0f} s"
    )
    print(f"{'stage':<19}{'base':>8}{'fine-tuned':>12}   ({last['episodes']} held-out layouts)")
    for key, value in last["rates"].items():
        print(f"{key:<19}{first['rates'][key]:>8.2f}{value:>12.2f}")
    print(f"wrote {out / 'residual_policy.npz'}, {out / 'learning_curve.png'}")
    return 0
