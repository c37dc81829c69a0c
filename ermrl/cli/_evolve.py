"""``ermrl evolve`` / ``evolve_res.py``: evolve reservoirs for one task."""

from __future__ import annotations

import argparse
import shlex
import sys
import textwrap
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from ermrl.cli._common import (
    ArgumentParser,
    HelpFormatter,
    add_for_learner_arg,
    add_progress_arg,
    add_stale_gradient_arg,
    add_storage_args,
    exit_on_failure,
    fail,
    nonneg_int,
    positive_float,
    positive_int,
    quiet_libraries,
)
from ermrl.config import (
    FITNESS_MODES,
    PRUNERS,
    RESET_MODES,
    STARTS,
    ConfigError,
    EvolveConfig,
    Range,
)
from ermrl.encoders import ENCODERS, flag_dest, reference_encoder
from ermrl.learners import LEARNERS
from ermrl.runner import _commands
from ermrl.runner._commands import (
    database_cause,
    interrupted_message,
    print_backend_notes,
    study_write_failure,
)
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

DESCRIPTION = textwrap.dedent(
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
    """Arguments shared by single-task and generalization evolution."""
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
    parser.set_defaults(encoder_flags=encoder_flags)
    if not multi_task:
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
    add_storage_args(parser, study_required=False)
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
    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    add_problem_args(parser)
    add_search_args(parser)
    return parser


def _range_text(r: Range) -> str:
    return f"[{r.low:g}, {r.high:g}]{'' if r.log else ' lin'}"


# The CLI's checked argparse types an encoder's flag data may name (``"type": "positive_int"``).
FLAG_TYPES: dict[str, Callable[[str], Any]] = {
    "positive_int": positive_int,
    "positive_float": positive_float,
    "nonneg_int": nonneg_int,
}


def add_encoder_args(add: Callable[..., Any]) -> None:
    """Every registered encoder's flags (:attr:`ermrl.encoders.Encoder.cli_flags`, plain data) as
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
    """:func:`ermrl.runner._commands.run_and_report`, its one-line errors exiting with code 2."""
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
    request = _commands.EvolveRequest(
        config, args.storage, study_name, command_line(prog, argv), tuple(notes), args.quiet,
        args.progress, args.tensorboard, args.wandb, args.heartbeat_interval, args.grace_period,
        args.max_retry, args.wait_for_running,
    )  # fmt: skip
    return exit_on_failure(prog, lambda: _commands.run_evolve(request, prog))
