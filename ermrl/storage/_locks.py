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
  dead process is broken after 30 s);
- PostgreSQL: a session advisory lock (``pg_advisory_lock``) on its own connection;
- MySQL / MariaDB: ``GET_LOCK`` on its own connection;
- Redis: a ``redis-py`` lock with a 120 s expiry.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ermrl.storage._url import (
    StorageURL,
    journal_file,
    parse_storage_url,
    redis_split,
    sqlite_file,
)

__all__ = ["LockTimeout", "storage_lock", "sqlite_path", "journal_path", "redis_parts", "lock_key"]

LOCK_TIMEOUT_S = 600.0
_JOURNAL_LOCK_GRACE_S = 30


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
def _symlink_lock(path: Path) -> Iterator[None]:
    from optuna.storages.journal import JournalFileSymlinkLock

    lock = JournalFileSymlinkLock(str(path), grace_period=_JOURNAL_LOCK_GRACE_S)
    lock.acquire()
    try:
        yield
    finally:
        with contextlib.suppress(RuntimeError):  # broken by another process after the grace
            lock.release()


_ENGINES: dict[str, Any] = {}


def _lock_engine(url: str) -> Any:
    """A pool-less engine: every lock gets a fresh connection, closed (and so released) after."""
    engine = _ENGINES.get(url)
    if engine is None:
        import sqlalchemy
        from sqlalchemy.pool import NullPool

        connect_args: dict[str, Any] = {"connect_timeout": 10}
        engine = sqlalchemy.create_engine(url, poolclass=NullPool, connect_args=connect_args)
        _ENGINES[url] = engine
    return engine


@contextlib.contextmanager
def _pg_lock(url: str, name: str, timeout: float) -> Iterator[None]:
    import sqlalchemy

    key = _pg_key(name)
    with _lock_engine(url).connect() as conn:
        conn.execute(sqlalchemy.text(f"SET lock_timeout = {int(timeout * 1000)}"))
        try:
            conn.execute(sqlalchemy.text("SELECT pg_advisory_lock(:k)"), {"k": key})
        except sqlalchemy.exc.OperationalError as err:
            raise LockTimeout(f"could not take advisory lock {name!r}: {err.orig}") from err
        conn.commit()
        try:
            yield
        finally:
            conn.execute(sqlalchemy.text("SELECT pg_advisory_unlock(:k)"), {"k": key})
            conn.commit()


@contextlib.contextmanager
def _mysql_lock(url: str, name: str, timeout: float) -> Iterator[None]:
    import sqlalchemy

    key = lock_key(name)
    with _lock_engine(url).connect() as conn:
        got = conn.execute(
            sqlalchemy.text("SELECT GET_LOCK(:n, :t)"), {"n": key, "t": int(timeout)}
        ).scalar()
        if got != 1:
            raise LockTimeout(f"could not take MySQL lock {name!r} within {timeout:.0f} s")
        try:
            yield
        finally:
            conn.execute(sqlalchemy.text("SELECT RELEASE_LOCK(:n)"), {"n": key})


@contextlib.contextmanager
def _redis_lock(spec: StorageURL, name: str, timeout: float) -> Iterator[None]:
    import redis

    client = redis.Redis.from_url(spec.url)
    lock = client.lock(lock_key(f"{spec.prefix}:{name}"), timeout=120, blocking_timeout=timeout)
    if not lock.acquire():
        raise LockTimeout(f"could not take Redis lock {name!r} within {timeout:.0f} s")
    try:
        yield
    finally:
        with contextlib.suppress(redis.exceptions.LockError):  # expired meanwhile
            lock.release()


@contextlib.contextmanager
def storage_lock(
    url: str | StorageURL, name: str = "storage", timeout: float = LOCK_TIMEOUT_S
) -> Iterator[None]:
    """Hold an inter-process lock tied to a storage URL.

    Args:
        url: The storage URL (see :func:`ermrl.storage.open_storage`), as a string or parsed.
        name: Which lock (e.g. ``"schema"`` or a study name). File-based locks (SQLite, journal)
            are one per storage whatever the name; server locks are one per name.
        timeout: Seconds to wait for the lock.

    Raises:
        StorageError: the URL is malformed.
        LockTimeout: the lock was not obtained in time.
    """
    spec = url if isinstance(url, StorageURL) else parse_storage_url(url)
    if spec.kind == "redis":
        with _redis_lock(spec, name, timeout):
            yield
    elif spec.kind == "postgresql":
        with _pg_lock(spec.url, name, timeout):
            yield
    elif spec.kind == "mysql":
        with _mysql_lock(spec.url, name, timeout):
            yield
    else:  # a file next to the SQLite database or the journal
        assert spec.path is not None, spec
        if spec.kind == "sqlite":
            with _flock(Path(f"{spec.path}.lock"), timeout):
                yield
        else:
            with _symlink_lock(Path(f"{spec.path}.ermrl")):
                yield
