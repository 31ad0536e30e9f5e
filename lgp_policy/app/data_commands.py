"""``gym-coffee teleop``, ``export`` and ``import``: demonstrations by hand, datasets out and in.

Added to the ``gym-coffee`` command line by :func:`add_subcommands`. Bad input raises
:class:`ValueError` (or ``FileExistsError``/``FileNotFoundError``) before any work; the CLI's one
error path prints it as one line and exits with code 2.

Examples:
    $ gym-coffee teleop --out my_demos.npz --n 3             # keyboard, PyBullet GUI
    $ gym-coffee export my_demos.npz --format robomimic --out my_demos.hdf5
    $ gym-coffee export my_demos.npz --format minari --out coffee/my-demos-v0
    $ gym-coffee import my_demos.hdf5 --out again.npz
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lgp_policy.app._common import (
    UsageError,
    add_force_option,
    check_output,
    finite_float,
    input_file,
    positive_int,
    seed_int,
)

__all__ = ["add_subcommands", "cmd_export", "cmd_import", "cmd_teleop"]

TELEOP_DEVICES = ("keyboard", "spacemouse", "waypoints")
"""``--device`` choices: a person at the keyboard or a SpaceMouse (both in the PyBullet GUI), or
the scripted operator (:class:`gym_coffee.teleop.WaypointInput`: no person, headless unless
``--gui``)."""
TELEOP_MAX_STEPS = 3000
"""Default time limit of a teleoperated episode (steps of 0.04 s: 2 minutes)."""
ROBOMIMIC_SUFFIXES = (".hdf5", ".h5")


def add_subcommands(subparsers: argparse._SubParsersAction) -> None:
    """Add ``teleop``, ``export`` and ``import`` to the ``gym-coffee`` subcommands."""
    import gym_coffee
    from gym_coffee.teleop import TELEOP_ACTION_TYPES

    p = subparsers.add_parser(
        "teleop",
        help="record demonstrations by hand (keyboard or SpaceMouse in the PyBullet GUI)",
        description=(
            "Teach the coffee task by hand: move the gripper with the keyboard (or a SpaceMouse) "
            "in the PyBullet window, keep or discard each episode, and save the kept ones in the "
            "same .npz format as `gym-coffee record` (actions in the end-effector mode used). "
            "The window shows the keys, the stage flags and whether the episode succeeded. "
            "See docs/human-demonstrations.md."
        ),
    )
    p.add_argument("--out", type=Path, required=True, help="output .npz file")
    p.add_argument("--n", type=positive_int, default=1, help="episodes to keep (default 1)")
    p.add_argument("--seed", type=seed_int, default=0, help="layout seed of the first episode")
    p.add_argument("--device", choices=TELEOP_DEVICES, default="keyboard", help="input device")
    p.add_argument(
        "--action-type",
        choices=TELEOP_ACTION_TYPES,
        default="ee_rot",
        help="end-effector mode: ee_rot turns the hand too (needed for the side grasp); "
        "ee keeps it pointing down",
    )
    p.add_argument(
        "--speed",
        type=finite_float(0.0, 1.0, lo_open=True),
        default=0.5,
        help="fraction of the largest step per key press (0.02 m, 0.05 rad; default 0.5)",
    )
    p.add_argument(
        "--max-steps",
        type=positive_int,
        default=TELEOP_MAX_STEPS,
        help=f"time limit per episode in steps of 0.04 s (default {TELEOP_MAX_STEPS})",
    )
    p.add_argument("--env-id", default=gym_coffee.ENV_ID, help="Gymnasium env id")
    p.add_argument("--gui", action="store_true", help="show the GUI for --device waypoints")
    add_force_option(p, "--out file")
    p.set_defaults(func=cmd_teleop)

    p = subparsers.add_parser(
        "export",
        help="write demonstrations as a robomimic HDF5 file or a Minari dataset",
        description=(
            "Export a demonstration file to robomimic's HDF5 layout (data/demo_i/obs/<key>, "
            "actions, rewards, dones, env_args; --out FILE.hdf5) or to a Minari dataset "
            "(--out DATASET_ID, e.g. coffee/teleop-v0, under --minari-root or "
            "$MINARI_DATASETS_PATH). Needs the datasets extra: pip install 'gym-coffee[datasets]'."
        ),
    )
    p.add_argument("demos", type=input_file(".npz"), help="demonstration .npz file")
    p.add_argument("--format", choices=("robomimic", "minari"), required=True)
    p.add_argument("--out", required=True, help="robomimic: .hdf5 file; minari: dataset id")
    p.add_argument(
        "--valid-fraction",
        type=finite_float(0.0, 0.99),
        default=0.1,
        help="robomimic: fraction of demonstrations in mask/valid (default 0.1; 0: no mask)",
    )
    p.add_argument("--minari-root", type=Path, default=None, help="minari: datasets folder")
    add_force_option(p, "--out file or dataset")
    p.set_defaults(func=cmd_export)

    p = subparsers.add_parser(
        "import",
        help="read a robomimic HDF5 file written by `export` back into a demonstration file",
        description=(
            "Read a robomimic HDF5 file written by `gym-coffee export --format robomimic` and save "
            "it as a demonstration .npz file (exactly the arrays that were exported)."
        ),
    )
    p.add_argument("file", type=input_file(*ROBOMIMIC_SUFFIXES), help="robomimic .hdf5 file")
    p.add_argument("--out", type=Path, required=True, help="output .npz file")
    add_force_option(p, "--out file")
    p.set_defaults(func=cmd_import)


def _check_env_id(env_id: str) -> None:
    import gymnasium as gym

    if env_id not in gym.registry or not env_id.startswith("gym_coffee/"):
        import gym_coffee

        raise UsageError(
            f"argument --env-id: {env_id!r} is not a gym_coffee environment; "
            f"expected one of {gym_coffee.ENV_IDS}"
        )


def cmd_teleop(args: argparse.Namespace) -> int:
    import gymnasium as gym

    from gym_coffee.simulation import display_available
    from gym_coffee.teleop import KeyboardInput, SpaceMouseInput, WaypointInput, record_teleop

    out = check_output("--out", args.out, force=args.force, suffixes=(".npz",))
    _check_env_id(args.env_id)
    person = args.device != "waypoints"
    gui = person or args.gui
    if gui and not display_available():
        raise UsageError(
            f"argument --device: {args.device} needs the PyBullet window, and no display is "
            "available (set DISPLAY, or use --device waypoints without --gui)"
        )
    device: Any
    if args.device == "keyboard":
        device = KeyboardInput(speed=args.speed)
    elif args.device == "spacemouse":
        device = SpaceMouseInput(speed=args.speed)  # ImportError names the teleop extra
    else:
        device = WaypointInput(variation=1.0)
    env = gym.make(
        args.env_id,
        render_mode="human" if gui else None,
        action_type=args.action_type,
        max_episode_steps=args.max_steps,
    )

    def report(i: int, demo: Any, decision: str) -> None:
        what = f"{demo.n_steps} steps, success={demo.success}" if demo is not None else ""
        print(f"episode {i + 1}: {decision} {what}".rstrip(), flush=True)

    if person:
        print(
            "teleop: keys are shown in the PyBullet window (enter: keep, backspace: discard, "
            "escape: quit)",
            flush=True,
        )
    try:
        demos = record_teleop(env, device, n=args.n, seed=args.seed, on_episode=report)
    finally:
        env.close()
    if not len(demos):
        raise RuntimeError("no episode was kept; nothing written")
    demos.save(out, overwrite=args.force)
    ok = sum(d.success for d in demos)
    print(f"saved {len(demos)} demonstrations ({ok} successful, seeds {demos.seeds}) to {out}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from gym_coffee.demonstrations import DemonstrationSet

    if args.format == "robomimic":
        if args.minari_root is not None:
            raise UsageError("argument --minari-root: only with --format minari")
        out = check_output(
            "--out", args.out, force=args.force, suffixes=ROBOMIMIC_SUFFIXES, inputs=[args.demos]
        )
        from gym_coffee.datasets import export_robomimic

        demos = DemonstrationSet.load(args.demos)
        path = export_robomimic(
            demos, out, overwrite=args.force, valid_fraction=args.valid_fraction
        )
    else:
        from gym_coffee.datasets import export_minari

        _check_minari_output(args.out, args.minari_root, args.force)
        demos = DemonstrationSet.load(args.demos)
        path = export_minari(demos, args.out, root=args.minari_root, overwrite=args.force)
    print(f"exported {len(demos)} demonstrations to {path}")
    return 0


def _check_minari_output(dataset_id: str, root: Path | None, force: bool) -> None:
    try:
        from minari.dataset.minari_dataset import parse_dataset_id
        from minari.storage import get_dataset_path
    except ImportError as exc:
        raise ImportError(
            "export to Minari needs the optional package 'minari': "
            'pip install "gym-coffee[datasets]"'
        ) from exc
    try:
        parse_dataset_id(dataset_id)
    except ValueError:
        raise UsageError(
            f"argument --out: {dataset_id!r} is not a Minari dataset id; expected "
            "(namespace/)name-v<version>, e.g. coffee/teleop-v0"
        ) from None
    folder = Path(get_dataset_path() if root is None else root) / dataset_id
    if folder.exists() and not force:
        raise UsageError(
            f"argument --out: Minari dataset {dataset_id} exists ({folder}); pass --force to "
            "replace it"
        )


def cmd_import(args: argparse.Namespace) -> int:
    from gym_coffee.datasets import import_robomimic

    out = check_output("--out", args.out, force=args.force, suffixes=(".npz",), inputs=[args.file])
    demos = import_robomimic(args.file)
    demos.save(out, overwrite=args.force)
    print(f"imported {len(demos)} demonstrations ({demos.action_type} actions) to {out}")
    return 0
