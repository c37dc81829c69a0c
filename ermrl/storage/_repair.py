"""Repairing a journal file whose last record was cut short.

A journal is a file of JSON records, one per line, only ever appended to. When a write is cut
short (the disk filled up, the file system hit its quota, the node died mid-write), the file ends
with a partial line. Optuna still reads the complete records before it, but the next worker
appends straight after the partial line, which makes one undecodable line: from then on every
read fails with ``JSONDecodeError``.

:func:`repair_journal` moves the partial record to ``<file>.torn-<UTC time>`` and cuts the
journal back to its last complete record, under the journal's own write lock, so no worker writes
while it does. Workers call it before they use a journal (:func:`~ermrl.storage.open_storage`);
``ermrl study repair`` calls it by hand. The partial record is never merged or dropped silently.
"""

from __future__ import annotations

import json
import logging
import os
from datetime import datetime, timezone
from pathlib import Path

from ermrl.storage._url import StorageError

__all__ = ["check_journal", "torn_tail", "repair_journal"]

_log = logging.getLogger("ermrl.storage")
_TAIL_CHUNK = 1 << 16
# How a record written by Optuna's JournalFileBackend begins (compact JSON, op_code first).
_RECORD_START = b'{"op_code":'
_FIRST_LINE_MAX = 1 << 20


def check_journal(path: Path | str) -> None:
    """Refuse a path that is not an Optuna journal file, before anything reads or writes it.

    A missing or empty file is a new journal. Otherwise the first line must be a journal
    record: a JSON object with ``op_code`` and ``worker_id``. A file that is one line without a
    newline is a journal whose first record was cut short when it begins as Optuna's records
    do (``{"op_code":``), so that :func:`repair_journal` can set it aside.

    Args:
        path: The journal file.

    Raises:
        StorageError: the path is a directory, or a file that is not a journal (one line; the
            file is left untouched).
    """
    path = Path(path)
    if path.is_dir():
        raise StorageError(f"journal {path} is a directory, not a file (check --storage)")
    try:
        with open(path, "rb") as f:
            head = f.readline(_FIRST_LINE_MAX)
    except FileNotFoundError:
        return
    if not head:
        return
    if head.endswith(b"\n"):
        try:
            record = json.loads(head)
        except ValueError:  # JSONDecodeError, UnicodeDecodeError
            record = None
        ok = isinstance(record, dict) and {"op_code", "worker_id"} <= record.keys()
    else:  # one partial line: a cut first record, or not a journal at all
        ok = len(head) < _FIRST_LINE_MAX and (
            head.startswith(_RECORD_START) or _RECORD_START.startswith(head)
        )
    if not ok:
        raise StorageError(
            f"{path} is not an Optuna journal (its first line is not a journal record); it was "
            "left untouched: check --storage, or give a new .log file"
        )


def torn_tail(path: Path) -> int:
    """Number of bytes after the last complete record of a journal file (0: not torn).

    Args:
        path: The journal file (missing or empty: 0).
    """
    try:
        size = os.path.getsize(path)
    except FileNotFoundError:
        return 0
    if size == 0:
        return 0
    with open(path, "rb") as f:
        end = size
        while end > 0:
            start = max(0, end - _TAIL_CHUNK)
            f.seek(start)
            chunk = f.read(end - start)
            if end == size and chunk.endswith(b"\n"):
                return 0
            newline = chunk.rfind(b"\n")
            if newline >= 0:
                return size - (start + newline + 1)
            end = start
    return size


def repair_journal(path: Path | str) -> Path | None:
    """Set aside the partial last record of a journal file, if there is one.

    The check is made again under the journal's write lock (the one Optuna's
    ``JournalFileBackend`` takes to append), so a record another worker is writing right now is
    never mistaken for a torn one. The partial bytes are written to ``<file>.torn-<UTC time>``
    (and synced) before the journal is cut back, so a failure (e.g. the disk is still full)
    leaves the journal as it was.

    Args:
        path: The journal file.

    Returns:
        The file the partial record was moved to, or ``None`` when the journal was intact.

    Raises:
        StorageError: the path is not a journal file (:func:`check_journal`; left untouched).
        OSError: the partial record could not be set aside (the journal is unchanged).
    """
    from optuna.storages.journal import JournalFileSymlinkLock

    path = Path(path)
    check_journal(path)
    if torn_tail(path) == 0:
        return None
    lock = JournalFileSymlinkLock(str(path))
    lock.acquire()
    try:
        n_torn = torn_tail(path)  # a write that was in progress has ended now
        if n_torn == 0:
            return None
        size = os.path.getsize(path)
        keep = size - n_torn
        with open(path, "rb") as f:
            f.seek(keep)
            partial = f.read()
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
        aside = path.with_name(f"{path.name}.torn-{stamp}")
        try:
            with open(aside, "xb") as f:
                f.write(partial)
                f.flush()
                os.fsync(f.fileno())
        except OSError:
            aside.unlink(missing_ok=True)
            raise
        with open(path, "r+b") as f:
            f.truncate(keep)
            f.flush()
            os.fsync(f.fileno())
    finally:
        lock.release()
    _log.warning(
        "journal %s ended with a partial record (%d bytes, e.g. a full disk during a write); "
        "moved it to %s",
        path,
        n_torn,
        aside,
    )
    return aside
