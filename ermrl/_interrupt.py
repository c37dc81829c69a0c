"""Ctrl-C during a command's start-up, remembered; SIGTERM raised like Ctrl-C.

:func:`ermrl.cli.run_command` installs :func:`catch_sigint` before it imports the command (torch,
MuJoCo, the envs: seconds). The handler raises ``KeyboardInterrupt`` as Python's default one
does, and also notes that the signal came. A library that swallows the exception during its
start-up (a broad ``except`` around an optional import, a C extension that turns it into
another error that is then handled) would otherwise lose the user's Ctrl-C and let the command
run on; :class:`ermrl.search.SignalGuard` raises it again once it takes over (see
:func:`sigint_received`).

:func:`catch_sigterm` makes SIGTERM (``kill``, a SLURM time limit) raise :class:`Terminated`,
a ``KeyboardInterrupt``, so that a command stopped by it cleans up as on Ctrl-C (temporary
folders removed, finished runs kept) and says so in one line (:func:`interruption`), instead of
dying silently. Commands that handle SIGTERM themselves (an evolution's worker) install their
own handler while they run.
"""

from __future__ import annotations

import signal
import threading
from typing import Any

__all__ = [
    "Terminated",
    "catch_sigint",
    "catch_sigterm",
    "interruption",
    "raise_swallowed_sigint",
    "sigint_received",
]

_received = False


def _handler(signum: int, frame: Any) -> None:
    global _received
    _received = True
    raise KeyboardInterrupt


def catch_sigint() -> None:
    """Install the remembering SIGINT handler (main thread only) and forget earlier signals."""
    global _received
    _received = False
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _handler)


def sigint_received() -> bool:
    """Whether a SIGINT reached the handler of :func:`catch_sigint` since it was installed."""
    return _received


def raise_swallowed_sigint() -> None:
    """Raise ``KeyboardInterrupt`` if a SIGINT reached the handler of :func:`catch_sigint` and
    was lost, then forget it; a training loop calls this at every step (a module-level flag: no
    measurable cost).

    A Ctrl-C can land where Python cannot raise it: in a weakref callback of the import system
    (``_get_module_lock``), whose exceptions are printed as "Exception ignored in" and dropped.
    A lazy import in a training loop's first steps is such a place; without this check the
    command would train on to the end of its budget.
    """
    global _received
    if _received:
        _received = False
        raise KeyboardInterrupt


class Terminated(KeyboardInterrupt):
    """SIGTERM during a command (see :func:`catch_sigterm`)."""

    signum = signal.SIGTERM


def _sigterm(signum: int, frame: Any) -> None:
    raise Terminated


def catch_sigterm() -> None:
    """Make SIGTERM raise :class:`Terminated` in the main thread (no-op in another thread)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _sigterm)


def interruption(err: BaseException) -> tuple[str, int]:
    """What stopped a command, in words, and its exit code: ``("stopped by SIGTERM", 143)``
    for SIGTERM (:class:`Terminated`, or an exception with ``signum`` SIGTERM), else
    ``("interrupted", 130)`` (Ctrl-C)."""
    signum = getattr(err, "signum", None)
    if signum is not None and signum != signal.SIGINT:
        return f"stopped by {signal.Signals(signum).name}", 128 + int(signum)
    return "interrupted", 130
