"""Ctrl-C during a command's start-up, remembered; SIGTERM raised like Ctrl-C.

`ermrl.cli.run_command` installs `catch_sigint` before it imports the command (torch,
MuJoCo, the envs: seconds). The handler raises ``KeyboardInterrupt`` as Python's default one
does, and also notes that the signal came. A library that swallows the exception during its
start-up (a broad ``except`` around an optional import, a C extension that turns it into
another error that is then handled) would otherwise lose the user's Ctrl-C and let the command
run on; `ermrl.search.SignalGuard` raises it again once it takes over (see
`sigint_received`).

`catch_sigterm` makes SIGTERM (``kill``, a SLURM time limit) raise `Terminated`,
a ``KeyboardInterrupt``, so that a command stopped by it cleans up as on Ctrl-C (temporary
folders removed, finished runs kept) and says so in one line (`interruption`), instead of
dying silently. Commands that handle SIGTERM themselves (an evolution's worker) install their
own handler while they run.
"""

from __future__ import annotations

import signal
import sys
import threading
from typing import Any

__all__ = [
    "Terminated",
    "catch_sigint",
    "catch_sigterm",
    "forget_signals",
    "interruption",
    "note_signal",
    "noted_signal",
    "raise_swallowed_signal",
    "sigint_received",
    "swallowed_signal",
]

_received = False
_terminated = False


def _handler(signum: int, frame: Any) -> None:
    global _received
    _received = True
    raise KeyboardInterrupt


def _unraisable(unraisable: Any) -> None:
    """Python's hook for an exception it must drop (one raised in a weakref callback or a
    ``__del__``), quiet for the interruptions of these handlers: they are raised again later
    (`raise_swallowed_signal`), and the command's one line says what stopped it."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt) and (_received or _terminated):
        return
    sys.__unraisablehook__(unraisable)


def catch_sigint() -> None:
    """Install the remembering SIGINT handler (main thread only) and forget earlier signals."""
    global _received
    _received = False
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _handler)
        sys.unraisablehook = _unraisable


def note_signal(signum: int) -> None:
    """Note a SIGINT or SIGTERM that another handler received (`ermrl.search.SignalGuard`'s),
    as `catch_sigint` and `catch_sigterm` do, so that a loop's `raise_swallowed_signal`
    raises it when the handler's exception was dropped in a weakref callback, and the dropped
    exception is not printed."""
    global _received, _terminated
    if signum == signal.SIGTERM:
        _terminated = True
    else:
        _received = True
    if threading.current_thread() is threading.main_thread():
        sys.unraisablehook = _unraisable


def forget_signals() -> None:
    """Forget the signals noted so far: an exception that carries them is being handled."""
    global _received, _terminated
    _received = _terminated = False


def noted_signal() -> int | None:
    """The signal noted and not raised again yet: SIGTERM before SIGINT (``None``: none)."""
    return signal.SIGTERM if _terminated else signal.SIGINT if _received else None


def sigint_received() -> bool:
    """Whether a SIGINT reached the handler of `catch_sigint` since it was installed."""
    return _received


def raise_swallowed_signal() -> None:
    """Raise `Terminated` if a SIGTERM reached the handler of `catch_sigterm`, else
    ``KeyboardInterrupt`` if a SIGINT reached that of `catch_sigint`, and was lost; then
    forget it. A training loop calls this at every step (module-level flags: no measurable
    cost), and `ermrl._io.staged_folder` before it moves its output into place.

    A signal can land where Python cannot raise its exception: in a weakref callback (of the
    import system's ``_get_module_lock``, of a ``WeakKeyDictionary`` being collected), whose
    exceptions are printed as "Exception ignored in" and dropped. Without this check the
    command would train on to the end of its budget, or publish a report it was told to stop
    writing and exit 0.
    """
    global _received, _terminated
    if _terminated:
        _terminated = _received = False
        raise Terminated
    if _received:
        _received = False
        raise KeyboardInterrupt


def swallowed_signal(code: int) -> int:
    """The exit code of a command that returned ``code``: 143 (SIGTERM) or 130 (SIGINT) when it
    returned 0 though a signal came that nothing raised again (`raise_swallowed_signal`),
    else ``code``. A command that handles the signal itself returns its own non-zero code."""
    global _received, _terminated
    if code != 0 or not (_received or _terminated):
        return code
    code = 143 if _terminated else 130
    _received = _terminated = False
    return code


class Terminated(KeyboardInterrupt):
    """SIGTERM during a command (see `catch_sigterm`)."""

    signum = signal.SIGTERM


def _sigterm(signum: int, frame: Any) -> None:
    global _terminated
    _terminated = True
    raise Terminated


def catch_sigterm() -> None:
    """Make SIGTERM raise `Terminated` in the main thread (no-op in another thread), and
    note that it came, as `catch_sigint` does, and forget earlier ones."""
    global _terminated
    _terminated = False
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _sigterm)
        sys.unraisablehook = _unraisable


def interruption(err: BaseException) -> tuple[str, int]:
    """What stopped a command, in words, and its exit code: ``("stopped by SIGTERM", 143)``
    for SIGTERM (`Terminated`, or an exception with ``signum`` SIGTERM), else
    ``("interrupted", 130)`` (Ctrl-C). The signals noted so far count as handled: nothing
    raises them again (`raise_swallowed_signal`)."""
    global _received, _terminated
    _received = _terminated = False
    signum = getattr(err, "signum", None)
    if signum is not None and signum != signal.SIGINT:
        return f"stopped by {signal.Signals(signum).name}", 128 + int(signum)
    return "interrupted", 130
