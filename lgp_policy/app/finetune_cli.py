"""``gym-coffee finetune``: residual-RL fine-tuning of the button press, one run per seed.

:func:`lgp_policy.app.commands.add_subcommands` adds it with::

    from lgp_policy.app.finetune_cli import add_finetune_subcommand
    add_finetune_subcommand(subparsers)

This module imports only the standard library at module level: ``gym-coffee --help`` and every
other subcommand work without the ``rl`` extra, and ``finetune`` says which extra to install.

It is the coffee task's side of :mod:`lgp_policy.residual`: the env factory (with the env's
calibration-bias perturbation), the default gate from the base policy's constraint report, the
learning curve's evaluation (through :mod:`lgp_policy.app.evaluation`'s one episode loop), the
figure, and the seeds run locally or as Ray tasks.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import sys
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from lgp_policy.app._common import (
    UsageError,
    add_force_option,
    check_output_folder,
    finite_float,
    input_file,
    int_range,
    seed_int,
)

__all__ = [
    "CURVE_SEED_OFFSET",
    "FinetuneJob",
    "add_finetune_subcommand",
    "build_env_fn",
    "evaluate_stages",
    "make_gate",
    "make_reward_fn",
    "plot_learning_curve",
    "run_finetune",
    "run_jobs",
]

CURVE_SEED_OFFSET = 20_000
"""Held-out layouts for the learning curve: seeds ``CURVE_SEED_OFFSET + i``. They are disjoint
from the demonstration seeds (``seed, seed + 1, ...``) and from ``gym-coffee evaluate``'s test
seeds (``EVAL_SEED_OFFSET + seed + i``, offset 10 000): the final benchmark is not selected on."""
PLACED_MARGIN = 0.05
"""Phase after the demonstrations' mean ``cup_placed`` phase at which the gate is fully open."""
MAX_CALIBRATION_BIAS = 0.1
"""The env's largest ``calibration_bias`` (``gym_coffee.env.MAX_PERTURBATION``), in metres."""
BACKENDS = ("local", "ray")
REWARDS = ("shaped", "env")
POTENTIAL_TERMS = ("reach", "carry", "press")
"""The coffee env's dense reward terms (distances, the button's travel): with ``--reward shaped``
(the default) the agent is paid their change, ``gamma * phi(s') - phi(s)``
(:class:`~lgp_policy.residual.rewards.PotentialShaping`), and the env's event terms (stage,
success, failure) as they are. Paid as they are, every step, the press term pays up to +1 per
step for holding the button short of the press: SAC then learns not to press."""


# ----------------------------------------------------------------------------- argument types
_positive = int_range(1, 10**9, what="an integer")
_non_negative = int_range(0, 10**9, what="an integer (0: never)")
_n_envs = int_range(1, 64, what="an integer")
_scale = finite_float(0.0, 2.0, lo_open=True)
_phase = finite_float(0.0, 1.0)
_bias = finite_float(0.0, MAX_CALIBRATION_BIAS)


def add_finetune_subcommand(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``finetune`` to a ``gym-coffee`` sub-parser set; returns the new parser."""
    p = subparsers.add_parser(
        "finetune",
        help="residual-RL fine-tuning of the button press (needs the rl extra)",
        description=(
            "Fine-tune a residual on top of a base policy with an unmodified stable-baselines3 "
            "algorithm: applied action = clip(base + scale * gate * residual). The gate opens "
            "in the press phase only; the residual actor starts at zero, so training starts "
            "from the base policy. Writes, per seed S, DIR/seedS/residual_policy.npz (accepted "
            "by gym-coffee evaluate), learning_curve.png/.json and checkpoints/. Seeds run one "
            "after another, or as Ray tasks with --backend ray. Needs "
            'pip install "gym-coffee[rl]" (and "gym-coffee[ray]" for --backend ray).'
        ),
    )
    p.add_argument(
        "policy",
        metavar="POLICY",
        type=input_file(".npz"),
        help="base GP policy file (from gym-coffee fit)",
    )
    p.add_argument("--algo", choices=("sac", "td3", "ppo"), default="sac", help="(default: sac)")
    p.add_argument(
        "--timesteps",
        type=_positive,
        default=100_000,
        metavar="N",
        help="training budget per seed in env steps (default: 100000)",
    )
    p.add_argument(
        "--seeds",
        type=seed_int,
        nargs="+",
        default=[0],
        metavar="S",
        help="training seeds, one run each (default: 0)",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="output folder (default: runs/finetune-ALGO)",
    )
    p.add_argument(
        "--scale",
        type=_scale,
        default=0.5,
        help="largest residual, in action units; 1 action unit = 0.05 rad per step (default 0.5)",
    )
    p.add_argument(
        "--gate-start",
        type=_phase,
        default=None,
        metavar="PHASE",
        help="phase in [0, 1] at which the residual is fully on (default: 0.05 after the phase "
        "at which the demonstrations had placed the cup, from the policy's constraint report)",
    )
    p.add_argument(
        "--eval-episodes",
        type=_positive,
        default=20,
        metavar="K",
        help="held-out layouts per learning-curve point (default: 20)",
    )
    p.add_argument(
        "--eval-freq",
        type=_non_negative,
        default=10_000,
        metavar="N",
        help="env steps between learning-curve points (0: start and end only; default: 10000)",
    )
    p.add_argument(
        "--keep-best",
        action="store_true",
        help="save the policy of the learning-curve point with the highest task success on the "
        "curve layouts (the start's included) instead of the last one",
    )
    p.add_argument(
        "--checkpoint-freq",
        type=_non_negative,
        default=25_000,
        metavar="N",
        help="env steps between checkpoints (0: none; default: 25000)",
    )
    p.add_argument(
        "--n-envs",
        type=_n_envs,
        default=1,
        metavar="K",
        help="training envs per seed; K > 1 runs them in subprocesses (default: 1, best on 2 "
        "cores)",
    )
    p.add_argument(
        "--calibration-bias",
        type=_bias,
        default=0.0,
        metavar="M",
        help="perturbation: the observed cup and machine positions are off by M metres, in a "
        "random direction per episode (the env's calibration_bias; default: 0)",
    )
    p.add_argument(
        "--reward",
        choices=REWARDS,
        default="shaped",
        help="shaped: the env's event terms (stage, success, failure) plus the change of its "
        "dense terms (potential-based shaping); env: the env's dense reward as it is "
        "(default: shaped)",
    )
    p.add_argument(
        "--backend", choices=BACKENDS, default="local", help="where seeds run (default: local)"
    )
    p.add_argument(
        "--address",
        default=None,
        metavar="ADDR",
        help="Ray cluster address for --backend ray (default: start a local Ray)",
    )
    add_force_option(p, "results of the same seeds in DIR")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run_finetune)
    return p


# ------------------------------------------------------------------------------- coffee parts
def make_gate(base: Any, start: float | None = None) -> Any:
    """The default gate for ``base``: a :class:`~lgp_policy.residual.gates.PhaseGate` on the
    base's own phase when it has ``phase(observation)``, else on the observation's time over
    the base's ``duration`` (seconds) if it has one, else over the env's time limit."""
    from lgp_policy.residual.gates import PhaseGate

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
        placed = report_fn().get("stage_phases", {}).get("cup_placed")
        if placed is not None:
            return float(min(placed + PLACED_MARGIN, 0.95))
    intervals_fn = getattr(base, "constraint_intervals", None)
    if callable(intervals_fn):
        starts = [
            float(iv["start"])
            for iv in intervals_fn()
            if "machine" in str(iv.get("frame", "")).lower()
        ]
        if starts:
            return max(starts)
    return default


class _EnvFactory:
    """Picklable coffee-env factory (``SubprocVecEnv`` and Ray workers call it)."""

    def __init__(self, calibration_bias: float, env_kwargs: Mapping[str, Any] | None) -> None:
        self.calibration_bias = float(calibration_bias)
        self.env_kwargs = dict(env_kwargs or {})

    def __call__(self) -> Any:
        import gymnasium as gym

        import gym_coffee

        return gym.make(
            gym_coffee.ENV_ID, calibration_bias=self.calibration_bias, **self.env_kwargs
        )


def build_env_fn(
    calibration_bias: float = 0.0, *, env_kwargs: Mapping[str, Any] | None = None
) -> Callable[[], Any]:
    """A picklable factory for the training/evaluation env with the env's ``calibration_bias``
    perturbation (a per-episode constant offset of that length, in a random direction, of the
    observed cup and machine positions)."""
    if not (math.isfinite(calibration_bias) and 0 <= calibration_bias <= MAX_CALIBRATION_BIAS):
        raise ValueError(
            f"calibration_bias must be in [0, {MAX_CALIBRATION_BIAS}] m, got {calibration_bias}"
        )
    return _EnvFactory(calibration_bias, env_kwargs)


def evaluate_stages(policy: Any, env_fn: Callable[[], Any], seeds: Sequence[int]) -> dict[str, Any]:
    """Per-stage rates of ``policy`` on one episode per seed, rolled out by the one episode loop
    (:func:`lgp_policy.rollout.run_episode`); also ``cup_placed_at_end`` (a residual that knocks
    the cup away after placing it loses that one). Returns ``{"episodes", "rates"}``."""
    from gym_coffee import STAGES
    from lgp_policy.rollout import run_episode

    flags = (*STAGES, "is_success")
    hits = dict.fromkeys([*flags, "cup_placed_at_end"], 0)
    env = env_fn()
    try:
        for seed in seeds:
            episode = run_episode(policy, env, int(seed), flags=flags)
            for flag in flags:
                hits[flag] += bool(episode.reached.get(flag, False))
            hits["cup_placed_at_end"] += bool(episode.final_info.get("cup_placed", False))
    finally:
        env.close()
    n = max(len(seeds), 1)
    return {"episodes": len(seeds), "rates": {k: v / n for k, v in hits.items()}}


def make_reward_fn(reward: str, algo: str) -> Any:
    """The agent's reward for ``--reward``: ``None`` (the env's) or the potential-based shaping
    of the env's dense terms with the algorithm's discount."""
    if reward not in REWARDS:
        raise ValueError(f"reward must be one of {REWARDS}, got {reward!r}")
    if reward == "env":
        return None
    from gym_coffee.env import REWARD_TERMS
    from lgp_policy.residual.models import resolve_hyperparameters
    from lgp_policy.residual.rewards import PotentialShaping

    assert set(POTENTIAL_TERMS) <= set(REWARD_TERMS), (POTENTIAL_TERMS, REWARD_TERMS)
    return PotentialShaping(POTENTIAL_TERMS, resolve_hyperparameters(algo, None)["gamma"])


class _CurveEvaluation:
    """``evaluate(policy)`` for :func:`lgp_policy.residual.train.finetune`'s learning curve."""

    def __init__(self, env_fn: Callable[[], Any], n_episodes: int) -> None:
        self.env_fn = env_fn
        self.seeds = [CURVE_SEED_OFFSET + i for i in range(n_episodes)]

    def __call__(self, policy: Any) -> dict[str, Any]:
        return evaluate_stages(policy, self.env_fn, self.seeds)


def plot_learning_curve(curve: Sequence[Mapping[str, Any]], path: Path, *, title: str = "") -> Path:
    """Per-stage success on the held-out layouts versus training env steps (PNG)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    steps = [c["env_steps"] for c in curve]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for key in curve[0]["rates"]:
        ax.plot(steps, [c["rates"][key] for c in curve], marker="o", label=key)
    ax.set_ylabel(f"success on {curve[0]['episodes']} held-out layouts")
    ax.set_ylim(-0.02, 1.02)
    ax.axhline(0.95, color="grey", lw=0.8, ls="--")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_xlabel("training env steps")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    path.write_bytes(buf.getvalue())
    return path


# ----------------------------------------------------------------------------------- the runs
class FinetuneJob:
    """One seed's fine-tuning, runnable in this process or as a Ray task.

    The base policy travels as its file's bytes and the results come back as bytes (file name
    -> content), so a task needs no shared disk; :func:`run_jobs` writes them under ``out``.
    """

    def __init__(self, base_bytes: bytes, seed: int, settings: Mapping[str, Any]) -> None:
        self.base_bytes, self.seed, self.settings = base_bytes, int(seed), dict(settings)

    def __call__(self) -> dict[str, bytes]:
        from threadpoolctl import threadpool_limits

        from lgp_policy.lfd.policy import GPDemonstrationPolicy
        from lgp_policy.residual.train import finetune

        s = self.settings
        base = GPDemonstrationPolicy.load(io.BytesIO(self.base_bytes))
        env_fn = build_env_fn(s["calibration_bias"])
        with tempfile.TemporaryDirectory() as tmp, threadpool_limits(1):
            base_path = Path(tmp) / "base_policy.npz"
            base_path.write_bytes(self.base_bytes)
            out = Path(tmp) / "run"
            result = finetune(
                base,
                env_fn,
                algo=s["algo"],
                total_env_steps=s["timesteps"],
                seed=self.seed,
                scale=s["scale"],
                gate=make_gate(base, s["gate_start"]),
                residual_dims=list(range(7)),
                reward_fn=make_reward_fn(s["reward"], s["algo"]),
                evaluate=_CurveEvaluation(env_fn, s["eval_episodes"]),
                eval_freq=s["eval_freq"],
                keep_best=bool(s.get("keep_best", False)),
                checkpoint_freq=s["checkpoint_freq"],
                n_envs=s["n_envs"],
                out_dir=out,
                base_path=base_path,
                progress=s["progress"],
            )
            if result.curve:
                plot_learning_curve(
                    result.curve,
                    out / "learning_curve.png",
                    title=f"residual {s['algo']}, seed {self.seed}",
                )
            return {
                str(f.relative_to(out)): f.read_bytes()
                for f in sorted(out.rglob("*"))
                if f.is_file()
            }


def _call(job: FinetuneJob) -> dict[str, bytes]:
    return job()


def _map_jobs(
    jobs: Sequence[FinetuneJob], backend: str, address: str | None
) -> list[dict[str, bytes]]:
    """The jobs' results, in order: here one after another, or as Ray tasks of 1 CPU each."""
    from lgp_policy.app.backends import map_tasks

    return map_tasks(_call, jobs, backend=backend, address=address)


def run_jobs(
    jobs: Sequence[FinetuneJob], out: Path, *, backend: str = "local", address: str | None = None
) -> dict[int, dict[str, Any]]:
    """Run the jobs, write each seed's files under ``out/seed<S>/`` and return each seed's
    ``learning_curve.json`` content."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    results = _map_jobs(jobs, backend, address)
    summaries: dict[int, dict[str, Any]] = {}
    for job, files in zip(jobs, results, strict=True):
        _replace_folder(out / f"seed{job.seed}", files)
        summaries[job.seed] = json.loads(files["learning_curve.json"])
    return summaries


def _replace_folder(folder: Path, files: Mapping[str, bytes]) -> None:
    """Write ``files`` into a fresh folder next to ``folder``, then swap it in: an overwritten
    run never mixes its files with an older run's."""
    import shutil

    folder.parent.mkdir(parents=True, exist_ok=True)
    fresh = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        for name, content in files.items():
            rel = Path(name)
            if rel.is_absolute() or ".." in rel.parts:
                raise ValueError(f"a task returned a file outside its folder: {name!r}")
            (fresh / rel).parent.mkdir(parents=True, exist_ok=True)
            (fresh / rel).write_bytes(content)
        fresh.chmod(0o755)
        old = None
        if folder.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old.", dir=folder.parent))
            folder.rename(old / folder.name)
        fresh.rename(folder)
        if old is not None:
            shutil.rmtree(old)
    except BaseException:
        shutil.rmtree(fresh, ignore_errors=True)
        raise


def run_finetune(args: argparse.Namespace) -> int:
    """Entry point of ``gym-coffee finetune``: everything is checked before any training (bad
    input raises; ``gym-coffee`` prints it as one line and exits with 2)."""
    from lgp_policy.residual.models import require_rl

    require_rl()  # ImportError naming the extra
    if args.backend == "ray":
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ImportError('--backend ray needs Ray: pip install "gym-coffee[ray]"') from None
    elif args.address is not None:
        raise UsageError("argument --address: needs --backend ray")
    if len(set(args.seeds)) != len(args.seeds):
        raise UsageError(f"argument --seeds: repeated seeds {args.seeds}")
    out = args.out or Path("runs") / f"finetune-{args.algo}"
    for seed in args.seeds:
        check_output_folder("--out", out / f"seed{seed}", force=args.force, owned=())
    base_path = Path(args.policy)
    import gym_coffee
    from lgp_policy.lfd.policy import MAX_FILE_BYTES, GPDemonstrationPolicy

    size = base_path.stat().st_size
    if size > MAX_FILE_BYTES:  # checked before the file is read into memory
        raise UsageError(
            f"argument POLICY: {base_path} is {size} bytes; a policy file has at most "
            f"{MAX_FILE_BYTES}"
        )
    base_bytes = base_path.read_bytes()
    named = io.BytesIO(base_bytes)
    named.name = str(base_path)  # the errors name the file, not "<in-memory file>"
    try:
        recorded = GPDemonstrationPolicy.load(named).demonstrations_env_
    except ValueError as exc:
        raise UsageError(f"argument POLICY: {exc}") from exc
    if recorded is not None and (
        recorded["env_id"] != gym_coffee.ENV_ID
        or recorded["env_kwargs"].get("physics", "default") != "default"
    ):  # finetuning runs on the easy level with the default physics
        print(
            f"note: the policy was fitted on demonstrations of {recorded['env_id']} "
            f"({recorded['env_kwargs'].get('physics', 'default')} physics); finetune trains "
            f"and evaluates on {gym_coffee.ENV_ID} with the default physics",
            file=sys.stderr,
            flush=True,
        )
    settings = {
        "algo": args.algo,
        "timesteps": args.timesteps,
        "scale": args.scale,
        "gate_start": args.gate_start,
        "eval_episodes": args.eval_episodes,
        "eval_freq": args.eval_freq,
        "keep_best": args.keep_best,
        "checkpoint_freq": args.checkpoint_freq,
        "n_envs": args.n_envs,
        "calibration_bias": args.calibration_bias,
        "reward": args.reward,
        "progress": not args.no_progress and args.backend == "local",
    }
    jobs = [FinetuneJob(base_bytes, seed, settings) for seed in args.seeds]
    summaries = run_jobs(jobs, out, backend=args.backend, address=args.address)
    for seed, summary in summaries.items():
        first, last = summary["curve"][0], summary["curve"][-1]
        kept_steps = summary.get("kept_env_steps")
        if kept_steps is not None:  # --keep-best: the saved policy is that curve point's
            last = next(c for c in summary["curve"] if c["env_steps"] == kept_steps)
        print(
            f"seed {seed}: {summary['env_steps']} env steps ({summary['agent_steps']} agent "
            f"steps), {summary['wall_time_s']:.0f} s wall, {summary['cpu_time_s']:.0f} s CPU"
            + ("" if kept_steps is None else f"; kept the policy of env step {kept_steps}")
        )
        print(f"{'stage':<19}{'base':>8}{'fine-tuned':>12}   ({last['episodes']} held-out layouts)")
        for key, value in last["rates"].items():
            print(f"{key:<19}{first['rates'][key]:>8.2f}{value:>12.2f}")
        print(f"wrote {out / f'seed{seed}'}/residual_policy.npz, learning_curve.png")
    return 0
