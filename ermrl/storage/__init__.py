"""Opening Optuna storages (SQLite, PostgreSQL, MySQL, journal files, Redis) and studies, the
locks that let many workers share one study, and the recovery of trials whose worker died."""

from ermrl.storage._heartbeat import (
    HEARTBEAT_ATTR,
    HeartbeatJournalStorage,
    RetryStaleTrial,
    fail_stale,
    fail_stale_trials,
    find_stale_trials,
    last_seen,
)
from ermrl.storage._locks import LockTimeout, storage_lock
from ermrl.storage._open import (
    DEFAULT_GRACE_PERIOD,
    DEFAULT_HEARTBEAT_INTERVAL,
    DEFAULT_MAX_RETRY,
    DEFAULT_STORAGE,
    StorageError,
    StudyNotFound,
    load_study,
    normalize_url,
    open_storage,
    storage_kind,
    storage_url,
    study_lock,
    study_names,
    worker_info,
)
from ermrl.storage._repair import repair_journal, torn_tail
from ermrl.storage._url import StorageKind, StorageURL, parse_storage_url

__all__ = [
    "DEFAULT_GRACE_PERIOD",
    "DEFAULT_HEARTBEAT_INTERVAL",
    "DEFAULT_MAX_RETRY",
    "DEFAULT_STORAGE",
    "HEARTBEAT_ATTR",
    "HeartbeatJournalStorage",
    "LockTimeout",
    "RetryStaleTrial",
    "StorageError",
    "StorageKind",
    "StorageURL",
    "StudyNotFound",
    "fail_stale",
    "fail_stale_trials",
    "find_stale_trials",
    "last_seen",
    "load_study",
    "normalize_url",
    "open_storage",
    "parse_storage_url",
    "repair_journal",
    "storage_kind",
    "storage_lock",
    "storage_url",
    "study_lock",
    "study_names",
    "torn_tail",
    "worker_info",
]
