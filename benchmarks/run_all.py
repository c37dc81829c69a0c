"""Run every ermrl benchmark: one command, JSON results in benchmarks/results/, printed tables.

    python benchmarks/run_all.py           # the real budgets (tens of minutes on 2 cores)
    python benchmarks/run_all.py --quick   # small budgets, a few minutes (CI runs this)

Targets are printed next to the measurements; a benchmark never fails on a timing threshold,
because timing on a shared machine is noisy.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import (  # noqa: E402
    bench_encoder,
    bench_plan,
    bench_pruning,
    bench_science,
    bench_trial,
    bench_workers,
)

BENCHMARKS = {
    "encoder": (bench_encoder.main, [], []),
    "plan": (bench_plan.main, [], []),
    "trial": (bench_trial.main, [], []),
    "pruning": (bench_pruning.main, [], []),
    "science": (bench_science.main, [], []),
    "workers": (
        bench_workers.main,
        ["--n-trials", "12"],
        ["--backends", "sqlite", "journal", "--workers", "1", "2", "--n-trials", "2"],
    ),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="small budgets (CI)")
    parser.add_argument("--only", nargs="+", choices=list(BENCHMARKS), default=list(BENCHMARKS))
    parser.add_argument("--results", default="benchmarks/results", help="folder of the JSON files")
    args = parser.parse_args(argv)
    for name in args.only:
        func, full_args, quick_args = BENCHMARKS[name]
        quick_flag = ["--quick"] if args.quick and name != "workers" else []
        extra = quick_flag + (quick_args if args.quick else full_args)
        print(f"\n=== {name} ===", flush=True)
        start = time.perf_counter()
        code = func([*extra, "--out", str(Path(args.results) / f"{name}.json")])
        print(f"=== {name}: {time.perf_counter() - start:.0f}s ===", flush=True)
        if code:
            return int(code)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
