"""Benchmark 4: pruning.

For a fixed study budget (trials) on a small task, compare the total env steps spent and the best
fitness reached with and without pruning (``--pruner median|halving|none``). Each configuration
runs with several sampler seeds; the CMA-ES proposals of a seed are the same until pruning
changes what the sampler is told.

    python benchmarks/bench_pruning.py            # CartPole-v1 (velocities hidden), 12 trials x 8192 steps
    python benchmarks/bench_pruning.py --quick    # tiny version (CI)
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import table, write_json  # noqa: E402

TARGET_SAVING = 0.40


def run_study(
    pruner: str, sampler_seed: int, n_trials: int, steps: int, n_seeds: int, env_id: str
) -> dict:
    from optuna.trial import TrialState

    from ermrl.agents import resolve_ppo_config
    from ermrl.config import (
        BudgetConfig,
        EncoderConfig,
        EvolveConfig,
        Problem,
        ReservoirSpace,
        SearchConfig,
        TaskConfig,
    )
    from ermrl.search import create_or_resume_study, run_evolution

    space = ReservoirSpace(units=50)
    problem = Problem(
        task=TaskConfig(env_id, "positions"),
        encoder=EncoderConfig(reservoirs=space.default_reservoirs()),
        ppo=resolve_ppo_config(env_id),
        budget=BudgetConfig(training_steps=steps, n_reports=4 if pruner != "none" else 0),
        seeds=tuple(range(n_seeds)),
    )
    config = EvolveConfig(
        problem=problem,
        space=space,
        search=SearchConfig(n_trials=n_trials, sampler_seed=sampler_seed, pruner=pruner),  # type: ignore[arg-type]
    )
    with tempfile.TemporaryDirectory() as tmp:
        study = create_or_resume_study(config, f"sqlite:///{tmp}/p.db", "p")
        run_evolution(config, study, quiet=True)
        trials = study.get_trials(states=[TrialState.COMPLETE, TrialState.PRUNED])
        env_steps = sum(int(t.user_attrs.get("env_steps", 0)) for t in trials)
        return {
            "pruner": pruner,
            "sampler_seed": sampler_seed,
            "complete": sum(t.state == TrialState.COMPLETE for t in trials),
            "pruned": sum(t.state == TrialState.PRUNED for t in trials),
            "env_steps": env_steps,
            "best_fitness": study.best_value,
        }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="tiny budgets (CI)")
    parser.add_argument("--env-id", default="CartPole-v1")
    parser.add_argument("--n-trials", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None, help="training steps per seed")
    parser.add_argument("--n-seeds", type=int, default=None, help="training seeds per trial")
    parser.add_argument("--sampler-seeds", type=int, nargs="+", default=None)
    parser.add_argument("--pruners", nargs="+", default=["none", "median", "halving"])
    parser.add_argument("--out", default="benchmarks/results/pruning.json")
    args = parser.parse_args(argv)
    n_trials = args.n_trials or (6 if args.quick else 12)
    steps = args.steps or (1024 if args.quick else 8192)
    n_seeds = args.n_seeds or 1
    sampler_seeds = args.sampler_seeds or ([0] if args.quick else [0, 1])

    rows = []
    for seed in sampler_seeds:  # alternate the pruners within each sampler seed
        for pruner in args.pruners:
            rows.append(run_study(pruner, seed, n_trials, steps, n_seeds, args.env_id))
            print(f"  {rows[-1]}", flush=True)
    summary = []
    baseline = [r for r in rows if r["pruner"] == "none"]
    base_steps = statistics.mean(r["env_steps"] for r in baseline)
    base_best = [r["best_fitness"] for r in baseline]
    for pruner in args.pruners:
        group = [r for r in rows if r["pruner"] == pruner]
        mean_steps = statistics.mean(r["env_steps"] for r in group)
        best = [r["best_fitness"] for r in group]
        summary.append(
            {
                "pruner": pruner,
                "studies": len(group),
                "pruned_trials": sum(r["pruned"] for r in group),
                "env_steps_mean": mean_steps,
                "steps_saved_%": 100 * (1 - mean_steps / base_steps),
                "best_fitness_mean": statistics.mean(best),
                "best_fitness_min": min(best),
                "best_fitness_max": max(best),
                "best_minus_none": statistics.mean(best) - statistics.mean(base_best),
            }
        )
    print(
        f"{args.env_id} (velocities hidden), {n_trials} trials x {n_seeds} seeds x {steps} steps, sampler seeds {sampler_seeds}:"
    )
    print(table(summary, list(summary[0])))
    noise = max(base_best) - min(base_best) if len(base_best) > 1 else float("nan")
    for s in summary[1:]:
        print(
            f"target {s['pruner']}: {s['steps_saved_%']:.0f}% fewer env steps (>= {100 * TARGET_SAVING:.0f}%: "
            f"{'met' if s['steps_saved_%'] >= 100 * TARGET_SAVING else 'NOT met'}); best fitness "
            f"{s['best_minus_none']:+.3g} against no pruning (spread of no-pruning best across sampler seeds: {noise:.3g})"
        )
    path = write_json(args.out, {"benchmark": "pruning", "env_id": args.env_id, "n_trials": n_trials,
                                 "steps": steps, "n_seeds": n_seeds, "rows": rows, "summary": summary})  # fmt: skip
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
