"""How long ``ermrl run FILE --dry-run`` takes to print its plan, for every experiment file.

Each measurement is a fresh process (``python -m ermrl run FILE --dry-run``), as a user types it:
interpreter start, imports, reading the file and the stored state, and the plan. Side by side in
each repeat, the variants alternate with two baselines, so that the plan's own cost can be read
on a noisy machine: the bare interpreter (``python -c pass``) and the package's import
(``python -c "import ermrl.cli"``). Wall seconds, median over the repeats; the target is under
10 seconds per file (issue: "Reproduce the paper").

    python benchmarks/bench_plan.py                       # experiments/paper/*.yaml, 3 repeats
    python benchmarks/bench_plan.py --quick               # one file, one repeat (CI)
    python benchmarks/bench_plan.py --files my.yaml --out results.json
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import alternate, median, table, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 10.0


def wall_seconds(argv: list[str], cwd: Path) -> float:
    """Wall seconds of one fresh process; a failed command is an error, not a timing."""
    start = time.perf_counter()
    proc = subprocess.run(argv, cwd=cwd, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"bench_plan: {' '.join(argv)} failed: {proc.stderr.strip()[-500:]}")
    return seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--files",
        nargs="+",
        type=Path,
        default=None,
        help="experiment files (default: experiments/paper/*.yaml; --quick: the first)",
    )
    parser.add_argument("--repeats", type=int, default=3, help="measurements per variant")
    parser.add_argument("--quick", action="store_true", help="one file, one repeat (CI)")
    parser.add_argument("--out", default=None, help="write the results as JSON here")
    args = parser.parse_args(argv)
    files = args.files or sorted((ROOT / "experiments" / "paper").glob("*.yaml"))
    if args.quick:
        files, args.repeats = files[:1], 1
    python = sys.executable
    variants = {
        "python -c pass": [python, "-c", "pass"],
        "import ermrl.cli": [python, "-c", "import ermrl.cli"],
    }
    for path in files:
        variants[f"dry-run {path.name}"] = [
            python, "-m", "ermrl", "run", str(path.resolve()), "--dry-run"
        ]  # fmt: skip
    # Rates are what the harness alternates; a rate of 1/seconds keeps its median honest.
    measured = alternate(
        {name: (lambda a=cmd: 1.0 / wall_seconds(a, ROOT)) for name, cmd in variants.items()},
        args.repeats,
        warmup=not args.quick,
        label="plan (runs per second)",
    )
    rows = []
    for name, rates in measured.items():
        seconds = 1.0 / median(rates)
        row = {"variant": name, "median_s": seconds, "repeats": len(rates)}
        if name.startswith("dry-run"):
            row["target"] = f"< {TARGET_S:g} s: {'met' if seconds < TARGET_S else 'NOT met'}"
        rows.append(row)
    print(table(rows, ["variant", "median_s", "repeats", "target"]))
    if args.out:
        write_json(args.out, {"rows": rows, "target_s": TARGET_S})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
