"""Progress of long work (a training run, a generation): steps done, rate and ETA.

One `Progress` per piece of work, in one of three modes:

- ``"lines"``: a line when a tenth of the work is done or ``interval`` seconds have passed since
  the last line, whichever comes first, and a last line at the end (logs, SLURM, pipes);
- ``"bar"``: a live `tqdm <https://tqdm.github.io>`_ bar, on a terminal; it stays on screen
  when the work ends, as the last line does in ``"lines"`` mode;
- ``"none"``: nothing.

`default_mode` picks ``"bar"`` when stdout is a terminal and ``"lines"`` otherwise.

The rate counts from the first `Progress.update`, not from the object's creation:
start-up (imports, env construction, spawning processes) is not work, and counting it made the
first run's rate look ten times lower than training's. The bar is created at the first update
for the same reason (tqdm counts its rate from the bar's creation, and ``smoothing=0`` makes it
the average since then, as the lines show).

A bar draws only in the process that created the `Progress`. Work sent to worker
processes prints lines there (bars from several processes on one terminal would overwrite each
other's rows), unless it reports to the parent: `relayed_bar` gives each part of a split
work a `Progress` that sends its counts to the parent over a queue, and the parent draws
one bar for them all (a population split over 2 processes shows one bar, not two streams of
lines).
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, Literal, TextIO

__all__ = [
    "PROGRESS_MODES",
    "Progress",
    "ProgressMode",
    "default_mode",
    "duration",
    "relayed_bar",
]

# A relayed part sends its count to the parent at most this often (seconds), and at its end.
RELAY_EVERY_S = 0.5

ProgressMode = Literal["bar", "lines", "none"]
PROGRESS_MODES: tuple[ProgressMode, ...] = ("bar", "lines", "none")


def default_mode(stream: TextIO | None = None) -> ProgressMode:
    """``"bar"`` when ``stream`` (default: ``sys.stdout``) is a terminal, else ``"lines"``.

    Examples:
        >>> import io
        >>> default_mode(io.StringIO())
        'lines'
    """
    stream = sys.stdout if stream is None else stream
    try:
        return "bar" if stream.isatty() else "lines"
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return "lines"


def duration(seconds: float) -> str:
    """``"1h02m"``, ``"3m05s"``, or ``"?"`` when not finite.

    Examples:
        >>> duration(3725), duration(185), duration(float("inf"))
        ('1h02m', '3m05s', '?')
    """
    if not math.isfinite(seconds):
        return "?"
    whole = int(round(seconds))
    h, rem = divmod(whole, 3600)
    m, s = divmod(rem, 60)
    return f"{h}h{m:02d}m" if h else f"{m}m{s:02d}s"


class Progress:
    """Lines of ``[label] done/total unit (pct) | rate | ETA`` at a steady interval, or a bar.

    Args:
        label: What is progressing, e.g. ``"res-ppo seed 10"``.
        total: The amount of work, e.g. training steps.
        mode: ``"bar"``, ``"lines"`` or ``"none"`` (see the module's docstring).
        interval: Seconds between lines at most.
        fraction: A line each time this fraction of ``total`` is passed.
        stream: Where lines go (default: ``sys.stdout`` at each line).
        unit: The unit of work, for the lines.
        clock: The clock (tests pass a fake one).
    """

    def __init__(
        self,
        label: str,
        total: int,
        *,
        mode: ProgressMode = "lines",
        interval: float = 30.0,
        fraction: float = 0.1,
        stream: TextIO | None = None,
        unit: str = "steps",
        clock: Callable[[], float] | None = None,
    ) -> None:
        if mode not in PROGRESS_MODES:
            raise ValueError(f"progress mode must be one of {PROGRESS_MODES}, got {mode!r}")
        self.label, self.total, self.mode, self.unit = label, max(int(total), 1), mode, unit
        self.interval, self.step = interval, max(int(self.total * fraction), 1)
        self._stream = stream
        self._clock = clock or time.monotonic
        self._t0: float | None = None
        self._done0 = 0
        self._last_time = 0.0
        self._next_mark = 0
        self.done = 0
        self.lines: list[str] = []  # every line due (printed in "lines" mode), for callers
        self._pid = os.getpid()  # a bar draws in this process only
        self._bar: Any = None
        self.note: str | None = None  # appended to the lines (the bar's postfix): "return -150.2"
        # (queue, part): this part's counts and messages go to the parent (relayed_bar).
        self.relay: tuple[Any, int] | None = None
        self._relayed_at = -math.inf

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_bar"] = None  # a bar stays with its process (a worker gets lines)
        return state

    @property
    def shows(self) -> ProgressMode:
        """What this process shows: the mode, except ``"lines"`` for a bar sent to a worker."""
        if self.mode == "bar" and os.getpid() != self._pid:
            return "lines"
        return self.mode

    def renamed(self, label: str, *, stream: TextIO | None = None) -> Progress:
        """A fresh progress of the same work and settings under another label (e.g. the part of
        a population that a worker process trains; a worker prints to its own stdout)."""
        other = Progress(
            label, self.total, mode=self.mode, interval=self.interval, stream=stream,
            unit=self.unit, clock=self._clock,
        )  # fmt: skip
        other.step = self.step
        return other

    def rate(self, now: float | None = None) -> float:
        """Units per second since the first update (``nan`` before two updates)."""
        if self._t0 is None:
            return math.nan
        elapsed = (self._clock() if now is None else now) - self._t0
        return (self.done - self._done0) / elapsed if elapsed > 0 else math.nan

    def update(self, done: int) -> None:
        """Record that ``done`` units are done (a running total); print a line when due."""
        now = self._clock()
        self.done = int(done)
        if self.relay is not None:
            if now - self._relayed_at >= RELAY_EVERY_S:
                self._relayed_at = now
                self.relay[0].put(("done", self.relay[1], self.done))
            return
        if self._t0 is None:  # the first update marks the end of start-up
            self._t0, self._done0, self._last_time = now, self.done, now
            self._next_mark = (self.done // self.step + 1) * self.step
            if self.shows == "bar":
                self._bar = self._new_bar()
            return
        if self._bar is not None:
            if self.note is not None:
                self._bar.set_postfix_str(self.note, refresh=False)
            self._bar.update(self.done - self._bar.n)
        if self.done >= self._next_mark or now - self._last_time >= self.interval:
            self._emit(now)

    def close(self) -> None:
        """Print the last line (once), unless the last update already printed it; in bar mode,
        draw the bar at its last count and leave it on screen."""
        if self.relay is not None:
            self.relay[0].put(("done", self.relay[1], self.done))
            return
        if self._t0 is not None and (not self.lines or self._last_done != self.done):
            self._emit(self._clock())
        if self._bar is not None:
            self._bar.update(self.done - self._bar.n)
            self._bar.close()
            self._bar = None

    def message(self, text: str) -> None:
        """Print ``[label] text`` once, as the lines are (above the bar in ``"bar"`` mode;
        nothing in ``"none"`` mode): an event inside the work, e.g. a resumed training."""
        line = f"[{self.label}] {text}"
        if self.relay is not None:
            self.relay[0].put(("message", self.relay[1], line))
            return
        if self.shows == "none":
            return
        if self._bar is not None:
            self._bar.write(line, file=self._stream or sys.stdout)
        else:
            print(line, file=self._stream or sys.stdout, flush=True)

    def _new_bar(self) -> Any:
        from tqdm import tqdm

        return tqdm(
            total=self.total,
            initial=self.done,  # tqdm's rate is (n - initial) / time since now: start-up excluded
            desc=self.label,
            unit=f" {self.unit}",  # "1,988 steps/s", not "1988steps/s"
            file=self._stream or sys.stdout,
            smoothing=0,  # the average rate since the first update, as in the lines
            dynamic_ncols=True,
            leave=True,
        )

    def line(self, now: float) -> str:
        """The progress line at ``now``."""
        rate = self.rate(now)
        left = max(self.total - self.done, 0)
        eta = left / rate if rate > 0 else math.inf
        pct = 100.0 * min(self.done, self.total) / self.total
        rate_text = "?" if not math.isfinite(rate) else f"{rate:.0f}"
        return (
            f"[{self.label}] {self.done:,}/{self.total:,} {self.unit} ({pct:.0f}%) | "
            f"{rate_text} {self.unit}/s | ETA {duration(eta)}"
            + ("" if self.note is None else f" | {self.note}")
        )

    def _emit(self, now: float) -> None:
        text = self.line(now)
        self.lines.append(text)
        self._last_time, self._last_done = now, self.done
        self._next_mark = (self.done // self.step + 1) * self.step
        if self.shows == "lines":
            print(text, file=self._stream or sys.stdout, flush=True)

    _last_done = -1


@contextlib.contextmanager
def relayed_bar(progress: Progress | None, n_parts: int) -> Iterator[list[Progress] | None]:
    """One bar for work split over ``n_parts`` worker processes.

    When ``progress`` draws a bar in this process (``"bar"`` mode, on a terminal), yields one
    `Progress` per part to send to the workers: each reports its count and messages to
    this process over a queue, and ``progress`` shows the count of the slowest part (the parts
    train in lockstep: the work ends with the last of them). The bar is closed on exit. In
    any other case yields ``None``: the caller labels a part per worker, which prints lines.

    Args:
        progress: The whole work's progress (its ``total`` is each part's).
        n_parts: The number of parts.
    """
    if progress is None or n_parts < 2 or progress.shows != "bar":
        yield None
        return
    import multiprocessing

    manager = multiprocessing.get_context("spawn").Manager()
    try:
        queue = manager.Queue()
        counts = [progress.done] * n_parts
        parts = []
        for k in range(n_parts):
            part = Progress(progress.label, progress.total, mode="none", unit=progress.unit)
            part.relay = (queue, k)
            parts.append(part)

        def pump() -> None:
            while True:
                item = queue.get()
                if item is None:
                    return
                kind, k, value = item
                if kind == "done":
                    counts[k] = value
                    progress.update(min(counts))
                else:
                    progress.message(str(value).split("] ", 1)[-1] + f" (part {k + 1}/{n_parts})")

        thread = threading.Thread(target=pump, name="ermrl-progress-relay", daemon=True)
        thread.start()
        try:
            yield parts
        finally:
            queue.put(None)
            thread.join(timeout=10)
            progress.close()
    finally:
        manager.shutdown()
