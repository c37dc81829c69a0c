"""The pinned OpenBLAS kernel against the CPU's own: speed of the population backend, and whether
the two give the same returns.

``import ermrl`` sets ``OPENBLAS_CORETYPE=Haswell`` on x86-64 CPUs with AVX2 and FMA, so that a
seed's result does not depend on the machine (``ermrl/_blas.py``). On a CPU whose own choice is
another kernel (``SkylakeX`` on AVX-512 CPUs), that could cost speed. This benchmark trains the
same CMA-ES generation as ``bench_backends.py`` (its ``--_one population`` child: candidates x
seeds in lockstep, wall clock from pool creation to shutdown) under each kernel, in fresh
processes, the variants alternating within each repeat; it reports the median env steps per
second of each, their ratio, and whether the runs' final returns are identical.

The CPU's own kernel is read off a process that imports numpy before ermrl (threadpoolctl's
``architecture``); on a CPU whose own kernel is the pinned one, both variants are the same and
the ratio only measures noise.

    python benchmarks/bench_blas.py                # HalfCheetah and Hopper, 8 x 3 runs x 16384 steps, 3 repeats
    python benchmarks/bench_blas.py --quick        # smoke test: 2 x 1 runs x 2048 steps, 1 repeat
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import median, table, write_json  # noqa: E402

BACKENDS_SCRIPT = Path(__file__).resolve().parent / "bench_backends.py"
DEFAULT_TASKS = ("HalfCheetah-v5:all", "Hopper-v5:all")


def native_kernel() -> str:
    """The OpenBLAS kernel numpy picks on this CPU when nothing pins it."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
    code = "import numpy, ermrl; from ermrl._blas import blas_kernel; print(blas_kernel())"
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True
    )
    return done.stdout.strip().split()[-1]


def run_child(args: argparse.Namespace, task: str, kernel: str) -> dict[str, Any]:
    """One generation on the population backend in a fresh process, under ``kernel``."""
    cmd = [sys.executable, str(BACKENDS_SCRIPT), "--_one", "population", "--tasks", task,
           "--candidates", str(args.candidates), "--seeds", str(args.seeds),
           "--training-steps", str(args.training_steps), "--n-procs", str(args.n_procs),
           "--sampler-seed", str(args.sampler_seed)]  # fmt: skip
    env = {**os.environ, "OPENBLAS_CORETYPE": kernel}
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, check=True, env=env)
    row = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"{task} {kernel}: {row['wall_s']:.1f} s, {row['steps_per_s']:.0f} steps/s, "
          f"mean last return {row['mean_last_return']:.6g}", file=sys.stderr, flush=True)  # fmt: skip
    return row


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", nargs="+", default=list(DEFAULT_TASKS), metavar="ENV:OBSERVE")
    parser.add_argument("--candidates", type=int, default=8)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--training-steps", type=int, default=16384)
    parser.add_argument("--n-procs", type=int, default=2)
    parser.add_argument("--sampler-seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="2 x 1 runs x 2048 steps, 1 repeat")
    parser.add_argument("--out", default=None, help="default benchmarks/results/blas")
    args = parser.parse_args(argv)
    if args.quick:
        args.candidates, args.seeds, args.training_steps, args.repeats = 2, 1, 2048, 1
    args.out = Path(args.out or ("runs/benchmarks/blas-quick" if args.quick else
                                 "benchmarks/results/blas"))  # fmt: skip
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    native = native_kernel()
    from ermrl._blas import PINNED_KERNEL

    kernels = [native, PINNED_KERNEL] if native.lower() != PINNED_KERNEL.lower() else [native]
    print(f"CPU's own kernel: {native}; pinned: {PINNED_KERNEL}", file=sys.stderr, flush=True)
    rows = []
    for task in args.tasks:
        measured: dict[str, list[dict[str, Any]]] = {k: [] for k in kernels}
        for r in range(args.repeats):
            order = kernels[r % len(kernels) :] + kernels[: r % len(kernels)]
            for kernel in order:
                measured[kernel].append(run_child(args, task, kernel))
        rates = {k: median([m["steps_per_s"] for m in v]) for k, v in measured.items()}
        returns = {k: v[0]["mean_last_return"] for k, v in measured.items()}
        rows.append({
            "task": task,
            "runs": measured[kernels[0]][0]["runs"],
            "native_kernel": native,
            "native_steps_per_s": round(rates[native]),
            "pinned_steps_per_s": round(rates[kernels[-1]]),
            "pinned_over_native": round(rates[kernels[-1]] / rates[native], 3),
            "native_mean_return": returns[native],
            "pinned_mean_return": returns[kernels[-1]],
            "same_returns": returns[native] == returns[kernels[-1]],
        })  # fmt: skip
    columns = list(rows[0])
    text = table(rows, columns)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "blas.md").write_text(text + "\n")
    write_json(
        args.out / "blas.json", {"rows": rows, "args": {k: str(v) for k, v in vars(args).items()}}
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
