"""The ``gym-coffee`` command line.

The single entry point of the application layer: ``record`` lives here; ``fit``, ``evaluate``,
``run`` and ``finetune`` are added by :func:`lgp_policy.app.commands.add_subcommands`.

Example:
    $ gym-coffee record --n 4 --out demos.npz --seed 0 --video demo.mp4
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lgp_policy.app.commands import add_subcommands

if TYPE_CHECKING:
    from gym_coffee.demonstrations import Demonstration

DEFAULT_ENV_ID = "gym_coffee/CoffeeTask-v0"


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


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
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--n", type=_positive_int, default=4, help="number of demonstrations")
    p.add_argument("--out", type=Path, required=True, help="output .npz file")
    p.add_argument(
        "--seed",
        type=_non_negative_int,
        default=0,
        help="first layout seed (keep it below 10000: evaluation uses 10000+)",
    )
    p.add_argument("--force", action="store_true", help="overwrite an existing --out file")
    p.add_argument(
        "--video",
        type=Path,
        default=None,
        help="also write a video (.mp4 or .gif) of the first demonstration, replayed",
    )
    p.add_argument("--env-id", default=DEFAULT_ENV_ID, help="Gymnasium env id")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=cmd_record)
    return p


def cmd_record(args: argparse.Namespace) -> int:
    import gymnasium as gym

    import gym_coffee  # noqa: F401  (registers the env ids)
    from gym_coffee.demonstrations import collect_demonstrations

    out: Path = args.out
    if out.exists() and not args.force:
        print(f"gym-coffee record: error: {out} exists; pass --force to overwrite", file=sys.stderr)
        return 2
    if out.parent and not out.parent.is_dir():
        print(f"gym-coffee record: error: folder {out.parent} does not exist", file=sys.stderr)
        return 2
    if args.video is not None:
        from gym_coffee.video import check_video_path

        try:
            check_video_path(args.video)
        except ValueError as exc:
            print(f"gym-coffee record: error: {exc}", file=sys.stderr)
            return 2

    env = gym.make(args.env_id)
    try:
        demos = collect_demonstrations(env, n=args.n, seed=args.seed, progress=not args.no_progress)
    except RuntimeError as exc:
        print(f"gym-coffee record: error: {exc}", file=sys.stderr)
        return 1
    finally:
        env.close()
    demos.save(out, overwrite=args.force)
    n_steps = [d.n_steps for d in demos]
    print(f"saved {len(demos)} demonstrations (seeds {demos.seeds}, {sum(n_steps)} steps) to {out}")
    failed = demos.metadata.get("failed_seeds") or []
    if failed:
        print(f"the teacher failed on seeds {failed}; they were skipped")
    if args.video is not None:
        path = record_video(args.env_id, demos[0], args.video, progress=not args.no_progress)
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
        frames = [env.render()]
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
    return write_video(path, frames, fps=fps)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gym-coffee",
        description="Coffee-task environment and learning from demonstration with local GPs.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    add_record_subcommand(sub)
    add_subcommands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else list(argv))
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
