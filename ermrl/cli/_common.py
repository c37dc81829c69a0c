"""Shared pieces of the command-line interface: one-line errors, exit codes, progress mode.

The options' own pieces (the parser class, its types and shared flags) live below the CLI, in
`ermrl.runner._options`, since experiment files check their stages with them; they are
re-exported here.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, NoReturn, TypeVar

from ermrl.runner._commands import (
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
    EXIT_USAGE,
    dashboard_line,
    quiet_libraries,
)
from ermrl.runner._options import (
    PROGRESS_DEFAULT_HELP,
    ArgumentParser,
    HelpFormatter,
    add_progress_arg,
    add_storage_args,
    nonneg_int,
    positive_int,
    storage_arg,
    study_name_arg,
)
from ermrl.runner._resolve import for_learner_names, learner_overrides
from ermrl.test_phase import parse_for_learner

__all__ = [
    "ArgumentParser",
    "HelpFormatter",
    "fail",
    "add_storage_args",
    "storage_arg",
    "study_name_arg",
    "parse_for_learner",
    "for_learner_names",
    "learner_overrides",
    "add_run_folder_args",
    "run_folder_kwargs",
    "positive_int",
    "nonneg_int",
    "PROGRESS_DEFAULT_HELP",
    "add_progress_arg",
    "progress_mode",
    "dashboard_line",
    "exit_on_failure",
    "quiet_libraries",
    "EXIT_INTERRUPTED",
    "EXIT_TERMINATED",
    "EXIT_USAGE",
]

if TYPE_CHECKING:
    from ermrl._progress import ProgressMode

T = TypeVar("T")


def fail(prog: str, message: str, code: int = EXIT_USAGE) -> NoReturn:
    """Print a one-line error and exit (code 2: bad input)."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    raise SystemExit(code)


def exit_on_failure(prog: str, run: Callable[[], T]) -> T:
    """``run()``, whose `CommandFailed` becomes its one-line
    error on stderr and its exit code (`fail`)."""
    from ermrl.runner._commands import CommandFailed

    try:
        return run()
    except CommandFailed as err:
        if err.message is None:
            raise SystemExit(err.code) from None
        fail(prog, err.message, err.code)


def progress_mode(args: argparse.Namespace) -> ProgressMode:
    """``args.progress``, or the default for where stdout goes (see `add_progress_arg`)."""
    from ermrl._progress import default_mode

    value = getattr(args, "progress", None)
    return default_mode() if value is None else value


def add_run_folder_args(parser: argparse.ArgumentParser, *, agent_help: str, out_help: str) -> None:
    """Add the options that pick one episode of a trained agent in a test-phase folder.

    Shared by ``ermrl dynamics`` and ``ermrl video``. Adds, in this order: ``--run``,
    ``--agent``, ``--seed``, ``--out``, ``--max-steps``, ``--env-seed`` and
    ``--deterministic/--no-deterministic``.

    Args:
        parser: the command's parser.
        agent_help: help of ``--agent`` (what the command does with the agent).
        out_help: help of ``--out`` (each command writes its own kind of output).
    """
    parser.add_argument("--run", required=True, help="test-phase folder (--out of ermrl test)")
    parser.add_argument("--agent", default="res-ppo", help=agent_help)
    parser.add_argument(
        "--seed",
        type=nonneg_int,
        default=None,
        help="run seed (default: the smallest seed with a saved model)",
    )
    parser.add_argument("--out", default=None, help=out_help)
    parser.add_argument(
        "--max-steps", type=positive_int, default=None, help="stop the episode after N steps"
    )
    parser.add_argument(
        "--env-seed",
        type=nonneg_int,
        default=None,
        help="seed of the episode (default: the run's evaluation seed)",
    )
    parser.add_argument(
        "--deterministic",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="take the policy's mean action (--no-deterministic samples)",
    )


def run_folder_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The options of `add_run_folder_args` (except ``--out``) as keyword arguments.

    Args:
        args: parsed arguments of a parser given `add_run_folder_args`.

    Returns:
        ``run``, ``agent``, ``seed``, ``max_steps``, ``deterministic`` and ``env_seed``, the
        keyword arguments shared by
        [`ermrl.analysis.record_dynamics`][ermrl.analysis.record_dynamics] and
        [`ermrl.analysis.record_video`][ermrl.analysis.record_video].
    """
    return {
        "run": args.run,
        "agent": args.agent,
        "seed": args.seed,
        "max_steps": args.max_steps,
        "deterministic": args.deterministic,
        "env_seed": args.env_seed,
    }
