"""The ``gym-coffee`` command line.

``record`` lives here; ``fit``, ``evaluate``, ``run`` and ``finetune`` are added by
:func:`lgp_policy.cli.add_subcommands`.
"""

from __future__ import annotations

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gym-coffee",
        description="Coffee-task environment and learning from demonstration with local GPs.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    from lgp_policy.cli import add_subcommands

    add_subcommands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
