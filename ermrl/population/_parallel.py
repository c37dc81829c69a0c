"""A population split over processes: ``--n-procs`` processes, each training a part of it.

Two processes with half the agents each beat two threads (the environments step in Python), and
an agent's result does not depend on which part it lands in (its random streams are its own), so
the split is a plain contiguous one.

Agents whose encoders differ in structure
([`encoder_structure`][ermrl.population.encoder_structure]: the units, an NVAR's delay and order)
see observations of different widths, so they cannot share one population; they are trained as one
population per structure, one after another (an agent's result does not depend on the population
around it either).
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from ermrl._progress import Progress, relayed_bar
from ermrl.agents._train import RunResult
from ermrl.config import BudgetConfig, PPOConfig, TaskConfig
from ermrl.population._envs import encoder_structure
from ermrl.population._ppo import PopulationJob, train_population

__all__ = ["group_jobs", "split_jobs", "train_population_parallel"]


def group_jobs(jobs: Sequence[PopulationJob]) -> list[list[int]]:
    """The indices of ``jobs`` grouped by encoder structure, in order of first appearance."""
    groups: dict[Any, list[int]] = {}
    for i, job in enumerate(jobs):
        groups.setdefault(encoder_structure(job.encoder), []).append(i)
    return list(groups.values())


def split_jobs(n_jobs: int, n_parts: int) -> list[range]:
    """Contiguous, near-equal parts of ``range(n_jobs)`` (at most ``n_parts``, none empty)."""
    n_parts = max(1, min(n_parts, n_jobs))
    size, extra = divmod(n_jobs, n_parts)
    parts, begin = [], 0
    for k in range(n_parts):
        end = begin + size + (1 if k < extra else 0)
        parts.append(range(begin, end))
        begin = end
    return parts


def _train_part(args: tuple[Any, ...]) -> list[RunResult | BaseException]:
    task, ppo, budget, jobs, evaluate, model_paths, progress, checkpoints, every, logs = args
    return train_population(
        task, ppo, budget, jobs, evaluate=evaluate, model_paths=model_paths, progress=progress,
        checkpoints=checkpoints, checkpoint_every=every, tensorboard_logs=logs,
    )  # fmt: skip


def train_population_parallel(
    task: TaskConfig,
    ppo: PPOConfig,
    budget: BudgetConfig,
    jobs: Sequence[PopulationJob],
    *,
    n_procs: int = 1,
    pool: ProcessPoolExecutor | None = None,
    evaluate: bool | None = None,
    model_paths: Sequence[str | Path | None] | None = None,
    progress: Progress | None = None,
    checkpoints: str | Path | None = None,
    checkpoint_every: int | None = None,
    tensorboard_logs: Sequence[str | Path | None] | None = None,
) -> list[RunResult | BaseException]:
    """[`train_population`][ermrl.population.train_population] with the jobs split over ``n_procs``
    processes.

    Args:
        pool: Processes to use (e.g. from [`training_pool`][ermrl.agents.training_pool], kept across
            generations); ``None`` with ``n_procs > 1``: a pool for this call only.
        n_procs: Parts the population is split into (1: this process).
        progress: The population's progress; with several parts, each part's process
            prints its own lines, labelled ``part k/n`` (lines even in ``"bar"`` mode: bars of
            several processes would overwrite each other on one terminal).
        checkpoints: A folder for each part's checkpoint (see
            [`train_population`][ermrl.population.train_population]); a rerun with the same jobs,
            split alike, resumes each part from its own.
        checkpoint_every: Env steps per agent between saves (default: a tenth of the budget).
        tensorboard_logs: Per job, its TensorBoard folder or ``None`` (see
            [`train_population`][ermrl.population.train_population]).

    Jobs whose encoders differ in structure ([`group_jobs`][ermrl.population.group_jobs]) are
    trained as one population per structure, one after another, each split over ``n_procs``
    processes.

    Returns:
        One result or exception per job, in order.
    """
    groups = group_jobs(jobs)
    if len(groups) > 1:
        results: list[RunResult | BaseException | None] = [None] * len(jobs)
        for k, group in enumerate(groups):
            part = train_population_parallel(
                task, ppo, budget, [jobs[i] for i in group],
                n_procs=n_procs, pool=pool, evaluate=evaluate, checkpoints=checkpoints,
                checkpoint_every=checkpoint_every,
                model_paths=None if model_paths is None else [model_paths[i] for i in group],
                tensorboard_logs=None if tensorboard_logs is None
                else [tensorboard_logs[i] for i in group],
                progress=None if progress is None
                else progress.renamed(f"{progress.label}, structure {k + 1}/{len(groups)}"),
            )  # fmt: skip
            for i, result in zip(group, part):
                results[i] = result
        return [r for r in results if r is not None]
    parts = split_jobs(len(jobs), n_procs)
    with relayed_bar(progress, len(parts)) as relayed:
        return _train_parts(
            task, ppo, budget, jobs, parts, pool, evaluate, model_paths, progress, relayed,
            checkpoints, checkpoint_every, tensorboard_logs,
        )  # fmt: skip


def _train_parts(
    task: TaskConfig,
    ppo: PPOConfig,
    budget: BudgetConfig,
    jobs: Sequence[PopulationJob],
    parts: Sequence[range],
    pool: ProcessPoolExecutor | None,
    evaluate: bool | None,
    model_paths: Sequence[str | Path | None] | None,
    progress: Progress | None,
    relayed: Sequence[Progress] | None,
    checkpoints: str | Path | None,
    checkpoint_every: int | None,
    tensorboard_logs: Sequence[str | Path | None] | None,
) -> list[RunResult | BaseException]:
    """Train the parts of one population, each in a process of ``pool`` (or one of its own);
    ``relayed``: the parts' progress reporting to one bar here, else each part prints lines."""
    args = [
        (
            task,
            ppo,
            budget,
            [jobs[i] for i in part],
            evaluate,
            None if model_paths is None else [model_paths[i] for i in part],
            None
            if progress is None
            else progress
            if len(parts) == 1
            else relayed[k]
            if relayed is not None
            else progress.renamed(f"{progress.label}, part {k + 1}/{len(parts)}"),
            checkpoints,
            checkpoint_every,
            None if tensorboard_logs is None else [tensorboard_logs[i] for i in part],
        )
        for k, part in enumerate(parts)
    ]
    if len(parts) == 1:
        return _train_part(args[0])
    if pool is None:
        from ermrl.agents._pool import training_pool

        with training_pool(len(parts)) as own:
            chunks = list(own.map(_train_part, args))
    else:
        chunks = list(pool.map(_train_part, args))
    return [result for chunk in chunks for result in chunk]
