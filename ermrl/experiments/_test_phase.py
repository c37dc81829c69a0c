"""The test phase: train the best evolved reservoir against baselines over many seeds.

Agents:

- ``ppo``: PPO on the raw (masked) observation;
- ``res-ppo``: PPO on the states of the best evolved reservoir(s);
- ``random-res-ppo``: PPO on reservoirs with default, unevolved hyperparameters (what evolution adds).

Every (agent, seed) run is saved in its own folder as soon as it finishes, so a test phase that
is interrupted, or split across SLURM array tasks, resumes and merges: the aggregated
``curves.csv``, ``summary.csv`` and ``learning_curves.png`` are rebuilt from all finished runs.
"""

from __future__ import annotations

import dataclasses
import shlex
import sys
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import optuna
import pandas as pd
import yaml

from ermrl.agents import RunResult, pool_size, train_agent, training_pool
from ermrl.analysis import (
    curves_on_grid,
    load_curves,
    load_run_results,
    plot_learning_curves,
    run_dir,
    summarize,
    write_atomic,
    write_run,
)
from ermrl.config import (
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    EvolveConfig,
    PPOConfig,
    ReservoirParams,
    TaskConfig,
    to_dict,
)

__all__ = [
    "AGENTS",
    "AgentSpec",
    "TestSettings",
    "default_test_seeds",
    "study_reservoirs",
    "run_comparison",
    "aggregate",
]

AGENTS: tuple[str, ...] = ("ppo", "res-ppo", "random-res-ppo")


@dataclass(frozen=True)
class AgentSpec:
    """One agent of a comparison: a name and its reservoirs (``None`` for plain PPO)."""

    name: str
    reservoirs: tuple[ReservoirParams, ...] | None


@dataclass(frozen=True)
class TestSettings:
    """How a comparison runs.

    Attributes:
        training_steps: Steps per run.
        seeds: Seeds; each agent trains once per seed.
        out: Output folder.
        n_procs: Cores for the runs (single-threaded processes; see
            :func:`~ermrl.agents.pool_size`).
        evaluate: Also run deterministic evaluation episodes after training.
        n_eval_episodes: Their number.
        n_last_episodes: Training episodes averaged into a run's final return.
        save_models: Save each trained model as ``model.zip`` in its run folder.
        overwrite: Retrain runs that already have results (default: skip them, i.e. resume).
        tensorboard: Log training curves for TensorBoard under ``<tensorboard>/<agent>/seed_<s>``
            (needs the ``tensorboard`` package).
    """

    __test__ = False  # not a pytest test class

    training_steps: int
    seeds: tuple[int, ...]
    out: Path
    n_procs: int = 1
    evaluate: bool = False
    n_eval_episodes: int = 5
    n_last_episodes: int = 10
    save_models: bool = True
    overwrite: bool = False
    tensorboard: Path | None = None

    def __post_init__(self) -> None:
        if self.training_steps < 1:
            raise ConfigError(f"training steps must be positive, got {self.training_steps}")
        if not self.seeds:
            raise ConfigError("at least one seed is needed")
        if self.n_procs < 1:
            raise ConfigError(f"n_procs must be >= 1, got {self.n_procs}")


def default_test_seeds(evolution_seeds: Sequence[int], n: int = 5) -> tuple[int, ...]:
    """``n`` seeds that evolution never trained on: the ones after its largest seed."""
    start = max(evolution_seeds) + 1 if evolution_seeds else 0
    return tuple(range(start, start + n))


def study_reservoirs(
    study: optuna.Study, config: EvolveConfig, trial_number: int | None = None
) -> tuple[dict[str, float], tuple[ReservoirParams, ...], int]:
    """The reservoirs of the best COMPLETE trial (or of ``trial_number``).

    Returns:
        The trial's parameters, its reservoirs and its number.

    Raises:
        ConfigError: the study has no complete trial, or no such trial.
    """
    if trial_number is None:
        try:
            trial = study.best_trial
        except ValueError as err:
            raise ConfigError(f"study {study.study_name!r} has no COMPLETE trial yet") from err
    else:
        matches = [t for t in study.get_trials(deepcopy=False) if t.number == trial_number]
        if not matches:
            raise ConfigError(f"study {study.study_name!r} has no trial {trial_number}")
        trial = matches[0]
    return dict(trial.params), config.space.reservoirs_from(trial.params), trial.number


def _train_job(args: tuple[Any, ...]) -> RunResult:
    task, encoder, ppo, budget, seed, evaluate, model_path, tensorboard_log = args
    return train_agent(
        task,
        encoder,
        ppo,
        budget,
        seed,
        evaluate=evaluate,
        model_path=model_path,
        tensorboard_log=tensorboard_log,
    )


def _say(stream: TextIO | None, quiet: bool, line: str) -> None:
    if not quiet:
        print(line, file=stream or sys.stdout, flush=True)


def run_comparison(
    task: TaskConfig,
    encoder: EncoderConfig,
    ppo: PPOConfig,
    agents: Sequence[AgentSpec],
    settings: TestSettings,
    *,
    metadata: Mapping[str, Any] | None = None,
    quiet: bool = False,
    stream: TextIO | None = None,
) -> pd.DataFrame:
    """Train every agent on every seed and write the comparison's results.

    Args:
        task: The environment.
        encoder: Encoding options (its reservoirs are replaced by each agent's).
        ppo: PPO settings shared by all agents.
        agents: The agents to compare.
        settings: Budget, seeds, output folder, parallelism.
        metadata: Saved in ``config.yaml`` (study name, storage, trial, ...).
        quiet: No progress lines.
        stream: Where progress lines go.

    Returns:
        The summary table (also written as ``summary.csv``).
    """
    out = Path(settings.out)
    out.mkdir(parents=True, exist_ok=True)
    budget = BudgetConfig(
        training_steps=settings.training_steps,
        n_last_episodes=settings.n_last_episodes,
        n_eval_episodes=settings.n_eval_episodes,
        fitness="eval" if settings.evaluate else "last",
        n_reports=0,
    )
    config_doc = {
        "task": to_dict(task),
        "encoder": to_dict(encoder),
        "ppo": to_dict(ppo),
        "settings": {
            k: (str(v) if isinstance(v, Path) else to_dict(v))
            for k, v in dataclasses.asdict(settings).items()
        },
        "agents": {a.name: None if a.reservoirs is None else to_dict(a.reservoirs) for a in agents},
        **dict(metadata or {}),
    }
    write_atomic(out / "config.yaml", yaml.safe_dump(config_doc, sort_keys=False))
    write_atomic(out / "command.txt", shlex.join(sys.argv) + "\n")

    jobs = []
    for seed in settings.seeds:
        for agent in agents:
            folder = run_dir(out, agent.name, seed)
            if (folder / "result.json").exists() and not settings.overwrite:
                _say(stream, quiet, f"[skip] {agent.name} seed {seed}: already done in {folder}")
                continue
            folder.mkdir(parents=True, exist_ok=True)
            enc = None if agent.reservoirs is None else encoder.with_reservoirs(agent.reservoirs)
            model_path = str(folder / "model.zip") if settings.save_models else None
            tb_log = (
                None
                if settings.tensorboard is None
                else str(Path(settings.tensorboard) / agent.name / f"seed_{seed}")
            )
            jobs.append(
                (agent, seed, (task, enc, ppo, budget, seed, settings.evaluate, model_path, tb_log))
            )

    started = time.perf_counter()
    done = 0

    def finished(agent: AgentSpec, seed: int, result: RunResult) -> None:
        nonlocal done
        done += 1
        extra = {
            "env_id": task.env_id,
            "observe": task.observe,
            "reservoirs": None if agent.reservoirs is None else to_dict(agent.reservoirs),
        }
        write_run(run_dir(out, agent.name, seed), agent.name, result, extra)
        elapsed = time.perf_counter() - started
        eta = elapsed / done * (len(jobs) - done)
        _say(
            stream,
            quiet,
            f"[run {done}/{len(jobs)}] {agent.name} seed {seed}: final return "
            f"{result.last_return:.4g} | {result.steps_per_second:.0f} steps/s | "
            f"{result.wall_seconds:.0f}s | ETA {eta:.0f}s",
        )

    if settings.n_procs == 1 or len(jobs) <= 1:
        for agent, seed, args in jobs:
            finished(agent, seed, _train_job(args))
    else:
        with training_pool(pool_size(len(jobs), settings.n_procs)) as pool:
            pending: dict[Future[RunResult], tuple[AgentSpec, int]] = {
                pool.submit(_train_job, args): (agent, seed) for agent, seed, args in jobs
            }
            try:
                while pending:
                    ready, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for future in ready:
                        agent, seed = pending.pop(future)
                        finished(agent, seed, future.result())
            except BaseException:
                for future in pending:
                    future.cancel()
                for proc in list(getattr(pool, "_processes", {}).values()):
                    proc.terminate()
                raise

    return aggregate(out, [a.name for a in agents], title=task.label)


def aggregate(
    out: str | Path, agents: Sequence[str] | None = None, *, title: str = ""
) -> pd.DataFrame:
    """Rebuild ``curves.csv``, ``summary.csv`` and ``learning_curves.png`` from finished runs."""
    out = Path(out)
    curves = load_curves(out)
    results = load_run_results(out)
    summary = summarize(results, agents)
    write_atomic(out / "curves.csv", curves.to_csv(index=False))
    write_atomic(out / "summary.csv", summary.to_csv(index=False))
    if not curves.empty:
        plot_learning_curves(
            curves_on_grid(curves), out / "learning_curves.png", title=title, agents=agents
        )
    return summary
