"""Shared pieces of the command-line interface."""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn

from ermrl.storage import DEFAULT_STORAGE

__all__ = [
    "ArgumentParser",
    "fail",
    "add_storage_args",
    "positive_int",
    "nonneg_int",
    "positive_float",
]

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143


def quiet_libraries() -> None:
    """Keep the terminal for ermrl's own progress lines: Optuna logs warnings only."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)


def fail(prog: str, message: str, code: int = EXIT_USAGE) -> NoReturn:
    """Print a one-line error and exit (code 2: bad input)."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    raise SystemExit(code)


class ArgumentParser(argparse.ArgumentParser):
    """``argparse`` with one-line errors (``prog: error: ... (see --help)``) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        fail(self.prog, f"{message} (see --help)")


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Shows defaults and keeps the description's line breaks."""


def positive_int(text: str) -> int:
    try:
        value = int(float(text)) if "e" in text.lower() else int(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from err
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def nonneg_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from err
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from err
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def add_storage_args(parser: argparse.ArgumentParser, *, study_required: bool) -> None:
    parser.add_argument(
        "--storage",
        default=DEFAULT_STORAGE,
        help="Optuna storage URL: sqlite:///file.db (embedded default), postgresql://user@host/db, "
        "mysql+pymysql://..., journal:///file.log (or file.log), redis://host:port",
    )
    parser.add_argument(
        "--study-name",
        required=study_required,
        default=None,
        help="study name"
        + ("" if study_required else " (default: derived from env, mask and budget)"),
    )
