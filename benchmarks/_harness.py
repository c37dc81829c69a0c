"""Side-by-side timing: variants alternate within each repeat, medians and ratios are reported.

The machine is noisy, so a benchmark never compares numbers taken in separate runs: each repeat
measures every variant once, in a rotating order, and ratios are computed from the medians.
"""

from __future__ import annotations

import json
import platform
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any


def alternate(
    variants: dict[str, Callable[[], float]],
    repeats: int,
    warmup: bool = True,
    label: str = "",
) -> dict[str, list[float]]:
    """Run each variant ``repeats`` times, rotating the order every repeat.

    Each measurement is reported on stderr as it ends (full runs take many minutes), so
    stdout keeps only the result tables.

    Args:
        variants: name -> function returning a rate (higher is better, e.g. steps per second).
        repeats: Measurements per variant.
        warmup: Run every variant once first, unmeasured.
        label: Prefix of the progress lines (e.g. the grid cell being measured).

    Returns:
        name -> the measured rates.
    """
    names = list(variants)
    prefix = f"{label} " if label else ""
    if warmup:
        for name in names:
            variants[name]()
        print(f"{prefix}warm-up done", file=sys.stderr, flush=True)
    rates: dict[str, list[float]] = {name: [] for name in names}
    for r in range(repeats):
        order = names[r % len(names) :] + names[: r % len(names)]
        for name in order:
            rates[name].append(variants[name]())
            print(
                f"{prefix}repeat {r + 1}/{repeats} {name}: {rates[name][-1]:.4g}",
                file=sys.stderr,
                flush=True,
            )
    return rates


def median(values: Sequence[float]) -> float:
    return float(statistics.median(values))


def timed_rate(work: Callable[[], int], clock: Callable[[], float] = time.perf_counter) -> float:
    """Units of work per second of ``work()`` (which returns how many units it did).

    Args:
        work: The measured function.
        clock: ``time.perf_counter`` (wall clock) or ``time.process_time`` (CPU time of this
            process: for single-threaded work it excludes time stolen by other processes, which
            makes comparisons on a loaded machine far steadier).
    """
    start = clock()
    units = work()
    return units / (clock() - start)


def machine() -> dict[str, Any]:
    import os

    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
    }


def write_json(path: str | Path, data: dict[str, Any]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"machine": machine(), **data}, indent=2))
    return path


def table(rows: list[dict[str, Any]], columns: Sequence[str]) -> str:
    """A plain-text table (the benchmark's printed output)."""

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v)

    cells = [[fmt(r.get(c, "")) for c in columns] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(columns, widths))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in cells]
    return "\n".join(lines)
