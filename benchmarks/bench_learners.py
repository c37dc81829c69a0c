"""Learners benchmark: does imitation-sac reach the expert's return in fewer learner steps than sac?

On one task (default Hopper-v5), every learner of ``--learners`` (default ``ppo sac dagger
imitation-sac``) trains with the same env-step budget (``--steps``) on the same seeds, with each
observation of ``--observe`` (default the full observation and ``positions``). The expert (for
the learners that take one: ``dagger``, ``imitation-sac``) is trained once beforehand, on the full
observation (``ermrl expert train``, or ``--train-expert-steps``); its steps are not the
learner's. Each run is :func:`ermrl.agents.train_agent` with its learner's own settings table
(``--set LEARNER KEY=VALUE`` over it) and evaluation checkpoints (``--checkpoints`` evenly spaced,
plus 25% of the budget): ``--n-eval-episodes`` deterministic episodes on a separate env, the same
seeds at every checkpoint.

Per run: the final evaluation return, the mean return of the last 10 training episodes, the
evaluation return at 25% of the budget (sample efficiency), the first checkpoint whose evaluation
reaches the expert's recorded return (and 90% of it; empty: not within the budget), wall
clock, env steps and the learner's own step counters (``phase_steps``, imitation-sac). Per
learner x observation: mean, std and bootstrap 95% CI of the final and 25% returns. Outputs in
``--out``: ``runs.csv``, ``summary.csv``, ``summary.md``, ``curves.png`` (mean evaluation return
against env steps, one panel per observation, the expert's return as a line) and ``meta.json``.

    python benchmarks/bench_learners.py --expert experts/hopper     # 3 seeds x 20k steps
    python benchmarks/bench_learners.py --quick --env-id Pendulum-v1 --train-expert-steps 300
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
import time
from collections.abc import Sequence
from concurrent.futures import as_completed
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import machine  # noqa: E402
from ermrl._io import write_atomic  # noqa: E402

LEARNERS = ("ppo", "sac", "dagger", "imitation-sac")
OBSERVE = ("all", "positions")
RUN_COLUMNS = (
    "env_id", "learner", "observe", "seed", "steps", "final_eval_return", "last10_return",
    "return_at_25pct", "steps_to_expert", "steps_to_90pct_expert", "wall_seconds", "env_steps",
    "steps_per_second", "phase_steps", "checkpoints", "error",
)  # fmt: skip
SUMMARY_COLUMNS = (
    "learner", "observe", "n_runs", "final_mean", "final_std", "final_ci_low", "final_ci_high",
    "at25_mean", "at25_std", "at25_ci_low", "at25_ci_high", "reached_expert",
    "steps_to_expert_median", "reached_90pct", "steps_to_90pct_median", "wall_seconds_mean",
    "steps_per_second_mean",
)  # fmt: skip


def takes_expert(learner: str) -> bool:
    """Whether a registered learner takes an ``expert=DIR`` setting (read from its keys)."""
    from ermrl.learners import get_learner

    spec = get_learner(learner)
    keys = {**spec.own_keys, **dict(getattr(spec, "common_keys", {}))}
    return "expert" in keys


def checkpoint_steps(steps: int, n_checkpoints: int) -> list[int]:
    """``n_checkpoints`` evenly spaced env steps ending at ``steps``, plus 25% of ``steps``."""
    even = {steps * (k + 1) // n_checkpoints for k in range(n_checkpoints)}
    return sorted(s for s in even | {max(1, steps // 4)} if s >= 1)


def first_reaching(checkpoints: Sequence[Sequence[float]], target: float) -> int | None:
    """The step of the first checkpoint whose mean evaluation return is ``>= target``."""
    for step, value in checkpoints:
        if value >= target:
            return int(step)
    return None


def _run_one(job: dict[str, Any]) -> dict[str, Any]:
    """One training run (in a pool process): the row of ``runs.csv`` (checkpoints as a list)."""
    from ermrl.agents import resolve_ppo_config, train_agent
    from ermrl.config import BudgetConfig, TaskConfig

    row: dict[str, Any] = {k: job[k] for k in ("env_id", "learner", "observe", "seed", "steps")}
    try:
        ppo = resolve_ppo_config(job["env_id"], job["settings"], learner=job["learner"])
        budget = BudgetConfig(
            training_steps=job["steps"], fitness="eval", n_eval_episodes=job["n_eval_episodes"]
        )
        result = train_agent(
            TaskConfig(job["env_id"], job["observe"]),
            None,
            ppo,
            budget,
            seed=job["seed"],
            evaluate=True,
            eval_at=job["checkpoints"],
        )
    except Exception as err:  # one failed run is a row, not the end of the benchmark
        return {**row, "error": f"{type(err).__name__}: {err}".splitlines()[0], "checkpoints": []}
    curve = [[int(s), float(r)] for s, r in result.checkpoint_returns]
    at25 = dict((s, r) for s, r in curve).get(job["quarter"])
    expert = job["expert_return"]
    row.update(
        final_eval_return=result.eval_return,
        last10_return=result.last_return if math.isfinite(result.last_return) else None,
        return_at_25pct=at25,
        steps_to_expert=None if expert is None else first_reaching(curve, expert),
        steps_to_90pct_expert=None
        if expert is None
        else first_reaching(curve, expert - 0.1 * abs(expert)),
        wall_seconds=result.wall_seconds,
        env_steps=result.env_steps,
        steps_per_second=result.steps_per_second,
        phase_steps=result.phase_steps,
        checkpoints=curve,
        error="",
    )
    return row


def _mean_ci(values: Sequence[float]) -> dict[str, float | None]:
    import numpy as np

    from ermrl.analysis import bootstrap_mean_diff_ci

    x = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    if not x:
        return {"mean": None, "std": None, "ci_low": None, "ci_high": None}
    # The CI of mean(x) - 0: ermrl's bootstrap with a constant second group.
    low, high = bootstrap_mean_diff_ci(x, [0.0])
    std = float(np.std(x, ddof=1)) if len(x) > 1 else 0.0
    return {"mean": float(np.mean(x)), "std": std, "ci_low": low, "ci_high": high}


def summarize(runs: list[dict[str, Any]], learners: Sequence[str], observes: Sequence[str]) -> list[dict[str, Any]]:  # fmt: skip
    """One row per learner x observation (runs that failed are left out of the statistics)."""
    import numpy as np

    rows = []
    for observe in observes:
        for learner in learners:
            cell = [
                r for r in runs if r["learner"] == learner and r["observe"] == observe
                and not r["error"]
            ]  # fmt: skip
            final = _mean_ci([r["final_eval_return"] for r in cell])
            at25 = _mean_ci([r["return_at_25pct"] for r in cell])
            row: dict[str, Any] = {"learner": learner, "observe": observe, "n_runs": len(cell)}
            row.update({f"final_{k}": v for k, v in final.items()})
            row.update({f"at25_{k}": v for k, v in at25.items()})
            for key, name in (("steps_to_expert", "expert"), ("steps_to_90pct_expert", "90pct")):
                reached = [r[key] for r in cell if r[key] is not None]
                row["reached_expert" if name == "expert" else "reached_90pct"] = (
                    f"{len(reached)}/{len(cell)}"
                )
                row[f"steps_to_{name}_median"] = float(np.median(reached)) if reached else None
            row["wall_seconds_mean"] = (
                float(np.mean([r["wall_seconds"] for r in cell])) if cell else None
            )
            row["steps_per_second_mean"] = (
                float(np.mean([r["steps_per_second"] for r in cell])) if cell else None
            )
            rows.append(row)
    return rows


def _fmt(value: Any, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def format_table(summary: list[dict[str, Any]], meta: dict[str, Any]) -> str:
    """Markdown: per learner x observation, the final and 25% returns and steps to the expert
    (CIs of fewer than ``FEW_SEEDS`` runs flagged)."""
    from ermrl.analysis import few_seeds_flag

    e = meta["expert"]
    lines = [
        f"### {meta['env_id']}: {meta['steps']} learner steps x {len(meta['seeds'])} seeds; "
        f"expert ({e['algo']}, {e['env_steps']} steps, full observation): "
        f"{_fmt(e['eval_return'])}",
        "",
        "| learner | observe | runs | final eval mean ± std [95% CI] | at 25% mean ± std "
        "[95% CI] | reached expert (median step) | reached 90% (median step) | wall / run "
        "| steps/s | flag |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in summary:
        lines.append(
            f"| {r['learner']} | {r['observe']} | {r['n_runs']} | {_fmt(r['final_mean'])} ± "
            f"{_fmt(r['final_std'])} [{_fmt(r['final_ci_low'])}, {_fmt(r['final_ci_high'])}] | "
            f"{_fmt(r['at25_mean'])} ± {_fmt(r['at25_std'])} [{_fmt(r['at25_ci_low'])}, "
            f"{_fmt(r['at25_ci_high'])}] | {r['reached_expert']} "
            f"({_fmt(r['steps_to_expert_median'], 0)}) | {r['reached_90pct']} "
            f"({_fmt(r['steps_to_90pct_median'], 0)}) | {_fmt(r['wall_seconds_mean'])} s | "
            f"{_fmt(r['steps_per_second_mean'], 0)} | "
            f"{few_seeds_flag(int(r['n_runs'])) if r['n_runs'] else ''} |"
        )
    return "\n".join(lines)


def plot_curves(
    runs: list[dict[str, Any]],
    learners: Sequence[str],
    observes: Sequence[str],
    expert_return: float | None,
    path: Path,
) -> None:
    """Mean evaluation return (± std over seeds) against env steps, one panel per observation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(
        1, len(observes), figsize=(5.5 * len(observes), 4), squeeze=False, sharey=True
    )
    for ax, observe in zip(axes[0], observes):
        for learner in learners:
            curves = [
                dict((int(s), float(v)) for s, v in r["checkpoints"])
                for r in runs
                if r["learner"] == learner and r["observe"] == observe and r["checkpoints"]
            ]
            if not curves:
                continue
            steps = sorted(set.intersection(*(set(c) for c in curves)))
            values = np.array([[c[s] for s in steps] for c in curves])
            mean, std = values.mean(axis=0), values.std(axis=0)
            (line,) = ax.plot(steps, mean, marker="o", ms=3, label=f"{learner} ({len(curves)})")
            ax.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.15)
        if expert_return is not None:
            ax.axhline(expert_return, color="black", ls="--", lw=1, label="expert")
        ax.set_title(f"observe {observe}")
        ax.set_xlabel("learner env steps")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("mean evaluation return")
    axes[0][-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _csv_value(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, (dict, list)):
        return json.dumps(value)
    return value


def write_csv(path: Path, rows: list[dict[str, Any]], columns: Sequence[str]) -> None:
    """Write ``rows`` as CSV, atomically (a temporary file renamed over ``path``)."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(columns))
    writer.writeheader()
    for row in rows:
        writer.writerow({c: _csv_value(row.get(c)) for c in columns})
    write_atomic(path, buffer.getvalue())


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--env-id", default="Hopper-v5")
    p.add_argument(
        "--expert", default=None, metavar="DIR", help="an expert folder (ermrl expert train)"
    )
    p.add_argument(
        "--train-expert-steps",
        type=int,
        default=None,
        metavar="N",
        help="train a SAC expert of N steps first, into OUT/expert (its wall clock is reported apart)",
    )
    p.add_argument("--steps", type=int, default=20_000, help="learner env steps per run")
    p.add_argument("--seeds", type=int, nargs="+", default=[200, 201, 202])
    p.add_argument("--learners", nargs="+", default=list(LEARNERS))
    p.add_argument(
        "--observe", nargs="+", default=list(OBSERVE), choices=("all", "positions", "velocities")
    )
    p.add_argument("--n-procs", type=int, default=2)
    p.add_argument(
        "--checkpoints", type=int, default=10, help="evenly spaced evaluations (25%% is added)"
    )
    p.add_argument("--n-eval-episodes", type=int, default=5)
    p.add_argument(
        "--set",
        nargs=2,
        action="append",
        default=[],
        metavar=("LEARNER", "KEY=VALUE"),
        help="a setting for one learner over its table (repeatable)",
    )
    p.add_argument("--out", default="benchmarks/results/learners")
    p.add_argument("--quick", action="store_true", help="tiny budgets: a smoke test")
    return p  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from ermrl.agents import parse_overrides, training_pool
    from ermrl.experts import load_expert, train_expert
    from ermrl.learners import learner_names

    if args.quick:
        args.steps, args.seeds, args.checkpoints, args.n_eval_episodes = 1000, [200, 201], 4, 1
    unknown = [name for name in args.learners if name not in learner_names()]
    unknown += [name for name, _ in args.set if name not in args.learners]
    if unknown:
        parser.error(f"unknown or unused learner(s) {unknown}; registered: {learner_names()}")
    if args.expert is None and args.train_expert_steps is None:
        parser.error("give --expert DIR or --train-expert-steps N")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    expert_train_seconds = None
    expert_dir = Path(args.expert) if args.expert else out / "expert"
    if args.train_expert_steps is not None:
        t0 = time.perf_counter()
        overrides = (
            {"learning_starts": min(100, args.train_expert_steps // 3)} if args.quick else None
        )
        train_expert(
            args.env_id, "sac", args.train_expert_steps, expert_dir, seed=0,
            overrides=overrides, n_eval_episodes=args.n_eval_episodes, overwrite=True,
        )  # fmt: skip
        expert_train_seconds = time.perf_counter() - t0
        print(f"expert trained in {expert_train_seconds:.1f} s -> {expert_dir}", flush=True)
    info = load_expert(expert_dir).info
    if info.env_id.split(":")[-1] != args.env_id:
        parser.error(f"the expert {expert_dir} acts on {info.env_id}, not on {args.env_id}")
    expert_return = info.eval_mean if math.isfinite(info.eval_mean) else None
    checkpoints = checkpoint_steps(args.steps, args.checkpoints)
    extra: dict[str, dict[str, Any]] = {name: {} for name in args.learners}
    for name, pair in args.set:
        extra[name].update(parse_overrides([pair]))
    jobs = []
    for seed in args.seeds:  # seeds outermost: every learner progresses together
        for observe in args.observe:
            for learner in args.learners:
                settings = dict(extra[learner])
                if takes_expert(learner):
                    settings.setdefault("expert", str(expert_dir.resolve()))
                jobs.append(
                    {
                        "env_id": args.env_id, "learner": learner, "observe": observe,
                        "seed": seed, "steps": args.steps, "settings": settings,
                        "n_eval_episodes": args.n_eval_episodes, "checkpoints": checkpoints,
                        "quarter": max(1, args.steps // 4), "expert_return": expert_return,
                    }
                )  # fmt: skip
    runs: list[dict[str, Any]] = []
    with training_pool(max(1, min(args.n_procs, len(jobs)))) as pool:
        futures = [pool.submit(_run_one, job) for job in jobs]
        for future in as_completed(futures):
            row = future.result()
            runs.append(row)
            write_csv(out / "runs.csv", runs, RUN_COLUMNS)  # an interrupted run keeps these
            status = row["error"] or (
                f"final {_fmt(row['final_eval_return'])}, 25% {_fmt(row['return_at_25pct'])}, "
                f"expert at {row['steps_to_expert']}, {row['wall_seconds']:.1f} s "
                f"({row['steps_per_second']:.0f} steps/s)"
            )
            print(
                f"[{len(runs)}/{len(jobs)}] {row['learner']} {row['observe']} seed "
                f"{row['seed']}: {status}",
                flush=True,
            )
    order = {(j["learner"], j["observe"], j["seed"]): i for i, j in enumerate(jobs)}
    runs.sort(key=lambda r: order[(r["learner"], r["observe"], r["seed"])])
    summary = summarize(runs, args.learners, args.observe)
    meta: dict[str, Any] = {
        "env_id": args.env_id,
        "steps": args.steps,
        "seeds": args.seeds,
        "learners": args.learners,
        "observe": args.observe,
        "checkpoints": checkpoints,
        "n_eval_episodes": args.n_eval_episodes,
        "settings": {name: extra[name] for name in args.learners},
        "expert": {
            "path": str(expert_dir),
            "algo": info.algo,
            "eval_return": expert_return,
            "eval_std": info.eval_std,
            "steps": info.steps,
            "env_steps": info.env_steps,
            "wall_seconds": info.wall_seconds,
            "trained_here_seconds": expert_train_seconds,
        },
        "wall_seconds": time.perf_counter() - started,
        "command": " ".join([sys.executable, *sys.argv]),
        "machine": machine(),
    }
    write_csv(out / "runs.csv", runs, RUN_COLUMNS)
    write_csv(out / "summary.csv", summary, SUMMARY_COLUMNS)
    plot_curves(runs, args.learners, args.observe, expert_return, out / "curves.png")
    table = format_table(summary, meta)
    (out / "summary.md").write_text(table + "\n")
    (out / "meta.json").write_text(json.dumps(meta, indent=2))
    print(table)
    print(f"wrote {out}/runs.csv, summary.csv, summary.md, curves.png, meta.json", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
