"""The parsers of ``ermrl evolve``, ``test``, ``report`` and the generalization commands.

A command's options are also the keys of its stage in an experiment file (``evolve:``,
``test:``, ``report:``), so these parsers are that file's schema: the CLI parses argv with them
(``ermrl.cli``), and the experiment-file plan (`ermrl.runner._experiment`) checks each
stage's options with the same parser and resolves them into configuration objects
(`ermrl.runner._resolve`). `PARSERS` maps each command to its parser's builder.
"""

from __future__ import annotations

import argparse
import textwrap
from collections.abc import Callable

from ermrl.runner._evolve_options import (
    GENES,
    INNER,
    OUTER,
    RESERVOIRS,
    TASKS,
    WORKERS,
    evolve_options,
    section,
)
from ermrl.runner._options import (
    ArgumentParser,
    HelpFormatter,
    add_progress_arg,
    add_schema_args,
    add_storage_args,
)
from ermrl.runner._requests import ReportRequest, TestGeneralizationRequest

__all__ = [
    "PARSERS",
    "EVOLVE_DESCRIPTION",
    "TEST_DESCRIPTION",
    "REPORT_DESCRIPTION",
    "EVOLVE_GENERALIZATION_DESCRIPTION",
    "TEST_GENERALIZATION_DESCRIPTION",
    "add_problem_args",
    "add_search_args",
    "build_evolve_parser",
    "add_test_args",
    "add_tensorboard_arg",
    "build_test_parser",
    "build_report_parser",
    "build_evolve_generalization_parser",
    "build_test_generalization_parser",
]


# -- evolve ---------------------------------------------------------------------------------------


EVOLVE_DESCRIPTION = textwrap.dedent(
    """\
    Evolve reservoir hyperparameters with an Optuna study (CMA-ES by default).

    Each trial samples sr, lr and input_scaling (per reservoir), trains one PPO agent per seed on
    the reservoir-encoded observations and records the mean return as the trial's fitness.
    --encoder evolves another registered encoder (its choices and flags are listed below): with
    --encoder rtu the reservoir is a frozen layer of recurrent trace units and the trial samples
    the ranges its decays and frequencies are drawn from. With --learner hebbian there is
    no encoder: each trial samples the Hebbian learner's genes (its network's spectral radius,
    input and bias scales, time constants, and its plasticity: noise, trace decay, learning rate,
    l2; see --gene). Re-running the same command resumes the study; several workers may share it.

    examples:
      ermrl evolve --env-id Pendulum-v1 --observe positions --n-trials 20 --n-seeds 2 \\
          --training-steps 20000 --storage sqlite:///ermrl.db
      ermrl evolve --env-id CartPole-v1 --observe positions --encoder rtu --n-trials 20 \\
          --training-steps 20000 --storage sqlite:///ermrl.db
      ermrl evolve --env-id Ant-v5 --learner hebbian --gene sigma=0.02:0.5 --n-trials 24 \\
          --training-steps 40000 --storage sqlite:///ermrl.db
    """
)


def add_problem_args(parser: argparse.ArgumentParser, *, multi_task: bool = False) -> None:
    """Options shared by single-task and generalization evolution: the task, the inner loop
    (learner), the reservoirs and, on one task, the learner's genes; generated from
    [`evolve_options`][ermrl.runner._evolve_options.evolve_options]."""
    cls = evolve_options(multi_task=multi_task)
    add_schema_args(parser, cls, section(cls, None)[: 1 if multi_task else 2])
    add_schema_args(parser, cls, section(cls, INNER, RESERVOIRS, GENES))


def add_search_args(parser: argparse.ArgumentParser, *, multi_task: bool = False) -> None:
    """The outer loop's options (sampler, pruner, re-evaluation), the storage, the workers'
    recovery options and the logs of ``ermrl evolve`` and ``ermrl evolve-generalization``."""
    cls = evolve_options(multi_task=multi_task)
    add_schema_args(parser, cls, section(cls, OUTER))
    add_storage_args(parser, study_required=False)
    add_schema_args(parser, cls, section(cls, WORKERS))
    add_progress_arg(parser)
    add_schema_args(parser, cls, ("tensorboard", "wandb"))
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def build_evolve_parser(prog: str = "ermrl evolve") -> ArgumentParser:
    parser = ArgumentParser(
        prog=prog, description=EVOLVE_DESCRIPTION, formatter_class=HelpFormatter
    )
    add_problem_args(parser)
    add_search_args(parser)
    return parser


# -- test -----------------------------------------------------------------------------------------


TEST_DESCRIPTION = textwrap.dedent(
    """\
    Test phase: train PPO (ppo), PPO on the full, unmasked observation (ppo-full), PPO on the
    best evolved reservoir (res-ppo) and PPO on an unevolved reservoir (random-res-ppo) on every
    seed, and write curves.csv, summary.csv, learning_curves.png, the models, config.yaml and
    command.txt to --out.

    The env, observation mask, encoding and PPO settings come from the study. When
    SLURM_ARRAY_TASK_ID is set, it selects one seed of the list (task i -> i-th seed). Finished
    runs are kept: re-running with the same settings resumes, and array tasks sharing --out
    merge their results. Each run records its settings (settings.json); a rerun into the same
    --out with other settings (--ppo, --trial, --training-steps, ...) is refused: use
    another --out, or --overwrite to retrain. --eval is not a training setting: it adds
    deterministic evaluation episodes to the runs it trains, beside runs made without them.

    The settings of each agent are its learner's table (ermrl/data/<learner>.yml), then --ppo
    (every agent), then the flags of its learner only (--for-learner, --stale-gradient). A
    setting other learners refuse, such as the dagger learner's expert, goes in --for-learner.

    examples:
      ermrl test --study-name S --storage sqlite:///ermrl.db --training-steps 1000000 --seeds 10 11 12
      ermrl test --study-name S --agents ppo dagger res-dagger --for-learner dagger expert=experts/hopper
    """
)


# The test phase's options, in the order the test commands show them (TestOptions' fields).
TEST_ARGS = (
    "training_steps", "seeds", "agents", "out", "trial", "n_procs", "evaluate",
    "n_eval_episodes", "ppo", "stale_gradient", "for_learner", "backend", "save_models",
    "overwrite", "checkpoint_every",
)  # fmt: skip


def add_test_args(parser: argparse.ArgumentParser, helps: dict[str, str] | None = None) -> None:
    """Add the test-phase options shared by ``ermrl test`` and ``ermrl test-generalization``,
    generated from [`TestOptions`][ermrl.test_phase.TestOptions] (`TEST_ARGS`).

    Args:
        parser: the command's parser.
        helps: help texts of this command that differ from the field's (``out``, ``trial``,
            ``ppo``: each command has its own default folder and reservoirs).
    """
    from ermrl.test_phase import TestOptions

    add_schema_args(parser, TestOptions, TEST_ARGS, helps)


def build_test_parser(prog: str = "ermrl test") -> ArgumentParser:
    from ermrl.test_phase import TestOptions

    parser = ArgumentParser(prog=prog, description=TEST_DESCRIPTION, formatter_class=HelpFormatter)
    add_storage_args(parser, study_required=True)
    add_test_args(parser)
    add_schema_args(parser, TestOptions, ("tensorboard", "wandb"))
    add_progress_arg(parser, inside="", finished="run")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


def add_tensorboard_arg(parser: argparse.ArgumentParser) -> None:
    """``--tensorboard DIR`` of the test-phase commands (on either backend)."""
    from ermrl.test_phase import TestOptions

    add_schema_args(parser, TestOptions, ("tensorboard",))


# -- report ---------------------------------------------------------------------------------------


REPORT_DESCRIPTION = textwrap.dedent(
    """\
    Write the report of a study: evolution figures (optimization history, parameter importances,
    sr/lr/input_scaling against fitness, contour of the two main parameters, fitness per CMA-ES
    generation), interactive HTML versions, the test phase (learning curves with 95% CI bands,
    final returns per agent, Welch t-test and bootstrap CI of res-ppo against the baselines),
    per-task scores of generalization studies, and the reservoir dynamics of one res-ppo episode
    (states, power spectra, dominant frequency). Everything is gathered in report.md and
    report.html. Reads only the study storage and the test-phase folder; runs headless.

    example:
      ermrl report --study-name S --storage sqlite:///ermrl.db --runs runs/S --out reports/S
    """
)


# The report's options, in the order ermrl report shows them (ReportRequest's fields).
REPORT_ARGS = ("runs", "out", "band", "dynamics", "interactive", "html")


def build_report_parser(prog: str = "ermrl report") -> ArgumentParser:
    parser = ArgumentParser(
        prog=prog, description=REPORT_DESCRIPTION, formatter_class=HelpFormatter
    )
    add_storage_args(parser, study_required=True)
    add_schema_args(parser, ReportRequest, REPORT_ARGS)
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


# -- evolve-generalization and test-generalization ------------------------------------------------


EVOLVE_GENERALIZATION_DESCRIPTION = textwrap.dedent(
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


TEST_GENERALIZATION_DESCRIPTION = textwrap.dedent(
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


def build_evolve_generalization_parser(
    prog: str = "ermrl evolve-generalization",
) -> ArgumentParser:
    parser = ArgumentParser(
        prog=prog, description=EVOLVE_GENERALIZATION_DESCRIPTION, formatter_class=HelpFormatter
    )
    cls = evolve_options(multi_task=True)
    which = parser.add_argument_group(TASKS).add_mutually_exclusive_group(required=True)
    add_schema_args(which, cls, ("env_ids", "suite"))
    add_schema_args(parser, cls, section(cls, TASKS)[2:])
    add_problem_args(parser, multi_task=True)
    add_search_args(parser, multi_task=True)
    return parser


# A generalization test task's own options (TestGeneralizationRequest's), after the test's.
TEST_TASK_ARGS = ("n_envs", "hyperparams", "scores")


def build_test_generalization_parser(prog: str = "ermrl test-generalization") -> ArgumentParser:
    parser = ArgumentParser(
        prog=prog, description=TEST_GENERALIZATION_DESCRIPTION, formatter_class=HelpFormatter
    )
    add_storage_args(parser, study_required=True)
    parser.add_argument(
        "--env-id", required=True, help="the test task, e.g. HalfCheetah-v5 (one outside the set)"
    )
    add_schema_args(parser, TestGeneralizationRequest, ("observe",))
    add_test_args(
        parser,
        {
            "out": "output folder (default: runs/<study name>__<env id>)",
            "trial": "test this trial's reservoirs instead of the best ones",
            "ppo": "PPO overrides on top of the table's and the study's, "
            "e.g. --ppo learning_rate=1e-4",
        },
    )
    add_schema_args(parser, TestGeneralizationRequest, TEST_TASK_ARGS)
    add_tensorboard_arg(parser)
    add_progress_arg(parser, inside="", finished="run")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


# -- every command --------------------------------------------------------------------------------


# Each command an experiment file's stage runs -> the builder of its parser.
PARSERS: dict[str, Callable[..., ArgumentParser]] = {
    "evolve": build_evolve_parser,
    "evolve-generalization": build_evolve_generalization_parser,
    "test": build_test_parser,
    "test-generalization": build_test_generalization_parser,
    "report": build_report_parser,
}
