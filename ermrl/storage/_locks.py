"""Inter-process locks that live next to (or inside) a storage.

Workers take a lock for the few milliseconds it takes to create a schema, create a study or
*claim* a trial (count the study's trials, then ``study.ask()``). Holding it makes the trial
budget exact with any number of workers, and serializes SQLite's first schema creation, which
otherwise races (``table studies already exists``).

One lock kind per backend, chosen so that a worker killed with ``kill -9`` never blocks the
others for long:

- SQLite: ``fcntl.flock`` on ``<db>.lock`` next to the database (released by the kernel when the
  process dies; needs a local file system, as SQLite itself does);
- journal file: a symlink lock ``<log>.ermrl.lock`` (Optuna's NFS-safe scheme; a lock left by a
  dead process, i.e. a link unchanged for 30 s, is broken, whatever it points at). Appends and
  repairs take Optuna's own ``<log>.lock`` through `JournalSymlinkLock`, which breaks a
  stale or dangling one the same way;
- PostgreSQL: a session advisory lock (``pg_advisory_lock``);
- MySQL / MariaDB: ``GET_LOCK``;
- Redis: a ``redis-py`` lock with a 120 s expiry.

A PostgreSQL or MySQL lock lives on a connection of its own, reused from lock to lock (one per
process), and dies with it: a worker that is killed, or whose connection the server drops (a
restart), holds it no longer. Taking one is retried through an outage as the storage's calls
are (`ermrl.storage._retry`); releasing one that its connection took along only logs a
warning. The claim made under it goes on: its storage calls are retried too.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import logging
import os
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from optuna.storages.journal._file import BaseJournalFileLock

from ermrl.storage._url import (
    StorageURL,
    bound_handshake,
    connect_args,
    journal_file,
    parse_storage_url,
    redis_split,
    sqlite_file,
)

__all__ = [
    "JournalSymlinkLock",
    "LockTimeout",
    "journal_file_lock",
    "storage_lock",
    "sqlite_file_lock",
    "sqlite_path",
    "journal_path",
    "redis_parts",
    "lock_key",
]

LOCK_TIMEOUT_S = 600.0
# Seconds a journal lock link (``<log>.lock``, ``<log>.ermrl.lock``) may stay unchanged before
# it is taken for a dead owner's and broken; Optuna's default grace period for the same lock.
_JOURNAL_LOCK_GRACE_S = 30.0

_log = logging.getLogger("ermrl.storage")


class LockTimeout(TimeoutError):
    """A storage lock could not be taken within the timeout."""


def lock_key(name: str) -> str:
    """A short, stable name for a lock (MySQL limits lock names to 64 characters)."""
    return "ermrl:" + hashlib.blake2b(name.encode(), digest_size=12).hexdigest()


def _pg_key(name: str) -> int:
    """A signed 64-bit key for ``pg_advisory_lock``."""
    return int.from_bytes(
        hashlib.blake2b(name.encode(), digest_size=8).digest(), "big", signed=True
    )


def sqlite_path(url: str) -> Path | None:
    """The database file of a ``sqlite:///`` URL (``None`` for in-memory databases)."""
    return sqlite_file(url)


def redis_parts(url: str) -> tuple[str, str]:
    """Split ``redis://host:port/db?prefix=NAME`` into the Redis URL and the journal's key prefix.

    The prefix keeps several journals apart in one Redis database (default: none).
    """
    return redis_split(url)


def journal_path(url: str) -> Path:
    """The log file of a ``journal:///path`` URL or of a bare ``path.log``."""
    return journal_file(url)


@contextlib.contextmanager
def _flock(path: Path, timeout: float) -> Iterator[None]:
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o664)
    try:
        deadline = time.monotonic() + timeout
        delay = 0.001
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise LockTimeout(f"could not lock {path} within {timeout:.0f} s") from None
                time.sleep(delay)
                delay = min(delay * 2, 0.05)
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


@contextlib.contextmanager
def sqlite_file_lock(
    path: os.PathLike[str] | str, timeout: float = LOCK_TIMEOUT_S
) -> Iterator[None]:
    """Hold ermrl's lock of a SQLite database: ``fcntl.flock`` on ``path`` (``<db>.lock``).

    Args:
        path: The lock file (created if missing).
        timeout: Seconds to wait for it.

    Raises:
        LockTimeout: it was not obtained in time.
    """
    with _flock(Path(path), timeout):
        yield


def _link_identity(path: Path) -> tuple[int, int] | None:
    """The symlink itself (inode and modification time), not what it points at."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    return (st.st_ino, st.st_mtime_ns)


def _remove_link(path: Path, expected: tuple[int, int]) -> bool:
    """Remove the lock link if it is still the one seen (``expected``); keep any other.

    The link is first renamed to a unique name, so when several processes remove it at once
    only one succeeds; a link that was replaced meanwhile (a live worker's fresh lock) is put
    back when the name is still free.

    Returns:
        Whether the expected link was removed.
    """
    aside = path.with_name(f"{path.name}.{uuid.uuid4().hex}.aside")
    try:
        os.rename(path, aside)
    except FileNotFoundError:
        return False  # released or broken by someone else meanwhile
    if _link_identity(aside) == expected:
        os.unlink(aside)
        return True
    with contextlib.suppress(FileExistsError):
        os.link(aside, path, follow_symlinks=False)  # the same link (inode and time) again
    os.unlink(aside)
    return False


class JournalSymlinkLock(BaseJournalFileLock):
    """Optuna's NFS-safe symlink lock on ``<path>.lock``, with a stale check that works.

    The same lock as Optuna's ``JournalFileSymlinkLock`` (a symlink ``<path>.lock`` created
    with ``symlink(2)``, which is atomic on NFS too), so ermrl and plain Optuna processes
    sharing a journal exclude each other. Optuna's own ``acquire`` judges a lock stale by the
    ``stat`` of the file the link points at; when that file does not exist (a dangling link:
    left by a process that ran elsewhere, pointing at a relative path, or made by hand) it
    retries at once, forever, at full CPU. Here the link itself is checked (``lstat``): a link
    unchanged for `_JOURNAL_LOCK_GRACE_S` seconds of this process's clock (immune to clock
    skew between NFS clients) is broken, with a warning, whatever it points at. A live holder
    keeps a lock for milliseconds (one append), and every acquisition makes a new link.

    Args:
        path: The file the lock protects (the journal); the link is ``<path>.lock``.
        timeout: Seconds to wait for the lock before [`LockTimeout`][ermrl.storage.LockTimeout].
        target: What the link points at, made absolute (default: ``path``): a file that
            exists, so that Optuna's own stale check in plain Optuna processes can ``stat`` it.
    """

    def __init__(
        self,
        path: os.PathLike[str] | str,
        timeout: float = LOCK_TIMEOUT_S,
        target: os.PathLike[str] | str | None = None,
    ) -> None:
        self._link = Path(f"{path}.lock")
        self._target = Path(path if target is None else target).absolute()
        self._timeout = timeout
        self._mine: tuple[int, int] | None = None

    def acquire(self) -> bool:
        """Take the lock, breaking a stale one; ``True`` once held.

        Raises:
            LockTimeout: it was not obtained within the timeout.
        """
        deadline = time.monotonic() + self._timeout
        delay = 0.001
        seen: tuple[int, int] | None = None
        seen_since = time.monotonic()
        while True:
            try:
                os.symlink(self._target, self._link)
                self._mine = _link_identity(self._link)
                return True
            except FileExistsError:
                pass
            now = time.monotonic()
            current = _link_identity(self._link)
            if current != seen:
                seen, seen_since = current, now
            elif current is not None and now - seen_since > _JOURNAL_LOCK_GRACE_S:
                if _remove_link(self._link, current):
                    _log.warning(
                        "broke the lock %s: unchanged for %g s, its owner is gone",
                        self._link,
                        _JOURNAL_LOCK_GRACE_S,
                    )
                seen, delay = None, 0.001
                continue
            if now > deadline:
                raise LockTimeout(f"could not lock {self._link} within {self._timeout:.0f} s")
            time.sleep(delay)
            delay = min(delay * 2, 0.05)

    def release(self) -> None:
        """Remove the lock link if it is still the one this lock made."""
        mine, self._mine = self._mine, None
        if mine is not None:  # else broken by another process at once (held past the grace)
            _remove_link(self._link, mine)

    def __enter__(self) -> JournalSymlinkLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


@contextlib.contextmanager
def journal_file_lock(
    path: os.PathLike[str] | str, timeout: float = LOCK_TIMEOUT_S
) -> Iterator[None]:
    """Hold the write lock of a journal file: Optuna's ``<path>.lock``, taken by
    `JournalSymlinkLock` (a stale or dangling link is broken after the grace period).

    Args:
        path: The journal file.
        timeout: Seconds to wait for the lock.

    Raises:
        LockTimeout: it was not obtained in time.
    """
    with JournalSymlinkLock(path, timeout):
        yield


_ENGINES: dict[str, Any] = {}


def _lock_engine(spec: StorageURL) -> Any:
    """The engine of a server's locks: one pooled connection per process, reused by every lock.

    SQLAlchemy's ``pool_pre_ping`` replaces a pooled connection that died (a server restart)
    before a lock uses it; a nested lock gets a connection of its own (pool overflow), closed
    when it is returned. Connecting is bounded as for the storage (`connect_args`); a lock
    wait is not.
    """
    engine = _ENGINES.get(spec.url)
    if engine is None:
        import sqlalchemy

        engine = sqlalchemy.create_engine(
            spec.url,
            pool_size=1,
            max_overflow=-1,
            pool_pre_ping=True,
            connect_args=connect_args(spec),
        )
        _ENGINES[spec.url] = bound_handshake(engine)
    return engine


@contextlib.contextmanager
def _server_lock(
    spec: StorageURL,
    name: str,
    take: Callable[[Any], None],
    give: Callable[[Any], None],
    window: float | None,
) -> Iterator[None]:
    """Hold a lock of a PostgreSQL or MySQL server, taken by ``take(connection)`` and released
    by ``give(connection)``.

    Taking it is retried as the storage's calls are (`ermrl.storage._retry`): a server that
    restarts or has no connection left is waited for, up to the retry window (0: not retried,
    the driver's error is raised, as when a storage is opened). A lock is tied to
    its connection, so a connection that dies while the lock is held (a server restart) takes
    the lock with it: releasing it then only logs a warning, and the connection is dropped.

    Raises:
        LockTimeout: the lock was not obtained in time.
        StorageError: the server stayed unreachable for the whole retry window (one line).
    """
    import sqlalchemy

    from ermrl.storage._retry import Outage, rdb_transient, retry_window

    def locked() -> Any:
        conn = _lock_engine(spec).connect()
        try:
            take(conn)
        except BaseException:
            conn.close()
            raise
        return conn

    window = retry_window(window)
    conn = Outage(spec.raw, window).call(rdb_transient, locked) if window > 0 else locked()
    try:
        yield
    finally:
        try:
            give(conn)
        except sqlalchemy.exc.DBAPIError as err:
            _log.warning("lock %r of %s was lost with its connection (%s)", name, spec, err.orig)
            conn.invalidate()  # never back in the pool, whatever it still holds
        finally:
            conn.close()


def _pg_lock(spec: StorageURL, name: str, timeout: float, window: float | None) -> Any:
    import sqlalchemy

    key = _pg_key(name)

    def take(conn: Any) -> None:
        conn.execute(sqlalchemy.text(f"SET lock_timeout = {int(timeout * 1000)}"))
        try:
            conn.execute(sqlalchemy.text("SELECT pg_advisory_lock(:k)"), {"k": key})
        except sqlalchemy.exc.OperationalError as err:
            if getattr(err.orig, "pgcode", None) != "55P03":  # lock_not_available
                raise  # the connection failed: taking the lock is retried
            raise LockTimeout(f"could not take advisory lock {name!r}: {err.orig}") from err
        conn.commit()

    def give(conn: Any) -> None:
        conn.execute(sqlalchemy.text("SELECT pg_advisory_unlock(:k)"), {"k": key})
        conn.commit()

    return _server_lock(spec, name, take, give, window)


def _mysql_lock(spec: StorageURL, name: str, timeout: float, window: float | None) -> Any:
    import sqlalchemy

    key = lock_key(name)

    def take(conn: Any) -> None:
        got = conn.execute(
            sqlalchemy.text("SELECT GET_LOCK(:n, :t)"), {"n": key, "t": int(timeout)}
        ).scalar()
        conn.commit()
        if got != 1:
            raise LockTimeout(f"could not take MySQL lock {name!r} within {timeout:.0f} s")

    def give(conn: Any) -> None:
        conn.execute(sqlalchemy.text("SELECT RELEASE_LOCK(:n)"), {"n": key})
        conn.commit()

    return _server_lock(spec, name, take, give, window)


@contextlib.contextmanager
def _redis_lock(
    spec: StorageURL, name: str, timeout: float, retry_s: float | None
) -> Iterator[None]:
    import redis

    from ermrl.storage._retry import Outage, redis_client, redis_transient, retry_window

    window = retry_window(retry_s)
    outage = Outage(spec.raw, window)
    client = redis_client(spec.url, window)
    lock = client.lock(lock_key(f"{spec.prefix}:{name}"), timeout=120, blocking_timeout=timeout)
    if not outage.call(redis_transient, lock.acquire):
        raise LockTimeout(f"could not take Redis lock {name!r} within {timeout:.0f} s")
    try:
        yield
    finally:
        with contextlib.suppress(redis.exceptions.LockError):  # expired meanwhile
            outage.call(redis_transient, lock.release)


@contextlib.contextmanager
def storage_lock(
    url: str | StorageURL,
    name: str = "storage",
    timeout: float = LOCK_TIMEOUT_S,
    retry_window: float | None = None,
) -> Iterator[None]:
    """Hold an inter-process lock tied to a storage URL.

    Args:
        url: The storage URL (see [`ermrl.storage.open_storage`][ermrl.storage.open_storage]), as a
            string or parsed.
        name: Which lock (e.g. ``"schema"`` or a study name). File-based locks (SQLite, journal)
            are one per storage whatever the name; server locks are one per name.
        timeout: Seconds to wait for the lock.
        retry_window: Seconds taking a server's lock is retried while the server is
            unreachable (``None``: ``ERMRL_STORAGE_RETRY_S`` or 120; see
            `ermrl.storage._retry`).

    Raises:
        StorageError: the URL is malformed, or the server stayed unreachable.
        LockTimeout: the lock was not obtained in time.
    """
    spec = url if isinstance(url, StorageURL) else parse_storage_url(url)
    if spec.kind == "redis":
        with _redis_lock(spec, name, timeout, retry_window):
            yield
    elif spec.kind == "postgresql":
        with _pg_lock(spec, name, timeout, retry_window):
            yield
    elif spec.kind == "mysql":
        with _mysql_lock(spec, name, timeout, retry_window):
            yield
    else:  # a file next to the SQLite database or the journal
        assert spec.path is not None, spec
        if spec.kind == "sqlite":
            with _flock(Path(f"{spec.path}.lock"), timeout):
                yield
        else:
            # A lock of its own, <log>.ermrl.lock, held for a claim; it points at the journal
            # itself: a file that exists, so Optuna's own stale check (in older ermrl workers
            # sharing the journal) can stat it.
            with JournalSymlinkLock(f"{spec.path}.ermrl", timeout, target=spec.path):
                yield
