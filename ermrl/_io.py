"""Reading YAML with a depth limit, and writing files atomically: readers (other SLURM tasks,
a live view) never see half a file."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import yaml

from ermrl._interrupt import raise_swallowed_signal

__all__ = ["MAX_YAML_DEPTH", "load_yaml", "staged_folder", "write_atomic"]

#: The deepest nesting of lists and mappings a YAML document may have (settings need a few).
MAX_YAML_DEPTH = 50


def load_yaml(text: str, loader: type[yaml.SafeLoader] = yaml.SafeLoader) -> Any:
    """Read a YAML document with a safe loader, refusing one nested too deeply.

    PyYAML reads nested lists and mappings recursively: ``[[[...]]]`` 500 deep stops it with
    a `RecursionError`. Every YAML that ermrl reads (experiment files, hyperparameter and
    suite files, ``--ppo`` values) comes through here, so the limit is checked once, on the
    parser's events, before anything is built.

    Args:
        text: The document.
        loader: `yaml.SafeLoader` or a subclass of it.

    Returns:
        The document's value.

    Raises:
        yaml.YAMLError: not valid YAML, or lists and mappings nested deeper than
            `MAX_YAML_DEPTH` (one line, with the line it happens on).

    Examples:
        >>> load_yaml("a: [1, {b: 2}]")
        {'a': [1, {'b': 2}]}
    """
    depth = 0
    for event in yaml.parse(text, Loader=loader):
        if isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                at = event.start_mark  # its line and column, without PyYAML's snippet
                raise yaml.MarkedYAMLError(
                    problem=f"lists and mappings nested deeper than {MAX_YAML_DEPTH} levels",
                    problem_mark=yaml.Mark(at.name, at.index, at.line, at.column, None, None),
                )
        elif isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
            depth -= 1
    return yaml.load(text, Loader=loader)  # noqa: S506 (a safe loader)


def write_atomic(path: str | Path, data: str | bytes) -> None:
    """Write a file so that readers never see it half-written (several SLURM tasks may race).

    The data goes to a temporary file in the same folder, renamed over ``path`` once complete;
    on an error (a full disk, ...) the temporary file is removed and ``path`` is left as it
    was. The file gets the usual permissions, ``0o666`` less the umask (``mkstemp`` alone
    would make it ``0o600``, unreadable by colleagues sharing a results folder).

    Args:
        path: The file to write.
        data: Its contents: text, or bytes (a ``torch.save`` of a policy, ...).

    Raises:
        OSError: the file cannot be written (``ENOSPC``, ``EROFS``, ...).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb" if isinstance(data, bytes) else "w") as handle:
            os.fchmod(handle.fileno(), 0o666 & ~_umask())
            handle.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def staged_folder(path: str | Path) -> Iterator[Path]:
    """A temporary folder whose contents move into ``path`` when the block ends without error.

    For outputs of many files (a report, a recording): the block writes into the yielded
    folder, created next to ``path`` (or inside it, when ``path`` exists, so that every move is
    a rename on one file system). On success each file is renamed into ``path``, replacing a
    file of the same name; files of ``path`` the block did not write are kept. On an error (a
    full disk, a read-only folder, an interruption) the temporary folder is removed, and so are
    the folders this created: ``path`` is left as it was, with no partial output. A temporary
    folder left by a process killed outright (``kill -9``) is removed by the next call for the
    same ``path`` on that machine.

    Args:
        path: The output folder.

    Yields:
        The folder to write into.

    Raises:
        OSError: the temporary folder cannot be created (``EROFS``, ``ENOSPC``, ...), or what
            the block raises.
    """
    path = Path(path)
    created = [p for p in (path, *path.parents) if not p.exists()]
    home = path if path.is_dir() else path.parent
    home.mkdir(parents=True, exist_ok=True)
    _remove_dead_stages(home, path.name)
    try:
        stage = Path(tempfile.mkdtemp(dir=home, prefix=_stage_prefix(path.name)))
    except BaseException:
        _remove_empty(created)
        raise
    try:
        yield stage
        raise_swallowed_signal()  # a SIGTERM dropped in a callback: publish nothing
        os.chmod(stage, 0o777 & ~_umask())  # mkdtemp makes it 0o700
        if not path.exists():
            os.replace(stage, path)
        else:
            _merge(stage, path)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        _remove_empty(created)
        raise
    shutil.rmtree(stage, ignore_errors=True)


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname()) or "host"


def _stage_prefix(name: str) -> str:
    """``.<name>.<host>.<pid>.``: whose a staging folder is, so a dead one can be told."""
    return f".{name}.{_host()}.{os.getpid()}."


def _remove_dead_stages(home: Path, name: str) -> None:
    """Remove the staging folders of ``name`` in ``home`` that a killed process left behind
    (``kill -9``, a machine that went down): those of a process of this machine that is gone,
    and those from before ermrl named them by process that no one touched for a day. A stage
    of a live process, or of another machine, is left alone."""
    pattern = re.compile(
        rf"\.{re.escape(name)}\.(?:(?P<host>[A-Za-z0-9-]+)\.(?P<pid>\d+)\.)?[A-Za-z0-9_]{{8}}"
    )
    host = _host()
    try:
        entries = list(home.iterdir())
    except OSError:
        return
    for entry in entries:
        match = pattern.fullmatch(entry.name)
        if match is None or not entry.is_dir() or entry.is_symlink():
            continue
        if match["pid"] is None:
            with contextlib.suppress(OSError):
                if time.time() - entry.stat().st_mtime > 86_400:
                    shutil.rmtree(entry, ignore_errors=True)
            continue
        if match["host"] == host and not _alive(int(match["pid"])):
            shutil.rmtree(entry, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _merge(source: Path, target: Path) -> None:
    """Rename every file under ``source`` to the same place under ``target``."""
    for entry in source.iterdir():
        dest = target / entry.name
        if entry.is_dir() and not entry.is_symlink() and dest.is_dir():
            _merge(entry, dest)
        else:
            if dest.is_dir() and not dest.is_symlink():
                shutil.rmtree(dest)
            os.replace(entry, dest)


def _remove_empty(folders: list[Path]) -> None:
    """Remove the folders of ``folders`` (deepest first) that are empty."""
    for folder in folders:
        with contextlib.suppress(OSError):
            folder.rmdir()


def _umask() -> int:
    """The process umask (it can only be read by setting it, so it is set back at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
