"""Opening Optuna storages (SQLite, PostgreSQL, MySQL, journal files, Redis) and studies."""

from ermrl.storage._open import (
    DEFAULT_STORAGE,
    StorageError,
    StudyNotFound,
    load_study,
    open_storage,
    storage_kind,
    study_names,
    worker_info,
)

__all__ = [
    "DEFAULT_STORAGE",
    "StorageError",
    "StudyNotFound",
    "load_study",
    "open_storage",
    "storage_kind",
    "study_names",
    "worker_info",
]
