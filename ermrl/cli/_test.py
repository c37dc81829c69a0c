"""``ermrl test`` / ``test.py``: train the best evolved reservoir against baselines.

The command's options are defined in `ermrl.runner._parsers` (experiment files check their
``test:`` stage with the same parser); this module parses argv, runs the test phase and turns
its failures into one-line errors and exit codes.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from ermrl.cli._common import exit_on_failure, quiet_libraries
from ermrl.runner import _commands
from ermrl.runner._commands import print_notes, setup_errors
from ermrl.runner._parsers import add_tensorboard_arg, add_test_args, build_test_parser
from ermrl.runner._resolve import test_options

if TYPE_CHECKING:
    from ermrl.test_phase import TestPlan

T = TypeVar("T")

__all__ = [
    "add_tensorboard_arg",
    "add_test_args",
    "build_test_parser",
    "print_notes",
    "require_tensorboard",
    "run_or_exit",
    "run_test_phase",
    "setup_errors",
    "test_main",
    "test_options",
]


def run_or_exit(prog: str, out: Path, run: Callable[[], T]) -> T | None:
    """`ermrl.runner._commands.run_or_fail`, its one-line errors exiting with code 2
    (a signal's code after its line)."""
    return exit_on_failure(prog, lambda: _commands.run_or_fail(prog, out, run))


def run_test_phase(
    prog: str,
    args: argparse.Namespace,
    plan: TestPlan,
    task: Any,
    encoder: Any,
    ppo: Any,
    metadata: dict[str, Any],
    *,
    then: Callable[[Any], Any] | None = None,
) -> Any:
    """`ermrl.runner._commands.run_test_phase` with the parsed options' ``--quiet`` and
    command line, its one-line errors exiting with code 2."""
    return exit_on_failure(
        prog,
        lambda: _commands.run_test_phase(
            *(prog, plan, task, encoder, ppo, metadata),
            quiet=args.quiet,
            command=getattr(args, "command_line", None),
            then=then,
        ),
    )


def require_tensorboard(args: argparse.Namespace, prog: str) -> None:
    """Exit 2 in one line when ``--tensorboard`` is given without the tensorboard package."""
    exit_on_failure(prog, lambda: _commands.require_tensorboard(getattr(args, "tensorboard", None)))


def test_main(argv: Sequence[str] | None = None, prog: str = "ermrl test") -> int:
    """Entry point of ``ermrl test`` and ``test.py``."""
    parser = build_test_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    # The command that made the test folder (command.txt): `ermrl test ...` also when `ermrl
    # run` runs this stage.
    command = shlex.join([*prog.split(), *(sys.argv[1:] if argv is None else argv)])
    require_tensorboard(args, prog)
    if args.wandb:
        exit_on_failure(prog, lambda: _commands.check_wandb(args.wandb))
    request = _commands.TestRequest(
        args.study_name, args.storage, test_options(args), args.quiet, command
    )
    return exit_on_failure(prog, lambda: _commands.run_test(request, prog))
