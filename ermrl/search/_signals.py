"""Signals in a worker: SIGTERM becomes [`Interrupted`][ermrl.search.Interrupted], Ctrl-C
``KeyboardInterrupt``.

Signals that arrive while a worker talks to the storage are deferred and raised right after, so
a claim or a ``tell`` is never cut in half.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from ermrl._interrupt import forget_signals, note_signal, noted_signal

__all__ = ["Interrupted", "SignalGuard", "sigterm_as_interrupt"]


class Interrupted(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM so that the running trial is closed like on Ctrl-C.

    Attributes:
        signum: The signal.
        trial_number: The trial this worker was running and closed as FAIL; ``None`` when the
            signal came between trials (nothing was running).
        requeued: Whether that trial was queued again (``False`` once its retries are spent).
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.trial_number: int | None = None
        self.requeued = False


class SignalGuard:
    """SIGTERM -> [`Interrupted`][ermrl.search.Interrupted], SIGINT -> ``KeyboardInterrupt``,
    deferred in critical sections (claiming a trial, telling a result) and raised at the next
    `check`.

    A second signal while one is already pending is raised at once (a way out of a hung storage).
    """

    def __init__(self) -> None:
        self.pending: int | None = None
        self._depth = 0

    def _handler(self, signum: int, frame: Any) -> None:
        second = self.pending is not None
        if not second:
            self.pending = signum
        # Also noted where a training loop looks (`raise_swallowed_signal`): raised in a weakref
        # callback, the exception is dropped, and the loop would train on to its end.
        note_signal(signum)
        if self._depth == 0 or second:
            self.check()

    def error(self) -> BaseException | None:
        """The exception of the pending signal, if any."""
        if self.pending is None:
            return None
        if self.pending == signal.SIGINT:
            return KeyboardInterrupt()
        return Interrupted(self.pending)

    def check(self) -> None:
        """Raise the pending signal's exception, if any."""
        error = self.error()
        if error is not None:
            raise error

    def wait(self, seconds: float) -> None:
        """Give a signal already on its way (e.g. to the whole process group) time to arrive."""
        deadline = time.monotonic() + seconds
        while self.pending is None and time.monotonic() < deadline:
            time.sleep(0.05)

    @contextmanager
    def deferred(self) -> Iterator[None]:
        self._depth += 1
        try:
            yield
        finally:
            self._depth = max(self._depth - 1, 0)

    @contextmanager
    def installed(self) -> Iterator[None]:
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = {s: signal.signal(s, self._handler) for s in (signal.SIGTERM, signal.SIGINT)}
        try:
            noted = noted_signal()  # a signal of the start-up that a library swallowed
            if noted is not None:
                self.pending = noted
                self.check()
            yield
        except BaseException:
            forget_signals()  # the exception on its way carries them: never raised twice
            raise
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Turn SIGTERM (SLURM time limit, preemption, ``kill``) into
    [`Interrupted`][ermrl.search.Interrupted]."""

    def handler(signum: int, frame: Any) -> None:
        raise Interrupted(signum)

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
