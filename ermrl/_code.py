"""Which code made a result: the package version, its git commit and a hash of its source files.

``ermrl 0.1.0`` names every commit alike, so a record that should say which code produced it
(a trial, a test-phase run, a checkpoint) stores `code_identity` instead: the installed
version, the git commit of the checkout the package runs from (when it is one, with whether
its files differ from that commit) and a SHA-256 of the package's own source files, which
identifies the code wherever git is not available (an installed wheel, a copied tree).

Two records were made by the same code when their ``source`` hashes are equal and, where both
name it, numpy's BLAS kernel is the same (`same_code`; `ermrl._blas`); the commit is
what a reader looks up.
"""

from __future__ import annotations

import functools
import hashlib
import subprocess
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "code_identity",
    "code_key",
    "code_versions",
    "describe_code",
    "mixed_code",
    "same_code",
]

_PACKAGE = Path(__file__).resolve().parent
# What decides a result: the package's Python files and the data files it reads (PPO tables,
# suites). Byte-compiled files and caches are left out.
_SOURCE_SUFFIXES = (".py", ".yml", ".yaml", ".csv", ".json")


def _source_hash(root: Path = _PACKAGE) -> str:
    digest = hashlib.sha256()
    files = sorted(
        p for p in root.rglob("*") if p.is_file() and p.suffix in _SOURCE_SUFFIXES
        and "__pycache__" not in p.parts
    )  # fmt: skip
    for path in files:
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
        digest.update(b"\0")
    return digest.hexdigest()


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(
            ["git", *args],
            cwd=_PACKAGE,
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


@functools.lru_cache(maxsize=1)
def code_identity() -> dict[str, Any]:
    """The code this process runs, as plain JSON data (computed once per process).

    Returns:
        ``{"version": ..., "commit": ... | None, "dirty": bool | None, "source": sha256,
        "blas": ...}``: ``commit`` is ``None`` outside a git checkout; ``dirty`` says whether
        the package's files differ from that commit (``None`` when unknown); ``blas`` is the
        kernel numpy's products run with (`ermrl._blas.blas_kernel`): the same code and
        seed give the same result under the same kernel.
    """
    from ermrl import __version__
    from ermrl._blas import blas_kernel

    commit = None
    dirty = None
    if (_git("rev-parse", "--is-inside-work-tree") or "") == "true":
        commit = _git("rev-parse", "HEAD")
        status = _git("status", "--porcelain", "--", ".")
        dirty = None if status is None else bool(status)
    return {
        "version": __version__,
        "commit": commit,
        "dirty": dirty,
        "source": _source_hash(),
        "blas": blas_kernel(),
    }


def code_key() -> str:
    """A short key of the source hash, for checkpoint keys (16 hex digits)."""
    return str(code_identity()["source"])[:16]


def same_code(record: Mapping[str, Any] | None) -> bool | None:
    """Whether a stored `code_identity` is this process's code and BLAS kernel (``None``:
    not recorded)."""
    if not isinstance(record, Mapping) or not isinstance(record.get("source"), str):
        return None
    here = code_identity()
    blas = record.get("blas")  # records older than the BLAS field: the source alone
    if isinstance(blas, str) and blas != here["blas"]:
        return False
    return record["source"] == here["source"]


def describe_code(record: Mapping[str, Any] | None) -> str:
    """One phrase naming a stored `code_identity`: ``ermrl 0.1.0 at 1a2b3c4d (modified)``."""
    if not isinstance(record, Mapping):
        return "unrecorded code"
    text = f"ermrl {record.get('version', '?')}"
    commit = record.get("commit")
    if isinstance(commit, str) and commit:
        text += f" at {commit[:10]}" + (" (modified)" if record.get("dirty") else "")
    source = record.get("source")
    if isinstance(source, str):
        text += f", source {source[:10]}"
    blas = record.get("blas")
    if isinstance(blas, str):
        text += f", BLAS {blas}"
    return text


def code_versions(records: Iterable[Any]) -> list[tuple[dict[str, Any], int]]:
    """The distinct `code_identity` records among ``records`` (e.g. a study's trials'), each
    with how many records name it, most first; records without a source hash are skipped.

    Two records are one version when their source and BLAS kernel are (`same_code`'s rule).
    """
    found: dict[tuple[Any, Any], tuple[dict[str, Any], int]] = {}
    for record in records:
        if isinstance(record, Mapping) and isinstance(record.get("source"), str):
            key = (record["source"], record.get("blas"))
            first, n = found.get(key, (dict(record), 0))
            found[key] = (first, n + 1)
    return sorted(found.values(), key=lambda version: -version[1])


def mixed_code(versions: Iterable[tuple[Mapping[str, Any], int]]) -> str | None:
    """One line when trials come from more than one code version (``None``: one or none).

    Args:
        versions: `code_versions` of the trials.
    """
    versions = list(versions)
    if len(versions) < 2:
        return None
    listed = "; ".join(
        f"{describe_code(record)} ({n} trial{'s' if n != 1 else ''})" for record, n in versions
    )
    return (
        f"trials come from {len(versions)} code versions, so their results may not compare: "
        f"{listed}"
    )
