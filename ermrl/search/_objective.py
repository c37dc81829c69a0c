"""Fitness of a reservoir: train one agent per seed and average their returns.

This is the *problem* side of the evolution, independent of how candidates are proposed.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from ermrl._progress import Progress, ProgressMode
from ermrl._text import plural
from ermrl.agents import (
    RunResult,
    pool_size,
    steps_trained,
    stop_workers,
    train_agent,
    training_pool,
)
from ermrl.config import (
    BudgetConfig,
    EncoderConfig,
    LearnerSpace,
    PPOConfig,
    Problem,
    SearchSpaceConfig,
    TaskConfig,
)

__all__ = [
    "EvaluateFn",
    "EvaluateGenerationFn",
    "FitnessResult",
    "SeedRunner",
    "decode_candidate",
    "evaluate_encoder",
    "evaluate_encoders",
    "train_generation",
    "library_versions",
    "pool_size",
    "train_runs",
]

ReportFn = Callable[[int, float], None]


def library_versions() -> dict[str, str]:
    """Versions of the libraries that determine a result."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in (
        "ermrl",
        "gymnasium",
        "stable-baselines3",
        "optuna",
        "reservoirpy",
        "mujoco",
        "torch",
    ):
        try:
            out[name.replace("-", "_")] = version(name)
        except PackageNotFoundError:
            out[name.replace("-", "_")] = "unknown"
    return out


@dataclass
class FitnessResult:
    """The fitness of one candidate and the runs behind it.

    Attributes:
        fitness: Mean over seeds of each run's return under the problem's fitness measure.
        mode: ``last`` or ``eval``.
        runs: One [`RunResult`][ermrl.agents.RunResult] per seed, in seed order.
        wall_seconds: Wall-clock time of the whole evaluation.
        dtype: Float type of the reservoir states (``None``: no reservoir). Above a spectral
            radius of about 1.5, float32 and float64 trajectories decorrelate, so a trial's
            result depends on it.
        backend: What trained the runs (``sb3`` or ``population``).
        population: Agents trained together (the population backend; 1 otherwise).
        n_last: Training episodes the ``last`` measure averages (for
            [`learning_curve`][ermrl.search.FitnessResult.learning_curve]).
    """

    fitness: float
    mode: str
    runs: list[RunResult] = field(default_factory=list)
    wall_seconds: float = 0.0
    dtype: str | None = None
    backend: str = "sb3"
    population: int = 1
    n_last: int = 10

    @property
    def env_steps(self) -> int:
        return sum(r.env_steps for r in self.runs)

    @property
    def steps_per_second(self) -> float:
        return self.env_steps / self.wall_seconds if self.wall_seconds > 0 else math.nan

    def user_attrs(self) -> dict[str, Any]:
        """JSON-friendly per-trial record (Optuna trial user attributes)."""
        return {
            "fitness_mode": self.mode,
            "seeds": [r.seed for r in self.runs],
            "returns_last": [_finite_or_none(r.last_return) for r in self.runs],
            "returns_eval": [_finite_or_none(r.eval_return) for r in self.runs],
            "n_episodes": [len(r.episode_returns) for r in self.runs],
            **self.totals(),
        }

    def learning_curve(self, n_points: int = 10) -> list[tuple[int, float]]:
        """The candidate's training curve at ``n_points`` evenly spaced env steps.

        At each step, the mean over seeds of the mean return of each run's last
        `n_last` training episodes ended by then (the ``last`` fitness measure, taken early). Steps
        at which some run has ended no episode yet are left out. Stored as the trial's intermediate
        values, so optuna-dashboard draws per-trial learning curves with or without a pruner.

        Returns:
            ``[(env_step, value), ...]`` in step order.
        """
        total = max((r.env_steps for r in self.runs), default=0)
        if total <= 0 or not all(r.episode_steps for r in self.runs):
            return []
        curve = []
        for k in range(1, n_points + 1):
            step = round(total * k / n_points)
            values = []
            for run in self.runs:
                ended = np.asarray(run.episode_steps) <= step
                returns = np.asarray(run.episode_returns, dtype=float)[ended]
                if len(returns) == 0:
                    break
                values.append(float(returns[-self.n_last :].mean()))
            else:
                curve.append((step, float(np.mean(values))))
        return curve

    def totals(self) -> dict[str, Any]:
        """The part of [`user_attrs`][ermrl.search.FitnessResult.user_attrs] every fitness shares:
        ``env_steps``, ``wall_seconds``, ``steps_per_second``, ``dtype``, ``backend``,
        ``population`` and ``versions``. With the population backend, ``wall_seconds`` is the
        trial's share of its generation's wall time (the generation's over its number of
        candidates)."""
        return {
            "env_steps": self.env_steps,
            "wall_seconds": round(self.wall_seconds, 3),
            "steps_per_second": round(self.steps_per_second, 1),
            "dtype": self.dtype,
            "backend": self.backend,
            "population": self.population,
            "versions": library_versions(),
        }


def decode_candidate(
    space: SearchSpaceConfig, params: Mapping[str, float], problem: Problem
) -> tuple[EncoderConfig | None, Problem]:
    """What a sampled point stands for: ``(encoder, problem)`` to train.

    An encoder's space decodes to the encoder's settings (the problem unchanged); a learner's
    genes ([`LearnerSpace`][ermrl.config.LearnerSpace]) decode to the problem with those learner
    settings, and no encoder.

    Raises:
        ConfigError: a parameter is missing, or decodes to a refused setting.
    """
    if isinstance(space, LearnerSpace):
        from ermrl.learners import get_learner

        ppo = get_learner(space.learner).with_genes(problem.ppo, space.values(params))
        return None, dataclasses.replace(problem, ppo=ppo)
    from ermrl.encoders import encoder_for

    assert problem.encoder is not None
    return encoder_for(problem.encoder).decode(space, params, problem.encoder), problem


def _finite_or_none(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


def _train_one(args: tuple[Any, ...]) -> RunResult:
    task, encoder, ppo, budget, seed, tensorboard_log, progress = args
    return train_agent(
        task, encoder, ppo, budget, seed, progress=progress, tensorboard_log=tensorboard_log
    )


class SeedRunner:
    """Runs the seeds of a candidate in this process or in a pool of worker processes.

    Worker processes are started once (``spawn``, so no forked torch state) and reused by every
    trial, which avoids paying the interpreter and import start-up per trial. The pool's size
    comes from [`pool_size`][ermrl.agents.pool_size]: ``n_procs`` cores, and one process per run up
    to twice that when the runs do not divide evenly among the cores (``balance=False``: exactly
    ``n_procs``).

    Args:
        n_procs: Cores for the runs (1 runs them one after another, in this process).
        balance: Size the pool with [`pool_size`][ermrl.agents.pool_size] (``False``: ``n_procs``
            processes).
        progress: ``"lines"``: each run (or population) prints a progress line every tenth
            of its steps or 30 s (`ermrl._progress.Progress`), labelled with
            `label` (what is training: ``"trial 12"``); ``"bar"``: a live bar for runs
            in this process, lines from worker processes; ``"none"``: silent.
        stream: Where the lines of runs in this process go (workers print to their stdout).
        tensorboard: Each run also logs training curves for TensorBoard (SB3's
            ``tensorboard_log``, or the same scalars from the population backend) under
            [`tensorboard_log`][ermrl.search.SeedRunner.tensorboard_log] (``None``: no logs).

    Attributes:
        label: What is training now, for the progress lines (``"trial 12"``).
        trial: The trial training now (its runs' TensorBoard folder; sb3 backend).
        trials: The trials of the generation training now, one per candidate in order (their
            runs' TensorBoard folders; population backend).
    """

    def __init__(
        self,
        n_procs: int = 1,
        *,
        balance: bool = True,
        progress: ProgressMode = "none",
        stream: TextIO | None = None,
        tensorboard: str | Path | None = None,
    ) -> None:
        self.n_procs = n_procs
        self.balance = balance
        self.n_processes = 0
        self._pool: ProcessPoolExecutor | None = None
        self.progress = progress
        self.stream = stream
        self.label = ""
        self.tensorboard = None if tensorboard is None else Path(tensorboard)
        self.trial: int | None = None
        self.trials: tuple[int, ...] = ()

    def tensorboard_log(
        self, seed: int, env_id: str | None = None, *, trial: int | None = None
    ) -> str | None:
        """The TensorBoard folder of a run: ``<tensorboard>/trial_<n>/seed_<s>``, with an
        ``<env_id>`` folder before the seed's when a trial trains on several tasks (``None``:
        no TensorBoard logs).

        Args:
            seed: The run's seed.
            env_id: The run's task, when the trial trains on several (``None``: one task).
            trial: The run's trial (``None``: `trial`).
        """
        if self.tensorboard is None:
            return None
        trial = self.trial if trial is None else trial
        folder = self.tensorboard / ("trial" if trial is None else f"trial_{trial}")
        if env_id is not None:
            folder /= env_id
        return str(folder / f"seed_{seed}")

    def run_progress(
        self, what: str, total: int, *, in_process: bool, unit: str = "steps"
    ) -> Progress:
        """The progress of one run or population: ``"<label>, <what>"``."""
        return Progress(
            f"{self.label}, {what}" if self.label else what,
            total,
            mode=self.progress,
            stream=self.stream if in_process else None,
            unit=unit,
        )

    def processes_for(self, n_jobs: int) -> int:
        """How many processes [`map`][ermrl.search.SeedRunner.map] uses for ``n_jobs`` runs (1: this
        process)."""
        if self.n_procs == 1 or n_jobs <= 1:
            return 1
        return pool_size(n_jobs, self.n_procs) if self.balance else min(self.n_procs, n_jobs)

    def start(self, n_jobs: int) -> int:
        """Start (or resize) the pool for ``n_jobs`` runs ahead of the first trial.

        Returns:
            The number of worker processes (1: runs stay in this process; no pool).
        """
        size = self.processes_for(n_jobs)
        if size == 1:
            return 1
        if self._pool is not None and self.n_processes != size:
            self.close()
        if self._pool is None:
            self._pool = training_pool(size)
            self.n_processes = size
            # Start every process (one task each spawns them all) before the first trial.
            list(self._pool.map(abs, range(size)))
        return size

    def population(
        self,
        task: TaskConfig,
        ppo: PPOConfig,
        budget: BudgetConfig,
        jobs: Sequence[Any],
        tensorboard_logs: Sequence[str | None] | None = None,
    ) -> list[RunResult | BaseException]:
        """Train ``jobs`` ([`PopulationJob`][ermrl.population.PopulationJob]) as one population
        split over ``n_procs`` processes of this runner's pool (the population backend); each job
        logs for TensorBoard in its folder of ``tensorboard_logs`` (``None``: no logs)."""
        from ermrl.population import split_jobs, steps_trained, train_population_parallel

        parts = len(split_jobs(len(jobs), self.n_procs))
        if parts > 1 and (self._pool is None or self.n_processes != parts):
            self.close()
            self._pool = training_pool(parts)
            self.n_processes = parts
        progress = self.run_progress(
            f"{plural(len(jobs), 'agent')} on {task.label}",
            steps_trained(ppo, budget.training_steps),
            in_process=parts == 1,
            unit="steps each",
        )
        return train_population_parallel(
            task, ppo, budget, jobs, n_procs=parts, pool=self._pool if parts > 1 else None,
            progress=progress, tensorboard_logs=tensorboard_logs,
        )  # fmt: skip

    def map(self, args: Sequence[tuple[Any, ...]], *, by_task: bool = False) -> list[RunResult]:
        """Train ``(task, encoder, ppo, budget, seed)`` runs; one result each, in order.

        ``by_task``: the runs' TensorBoard folders are per task (see
        [`tensorboard_log`][ermrl.search.SeedRunner.tensorboard_log]).
        """
        in_process = self.start(len(args)) == 1
        jobs = [
            (
                *a,
                self.tensorboard_log(a[4], a[0].env_id if by_task else None),
                self.run_progress(
                    f"seed {a[4]} on {a[0].label}",
                    steps_trained(a[2], a[3].training_steps),
                    in_process=in_process,
                ),
            )
            for a in args
        ]
        if in_process:
            return [_train_one(job) for job in jobs]
        assert self._pool is not None
        return list(self._pool.map(_train_one, jobs))

    def close(self, cancel: bool = False) -> None:
        if self._pool is not None:
            if cancel:
                stop_workers(self._pool)
            else:
                self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
            self.n_processes = 0

    def __enter__(self) -> SeedRunner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close(cancel=exc[0] is not None)


# The fitness hooks of [`run_evolution`][ermrl.search.run_evolution]: one candidate
# (``evaluate(encoder, runner, report)``), or a whole generation with the population backend.
EvaluateFn = Callable[[EncoderConfig, SeedRunner, ReportFn | None], FitnessResult]
EvaluateGenerationFn = Callable[
    [Sequence[EncoderConfig], SeedRunner], list[FitnessResult | BaseException]
]


def train_runs(
    encoder: EncoderConfig | None,
    tasks: Sequence[tuple[TaskConfig, PPOConfig, Callable[[float], float] | None]],
    budget: BudgetConfig,
    seeds: Sequence[int],
    *,
    runner: SeedRunner,
    report: ReportFn | None = None,
) -> list[list[RunResult]]:
    """Train one PPO agent per (task, seed) with the same encoder: the core of every fitness.

    Args:
        encoder: The encoder's settings (``None``: the raw observation).
        tasks: One ``(task, ppo, normalize)`` per task; ``normalize`` maps a raw return to the
            value reported for pruning (``None``: the raw return).
        budget: Training budget of each run.
        seeds: Training seeds, the same on every task.
        runner: Where the runs go (a pool trains all of them in parallel).
        report: Intermediate returns for pruning, ``report(step, value)``; steps are counted
            across tasks then seeds (task ``i``, seed ``j`` starts at
            ``(i * len(seeds) + j) * training_steps``). Used only when runs stay in this process.

    Returns:
        The runs of each task, in seed order.
    """
    n_seeds = len(seeds)
    if report is not None and runner.n_procs == 1:
        per_task: list[list[RunResult]] = []
        for i, (task, ppo, normalize) in enumerate(tasks):
            runs = []
            for j, seed in enumerate(seeds):
                offset = (i * n_seeds + j) * budget.training_steps

                def run_report(
                    step: int,
                    value: float,
                    offset: int = offset,
                    normalize: Callable[[float], float] | None = normalize,
                ) -> None:
                    report(offset + step, value if normalize is None else normalize(value))

                progress = runner.run_progress(
                    f"seed {seed} on {task.label}",
                    steps_trained(ppo, budget.training_steps),
                    in_process=True,
                )
                log = runner.tensorboard_log(seed, task.env_id if len(tasks) > 1 else None)
                runs.append(
                    train_agent(
                        task,
                        encoder,
                        ppo,
                        budget,
                        seed,
                        report=run_report,
                        progress=progress,
                        tensorboard_log=log,
                    )  # fmt: skip
                )
            per_task.append(runs)
        return per_task
    args = [(task, encoder, ppo, budget, seed) for task, ppo, _ in tasks for seed in seeds]
    flat = runner.map(args, by_task=len(tasks) > 1)
    return [flat[i * n_seeds : (i + 1) * n_seeds] for i in range(len(tasks))]


def train_generation(
    encoders: Sequence[EncoderConfig],
    tasks: Sequence[tuple[TaskConfig, PPOConfig]],
    budget: BudgetConfig,
    seeds: Sequence[int],
    *,
    runner: SeedRunner,
) -> list[list[list[RunResult | BaseException]]]:
    """Train a whole generation with the population backend: every (candidate, seed) of a task
    in one population (split over the runner's processes), one task after another.

    With the runner's ``tensorboard`` folder, each run logs SB3's scalars where the sb3 backend
    would log it ([`SeedRunner.tensorboard_log`][ermrl.search.SeedRunner.tensorboard_log]), under
    its candidate's trial number (`SeedRunner.trials`).

    Returns:
        ``[candidate][task][seed]``: a run, or the exception that ended it (a diverged run fails
        alone; the other agents go on).

    Raises:
        ValueError: TensorBoard logs asked for without one trial number per candidate.
    """
    from ermrl.population import PopulationJob

    n_seeds = len(seeds)
    out: list[list[list[RunResult | BaseException]]] = [[] for _ in encoders]
    for task, ppo in tasks:
        jobs = [PopulationJob(enc, seed) for enc in encoders for seed in seeds]
        logs = _generation_logs(
            runner, len(encoders), seeds, task.env_id if len(tasks) > 1 else None
        )
        flat = runner.population(task, ppo, budget, jobs, tensorboard_logs=logs)
        for c in range(len(encoders)):
            out[c].append(flat[c * n_seeds : (c + 1) * n_seeds])
    return out


def _generation_logs(
    runner: SeedRunner, n_candidates: int, seeds: Sequence[int], env_id: str | None
) -> list[str | None] | None:
    """The TensorBoard folder of each (candidate, seed) job of a generation (``None``: no logs)."""
    if runner.tensorboard is None:
        return None
    if len(runner.trials) != n_candidates:
        raise ValueError(
            f"TensorBoard logs of a generation need one trial number per candidate "
            f"(runner.trials): {n_candidates} candidates, {len(runner.trials)} trials"
        )
    return [
        runner.tensorboard_log(seed, env_id, trial=trial)
        for trial in runner.trials
        for seed in seeds
    ]


def first_failure(runs: Sequence[RunResult | BaseException]) -> BaseException | None:
    """The first exception among a candidate's runs (its trial then fails), or ``None``."""
    return next((r for r in runs if isinstance(r, BaseException)), None)


def evaluate_encoders(
    encoders: Sequence[EncoderConfig], problem: Problem, *, runner: SeedRunner
) -> list[FitnessResult | BaseException]:
    """The fitness of each candidate of a generation, trained together (population backend).

    A candidate one of whose seeds diverged (or finished no episode) gets that exception instead
    of a fitness, as [`evaluate_encoder`][ermrl.search.evaluate_encoder] would raise it; the other
    candidates are unaffected.
    """
    start = time.perf_counter()
    trained = train_generation(
        encoders, [(problem.task, problem.ppo)], problem.budget, problem.seeds, runner=runner
    )
    share = (time.perf_counter() - start) / max(len(encoders), 1)
    out: list[FitnessResult | BaseException] = []
    for encoder, (runs,) in zip(encoders, trained):
        failure = first_failure(runs)
        if failure is not None:
            out.append(failure)
            continue
        done = [r for r in runs if isinstance(r, RunResult)]
        values = [r.fitness(problem.budget.fitness) for r in done]
        out.append(
            FitnessResult(
                fitness=float(np.mean(values)),
                mode=problem.budget.fitness,
                runs=done,
                wall_seconds=share,
                dtype=encoder.dtype,
                backend="population",
                population=len(encoders) * len(problem.seeds),
                n_last=problem.budget.n_last_episodes,
            )
        )
    return out


def evaluate_encoder(
    encoder: EncoderConfig | None,
    problem: Problem,
    *,
    runner: SeedRunner | None = None,
    report: ReportFn | None = None,
) -> FitnessResult:
    """Train one agent per seed on encoded observations; return the mean return.

    The single-task case of [`evaluate_generalization`][ermrl.search.evaluate_generalization]: both
    train through `train_runs`.

    Args:
        encoder: The candidate's encoder settings (decoded from a sampled point by the problem's
            encoder, see [`ermrl.encoders`][ermrl.encoders]); ``None`` trains on the raw
            observation.
        problem: Task, encoding options, PPO settings, budget and seeds.
        runner: Where the seeds run (default: one after another in this process).
        report: Intermediate-return callback for pruning, called as ``report(step, value)``
            with ``step`` counted across seeds; used only when seeds run in this process.

    Returns:
        The fitness and the per-seed runs.
    """
    start = time.perf_counter()
    runner = runner or SeedRunner(1)
    (runs,) = train_runs(
        encoder,
        [(problem.task, problem.ppo, None)],
        problem.budget,
        problem.seeds,
        runner=runner,
        report=report,
    )
    values = [r.fitness(problem.budget.fitness) for r in runs]
    return FitnessResult(
        fitness=float(np.mean(values)),
        mode=problem.budget.fitness,
        runs=runs,
        wall_seconds=time.perf_counter() - start,
        dtype=None if encoder is None else encoder.dtype,
        n_last=problem.budget.n_last_episodes,
    )
