"""Calibration: do the ``sb3`` and ``population`` backends learn equally well?

For a fixed reservoir (the unevolved reference, reservoirpy's defaults: ``EncoderConfig()``; a
task written ``ENV_ID:observe@rtu`` uses the unevolved RTU layer instead, the paper's
initialization ranges: ``RTUSpace().default_reservoirs()``; ``@nvar`` the unevolved NVAR,
reservoirpy's example: ``NVARSpace().default_reservoirs()``), each task is trained on seeds
0..N-1 under both backends (``SeedRunner(n_procs).map`` for ``sb3``,
``train_population_parallel(..., n_procs)`` for ``population``), with the packaged PPO settings
(``resolve_ppo_config``) and ``BudgetConfig(fitness="eval")``, which gives both measures: ``last``
(mean of the last 10 training episodes) and ``eval`` (mean of 5 deterministic episodes).

Per task and measure, the two backends' final returns are compared: mean ± std, the difference
of means (population − sb3) with a percentile-bootstrap 95% CI
(``ermrl.analysis.bootstrap_mean_diff_ci``), and a two-sided Mann-Whitney U test; "agree within
noise" means p >= 0.05 (no evidence of a difference at these seeds, not proof of equality).

Outputs under ``--out`` (default benchmarks/results/calibration): ``runs.csv`` (task, backend,
seed, last_return, eval_return, wall_seconds, error; one row per run) and ``summary.md`` (the table
printed at the end). Resumable: runs already in ``runs.csv`` (same task, backend and seed) are
skipped, so an interrupted run continues where it stopped; rows are written after each (task,
backend) batch. Use a new ``--out`` when changing ``--training-steps`` or ``--reservoir``.

    python benchmarks/calibrate_backends.py           # 5 tasks x 10 seeds x 100k steps, ~40 min on 2 cores
    python benchmarks/calibrate_backends.py --quick   # smoke test: 2 seeds x 4096 steps
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEFAULT_TASKS = (
    "HalfCheetah-v5:velocities",
    "Pendulum-v1:positions",
    "CartPole-v1:positions",
    "Pendulum-v1:positions@rtu",
    "Pendulum-v1:positions@nvar",
)
BACKENDS = ("sb3", "population")
FIELDS = ("task", "backend", "seed", "last_return", "eval_return", "wall_seconds", "error")
MEASURES = ("last", "eval")


def parse_task(spec: str):  # noqa: ANN201
    """``ENV_ID[:observe][@encoder]`` -> (TaskConfig, encoder family, label); observe: all,
    positions or velocities; encoder: a registered encoder's family (esn, the default, rtu,
    nvar, ...)."""
    from ermrl.config import TaskConfig
    from ermrl.encoders import encoder_families

    families = encoder_families()
    task_spec, _, encoder = spec.partition("@")
    if encoder and encoder not in families:
        raise SystemExit(f"calibrate_backends.py: unknown encoder {encoder!r} in {spec!r}; "
                         f"choose one of {', '.join(families)}")  # fmt: skip
    env_id, _, observe = task_spec.partition(":")
    task = TaskConfig(env_id, observe or "all")
    encoder = encoder or families[0]
    return task, encoder, task.label if encoder == families[0] else f"{task.label} {encoder}"


def reservoir(spec: str | None, encoder: str = "esn"):  # noqa: ANN201
    """``None``: the reference ``EncoderConfig()`` (``rtu``, ``nvar``: that encoder's unevolved
    reference); else
    ``sr,lr,input_scaling`` (a 100-unit ESN)."""
    from ermrl.config import EncoderConfig, ReservoirParams

    if encoder != "esn":
        if spec is not None:
            raise SystemExit(
                f"calibrate_backends.py: --reservoir sets an ESN, not an @{encoder} task"
            )
        from ermrl.encoders import encoder_of_family

        # The registered encoder's unevolved reference (its search space's default reservoirs).
        registered = encoder_of_family(encoder)
        if registered is None:  # parse_task accepts registered families only
            raise SystemExit(f"calibrate_backends.py: no registered encoder of family {encoder!r}")
        space = registered.space_cls()
        return EncoderConfig(reservoirs=space.default_reservoirs())
    if spec is None:
        return EncoderConfig()
    sr, lr, scaling = (float(x) for x in spec.split(","))
    return EncoderConfig(
        reservoirs=(ReservoirParams(units=100, sr=sr, lr=lr, input_scaling=scaling),)
    )


def train(
    backend: str, task: Any, label: str, encoder: Any, seeds: list[int], steps: int, n_procs: int
) -> list[dict]:
    """Train ``seeds`` with one backend; one CSV row per seed (failures get ``error``)."""
    from ermrl.agents import resolve_ppo_config
    from ermrl.config import BudgetConfig

    ppo = resolve_ppo_config(task.env_id)
    budget = BudgetConfig(training_steps=steps, fitness="eval")
    if backend == "sb3":
        from ermrl.search import SeedRunner

        with SeedRunner(n_procs) as runner:
            results: list[Any] = runner.map([(task, encoder, ppo, budget, s) for s in seeds])
    else:
        from ermrl.population import PopulationJob, train_population_parallel

        jobs = [PopulationJob(encoder, s) for s in seeds]
        results = train_population_parallel(task, ppo, budget, jobs, n_procs=n_procs)
    rows = []
    for seed, r in zip(seeds, results):
        row = {"task": label, "backend": backend, "seed": seed}
        if isinstance(r, BaseException):
            rows.append({**row, "last_return": math.nan, "eval_return": math.nan,
                         "wall_seconds": math.nan, "error": f"{type(r).__name__}: {r}"})  # fmt: skip
        else:
            ev = math.nan if r.eval_return is None else r.eval_return
            rows.append({**row, "last_return": r.last_return, "eval_return": ev,
                         "wall_seconds": r.wall_seconds, "error": ""})  # fmt: skip
    return rows


def read_runs(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with path.open() as fh:
        return list(csv.DictReader(fh))


def append_runs(path: Path, rows: list[dict]) -> None:
    new = not path.exists()
    with path.open("a", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=FIELDS)
        if new:
            writer.writeheader()
        writer.writerows(rows)


def compare(runs: list[dict], labels: list[str]) -> str:
    """Markdown table: per task and measure, both backends and their two-sample comparison."""
    import numpy as np
    from scipy.stats import mannwhitneyu

    from ermrl.analysis import bootstrap_mean_diff_ci

    lines = [
        "| task | measure | sb3 (n) | population (n) | population − sb3 [95% CI] | Mann-Whitney p | agree within noise |",
        "|---|---|---|---|---|---|---|",
    ]
    for label in labels:
        for measure in MEASURES:
            values = {}
            for backend in BACKENDS:
                v = [float(r[f"{measure}_return"]) for r in runs
                     if r["task"] == label and r["backend"] == backend]  # fmt: skip
                values[backend] = np.array([x for x in v if math.isfinite(x)])
            a, b = values["population"], values["sb3"]
            cells = [f"{x.mean():.1f} ± {x.std(ddof=1) if len(x) > 1 else 0:.1f} ({len(x)})"
                     if len(x) else "– (0)" for x in (b, a)]  # fmt: skip
            if len(a) and len(b):
                low, high = bootstrap_mean_diff_ci(a, b)
                diff = f"{a.mean() - b.mean():+.1f} [{low:+.1f}, {high:+.1f}]"
                p = float(mannwhitneyu(a, b, alternative="two-sided").pvalue)
                verdict = "yes" if p >= 0.05 else "**no**"
            else:
                diff, p, verdict = "–", math.nan, "–"
            lines.append(
                f"| {label} | {measure} | {cells[0]} | {cells[1]} | {diff} | {p:.3g} | {verdict} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="smoke test: 2 seeds x 4096 steps")
    parser.add_argument("--tasks", nargs="+", default=list(DEFAULT_TASKS),
                        help="ENV_ID[:all|positions|velocities][@esn|@rtu|@nvar] (default: %(default)s)")  # fmt: skip
    parser.add_argument("--seeds", type=int, default=None, help="seeds 0..N-1 per backend (10)")
    parser.add_argument("--training-steps", type=int, default=None,
                        help="training steps per run (100000)")  # fmt: skip
    parser.add_argument("--reservoir", default=None, metavar="SR,LR,INPUT_SCALING",
                        help="a fixed 100-unit reservoir instead of EncoderConfig()")  # fmt: skip
    parser.add_argument("--n-procs", type=int, default=2, help="processes per backend (2)")
    parser.add_argument("--out", default="benchmarks/results/calibration", help="results folder")
    args = parser.parse_args(argv)
    n_seeds = args.seeds or (2 if args.quick else 10)
    steps = args.training_steps or (4096 if args.quick else 100_000)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "runs.csv"
    tasks = [parse_task(t) for t in args.tasks]
    encoders = {name: reservoir(args.reservoir, name) for _, name, _ in tasks}
    for task, name, label in tasks:
        for backend in BACKENDS:
            done = {int(r["seed"]) for r in read_runs(path)
                    if r["task"] == label and r["backend"] == backend}  # fmt: skip
            todo = [s for s in range(n_seeds) if s not in done]
            if not todo:
                continue
            print(f"{label} {backend}: {len(todo)} seeds ...", file=sys.stderr, flush=True)
            start = time.perf_counter()
            rows = train(backend, task, label, encoders[name], todo, steps, args.n_procs)
            append_runs(path, rows)
            print(f"{label} {backend}: {time.perf_counter() - start:.1f} s",
                  file=sys.stderr, flush=True)  # fmt: skip

    runs = [r for r in read_runs(path) if int(r["seed"]) < n_seeds]
    md = compare(runs, [label for _, _, label in tasks])
    used = "\n".join(f"Reservoir ({name}): {enc.reservoirs}" for name, enc in encoders.items())
    header = (f"{used}\nSeeds 0..{n_seeds - 1}, {steps} training steps, "
              f"--n-procs {args.n_procs}\n")  # fmt: skip
    (out / "summary.md").write_text(header + "\n" + md + "\n")
    print(header)
    print(md)
    print(f"\nwrote {path} and {out / 'summary.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
