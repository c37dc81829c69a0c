"""Riding out a short storage outage: a worker's storage calls are retried, with backoff.

A database restart (PostgreSQL or MySQL stopped for half a minute, a Redis ``CLIENT PAUSE`` or
failover) used to kill every worker at its next storage call, with a traceback, and leave its
trial RUNNING. Now each call to a server storage that fails on the connection (the server is
down, refuses, drops or does not answer) is tried again, after 0.5 s, 1 s, 2 s, ... (at most
5 s apart), for up to `DEFAULT_RETRY_WINDOW_S` seconds (``ERMRL_STORAGE_RETRY_S``, or
``open_storage(retry_window=...)``). When the storage is still unreachable after that, the call
raises a one-line [`StorageError`][ermrl.storage.StorageError] (commands exit with it, code 2) and
the storage's later calls fail at once instead of waiting again. A missed heartbeat is only
logged: the trial's next one counts.

What is retried:

- PostgreSQL and MySQL (`RetryingRDBStorage`): every storage call whose database error
  is about the connection (SQLAlchemy's ``OperationalError`` or ``InterfaceError``), each in a
  fresh transaction (Optuna's ``RDBStorage`` rolls back a failed one);
- Redis journals (`PlainRedisBackend` and the claim lock): every Redis
  command on a connection or timeout error. A paused server holds the commands it receives and
  runs them when the pause ends, so the client waits as long as the retry window for an answer
  instead of timing out after 5 s and sending a record twice.

SQLite and journal files are local: they wait for their own locks and are not retried.
Opening a storage is not retried either: a wrong URL or a server that is down when a command
starts still fails within seconds.
"""

from __future__ import annotations

import functools
import logging
import os
import time
from collections.abc import Callable
from typing import Any, TypeVar

import optuna

from ermrl.storage._url import CONNECT_TIMEOUT_S, StorageError

__all__ = [
    "DEFAULT_RETRY_WINDOW_S",
    "RETRY_WINDOW_ENV",
    "Outage",
    "RetryingRDBStorage",
    "rdb_transient",
    "redis_client",
    "redis_transient",
    "retry_window",
]

DEFAULT_RETRY_WINDOW_S = 120.0
RETRY_WINDOW_ENV = "ERMRL_STORAGE_RETRY_S"
_FIRST_DELAY_S = 0.5
_MAX_DELAY_S = 5.0
# A Redis answer may take this much longer than the retry window before the client gives up.
_ANSWER_MARGIN_S = 5.0

_log = logging.getLogger("ermrl.storage")
T = TypeVar("T")


def retry_window(value: float | None = None) -> float:
    """Seconds a storage call is retried through an outage.

    Args:
        value: The window asked for (``None``: ``ERMRL_STORAGE_RETRY_S`` if set, else
            `DEFAULT_RETRY_WINDOW_S`); 0 turns retries off.

    Raises:
        StorageError: a negative or non-numeric window (one line).
    """
    if value is None:
        text = os.environ.get(RETRY_WINDOW_ENV, "").strip()
        if not text:
            return DEFAULT_RETRY_WINDOW_S
        try:
            value = float(text)
        except ValueError:
            raise StorageError(f"{RETRY_WINDOW_ENV}={text!r} is not a number of seconds") from None
    if not value >= 0 or value == float("inf"):
        raise StorageError(f"the storage retry window must be 0 or more seconds, got {value!r}")
    return float(value)


def _short(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


class Outage:
    """Retries of one storage's calls through an outage (plain data: it pickles).

    Args:
        storage: What the messages call the storage (its URL).
        window: Seconds a call is retried before it fails (0: never retried).
    """

    def __init__(self, storage: str, window: float) -> None:
        self.storage = storage
        self.window = window
        self.gave_up = False

    def call(
        self,
        transient: Callable[[BaseException], bool],
        fn: Callable[..., T],
        *args: Any,
        **kwargs: Any,
    ) -> T:
        """``fn(*args, **kwargs)``, tried again while it fails with a ``transient`` error.

        Raises:
            StorageError: still failing after the window (or at once once given up: one line).
        """
        start: float | None = None
        delay = _FIRST_DELAY_S
        while True:
            try:
                result = fn(*args, **kwargs)
            except Exception as err:
                if not transient(err):
                    raise
                now = time.monotonic()
                if start is None:
                    start = now
                    if not self.gave_up and self.window > 0:
                        _log.warning(
                            "storage %s unreachable (%s); retrying for up to %g s",
                            self.storage,
                            _short(err),
                            self.window,
                        )
                if self.gave_up or now - start >= self.window:
                    self.gave_up = True
                    raise StorageError(
                        f"storage {self.storage} unreachable for {self.window:g} s "
                        f"({_short(err)}); finished trials are kept and a trial cut short is "
                        f"retried once its heartbeat is stale: rerun when it is back (set "
                        f"{RETRY_WINDOW_ENV} to wait longer)"
                    ) from err
                time.sleep(min(delay, max(0.0, start + self.window - now)))
                delay = min(delay * 2, _MAX_DELAY_S)
                continue
            if start is not None:
                _log.warning(
                    "storage %s reachable again after %.1f s",
                    self.storage,
                    time.monotonic() - start,
                )
            self.gave_up = False
            return result


def redis_client(url: str, window: float) -> Any:
    """A Redis client that waits up to the retry window for an answer.

    A paused server runs the commands it holds when the pause ends: a client that timed out and
    sent one again would store a record twice. The client itself does not retry; the caller's
    `Outage` does.

    Args:
        url: The Redis URL (without ermrl's ``prefix`` parameter).
        window: The retry window in seconds (0: Redis' default timeouts and retries).
    """
    import redis
    from redis.backoff import NoBackoff
    from redis.retry import Retry

    if window <= 0:
        return redis.Redis.from_url(url)
    return redis.Redis.from_url(
        url,
        socket_timeout=window + _ANSWER_MARGIN_S,
        socket_connect_timeout=CONNECT_TIMEOUT_S,
        retry=Retry(NoBackoff(), 0),
    )


def rdb_transient(err: BaseException) -> bool:
    """Whether a storage error is the database connection failing (worth a retry)."""
    import sqlalchemy

    connection_errors = (sqlalchemy.exc.OperationalError, sqlalchemy.exc.InterfaceError)
    if isinstance(err, optuna.exceptions.StorageInternalError):
        err = err.__cause__ or err
    return isinstance(err, connection_errors)


def redis_transient(err: BaseException) -> bool:
    """Whether a Redis error is the server not answering (connection or timeout error)."""
    import redis

    return isinstance(err, (redis.exceptions.ConnectionError, redis.exceptions.TimeoutError))


# RDBStorage's calls that talk to the database (the rest only read settings).
_RDB_CALLS = (
    "create_new_study",
    "delete_study",
    "set_study_user_attr",
    "set_study_system_attr",
    "get_study_id_from_name",
    "get_study_name_from_id",
    "get_study_directions",
    "get_study_user_attrs",
    "get_study_system_attrs",
    "get_all_studies",
    "create_new_trial",
    "_create_new_trial",
    "set_trial_param",
    "_set_trial_param",
    "get_trial_id_from_study_id_trial_number",
    "get_trial_param",
    "set_trial_state_values",
    "set_trial_intermediate_value",
    "set_trial_user_attr",
    "set_trial_system_attr",
    "get_trial_user_attrs",
    "get_trial_system_attrs",
    "get_trial",
    "get_all_trials",
    "get_best_trial",
    "_get_best_trial_id",
    "_get_trials",
    "_get_stale_trial_ids",
)


class RetryingRDBStorage(optuna.storages.RDBStorage):
    """Optuna's ``RDBStorage`` whose database calls are retried through an outage.

    Args:
        url: The SQLAlchemy URL.
        retry_window: Seconds a failing call is retried (`retry_window`).
        **kwargs: Passed to ``RDBStorage`` (``engine_kwargs``, heartbeat settings).
    """

    def __init__(self, url: str, *, retry_window: float, **kwargs: Any) -> None:
        self._outage = Outage(url, retry_window)
        super().__init__(url, **kwargs)

    def record_heartbeat(self, trial_id: int) -> None:
        """Record a heartbeat; one the storage did not take is logged, not raised (it runs in
        a thread of its own, and the trial's next heartbeat counts)."""
        try:
            self._outage.call(rdb_transient, super().record_heartbeat, trial_id)
        except StorageError as err:
            _log.warning("missed a heartbeat of trial id %d: %s", trial_id, err)


def _retrying(method: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(method)
    def call(self: RetryingRDBStorage, *args: Any, **kwargs: Any) -> Any:
        outage = getattr(self, "_outage", None)
        if outage is None:  # while RDBStorage.__init__ runs
            return method(self, *args, **kwargs)
        return outage.call(rdb_transient, method, self, *args, **kwargs)

    return call


for _name in _RDB_CALLS:
    setattr(RetryingRDBStorage, _name, _retrying(getattr(optuna.storages.RDBStorage, _name)))
