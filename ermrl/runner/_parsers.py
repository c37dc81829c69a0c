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
from typing import Any

from ermrl.config import FITNESS_MODES, PRUNERS, RESET_MODES, STARTS, Range
from ermrl.encoders import ENCODERS, flag_dest, reference_encoder
from ermrl.learners import LEARNERS
from ermrl.runner._options import (
    ArgumentParser,
    HelpFormatter,
    add_for_learner_arg,
    add_progress_arg,
    add_schema_args,
    add_stale_gradient_arg,
    add_storage_args,
    nonneg_int,
    positive_float,
    positive_int,
)
from ermrl.runner._requests import ReportRequest, TestGeneralizationRequest

__all__ = [
    "PARSERS",
    "EVOLVE_DESCRIPTION",
    "TEST_DESCRIPTION",
    "REPORT_DESCRIPTION",
    "EVOLVE_GENERALIZATION_DESCRIPTION",
    "TEST_GENERALIZATION_DESCRIPTION",
    "FLAG_TYPES",
    "add_problem_args",
    "add_search_args",
    "add_encoder_args",
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
    """Arguments shared by single-task and generalization evolution: the task, the inner
    loop (learner), the reservoirs and, on one task, the learner's genes."""
    if not multi_task:
        parser.add_argument(
            "--env-id",
            required=True,
            help="gymnasium env id, e.g. Pendulum-v1, HalfCheetah-v5, popgym-RepeatFirstEasy-v0",
        )
    parser.add_argument(
        "--observe",
        choices=("all", "positions", "velocities"),
        default="all",
        help="keep the whole observation, only its positions (velocities hidden) or only its velocities",
    )
    _add_learner_args(parser)
    _add_reservoir_args(parser)
    if not multi_task:
        _add_gene_args(parser)


def _add_learner_args(parser: argparse.ArgumentParser) -> None:
    """The inner loop's options: the learner, its settings and its training layout."""
    g = parser.add_argument_group("inner loop (the learner: PPO by default)")
    g.add_argument(
        "--learner",
        choices=tuple(LEARNERS),
        default="ppo",
        help="the inner learner, trained on the reservoir states: "
        + "; ".join(f"{name}: {learner.description}" for name, learner in LEARNERS.items())
        + ". Its settings come from its own table (see --hyperparams) and --ppo",
    )
    add_stale_gradient_arg(g)
    add_for_learner_arg(g)
    g.add_argument(
        "--backend",
        choices=("population", "sb3"),
        default=None,
        help="what trains the agents: population (a whole generation's candidates x seeds "
        "trained in lockstep with the same PPO, several times faster per core; ppo learner "
        "only, no --pruner) or sb3 (the reference implementation: one Stable-Baselines3 "
        "process per agent). Default: population where it applies, else sb3 with one line "
        "saying why. Stored with the study: a study never mixes backends, and a resumed study "
        "keeps its own",
    )
    g.add_argument(
        "--training-steps",
        type=positive_int,
        default=300_000,
        help="env steps per agent (paper: 300000)",
    )
    g.add_argument(
        "--n-seeds",
        type=positive_int,
        default=3,
        help="agents (seeds) per trial; fitness is their mean",
    )
    g.add_argument(
        "--seed",
        type=nonneg_int,
        default=0,
        help="first training seed; a trial uses seed .. seed+n_seeds-1",
    )
    _add_fitness_args(g)
    _add_layout_args(g)


def _add_fitness_args(g: argparse._ArgumentGroup) -> None:
    """How a run's fitness is measured (part of the inner loop's options)."""
    g.add_argument(
        "--fitness",
        choices=FITNESS_MODES,
        default="last",
        help="'last': mean return of the last --n-last-episodes training episodes (paper); "
        "'eval': mean return of --n-eval-episodes deterministic episodes after training",
    )
    g.add_argument(
        "--n-last-episodes",
        type=positive_int,
        default=10,
        help="training episodes averaged by --fitness last",
    )
    g.add_argument(
        "--n-eval-episodes",
        type=positive_int,
        default=5,
        help="evaluation episodes of --fitness eval",
    )


def _add_layout_args(g: argparse._ArgumentGroup) -> None:
    """The learner's settings and the runs' processes and threads (part of the inner loop's
    options)."""
    g.add_argument(
        "--n-envs",
        type=positive_int,
        default=None,
        help="environments per agent stepped in lockstep (DummyVecEnv); PPO collects n_steps*n_envs "
        "transitions per update. Default: the packaged table's value for the env, else 1 (paper)",
    )
    g.add_argument(
        "--ppo",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="the learner's hyperparameter overrides, e.g. --ppo learning_rate=1e-4 n_steps=1024 "
        "(rl-zoo's KEY:VALUE works too; framestack-ppo: frame_stack=K)",
    )
    g.add_argument(
        "--hyperparams",
        default=None,
        metavar="YAML",
        help="the learner's settings table keyed by env id (default: its packaged table, "
        "ermrl/data/ppo.yml for PPO)",
    )
    g.add_argument(
        "--n-procs",
        type=positive_int,
        default=1,
        help="cores that train a trial's runs in parallel (one single-threaded process per "
        "core, or per run up to twice the cores when the runs do not divide evenly: 3 seeds "
        "on 2 cores run in 3 processes so that no core idles; needs --pruner none)",
    )
    g.add_argument(
        "--torch-threads", type=positive_int, default=1, help="torch threads per training process"
    )


def _add_reservoir_args(parser: argparse.ArgumentParser) -> None:
    """The evolved encoder's options; each option's flag and default are kept in
    ``encoder_flags`` (a parser default), so that a learner with genes, which has no encoder,
    refuses them."""
    r = parser.add_argument_group("reservoirs (the evolved encoder)")
    encoder_flags: dict[str, tuple[str, Any]] = {}

    def radd(*names: str, **kwargs: Any) -> None:
        action = r.add_argument(*names, **kwargs)
        encoder_flags[action.dest] = (names[0], action.default)

    radd(
        "--encoder",
        choices=tuple(ENCODERS),
        default=reference_encoder().name,
        help="; ".join(f"'{e.name}': {e.description}" for e in ENCODERS.values()),
    )
    radd(
        "--n-reservoirs",
        type=positive_int,
        default=1,
        help="reservoirs (or RTU layers, NVARs, ...) per agent, each with its own evolved "
        "parameters",
    )
    add_encoder_args(radd)
    _add_reservoir_io_args(radd)
    parser.set_defaults(encoder_flags=encoder_flags)


def _add_reservoir_io_args(radd: Callable[..., None]) -> None:
    """What the reservoirs read and show the policy: input scaling, skip connection, resets,
    exposed units, reward scale, precision and the fed action and reward."""
    radd(
        "--input-scaling-range",
        nargs=2,
        type=positive_float,
        default=[1e-1, 10.0],
        metavar=("LOW", "HIGH"),
        help="input scaling range (log scale)",
    )
    radd(
        "--fixed-input-scaling",
        nargs="?",
        type=positive_float,
        const=1.0,
        default=None,
        metavar="VALUE",
        help="do not evolve input scaling; fix it at VALUE (1.0 when no value is given)",
    )
    radd(
        "--skip-connection",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="the policy also sees [observation, previous action, previous reward]",
    )
    radd(
        "--reset",
        choices=RESET_MODES,
        default="episode",
        help="reset reservoir states at each episode, or carry them across episodes",
    )
    radd(
        "--exposed-units",
        type=positive_int,
        default=None,
        help="show the policy only the first N units of each reservoir",
    )
    radd(
        "--reward-scale",
        type=float,
        default=1.0,
        help="factor applied to the reward fed to the reservoir",
    )
    radd(
        "--dtype",
        choices=("float32", "float64"),
        default="float32",
        help="reservoir state precision: float32 is about twice as cheap per step; float64 "
        "reproduces reservoirpy's own states to 1e-10",
    )
    radd(
        "--feed-action",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="feed the previous action to the reservoir",
    )
    radd(
        "--feed-reward",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="feed the previous reward to the reservoir",
    )


def _add_gene_args(parser: argparse.ArgumentParser) -> None:
    """``--gene``: other search ranges of a learner's genes (one-task evolution only)."""
    genes = "; ".join(
        f"{name}: " + ", ".join(f"{g} {_range_text(r)}" for g, r in learner.genes.items())
        for name, learner in LEARNERS.items()
        if learner.genes
    )
    e = parser.add_argument_group(
        "learner genes (a learner with genes, --learner hebbian, has no encoder: evolution "
        "shapes the learner itself)"
    )
    e.add_argument(
        "--gene",
        nargs="+",
        default=argparse.SUPPRESS,
        metavar="NAME=LOW:HIGH",
        help="another search range for a gene (log scale when the default range is; "
        f"NAME=LOW:HIGH:lin or :log to choose). Genes and default ranges: {genes}",
    )


def add_search_args(parser: argparse.ArgumentParser) -> None:
    """The outer loop's options (sampler, pruner, re-evaluation), the storage, the workers'
    recovery options and the logs of ``ermrl evolve`` and ``ermrl evolve-generalization``."""
    s = parser.add_argument_group("outer loop (Optuna)")
    s.add_argument(
        "--n-trials",
        type=positive_int,
        default=100,
        help="total trials of the study, all workers together",
    )
    s.add_argument(
        "--sampler", choices=("cmaes", "tpe", "random"), default="cmaes", help="search algorithm"
    )
    s.add_argument(
        "--sampler-seed",
        type=nonneg_int,
        default=None,
        help="sampler seed (default: nondeterministic)",
    )
    s.add_argument(
        "--restart",
        choices=("none", "ipop", "bipop"),
        default="none",
        help="CMA-ES restart strategy (larger populations on restart)",
    )
    s.add_argument(
        "--popsize",
        type=positive_int,
        default=None,
        help="CMA-ES population size (default: 4 + 3 ln(dim))",
    )
    s.add_argument(
        "--pruner",
        choices=PRUNERS,
        default="none",
        help="stop unpromising trials early from intermediate training returns",
    )
    s.add_argument(
        "--cma-start",
        choices=STARTS,
        default="center",
        help="first CMA-ES mean: 'center' = the centre of the log-scaled box, as in the ER-MRL "
        "paper's code (with the reference trial competing, it did at least as well in "
        "benchmarks/bench_science.py); 'reference' = the unevolved reservoir (reservoirpy "
        "defaults sr = lr = input_scaling = 1, clipped into the box), better for a handful of "
        "trials",
    )
    s.add_argument(
        "--reference-trial",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="queue the unevolved reference reservoir as the study's first trial, so that the "
        "study's best can never be worse than it without showing it",
    )
    _add_reevaluation_args(s)
    add_storage_args(parser, study_required=False)
    _add_worker_args(parser)
    _add_logging_args(parser)


def _add_reevaluation_args(s: argparse._ArgumentGroup) -> None:
    """The re-evaluation of the best trials on fresh seeds (part of the outer loop's options)."""
    s.add_argument(
        "--reevaluate-top",
        type=nonneg_int,
        default=0,
        metavar="K",
        help="when the budget is spent, re-train the K best trials and the reference trial on "
        "fresh seeds (study '<name>.reeval'); the test phase then uses that ranking (0: off)",
    )
    s.add_argument(
        "--reevaluate-seeds",
        type=positive_int,
        default=3,
        help="fresh seeds per re-evaluated candidate (seed + 1000 and up)",
    )
    s.add_argument(
        "--reevaluate-steps",
        type=positive_int,
        default=None,
        help="training steps of a re-evaluation run (default: --training-steps; the test "
        "budget removes the evolution/test budget mismatch)",
    )


def _add_worker_args(parser: argparse.ArgumentParser) -> None:
    """Heartbeats, retries and the end of a worker that shares a study with others."""
    w = parser.add_argument_group("workers sharing a study (crash and preemption recovery)")
    w.add_argument(
        "--heartbeat-interval",
        type=nonneg_int,
        default=60,
        metavar="SECONDS",
        help="a running trial records a heartbeat this often; 0 turns heartbeats off (for every "
        "worker of the study: a trial that never sent one is failed after the grace period)",
    )
    w.add_argument(
        "--grace-period",
        type=positive_int,
        default=300,
        metavar="SECONDS",
        help="a running trial without heartbeat for this long is failed and retried (its worker died)",
    )
    w.add_argument(
        "--max-retry",
        type=nonneg_int,
        default=3,
        help="retries of a trial whose worker died or was preempted (SIGTERM), same parameters",
    )
    w.add_argument(
        "--wait-for-running",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="when the budget is reached, wait for other workers' running trials (and retry "
        "those whose worker died) instead of exiting",
    )


def _add_logging_args(parser: argparse.ArgumentParser) -> None:
    """Progress lines, TensorBoard and Weights & Biases logs, and ``--quiet``."""
    add_progress_arg(parser)
    parser.add_argument(
        "--tensorboard",
        default=None,
        metavar="DIR",
        help="also log each trial's training curves for TensorBoard under "
        "DIR/trial_<n>/seed_<s> (a trial on several tasks: DIR/trial_<n>/<env_id>/seed_<s>), "
        "the scalars SB3's PPO logs, on either backend (needs: pip install tensorboard)",
    )
    parser.add_argument(
        "--wandb",
        default=None,
        metavar="PROJECT",
        help="also log each trial (its parameters and fitness) to the Weights & Biases project "
        "PROJECT, through optuna-integration's WeightsAndBiasesCallback: one W&B run per worker, "
        "grouped by study name (WANDB_MODE=offline logs locally; needs: pip install "
        "'ermrl[wandb]')",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def build_evolve_parser(prog: str = "ermrl evolve") -> ArgumentParser:
    parser = ArgumentParser(
        prog=prog, description=EVOLVE_DESCRIPTION, formatter_class=HelpFormatter
    )
    add_problem_args(parser)
    add_search_args(parser)
    return parser


def _range_text(r: Range) -> str:
    return f"[{r.low:g}, {r.high:g}]{'' if r.log else ' lin'}"


# The checked argparse types an encoder's flag data may name (``"type": "positive_int"``).
FLAG_TYPES: dict[str, Callable[[str], Any]] = {
    "positive_int": positive_int,
    "positive_float": positive_float,
    "nonneg_int": nonneg_int,
}


def add_encoder_args(add: Callable[..., Any]) -> None:
    """Every registered encoder's flags (`ermrl.encoders.Encoder.cli_flags`, plain data) as
    options, through ``add`` (``add_argument``'s signature). A flag that several encoders
    declare alike becomes one option whose help joins theirs.

    Raises:
        ValueError: two encoders declare one flag with different keywords (other than help).
    """
    merged: dict[str, dict[str, Any]] = {}
    for encoder in ENCODERS.values():
        for flag in encoder.cli_flags:
            options = {k: v for k, v in flag.items() if k != "space_field"}
            options["dest"] = flag_dest(flag)
            if isinstance(options.get("type"), str):
                options["type"] = FLAG_TYPES[options["type"]]
            known = merged.get(options["dest"])
            if known is None:
                merged[options["dest"]] = options
                continue
            if {k: v for k, v in known.items() if k != "help"} != {
                k: v for k, v in options.items() if k != "help"
            }:
                raise ValueError(f"encoders declare {flag['flags'][0]} differently")
            if options.get("help") and options["help"] not in known.get("help", ""):
                known["help"] = "; ".join(h for h in (known.get("help"), options["help"]) if h)
    for options in merged.values():
        add(*options.pop("flags"), **options)


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


_TARGET_COLUMNS = ("target", "provisional_target")


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
