"""Ctrl-C during a command's start-up, remembered.

:func:`ermrl.cli.run_command` installs :func:`catch_sigint` before it imports the command (torch,
MuJoCo, the envs: seconds). The handler raises ``KeyboardInterrupt`` as Python's default one
does, and also notes that the signal came. A library that swallows the exception during its
start-up (a broad ``except`` around an optional import, a C extension that turns it into
another error that is then handled) would otherwise lose the user's Ctrl-C and let the command
run on; :class:`ermrl.search.SignalGuard` raises it again once it takes over (see
:func:`sigint_received`).
"""

from __future__ import annotations

import signal
import threading
from typing import Any

__all__ = ["catch_sigint", "sigint_received"]

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
