"""The outer loop: an Optuna study that proposes reservoirs and records their fitness.

One call of :func:`run_evolution` is one *worker*. Any number of workers (processes, machines,
SLURM array tasks) may share a study:

- **Exact budget.** ``n_trials`` is the study's total of COMPLETE, PRUNED, RUNNING and WAITING
  trials. A worker *claims* a trial (counts, then ``study.ask()``) under the storage's
  inter-process lock (:func:`ermrl.storage.study_lock`), so the workers never overshoot.
- **Dead workers.** RUNNING trials send heartbeats. Before each claim, a worker fails the trials
  whose heartbeat stopped (``grace_period``) and queues a WAITING copy with the same parameters
  (:class:`ermrl.storage.RetryStaleTrial`), which the next claim picks up. When the budget is
  reached while other workers' trials still run, a worker waits for them, so that a trial whose
  worker died is still retried.
- **SIGTERM** (SLURM time limit, preemption) closes the running trial as FAIL, queues its retry
  and raises :class:`Interrupted`; Ctrl-C closes it as FAIL and raises ``KeyboardInterrupt``.
  Signals that arrive while a worker talks to the storage are handled right after, so a claim or
  a ``tell`` is never cut in half.

Re-running the same command resumes the study.
"""

from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TextIO

import optuna
from optuna.distributions import FloatDistribution
from optuna.exceptions import ExperimentalWarning, UpdateFinishedTrialError
from optuna.storages._heartbeat import get_heartbeat_thread, is_heartbeat_enabled
from optuna.trial import FrozenTrial, TrialState

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
from ermrl.search._samplers import RestartCmaEsSampler
from ermrl.storage import (
    DEFAULT_GRACE_PERIOD,
    DEFAULT_HEARTBEAT_INTERVAL,
    DEFAULT_MAX_RETRY,
    RetryStaleTrial,
    fail_stale_trials,
    open_storage,
    storage_lock,
    study_lock,
    worker_info,
)
from ermrl.storage._heartbeat import base_storage

__all__ = [
    "STUDY_CONFIG_ATTR",
    "STUDY_COMMAND_ATTR",
    "EvolutionSummary",
    "Interrupted",
    "PopulationWarning",
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
    """Raised in the main thread on SIGTERM so that the running trial is closed like on Ctrl-C.

    Attributes:
        signum: The signal.
        trial_number: The trial this worker was running and closed as FAIL; ``None`` when the
            signal came between trials (nothing was running).
        requeued: Whether that trial was queued again (``False`` once its retries are spent).
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.trial_number: int | None = None
        self.requeued = False


class PopulationWarning(UserWarning):
    """More workers evaluate a study at once than the CMA-ES population size."""


class _SignalGuard:
    """SIGTERM -> :class:`Interrupted`, SIGINT -> ``KeyboardInterrupt``, deferred in critical
    sections (claiming a trial, telling a result) and raised at the next :meth:`check`.

    A second signal while one is already pending is raised at once (a way out of a hung storage).
    """

    def __init__(self) -> None:
        self.pending: int | None = None
        self._depth = 0

    def _handler(self, signum: int, frame: Any) -> None:
        second = self.pending is not None
        if not second:
            self.pending = signum
        if self._depth == 0 or second:
            self.check()

    def error(self) -> BaseException | None:
        """The exception of the pending signal, if any."""
        if self.pending is None:
            return None
        if self.pending == signal.SIGINT:
            return KeyboardInterrupt()
        return Interrupted(self.pending)

    def check(self) -> None:
        """Raise the pending signal's exception, if any."""
        error = self.error()
        if error is not None:
            raise error

    def wait(self, seconds: float) -> None:
        """Give a signal already on its way (e.g. to the whole process group) time to arrive."""
        deadline = time.monotonic() + seconds
        while self.pending is None and time.monotonic() < deadline:
            time.sleep(0.05)

    @contextmanager
    def deferred(self) -> Iterator[None]:
        self._depth += 1
        try:
            yield
        finally:
            self._depth = max(self._depth - 1, 0)

    @contextmanager
    def installed(self) -> Iterator[None]:
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = {s: signal.signal(s, self._handler) for s in (signal.SIGTERM, signal.SIGINT)}
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)


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


def search_distributions(space: ReservoirSpace) -> dict[str, FloatDistribution]:
    """The fixed search space as Optuna distributions (what :func:`sample_params` asks)."""
    return {name: FloatDistribution(r.low, r.high, log=r.log) for name, r in space.ranges().items()}


def cma_start(search: SearchConfig, space: ReservoirSpace) -> dict[str, float]:
    """The first CMA-ES mean: the reference reservoir (clipped into the box) or the box centre."""
    if search.start == "center":
        return space.center_params()
    ranges = space.ranges()
    return {
        name: min(max(value, ranges[name].low), ranges[name].high)
        for name, value in space.reference_params().items()
    }


def make_study_sampler(
    search: SearchConfig, space: ReservoirSpace | None = None
) -> optuna.samplers.BaseSampler:
    """The study's sampler; with ``space``, CMA-ES knows the space before any trial completes."""
    from ermrl.search._samplers import make_sampler

    fixed = search.sampler == "cmaes" and space is not None
    return make_sampler(
        search.sampler,  # type: ignore[arg-type]
        seed=search.sampler_seed,
        restart=search.restart,  # type: ignore[arg-type]
        popsize=search.popsize,
        consider_pruned_trials=search.pruner != "none",
        search_space=search_distributions(space) if fixed else None,  # type: ignore[arg-type]
        x0=cma_start(search, space) if fixed else None,  # type: ignore[arg-type]
    )


REFERENCE_ATTR = "reference"


def enqueue_reference(study: optuna.Study, space: ReservoirSpace) -> bool:
    """Queue the unevolved reference reservoir as a trial (user attribute ``reference``).

    Returns:
        ``False`` when the reference lies outside the search space (nothing is queued).
    """
    params = space.reference_params()
    if not space.contains(params):
        return False
    study.enqueue_trial(params, user_attrs={REFERENCE_ATTR: True}, skip_if_exists=True)
    return True


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
    config: EvolveConfig | None,
    storage_url: str,
    study_name: str,
    *,
    command: str | None = None,
    kind: str = "evolve",
    heartbeat_interval: int | None = DEFAULT_HEARTBEAT_INTERVAL,
    grace_period: int | None = DEFAULT_GRACE_PERIOD,
    max_retry: int | None = DEFAULT_MAX_RETRY,
) -> optuna.Study:
    """Create the study, or load it when it exists with the same problem and search space.

    Safe with many workers starting at once: the schema and the study are created under the
    storage's inter-process lock, and the first worker stores the configuration.

    Args:
        config: The run's configuration (``None``: create or load a bare study; the first
            worker that brings a configuration stores it).
        storage_url: Where the study lives (see :func:`ermrl.storage.open_storage`).
        study_name: The study's name.
        command: Launch command stored with the configuration (default: ``sys.argv``).
        kind: ``"evolve"`` or ``"generalization"``, stored as the ``ermrl_kind`` attribute.
        heartbeat_interval: Seconds between heartbeats of running trials (``None``: off).
        grace_period: Seconds without heartbeat before a running trial is failed and retried.
        max_retry: Retries of a trial whose worker died or was preempted (0: none; ``None``:
            no limit).

    Returns:
        The study.

    Raises:
        ConfigError: a study of that name exists with another configuration.
        StorageError: the storage cannot be opened.
    """
    storage = open_storage(
        storage_url,
        heartbeat_interval=heartbeat_interval,
        grace_period=grace_period,
        max_retry=max_retry,
    )
    search = config.search if config is not None else SearchConfig()
    sampler = make_study_sampler(search, config.space if config is not None else None)
    pruner = make_pruner(search.pruner)
    with storage_lock(storage_url, study_name):
        study = optuna.create_study(
            study_name=study_name,
            storage=storage,
            sampler=sampler,
            pruner=pruner,
            direction="maximize",
            load_if_exists=True,
        )
        if config is None:
            return study
        new = to_dict(config)
        stored = study.user_attrs.get(STUDY_CONFIG_ATTR)
        if stored is None:
            study.set_user_attr(STUDY_CONFIG_ATTR, new)
            study.set_user_attr(STUDY_KIND_ATTR, kind)
            study.set_user_attr(STUDY_COMMAND_ATTR, command or " ".join(sys.argv))
            from ermrl import __version__

            study.set_user_attr("ermrl_version", __version__)
            if config.search.reference_trial and not enqueue_reference(study, config.space):
                warnings.warn(
                    "the reference reservoir (sr = lr = input_scaling = 1) lies outside the "
                    "search space: it does not take part in this study",
                    stacklevel=2,
                )
            return study
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

_FIRST_POLL = 0.5  # seconds between the first claims while waiting for other workers' trials
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
            # Seeds run one after another, so `step` counts the env steps the trial used.
            trial.set_user_attr("env_steps", int(step))
            raise optuna.TrialPruned(f"pruned at step {step} (return {value:.4g})")

    return report


def cma_popsize(config: EvolveConfig) -> int | None:
    """The first CMA-ES population size of a run (``None`` for other samplers)."""
    if config.search.sampler != "cmaes":
        return None
    if config.search.popsize is not None:
        return config.search.popsize
    return 4 + math.floor(3 * math.log(len(config.space.param_names)))


def _popsize_message(popsize: int, workers: int, what: str) -> str:
    return (
        f"{what} {workers} but the CMA-ES population size is {popsize}: a generation is told "
        f"its first {popsize} COMPLETE trials, so the others are evaluated for little use. "
        f"Pass --popsize {workers} or more, or run at most {popsize} workers"
    )


def _retry_policy(study: optuna.Study) -> RetryStaleTrial | None:
    """The retry callback the study's storage was opened with (see ``open_storage``)."""
    callback = getattr(base_storage(study._storage), "heartbeat_stale_trial_callback", None)
    return callback if isinstance(callback, RetryStaleTrial) else None


@dataclass
class _Claim:
    """The outcome of one claim: a trial, or why there is none."""

    trial: optuna.Trial | None
    params: dict[str, float]
    running: int
    retry_of: int | None = None


def _claim(
    study: optuna.Study,
    space: ReservoirSpace,
    n_trials: int,
    stale_check: bool,
    queued_only: bool = False,
) -> _Claim:
    """Under the study lock: fail stale trials, count, and ask for a trial if the budget allows.

    WAITING trials (retries, enqueued trials) are counted and are always claimable. With
    ``queued_only``, nothing else is: the sampler never proposes a new point.
    """
    with study_lock(study), warnings.catch_warnings():
        warnings.simplefilter("ignore", ExperimentalWarning)
        # study.ask() warns that heartbeats are meant for study.optimize(); this loop runs them.
        warnings.filterwarnings("ignore", message=".*Heartbeat.*", category=UserWarning)
        if stale_check:
            fail_stale_trials(study)
        trials = study.get_trials(deepcopy=False, states=_COUNTED)
        waiting = any(t.state == TrialState.WAITING for t in trials)
        running = sum(t.state == TrialState.RUNNING for t in trials)
        if (len(trials) >= n_trials or queued_only) and not waiting:
            return _Claim(None, {}, running)
        trial = study.ask()
        params = sample_params(trial, space)
        if trial.user_attrs.get(REFERENCE_ATTR) and isinstance(study.sampler, RestartCmaEsSampler):
            # Every parameter is fixed, so Optuna never asked CMA-ES: ask it now, so that the
            # reference is labelled and told to CMA-ES as a member of the current generation.
            _ = trial.relative_params
        for key, value in worker_info().items():
            trial.set_user_attr(f"worker_{key}", value)
        trial.set_user_attr("worker_n_trials", n_trials)  # this worker's budget (study show)
        retry_of = trial.user_attrs.get("retry_of") if waiting else None
    return _Claim(trial, params, running + 1, retry_of)


def _requeue(study: optuna.Study, trial_id: int, retry: RetryStaleTrial | None) -> int | None:
    """Queue a WAITING copy of a running trial (before it is closed: the count never drops).

    Returns:
        The number of the original trial of the retry chain, or ``None`` if not retried.
    """
    if retry is None:
        return None
    frozen: FrozenTrial = study._storage.get_trial(trial_id)
    if not retry.would_retry(frozen):
        return None
    retry(study, frozen)
    return int(frozen.system_attrs.get("failed_trial", frozen.number))


def run_evolution(
    config: EvolveConfig,
    study: optuna.Study,
    *,
    quiet: bool = False,
    stream: TextIO | None = None,
    evaluate: EvaluateFn | None = None,
    wait_for_running: bool = True,
    requeue_interrupted: bool = True,
    n_workers: int | None = None,
    queued_only: bool = False,
) -> EvolutionSummary:
    """Run trials until the study holds ``config.search.n_trials`` counted trials.

    COMPLETE, PRUNED, RUNNING and WAITING trials count towards the budget, and trials are claimed
    under the storage's lock, so several workers sharing a study stop together at exactly the
    budget. A trial whose training diverges (NaN) or finishes no episode is marked FAIL and the
    worker goes on (a FAIL trial does not count: another one replaces it), unless its last
    ``n_trials`` trials all failed (a broken problem must not loop forever). Ctrl-C marks the
    running trial FAIL and re-raises; SIGTERM does the same, queues a retry of the trial with the
    same parameters and raises :class:`Interrupted`. Nothing else is lost either way.

    Args:
        config: The run's configuration.
        study: A study from :func:`create_or_resume_study`.
        quiet: No progress lines.
        stream: Where progress lines go (default ``sys.stdout``).
        evaluate: Fitness of a candidate, called as ``evaluate(reservoirs, runner, report)``
            (default: :func:`~ermrl.search.evaluate_reservoir` on ``config.problem``; the
            generalization pipeline passes a multi-task fitness).
        wait_for_running: When the budget is reached but trials of other workers still run, wait
            for them (with heartbeats on): a trial whose worker died is then failed and retried
            here, and the study ends with ``n_trials`` finished trials.
        requeue_interrupted: On SIGTERM, queue a WAITING copy of the interrupted trial (within
            the storage's ``max_retry``).
        n_workers: Workers expected to share the study, for the population-size warning
            (default: ``SLURM_ARRAY_TASK_COUNT`` when set).
        queued_only: Run only queued (WAITING) trials, never ask the sampler for a new point
            (re-evaluation: a failed candidate is not replaced by a random one).

    Returns:
        What this worker did.

    Raises:
        Interrupted: SIGTERM arrived (the running trial was closed).
        KeyboardInterrupt: Ctrl-C (the running trial was closed).
    """
    out = stream or sys.stdout
    summary = EvolutionSummary()
    n_trials = config.search.n_trials
    problem = config.problem
    durations: list[float] = []
    heartbeats = is_heartbeat_enabled(study._storage)
    # Waiting for other workers' trials at the end: a claim is cheap, so poll at 0.5 s first (a
    # trial about to end is seen at once) and back off to at most `poll` for long waits.
    interval = float(study._storage.get_heartbeat_interval() or 1) if heartbeats else 1.0
    poll = min(max(interval / 2, 0.5), 5.0)
    retry = _retry_policy(study)
    popsize = cma_popsize(config)
    warned_popsize = False

    def say(line: str) -> None:
        if not quiet:
            print(line, file=out, flush=True)

    expected = n_workers or int(os.environ.get("SLURM_ARRAY_TASK_COUNT", "0") or 0)
    if popsize is not None and expected > popsize:
        warnings.warn(
            _popsize_message(popsize, expected, "this study expects up to"),
            PopulationWarning,
            stacklevel=2,
        )
        warned_popsize = True

    done_before = _n_counted(study)
    queued = len(study.get_trials(deepcopy=False, states=(TrialState.WAITING,)))
    if done_before >= n_trials and not queued:
        say(
            f"study {study.study_name!r} already has {done_before}/{n_trials} trials: nothing to do"
        )
    guard = _SignalGuard()
    waiting_said = False
    wait = _FIRST_POLL
    failed_in_a_row = 0
    with SeedRunner(config.n_procs) as runner, guard.installed():
        if config.n_procs > 1 and (done_before < n_trials or queued):
            n_tasks = len(config.generalization.tasks) if config.generalization else 1
            n_runs = n_tasks * len(problem.seeds)
            with guard.deferred():
                size = runner.start(n_runs)
            say(
                f"{n_runs} training runs per trial on {config.n_procs} cores: "
                f"{size} single-threaded processes"
                + (
                    " (more processes than cores keeps every core busy)"
                    if size > config.n_procs
                    else ""
                )
            )
        while True:
            guard.check()
            with guard.deferred():
                claim = _claim(study, config.space, n_trials, heartbeats, queued_only)
            if claim.trial is None:
                if wait_for_running and heartbeats and claim.running > 0:
                    if not waiting_said:
                        say(
                            f"budget reached; waiting for {claim.running} running trial(s) of "
                            "other workers (a trial whose worker died is retried here)"
                        )
                        waiting_said = True
                    time.sleep(wait)
                    wait = min(wait * 1.5, poll)
                    continue
                break
            trial, params = claim.trial, claim.params
            wait = _FIRST_POLL
            if popsize is not None and claim.running > popsize and not warned_popsize:
                warnings.warn(
                    _popsize_message(popsize, claim.running, "trials running at once:"),
                    PopulationWarning,
                    stacklevel=2,
                )
                warned_popsize = True
            heartbeat = get_heartbeat_thread(trial._trial_id, study._storage)
            heartbeat.start()
            summary.trials_run += 1
            started = time.perf_counter()
            use_report = _pruning_reporter(trial) if config.search.pruner != "none" else None
            state = TrialState.COMPLETE
            result: FitnessResult | None = None
            note = ""
            try:
                guard.check()  # a signal that arrived during the claim
                reservoirs = config.space.reservoirs_from(params)
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
            except BaseException as err:
                _close_interrupted(
                    study, trial, err, guard, runner, heartbeat, say,
                    retry if requeue_interrupted else None,
                )  # fmt: skip
                raise
            with guard.deferred():
                heartbeat.join()
                elapsed = time.perf_counter() - started
                durations.append(elapsed)
                closed = _record(study, trial, state, result, note)
            if closed is None:
                say(f"[trial {trial.number}] was closed by another worker (stale); result dropped")
                continue
            if state == TrialState.COMPLETE:
                summary.completed += 1
                failed_in_a_row = 0
            elif state == TrialState.PRUNED:
                summary.pruned += 1
                failed_in_a_row = 0
            else:
                summary.failed += 1
                failed_in_a_row += 1

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
            retried = "" if claim.retry_of is None else f" | retry of #{claim.retry_of}"
            say(
                f"[trial {trial.number} | {counted}/{n_trials}{retried}] {format_params(params)} | "
                f"{outcome} | best {best} | {speed} | ETA {_fmt_duration(eta)}"
            )
            if failed_in_a_row >= n_trials:
                say(
                    f"stopping: the last {failed_in_a_row} trials of this worker failed "
                    "(FAIL trials do not count towards the budget; is the problem broken?)"
                )
                break

    summary.best_value, _, summary.best_params = _best(study)
    return summary


def _record(
    study: optuna.Study,
    trial: optuna.Trial,
    state: TrialState,
    result: FitnessResult | None,
    note: str,
) -> FrozenTrial | None:
    """Store a finished trial's attributes and state (``None``: another worker closed it)."""
    try:
        if state == TrialState.FAIL:
            trial.set_user_attr("fail_reason", note)
        if result is not None:
            for key, value in result.user_attrs().items():
                trial.set_user_attr(key, value)
        if state == TrialState.COMPLETE:
            assert result is not None
            return study.tell(trial, result.fitness)
        return study.tell(trial, state=state)
    except UpdateFinishedTrialError:
        return None
    except ValueError as err:  # tell on a trial failed as stale by another worker
        if "Cannot tell a" in str(err):
            return None
        raise


def _close_interrupted(
    study: optuna.Study,
    trial: optuna.Trial,
    err: BaseException,
    guard: _SignalGuard,
    runner: SeedRunner,
    heartbeat: Any,
    say: Callable[[str], None],
    retry: RetryStaleTrial | None,
) -> None:
    """Close a trial cut short by a signal or an error as FAIL (SIGTERM: and queue its retry).

    When SLURM signals a whole job, the seed processes may die before this process receives its
    own SIGTERM; a broken process pool therefore waits a moment for that signal.
    """
    with guard.deferred():
        if isinstance(err, BrokenProcessPool) and guard.pending is None:
            guard.wait(2.0)
        runner.close(cancel=True)
        heartbeat.join()
        signum = err.signum if isinstance(err, Interrupted) else guard.pending
        if isinstance(err, KeyboardInterrupt) and not isinstance(err, Interrupted):
            signum = signal.SIGINT
        if signum is None:
            reason = repr(err)
        elif signum == signal.SIGINT:
            reason = "interrupted"
        else:
            reason = f"interrupted by {signal.Signals(signum).name}"
        retry_of = None
        try:
            if signum is not None and signum != signal.SIGINT:
                retry_of = _requeue(study, trial._trial_id, retry)
            trial.set_user_attr("fail_reason", reason)
            study.tell(trial, state=TrialState.FAIL)
        except (UpdateFinishedTrialError, ValueError):
            pass  # already closed by another worker as stale
        queued = "" if retry_of is None else f"; queued again (retry of #{retry_of})"
        say(f"[trial {trial.number}] closed as FAIL ({reason}){queued}")
    if isinstance(err, KeyboardInterrupt):  # Interrupted (SIGTERM) or Ctrl-C
        err.trial_number, err.requeued = trial.number, retry_of is not None  # type: ignore[attr-defined]
    if signum is not None and not isinstance(err, KeyboardInterrupt):
        error = guard.error() or Interrupted(signum)
        if isinstance(error, Interrupted):
            error.trial_number, error.requeued = trial.number, retry_of is not None
        raise error from err
