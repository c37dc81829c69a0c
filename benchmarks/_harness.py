"""Side-by-side timing: variants alternate within each repeat, medians and ratios are reported.

The machine is noisy, so a benchmark never compares numbers taken in separate runs: each repeat
measures every variant once, in a rotating order, and ratios are computed from the medians.
The science benchmarks' differences of returns share one helper too (:func:`difference`).
"""

from __future__ import annotations

import json
import math
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


def difference(
    a: Sequence[float],
    b: Sequence[float],
    seeds_a: Sequence[int] | None = None,
    seeds_b: Sequence[int] | None = None,
) -> dict[str, Any]:
    """``mean(a) - mean(b)`` of two agents' final returns, with every interval a report shows.

    Computed by :func:`ermrl.analysis.compare_agents` (no statistics of its own).

    Args:
        a: The first agent's final returns, one per seed.
        b: The second agent's.
        seeds_a: The seeds of ``a`` (with ``seeds_b``: the paired CI over the shared seeds).
        seeds_b: The seeds of ``b``.

    Returns:
        ``diff``, ``ci95`` (percentile bootstrap), ``welch_ci95``, ``p_value`` (Welch's t-test),
        ``paired_ci95`` (``None`` without seeds or fewer than 2 shared ones) and ``few_seeds``
        (the flag text, ``""`` with at least ``FEW_SEEDS`` seeds per agent); ``diff`` and the
        intervals are ``None`` when an agent has no run.
    """
    import pandas as pd

    from ermrl.analysis import compare_agents, few_seeds_flag

    none: dict[str, Any] = {
        "diff": None, "ci95": [None, None], "welch_ci95": [None, None], "p_value": None,
        "paired_ci95": None, "few_seeds": "",
    }  # fmt: skip
    if not len(a) or not len(b):
        return none
    paired = seeds_a is not None and seeds_b is not None
    frame = pd.DataFrame(
        {
            "agent": ["a"] * len(a) + ["b"] * len(b),
            "final_return": [*a, *b],
            **({"seed": [*seeds_a, *seeds_b]} if paired else {}),  # type: ignore[misc]
        }
    )
    row = compare_agents(frame, "a", ["b"]).iloc[0]

    def number(value: Any) -> float | None:
        return float(value) if value is not None and math.isfinite(float(value)) else None

    return {
        "diff": number(row["mean_diff"]),
        "ci95": [number(row["boot_ci_low"]), number(row["boot_ci_high"])],
        "welch_ci95": [number(row["welch_ci_low"]), number(row["welch_ci_high"])],
        "p_value": number(row["p_value"]),
        "paired_ci95": (
            [number(row["paired_ci_low"]), number(row["paired_ci_high"])]
            if row["n_paired"] >= 2
            else None
        ),
        "few_seeds": few_seeds_flag(int(row["n_candidate"]), int(row["n_baseline"])),
    }


def format_difference(d: dict[str, Any], digits: int = 1) -> str:
    """One table cell: the difference, its bootstrap CI, Welch's CI and p, and the flag.

    Example: ``-6.9 [-13.9, -0.3]; Welch [-28.1, +13.9], p=0.28; few seeds (n=2 < 5)``.
    Results written before Welch's interval was recorded show the bootstrap CI alone.
    """
    if d.get("diff") is None:
        return "-"

    def ci(pair: list[float | None] | None) -> str:
        if not pair or pair[0] is None or pair[1] is None:
            return "-"
        return f"[{pair[0]:+.{digits}f}, {pair[1]:+.{digits}f}]"

    text = f"{d['diff']:+.{digits}f} {ci(d.get('ci95'))}"
    if d.get("welch_ci95") is not None:
        p = d.get("p_value")
        text += f"; Welch {ci(d['welch_ci95'])}, p={'-' if p is None else f'{p:.2g}'}"
    if d.get("few_seeds"):
        text += f"; {d['few_seeds']}"
    return text
