"""Finding trials whose worker died, and retrying them.

RDB storages (SQLite, PostgreSQL, MySQL) use Optuna's own heartbeat: a thread records a
timestamp per running trial every ``heartbeat_interval`` seconds, and
`optuna.storages.fail_stale_trials` marks FAIL the RUNNING trials whose last heartbeat is
older than ``grace_period``.

Journal storages (file or Redis) have no heartbeat in Optuna.
[`HeartbeatJournalStorage`][ermrl.storage.HeartbeatJournalStorage] adds the same mechanism: the
heartbeat is the trial system attribute ``ermrl:heartbeat`` (a Unix time), so ``fail_stale_trials``
and Optuna's heartbeat thread work on it unchanged. Clocks of the machines sharing a journal must
agree to well within the grace period (NTP does).

A stale trial is retried by [`RetryStaleTrial`][ermrl.storage.RetryStaleTrial]: a WAITING copy with
the same parameters, which the next ``study.ask()`` of any worker picks up.
"""

from __future__ import annotations

import copy
import logging
import time
import warnings
from collections.abc import Callable
from datetime import datetime, timezone
from typing import Any

import optuna
from optuna.exceptions import ExperimentalWarning, UpdateFinishedTrialError
from optuna.storages import BaseStorage, JournalStorage, RetryHeartbeatStaleTrialCallback
from optuna.storages._heartbeat import BaseHeartbeat
from optuna.storages.journal import BaseJournalBackend
from optuna.trial import FrozenTrial, TrialState

from ermrl.storage._url import StorageError

_log = logging.getLogger("ermrl.storage")

__all__ = [
    "HEARTBEAT_ATTR",
    "HeartbeatJournalStorage",
    "RetryStaleTrial",
    "base_storage",
    "find_stale_trials",
    "fail_stale",
    "fail_stale_trials",
    "last_seen",
]

HEARTBEAT_ATTR = "ermrl:heartbeat"
# System attributes a retried trial must not inherit: the CMA-ES optimizer stored on the failed
# trial (a COMPLETE copy with a higher number would roll the CMA-ES state back) and heartbeats.
_NOT_INHERITED = (":state:", ":optimizer:", ":restart_state", HEARTBEAT_ATTR)
# User attributes of the failed run, not of the retry (the worker that runs it writes its own).
_NOT_INHERITED_USER = ("fail_reason", "worker_")


def _utc(moment: datetime) -> datetime:
    """Naive datetimes from Optuna are local time; make every datetime UTC-aware."""
    return moment.astimezone(timezone.utc)


class HeartbeatJournalStorage(JournalStorage, BaseHeartbeat):
    """A `JournalStorage` with Optuna's heartbeat protocol.

    Args:
        backend: The journal backend (file or Redis).
        heartbeat_interval: Seconds between heartbeats of a running trial (``None``: off).
        grace_period: Seconds without heartbeat after which a RUNNING trial is stale
            (default ``2 * heartbeat_interval``, as in Optuna).
        heartbeat_stale_trial_callback: Called with each trial failed as stale (e.g.
            [`RetryStaleTrial`][ermrl.storage.RetryStaleTrial]).
    """

    def __init__(
        self,
        backend: BaseJournalBackend,
        *,
        heartbeat_interval: int | None = None,
        grace_period: int | None = None,
        heartbeat_stale_trial_callback: Callable[[optuna.Study, FrozenTrial], None] | None = None,
    ) -> None:
        super().__init__(backend)
        if heartbeat_interval is not None and heartbeat_interval <= 0:
            raise ValueError(f"heartbeat_interval must be positive, got {heartbeat_interval}")
        if grace_period is not None and grace_period <= 0:
            raise ValueError(f"grace_period must be positive, got {grace_period}")
        self.heartbeat_interval = heartbeat_interval
        self.grace_period = grace_period
        self.heartbeat_stale_trial_callback = heartbeat_stale_trial_callback

    def record_heartbeat(self, trial_id: int) -> None:
        """Write the current time to the trial's ``ermrl:heartbeat`` system attribute."""
        try:
            self.set_trial_system_attr(trial_id, HEARTBEAT_ATTR, time.time())
        except UpdateFinishedTrialError:
            pass  # finished (or failed as stale by another worker) meanwhile
        except (StorageError, OSError) as err:  # unreachable past the retry window, or a
            # journal file that cannot be written (a full disk): the next one counts
            _log.warning("missed a heartbeat of trial id %d: %s", trial_id, err)

    def _get_stale_trial_ids(self, study_id: int) -> list[int]:
        assert self.heartbeat_interval is not None
        grace = self.grace_period or 2 * self.heartbeat_interval
        now = time.time()
        trials = self.get_all_trials(study_id, deepcopy=False, states=(TrialState.RUNNING,))
        return [t._trial_id for t in trials if now - last_seen(t) > grace]

    def get_heartbeat_interval(self) -> int | None:
        return self.heartbeat_interval

    def get_heartbeat_stale_trial_callback(
        self,
    ) -> Callable[[optuna.Study, FrozenTrial], None] | None:
        return self.heartbeat_stale_trial_callback


class RetryStaleTrial(RetryHeartbeatStaleTrialCallback):
    """Optuna's `RetryHeartbeatStaleTrialCallback`, made safe for CMA-ES.

    The WAITING copy keeps the parameters, the user attributes and the CMA-ES generation of the
    failed trial, and records ``retry_history`` (Optuna's convention), but not the stored CMA-ES
    optimizer state (``cma:state:*``, or an older ermrl's ``cma:optimizer:*``), the heartbeat,
    the ``fail_reason`` or the ``worker_*`` attributes of the dead worker. Its user attribute
    ``retry_of`` is the number of the first failed trial of the chain.

    Args:
        max_retry: Retries of one original trial at most (``None``: no limit).
    """

    def __init__(self, max_retry: int | None = 3) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ExperimentalWarning)
            super().__init__(max_retry=max_retry)

    @property
    def max_retry(self) -> int | None:
        return self._max_retry

    def __call__(self, study: optuna.Study, trial: FrozenTrial) -> None:
        clean = copy.copy(trial)
        clean.system_attrs = {
            k: v
            for k, v in trial.system_attrs.items()
            if not any(part in k for part in _NOT_INHERITED)
        }
        user = {k: v for k, v in trial.user_attrs.items() if not k.startswith(_NOT_INHERITED_USER)}
        user["retry_of"] = trial.system_attrs.get("failed_trial", trial.number)
        clean.user_attrs = user
        super().__call__(study, clean)

    def would_retry(self, trial: FrozenTrial) -> bool:
        """Whether calling this callback on ``trial`` creates a retry (``max_retry`` allows it)."""
        history = trial.system_attrs.get("retry_history", [])
        return self._max_retry is None or len(history) + 1 <= self._max_retry


def base_storage(storage: BaseStorage) -> BaseStorage:
    """The storage under Optuna's ``_CachedStorage`` wrapper (RDB studies are wrapped)."""
    inner = getattr(storage, "_backend", None)
    return inner if isinstance(inner, BaseStorage) else storage


def _rdb_heartbeats(storage: Any, study_id: int) -> dict[int, datetime]:
    """Last heartbeat (UTC) of every trial of an RDB study that has one."""
    import sqlalchemy
    from optuna.storages._rdb import models

    query = (
        sqlalchemy.select(models.TrialHeartbeatModel.trial_id, models.TrialHeartbeatModel.heartbeat)
        .join(models.TrialModel, models.TrialModel.trial_id == models.TrialHeartbeatModel.trial_id)
        .where(models.TrialModel.study_id == study_id)
    )
    with storage.engine.connect() as conn:
        rows = conn.execute(query).all()
        db_now = conn.execute(sqlalchemy.select(sqlalchemy.func.now())).scalar()
    # Heartbeats are the server's now(): shift them onto this machine's clock.
    skew = datetime.now(timezone.utc) - _db_time_utc(db_now, storage)
    return {trial_id: _db_time_utc(beat, storage) + skew for trial_id, beat in rows}


def _db_time_utc(moment: datetime, storage: Any) -> datetime:
    if moment.tzinfo is not None:
        return moment.astimezone(timezone.utc)
    # SQLite's CURRENT_TIMESTAMP is UTC; other servers return their session's local time.
    if storage.engine.dialect.name == "sqlite":
        return moment.replace(tzinfo=timezone.utc)
    return moment.astimezone(timezone.utc)


def last_seen(trial: FrozenTrial, heartbeats: dict[int, datetime] | None = None) -> float:
    """Unix time of the last sign of life of a trial: its latest heartbeat, else its start."""
    times = []
    if trial.datetime_start is not None:
        times.append(_utc(trial.datetime_start).timestamp())
    beat = trial.system_attrs.get(HEARTBEAT_ATTR)
    if isinstance(beat, (int, float)):
        times.append(float(beat))
    if heartbeats and trial._trial_id in heartbeats:
        times.append(heartbeats[trial._trial_id].timestamp())
    return max(times) if times else 0.0


def find_stale_trials(study: optuna.Study, older_than: float) -> list[FrozenTrial]:
    """RUNNING trials with no sign of life (heartbeat, else start) for ``older_than`` seconds.

    Works on every backend: RDB heartbeats (Optuna's table), journal heartbeats
    (``ermrl:heartbeat``) or, for trials without any heartbeat, the start time.
    """
    storage = base_storage(study._storage)
    heartbeats = None
    if hasattr(storage, "engine"):
        heartbeats = _rdb_heartbeats(storage, study._study_id)
    now = time.time()
    running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    return [t for t in running if now - last_seen(t, heartbeats) > older_than]


def _grace(storage: BaseStorage) -> float | None:
    inner = base_storage(storage)
    interval = getattr(inner, "heartbeat_interval", None)
    grace = getattr(inner, "grace_period", None)
    return grace or (2 * interval if interval else None)


def _stale_trial_ids(study: optuna.Study, storage: BaseHeartbeat, grace: float | None) -> list[int]:
    """The storage's stale trials, and the RUNNING trials that never sent a heartbeat.

    Optuna's RDB check skips a RUNNING trial without any heartbeat row, so a worker killed
    between ``ask()`` and its first heartbeat left its trial RUNNING forever (and every other
    worker waiting for it). Such a trial is stale once its start is older than the grace period,
    as on journal storages.
    """
    ids = list(storage._get_stale_trial_ids(study._study_id))
    if grace is not None:
        ids += [t._trial_id for t in find_stale_trials(study, grace) if t._trial_id not in ids]
    return ids


def fail_stale_trials(study: optuna.Study) -> list[FrozenTrial]:
    """Optuna's `fail_stale_trials`, with a ``fail_reason`` on each trial.

    A trial whose worker stopped sending heartbeats (killed with ``kill -9``, a dead node), or
    that has run longer than the grace period without ever sending one (its worker died before
    the first heartbeat; so every worker of a study must use heartbeats, or none), is marked FAIL with the user attribute ``fail_reason`` set to ``"heartbeat lost (none for G s),
    retried as trial N"``, or ``"heartbeat lost (none for G s), not retried (max_retry M
    reached)"``, then retried by the storage's stale-trial callback
    ([`RetryStaleTrial`][ermrl.storage.RetryStaleTrial]).

    The trial number ``N`` is that of the WAITING copy the callback adds: exact when no other
    process adds trials meanwhile, which holding [`study_lock`][ermrl.storage.study_lock] (as
    ermrl's workers and ``ermrl study fail-stale`` do) guarantees.

    Args:
        study: The study (its storage must have heartbeats, else nothing is done).

    Returns:
        The trials failed, as they were before failing.
    """
    from optuna.storages._heartbeat import is_heartbeat_enabled

    storage = study._storage
    if not isinstance(storage, BaseHeartbeat) or not is_heartbeat_enabled(storage):
        return []
    callback = storage.get_heartbeat_stale_trial_callback()
    grace = _grace(storage)
    stale_ids = _stale_trial_ids(study, storage, grace)
    if not stale_ids:
        return []
    lost = "heartbeat lost" + (f" (none for {grace:.0f} s)" if grace else "")
    next_number = len(study.get_trials(deepcopy=False))
    failed = []
    n_retries = 0
    for trial_id in stale_ids:
        trial = storage.get_trial(trial_id)
        retried = isinstance(callback, RetryStaleTrial) and callback.would_retry(trial)
        if isinstance(callback, RetryStaleTrial):
            if retried:
                reason = f"{lost}, retried as trial {next_number + n_retries}"
            else:
                reason = f"{lost}, not retried (max_retry {callback.max_retry} reached)"
        elif callback is not None:
            reason = f"{lost}, passed to {type(callback).__name__}"
        else:
            reason = f"{lost}, not retried"
        try:
            storage.set_trial_user_attr(trial_id, "fail_reason", reason)
            if not storage.set_trial_state_values(trial_id, state=TrialState.FAIL):
                continue
        except UpdateFinishedTrialError:
            continue  # finished, or failed by another process, meanwhile
        failed.append(trial)
        n_retries += retried
    if callback is not None:
        for trial in failed:
            callback(study, copy.deepcopy(storage.get_trial(trial._trial_id)))
    return failed


def fail_stale(
    study: optuna.Study,
    older_than: float,
    *,
    retry: RetryStaleTrial | None = None,
    dry_run: bool = False,
) -> list[tuple[FrozenTrial, bool]]:
    """Mark FAIL the trials of [`find_stale_trials`][ermrl.storage.find_stale_trials], and retry
    them.

    Run it under [`storage_lock`][ermrl.storage.storage_lock] (``ermrl study fail-stale`` does): two
    concurrent calls on a journal storage could both retry the same trial.

    Args:
        study: The study.
        older_than: Seconds without a sign of life.
        retry: Creates the WAITING copies (``None``: no retry).
        dry_run: Only report what would be done.

    Returns:
        ``(trial, retried)`` for each stale trial (failed unless ``dry_run``).
    """
    out = []
    for trial in find_stale_trials(study, older_than):
        retried = retry is not None and retry.would_retry(trial)
        if dry_run:
            out.append((trial, retried))
            continue
        try:
            reason = f"stale: no heartbeat for {older_than:.0f} s"
            study._storage.set_trial_user_attr(trial._trial_id, "fail_reason", reason)
            if not study._storage.set_trial_state_values(trial._trial_id, state=TrialState.FAIL):
                continue
        except UpdateFinishedTrialError:
            continue  # finished meanwhile
        if retry is not None:
            retry(study, study._storage.get_trial(trial._trial_id))
        out.append((trial, retried))
    return out
