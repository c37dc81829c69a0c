"""``ermrl evolve-generalization`` / ``ermrl test-generalization``: evolve on a set of tasks, test
on a task the reservoirs never saw."""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ermrl._text import plural
from ermrl.cli._common import (
    EXIT_INTERRUPTED,
    ArgumentParser,
    HelpFormatter,
    add_progress_arg,
    add_storage_args,
    dashboard_line,
    fail,
    positive_int,
    progress_mode,
    quiet_libraries,
)
from ermrl.cli._evolve import (
    add_problem_args,
    add_search_args,
    check_wandb,
    command_line,
    run_and_report,
)
from ermrl.cli._test import (
    add_tensorboard_arg,
    add_test_args,
    require_tensorboard,
    run_test_phase,
)
from ermrl.config import ConfigError, EvolveConfig, GeneralizationTask, PPOConfig, TaskConfig
from ermrl.runner._commands import (
    print_backend_notes,
    print_notes,
    setup_errors,
    study_write_failure,
)
from ermrl.runner._resolve import (
    budget_from_args,
    check_tensorboard,
    encoder_from_args,
    keep_study_backend,
    learner_flags,
    search_from_args,
    space_from_args,
    test_options,
)

if TYPE_CHECKING:
    from ermrl.test_phase import TestPlan

__all__ = [
    "build_evolve_generalization_parser",
    "build_test_generalization_parser",
    "evolve_generalization_main",
    "generalization_config_from_args",
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


def generalization_config_from_args(
    args: argparse.Namespace, *, build_agent: bool = True, notes: list[str] | None = None
) -> EvolveConfig:
    """Build and validate a multi-task configuration (raises ConfigError / env errors).

    Args:
        args: The parsed options.
        build_agent: Also build each task's agent once (see
            :func:`ermrl.cli._evolve.config_from_args`); ``False`` checks the options only.
        notes: Receives the one-line reason when ``--backend`` is left out and the population
            backend does not apply to some task (the study then trains with sb3).
    """
    from ermrl.agents import parse_overrides
    from ermrl.encoders import get_encoder
    from ermrl.search import generalization_config, generalization_tasks

    env_ids, suite = _suite_env_ids(args)
    _refuse_learner_genes(args.learner)
    overrides = {**parse_overrides(args.ppo, args.learner), **learner_flags(args, args.learner)}
    tasks = generalization_tasks(
        env_ids,
        observe=args.observe,
        ppo_overrides=overrides,
        n_envs=args.n_envs,
        hyperparams=args.hyperparams,
        torch_threads=args.torch_threads,
        scores=args.scores,
        target_column=args.target_column,
        learner=args.learner,
        backend=args.backend or "sb3",
    )
    if args.backend is None:  # population where it applies to every task; a study has one
        tasks = _one_backend(tasks, args, notes)
    space = space_from_args(args)
    encoder = encoder_from_args(args, space)
    for t in tasks:  # what depends on a task's sizes is refused before the study exists
        get_encoder(args.encoder).check(t.task, encoder, space)
    config = generalization_config(
        tasks,
        encoder=encoder,
        budget=budget_from_args(args),
        seeds=tuple(range(args.seed, args.seed + args.n_seeds)),
        space=space,
        search=search_from_args(args),
        n_procs=args.n_procs,
        suite=suite,
        scores=None if args.scores is None else str(Path(args.scores).resolve()),
        target_column=args.target_column,
        ppo_overrides=overrides,
        n_envs=args.n_envs,
        hyperparams=args.hyperparams,
    )
    _check_agents(config, tasks, build_agent)
    check_tensorboard(args)
    return config


def _suite_env_ids(args: argparse.Namespace) -> tuple[Sequence[str], str | None]:
    """The evolution tasks' env ids and the suite they come from (``None``: ``--env-ids``).

    Raises:
        ConfigError: ``--env-version`` without ``--suite``, or an unknown suite.
    """
    from ermrl.envs import get_suite

    if args.suite is not None:
        found = get_suite(args.suite, args.suites_file, env_version=args.env_version)
        return found.env_ids, found.name
    if args.env_version is not None:
        raise ConfigError("--env-version applies to --suite only; write the ids in full")
    return args.env_ids or (), None


def _refuse_learner_genes(learner: str) -> None:
    """A learner with genes of its own is evolved on one task (``ermrl evolve``).

    Raises:
        ConfigError: The learner has genes.
    """
    from ermrl.learners import get_learner

    if get_learner(learner).genes:
        raise ConfigError(
            f"evolve-generalization evolves encoders; the {learner} learner's genes are "
            "evolved on one task with evolve"
        )


def _one_backend(
    tasks: Sequence[GeneralizationTask], args: argparse.Namespace, notes: list[str] | None
) -> tuple[GeneralizationTask, ...]:
    """The tasks with one backend for all: population where it applies to every task, else sb3.

    Args:
        tasks: The evolution tasks.
        args: The parsed options (``--pruner``, ``--encoder``).
        notes: Receives the first task's reason the population backend does not apply.

    Returns:
        The tasks, each with the chosen backend.
    """
    from ermrl.population import choose_backend

    backend, why = "population", None
    for t in tasks:
        backend, why = choose_backend(
            None,
            t.ppo,
            (t.task,),
            pruner=args.pruner,
            encoder=args.encoder,
        )
        if why is not None:
            if notes is not None:
                notes.append(f"{t.task.env_id}: {why}")
            break
    return tuple(
        dataclasses.replace(t, ppo=dataclasses.replace(t.ppo, backend=backend)) for t in tasks
    )


def _check_agents(
    config: EvolveConfig, tasks: Sequence[GeneralizationTask], build_agent: bool
) -> None:
    """What PPO (or the population backend) would refuse in the first trial is refused before
    the study exists; ``build_agent=False`` skips building each task's agent."""
    from ermrl.agents import check_ppo_config

    for task in tasks if build_agent else ():
        check_ppo_config(task.task, config.problem.encoder, task.ppo, where=task.task.env_id)
    if config.problem.ppo.backend == "population":
        from ermrl.population import check_population_config

        check_population_config(config.problem.ppo)


def _command(prog: str, argv: Sequence[str] | None) -> str:
    return command_line(prog, argv)


_LEFT_OUT = {
    "no_ant": "Ant",
    "no_halfcheetah": "HalfCheetah",
    "no_hopper": "Hopper",
    "no_swimmer": "Swimmer",
    "no_walker2d": "Walker2d",
}


def _suggested_test_env(config: EvolveConfig) -> str:
    """The left-out task of a leave-one-out suite (same version), else a placeholder."""
    gen = config.generalization
    family = _LEFT_OUT.get(gen.suite or "") if gen is not None else None
    if family is None:
        return "ENV_ID"
    version = config.problem.task.env_id.rpartition("-")[2]
    return f"{family}-{version}"


def evolve_generalization_main(
    argv: Sequence[str] | None = None, prog: str = "ermrl evolve-generalization"
) -> int:
    """Entry point of ``ermrl evolve-generalization`` and ``evolve_generalization.py``."""
    from ermrl.envs import UnknownEnvError, UnsupportedObserveError
    from ermrl.search import (
        create_or_resume_generalization_study,
        generalization_evaluator,
        generalization_study_name,
    )
    from ermrl.storage import LockTimeout, StorageError

    parser = build_evolve_generalization_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    check_wandb(prog, args.wandb)
    notes: list[str] = []
    try:
        config = generalization_config_from_args(args, notes=notes)
        study_name = args.study_name or generalization_study_name(config)
        args, config = keep_study_backend(
            args, config, args.storage, study_name, generalization_config_from_args, notes
        )
    except (ConfigError, UnknownEnvError, UnsupportedObserveError) as err:
        fail(prog, str(err))
    assert config.generalization is not None
    print_backend_notes(prog, config, notes)
    study_kwargs, run_kwargs = _forwarded_options(args)
    try:
        study = create_or_resume_generalization_study(
            config, args.storage, study_name, command=_command(prog, argv), **study_kwargs
        )
    except (ConfigError, StorageError, LockTimeout) as err:
        fail(prog, str(err))
    except OSError as err:  # a full disk or read-only folder under a journal file
        message = study_write_failure(err, args.storage)
        if message is None:
            raise
        fail(prog, message)
    if not args.quiet:
        _print_study(config, study_name, args.storage)
    return run_and_report(
        prog,
        config,
        study,
        quiet=args.quiet,
        fitness_name="normalized fitness",
        next_command=f"ermrl test-generalization --study-name {shlex.quote(study_name)} "
        f"--storage {shlex.quote(args.storage)} --env-id {_suggested_test_env(config)}",
        evaluate=generalization_evaluator(config, quiet=args.quiet),
        storage_url=args.storage,
        study_kwargs=study_kwargs,
        evaluator_factory=lambda c: generalization_evaluator(c, quiet=args.quiet),
        wandb=args.wandb,
        **run_kwargs,
    )


def _forwarded_options(args: argparse.Namespace) -> tuple[dict[str, Any], dict[str, Any]]:
    """The study's and the run's options, forwarded like ``ermrl evolve`` does.

    Returns:
        ``(study_kwargs, run_kwargs)``: the cluster options of ``add_search_args`` (heartbeats,
        retries) given, and ``progress``, ``tensorboard`` and ``wait_for_running``.
    """
    study_kwargs: dict[str, Any] = {}
    if getattr(args, "heartbeat_interval", None) is not None:
        study_kwargs["heartbeat_interval"] = args.heartbeat_interval or None
    for name in ("grace_period", "max_retry"):
        if hasattr(args, name):
            study_kwargs[name] = getattr(args, name)
    run_kwargs: dict[str, Any] = {
        "progress": progress_mode(args),
        "tensorboard": getattr(args, "tensorboard", None),
    }
    if hasattr(args, "wait_for_running"):
        run_kwargs["wait_for_running"] = args.wait_for_running
    return study_kwargs, run_kwargs


def _print_study(config: EvolveConfig, study_name: str, storage: str) -> None:
    """The study's tasks, seeds, budget and search, and where to watch it live."""
    gen = config.generalization
    assert gen is not None
    suite = f" (suite {gen.suite})" if gen.suite else ""
    print(
        f"study {study_name!r} in {storage}: {len(gen.tasks)} tasks{suite}, "
        f"{plural(len(config.problem.seeds), 'seed')} x {config.problem.budget.training_steps} steps "
        f"per task per trial, {config.space.n_reservoirs} reservoir(s), "
        f"{config.search.sampler} sampler, {plural(config.search.n_trials, 'trial')}",
        flush=True,
    )
    if (live := dashboard_line(storage)) is not None:
        print(live, flush=True)
    for t in gen.tasks:
        print(
            f"  {t.task.label}: R_random {t.random_return:.4g}, R_target "
            f"{t.target_return:.4g} ({gen.target_column}), n_envs {t.ppo.n_envs}",
            flush=True,
        )


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


def _evolution_env_ids(config: EvolveConfig) -> tuple[str, ...]:
    if config.generalization is not None:
        return config.generalization.env_ids
    return (config.problem.task.env_id,)


def overlap_warning(env_id: str, evolution_ids: Sequence[str], study_name: str) -> str | None:
    """The WARNING text when the test env (or another version of it) was an evolution task."""
    from ermrl.search._scores import env_family

    listed = ", ".join(evolution_ids)
    if env_id in evolution_ids:
        return (
            f"WARNING: {env_id} was one of the evolution tasks of study {study_name!r} "
            f"({listed}): this is NOT a generalization test"
        )
    same_body = [e for e in evolution_ids if env_family(e) == env_family(env_id)]
    if same_body:
        return (
            f"WARNING: {env_id} is another version of evolution task {same_body[0]} of study "
            f"{study_name!r} ({listed}): this is NOT a test on an unseen body"
        )
    return None


def _shout(message: str) -> None:
    bar = "!" * min(len(message), 100)
    print(f"{bar}\n{message}\n{bar}", file=sys.stderr, flush=True)


def _test_ppo(config: EvolveConfig, env_id: str, args: argparse.Namespace) -> PPOConfig:
    """PPO settings of the test env: the study's for an evolution task, else table + overrides."""
    from ermrl.agents import parse_overrides, resolve_ppo_config, with_overrides
    from ermrl.runner._resolve import learner_overrides

    own = learner_overrides(args).get(config.problem.ppo.learner, {})
    cli = {**parse_overrides(args.ppo, config.problem.ppo.learner), **own}
    gen = config.generalization
    known: PPOConfig | None = None
    if gen is not None:
        known = next((t.ppo for t in gen.tasks if t.task.env_id == env_id), None)
    elif config.problem.task.env_id == env_id:
        known = config.problem.ppo
    if known is not None and args.n_envs is None and args.hyperparams is None:
        return with_overrides(known, cli)
    study_overrides = dict(gen.ppo_overrides) if gen is not None else {}
    n_envs = args.n_envs if args.n_envs is not None else (gen.n_envs if gen is not None else None)
    table = args.hyperparams or (gen.hyperparams if gen is not None else None)
    return resolve_ppo_config(
        env_id,
        {**study_overrides, **cli},
        n_envs=n_envs,
        table_path=table,
        torch_threads=config.problem.ppo.torch_threads,
        learner=config.problem.ppo.learner,
        backend=config.problem.ppo.backend,
    )


def _normalize_summary(summary: Any, out: Path, reference: tuple[float, float] | None) -> Any:
    """Add normalized-return columns to ``summary.csv`` when the env has reference scores."""
    from ermrl._io import write_atomic

    if reference is None or summary.empty:
        return summary
    random_return, target_return = reference
    scale = target_return - random_return
    summary = summary.copy()
    summary["final_return_normalized_mean"] = (summary["final_return_mean"] - random_return) / scale
    summary["final_return_normalized_std"] = summary["final_return_std"] / abs(scale)
    write_atomic(out / "summary.csv", summary.to_csv(index=False))
    return summary


@dataclasses.dataclass(frozen=True)
class _GeneralizationTest:
    """What ``ermrl test-generalization`` trains, resolved before any training.

    Attributes:
        config: The study's configuration.
        task: The test task (the study's task settings on the test env).
        ppo: The test env's PPO settings.
        plan: The test phase's plan (agents, seeds, selected trial, output folder).
        evolution_ids: The env ids the study evolved on.
        warning: Why this is not a generalization test (``None``: it is one).
        reference: The test env's random and target returns (``None``: no reference scores).
        target_column: The scores table's target column.
    """

    config: EvolveConfig
    task: TaskConfig
    ppo: PPOConfig
    plan: TestPlan
    evolution_ids: tuple[str, ...]
    warning: str | None
    reference: tuple[float, float] | None
    target_column: str


def test_generalization_main(
    argv: Sequence[str] | None = None, prog: str = "ermrl test-generalization"
) -> int:
    """Entry point of ``ermrl test-generalization`` and ``test_generalization.py``."""
    parser = build_test_generalization_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    require_tensorboard(args, prog)
    notes: list[str] = []
    try:
        test = _resolve_test(args, notes)
    except setup_errors() as err:
        fail(prog, str(err))
    print_notes(prog, test.ppo, notes)
    _say_test_plan(prog, args, test)
    summary = run_test_phase(
        prog,
        args,
        test.plan,
        test.task,
        test.config.problem.encoder,
        test.ppo,
        _test_metadata(args, test),
        then=lambda table: _normalize_summary(table, test.plan.out, test.reference),
    )
    if summary is None:
        return EXIT_INTERRUPTED
    if not args.quiet:
        if test.reference is None:
            print(f"note: no reference scores for {args.env_id}: summary.csv has raw returns only")
        print(f"wrote {test.plan.out}/summary.csv, curves.csv, learning_curves.png", flush=True)
        if test.warning:  # again, below the progress lines
            _shout(test.warning)
    return 0


def _resolve_test(args: argparse.Namespace, notes: list[str]) -> _GeneralizationTest:
    """Read the study and resolve the test task, its PPO settings and the test phase's plan.

    Args:
        args: The parsed options.
        notes: Receives why the test trains with the backend it does.

    Raises:
        The errors of :func:`setup_errors` (a bad env id, study or option).
    """
    from ermrl.agents import check_ppo_config
    from ermrl.envs import check_env_id, observation_indices
    from ermrl.search import study_config
    from ermrl.storage import load_study
    from ermrl.test_phase._prepare import choose_agents, plan_test_phase, with_backend

    study = load_study(args.study_name, args.storage)
    config = study_config(study)
    problem = config.problem
    observe = args.observe or problem.task.observe
    check_env_id(args.env_id)
    observation_indices(args.env_id, observe)
    evolution_ids = _evolution_env_ids(config)
    warning = overlap_warning(args.env_id, evolution_ids, args.study_name)
    options = test_options(args)
    options = dataclasses.replace(options, agents=choose_agents(options, config, observe))
    task = dataclasses.replace(problem.task, env_id=args.env_id, observe=observe)
    default_out = Path("runs") / f"{args.study_name}__{args.env_id}"
    ppo = with_backend(
        _test_ppo(config, args.env_id, args),
        options,
        task=task,
        out=Path(args.out) if args.out else default_out,
        notes=notes,
    )
    # The test env's settings (the study's, a table's, --ppo): refused now, not by a run.
    check_ppo_config(task, problem.encoder, ppo, where=args.env_id)
    plan = plan_test_phase(options, study, config, task, ppo, default_out, observe=observe)
    reference, target_column = _reference_returns(args, config)
    return _GeneralizationTest(
        config, task, ppo, plan, evolution_ids, warning, reference, target_column
    )


def _reference_returns(
    args: argparse.Namespace, config: EvolveConfig
) -> tuple[tuple[float, float] | None, str]:
    """The test env's random and target returns (``None``: not in the scores table) and the
    table's target column: ``--scores``, else the study's table, else the packaged one."""
    from ermrl.search._scores import load_scores, reference_returns

    gen = config.generalization
    scores = args.scores
    if scores is None and gen is not None and gen.scores != "packaged":
        scores = gen.scores if Path(gen.scores).exists() else None
    target_column = gen.target_column if gen is not None else "target"
    table = load_scores(scores)
    try:
        reference: tuple[float, float] | None = reference_returns(
            args.env_id, table, target_column=target_column, path=scores
        )
    except ConfigError:
        reference = None
    return reference, target_column


def _say_test_plan(prog: str, args: argparse.Namespace, test: _GeneralizationTest) -> None:
    """The warnings (also with ``--quiet``) and, unless quiet, what the test trains."""
    from ermrl.test_phase import describe_selection

    if test.warning:
        _shout(test.warning)
    plan = test.plan
    if plan.warning:  # also with --quiet: the selection is not the one a ranking would give
        print(f"{prog}: warning: {plan.warning}", file=sys.stderr, flush=True)
    if not args.quiet:
        best = describe_selection(plan.chosen)
        print(
            f"generalization test of {args.study_name!r} (evolved on "
            f"{', '.join(test.evolution_ids)}) on {test.task.label}: agents "
            f"{' '.join(plan.agent_names)}, seeds {' '.join(map(str, plan.seeds))}, "
            f"{args.training_steps} steps each; selected: {best}; out: {plan.out}",
            flush=True,
        )


def _test_metadata(args: argparse.Namespace, test: _GeneralizationTest) -> dict[str, Any]:
    """What the run folder records of the study, the selection and the test env."""
    from ermrl.test_phase import selection_metadata

    gen = test.config.generalization
    reference = test.reference
    return {
        "study_name": args.study_name,
        "storage": args.storage,
        **selection_metadata(test.plan.chosen),
        "evolution_env_ids": list(test.evolution_ids),
        "evolution_suite": gen.suite if gen is not None else None,
        "test_env_id": args.env_id,
        "in_evolution_set": args.env_id in test.evolution_ids,
        "reference_returns": None
        if reference is None
        else {"random": reference[0], "target": reference[1], "column": test.target_column},
    }


test_generalization_main.__test__ = False  # type: ignore[attr-defined]  # not a pytest test
