"""What every ``gym-coffee`` subcommand shares: argument types that check values while parsing,
output checks that run before any work (the one overwrite rule, ``--force``), and the one error
path (``gym-coffee CMD: error: ...``, exit code 2; ``--debug`` shows the traceback).

Exit codes: 0 success; 1 the work failed (e.g. the disk is full, the teacher failed on every
layout, an optional package is missing); 2 bad input (an argument or an input file); 130
interrupted (Ctrl-C). See ``docs/files-and-errors.md``.

Other modules that add subcommands (``finetune``, ``teleop``, ``export``) use these helpers and
raise :class:`ValueError` (or :class:`FileExistsError`, :class:`FileNotFoundError`) for bad input;
:func:`run_command` turns any of them into the one line.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys
import tempfile
import traceback
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, NoReturn

import gym_coffee
from lgp_policy._io import check_creatable, check_output_path

__all__ = [
    "EXIT_FAILURE",
    "EXIT_INTERRUPTED",
    "EXIT_USAGE",
    "MAX_DEMOS",
    "MAX_SEED",
    "ArgumentParser",
    "UsageError",
    "add_env_options",
    "add_force_option",
    "check_env_id",
    "check_output",
    "check_output_folder",
    "check_seed_room",
    "check_video_output",
    "demos_int",
    "env_id_from_args",
    "finite_float",
    "input_file",
    "int_range",
    "non_negative_int",
    "positive_int",
    "run_command",
    "seed_int",
    "set_aside",
]

PROG = "gym-coffee"
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
MAX_SEED = 2**31 - 1
"""Largest seed any layout may get (seeds are also offset, e.g. ``10000 + S + i``)."""
MAX_DEMOS = 10_000
"""Most demonstrations one command records (``record --n``, ``run --demos``)."""
VIDEO_SUFFIXES = (".mp4", ".gif")
"""Video formats (``gym_coffee.video.VIDEO_SUFFIXES``; ``.mp4`` needs ``imageio-ffmpeg``)."""


class UsageError(ValueError):
    """Bad command-line input; the message names the argument (``argument --out: ...``)."""


class ArgumentParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose errors are one line (no usage block):
    ``gym-coffee CMD: error: <message> (see gym-coffee CMD --help)``, exit code 2."""

    def error(self, message: str) -> NoReturn:
        sys.stderr.write(f"{self.prog}: error: {message} (see '{self.prog} --help')\n")
        sys.exit(EXIT_USAGE)


# ----------------------------------------------------------------------- argument types
def int_range(lo: int, hi: int | None = None, *, what: str = "an integer") -> Callable[[str], int]:
    """An argparse ``type`` accepting integers in ``[lo, hi]``."""
    bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"

    def parse(text: str) -> int:
        try:
            value = int(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what} {bound}, got {text!r}") from None
        if value < lo or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"expected {what} {bound}, got {value}")
        return value

    parse.__name__ = what
    return parse


positive_int = int_range(1, None, what="an integer")
non_negative_int = int_range(0, None, what="an integer")
demos_int = int_range(1, MAX_DEMOS, what="a number of demonstrations")
seed_int = int_range(0, MAX_SEED, what="a seed")


def finite_float(
    lo: float = -math.inf, hi: float = math.inf, *, lo_open: bool = False
) -> Callable[[str], float]:
    """An argparse ``type`` accepting finite floats in ``[lo, hi]`` (``(lo, hi]`` if
    ``lo_open``); NaN and inf are refused."""
    left = "(" if lo_open else "["
    bound = f"in {left}{lo:g}, {hi:g}]"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number {bound}, got {text!r}") from None
        if not math.isfinite(value) or value < lo or value > hi or (lo_open and value == lo):
            raise argparse.ArgumentTypeError(f"expected a finite number {bound}, got {text!r}")
        return value

    parse.__name__ = "number"
    return parse


def input_file(*suffixes: str) -> Callable[[str], Path]:
    """An argparse ``type`` for a file to read: it must exist, be a readable file and (if
    ``suffixes`` are given) end in one of them."""

    def parse(text: str) -> Path:
        path = Path(text)
        if suffixes and path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(
                f"expected a {' or '.join(suffixes)} file, got {text!r}"
            )
        if not path.exists():
            raise argparse.ArgumentTypeError(f"no such file: {text}")
        if not path.is_file():
            raise argparse.ArgumentTypeError(f"{text} is not a file")
        if not os.access(path, os.R_OK):
            raise argparse.ArgumentTypeError(f"{text} is not readable")
        return path

    parse.__name__ = "file"
    return parse


def check_seed_room(seed: int, count: int, flag: str, value: int) -> None:
    """Raise :class:`UsageError` naming ``--seed`` unless seeds ``seed .. seed + count`` fit
    below :data:`MAX_SEED` (``count`` seeds are used with ``flag value``)."""
    if seed + count > MAX_SEED:
        raise UsageError(
            f"argument --seed: expected at most {MAX_SEED - count} with {flag} {value}, got {seed}"
        )


# ------------------------------------------------------------------ environment: level or id
def check_env_id(env_id: str) -> str:
    """Raise :class:`UsageError` naming ``--env-id`` unless it is a registered coffee env id
    (:data:`gym_coffee.ENV_IDS`, one per level)."""
    if env_id not in gym_coffee.ENV_IDS:
        raise UsageError(
            f"argument --env-id: expected one of {list(gym_coffee.ENV_IDS)} (or use --level "
            f"{'/'.join(gym_coffee.LEVELS)}), got {env_id!r}"
        )
    return env_id


def add_env_options(
    p: argparse.ArgumentParser, what: str = "the layouts", *, from_policy: bool = False
) -> None:
    """Add ``--level`` (a name of :data:`gym_coffee.LEVELS`) and ``--env-id`` (a registered id),
    mutually exclusive, read with :func:`env_id_from_args`, and ``--physics`` (a preset of
    :data:`gym_coffee.PHYSICS_PRESETS`), read with :func:`env_kwargs_from_args`.
    ``from_policy``: the defaults are the env of a policy's demonstrations (the help says so)."""
    g = p.add_mutually_exclusive_group()
    levels = ", ".join(f"{name}: {env_id}" for name, env_id in gym_coffee.LEVELS.items())
    first = "the level of the policy's demonstrations, else " if from_policy else ""
    g.add_argument(
        "--level",
        choices=list(gym_coffee.LEVELS),
        default=None,
        help=f"difficulty level of {what} ({levels}; default {first}{_default_level()})",
    )
    g.add_argument(
        "--env-id",
        default=None,
        metavar="ID",
        help=f"registered env id of {what}, instead of --level (default {first}"
        f"{gym_coffee.ENV_ID})",
    )
    first = "that of the policy's demonstrations, else " if from_policy else ""
    p.add_argument(
        "--physics",
        choices=list(gym_coffee.PHYSICS_PRESETS),
        default=None,
        help=f"physics preset of {what} (default: {first}the task's physics; fast: 5 physics "
        "steps of 8 ms with 20 solver iterations, ~40%% less CPU per step, other trajectories)",
    )


def _default_level() -> str:
    return next(name for name, env_id in gym_coffee.LEVELS.items() if env_id == gym_coffee.ENV_ID)


def env_id_from_args(args: argparse.Namespace) -> str:
    """The env id chosen with :func:`add_env_options` (``--level`` through
    :data:`gym_coffee.LEVELS`, a checked ``--env-id``, or :data:`gym_coffee.ENV_ID`).

    Raises:
        UsageError: ``--env-id`` is not a registered coffee env id.
    """
    level = getattr(args, "level", None)
    if level is not None:
        return gym_coffee.LEVELS[level]
    env_id = getattr(args, "env_id", None)
    return gym_coffee.ENV_ID if env_id is None else check_env_id(env_id)


def env_kwargs_from_args(args: argparse.Namespace, default: str = "default") -> dict[str, Any]:
    """The env keywords chosen with :func:`add_env_options` (``{}`` for the default physics);
    ``default``: the physics preset when ``--physics`` is not given."""
    physics = getattr(args, "physics", None) or default
    return {} if physics == "default" else {"physics": physics}


# ------------------------------------------------------------- outputs: one overwrite rule
class _DeprecatedOverwrite(argparse.Action):
    def __call__(self, parser: Any, namespace: Any, values: Any, option: Any = None) -> None:
        print(f"{parser.prog}: warning: --overwrite is deprecated; use --force", file=sys.stderr)
        namespace.force = True


def add_force_option(p: argparse.ArgumentParser, what: str = "output files") -> None:
    """Add ``--force`` (overwrite existing outputs) and the hidden deprecated ``--overwrite``."""
    p.add_argument("--force", action="store_true", help=f"overwrite existing {what}")
    p.add_argument("--overwrite", nargs=0, action=_DeprecatedOverwrite, help=argparse.SUPPRESS)


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_output(
    flag: str,
    path: str | os.PathLike[str],
    *,
    force: bool,
    suffixes: tuple[str, ...] | None = None,
    inputs: Iterable[Path] = (),
) -> Path:
    """Check an output file before any work (see :func:`lgp_policy._io.check_output_path`).

    Raises:
        UsageError: ``argument FLAG: ...``: wrong suffix, exists without ``--force``, a folder,
            not writable, or the same file as one of ``inputs``.
    """
    path = Path(path)
    for source in inputs:
        if _same_file(path, source) or path.absolute() == Path(source).absolute():
            raise UsageError(f"argument {flag}: {path} is also an input; choose another name")
    try:
        return check_output_path(path, force=force, suffixes=suffixes, what="output")
    except FileExistsError:
        raise UsageError(f"argument {flag}: {path} exists; pass --force to overwrite it") from None
    except ValueError as exc:
        raise UsageError(f"argument {flag}: {exc}") from None


def check_video_output(flag: str, path: str | os.PathLike[str], *, force: bool) -> Path:
    """:func:`check_output` for a video, and for ``.mp4`` that its encoder is installed."""
    path = check_output(flag, path, force=force, suffixes=VIDEO_SUFFIXES)
    if path.suffix.lower() == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise UsageError(
            f"argument {flag}: writing .mp4 needs the imageio-ffmpeg package "
            "(pip install imageio-ffmpeg); or use a .gif name"
        )
    return path


def check_output_folder(
    flag: str, path: str | os.PathLike[str], *, force: bool, owned: Iterable[str]
) -> list[Path]:
    """Check an output folder before any work; return the earlier files it would replace.

    A new or empty folder is fine. A folder with files needs ``force``; then the files named in
    ``owned`` (those the command writes) are returned, to be set aside (:func:`set_aside`) so
    that the folder never mixes the outputs of two runs; other files are left alone.

    Raises:
        UsageError: ``path`` is a file, not writable, or a non-empty folder without ``force``;
            a name in ``owned`` is a folder.
    """
    path = Path(path)
    if path.is_symlink() and not path.exists():
        raise UsageError(f"argument {flag}: {path} is a link to nothing; expected a folder")
    if path.exists() and not path.is_dir():
        raise UsageError(f"argument {flag}: {path} is a file; expected a folder")
    if path.is_dir():
        entries = sorted(p.name for p in path.iterdir())
        if entries and not force:
            shown = ", ".join(entries[:5]) + (", ..." if len(entries) > 5 else "")
            raise UsageError(
                f"argument {flag}: folder {path} is not empty ({shown}); pass --force to "
                "replace the files this command writes there, or choose a new folder"
            )
        if not os.access(path, os.W_OK | os.X_OK):
            raise UsageError(f"argument {flag}: folder {path} is not writable")
        present = [path / name for name in owned if os.path.lexists(path / name)]
        for file in present:
            if file.is_dir() and not file.is_symlink():
                raise UsageError(
                    f"argument {flag}: {file} is a folder; this command writes a file there"
                )
        return present
    try:  # a new folder: its nearest existing parent must be writable
        check_creatable(path, f"output folder {path}")
    except ValueError as exc:
        raise UsageError(f"argument {flag}: {exc}") from None
    return []


def set_aside(files: list[Path], folder: Path) -> Path | None:
    """Move ``files`` (an earlier run's, in ``folder``) into a new hidden subfolder of ``folder``
    (``.previous-run-*``, renames only); return it, or ``None`` when there are none. The caller
    removes it once the new outputs are complete, and otherwise leaves it for the user."""
    if not files:
        return None
    aside = Path(tempfile.mkdtemp(prefix=".previous-run-", dir=folder))
    for file in files:
        os.replace(file, aside / file.name)
    return aside


# ----------------------------------------------------------------------- the one error path
_INPUT_ERRORS = (ValueError, FileExistsError, FileNotFoundError, IsADirectoryError, PermissionError)


def describe_error(exc: BaseException) -> tuple[int, str]:
    """``(exit code, one-line message)`` for an exception that ended a command."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        text = f"{exc.filename}: {exc.strerror}"
    else:
        text = str(exc) or type(exc).__name__
    text = " ".join(text.split())  # one line
    if isinstance(exc, _INPUT_ERRORS):
        return EXIT_USAGE, text
    if isinstance(exc, MemoryError):
        return EXIT_FAILURE, f"out of memory ({text})"
    if isinstance(exc, (OSError, RuntimeError, ImportError)):
        return EXIT_FAILURE, text
    return EXIT_FAILURE, (
        f"internal error: {type(exc).__name__}: {text} (rerun with --debug for the traceback "
        "and please report it)"
    )


def run_command(func: Callable[[argparse.Namespace], int | None], args: argparse.Namespace) -> int:
    """Run a subcommand; map any error to one line on stderr and an exit code."""
    command = f"{PROG} {getattr(args, 'command', '')}".strip()
    debug = bool(getattr(args, "debug", False))
    try:
        return int(func(args) or 0)
    except KeyboardInterrupt:
        if debug:
            traceback.print_exc()
        sys.stderr.write(
            f"\n{command}: interrupted; finished files are kept, partial ones removed\n"
        )
        return EXIT_INTERRUPTED
    except Exception as exc:
        if debug:
            traceback.print_exc()
        code, text = describe_error(exc)
        sys.stderr.write(f"{command}: error: {text}\n")
        return code
