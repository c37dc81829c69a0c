#!/usr/bin/env python
"""Trials per minute with 1, 2 and 4 workers on each storage backend, side by side in one run.

Every cell starts W real ``ermrl evolve`` workers at the same instant on a fresh study (a fresh
SQLite file, journal file or PostgreSQL database) with tiny trials (Pendulum-v1, velocities
hidden, 256 steps, one seed, a 20-unit reservoir) and a budget of ``--n-trials``. Cells run
interleaved (1 worker on every backend, then 2, then 4) so that the load of the machine affects
the backends alike.

For each cell it reports:

- trials per minute between the first trial's start and the last trial's end (the storage's
  timestamps, so interpreter start-up is excluded), and over the whole wall time;
- lock errors: lines of the workers' output matching ``database is locked``, ``already exists``,
  ``deadlock``, ``could not serialize``, ``LockTimeout``;
- the budget: requested trials against COMPLETE, FAIL and other trials, and whether trial
  numbers are unique.

Usage:
  python benchmarks/bench_workers.py                      # sqlite, journal, postgresql x 1 2 4
  python benchmarks/bench_workers.py --backends sqlite journal --workers 1 2 --n-trials 8
  python benchmarks/bench_workers.py --out bench_workers.json

PostgreSQL cells need a server (``--postgres`` admin URL; a database is created and dropped per
cell); they are skipped with a note when it is unreachable.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
import uuid
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

LOCK_ERROR = re.compile(
    r"database is locked|already exists|deadlock|could not serialize|LockTimeout", re.IGNORECASE
)
TINY = [
    "--env-id", "Pendulum-v1", "--observe", "positions", "--n-seeds", "1", "--units", "20",
    "--n-envs", "1", "--ppo", "n_steps=128", "batch_size=64", "n_epochs=2", "--quiet",
]  # fmt: skip


@dataclass
class Cell:
    """One (backend, workers) measurement."""

    backend: str
    workers: int
    requested: int
    complete: int = 0
    failed: int = 0
    other: int = 0
    unique_numbers: bool = True
    lock_errors: int = 0
    exit_codes: list[int] = field(default_factory=list)
    active_seconds: float = 0.0
    wall_seconds: float = 0.0
    trials_per_minute: float = 0.0
    trials_per_minute_wall: float = 0.0
    note: str = ""


def _postgres_database(admin: str) -> tuple[str, Any] | None:
    try:
        import psycopg2

        conn = psycopg2.connect(admin, connect_timeout=3)
    except Exception as err:
        print(f"postgresql unreachable ({str(err).strip()}): skipping its cells", file=sys.stderr)
        return None
    conn.autocommit = True
    name = f"ermrl_bench_{uuid.uuid4().hex[:10]}"
    with conn.cursor() as cur:
        cur.execute(f"CREATE DATABASE {name}")
    base = admin.rsplit("/", 1)[0]
    return f"{base}/{name}", (conn, name)


def _drop_postgres(handle: Any) -> None:
    conn, name = handle
    with conn.cursor() as cur:
        cur.execute(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")
    conn.close()


def run_cell(backend: str, workers: int, args: argparse.Namespace, folder: Path) -> Cell:
    """Start ``workers`` CLI workers on a fresh study of ``backend`` and measure them."""
    import optuna

    from ermrl.storage import open_storage

    cell = Cell(backend, workers, args.n_trials)
    handle = None
    if backend == "sqlite":
        url = f"sqlite:///{folder}/study.db"
    elif backend == "journal":
        url = f"journal:///{folder}/study.log"
    elif backend == "postgresql":
        made = _postgres_database(args.postgres)
        if made is None:
            cell.note = "postgresql unreachable"
            return cell
        url, handle = made
    else:
        raise ValueError(backend)
    command = [sys.executable, "-m", "ermrl", "evolve", *TINY]
    command += ["--training-steps", str(args.training_steps), "--n-trials", str(args.n_trials)]
    command += ["--storage", url, "--study-name", "bench"]
    logs = [folder / f"worker{i}.log" for i in range(workers)]
    started = time.time()
    procs = []
    for log in logs:
        with open(log, "w") as out:
            procs.append(subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT))
    cell.exit_codes = [p.wait() for p in procs]
    cell.wall_seconds = time.time() - started
    text = "".join(log.read_text() for log in logs)
    cell.lock_errors = len(LOCK_ERROR.findall(text))
    try:
        study = optuna.load_study(study_name="bench", storage=open_storage(url))
        trials = study.get_trials()
        states = Counter(t.state.name for t in trials)
        cell.complete = states.pop("COMPLETE", 0)
        cell.failed = states.pop("FAIL", 0)
        cell.other = sum(states.values())
        numbers = [t.number for t in trials]
        cell.unique_numbers = len(set(numbers)) == len(numbers)
        starts = [t.datetime_start for t in trials if t.datetime_start]
        ends = [t.datetime_complete for t in trials if t.datetime_complete]
        if starts and ends:
            cell.active_seconds = (max(ends) - min(starts)).total_seconds()
    finally:
        if handle is not None:
            _drop_postgres(handle)
    if cell.active_seconds > 0:
        cell.trials_per_minute = 60 * cell.complete / cell.active_seconds
    cell.trials_per_minute_wall = 60 * cell.complete / cell.wall_seconds
    if any(cell.exit_codes):
        cell.note = f"exit codes {cell.exit_codes}; see {folder}"
    return cell


def table(cells: list[Cell], backends: list[str], workers: list[int]) -> str:
    by = {(c.backend, c.workers): c for c in cells}
    head = ["workers", *[f"{b} trials/min (wall)" for b in backends]]
    rows = [head]
    for w in workers:
        row = [str(w)]
        for b in backends:
            c = by.get((b, w))
            if c is None or c.note == "postgresql unreachable":
                row.append("-")
            else:
                row.append(f"{c.trials_per_minute:.1f} ({c.trials_per_minute_wall:.1f})")
        rows.append(row)
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    lines = ["  ".join(x.ljust(wd) for x, wd in zip(r, widths)) for r in rows]
    lines.append("")
    head2 = [
        "backend",
        "workers",
        "requested",
        "complete",
        "fail",
        "other",
        "unique #",
        "lock errors",
    ]
    rows2 = [head2] + [
        [
            c.backend,
            str(c.workers),
            str(c.requested),
            str(c.complete),
            str(c.failed),
            str(c.other),
            "yes" if c.unique_numbers else "NO",
            str(c.lock_errors),
        ]
        for c in cells
        if c.note != "postgresql unreachable"
    ]
    widths2 = [max(len(r[i]) for r in rows2) for i in range(len(head2))]
    lines += ["  ".join(x.ljust(wd) for x, wd in zip(r, widths2)) for r in rows2]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--backends", nargs="+", default=["sqlite", "journal", "postgresql"],
        choices=("sqlite", "journal", "postgresql"),
    )  # fmt: skip
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2, 4])
    parser.add_argument("--n-trials", type=int, default=12, help="budget of each cell's study")
    parser.add_argument("--training-steps", type=int, default=256)
    parser.add_argument(
        "--postgres", default="postgresql://postgres@127.0.0.1:5432/test", help="admin URL"
    )
    parser.add_argument("--out", default="bench_workers.json", help="JSON results")
    args = parser.parse_args(argv)

    cells = []
    with tempfile.TemporaryDirectory(prefix="ermrl-bench-") as tmp:
        for w in args.workers:
            for backend in args.backends:
                folder = Path(tmp) / f"{backend}_{w}"
                folder.mkdir()
                cell = run_cell(backend, w, args, folder)
                cells.append(cell)
                print(
                    f"{backend:<10} {w} worker(s): {cell.complete}/{cell.requested} complete, "
                    f"{cell.failed} fail, {cell.lock_errors} lock errors, "
                    f"{cell.trials_per_minute:.1f} trials/min ({cell.wall_seconds:.0f} s wall)"
                    + (f" [{cell.note}]" if cell.note else ""),
                    flush=True,
                )
        print()
        print(table(cells, args.backends, args.workers))
    doc = {
        "settings": {k: v for k, v in vars(args).items() if k != "out"},
        "machine": {"cpus": __import__("os").cpu_count()},
        "cells": [asdict(c) for c in cells],
    }
    Path(args.out).write_text(json.dumps(doc, indent=2) + "\n")
    print(f"\nwrote {args.out}")
    bad = [c for c in cells if c.note and c.note != "postgresql unreachable"]
    return 1 if bad or any(c.lock_errors or not c.unique_numbers for c in cells) else 0


if __name__ == "__main__":
    raise SystemExit(main())
