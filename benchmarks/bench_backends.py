"""Backends side by side: one CMA-ES generation trained by ``sb3`` and by ``population``.

For each task, the same candidates x seeds (default 8 x 3 = 24 runs) are trained twice:

- ``sb3``: one SB3 process per run, ``SeedRunner(n_procs).map`` over all the runs;
- ``population``: ``train_population_parallel(..., n_procs=n_procs)``, all the runs in lockstep,
  split over its own ``n_procs`` processes.

The candidates are the first generation asked from a seeded ermrl study sampler (CMA-ES over the
default ``ReservoirSpace``, ``--sampler-seed``, population size ``--candidates``, no reference
trial), decoded onto the unevolved ``EncoderConfig()``: the same reservoirs for both backends. PPO
settings are the packaged ones (``resolve_ppo_config``), fitness ``last``. The default 16384 training
steps are whole rollouts for every task (MuJoCo 8 x 2048, Pendulum 4 x 4096, CartPole 64 x 256), so
neither backend trains past the budget.

Each (task, backend) is measured in a fresh child process (this script with a hidden flag), so
that its peak memory is its own. Wall clock runs from before the pool is created to its shutdown
(process start-up included). Peak memory: ``ru_maxrss`` of the measuring process (RUSAGE_SELF)
and of its largest worker (RUSAGE_CHILDREN gives the largest descendant, not a sum); the tree's
total is estimated as parent + workers x largest worker. The population backend's time breakdown
(env, reservoir, policy, update, total) is summed over its processes (process-seconds).

A third row per task, ``physics``, is the limit the population backend can approach: the same
envs (the population's :class:`~ermrl.population.PopulationEnvs`, one per part of the same
``split_jobs`` layout, in the same ``spawn`` pool) stepped for the same number of env steps with a
fixed action (the middle of a Box's bounds; action 0 of a Discrete space), with no reservoir, no
normalization, no policy and no update. ``population / physics`` is the share of that limit the
whole backend reaches, start-up included on both sides.

Targets (population / sb3 env steps per second): >= 8x HalfCheetah-v5, >= 5x Hopper-v5, >= 7x
Pendulum-v1, >= 4x CartPole-v1; population / physics >= 50% on HalfCheetah-v5.

Outputs under ``--out``: ``backends.csv`` (one row per task and backend), ``backends.md`` (the
table printed at the end) and ``backends.json`` (rows, candidates, machine). The default is
benchmarks/results/backends, where the last full run is published; with ``--quick`` it is
runs/benchmarks/backends-quick, so that a smoke test never replaces the published table.

    python benchmarks/bench_backends.py            # 4 tasks x 24 runs x 16384 steps, ~17 min on 2 cores
    python benchmarks/bench_backends.py --quick    # smoke test: 2 candidates x 1 seed x 2048 steps
"""

from __future__ import annotations

import argparse
import csv
import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import table, write_json  # noqa: E402

DEFAULT_TASKS = (
    "HalfCheetah-v5:all",
    "Hopper-v5:all",
    "Pendulum-v1:positions",
    "CartPole-v1:positions",
)
BACKENDS = ("sb3", "population")
MEASURED = (*BACKENDS, "physics")
TARGETS = {"HalfCheetah-v5": 8.0, "Hopper-v5": 5.0, "Pendulum-v1": 7.0, "CartPole-v1": 4.0}
PHYSICS_TARGETS = {"HalfCheetah-v5": 0.5}
TIMING_KEYS = ("env", "reservoir", "policy", "update", "total")


def parse_task(spec: str):  # noqa: ANN201
    """``ENV_ID[:observe]`` -> TaskConfig (observe: all, positions or velocities)."""
    from ermrl.config import TaskConfig

    env_id, _, observe = spec.partition(":")
    return TaskConfig(env_id, observe or "all")


def candidates(n: int, sampler_seed: int) -> list[tuple[dict[str, float], Any]]:
    """The first CMA-ES generation of a seeded ermrl study: ``n`` (params, EncoderConfig)."""
    import optuna

    from ermrl.config import EncoderConfig, ReservoirSpace, SearchConfig
    from ermrl.encoders import encoder_for
    from ermrl.search._study import make_study_sampler, sample_params

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    space, base = ReservoirSpace(), EncoderConfig()
    search = SearchConfig(sampler="cmaes", sampler_seed=sampler_seed, popsize=n)
    study = optuna.create_study(direction="maximize", sampler=make_study_sampler(search, space))
    out = []
    for _ in range(n):
        params = sample_params(study.ask(), space)
        out.append((params, encoder_for(base).decode(space, params, base)))
    return out


def _peak_rss_mb() -> tuple[float, float]:
    """(this process, largest waited-for descendant) peak RSS in MB (Linux: ru_maxrss is KiB)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return own, children


def _physics_part(task: Any, n_agents: int, n_envs: int, iterations: int) -> int:
    """Step ``n_agents x n_envs`` population envs ``iterations`` times with a fixed action."""
    import numpy as np
    from gymnasium import spaces

    from ermrl.population import PopulationEnvs

    envs = PopulationEnvs(task, n_envs, [1000 * p for p in range(n_agents)])
    space = envs.action_space
    if isinstance(space, spaces.Box):
        action = (space.low + space.high) / 2.0
        actions = np.broadcast_to(action, (n_agents, n_envs, *space.shape)).copy()
    else:
        actions = np.zeros((n_agents, n_envs), np.int64)
    envs.reset()
    for _ in range(iterations):
        envs.step(actions)
    envs.close()
    return n_agents * n_envs * iterations


def measure_physics(
    task: Any, ppo: Any, budget: Any, n_runs: int, n_procs: int
) -> tuple[float, int, int]:
    """(wall s, env steps, processes) of the physics limit: the population's env layout only."""
    from ermrl.agents import training_pool
    from ermrl.population import split_jobs, steps_trained

    iterations = steps_trained(ppo, budget.training_steps) // ppo.n_envs
    parts = split_jobs(n_runs, n_procs)
    start = time.perf_counter()
    if len(parts) == 1:
        steps = _physics_part(task, n_runs, ppo.n_envs, iterations)
    else:
        with training_pool(len(parts)) as pool:
            futures = [pool.submit(_physics_part, task, len(part), ppo.n_envs, iterations)
                       for part in parts]  # fmt: skip
            steps = sum(f.result() for f in futures)
    return time.perf_counter() - start, steps, len(parts)


def measure_one(args: argparse.Namespace) -> dict[str, Any]:
    """Train the generation on one task with one backend, in this (fresh) process."""
    from ermrl.agents import resolve_ppo_config
    from ermrl.config import BudgetConfig

    task = parse_task(args.tasks[0])
    ppo = resolve_ppo_config(task.env_id)
    budget = BudgetConfig(training_steps=args.training_steps)
    runs = [(enc, seed) for _, enc in candidates(args.candidates, args.sampler_seed)
            for seed in range(args.seeds)]  # fmt: skip
    timings: dict[str, float] = dict.fromkeys(TIMING_KEYS, 0.0)
    results: list[Any] = []
    steps = 0
    if args._one == "physics":
        wall, steps, processes = measure_physics(task, ppo, budget, len(runs), args.n_procs)
    elif args._one == "sb3":
        from ermrl.search import SeedRunner

        start = time.perf_counter()
        runner = SeedRunner(args.n_procs)
        try:
            results = runner.map([(task, enc, ppo, budget, s) for enc, s in runs])
        finally:
            runner.close()
        wall = time.perf_counter() - start
        processes = runner.processes_for(len(runs))
    else:
        from ermrl.population import PopulationJob, split_jobs, train_population_parallel

        start = time.perf_counter()
        results = train_population_parallel(
            task, ppo, budget, [PopulationJob(enc, s) for enc, s in runs], n_procs=args.n_procs
        )
        wall = time.perf_counter() - start
        processes = len(split_jobs(len(runs), args.n_procs))
        # All results of one process share its timings dict: count each process once.
        per_process = {tuple(r.timings.get(k, 0.0) for k in TIMING_KEYS)
                       for r in results if not isinstance(r, BaseException)}  # fmt: skip
        for values in per_process:
            for k, v in zip(TIMING_KEYS, values):
                timings[k] += v
    ok = [r for r in results if not isinstance(r, BaseException)]
    steps = steps or sum(r.env_steps for r in ok)
    own, worker = _peak_rss_mb()
    n_workers = processes if processes > 1 else 0
    return {
        "task": task.label,
        "backend": args._one,
        "runs": len(runs),
        "failed": len(results) - len(ok),
        "processes": processes,
        "wall_s": wall,
        "env_steps": steps,
        "steps_per_s": steps / wall,
        "mean_last_return": sum(r.last_return for r in ok) / len(ok) if ok else float("nan"),
        **{f"{k}_s": timings[k] for k in TIMING_KEYS},
        "rss_parent_mb": own,
        "rss_worker_max_mb": worker,
        "rss_tree_est_mb": own + n_workers * worker,
    }


def run_child(args: argparse.Namespace, task: str, backend: str) -> dict[str, Any]:
    """Measure one (task, backend) in a fresh process of this script; its last line is JSON."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--_one", backend, "--tasks", task,
           "--candidates", str(args.candidates), "--seeds", str(args.seeds),
           "--training-steps", str(args.training_steps), "--n-procs", str(args.n_procs),
           "--sampler-seed", str(args.sampler_seed)]  # fmt: skip
    print(f"{task} {backend}: running ...", file=sys.stderr, flush=True)
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, check=True)
    row = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"{task} {backend}: {row['wall_s']:.1f} s, {row['steps_per_s']:.0f} steps/s",
          file=sys.stderr, flush=True)  # fmt: skip
    return row


def summary(rows: list[dict[str, Any]]) -> str:
    """The markdown table: per task and backend, with the ratio and the target."""
    by = {(r["task"], r["backend"]): r for r in rows}
    lines = [
        "| task | backend | wall (s) | env steps | steps/s | population / sb3 | target "
        "| population / physics | target "
        "| env / reservoir / policy / update / total (process-s) | peak RSS parent / worker / tree est. (MB) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def against(
        r: dict[str, Any], other: str, goals: dict[str, float], value: str, goal_fmt: str
    ) -> tuple[str, str]:
        """(population's steps/s over ``other``'s, the verdict on its target) as cells;
        ``value`` and ``goal_fmt`` are ``str.format`` templates."""
        if r["backend"] != "population" or (r["task"], other) not in by:
            return "", ""
        x = r["steps_per_s"] / by[(r["task"], other)]["steps_per_s"]
        goal = goals.get(r["task"].split("[")[0])
        if goal is None:
            return f"**{value.format(x)}**", ""
        return f"**{value.format(x)}**", f">= {goal_fmt.format(goal)} " + (
            "met" if x >= goal else "NOT met"
        )

    for r in rows:
        ratio, target = against(r, "sb3", TARGETS, "{:.2f}x", "{:g}x")
        share, share_target = against(r, "physics", PHYSICS_TARGETS, "{:.0%}", "{:.0%}")
        breakdown = (" / ".join(f"{r[f'{k}_s']:.1f}" for k in TIMING_KEYS)
                     if r["backend"] == "population" else "")  # fmt: skip
        lines.append(
            f"| {r['task']} | {r['backend']} | {r['wall_s']:.1f} | {r['env_steps']} "
            f"| {r['steps_per_s']:.0f} | {ratio} | {target} | {share} | {share_target} | {breakdown} "
            f"| {r['rss_parent_mb']:.0f} / {r['rss_worker_max_mb']:.0f} / {r['rss_tree_est_mb']:.0f} |"
        )
    return "\n".join(lines)


RESULTS = "benchmarks/results/backends"  # the published full run (committed)
QUICK_RESULTS = "runs/benchmarks/backends-quick"  # --quick (runs/ is not committed)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The options, with the defaults that depend on ``--quick`` filled in."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true",
                        help="smoke test: 2 candidates x 1 seed x 2048 steps")  # fmt: skip
    parser.add_argument("--tasks", nargs="+", default=list(DEFAULT_TASKS),
                        help="ENV_ID[:all|positions|velocities] (default: %(default)s)")  # fmt: skip
    parser.add_argument("--candidates", type=int, default=None, help="CMA-ES candidates (8)")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per candidate (3)")
    parser.add_argument("--training-steps", type=int, default=None,
                        help="training steps per run (16384: whole rollouts for every task)")  # fmt: skip
    parser.add_argument("--n-procs", type=int, default=2, help="processes per backend (2)")
    parser.add_argument("--sampler-seed", type=int, default=0, help="CMA-ES seed (0)")
    parser.add_argument("--out", default=None,
                        help=f"results folder (default: {RESULTS}; with --quick, {QUICK_RESULTS})")  # fmt: skip
    parser.add_argument("--_one", choices=MEASURED, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    args.candidates = args.candidates or (2 if args.quick else 8)
    args.seeds = args.seeds or (1 if args.quick else 3)
    args.training_steps = args.training_steps or (2048 if args.quick else 16384)
    args.out = args.out or (QUICK_RESULTS if args.quick else RESULTS)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args._one:
        print(json.dumps(measure_one(args)), flush=True)
        return 0

    rows = []
    for i, task in enumerate(args.tasks):
        order = MEASURED if i % 2 == 0 else MEASURED[::-1]  # alternate who runs first
        measured = {b: run_child(args, task, b) for b in order}
        rows += [measured[b] for b in MEASURED]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with (out / "backends.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    md = summary(rows)
    (out / "backends.md").write_text(md + "\n")
    settings = {k: v for k, v in vars(args).items() if k != "_one"}
    cands = [p for p, _ in candidates(args.candidates, args.sampler_seed)]
    write_json(out / "backends.json", {"settings": settings, "candidates": cands, "rows": rows})
    print(table(rows, ["task", "backend", "wall_s", "env_steps", "steps_per_s",
                       "mean_last_return", "failed"]))  # fmt: skip
    print()
    print(md)
    print(f"\nwrote {out}/backends.csv, backends.md, backends.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
