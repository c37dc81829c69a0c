"""Open Optuna storages and studies from a URL, with clear errors.

Accepted URLs:

- ``sqlite:///path.db``: the embedded default (one machine; see README for concurrency notes);
- ``postgresql://user@host/db`` and ``mysql+pymysql://...``: shared RDB servers for clusters;
- ``journal:///path.log`` or any path ending in ``.log``: an append-only journal file;
- ``redis://host:port``: Optuna's journal over Redis (needs the ``redis`` package).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import optuna
from optuna.storages import BaseStorage

__all__ = [
    "StorageError",
    "StudyNotFound",
    "DEFAULT_STORAGE",
    "storage_kind",
    "open_storage",
    "load_study",
    "study_names",
]

DEFAULT_STORAGE = "sqlite:///ermrl.db"
SQLITE_BUSY_TIMEOUT_S = 60


class StorageError(RuntimeError):
    """The storage URL is malformed or the storage cannot be reached."""


class StudyNotFound(LookupError):
    """No study of that name exists in the storage."""


def storage_kind(url: str) -> str:
    """Classify a storage URL: ``sqlite``, ``postgresql``, ``mysql``, ``journal`` or ``redis``."""
    if url.startswith("journal://") or (url.endswith(".log") and "://" not in url):
        return "journal"
    scheme = url.split("://", 1)[0].split("+", 1)[0].lower() if "://" in url else ""
    if scheme in ("sqlite", "postgresql", "postgres", "mysql", "redis"):
        return "postgresql" if scheme == "postgres" else scheme
    raise StorageError(
        f"unsupported storage URL {url!r}; use sqlite:///file.db, postgresql://..., "
        "mysql+pymysql://..., journal:///file.log (or file.log) or redis://host:port"
    )


def _journal_path(url: str) -> Path:
    return Path(url[len("journal://") :] if url.startswith("journal://") else url)


def open_storage(
    url: str, *, heartbeat_interval: int | None = None, grace_period: int | None = None
) -> BaseStorage:
    """Open (and for RDB storages create the schema of) a storage.

    Args:
        url: A storage URL (see module docstring).
        heartbeat_interval: Seconds between heartbeats of running trials (RDB storages only).
        grace_period: Seconds without a heartbeat after which a running trial is stale.

    Returns:
        An Optuna storage.

    Raises:
        StorageError: the URL is malformed or the storage is unreachable.
    """
    kind = storage_kind(url)
    try:
        if kind == "journal":
            from optuna.storages import JournalStorage
            from optuna.storages.journal import JournalFileBackend

            path = _journal_path(url)
            if not path.parent.exists():
                raise StorageError(f"directory {path.parent} of journal {path} does not exist")
            return JournalStorage(JournalFileBackend(str(path)))
        if kind == "redis":
            from optuna.storages import JournalStorage
            from optuna.storages.journal import JournalRedisBackend

            storage = JournalStorage(JournalRedisBackend(url))
            storage.get_all_studies()  # fail now if the server is unreachable
            return storage
        engine_kwargs: dict[str, Any] = {}
        if kind == "sqlite":
            path_part = url.split("///", 1)[1] if "///" in url else ""
            if path_part and path_part != ":memory:":
                parent = Path(path_part).expanduser().resolve().parent
                if not parent.exists():
                    raise StorageError(f"directory {parent} of SQLite database does not exist")
            engine_kwargs["connect_args"] = {"timeout": SQLITE_BUSY_TIMEOUT_S}
        else:
            engine_kwargs["pool_pre_ping"] = True
            engine_kwargs["connect_args"] = {"connect_timeout": 10}
        return optuna.storages.RDBStorage(
            url,
            engine_kwargs=engine_kwargs,
            heartbeat_interval=heartbeat_interval,
            grace_period=grace_period,
        )
    except StorageError:
        raise
    except Exception as err:  # sqlalchemy / driver / redis errors: keep the message short
        message = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise StorageError(f"cannot open storage {url}: {message}") from err


def study_names(storage: BaseStorage) -> list[str]:
    """Names of the studies in a storage."""
    return [s.study_name for s in storage.get_all_studies()]


def load_study(name: str, storage: BaseStorage | str, **kwargs: Any) -> optuna.Study:
    """Load an existing study, with the available names in the error when it is missing."""
    if isinstance(storage, str):
        storage = open_storage(storage)
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
