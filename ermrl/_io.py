"""Writing files atomically: readers (other SLURM tasks, a live view) never see half a file."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["write_atomic"]


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


def _umask() -> int:
    """The process umask (it can only be read by setting it, so it is set back at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
