"""A worker's trials against the storage: claiming one under the study lock, recording its
result, and closing one cut short (by any signal or error: with a retry queued).

``n_trials`` is the study's total of COMPLETE, PRUNED, RUNNING and WAITING trials. A worker
*claims* a trial (counts, then ``study.ask()``) under the storage's inter-process lock
([`ermrl.storage.study_lock`][ermrl.storage.study_lock]), so the workers never overshoot. Before
each claim, a worker fails the trials whose heartbeat stopped and queues a WAITING copy with the
same parameters ([`ermrl.storage.RetryStaleTrial`][ermrl.storage.RetryStaleTrial]), which the next
claim picks up.
"""

from __future__ import annotations

import signal
import warnings
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

import optuna
from optuna.exceptions import ExperimentalWarning, UpdateFinishedTrialError
from optuna.trial import FrozenTrial, TrialState

from ermrl._code import code_identity
from ermrl.config import SearchSpace
from ermrl.search._objective import FitnessResult, SeedRunner
from ermrl.search._samplers import RestartCmaEsSampler
from ermrl.search._signals import Interrupted, SignalGuard
from ermrl.search._study import REFERENCE_ATTR, sample_params, warn_other_code
from ermrl.storage import RetryStaleTrial, fail_stale_trials, study_lock, worker_info
from ermrl.storage._heartbeat import base_storage

__all__ = [
    "CRASHED_ATTR",
    "COUNTED",
    "Claim",
    "claim_trial",
    "close_interrupted",
    "cut_short",
    "n_counted",
    "record",
    "requeue",
    "requeue_lost_reference",
    "retry_policy",
]

# User attribute of a trial closed as FAIL because the program raised (a bug, a worker process
# that died, code changed under a running command), not because training diverged: its
# measurement never happened, so a re-evaluation runs it again.
CRASHED_ATTR = "crashed"

COUNTED = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING, TrialState.WAITING)


def n_counted(study: optuna.Study) -> int:
    return len(study.get_trials(deepcopy=False, states=COUNTED))


def cut_short(trial: FrozenTrial) -> bool:
    """Whether a FAIL trial was cut short by a signal (Ctrl-C, SIGTERM) or by an error of the
    program (`CRASHED_ATTR`) rather than failing in training: it measured nothing."""
    reason = str(trial.user_attrs.get("fail_reason", ""))
    crashed = bool(trial.user_attrs.get(CRASHED_ATTR))
    return crashed or reason == "interrupted" or reason.startswith("interrupted by ")


def requeue_lost_reference(study: optuna.Study, space: SearchSpace) -> int | None:
    """Queue the reference trial again when every run of it was cut short and none is queued.

    A study from before every interruption queued its trials again (Ctrl-C did not), or one
    whose reference spent its retries on interruptions, would otherwise never train the
    unevolved reference, and the study's best could then be worse than it.

    Returns:
        The number of the reference trial queued again, or ``None`` (nothing to do).
    """
    with study_lock(study):
        runs = [t for t in study.get_trials(deepcopy=False) if t.user_attrs.get(REFERENCE_ATTR)]
        if not runs or not all(t.state == TrialState.FAIL and cut_short(t) for t in runs):
            return None
        first = runs[0]
        origin = first.user_attrs.get("retry_of", first.number)
        params = space.reference_params()
        study.enqueue_trial(params, user_attrs={REFERENCE_ATTR: True, "retry_of": origin})
        return int(origin)


def retry_policy(study: optuna.Study) -> RetryStaleTrial | None:
    """The retry callback the study's storage was opened with (see ``open_storage``)."""
    callback = getattr(base_storage(study._storage), "heartbeat_stale_trial_callback", None)
    return callback if isinstance(callback, RetryStaleTrial) else None


@dataclass
class Claim:
    """The outcome of one claim: a trial, or why there is none."""

    trial: optuna.Trial | None
    params: dict[str, float]
    running: int
    retry_of: int | None = None


def claim_trial(
    study: optuna.Study,
    space: SearchSpace,
    n_trials: int,
    stale_check: bool,
    queued_only: bool = False,
) -> Claim:
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
        trials = study.get_trials(deepcopy=False, states=COUNTED)
        warn_other_code(study, trials)  # another worker's code, new or old: say so, once
        waiting = any(t.state == TrialState.WAITING for t in trials)
        running = sum(t.state == TrialState.RUNNING for t in trials)
        if (len(trials) >= n_trials or queued_only) and not waiting:
            return Claim(None, {}, running)
        trial = study.ask()
        params = sample_params(trial, space)
        if trial.user_attrs.get(REFERENCE_ATTR) and isinstance(study.sampler, RestartCmaEsSampler):
            # Every parameter is fixed, so Optuna never asked CMA-ES: ask it now, so that the
            # reference is labelled and told to CMA-ES as a member of the current generation.
            _ = trial.relative_params
        for key, value in worker_info().items():
            trial.set_user_attr(f"worker_{key}", value)
        trial.set_user_attr("worker_n_trials", n_trials)  # this worker's budget (study show)
        trial.set_user_attr("ermrl_code", code_identity())  # seen by the others' next claims
        retry_of = trial.user_attrs.get("retry_of") if waiting else None
    return Claim(trial, params, running + 1, retry_of)


def requeue(study: optuna.Study, trial_id: int, retry: RetryStaleTrial | None) -> int | None:
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


def record(
    study: optuna.Study,
    trial: optuna.Trial,
    state: TrialState,
    result: FitnessResult | None,
    note: str,
) -> FrozenTrial | None:
    """Store a finished trial's attributes and state (``None``: another worker closed it)."""
    try:
        trial.set_user_attr("ermrl_code", code_identity())  # the code that trained it
        if state == TrialState.FAIL:
            trial.set_user_attr("fail_reason", note)
        if result is not None:
            for key, value in result.user_attrs().items():
                trial.set_user_attr(key, value)
            # A pruner reports its own; otherwise the training curve, for optuna-dashboard.
            if not study._storage.get_trial(trial._trial_id).intermediate_values:
                for step, value in result.learning_curve():
                    trial.report(value, step)
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


def close_interrupted(
    study: optuna.Study,
    trial: optuna.Trial,
    err: BaseException,
    guard: SignalGuard,
    runner: SeedRunner,
    heartbeat: Any,
    say: Callable[[str], None],
    retry: RetryStaleTrial | None,
) -> None:
    """Close a trial cut short by a signal or an error as FAIL and queue its retry.

    Whatever cut it short (Ctrl-C, SIGTERM, a crash), the trial measured nothing, so a WAITING
    copy with its parameters is queued (within the retry policy's ``max_retry``) before it is
    closed: the next worker trains it, and the reference trial is never lost.

    When SLURM signals a whole job, the seed processes may die before this process receives its
    own SIGTERM; a broken process pool therefore waits a moment for that signal.
    """
    with guard.deferred():
        if isinstance(err, BrokenProcessPool) and guard.pending is None:
            guard.wait(2.0)
        runner.close(cancel=True)
        heartbeat.join()
        # Interrupted (the guard's SIGTERM), Terminated (a SIGTERM a training loop raised again
        # after a callback dropped it: `ermrl._interrupt`), or Ctrl-C.
        signum = getattr(err, "signum", None) or guard.pending
        if isinstance(err, KeyboardInterrupt) and getattr(err, "signum", None) is None:
            signum = signal.SIGINT
        if signum is None:
            reason = repr(err)
        elif signum == signal.SIGINT:
            reason = "interrupted"
        else:
            reason = f"interrupted by {signal.Signals(signum).name}"
        retry_of = None
        try:
            retry_of = requeue(study, trial._trial_id, retry)
            trial.set_user_attr("fail_reason", reason)
            if signum is None:  # an error of the program, not an outcome of training
                trial.set_user_attr(CRASHED_ATTR, True)
            study.tell(trial, state=TrialState.FAIL)
        except (UpdateFinishedTrialError, ValueError):
            pass  # already closed by another worker as stale
        queued = "" if retry_of is None else f"; queued again (retry of #{retry_of})"
        say(f"[trial {trial.number}] closed as FAIL ({reason}){queued}")
    # Every trial closed for this error (a generation's: one call each), shared by the errors
    # raised for it, so that the command's last line counts them all.
    closed: list[tuple[int, bool]] = getattr(err, "closed_trials", [])
    closed.append((trial.number, retry_of is not None))
    err.closed_trials = closed  # type: ignore[attr-defined]
    if isinstance(err, KeyboardInterrupt):  # Interrupted (SIGTERM) or Ctrl-C
        err.trial_number, err.requeued = trial.number, retry_of is not None  # type: ignore[attr-defined]
    # A signal raised as another error (a broken pool, a SIGTERM raised again as Terminated)
    # becomes the guard's own (Interrupted for SIGTERM); Ctrl-C stays a KeyboardInterrupt.
    plain = isinstance(err, Interrupted) or (
        isinstance(err, KeyboardInterrupt) and signum == signal.SIGINT
    )
    if signum is not None and not plain:
        error = guard.error() or Interrupted(signum)
        error.trial_number, error.requeued = trial.number, retry_of is not None  # type: ignore[attr-defined]
        error.closed_trials = closed  # type: ignore[attr-defined]
        raise error from err
