"""Multi-task fitness: evolve one set of reservoirs on several tasks (the generalization question).

A candidate (the hyperparameters of ``K`` reservoirs) is trained on every task of the set, once
per seed. Its fitness is the mean over tasks of the normalized return

    (R_task - R_random) / (R_target - R_random),

where ``R_task`` is the task's return averaged over seeds (see `ermrl.search._scores` for
the references). 0 means "as good as a random policy" and 1 "as good as the target".

"The same reservoir" on two tasks means: the same hyperparameters (``sr``, ``lr``,
``input_scaling`` per reservoir) and, for a given training seed, the same recurrent matrix ``W``
and bias. Only the input matrix ``Win`` differs, because its shape ``(units, obs + action + 1)``
depends on the task; it is drawn from the same seed (reservoirpy spawns separate generators
for ``Win``, ``W`` and the bias, so ``W`` does not depend on the input size).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TextIO

import numpy as np
import optuna

from ermrl.agents import RunResult
from ermrl.config import (
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    EvolveConfig,
    GeneralizationConfig,
    GeneralizationTask,
    Problem,
    SearchConfig,
    TaskConfig,
)
from ermrl.search._objective import (
    EvaluateFn,
    FitnessResult,
    SeedRunner,
    _finite_or_none,
    first_failure,
    train_generation,
    train_runs,
)
from ermrl.search._scores import load_scores, reference_returns
from ermrl.search._study import STUDY_CONFIG_ATTR, create_or_resume_study

__all__ = [
    "GeneralizationFitness",
    "TaskOutcome",
    "create_or_resume_generalization_study",
    "evaluate_generalization",
    "generalization_config",
    "generalization_evaluator",
    "generalization_study_name",
    "generalization_tasks",
]

ReportFn = Callable[[int, float], None]


@dataclass
class TaskOutcome:
    """What one task contributed to a candidate's fitness.

    Attributes:
        spec: The task and its references.
        runs: One run per seed, in seed order.
        mode: The fitness measure (``last`` or ``eval``).
    """

    spec: GeneralizationTask
    runs: list[RunResult]
    mode: str

    @property
    def env_id(self) -> str:
        return self.spec.task.env_id

    @property
    def seed_returns(self) -> list[float]:
        """Each seed's return under the fitness measure."""
        return [r.fitness(self.mode) for r in self.runs]

    @property
    def mean_return(self) -> float:
        """The task's raw return: the mean over seeds."""
        return float(np.mean(self.seed_returns))

    @property
    def normalized(self) -> float:
        """``(mean_return - R_random) / (R_target - R_random)``."""
        return self.spec.normalize(self.mean_return)


@dataclass
class GeneralizationFitness(FitnessResult):
    """The multi-task fitness of one candidate: the mean normalized return over tasks.

    Attributes:
        tasks: One [`TaskOutcome`][ermrl.search.TaskOutcome] per task, in the task set's order.
    """

    tasks: list[TaskOutcome] = field(default_factory=list)

    def user_attrs(self) -> dict[str, Any]:
        """JSON-friendly per-trial record, keyed by env id for each per-task value.

        Keys: ``fitness`` (mean normalized return), ``tasks`` (env ids in order),
        ``task_returns`` ({env_id: raw return, mean over seeds}), ``task_normalized``
        ({env_id: normalized return}), ``task_seed_returns`` ({env_id: [raw return per seed]}),
        ``task_random_returns`` / ``task_target_returns`` (the references), ``task_n_episodes``,
        ``task_env_steps``, plus ``fitness_mode``, ``seeds``, ``env_steps``, ``wall_seconds``,
        ``steps_per_second`` and ``versions``.
        """
        return {
            "fitness": _finite_or_none(self.fitness),
            "fitness_mode": self.mode,
            "seeds": [r.seed for r in self.tasks[0].runs] if self.tasks else [],
            "tasks": [t.env_id for t in self.tasks],
            "task_returns": {t.env_id: _finite_or_none(t.mean_return) for t in self.tasks},
            "task_normalized": {t.env_id: _finite_or_none(t.normalized) for t in self.tasks},
            "task_seed_returns": {
                t.env_id: [_finite_or_none(v) for v in t.seed_returns] for t in self.tasks
            },
            "task_random_returns": {t.env_id: t.spec.random_return for t in self.tasks},
            "task_target_returns": {t.env_id: t.spec.target_return for t in self.tasks},
            "task_n_episodes": {
                t.env_id: [len(r.episode_returns) for r in t.runs] for t in self.tasks
            },
            "task_env_steps": {t.env_id: sum(r.env_steps for r in t.runs) for t in self.tasks},
            **self.totals(),
        }

    def describe(self) -> str:
        """One line per trial: each task's raw and normalized return."""
        return " | ".join(
            f"{t.env_id}: {t.mean_return:.4g} (norm {t.normalized:.3g})" for t in self.tasks
        )


def evaluate_generalization(
    encoder: EncoderConfig | None,
    problem: Problem,
    tasks: Sequence[GeneralizationTask],
    *,
    runner: SeedRunner | None = None,
    report: ReportFn | None = None,
) -> GeneralizationFitness:
    """Train one agent per (task, seed) with the same encoder; return the mean normalized return.

    Args:
        encoder: The candidate's encoder settings (decoded from a sampled point by the problem's
            encoder); ``None`` trains on the raw observation.
        problem: Shared encoding options, budget and seeds (its ``task`` and ``ppo`` are
            ignored: each task brings its own).
        tasks: The tasks with their PPO settings and reference returns.
        runner: Where the runs go (a pool trains all tasks' seeds in parallel).
        report: Intermediate normalized returns for pruning, ``report(step, value)``; steps are
            counted across tasks then seeds (task ``i``, seed ``j`` starts at
            ``(i * n_seeds + j) * training_steps``). Used only when runs stay in this process.

    Returns:
        The fitness, with every run and per-task values.
    """
    if not tasks:
        raise ConfigError("a generalization problem needs at least one task")
    budget = problem.budget
    start = time.perf_counter()
    runner = runner or SeedRunner(1)
    per_task = train_runs(
        encoder,
        [(spec.task, spec.ppo, spec.normalize) for spec in tasks],
        budget,
        problem.seeds,
        runner=runner,
        report=report,
    )
    outcomes = [TaskOutcome(spec, runs, budget.fitness) for spec, runs in zip(tasks, per_task)]
    fitness = float(np.mean([o.normalized for o in outcomes]))
    return GeneralizationFitness(
        fitness=fitness,
        dtype=None if encoder is None else encoder.dtype,
        mode=budget.fitness,
        runs=[r for runs in per_task for r in runs],
        wall_seconds=time.perf_counter() - start,
        tasks=outcomes,
    )


def generalization_generation(
    config: EvolveConfig, *, quiet: bool = False, stream: TextIO | None = None
) -> Callable[[Sequence[EncoderConfig], SeedRunner], list[FitnessResult | BaseException]]:
    """The population backend's counterpart of
    [`generalization_evaluator`][ermrl.search.generalization_evaluator]: the multi-task fitness of a
    whole generation, each task's (candidate, seed) runs trained as one population.

    Raises:
        ConfigError: the config has no task set.
    """
    if config.generalization is None:
        raise ConfigError("this configuration has no generalization task set")
    tasks = config.generalization.tasks
    problem = config.problem

    def evaluate(
        encoders: Sequence[EncoderConfig], runner: SeedRunner
    ) -> list[FitnessResult | BaseException]:
        start = time.perf_counter()
        trained = train_generation(
            encoders,
            [(spec.task, spec.ppo) for spec in tasks],
            problem.budget,
            problem.seeds,
            runner=runner,
        )
        share = (time.perf_counter() - start) / max(len(encoders), 1)
        out: list[FitnessResult | BaseException] = []
        for encoder, per_task in zip(encoders, trained):
            failure = first_failure([r for runs in per_task for r in runs])
            if failure is not None:
                out.append(failure)
                continue
            outcomes = [
                TaskOutcome(
                    spec, [r for r in runs if isinstance(r, RunResult)], problem.budget.fitness
                )
                for spec, runs in zip(tasks, per_task)
            ]
            result = GeneralizationFitness(
                fitness=float(np.mean([o.normalized for o in outcomes])),
                dtype=encoder.dtype,
                mode=problem.budget.fitness,
                runs=[r for o in outcomes for r in o.runs],
                wall_seconds=share,
                backend="population",
                population=len(encoders) * len(problem.seeds),
                tasks=outcomes,
            )
            if not quiet:
                print(f"  {result.describe()}", file=stream or sys.stdout, flush=True)
            out.append(result)
        return out

    return evaluate


def generalization_evaluator(
    config: EvolveConfig, *, quiet: bool = False, stream: TextIO | None = None
) -> EvaluateFn:
    """The ``evaluate`` hook of [`run_evolution`][ermrl.search.run_evolution] for a multi-task
    config.

    Args:
        config: A config with ``generalization`` set.
        quiet: No per-task progress line.
        stream: Where the per-task line goes (default ``sys.stdout``).

    Raises:
        ConfigError: the config has no task set.
    """
    if config.generalization is None:
        raise ConfigError("this configuration has no generalization task set")
    tasks = config.generalization.tasks

    def evaluate(
        encoder: EncoderConfig, runner: SeedRunner, report: ReportFn | None
    ) -> FitnessResult:
        result = evaluate_generalization(
            encoder, config.problem, tasks, runner=runner, report=report
        )
        if not quiet:
            print(f"  {result.describe()}", file=stream or sys.stdout, flush=True)
        return result

    return evaluate


def generalization_tasks(
    env_ids: Sequence[str],
    *,
    observe: str = "all",
    ppo_overrides: Mapping[str, Any] | None = None,
    n_envs: int | None = None,
    hyperparams: str | None = None,
    torch_threads: int = 1,
    scores: str | None = None,
    target_column: str = "target",
    learner: str = "ppo",
    backend: str = "sb3",
) -> tuple[GeneralizationTask, ...]:
    """Validate env ids and attach each one's PPO settings and reference returns.

    Args:
        env_ids: The task set (distinct registered ids).
        observe: Observation mask applied to every task.
        ppo_overrides: ``--ppo`` overrides on top of each env's PPO table entry.
        n_envs: Explicit environments per agent (``None``: the table's value per env).
        hyperparams: Alternative PPO table.
        torch_threads: Torch threads per training process.
        scores: Reference table (``None``: the packaged ``ermrl/data/scores.csv``).
        target_column: ``target`` or ``provisional_target``.
        learner: The inner learner (its table gives each task's settings).
        backend: What trains the agents (``sb3`` or ``population``).

    Raises:
        ConfigError: an empty or repeated task set, or a missing reference score.
        UnknownEnvError: an unregistered id.
        UnsupportedObserveError: a mask the env does not support.
    """
    from ermrl.agents import resolve_ppo_config
    from ermrl.envs import check_env_id, observation_indices

    if not env_ids:
        raise ConfigError("the task set is empty: give --env-ids or --suite")
    repeated = sorted({e for e in env_ids if list(env_ids).count(e) > 1})
    if repeated:
        raise ConfigError(f"each task may appear once; repeated: {', '.join(repeated)}")
    for env_id in env_ids:
        check_env_id(env_id)
        observation_indices(env_id, observe)  # type: ignore[arg-type]
    table = load_scores(scores)
    out = []
    for env_id in env_ids:
        random_return, target_return = reference_returns(
            env_id, table, target_column=target_column, path=scores
        )
        ppo = resolve_ppo_config(
            env_id,
            ppo_overrides,
            n_envs=n_envs,
            table_path=hyperparams,
            torch_threads=torch_threads,
            learner=learner,
            backend=backend,
        )
        out.append(
            GeneralizationTask(
                task=TaskConfig(env_id=env_id, observe=observe),  # type: ignore[arg-type]
                ppo=ppo,
                random_return=random_return,
                target_return=target_return,
            )
        )
    return tuple(out)


def generalization_config(
    tasks: Sequence[GeneralizationTask],
    *,
    encoder: EncoderConfig,
    budget: BudgetConfig,
    seeds: Sequence[int],
    space: Any,
    search: SearchConfig,
    n_procs: int = 1,
    suite: str | None = None,
    scores: str | None = None,
    target_column: str = "target",
    ppo_overrides: Mapping[str, Any] | None = None,
    n_envs: int | None = None,
    hyperparams: str | None = None,
) -> EvolveConfig:
    """The configuration of a multi-task evolution.

    The result's ``problem`` holds the shared encoder, budget and seeds; its ``task`` and
    ``ppo`` are the first task's, so code that reads a single-task config still finds a valid
    one. ``generalization`` holds every task with its PPO settings and reference returns.

    Args:
        tasks: From [`generalization_tasks`][ermrl.search.generalization_tasks].
        encoder: Encoding options shared by all tasks.
        budget: Training budget per (task, seed).
        seeds: Training seeds, the same on every task.
        space: The evolved search space (the encoder's; a
            [`SearchSpace`][ermrl.config.SearchSpace]).
        search: The sampler and trial budget.
        n_procs: Processes that train a trial's runs in parallel.
        suite: The suite name, if the tasks come from one.
        scores: The reference table used (``None``: the packaged one).
        target_column: The table column used as R_target.
        ppo_overrides: The ``--ppo`` overrides (kept to configure a test env the same way).
        n_envs: Explicit ``--n-envs``.
        hyperparams: The PPO table used (``None``: the packaged one).
    """
    if not tasks:
        raise ConfigError("the task set is empty: give --env-ids or --suite")
    problem = Problem(
        task=tasks[0].task,
        encoder=encoder,
        ppo=tasks[0].ppo,
        budget=budget,
        seeds=tuple(seeds),
    )
    return EvolveConfig(
        problem=problem,
        space=space,
        search=search,
        n_procs=n_procs,
        generalization=GeneralizationConfig(
            tasks=tuple(tasks),
            suite=suite,
            scores="packaged" if scores is None else str(scores),
            target_column=target_column,
            ppo_overrides=dict(ppo_overrides or {}),
            n_envs=n_envs,
            hyperparams=hyperparams,
        ),
    )


def generalization_study_name(config: EvolveConfig) -> str:
    """Default study name: ``gen__<suite or ids>__<observe>__<steps>steps[__rtu][__<K>res]``."""
    if config.generalization is None:
        return config.default_study_name
    gen = config.generalization
    what = gen.suite or "+".join(gen.env_ids)
    parts = [
        "gen",
        what,
        config.problem.task.observe,
        f"{config.problem.budget.training_steps}steps",
    ]
    from ermrl.encoders import reference_encoder

    if config.space.family != reference_encoder().family:
        parts.append(config.space.family)
    if config.space.n_reservoirs > 1:
        parts.append(f"{config.space.n_reservoirs}res")
    return "__".join(parts)


def create_or_resume_generalization_study(
    config: EvolveConfig,
    storage_url: str,
    study_name: str,
    *,
    command: str | None = None,
    **kwargs: Any,
) -> optuna.Study:
    """[`create_or_resume_study`][ermrl.search.create_or_resume_study] for a multi-task config.

    Beyond the problem and the search space, a resumed study must have the same task set,
    PPO settings per task, reference returns, target column and ``--ppo``/``--n-envs`` options
    (the paths of the score table and PPO table may differ).

    Raises:
        ConfigError: the study exists with another configuration.
        StorageError: the storage cannot be opened.
    """
    if config.generalization is None:
        raise ConfigError("this configuration has no generalization task set")
    study = create_or_resume_study(
        config, storage_url, study_name, command=command, kind="evolve-generalization", **kwargs
    )
    stored = (study.user_attrs.get(STUDY_CONFIG_ATTR) or {}).get("generalization")
    if stored is None:
        raise ConfigError(
            f"study {study_name!r} already exists and is not a generalization study; "
            "pick another --study-name"
        )
    # create_or_resume_study compared the task sets too (resume_conflicts).
    return study
