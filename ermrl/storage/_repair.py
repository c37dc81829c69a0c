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

import logging
import os
from datetime import datetime, timezone
from pathlib import Path

__all__ = ["torn_tail", "repair_journal"]

_log = logging.getLogger("ermrl.storage")
_TAIL_CHUNK = 1 << 16


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
        OSError: the partial record could not be set aside (the journal is unchanged).
    """
    from optuna.storages.journal import JournalFileSymlinkLock

    path = Path(path)
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
