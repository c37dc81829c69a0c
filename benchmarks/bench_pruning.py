"""Benchmark 4: pruning.

For a fixed study budget (trials) on a small task, compare the total env steps spent and the best
fitness reached with and without pruning (``--pruner median|halving|none``). Each configuration
runs with several sampler seeds; the CMA-ES proposals of a seed are the same until pruning
changes what the sampler is told. With a pruner, CMA-ES counts a pruned trial in its generation
with its last intermediate return (``consider_pruned_trials``).

"Best fitness" is measured twice:

- the study's best value: the best of its COMPLETE trials' noisy fitness values. It is biased
  upwards by the number of COMPLETE trials (the best of 24 noisy draws beats the best of 10 of
  the same quality), so it penalizes pruning for evaluating fewer trials to the end;
- the best trial's parameters re-trained on fresh seeds (``--reeval-seeds``), which measures the
  reservoir that each study found rather than its luckiest evaluation. This is the comparison
  the target is judged on; "within noise" means the difference of the means is at most two
  standard errors of that difference across sampler seeds.

Studies run in ``--jobs`` processes at once (this benchmark counts env steps, not seconds).

    python benchmarks/bench_pruning.py            # CartPole-v1 (velocities hidden), 24 trials x 8192
                                                  # steps, sampler seeds 0-5 (~7 min on 2 cores)
    python benchmarks/bench_pruning.py --quick    # tiny version (CI)
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import statistics
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import table, write_json  # noqa: E402

TARGET_SAVING = 0.40


def run_study(
    pruner: str,
    sampler_seed: int,
    n_trials: int,
    steps: int,
    n_seeds: int,
    env_id: str,
    reeval_seeds: tuple[int, ...],
) -> dict:
    """One study; then its best parameters re-trained on ``reeval_seeds``."""
    import dataclasses

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
    from ermrl.search import create_or_resume_study, evaluate_encoder, run_evolution

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
        best = study.best_trial
    reeval_problem = dataclasses.replace(
        problem,
        seeds=reeval_seeds,
        budget=dataclasses.replace(problem.budget, n_reports=0),
    )
    reeval = evaluate_encoder(
        problem.encoder.with_reservoirs(space.reservoirs_from(best.params)), reeval_problem
    )
    return {
        "pruner": pruner,
        "sampler_seed": sampler_seed,
        "complete": sum(t.state == TrialState.COMPLETE for t in trials),
        "pruned": sum(t.state == TrialState.PRUNED for t in trials),
        "env_steps": env_steps,
        "best_fitness": best.value,
        "best_trial": best.number,
        "best_params": best.params,
        "best_reevaluated": reeval.fitness,
        "reeval_returns": [r.last_return for r in reeval.runs],
    }


def _run_study(args: tuple) -> dict:
    return run_study(*args)


def summarize(rows: list[dict], pruners: list[str]) -> list[dict]:
    """Per pruner: steps saved against ``none``, and both best-fitness measures with noise."""
    baseline = [r for r in rows if r["pruner"] == "none"]
    base_steps = statistics.mean(r["env_steps"] for r in baseline)
    base_re = [r["best_reevaluated"] for r in baseline]
    base_best = [r["best_fitness"] for r in baseline]
    out = []
    for pruner in pruners:
        group = [r for r in rows if r["pruner"] == pruner]
        re = [r["best_reevaluated"] for r in group]
        best = [r["best_fitness"] for r in group]
        n = len(group)
        sd = statistics.stdev(re) if n > 1 else math.nan
        base_sd = statistics.stdev(base_re) if len(base_re) > 1 else math.nan
        noise = 2 * math.sqrt(sd**2 / n + base_sd**2 / len(base_re))
        diff = statistics.mean(re) - statistics.mean(base_re)
        out.append(
            {
                "pruner": pruner,
                "studies": n,
                "complete": sum(r["complete"] for r in group),
                "pruned": sum(r["pruned"] for r in group),
                "env_steps_mean": statistics.mean(r["env_steps"] for r in group),
                "steps_saved_%": 100
                * (1 - statistics.mean(r["env_steps"] for r in group) / base_steps),
                "study_best_mean": statistics.mean(best),
                "study_best_minus_none": statistics.mean(best) - statistics.mean(base_best),
                "reeval_mean": statistics.mean(re),
                "reeval_sd": sd,
                "reeval_minus_none": diff,
                "noise_2se": noise,
            }
        )
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="tiny budgets (CI)")
    parser.add_argument("--env-id", default="CartPole-v1")
    parser.add_argument("--n-trials", type=int, default=None, help="trials per study")
    parser.add_argument("--steps", type=int, default=None, help="training steps per seed")
    parser.add_argument("--n-seeds", type=int, default=None, help="training seeds per trial")
    parser.add_argument("--sampler-seeds", type=int, nargs="+", default=None)
    parser.add_argument(
        "--reeval-seeds",
        type=int,
        nargs="+",
        default=None,
        help="fresh training seeds on which each study's best parameters are re-trained",
    )
    parser.add_argument("--pruners", nargs="+", default=["none", "median", "halving"])
    parser.add_argument("--jobs", type=int, default=None, help="studies run at once (processes)")
    parser.add_argument("--out", default="benchmarks/results/pruning.json")
    args = parser.parse_args(argv)
    if "none" not in args.pruners:
        parser.error("--pruners must include none (the baseline)")
    n_trials = args.n_trials or (6 if args.quick else 24)
    steps = args.steps or (1024 if args.quick else 8192)
    n_seeds = args.n_seeds or 1
    sampler_seeds = args.sampler_seeds or ([0] if args.quick else [0, 1, 2, 3, 4, 5])
    reeval_seeds = tuple(args.reeval_seeds or ([1000] if args.quick else [1000, 1001, 1002, 1003]))
    jobs = args.jobs or (1 if args.quick else 2)

    work = [
        (pruner, seed, n_trials, steps, n_seeds, args.env_id, reeval_seeds)
        for seed in sampler_seeds
        for pruner in args.pruners
    ]
    rows = []
    if jobs == 1:
        for item in work:
            rows.append(run_study(*item))
            print(f"  {rows[-1]}", flush=True)
    else:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=jobs, mp_context=context) as pool:
            for row in pool.map(_run_study, work):
                rows.append(row)
                print(f"  {row}", flush=True)
    summary = summarize(rows, args.pruners)
    print(
        f"{args.env_id} (velocities hidden), {n_trials} trials x {n_seeds} seeds x {steps} steps, "
        f"sampler seeds {sampler_seeds}; best parameters re-trained on seeds {list(reeval_seeds)}:"
    )
    print(table(summary, list(summary[0])))
    for s in summary:
        if s["pruner"] == "none":
            continue
        saved = s["steps_saved_%"]
        diff, noise = s["reeval_minus_none"], s["noise_2se"]
        verdict = (
            "within noise" if abs(diff) <= noise else ("better" if diff > 0 else "NOT within noise")
        )
        print(
            f"target {s['pruner']}: {saved:.0f}% fewer env steps (>= {100 * TARGET_SAVING:.0f}%: "
            f"{'met' if saved >= 100 * TARGET_SAVING else 'NOT met'}); re-trained best "
            f"{s['reeval_minus_none']:+.3g} against no pruning, noise (2 SE) {s['noise_2se']:.3g}: "
            f"{verdict}; study best value "
            f"{s['study_best_minus_none']:+.3g} (biased by the number of COMPLETE trials)"
        )
    path = write_json(
        args.out,
        {"benchmark": "pruning", "env_id": args.env_id, "n_trials": n_trials, "steps": steps,
         "n_seeds": n_seeds, "reeval_seeds": list(reeval_seeds), "rows": rows, "summary": summary},
    )  # fmt: skip
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
