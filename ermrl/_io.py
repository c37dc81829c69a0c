"""Writing files atomically: readers (other SLURM tasks, a live view) never see half a file."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["staged_folder", "write_atomic"]


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
    the folders this created: ``path`` is left as it was, with no partial output.

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
    try:
        stage = Path(tempfile.mkdtemp(dir=home, prefix=f".{path.name}."))
    except BaseException:
        _remove_empty(created)
        raise
    try:
        yield stage
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
