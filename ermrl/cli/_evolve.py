"""``ermrl evolve`` / ``evolve_res.py``: evolve reservoirs for one task.

The command's options are defined in `ermrl.runner._parsers` (experiment files check their
``evolve:`` stage with the same parser); this module parses argv, runs the evolution and turns
its failures into one-line errors and exit codes.
"""

from __future__ import annotations

import shlex
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from ermrl.cli._common import exit_on_failure, fail, quiet_libraries
from ermrl.config import ConfigError, EvolveConfig
from ermrl.runner import _commands
from ermrl.runner._commands import (
    database_cause,
    interrupted_message,
    print_backend_notes,
    study_write_failure,
)
from ermrl.runner._parsers import add_problem_args, add_search_args, build_evolve_parser
from ermrl.runner._resolve import (
    check_tensorboard,
    config_from_args,
    keep_study_backend,
    learner_flags,
    space_from_args,
    stored_backend,
)

if TYPE_CHECKING:
    import optuna

__all__ = [
    "build_evolve_parser",
    "add_problem_args",
    "add_search_args",
    "command_line",
    "config_from_args",
    "evolve_main",
    "keep_study_backend",
    "learner_flags",
    "check_tensorboard",
    "check_wandb",
    "database_cause",
    "interrupted_message",
    "print_backend_notes",
    "study_write_failure",
    "run_and_report",
    "space_from_args",
    "stored_backend",
]


def command_line(prog: str, argv: Sequence[str] | None) -> str:
    """The command as it can be pasted back into a shell (stored in the study).

    Each word of ``prog`` stays a word (``ermrl evolve --env-id ...``, not
    ``'ermrl evolve' --env-id ...``); a root script keeps its file name only.

    Args:
        prog: the program name, e.g. ``"ermrl evolve"`` or ``"evolve_res.py"``.
        argv: the arguments (``None``: ``sys.argv[1:]``).
    """
    words = prog.split()
    return shlex.join(
        [
            *(words[-1:] if prog.endswith(".py") else words),
            *(argv if argv is not None else sys.argv[1:]),
        ]
    )


def check_wandb(prog: str, project: str | None) -> None:
    """``--wandb`` without its packages: one line, before anything is written."""
    exit_on_failure(prog, lambda: _commands.check_wandb(project))


def run_and_report(prog: str, config: EvolveConfig, study: optuna.Study, **kwargs: Any) -> int:
    """`ermrl.runner._commands.run_and_report`, its one-line errors exiting with code 2."""
    return exit_on_failure(prog, lambda: _commands.run_and_report(prog, config, study, **kwargs))


def evolve_main(argv: Sequence[str] | None = None, prog: str = "ermrl evolve") -> int:
    """Entry point of ``ermrl evolve`` and ``evolve_res.py``."""
    from ermrl.envs import UnknownEnvError, UnsupportedObserveError

    parser = build_evolve_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    check_wandb(prog, args.wandb)
    notes: list[str] = []
    try:
        config = config_from_args(args, notes=notes)
        study_name = args.study_name or config.default_study_name
        args, config = keep_study_backend(
            args, config, args.storage, study_name, config_from_args, notes
        )
    except (ConfigError, UnknownEnvError, UnsupportedObserveError) as err:
        fail(prog, str(err))
    request = _commands.EvolveRequest.from_options(
        config, args.storage, study_name, args, command=command_line(prog, argv), notes=notes
    )
    return exit_on_failure(prog, lambda: _commands.run_evolve(request, prog))
