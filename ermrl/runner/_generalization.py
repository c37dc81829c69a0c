"""What ``ermrl evolve-generalization`` and ``ermrl test-generalization`` run once their options
are parsed: evolve on a set of tasks, test on a task the reservoirs never saw.

`ermrl.runner._resolve.generalization_config_from_args` resolves the evolution's
options into its configuration; `run_evolve_generalization` runs it (an
`EvolveRequest`, as a one-task study's) and
`run_test_generalization` runs a `TestGeneralizationRequest`. ``ermrl run`` calls
both with what its plan resolved; the two commands parse their argv and call the same
functions.
"""

from __future__ import annotations

import dataclasses
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ermrl.config import ConfigError, EvolveConfig, PPOConfig, TaskConfig
from ermrl.runner._commands import (
    EXIT_INTERRUPTED,
    CommandFailed,
    check_wandb,
    create_study,
    dashboard_line,
    print_notes,
    progress_or_default,
    require_tensorboard,
    run_and_report,
    run_test_phase,
    setup_errors,
    study_options,
)
from ermrl.runner._requests import EvolveRequest, TestGeneralizationRequest
from ermrl.runner._resolve import generalization_config_from_args

if TYPE_CHECKING:
    import optuna

    from ermrl._config_base import ObserveMode
    from ermrl.test_phase import TestPlan

__all__ = [
    "TestGeneralizationRequest",
    "generalization_config_from_args",
    "overlap_warning",
    "print_generalization_study",
    "run_evolve_generalization",
    "run_test_generalization",
    "suggested_test_env",
]


# -- evolve-generalization ----------------------------------------------------------------------


_LEFT_OUT = {
    "no_ant": "Ant",
    "no_halfcheetah": "HalfCheetah",
    "no_hopper": "Hopper",
    "no_swimmer": "Swimmer",
    "no_walker2d": "Walker2d",
}


def suggested_test_env(config: EvolveConfig) -> str:
    """The left-out task of a leave-one-out suite (same version), else a placeholder."""
    gen = config.generalization
    family = _LEFT_OUT.get(gen.suite or "") if gen is not None else None
    if family is None:
        return "ENV_ID"
    version = config.problem.task.env_id.rpartition("-")[2]
    return f"{family}-{version}"


def run_evolve_generalization(
    request: EvolveRequest, prog: str = "ermrl evolve-generalization"
) -> int:
    """Create or resume the study on a set of tasks and run this worker's trials, printing what
    ``ermrl evolve-generalization`` prints; return its exit code.

    Raises:
        CommandFailed: The study cannot be created or written (one line, exit code 2).
    """
    from ermrl.search import generalization_evaluator

    config, storage, study_name = request.config, request.storage, request.study_name
    study: optuna.Study = create_study(request, prog)
    if not request.quiet:
        print_generalization_study(config, study_name, storage)
    return run_and_report(
        prog,
        config,
        study,
        quiet=request.quiet,
        fitness_name="normalized fitness",
        next_command=f"ermrl test-generalization --study-name {shlex.quote(study_name)} "
        f"--storage {shlex.quote(storage)} --env-id {suggested_test_env(config)}",
        evaluate=generalization_evaluator(config, quiet=request.quiet),
        storage_url=storage,
        study_kwargs=study_options(request),
        evaluator_factory=lambda c: generalization_evaluator(c, quiet=request.quiet),
        wait_for_running=request.wait_for_running,
        progress=progress_or_default(request.progress),
        wandb=request.wandb,
        tensorboard=request.tensorboard,
    )


def print_generalization_study(config: EvolveConfig, study_name: str, storage: str) -> None:
    """The study's tasks, seeds, budget and search, and where to watch it live."""
    from ermrl._text import plural

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


def run_test_generalization(
    request: TestGeneralizationRequest, prog: str = "ermrl test-generalization"
) -> int:
    """The generalization test, printing what ``ermrl test-generalization`` prints; return its
    exit code.

    Raises:
        CommandFailed: Bad options, study or folder, or a run that cannot be measured.
    """
    r = request
    require_tensorboard(r.options.tensorboard)
    check_wandb(r.options.wandb)
    notes: list[str] = []
    try:
        test = _resolve_test(r, notes)
    except setup_errors() as err:
        raise CommandFailed(str(err)) from None
    print_notes(prog, test.ppo, notes)
    _say_test_plan(prog, r, test)
    summary = run_test_phase(
        prog, test.plan, test.task, test.config.problem.encoder, test.ppo,
        _test_metadata(r, test), quiet=r.quiet, command=r.command,
        then=lambda table: _normalize_summary(table, test.plan.out, test.reference),
    )  # fmt: skip
    if summary is None:
        return EXIT_INTERRUPTED
    if not r.quiet:
        if test.reference is None:
            print(f"note: no reference scores for {r.env_id}: summary.csv has raw returns only")
        print(f"wrote {test.plan.out}/summary.csv, curves.csv, learning_curves.png", flush=True)
        if test.warning:  # again, below the progress lines
            _shout(test.warning)
    return 0


def _resolve_test(r: TestGeneralizationRequest, notes: list[str]) -> _GeneralizationTest:
    """Read the study and resolve the test task, its PPO settings and the test phase's plan.

    Args:
        r: The request.
        notes: Receives why the test trains with the backend it does.

    Raises:
        The errors of `setup_errors` (a bad env id, study or option).
    """
    from ermrl.agents import check_ppo_config
    from ermrl.envs import check_env_id, observation_indices
    from ermrl.search import study_config
    from ermrl.storage import folder_for, load_study
    from ermrl.test_phase._prepare import choose_agents, plan_test_phase, with_backend

    study = load_study(r.study_name, r.storage)
    config = study_config(study)
    problem = config.problem
    observe: ObserveMode = r.observe or problem.task.observe
    check_env_id(r.env_id)
    observation_indices(r.env_id, observe)
    gen = config.generalization
    evolution_ids = gen.env_ids if gen is not None else (problem.task.env_id,)
    warning = overlap_warning(r.env_id, evolution_ids, r.study_name)
    options = dataclasses.replace(r.options, agents=choose_agents(r.options, config, observe))
    task = dataclasses.replace(problem.task, env_id=r.env_id, observe=observe)
    default_out = folder_for("runs", f"{r.study_name}__{r.env_id.replace('/', '-')}")
    ppo = with_backend(
        _test_ppo(config, r),
        options,
        task=task,
        out=Path(options.out) if options.out else default_out,
        notes=notes,
    )
    # The test env's settings (the study's, a table's, --ppo): refused now, not by a run.
    check_ppo_config(task, problem.encoder, ppo, where=r.env_id)
    plan = plan_test_phase(options, study, config, task, ppo, default_out, observe=observe)
    reference, target_column = _reference_returns(r, config)
    return _GeneralizationTest(
        config, task, ppo, plan, tuple(evolution_ids), warning, reference, target_column
    )


def _test_ppo(config: EvolveConfig, r: TestGeneralizationRequest) -> PPOConfig:
    """PPO settings of the test env: the study's for an evolution task, else table + overrides."""
    from ermrl.agents import resolve_ppo_config, with_overrides

    learner = config.problem.ppo.learner
    own = r.options.learner_settings().get(learner, {})
    cli = {**r.options.ppo_overrides(learner), **own}
    gen = config.generalization
    known: PPOConfig | None = None
    if gen is not None:
        known = next((t.ppo for t in gen.tasks if t.task.env_id == r.env_id), None)
    elif config.problem.task.env_id == r.env_id:
        known = config.problem.ppo
    if known is not None and r.n_envs is None and r.hyperparams is None:
        return with_overrides(known, cli)
    study_overrides = dict(gen.ppo_overrides) if gen is not None else {}
    n_envs = r.n_envs if r.n_envs is not None else (gen.n_envs if gen is not None else None)
    table = r.hyperparams or (gen.hyperparams if gen is not None else None)
    return resolve_ppo_config(
        r.env_id,
        {**study_overrides, **cli},
        n_envs=n_envs,
        table_path=table,
        torch_threads=config.problem.ppo.torch_threads,
        learner=learner,
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


def _reference_returns(
    r: TestGeneralizationRequest, config: EvolveConfig
) -> tuple[tuple[float, float] | None, str]:
    """The test env's random and target returns (``None``: not in the scores table) and the
    table's target column: ``--scores``, else the study's table, else the packaged one."""
    from ermrl.search._scores import load_scores, reference_returns

    gen = config.generalization
    scores = r.scores
    if scores is None and gen is not None and gen.scores != "packaged":
        scores = gen.scores if Path(gen.scores).exists() else None
    target_column = gen.target_column if gen is not None else "target"
    table = load_scores(scores)
    try:
        reference: tuple[float, float] | None = reference_returns(
            r.env_id, table, target_column=target_column, path=scores
        )
    except ConfigError:
        reference = None
    return reference, target_column


def _shout(message: str) -> None:
    bar = "!" * min(len(message), 100)
    print(f"{bar}\n{message}\n{bar}", file=sys.stderr, flush=True)


def _say_test_plan(prog: str, r: TestGeneralizationRequest, test: _GeneralizationTest) -> None:
    """The warnings (also with ``--quiet``) and, unless quiet, what the test trains."""
    from ermrl.test_phase import describe_selection

    if test.warning:
        _shout(test.warning)
    plan = test.plan
    if plan.warning:  # also with --quiet: the selection is not the one a ranking would give
        print(f"{prog}: warning: {plan.warning}", file=sys.stderr, flush=True)
    if not r.quiet:
        best = describe_selection(plan.chosen)
        print(
            f"generalization test of {r.study_name!r} (evolved on "
            f"{', '.join(test.evolution_ids)}) on {test.task.label}: agents "
            f"{' '.join(plan.agent_names)}, seeds {' '.join(map(str, plan.seeds))}, "
            f"{r.options.training_steps} steps each; selected: {best}; out: {plan.out}",
            flush=True,
        )


def _test_metadata(r: TestGeneralizationRequest, test: _GeneralizationTest) -> dict[str, Any]:
    """What the run folder records of the study, the selection and the test env."""
    from ermrl.test_phase import selection_metadata

    gen = test.config.generalization
    reference = test.reference
    return {
        "study_name": r.study_name,
        "storage": r.storage,
        **selection_metadata(test.plan.chosen),
        "evolution_env_ids": list(test.evolution_ids),
        "evolution_suite": gen.suite if gen is not None else None,
        "test_env_id": r.env_id,
        "in_evolution_set": r.env_id in test.evolution_ids,
        "reference_returns": None
        if reference is None
        else {"random": reference[0], "target": reference[1], "column": test.target_column},
    }
