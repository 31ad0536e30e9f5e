"""Subcommands of ``gym-coffee`` that belong to the learning side."""

from __future__ import annotations

import argparse


def add_subcommands(subparsers: argparse._SubParsersAction) -> None:
    """Add ``fit``, ``evaluate``, ``run`` and ``finetune`` to the ``gym-coffee`` parser."""
