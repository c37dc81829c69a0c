"""Open Optuna storages and studies from a URL, with clear errors.

Accepted URLs:

- ``sqlite:///path.db``: the embedded default (one machine, local disk; see README for
  concurrency notes and why not on NFS);
- ``postgresql://user@host/db`` and ``mysql://...`` / ``mysql+pymysql://...``: shared RDB servers
  for clusters;
- ``journal:///path.log`` or any path ending in ``.log``: an append-only journal file (works on
  NFS);
- ``redis://host:port[/db][?prefix=NAME]``: Optuna's journal over Redis (``prefix`` keeps
  several journals apart in one database). Optuna's pickled ``<prefix>:snapshot`` is never
  loaded (a pickle can run code): the log is replayed instead (`PlainRedisBackend`),
  and a missing or unreadable record stops a command in one line instead of a wait forever.

Every storage is opened with the same guarantees: the schema is created under an inter-process
lock (no ``table studies already exists`` when many workers start at once on a fresh file),
SQLite waits up to 60 s for a busy database, and RUNNING trials get heartbeats (Optuna's for RDB
storages, [`HeartbeatJournalStorage`][ermrl.storage.HeartbeatJournalStorage] for journals) so that
the trial of a dead worker is failed and retried.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import warnings
import weakref
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import optuna
from optuna.exceptions import ExperimentalWarning
from optuna.storages import BaseStorage

from ermrl.storage._backends import LineJournalFileBackend, PlainRedisBackend
from ermrl.storage._heartbeat import HeartbeatJournalStorage, RetryStaleTrial, base_storage
from ermrl.storage._locks import LOCK_TIMEOUT_S, sqlite_file_lock, storage_lock
from ermrl.storage._repair import check_journal, repair_journal
from ermrl.storage._retry import RetryingRDBStorage
from ermrl.storage._retry import retry_window as retry_window_s
from ermrl.storage._url import (
    StorageError,
    StorageKind,
    StorageURL,
    bound_handshake,
    connect_args,
    parse_storage_url,
)

__all__ = [
    "StorageError",
    "StudyNotFound",
    "DEFAULT_STORAGE",
    "DEFAULT_HEARTBEAT_INTERVAL",
    "DEFAULT_GRACE_PERIOD",
    "DEFAULT_MAX_RETRY",
    "storage_kind",
    "normalize_url",
    "open_storage",
    "repair_sqlite",
    "storage_url",
    "study_lock",
    "load_study",
    "study_names",
    "worker_info",
]

DEFAULT_STORAGE = "sqlite:///ermrl.db"
SQLITE_BUSY_TIMEOUT_S = 60
DEFAULT_HEARTBEAT_INTERVAL = 60
DEFAULT_GRACE_PERIOD = 300
DEFAULT_MAX_RETRY = 3
# How long a reader waits for a schema another process is creating (seconds).
SCHEMA_WAIT_S = 30

_log = logging.getLogger("ermrl.storage")

# URL each storage was opened from (the claim lock of a study is found from its storage).
_OPENED_FROM: weakref.WeakKeyDictionary[BaseStorage, StorageURL] = weakref.WeakKeyDictionary()


class StudyNotFound(LookupError):
    """No study of that name exists in the storage."""


def greet_redis(url: str, shown: str) -> None:
    """Fail now, in one line, when the Redis server does not answer a PING within the connect
    bound (`CONNECT_TIMEOUT_S`).

    The storage's own client waits up to the retry window for each answer (a paused server is
    an outage to ride out), so without this a listener that never answers held a command for
    minutes. Opening a storage is not retried: a wrong URL fails fast.
    """
    import redis
    from redis.backoff import NoBackoff
    from redis.retry import Retry

    import ermrl.storage._url as _url

    bound = _url.CONNECT_TIMEOUT_S
    client = redis.Redis.from_url(
        url, socket_timeout=bound, socket_connect_timeout=bound, retry=Retry(NoBackoff(), 0)
    )
    try:
        client.ping()
    except redis.exceptions.RedisError as err:
        detail = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise StorageError(
            f"cannot open storage {shown}: the Redis server did not answer within {bound:g} s "
            f"({detail})"
        ) from None
    finally:
        client.close()


def storage_kind(url: str) -> StorageKind:
    """Classify a storage URL: ``sqlite``, ``postgresql``, ``mysql``, ``journal`` or ``redis``.

    Raises:
        StorageError: an unsupported URL, or an in-memory SQLite database (``sqlite://``,
            ``sqlite:///:memory:``), whose results no later command could read.
    """
    return parse_storage_url(url).kind


def normalize_url(url: str) -> str:
    """The SQLAlchemy URL of an RDB storage URL (`StorageURL.url`).

    ``postgres://`` becomes ``postgresql://``; a URL without a driver uses one that is installed:
    ``postgresql://`` psycopg2 unless psycopg 3 (SQLAlchemy 2.1's default) is there, ``mysql://``
    PyMySQL unless ``mysqlclient`` is. Other URLs, and URLs that are not storage URLs, are
    returned unchanged.
    """
    try:
        spec = parse_storage_url(url)
    except StorageError:
        return url
    return spec.url if spec.is_rdb else url


def _short(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def open_storage(
    url: str | StorageURL,
    *,
    heartbeat_interval: int | None = None,
    grace_period: int | None = None,
    max_retry: int | None = DEFAULT_MAX_RETRY,
    mode: Literal["create", "write", "read"] = "create",
    retry_window: float | None = None,
) -> BaseStorage:
    """Open a storage, creating its schema under an inter-process lock.

    Args:
        url: A storage URL (see module docstring), as a string or parsed.
        heartbeat_interval: Seconds between heartbeats of running trials (``None``: no
            heartbeat, so a dead worker's trial stays RUNNING until ``ermrl study fail-stale``).
        grace_period: Seconds without a heartbeat after which a running trial is stale
            (``None``: twice the interval, Optuna's default).
        max_retry: How many times a stale trial is retried (a WAITING copy with the same
            parameters; ``None``: no limit, 0: never).
        mode: ``"create"`` (workers, ``ermrl study create``): a missing SQLite or journal file
            is created; ``"write"``: the file must exist; ``"read"`` (commands that only read
            a study): the file must exist and nothing is created or changed next to it (no
            lock file, no schema, no journal repair: Optuna reads a journal's complete
            records). In both, a database without Optuna's tables (a 0-byte SQLite file, an
            empty server database) is a [`StorageError`][ermrl.storage.StorageError], and is left
            without them.
        retry_window: Seconds a call to a server storage (PostgreSQL, MySQL, Redis) is retried
            while the server is unreachable, before it fails with a
            [`StorageError`][ermrl.storage.StorageError] (``None``: ``ERMRL_STORAGE_RETRY_S`` or
            120; 0: no retries; see `ermrl.storage._retry`). Opening is not retried.

    Returns:
        An Optuna storage.

    Raises:
        StorageError: the URL is malformed or the storage is unreachable.
    """
    spec = url if isinstance(url, StorageURL) else parse_storage_url(url)
    if heartbeat_interval is not None and heartbeat_interval <= 0:
        raise StorageError(f"heartbeat interval must be positive, got {heartbeat_interval}")
    if grace_period is not None and grace_period <= 0:
        raise StorageError(f"grace period must be positive, got {grace_period}")
    if (
        heartbeat_interval is not None
        and grace_period is not None
        and grace_period <= heartbeat_interval
    ):
        raise StorageError(
            f"grace period ({grace_period} s) must be longer than the heartbeat interval "
            f"({heartbeat_interval} s)"
        )
    window = retry_window_s(retry_window)
    retry = RetryStaleTrial(max_retry) if max_retry is None or max_retry > 0 else None
    heartbeat: dict[str, Any] = {
        "heartbeat_interval": heartbeat_interval,
        "grace_period": grace_period if heartbeat_interval is not None else None,
        # Also kept without heartbeats: it is the retry policy of SIGTERM-interrupted trials.
        "heartbeat_stale_trial_callback": retry,
    }
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ExperimentalWarning)
            storage = _open(spec, heartbeat, mode, window)
    except StorageError:
        raise
    except Exception as err:  # sqlalchemy / driver / redis errors: keep the message short
        raise StorageError(f"cannot open storage {spec}: {_short(err)}") from err
    _OPENED_FROM[storage] = spec
    return storage


def _open(spec: StorageURL, heartbeat: dict[str, Any], mode: str, window: float) -> BaseStorage:
    if spec.kind == "journal":
        path = spec.path
        assert path is not None, spec
        if not path.parent.exists():
            raise StorageError(f"directory {path.parent} of journal {path} does not exist")
        check_journal(path)  # a directory, or a file that is not a journal: left untouched
        if mode != "create" and not path.is_file():
            raise StorageError(f"no journal file {path} (check --storage)")
        if mode != "read":
            try:
                # A record cut short, or garbage, would stop every read from here on.
                repair_journal(path)
            except OSError as err:
                raise StorageError(
                    f"journal {path} has unreadable records that could not be set aside "
                    f"({err.strerror or err}); free some space and run: ermrl study repair "
                    f"--storage {spec}"
                ) from err
        return HeartbeatJournalStorage(LineJournalFileBackend(str(path), spec.raw), **heartbeat)
    if spec.kind == "redis":
        greet_redis(spec.url, spec.raw)
        backend = PlainRedisBackend(
            spec.url, prefix=spec.prefix, storage=spec.raw, retry_window=window
        )
        storage = HeartbeatJournalStorage(backend, **heartbeat)
        storage.get_all_studies()  # fail now if the server is unreachable
        return storage
    engine_kwargs: dict[str, Any] = {}
    if spec.kind == "sqlite":
        path = spec.path
        assert path is not None, spec  # parse_storage_url refuses in-memory databases
        parent = path.resolve().parent
        if not parent.exists():
            raise StorageError(f"directory {parent} of SQLite database does not exist")
        if path.is_dir():  # before the schema lock creates <path>.lock next to it
            raise StorageError(
                f"SQLite database {path} is a directory, not a file (check --storage)"
            )
        if mode != "create" and not path.is_file():
            raise StorageError(_no_sqlite_database(path))
        _check_sqlite(path, lock=mode != "read")
        # Python's sqlite3 waits this long for a lock before "database is locked".
        engine_kwargs["connect_args"] = {"timeout": SQLITE_BUSY_TIMEOUT_S}
    else:
        engine_kwargs["pool_pre_ping"] = True
        engine_kwargs["connect_args"] = connect_args(spec)
    if mode != "create" and not _has_optuna_schema(spec, engine_kwargs):
        # RDBStorage would create the tables: a reader must leave an empty database as it is.
        raise StorageError(
            f"{spec} holds no ermrl study: the database is empty (no Optuna tables), and was "
            "left so (check --storage)"
        )
    if mode == "read":  # the schema exists: no lock (and no lock file) needed
        _wait_for_whole_schema(spec, engine_kwargs)
        return _rdb_storage(spec, engine_kwargs, heartbeat, window)
    # Many workers starting at once on a fresh database race on CREATE TABLE: one at a time.
    # Opening is not retried: a server down when a command starts fails at once.
    with storage_lock(spec, "schema", retry_window=0):
        return _rdb_storage(spec, engine_kwargs, heartbeat, window)


def _rdb_storage(
    spec: StorageURL, engine_kwargs: dict[str, Any], heartbeat: dict[str, Any], window: float
) -> optuna.storages.RDBStorage:
    """Optuna's RDB storage; on a server, calls are retried through an outage
    (`RetryingRDBStorage`) and only connecting is time-bounded."""
    if spec.kind == "sqlite":
        return optuna.storages.RDBStorage(spec.url, engine_kwargs=engine_kwargs, **heartbeat)
    storage = RetryingRDBStorage(
        spec.url, retry_window=window, engine_kwargs=engine_kwargs, **heartbeat
    )
    bound_handshake(storage.engine)
    return storage


def _wait_for_whole_schema(
    spec: StorageURL, engine_kwargs: dict[str, Any], timeout: float | None = None
) -> None:
    """Wait until the schema another process is creating is whole (Alembic's revision stamped).

    A reader opened between a worker's CREATE TABLE and its Alembic stamp would stamp the
    revision itself (``RDBStorage`` does so on a database without one), outside the schema
    lock, and the worker's own stamp then fails on ``UNIQUE constraint failed:
    alembic_version.version_num``: a periodic snapshot started with a fresh study stopped its
    evolution so. A reader never creates anything, so it waits instead.
    """
    import sqlalchemy

    timeout = SCHEMA_WAIT_S if timeout is None else timeout
    deadline = time.monotonic() + timeout
    engine = sqlalchemy.create_engine(spec.url, **engine_kwargs)
    try:
        while True:
            try:
                with engine.connect() as connection:
                    stamped = connection.execute(
                        sqlalchemy.text("SELECT COUNT(*) FROM alembic_version")
                    ).scalar()
            except sqlalchemy.exc.DatabaseError:  # the table is not made yet
                stamped = 0
            if stamped:
                return
            if time.monotonic() >= deadline:
                raise StorageError(
                    f"{spec} holds a half-made schema (Optuna's tables without their Alembic "
                    f"revision) after {timeout:g} s: another process may be creating it; "
                    "try again"
                )
            time.sleep(0.2)
    finally:
        engine.dispose()


def _has_optuna_schema(spec: StorageURL, engine_kwargs: dict[str, Any]) -> bool:
    """Whether an RDB storage holds Optuna's tables, looked up without creating any.

    ``optuna.storages.RDBStorage`` creates its schema when it opens a database, so a read-only
    command would otherwise turn a 0-byte SQLite file or an empty server database into an Optuna
    one.
    """
    import sqlalchemy

    engine = sqlalchemy.create_engine(spec.url, **engine_kwargs)
    try:
        tables = set(sqlalchemy.inspect(engine).get_table_names())
    finally:
        engine.dispose()
    return bool(tables & {"studies", "alembic_version"})


def damaged_sqlite_message(path: os.PathLike[str] | str, detail: str) -> str:
    """The one-line error for a damaged SQLite database, with what to try."""
    recovered = f"{os.path.splitext(str(path))[0]}-recovered.db"
    return (
        f"SQLite database {path} is damaged ({detail}); recover what is readable with: "
        f'sqlite3 {path} ".recover" | sqlite3 {recovered} (then --storage sqlite:///{recovered}), '
        "or restore a backup"
    )


def _check_sqlite(path: os.PathLike[str] | str, *, lock: bool = True) -> bool:
    """Fail with `damaged_sqlite_message` unless SQLite's ``quick_check`` passes.

    A damaged page otherwise surfaces only when a query reads it, as a long traceback that ends
    in Optuna's misleading "invalid data in the commit". Opened read-only, so nothing is
    created, unless a rollback journal (``<db>-journal``) is there: a writer that died
    mid-transaction leaves it *hot*, and only a read-write connection can roll it back, as
    SQLite does on its next open (a read-only one fails on "attempt to write a readonly
    database"). The check then opens the file read-write (never creating it), under ermrl's
    lock on the database (``<db>.lock``, when ``lock`` or when it exists already), so the
    interrupted transaction is rolled back before anything reads. The journal of a live writer
    (another worker in a transaction) is not hot and is left to it (`_roll_back_hot_journal`).

    Args:
        path: The database file (missing or empty: nothing to check).
        lock: Take ermrl's lock, creating ``<db>.lock`` if needed (``False``: only an existing
            one, for commands that create nothing).

    Returns:
        Whether an interrupted transaction was rolled back (its journal is gone).

    Raises:
        StorageError: the database is damaged, or a hot journal cannot be rolled back (the file
            is read-only here); one line.
    """
    if not os.path.isfile(path) or os.path.getsize(path) == 0:
        return False
    journal = f"{path}-journal"
    if not _nonempty(journal):
        _quick_check(path, "ro")
        return False
    lock_file = f"{path}.lock"
    with sqlite_file_lock(lock_file) if lock or os.path.exists(lock_file) else _no_lock():
        rolled_back = _roll_back_hot_journal(path)
        _quick_check(path, "rw")
    if rolled_back:
        _log.warning(
            "SQLite database %s: rolled back the transaction a writer left unfinished (%s)",
            path,
            journal,
        )
    return rolled_back


def _roll_back_hot_journal(path: os.PathLike[str] | str) -> bool:
    """Roll back the journal of a writer that died, as SQLite does; whether one was.

    A live writer's journal is not *hot*: the writer holds SQLite's RESERVED lock on the
    database (an EXCLUSIVE one while it commits) until its journal is gone. ``BEGIN
    IMMEDIATE``, which does not wait here, takes that lock only when no process holds it, and
    first rolls back a hot journal. A writer that committed between the look at its journal and
    this lock (its journal gone, the database's change counter up) rolled nothing back either.
    Any other error is left to `_quick_check`, which says what is wrong.
    """
    import sqlite3
    from urllib.parse import quote

    before = _change_counter(path)
    uri = f"file:{quote(os.path.abspath(path))}?mode=rw"
    try:
        conn = sqlite3.connect(uri, uri=True, timeout=0, isolation_level=None)
        try:
            conn.execute("BEGIN IMMEDIATE")
            conn.execute("ROLLBACK")
        finally:
            conn.close()
    except sqlite3.DatabaseError:
        return False  # busy: a live writer holds it (or an error _quick_check reports)
    return not _nonempty(f"{path}-journal") and _change_counter(path) <= before


def _change_counter(path: os.PathLike[str] | str) -> int:
    """SQLite's file change counter (header bytes 24-27), which every commit increments."""
    with open(path, "rb") as f:
        f.seek(24)
        return int.from_bytes(f.read(4), "big")


def _nonempty(path: str) -> bool:
    try:
        return os.path.getsize(path) > 0
    except OSError:
        return False


@contextlib.contextmanager
def _no_lock() -> Iterator[None]:
    yield


def _quick_check(path: os.PathLike[str] | str, mode: Literal["ro", "rw"]) -> None:
    """Run ``PRAGMA quick_check`` on a connection opened in ``mode`` (``rw`` never creates)."""
    import sqlite3
    from urllib.parse import quote

    uri = f"file:{quote(os.path.abspath(path))}?mode={mode}"
    try:
        conn = sqlite3.connect(uri, uri=True, timeout=SQLITE_BUSY_TIMEOUT_S)
        try:
            rows = conn.execute("PRAGMA quick_check(1)").fetchall()
        finally:
            conn.close()
    except sqlite3.OperationalError as err:
        if "locked" in str(err) or "busy" in str(err):
            return  # a writer holds it for longer than the timeout: let Optuna wait and report
        if mode == "rw" and "readonly" in str(err):
            raise StorageError(
                f"SQLite database {path} holds a transaction a writer left unfinished "
                f"({path}-journal) and is read-only here, so it cannot be rolled back; run any "
                "ermrl command on it as a user who can write the file and its folder"
            ) from err
        raise StorageError(damaged_sqlite_message(path, _short(err))) from err
    except sqlite3.DatabaseError as err:  # "file is not a database", "disk image is malformed"
        raise StorageError(damaged_sqlite_message(path, _short(err))) from err
    if rows != [("ok",)]:
        lines = [line for row in rows for line in str(row[0]).splitlines()]
        lines = [line for line in lines if not line.startswith("***")] or ["quick_check failed"]
        raise StorageError(damaged_sqlite_message(path, lines[0]))


def repair_sqlite(url: str | StorageURL) -> bool:
    """Roll back the transaction a dead writer left in a SQLite database, then check it.

    What every command does when it opens the database (see `_check_sqlite`), by hand.

    Args:
        url: A ``sqlite:///`` storage URL (string or parsed).

    Returns:
        Whether an unfinished transaction was rolled back (``False``: the database was intact).

    Raises:
        StorageError: not a SQLite file, or a damaged database (one line).
    """
    spec = url if isinstance(url, StorageURL) else parse_storage_url(url)
    if spec.kind != "sqlite" or spec.path is None:
        raise StorageError(f"{spec} is not a SQLite database")
    if not spec.path.is_file():
        raise StorageError(_no_sqlite_database(spec.path))
    return _check_sqlite(spec.path)


def _no_sqlite_database(path: Path) -> str:
    """The one line for a SQLite file that does not exist, with its full path: a relative
    ``sqlite:///ermrl.db`` is read from the current folder, which a command run from another
    folder does not show."""
    if path.is_absolute():
        return f"no SQLite database {path} (check --storage)"
    return (
        f"no SQLite database {path.absolute()} ({path} is relative to the current folder "
        f"{Path.cwd()}; check --storage)"
    )


def _registered(storage: BaseStorage) -> StorageURL | None:
    """The URL [`open_storage`][ermrl.storage.open_storage] opened a storage from (also under
    Optuna's cache wrapper)."""
    for candidate in (storage, base_storage(storage)):
        spec = _OPENED_FROM.get(candidate)
        if spec is not None:
            return spec
    return None


def storage_url(storage: BaseStorage) -> str | None:
    """The URL a storage was opened from with [`open_storage`][ermrl.storage.open_storage] (``None``
    if unknown)."""
    spec = _registered(storage)
    if spec is not None:
        return spec.raw
    inner = base_storage(storage)
    return inner.url if isinstance(inner, optuna.storages.RDBStorage) else None


@contextlib.contextmanager
def study_lock(study: optuna.Study, timeout: float = LOCK_TIMEOUT_S) -> Iterator[bool]:
    """Hold the inter-process lock of a study's storage (see
    [`storage_lock`][ermrl.storage.storage_lock]).

    Workers hold it while they count the study's trials and ask for a new one, which makes the
    trial budget exact. Yields ``False`` (and locks nothing) for storages not opened by
    [`open_storage`][ermrl.storage.open_storage], e.g. Optuna's in-memory storage.
    """
    spec = _registered(study._storage)
    if spec is None:
        url = storage_url(study._storage)  # an RDBStorage opened without open_storage
        if url is None:
            yield False
            return
        spec = parse_storage_url(url)
    outage = getattr(base_storage(study._storage), "_outage", None)  # RetryingRDBStorage's
    window = outage.window if outage is not None else None
    with storage_lock(spec, study.study_name, timeout=timeout, retry_window=window):
        yield True


def study_names(storage: BaseStorage) -> list[str]:
    """Names of the studies in a storage."""
    return [s.study_name for s in storage.get_all_studies()]


def load_study(
    name: str,
    storage: BaseStorage | str | StorageURL,
    *,
    mode: Literal["write", "read"] = "read",
    **kwargs: Any,
) -> optuna.Study:
    """Load an existing study, with the available names in the error when it is missing.

    Args:
        name: The study's name.
        storage: A storage, or a URL (string or parsed) opened with
            [`open_storage`][ermrl.storage.open_storage] in ``mode``.
        mode: ``"read"`` (default): nothing is created, a missing SQLite or journal file is a
            [`StorageError`][ermrl.storage.StorageError]; ``"write"``: the same, for commands that
            change the study.
        **kwargs: Passed to `optuna.load_study` (e.g. ``sampler``).

    Raises:
        StorageError: the storage cannot be opened or its file does not exist.
        StudyNotFound: no study of that name.
    """
    if isinstance(storage, (str, StorageURL)):
        storage = open_storage(storage, mode=mode)
    try:
        return optuna.load_study(study_name=name, storage=storage, **kwargs)
    except KeyError as err:
        names = study_names(storage)
        hint = f"; studies there: {', '.join(names)}" if names else "; the storage has no study"
        raise StudyNotFound(f"no study named {name!r}{hint}") from err


def worker_info() -> dict[str, Any]:
    """Who runs a trial: hostname, pid and SLURM ids when set."""
    import socket

    info: dict[str, Any] = {"hostname": socket.gethostname(), "pid": os.getpid()}
    for var in ("SLURM_JOB_ID", "SLURM_ARRAY_JOB_ID", "SLURM_ARRAY_TASK_ID"):
        if os.environ.get(var):
            info[var.lower()] = os.environ[var]
    return info
