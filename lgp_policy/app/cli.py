"""The ``gym-coffee`` command line.

The single entry point of the application layer: ``record`` lives here; ``fit``, ``evaluate``,
``run`` and ``finetune`` are added by :func:`lgp_policy.app.commands.add_subcommands`.

Example:
    $ gym-coffee record --n 4 --out demos.npz --seed 0 --video demo.mp4
    $ gym-coffee record --n 8 --out hard.npz --level hard
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lgp_policy.app._common import (
    ArgumentParser,
    UsageError,
    add_env_options,
    add_force_option,
    check_output,
    check_seed_room,
    check_video_output,
    demos_int,
    env_id_from_args,
    env_kwargs_from_args,
    run_command,
    seed_int,
)
from lgp_policy.app.commands import EVAL_SEED_OFFSET, add_subcommands

if TYPE_CHECKING:
    from gym_coffee.demonstrations import Demonstration


def add_record_subcommand(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``record``: run the scripted teacher and save demonstrations to one ``.npz``."""
    p = sub.add_parser(
        "record",
        help="record scripted-teacher demonstrations to an .npz file",
        description=(
            "Record N successful demonstrations of the scripted teacher on the layouts of seeds "
            "SEED, SEED+1, ... (a layout on which the teacher fails is skipped and the next "
            "seed is tried; the seeds used are stored in the file) and save them as one .npz "
            "file (schema: docs/demonstration-format.md)."
        ),
    )
    p.add_argument("--n", type=demos_int, default=4, help="number of demonstrations (default 4)")
    p.add_argument("--out", type=Path, required=True, help="output .npz file")
    p.add_argument(
        "--seed",
        type=seed_int,
        default=0,
        help="first layout seed (default 0; keep the seeds below 10000: evaluation uses 10000+)",
    )
    add_force_option(p, "--out and --video files")
    p.add_argument(
        "--video",
        type=Path,
        default=None,
        help="also write a video (.mp4 or .gif) of the first demonstration, replayed",
    )
    add_env_options(p, "the demonstrations")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=cmd_record)
    return p


def check_record(args: argparse.Namespace) -> str:
    """Check every ``record`` argument before any work; return the env id to record on."""
    env_id = env_id_from_args(args)
    check_seed_room(args.seed, 100 * args.n, "--n", args.n)
    check_output("--out", args.out, force=args.force, suffixes=(".npz",))
    if args.video is not None:
        check_video_output("--video", args.video, force=args.force)
        if args.video.absolute() == args.out.absolute():
            raise UsageError("argument --video: the same file as --out")
    return env_id


def cmd_record(args: argparse.Namespace) -> int:
    import gymnasium as gym

    from gym_coffee.demonstrations import collect_demonstrations

    env_id = check_record(args)
    env_kwargs = env_kwargs_from_args(args)
    env = gym.make(env_id, **env_kwargs)
    try:
        demos = collect_demonstrations(env, n=args.n, seed=args.seed, progress=not args.no_progress)
    finally:
        env.close()
    demos.save(args.out, overwrite=args.force)
    n_steps = sum(d.n_steps for d in demos)
    print(
        f"saved {len(demos)} demonstrations on {env_id} (seeds {demos.seeds}, {n_steps} steps) "
        f"to {args.out}"
    )
    failed = demos.metadata.get("failed_seeds") or []
    if failed:
        print(f"the teacher failed on seeds {failed}; they were skipped")
    shared = [s for s in demos.seeds if s >= EVAL_SEED_OFFSET]
    if shared:
        print(
            f"note: seeds {shared} are also layouts of `gym-coffee evaluate` (seeds "
            f"{EVAL_SEED_OFFSET}+S...); an evaluation there is not on held-out layouts",
            file=sys.stderr,
        )
    if args.video is not None:
        path = record_video(
            env_id,
            demos[0],
            args.video,
            env_kwargs=env_kwargs,
            progress=not args.no_progress,
            overwrite=args.force,
        )
        print(f"wrote {path}")
    return 0


VIDEO_FRAME_STRIDE = 2
"""Render every 2nd control step for ``--video`` (played back at half the control rate, so in real
time): the headless TinyRenderer takes ~0.1-0.2 s per frame."""
VIDEO_MAX_FRAMES: int | None = None
"""Stop a ``--video`` after this many frames (``None``: the whole demonstration)."""


def record_video(
    env_id: str,
    demo: Demonstration,
    path: Path,
    *,
    stride: int = VIDEO_FRAME_STRIDE,
    max_frames: int | None = None,
    env_kwargs: dict[str, Any] | None = None,
    progress: bool = False,
    overwrite: bool = False,
) -> Path:
    """Replay ``demo``'s actions in a fresh ``rgb_array`` env and write every ``stride``-th frame.

    The replay is exact because the env is deterministic for a given seed and action sequence.
    The video plays in real time (``render_fps / stride`` frames per second).
    """
    import gymnasium as gym

    from gym_coffee.video import write_video

    if max_frames is None:
        max_frames = VIDEO_MAX_FRAMES
    env = gym.make(env_id, render_mode="rgb_array", **(env_kwargs or {}))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=demo.n_steps - 1, desc=f"rendering {path.name}", unit="step")
    try:
        env.reset(seed=demo.seed)
        frames: list[Any] = [env.render()]
        for t, action in enumerate(demo.actions[:-1], start=1):  # the last one was not applied
            if max_frames is not None and len(frames) >= max_frames:
                break
            if bar is not None:
                bar.update(1)
            _, _, terminated, truncated, _ = env.step(action)
            if t % stride == 0 or terminated or truncated:
                frames.append(env.render())
            if terminated or truncated:
                break
        fps = float(env.metadata.get("render_fps") or 25) / stride
    finally:
        env.close()
        if bar is not None:
            bar.close()
    return write_video(path, frames, fps=fps, overwrite=overwrite)


def _add_debug_option(p: argparse.ArgumentParser, default: Any) -> None:
    p.add_argument(
        "--debug",
        action="store_true",
        default=default,
        help="show the full traceback of an error (default: one line)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The ``gym-coffee`` parser: ``record``, ``fit``, ``evaluate``, ``run`` and the subcommands
    of the optional modules (``finetune``; ``teleop`` and ``export``)."""
    parser = ArgumentParser(
        prog="gym-coffee",
        description="Coffee-task environment and learning from demonstration with local GPs. "
        "Exit codes: 0 done, 1 the work failed, 2 bad input, 130 interrupted.",
    )
    _add_debug_option(parser, False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=ArgumentParser)
    sub.required = True
    add_record_subcommand(sub)
    add_subcommands(sub)
    for p in sub.choices.values():  # --debug also after the command name
        _add_debug_option(p, argparse.SUPPRESS)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``gym-coffee``; return the exit code (errors are one line on stderr, see
    :mod:`lgp_policy.app._common`)."""
    parser = build_parser()
    try:
        args = parser.parse_args(sys.argv[1:] if argv is None else list(argv))
    except KeyboardInterrupt:
        sys.stderr.write("gym-coffee: interrupted\n")
        return 130
    return run_command(args.func, args)


if __name__ == "__main__":
    sys.exit(main())
