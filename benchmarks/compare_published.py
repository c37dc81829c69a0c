"""Compare groups of published test runs, from any folders, with confidence intervals.

    python benchmarks/compare_published.py \
        band=benchmarks/results/multiscale/Pendulum-v1/test-trial59:res-ppo \
        reference=benchmarks/results/multiscale/Pendulum-v1/test:res-ppo \
        --candidate band --baselines reference

Each group is ``NAME=TEST_FOLDER:AGENT``: that agent's finished runs (``agents/AGENT/seed_*``)
in a published test folder, under ``NAME``. For the candidate against each baseline and each
metric (``last10``, ``last100``, ``eval``): the difference of means, its percentile bootstrap and
Welch 95% intervals, Welch's p and the paired bootstrap interval over shared seeds
(``ermrl.analysis.compare_agents``). No multiple-comparison correction: this is for exploratory
comparisons outside an experiment file's ``verdict:`` rule, and says so in its output. Writes
CSV with ``--out``. ``--at-step 300000`` adds ``last10@300000``: the same comparison of what the
runs had learned by that env step (``ermrl.analysis.returns_at_step``), such as an evolution's
budget inside a longer test.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ermrl.analysis import METRICS, compare_agents, load_test_runs, returns_at_step  # noqa: E402


def _group(text: str) -> tuple[str, Path, str]:
    name, sep, rest = text.partition("=")
    folder, colon, agent = rest.rpartition(":")
    if not (sep and colon and name and folder and agent):
        raise argparse.ArgumentTypeError(f"{text!r}: NAME=TEST_FOLDER:AGENT is needed")
    return name, Path(folder), agent


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("groups", nargs="+", type=_group, metavar="NAME=TEST_FOLDER:AGENT")
    p.add_argument("--candidate", required=True, help="the NAME tested")
    p.add_argument("--baselines", nargs="+", required=True, help="the NAMEs it is compared with")
    p.add_argument(
        "--at-step",
        nargs="+",
        type=int,
        default=[],
        metavar="STEP",
        help="also compare what the runs had learned by these env steps (the mean of the last 10 "
        "training episodes ended by then, from episodes.csv): metric last10@STEP",
    )
    p.add_argument("--out", default=None, help="CSV file (default: none)")
    args = p.parse_args(argv)
    names = [g[0] for g in args.groups]
    for name in (args.candidate, *args.baselines):
        if name not in names:
            p.error(f"{name!r} is not a group (groups: {', '.join(names)})")
    for step in args.at_step:
        if step <= 0:
            p.error(f"--at-step {step}: a number of env steps above 0 is needed")
    frames = []
    for name, folder, agent in args.groups:
        runs = load_test_runs(folder) if folder.is_dir() else pd.DataFrame()
        runs = runs[runs["agent"] == agent] if not runs.empty else runs
        if runs.empty:
            p.error(f"{name}: no finished run of {agent} in {folder}")
        for step in args.at_step:
            at = returns_at_step(folder, step, agent=agent)
            at = at.rename(columns={"return_at_step": f"last10@{step}"})
            runs = runs.merge(at, on=["agent", "seed"], how="left")
        frames.append(runs.assign(agent=name))
    runs = pd.concat(frames, ignore_index=True)
    metrics = {k: c for k, (c, _) in METRICS.items()} | {
        f"last10@{s}": f"last10@{s}" for s in args.at_step
    }
    rows = []
    for metric, column in metrics.items():
        table = compare_agents(runs, args.candidate, args.baselines, metric=column)
        rows.append(table.assign(metric=metric))
    out = pd.concat(rows, ignore_index=True)
    means = runs.groupby("agent")[list(metrics.values())].agg(["mean", "std", "count"])
    with pd.option_context("display.width", 200, "display.max_columns", 30):
        print(means.round(1).to_string())
        print("\nexploratory: 95% intervals, no multiple-comparison correction")
        cols = ["candidate", "baseline", "metric", "n_candidate", "n_baseline", "mean_diff",
                "welch_ci_low", "welch_ci_high", "boot_ci_low", "boot_ci_high", "p_value",
                "paired_ci_low", "paired_ci_high"]  # fmt: skip
        print(out[cols].to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    if args.out:
        out.to_csv(args.out, index=False)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
