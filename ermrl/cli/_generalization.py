"""``ermrl evolve-generalization`` / ``ermrl test-generalization``: evolve on a set of tasks, test
on a task the reservoirs never saw.

The commands' options are defined in `ermrl.runner._parsers` (experiment files check their
stages with the same parsers).
"""

from __future__ import annotations

import shlex
import sys
from collections.abc import Sequence

from ermrl.cli._common import exit_on_failure, fail, quiet_libraries
from ermrl.cli._evolve import command_line
from ermrl.config import ConfigError
from ermrl.runner import _commands
from ermrl.runner._generalization import (
    TestGeneralizationRequest,
    overlap_warning,
    run_evolve_generalization,
    run_test_generalization,
)
from ermrl.runner._parsers import (
    build_evolve_generalization_parser,
    build_test_generalization_parser,
)
from ermrl.runner._resolve import (
    generalization_config_from_args,
    keep_study_backend,
    test_options,
)

__all__ = [
    "build_evolve_generalization_parser",
    "build_test_generalization_parser",
    "evolve_generalization_main",
    "generalization_config_from_args",
    "overlap_warning",
    "test_generalization_main",
]


# -- evolve-generalization ----------------------------------------------------------------------


def evolve_generalization_main(
    argv: Sequence[str] | None = None, prog: str = "ermrl evolve-generalization"
) -> int:
    """Entry point of ``ermrl evolve-generalization`` and ``evolve_generalization.py``."""
    from ermrl.envs import UnknownEnvError, UnsupportedObserveError
    from ermrl.search import generalization_study_name

    parser = build_evolve_generalization_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    exit_on_failure(prog, lambda: _commands.check_wandb(args.wandb))
    notes: list[str] = []
    try:
        config = generalization_config_from_args(args, notes=notes)
        study_name = args.study_name or generalization_study_name(config)
        args, config = keep_study_backend(
            args, config, args.storage, study_name, generalization_config_from_args, notes
        )
    except (ConfigError, UnknownEnvError, UnsupportedObserveError) as err:
        fail(prog, str(err))
    request = _commands.EvolveRequest.from_options(
        config, args.storage, study_name, args, command=command_line(prog, argv), notes=notes
    )
    return exit_on_failure(prog, lambda: run_evolve_generalization(request, prog))


# -- test-generalization ------------------------------------------------------------------------


def test_generalization_main(
    argv: Sequence[str] | None = None, prog: str = "ermrl test-generalization"
) -> int:
    """Entry point of ``ermrl test-generalization`` and ``test_generalization.py``."""
    parser = build_test_generalization_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    # The command that made the test folder (command.txt): `ermrl test-generalization ...`
    # also when `ermrl run` runs this stage.
    command = shlex.join([*prog.split(), *(sys.argv[1:] if argv is None else argv)])
    request = TestGeneralizationRequest(
        args.study_name, args.storage, args.env_id, test_options(args), observe=args.observe,
        n_envs=args.n_envs, hyperparams=args.hyperparams, scores=args.scores, quiet=args.quiet,
        command=command,
    )  # fmt: skip
    return exit_on_failure(prog, lambda: run_test_generalization(request, prog))


test_generalization_main.__test__ = False  # type: ignore[attr-defined]  # not a pytest test
