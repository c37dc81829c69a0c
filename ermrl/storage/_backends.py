"""Optuna's journal backends (file, Redis), made safe to share and to read when damaged.

- `LineJournalFileBackend`: every append starts on a line of its own, so a record another
  process cut short can never glue onto a valid one; a record that cannot be read stops the
  command in one line that says how to repair the journal.
- `PlainRedisBackend`: no pickled snapshot is ever loaded or saved, and reading stops at a
  missing or unreadable record in one line, where Optuna's backend waits forever for a record
  that ``log_number`` promises but that was never stored.

Both point to ``ermrl study repair`` (`ermrl.storage._repair`), which sets such records
aside.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Generator, Iterator
from typing import Any, TypeVar

from optuna.storages.journal import JournalFileBackend, JournalRedisBackend

from ermrl.storage._locks import JournalSymlinkLock
from ermrl.storage._repair import is_journal_record, journal_record
from ermrl.storage._retry import DEFAULT_RETRY_WINDOW_S, Outage, redis_client, redis_transient
from ermrl.storage._url import StorageError

__all__ = ["LineJournalFileBackend", "PlainRedisBackend"]

_log = logging.getLogger("ermrl.storage")
_REDIS_BATCH = 1000  # records fetched per MGET
T = TypeVar("T")


def _short(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


class LineJournalFileBackend(JournalFileBackend):
    """Optuna's journal file backend whose records always begin on a fresh line.

    Args:
        file_path: The journal file (created if missing, as Optuna does).
        storage: The ``--storage`` value, for the ``ermrl study repair`` hint of read errors.
    """

    def __init__(self, file_path: str, storage: str) -> None:
        # Optuna's lock on <file>.lock, with a stale check that also breaks a dangling link
        # (Optuna's own acquire spins on one forever, at full CPU).
        super().__init__(file_path, lock_obj=JournalSymlinkLock(file_path))
        self._storage = storage

    def append_logs(self, logs: list[dict[str, Any]]) -> None:
        """Append records under the journal's lock, after a newline if the file lacks one.

        A file that does not end in a newline ends with a record another process cut short
        (it died, or its disk filled up, mid-write). Optuna appended straight after it, which
        made one undecodable line of the two records; here the partial one stays a line of its
        own, which ``ermrl study repair`` sets aside without touching this record.
        """
        if not logs:
            return
        data = "".join(json.dumps(log, separators=(",", ":")) + "\n" for log in logs).encode()
        with self._lock_held():
            with open(self._file_path, "a+b") as f:
                end = f.seek(0, os.SEEK_END)
                if end > 0:
                    f.seek(end - 1)
                    if f.read(1) != b"\n":
                        data = b"\n" + data
                f.write(data)  # "a" mode: at the end of the file, whatever the position
                f.flush()
                os.fsync(f.fileno())

    def _lock_held(self) -> JournalSymlinkLock:
        assert isinstance(self._lock, JournalSymlinkLock)
        return self._lock

    def read_logs(self, log_number_from: int) -> Generator[dict[str, Any], None, None]:
        """Optuna's reader, with a one-line [`StorageError`][ermrl.storage.StorageError] for an
        unreadable record."""
        logs: Iterator[dict[str, Any]] = super().read_logs(log_number_from)
        while True:
            try:
                log = next(logs)
            except StopIteration:
                return
            except ValueError as err:  # JSONDecodeError, UnicodeDecodeError, "Invalid log format"
                raise self._unreadable(_short(err)) from err
            if not is_journal_record(log):
                raise self._unreadable("a JSON line that is not a journal record")
            yield log

    def _unreadable(self, detail: str) -> StorageError:
        return StorageError(
            f"journal {self._file_path} has an unreadable record ({detail}); set it aside with: "
            f"ermrl study repair --storage {self._storage}"
        )


class PlainRedisBackend(JournalRedisBackend):
    """Optuna's Redis journal backend that never loads or saves a pickled snapshot.

    ``JournalStorage`` unpickles ``<prefix>:snapshot`` when it opens a Redis journal, so whoever
    can write that key could run code in every command that opens the storage, read-only ones
    included. The snapshot is only a shortcut: the log holds every operation, and replaying it
    gives the same studies. A snapshot found there is ignored, with one warning per process.

    Records are read in batches up to ``<prefix>:log_number``. Optuna stores each record in one
    atomic script with the counter, so a record missing below the counter was lost (or the
    counter was changed by hand): reading stops with a one-line
    [`StorageError`][ermrl.storage.StorageError] instead of waiting for it forever, as it does for a
    record that cannot be decoded, last one included.

    Args:
        url: The Redis URL, without the ``prefix`` parameter.
        prefix: The journal's key prefix.
        storage: The ``--storage`` value, for the ``ermrl study repair`` hint of read errors
            (default: ``url``).
    """

    def __init__(
        self,
        url: str,
        prefix: str = "",
        storage: str | None = None,
        retry_window: float = DEFAULT_RETRY_WINDOW_S,
    ) -> None:
        super().__init__(url, prefix=prefix)
        self._storage = storage or url
        self._outage = Outage(self._storage, retry_window)
        self._redis = redis_client(url, retry_window)

    def __setstate__(self, state: dict[Any, Any]) -> None:
        self.__dict__.update(state)
        self._redis = redis_client(self._url, self._outage.window)

    def _call(self, fn: Callable[..., T], *args: Any) -> T:
        """A Redis command, retried through an outage (`ermrl.storage._retry`)."""
        return self._outage.call(redis_transient, fn, *args)

    def append_logs(self, logs: list[dict[str, Any]]) -> None:
        """Optuna's append (one atomic script per record), each command retried on its own, so
        a record that was stored is never sent again by a retry of the whole batch."""
        self._call(self._redis.setnx, f"{self._prefix}:log_number", -1)
        for log in logs:
            self._call(
                self._redis.eval,
                "local i = redis.call('incr', string.format('%s:log_number', ARGV[1])) "
                "redis.call('set', string.format('%s:log:%d', ARGV[1], i), ARGV[2])",
                0,
                self._prefix,
                json.dumps(log),
            )

    def read_logs(self, log_number_from: int) -> Generator[dict[str, Any], None, None]:
        raw = self._call(self._redis.get, f"{self._prefix}:log_number")
        if raw is None:
            return
        try:
            last = int(raw)
        except ValueError:
            raise self._damaged(f"its log_number is not a number ({raw!r})") from None
        for start in range(log_number_from, last + 1, _REDIS_BATCH):
            numbers = range(start, min(start + _REDIS_BATCH, last + 1))
            values = self._call(self._redis.mget, [self._key_log_id(n) for n in numbers])
            for number, value in zip(numbers, values):
                if value is None:
                    raise self._damaged(f"record {number} of {last + 1} is missing")
                log = journal_record(value)
                if log is None:
                    raise self._damaged(f"record {number} of {last + 1} is unreadable")
                yield log

    def _damaged(self, detail: str) -> StorageError:
        return StorageError(
            f"Redis journal {self._storage}: {detail}; set aside unreadable records and "
            f"renumber the log with: ermrl study repair --storage {self._storage}"
        )

    def load_snapshot(self) -> bytes | None:
        key = f"{self._prefix}:snapshot"
        if (self._url, key) not in _SNAPSHOTS_WARNED and self._call(self._redis.exists, key):
            _SNAPSHOTS_WARNED.add((self._url, key))
            _log.warning(
                "ignoring Redis key %s (a pickled snapshot, never loaded: the journal log is "
                "replayed instead); delete it with: redis-cli -u %s DEL %s",
                key,
                self._url,
                key,
            )
        return None

    def save_snapshot(self, snapshot: bytes) -> None:
        """Write nothing: no pickle is stored for anyone to load."""


_SNAPSHOTS_WARNED: set[tuple[str, str]] = set()
