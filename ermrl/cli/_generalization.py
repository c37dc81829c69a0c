"""``ermrl evolve-generalization`` / ``ermrl test-generalization``: evolve on a set of tasks, test
on a task the reservoirs never saw."""

from __future__ import annotations

import shlex
import sys
import textwrap
from collections.abc import Sequence

from ermrl.cli._common import (
    ArgumentParser,
    HelpFormatter,
    add_progress_arg,
    add_storage_args,
    exit_on_failure,
    fail,
    positive_int,
    quiet_libraries,
)
from ermrl.cli._evolve import add_problem_args, add_search_args, command_line
from ermrl.cli._test import add_tensorboard_arg, add_test_args
from ermrl.config import ConfigError
from ermrl.runner import _commands
from ermrl.runner._generalization import (
    TestGeneralizationRequest,
    overlap_warning,
    run_evolve_generalization,
    run_test_generalization,
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

_TARGET_COLUMNS = ("target", "provisional_target")

EVOLVE_DESCRIPTION = textwrap.dedent(
    """\
    Evolve reservoir hyperparameters on a set of tasks (the ER-MRL generalization experiment).

    Each trial samples sr, lr and input_scaling per reservoir, trains one PPO agent per seed on
    every task with the same reservoirs, and records as fitness the mean over tasks of the
    normalized return (R - R_random) / (R_target - R_random), where R is the task's return
    averaged over seeds. R_random (a random policy's episodic return) and R_target (PPO at 1M
    steps, rl-baselines3-zoo) come from ermrl/data/scores.csv or --scores.

    "The same reservoir" on every task: the same hyperparameters and, for a given seed, the
    same recurrent weights W and bias; the input weights Win are drawn per task from that seed
    (their shape depends on the task's observation and action sizes).

    examples:
      ermrl evolve-generalization --suite no_halfcheetah --n-reservoirs 2 --n-trials 100 \\
          --training-steps 300000 --storage sqlite:///ermrl.db
      ermrl evolve-generalization --env-ids Swimmer-v5 Hopper-v5 --n-trials 2 --n-seeds 1 \\
          --training-steps 2048 --storage sqlite:///ermrl.db --study-name demo
    """
)

TEST_DESCRIPTION = textwrap.dedent(
    """\
    Generalization test: train PPO (ppo), PPO on the full, unmasked observation (ppo-full, when
    --observe hides something), PPO on the reservoirs evolved on a set of tasks (res-ppo) and
    PPO on unevolved reservoirs (random-res-ppo) on another task, and write curves.csv,
    summary.csv, learning_curves.png, the models, config.yaml and command.txt to --out.

    The encoding options come from the study; the PPO settings of the test env come from the
    PPO table and the study's --ppo overrides. When the env has reference scores, summary.csv
    also has normalized returns. A loud WARNING is printed when the test env was one of the
    evolution tasks (then this is not a generalization test). SLURM_ARRAY_TASK_ID selects one
    seed of the list, as in ermrl test.

    example:
      ermrl test-generalization --study-name S --storage sqlite:///ermrl.db --env-id HalfCheetah-v5 \\
          --training-steps 1000000 --seeds 10 11 12
    """
)


# -- evolve-generalization ----------------------------------------------------------------------


def build_evolve_generalization_parser(
    prog: str = "ermrl evolve-generalization",
) -> ArgumentParser:
    parser = ArgumentParser(
        prog=prog, description=EVOLVE_DESCRIPTION, formatter_class=HelpFormatter
    )
    g = parser.add_argument_group("tasks")
    which = g.add_mutually_exclusive_group(required=True)
    which.add_argument(
        "--env-ids", nargs="+", metavar="ENV_ID", help="the task set, e.g. Ant-v5 Swimmer-v5"
    )
    which.add_argument(
        "--suite",
        default=None,
        help="a named task set: ant_swimmer, ant_cheetah, cheetah_swimmer, no_ant, "
        "no_halfcheetah, no_hopper, no_swimmer, no_walker2d, forward_mujoco, or one of "
        "--suites-file",
    )
    g.add_argument(
        "--suites-file",
        default=None,
        metavar="YAML",
        help="your own suites (same format as ermrl/data/suites.yml), added to the packaged ones",
    )
    g.add_argument(
        "--env-version",
        default=None,
        metavar="vN",
        help="with --suite: use this version of every env (the packaged suites are v5)",
    )
    g.add_argument(
        "--scores",
        default=None,
        metavar="CSV",
        help="reference table of random and target returns (default: ermrl/data/scores.csv)",
    )
    g.add_argument(
        "--target-column",
        choices=_TARGET_COLUMNS,
        default="target",
        help="R_target: 'target' (PPO at 1M steps, rl-baselines3-zoo) or 'provisional_target' "
        "(the original ER-MRL code's values)",
    )
    add_problem_args(parser, multi_task=True)
    add_search_args(parser)
    return parser


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
    request = _commands.EvolveRequest(
        config, args.storage, study_name, command_line(prog, argv), tuple(notes), args.quiet,
        args.progress, args.tensorboard, args.wandb, args.heartbeat_interval, args.grace_period,
        args.max_retry, args.wait_for_running,
    )  # fmt: skip
    return exit_on_failure(prog, lambda: run_evolve_generalization(request, prog))


# -- test-generalization ------------------------------------------------------------------------


def build_test_generalization_parser(prog: str = "ermrl test-generalization") -> ArgumentParser:
    parser = ArgumentParser(prog=prog, description=TEST_DESCRIPTION, formatter_class=HelpFormatter)
    add_storage_args(parser, study_required=True)
    parser.add_argument(
        "--env-id", required=True, help="the test task, e.g. HalfCheetah-v5 (one outside the set)"
    )
    parser.add_argument(
        "--observe",
        choices=("all", "positions", "velocities"),
        default=None,
        help="observation mask of the test task (default: the study's)",
    )
    add_test_args(
        parser,
        out_help="output folder (default: runs/<study name>__<env id>)",
        trial_help="test this trial's reservoirs instead of the best ones",
        ppo_help="PPO overrides on top of the table's and the study's, "
        "e.g. --ppo learning_rate=1e-4",
    )
    parser.add_argument(
        "--n-envs",
        type=positive_int,
        default=None,
        help="environments per agent (default: the study's --n-envs, else the PPO table's)",
    )
    parser.add_argument(
        "--hyperparams",
        default=None,
        metavar="YAML",
        help="PPO table keyed by env id (default: the study's, else ermrl/data/ppo.yml)",
    )
    parser.add_argument(
        "--scores",
        default=None,
        metavar="CSV",
        help="reference table for the normalized returns (default: the study's)",
    )
    add_tensorboard_arg(parser)
    add_progress_arg(parser, inside="", finished="run")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


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
