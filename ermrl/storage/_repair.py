"""Repairing a journal (file or Redis) that holds records no command can read.

A journal file is JSON records, one per line, only ever appended to. When a write is cut short
(the disk filled up, the file system hit its quota, the node died mid-write), the file ends with
a partial line; an older ermrl (or plain Optuna) then appended the next record straight after
it, which glued the two into one undecodable line. A line can also be garbage for other reasons
(written by hand, a bad disk). Optuna reads a journal up to its first unreadable record and then
fails, so every command fails.

[`repair_journal`][ermrl.storage.repair_journal] finds every unreadable line of a journal file
(anywhere, not only at its end) and, under the journal's own write lock (so no worker writes while
it does), keeps every record in it and moves only what cannot be read to ``<file>.torn-<UTC time>``:
records glued together (a newline lost) are split onto lines of their own, a record glued onto a
partial one is kept and only the partial one is set aside. A readable record is never removed; every
other line stays, in order. Workers call it before they use a journal
([`open_storage`][ermrl.storage.open_storage]); ``ermrl study repair`` calls it by hand.

A Redis journal numbers its records ``<prefix>:log:0``, ``:log:1``, ... up to the counter
``<prefix>:log_number``. [`repair_redis_journal`][ermrl.storage.repair_redis_journal] moves
unreadable records to the hash ``<prefix>:torn-<UTC time>`` (field: the record's old number),
renumbers the records that are left without gaps, and sets ``log_number`` to the last of them, in
one transaction that is retried if a worker appends meanwhile.

Nothing is merged or dropped silently: what is set aside stays there, and a warning (or
``ermrl study repair``'s one line) says how many records and where.
"""

from __future__ import annotations

import json
import logging
import os
import stat
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from ermrl.storage._url import StorageError, StorageURL, parse_storage_url

__all__ = [
    "JournalRepair",
    "check_journal",
    "is_journal_record",
    "journal_record",
    "repair_journal",
    "repair_redis_journal",
    "torn_tail",
]

_log = logging.getLogger("ermrl.storage")
_TAIL_CHUNK = 1 << 16
_COPY_CHUNK = 1 << 20
# How a record written by Optuna's JournalFileBackend begins (compact JSON, op_code first).
_RECORD_START = b'{"op_code":'
_FIRST_LINE_MAX = 1 << 20
_REDIS_BATCH = 1000
_DECODER = json.JSONDecoder()


def _op_codes() -> frozenset[int]:
    from optuna.storages.journal._storage import JournalOperation

    return frozenset(int(op) for op in JournalOperation)


_OP_CODES = _op_codes()


def is_journal_record(value: object) -> bool:
    """Whether a decoded value is an Optuna journal record: a JSON object with a known integer
    ``op_code`` and a string ``worker_id``."""
    if not isinstance(value, dict):
        return False
    op_code = value.get("op_code")
    return type(op_code) is int and op_code in _OP_CODES and isinstance(value.get("worker_id"), str)


def journal_record(raw: bytes | str) -> dict[str, Any] | None:
    """The journal record encoded in ``raw``, or ``None`` when it is not one (see
    `is_journal_record`)."""
    try:
        value = json.loads(raw)
    except (ValueError, RecursionError):  # JSONDecodeError, UnicodeDecodeError
        return None
    return value if is_journal_record(value) else None


@dataclass(frozen=True)
class JournalRepair:
    """What a repair changed in a journal.

    Attributes:
        journal: The journal: its file, or its Redis storage URL.
        aside: Where the set-aside records are kept: the file ``<journal>.torn-<UTC time>``
            (one record a line; a partial last record without its newline) or the Redis hash
            ``<prefix>:torn-<UTC time>`` (field: the record's old number); ``None`` when no
            record was set aside.
        n_records: Unreadable records set aside.
        n_bytes: Their size in bytes.
        partial: Whether the last of them was a partial last line (a write cut short).
        n_missing: Redis: record numbers below ``log_number`` that held no record; the records
            after them were renumbered.
        n_split: File: lines that held several records glued together (a newline lost), split
            so that each record is a line of its own.
        log_number: Redis: ``log_number`` before and after, when it did not name the last
            stored record (``None`` before: the key was missing or not a number).
    """

    journal: str
    aside: str | None = None
    n_records: int = 0
    n_bytes: int = 0
    partial: bool = False
    n_missing: int = 0
    log_number: tuple[int | None, int] | None = None
    n_split: int = 0

    def describe(self) -> str:
        """One line: what was set aside, renumbered and fixed."""
        parts = []
        if self.n_records:
            s = "" if self.n_records == 1 else "s"
            last = ", the last one partial" if self.partial else ""
            parts.append(
                f"set aside {self.n_records} unreadable record{s} ({self.n_bytes} bytes{last}) "
                f"in {self.aside}"
            )
        if self.n_split:
            s = "" if self.n_split == 1 else "s"
            parts.append(
                f"split {self.n_split} line{s} of glued records, each record kept on a line of "
                "its own"
            )
        if self.n_missing:
            s = "" if self.n_missing == 1 else "s"
            parts.append(f"renumbered the records after {self.n_missing} missing number{s}")
        if self.log_number is not None:
            before, after = self.log_number
            parts.append(
                f"set log_number from {'none' if before is None else before} to {after} "
                f"({after + 1} records)"
            )
        return f"{self.journal}: " + "; ".join(parts)


def _stamp() -> str:
    return datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")


def check_journal(path: Path | str) -> None:
    """Refuse a path that is not an Optuna journal file, before anything reads or writes it.

    A missing or empty file is a new journal. Otherwise the first line must be a journal
    record: a JSON object with ``op_code`` and ``worker_id``. A file that is one line without a
    newline is a journal whose first record was cut short when it begins as Optuna's records
    do (``{"op_code":``), so that [`repair_journal`][ermrl.storage.repair_journal] can set it aside.

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
        # A first record glued onto a partial one (an older ermrl) is repaired, not refused.
        ok = is_journal_record(record) or head.startswith(_RECORD_START)
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


@dataclass(frozen=True)
class _Damage:
    """An unreadable line of a journal file and what a repair makes of it.

    Attributes:
        start: Offset of the line in the file.
        end: Offset just past it (past its newline, when it has one).
        kept: Byte spans (absolute) of the readable records found in it, in order: each is
            written back as a line of its own.
        aside: Byte spans (absolute) of what cannot be read, in order: each is set aside.
        whole: Whether the whole line, newline included, is one span set aside.
    """

    start: int
    end: int
    kept: tuple[tuple[int, int], ...]
    aside: tuple[tuple[int, int], ...]

    @property
    def whole(self) -> bool:
        return not self.kept and self.aside == ((self.start, self.end),)


def _record_end(line: bytes, position: int) -> int | None:
    """Where the journal record that starts at ``line[position]`` ends (``None``: none does)."""
    text = line[position:].decode("utf-8", errors="surrogateescape")
    try:
        _, end = _DECODER.raw_decode(text)
    except (ValueError, RecursionError):
        return None
    stop = position + len(text[:end].encode("utf-8", errors="surrogateescape"))
    return stop if journal_record(line[position:stop]) is not None else None


def _split(line: bytes) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Split an unreadable line (without its newline) into records and unreadable pieces.

    Records glued together (a newline lost, an edit by hand, an older ermrl that appended after
    a partial record) are each kept; the bytes between them that are no record are set aside,
    except whitespace alone. A record starts where Optuna's records do (``{"op_code":``).

    Returns:
        ``(kept, aside)``: byte spans relative to the line.
    """
    kept: list[tuple[int, int]] = []
    aside: list[tuple[int, int]] = []
    position = 0
    while position < len(line):
        end = _record_end(line, position) if line.startswith(_RECORD_START, position) else None
        if end is not None:
            kept.append((position, end))
            position = end
            continue
        following = line.find(_RECORD_START, position + 1)
        stop = len(line) if following < 0 else following
        if line[position:stop].strip():
            aside.append((position, stop))
        position = stop
    return kept, aside


def _damage(path: Path) -> list[_Damage]:
    """The unreadable lines of a journal file, in order, each split (see `_Damage`).

    A line is split into the records glued in it, which are kept, and what cannot be read,
    which is set aside; a line without any record is set aside whole. The records of a last
    line without its newline (a write cut short) are kept, its last piece is set aside.
    """
    damage = []
    offset = 0
    with open(path, "rb") as f:
        for line in f:
            start, offset = offset, offset + len(line)
            complete = line.endswith(b"\n")
            if complete and journal_record(line) is not None:
                continue
            body = line[:-1] if complete else line
            kept, aside = _split(body)
            if not complete and kept and kept[-1][1] == len(body):
                aside.append(kept.pop())  # a cut write: its last record may be incomplete
            if not kept:
                aside = [(0, len(line))]
            damage.append(
                _Damage(
                    start=start,
                    end=offset,
                    kept=tuple((start + a, start + b) for a, b in kept),
                    aside=tuple((start + a, start + b) for a, b in aside),
                )
            )
    return damage


def repair_journal(path: Path | str) -> JournalRepair | None:
    """Set aside every unreadable record of a journal file, if there is any.

    The file is read again under the journal's write lock (the one Optuna's
    ``JournalFileBackend`` takes to append), so a record another worker is writing right now is
    never mistaken for a torn one. A line that holds several records glued together is split,
    each record on a line of its own; only what cannot be read is set aside: a readable record
    is never removed. The unreadable bytes are written to ``<file>.torn-<UTC time>`` (and synced)
    before the journal changes, so a failure (e.g. the disk is still full) leaves the journal as
    it was. A partial last record alone is cut off in place; otherwise the kept records are
    written to a new file that replaces the journal in one step. Workers that have the journal
    open stay consistent: none could read past an unreadable record, and the records before it
    keep their numbers.

    Args:
        path: The journal file.

    Returns:
        What was set aside or split, or ``None`` when every record was readable.

    Raises:
        StorageError: the path is not a journal file (`check_journal`; left untouched).
        OSError: the records could not be set aside (the journal is unchanged).
    """
    from ermrl.storage._locks import journal_file_lock

    path = Path(path)
    check_journal(path)
    if not path.is_file() or not _damage(path):
        return None
    with journal_file_lock(path):
        damage = _damage(path)  # a write that was in progress has ended now
        if not damage:
            return None
        size = os.path.getsize(path)
        last = damage[-1]
        partial = bool(last.aside) and last.aside[-1][1] == size and torn_tail(path) > 0
        aside = path.with_name(f"{path.name}.torn-{_stamp()}") if _n_aside(damage) else None
        n_bytes = _set_aside(path, damage, aside) if aside is not None else 0
        if len(damage) == 1 and last.whole and partial:
            with open(path, "r+b") as f:
                f.truncate(last.start)
                f.flush()
                os.fsync(f.fileno())
        else:
            _rewrite(path, damage)
    repair = JournalRepair(
        journal=str(path),
        aside=None if aside is None else str(aside),
        n_records=_n_aside(damage),
        n_bytes=n_bytes,
        partial=partial,
        n_split=sum(1 for d in damage if d.kept),
    )
    _log.warning(
        "repaired journal (unreadable records come from a write cut short, or garbage): %s",
        repair.describe(),
    )
    return repair


def _n_aside(damage: list[_Damage]) -> int:
    return sum(len(d.aside) for d in damage)


def _set_aside(path: Path, damage: list[_Damage], aside: Path) -> int:
    """Write the unreadable pieces of ``damage`` to ``aside``, one a line; their byte count.

    A line set aside whole keeps its own newline (a partial last line has none); a piece cut
    out of a line gets one.
    """
    n_bytes = 0
    try:
        with open(path, "rb") as src, open(aside, "xb") as out:
            for line in damage:
                for start, end in line.aside:
                    src.seek(start)
                    piece = src.read(end - start)
                    n_bytes += len(piece)
                    out.write(piece if line.whole else piece + b"\n")
            out.flush()
            os.fsync(out.fileno())
    except OSError:
        aside.unlink(missing_ok=True)
        raise
    return n_bytes


def _rewrite(path: Path, damage: list[_Damage]) -> None:
    """Replace ``path`` by a copy where each damaged line is its kept records, one a line."""
    new = path.with_name(f".{path.name}.repair-{_stamp()}")
    try:
        with open(path, "rb") as src, open(new, "xb") as out:
            os.chmod(new, stat.S_IMODE(os.fstat(src.fileno()).st_mode))
            position = 0
            for line in [*damage, None]:
                stop = os.fstat(src.fileno()).st_size if line is None else line.start
                _copy(src, out, position, stop)
                if line is None:
                    break
                for start, end in line.kept:
                    src.seek(start)
                    out.write(src.read(end - start) + b"\n")
                position = line.end
            out.flush()
            os.fsync(out.fileno())
        os.replace(new, path)
    except BaseException:
        new.unlink(missing_ok=True)
        raise
    try:
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _copy(src: Any, out: Any, start: int, stop: int) -> None:
    """Copy the bytes ``[start, stop)`` of ``src`` to ``out``, in chunks."""
    src.seek(start)
    left = stop - start
    while left > 0:
        chunk = src.read(min(left, _COPY_CHUNK))
        if not chunk:
            break
        out.write(chunk)
        left -= len(chunk)


def repair_redis_journal(url: str | StorageURL) -> JournalRepair | None:
    """Set aside the unreadable records of a Redis journal and renumber the others.

    The records ``<prefix>:log:N`` are read in order of ``N``. Unreadable ones go to the hash
    ``<prefix>:torn-<UTC time>`` (field ``N``); the rest are renumbered ``0, 1, ...`` (closing
    the gaps of numbers that hold no record) and ``<prefix>:log_number`` is set to the last of
    them, as Optuna counts it. All of it is one ``MULTI``/``EXEC`` transaction that watches
    ``log_number``: when a worker appends meanwhile, it is read and done again. Workers that
    have the journal open stay consistent: none could read past a missing or unreadable
    record, and the records before it keep their numbers.

    Args:
        url: The ``redis://`` storage URL (``?prefix=NAME`` selects the journal).

    Returns:
        What was changed, or ``None`` when the journal was intact.

    Raises:
        StorageError: not a Redis URL, or the server cannot be reached (one line).
    """
    import redis

    spec = url if isinstance(url, StorageURL) else parse_storage_url(url)
    if spec.kind != "redis":
        raise StorageError(f"{spec} is not a Redis journal")
    try:
        client = redis.Redis.from_url(spec.url)
        try:
            with client.pipeline() as pipe:
                while True:
                    try:
                        return _repair_redis(pipe, spec)
                    except redis.WatchError:
                        continue  # a worker appended meanwhile: read again
        finally:
            client.close()
    except redis.RedisError as err:
        text = str(err).strip().splitlines()
        raise StorageError(
            f"cannot repair Redis journal {spec}: {text[0] if text else type(err).__name__}"
        ) from err


def _glob_escape(text: str) -> str:
    return "".join("\\" + c if c in "*?[]\\" else c for c in text)


def _repair_redis(pipe: Any, spec: StorageURL) -> JournalRepair | None:
    prefix = spec.prefix
    counter = f"{prefix}:log_number"
    pipe.watch(counter)
    raw = pipe.get(counter)
    try:
        log_number: int | None = None if raw is None else int(raw)
    except ValueError:
        log_number = None
    head = f"{prefix}:log:".encode()
    numbers = []
    for key in pipe.scan_iter(match=_glob_escape(prefix) + ":log:*", count=1000):
        suffix = key[len(head) :] if key.startswith(head) else b""
        if suffix.isdigit() and str(int(suffix)).encode() == suffix:
            numbers.append(int(suffix))
    numbers.sort()
    kept: list[tuple[int, bytes]] = []
    bad: list[tuple[int, bytes]] = []
    for start in range(0, len(numbers), _REDIS_BATCH):
        batch = numbers[start : start + _REDIS_BATCH]
        for number, value in zip(batch, pipe.mget([f"{prefix}:log:{n}" for n in batch])):
            if value is None:
                continue  # deleted meanwhile
            (kept if journal_record(value) is not None else bad).append((number, value))
    last = len(kept) - 1
    if raw is None and not numbers:
        return None  # a new journal: nothing written yet
    n_missing = numbers[-1] + 1 - len(numbers) if numbers else 0
    in_place = all(number == i for i, (number, _) in enumerate(kept))
    if not bad and in_place and log_number == last:
        return None
    aside = f"{prefix}:torn-{_stamp()}"
    pipe.multi()
    if bad:
        pipe.hset(aside, mapping={str(number): value for number, value in bad})
    for i, (number, value) in enumerate(kept):
        if number != i:
            pipe.set(f"{prefix}:log:{i}", value)
    for number in numbers:
        if number > last:
            pipe.delete(f"{prefix}:log:{number}")
    pipe.set(counter, last)
    pipe.execute()
    repair = JournalRepair(
        journal=spec.raw,
        aside=aside if bad else None,
        n_records=len(bad),
        n_bytes=sum(len(value) for _, value in bad),
        n_missing=n_missing,
        log_number=None if log_number == last else (log_number, last),
    )
    _log.warning("repaired Redis journal: %s", repair.describe())
    return repair
