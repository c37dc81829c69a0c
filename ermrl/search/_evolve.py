"""The outer loop: an Optuna study that proposes reservoirs and records their fitness.

One call of :func:`run_evolution` is one *worker*. Any number of workers may share a study: the
trial budget is the study's total, and re-running the same command resumes the study.
"""

from __future__ import annotations

import math
import signal
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TextIO

import optuna
from optuna.trial import TrialState

from ermrl.agents import NoEpisodeFinished, TrainingDiverged
from ermrl.config import (
    ConfigError,
    EvolveConfig,
    ReservoirParams,
    ReservoirSpace,
    SearchConfig,
    to_dict,
)
from ermrl.search._objective import FitnessResult, SeedRunner, evaluate_reservoir
from ermrl.storage import open_storage, worker_info

__all__ = [
    "STUDY_CONFIG_ATTR",
    "STUDY_COMMAND_ATTR",
    "EvolutionSummary",
    "Interrupted",
    "make_pruner",
    "sample_params",
    "create_or_resume_study",
    "study_config",
    "run_evolution",
    "format_params",
]

STUDY_CONFIG_ATTR = "ermrl_config"
STUDY_COMMAND_ATTR = "ermrl_command"
STUDY_KIND_ATTR = "ermrl_kind"
# Parts of the configuration that define the fitness landscape: a resumed study must match them.
_MUST_MATCH = ("problem", "space")


class Interrupted(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM so that the running trial is closed like on Ctrl-C."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Turn SIGTERM (SLURM time limit, preemption, ``kill``) into :class:`Interrupted`."""

    def handler(signum: int, frame: Any) -> None:
        raise Interrupted(signum)

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def make_pruner(name: str) -> optuna.pruners.BasePruner:
    """``none``, ``median`` (median of earlier trials at the same step) or ``halving``."""
    if name == "median":
        return optuna.pruners.MedianPruner(n_startup_trials=4, n_warmup_steps=0)
    if name == "halving":
        return optuna.pruners.SuccessiveHalvingPruner()
    if name == "none":
        return optuna.pruners.NopPruner()
    raise ConfigError(f"unknown pruner {name!r}")


def make_study_sampler(search: SearchConfig) -> optuna.samplers.BaseSampler:
    from ermrl.search._samplers import make_sampler

    return make_sampler(
        search.sampler,  # type: ignore[arg-type]
        seed=search.sampler_seed,
        restart=search.restart,  # type: ignore[arg-type]
        popsize=search.popsize,
    )


def sample_params(trial: optuna.Trial, space: ReservoirSpace) -> dict[str, float]:
    """Ask a trial for every evolved hyperparameter of the space (fixed order and ranges)."""
    return {
        name: trial.suggest_float(name, r.low, r.high, log=r.log)
        for name, r in space.ranges().items()
    }


def study_config(study: optuna.Study) -> EvolveConfig:
    """The configuration an ermrl study was created with.

    Raises:
        ConfigError: the study was not created by ``ermrl evolve``.
    """
    data = study.user_attrs.get(STUDY_CONFIG_ATTR)
    if data is None:
        raise ConfigError(f"study {study.study_name!r} has no ermrl configuration")
    return EvolveConfig.from_dict(data)


def _config_diff(a: Any, b: Any, path: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            out += _config_diff(a.get(key), b.get(key), f"{path}.{key}" if path else key)
        return out
    return [] if a == b else [f"{path}: {b!r} in the study, {a!r} now"]


def create_or_resume_study(
    config: EvolveConfig,
    storage_url: str,
    study_name: str,
    *,
    command: str | None = None,
    kind: str = "evolve",
    heartbeat_interval: int | None = None,
    grace_period: int | None = None,
) -> optuna.Study:
    """Create the study, or load it when it exists with the same problem and search space.

    Raises:
        ConfigError: a study of that name exists with another configuration.
        StorageError: the storage cannot be opened.
    """
    storage = open_storage(
        storage_url, heartbeat_interval=heartbeat_interval, grace_period=grace_period
    )
    sampler = make_study_sampler(config.search)
    pruner = make_pruner(config.search.pruner)
    study = optuna.create_study(
        study_name=study_name,
        storage=storage,
        sampler=sampler,
        pruner=pruner,
        direction="maximize",
        load_if_exists=True,
    )
    new = to_dict(config)
    stored = study.user_attrs.get(STUDY_CONFIG_ATTR)
    if stored is None:
        study.set_user_attr(STUDY_CONFIG_ATTR, new)
        study.set_user_attr(STUDY_KIND_ATTR, kind)
        study.set_user_attr(STUDY_COMMAND_ATTR, command or " ".join(sys.argv))
        from ermrl import __version__

        study.set_user_attr("ermrl_version", __version__)
    else:
        diffs = [d for key in _MUST_MATCH for d in _config_diff(new[key], stored.get(key), key)]
        if diffs:
            raise ConfigError(
                f"study {study_name!r} already exists with another configuration ("
                + "; ".join(diffs[:4])
                + (" ..." if len(diffs) > 4 else "")
                + "); pick another --study-name"
            )
    return study


def format_params(params: dict[str, float]) -> str:
    return " ".join(f"{k}={v:.3g}" for k, v in params.items())


def _fmt_duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}h{m:02d}m" if h else f"{m}m{s:02d}s"


@dataclass
class EvolutionSummary:
    """What one worker did.

    Attributes:
        trials_run: Trials this worker started.
        completed: Trials it completed.
        failed: Trials it marked FAIL (diverged, no episode, interrupted).
        pruned: Trials pruned.
        best_value: The study's best fitness at the end (``None`` if no trial completed).
        best_params: Its parameters.
    """

    trials_run: int = 0
    completed: int = 0
    failed: int = 0
    pruned: int = 0
    best_value: float | None = None
    best_params: dict[str, float] | None = None


EvaluateFn = Callable[
    [tuple[ReservoirParams, ...], SeedRunner, Callable[[int, float], None] | None], FitnessResult
]

_COUNTED = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING, TrialState.WAITING)


def _n_counted(study: optuna.Study) -> int:
    return len(study.get_trials(deepcopy=False, states=_COUNTED))


def _best(study: optuna.Study) -> tuple[float | None, int | None, dict[str, float] | None]:
    try:
        best = study.best_trial
    except ValueError:
        return None, None, None
    return best.value, best.number, best.params


def _pruning_reporter(trial: optuna.Trial):  # noqa: ANN202
    """Report intermediate returns to the study and raise TrialPruned when the pruner says so."""

    def report(step: int, value: float) -> None:
        trial.report(value, step)
        if trial.should_prune():
            raise optuna.TrialPruned(f"pruned at step {step} (return {value:.4g})")

    return report


def run_evolution(
    config: EvolveConfig,
    study: optuna.Study,
    *,
    quiet: bool = False,
    stream: TextIO | None = None,
    evaluate: EvaluateFn | None = None,
) -> EvolutionSummary:
    """Run trials until the study holds ``config.search.n_trials`` counted trials.

    COMPLETE, PRUNED, RUNNING and WAITING trials count towards the budget, so several workers
    sharing a study stop together. A trial whose training diverges (NaN) or finishes no episode is
    marked FAIL and the worker goes on. Ctrl-C or SIGTERM marks the running trial FAIL and
    re-raises, so that the process exits without losing anything else.

    Args:
        config: The run's configuration.
        study: A study from :func:`create_or_resume_study`.
        quiet: No progress lines.
        stream: Where progress lines go (default ``sys.stdout``).
        evaluate: Fitness of a candidate, called as ``evaluate(reservoirs, runner, report)``
            (default: :func:`~ermrl.search.evaluate_reservoir` on ``config.problem``; the
            generalization pipeline passes a multi-task fitness).

    Returns:
        What this worker did.
    """
    out = stream or sys.stdout
    summary = EvolutionSummary()
    n_trials = config.search.n_trials
    problem = config.problem
    durations: list[float] = []

    def say(line: str) -> None:
        if not quiet:
            print(line, file=out, flush=True)

    done_before = _n_counted(study)
    if done_before >= n_trials:
        say(
            f"study {study.study_name!r} already has {done_before}/{n_trials} trials: nothing to do"
        )
    with SeedRunner(config.n_procs) as runner, sigterm_as_interrupt():
        while True:
            if _n_counted(study) >= n_trials:
                break
            trial = study.ask()
            params = sample_params(trial, config.space)
            for key, value in worker_info().items():
                trial.set_user_attr(f"worker_{key}", value)
            reservoirs = config.space.reservoirs_from(params)
            summary.trials_run += 1
            started = time.perf_counter()

            use_report = _pruning_reporter(trial) if config.search.pruner != "none" else None
            state = TrialState.COMPLETE
            result: FitnessResult | None = None
            note = ""
            try:
                if evaluate is None:
                    result = evaluate_reservoir(
                        reservoirs, problem, runner=runner, report=use_report
                    )
                else:
                    result = evaluate(reservoirs, runner, use_report)
                if not math.isfinite(result.fitness):
                    raise TrainingDiverged(f"non-finite fitness {result.fitness}")
            except optuna.TrialPruned as err:
                state, note = TrialState.PRUNED, str(err)
            except (TrainingDiverged, NoEpisodeFinished) as err:
                state, note = TrialState.FAIL, str(err)
                trial.set_user_attr("fail_reason", note)
            except BaseException as err:
                # Ctrl-C, SIGTERM or a bug: close the trial as FAIL, then let the error end the run.
                reason = "interrupted" if isinstance(err, KeyboardInterrupt) else repr(err)
                try:
                    trial.set_user_attr("fail_reason", reason)
                    study.tell(trial, state=TrialState.FAIL)
                finally:
                    runner.close(cancel=True)
                say(f"[trial {trial.number}] closed as FAIL ({reason})")
                raise
            elapsed = time.perf_counter() - started
            durations.append(elapsed)
            if result is not None:
                for key, value in result.user_attrs().items():
                    trial.set_user_attr(key, value)
            if state == TrialState.COMPLETE:
                assert result is not None
                study.tell(trial, result.fitness)
                summary.completed += 1
            elif state == TrialState.PRUNED:
                study.tell(trial, state=TrialState.PRUNED)
                summary.pruned += 1
            else:
                study.tell(trial, state=TrialState.FAIL)
                summary.failed += 1

            best_value, best_number, _ = _best(study)
            counted = _n_counted(study)
            remaining = max(n_trials - counted, 0)
            eta = remaining * (sum(durations) / len(durations))
            if state == TrialState.COMPLETE and result is not None:
                outcome = f"fitness {result.fitness:.4g}"
                speed = f"{result.steps_per_second:.0f} steps/s"
            else:
                outcome = f"{state.name} ({note})"
                speed = f"{elapsed:.0f}s"
            best = "-" if best_value is None else f"{best_value:.4g} (#{best_number})"
            say(
                f"[trial {trial.number} | {counted}/{n_trials}] {format_params(params)} | "
                f"{outcome} | best {best} | {speed} | ETA {_fmt_duration(eta)}"
            )

    summary.best_value, _, summary.best_params = _best(study)
    return summary
