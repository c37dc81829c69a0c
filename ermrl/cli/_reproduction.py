"""``ermrl reproduction``: the reproduction page of experiment files, from their published files."""

from __future__ import annotations

import argparse
import math
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ermrl.cli._common import fail
from ermrl.runner._options import ArgumentParser, HelpFormatter

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["build_reproduction_parser", "reproduction_main"]

DESCRIPTION = textwrap.dedent(
    """\
    Write the reproduction page (Markdown and HTML) of experiment files: for each hypothesis
    and task, the claim, mean and std over the test seeds, bootstrap CIs of res-ppo - ppo and
    res-ppo - random-res-ppo (independent and paired by seed), learning curves, the selected
    reservoir, env steps and wall time, and verdicts under each file's `verdict:` rule
    (supported, contradicted or inconclusive after Holm's correction, under three metrics). A
    task whose tested trial cannot be traced to a recorded selection in its study snapshot is
    not rendered: the page and stderr say what is missing. A task whose test phase is published
    in part (fewer runs than its file's agents x seeds) is shown but not judged until every
    planned run is in. It reads only the plain files that `ermrl run` published (the
    experiment's `publish:` folder), so anyone can recompute it from a clone.

    With --summary-in, it writes the results table (per sub-question and task, the outcome
    under the primary metric, the other metrics where they differ) into README files between
    their <!-- reproduction:start --> and <!-- reproduction:end --> lines.

    With --compare, it also prints which verdicts moved since an earlier page's CSV (for
    instance one taken from git history), with the seeds per agent that would give 80% power
    to each one still inconclusive (n80), and --changes writes the full comparison as CSV.

    examples:
      ermrl reproduction experiments/paper/*.yaml experiments/multiscale.yaml --out docs/reproduction.md \\
          --summary-in README.md docs/getting-started.md
      git show HEAD~5:docs/reproduction.csv > /tmp/before.csv
      ermrl reproduction experiments/paper/*.yaml --compare /tmp/before.csv
    """
)


def build_reproduction_parser(prog: str = "ermrl reproduction") -> ArgumentParser:
    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    parser.add_argument("files", nargs="+", metavar="EXPERIMENT.yaml", help="experiment files")
    parser.add_argument(
        "--out", default="docs/reproduction.md", help="the Markdown page (HTML beside it)"
    )
    parser.add_argument(
        "--html",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also write the HTML form beside the Markdown page",
    )
    parser.add_argument(
        "--summary-in",
        nargs="+",
        default=[],
        metavar="FILE",
        help="also write the page's results table into each FILE (README.md, "
        "docs/getting-started.md), between its <!-- reproduction:start --> and "
        "<!-- reproduction:end --> lines",
    )
    parser.add_argument(
        "--compare",
        metavar="BEFORE.csv",
        help="an earlier page's CSV (reproduction.csv): print each verdict that moved, and "
        "the comparisons only one page has",
    )
    parser.add_argument(
        "--changes",
        metavar="CHANGES.csv",
        help="with --compare, write every comparison of both pages side by side to this CSV",
    )
    return parser


def _print_changes(changes: pd.DataFrame, before: str) -> None:
    import pandas as pd

    counts = changes["change"].value_counts()
    summary = ", ".join(f"{counts.get(k, 0)} {k}" for k in ("moved", "new", "gone", "same"))
    print(f"verdicts against {before}: {len(changes)} comparisons; {summary}", flush=True)
    shown = changes[changes["change"] != "same"]
    if shown.empty:
        return
    records = shown.to_dict("records")
    table = pd.DataFrame(
        {
            "change": shown["change"],
            "hypothesis": shown["hypothesis"],
            "task": shown["task"],
            "comparison": shown["comparison"],
            "metric": shown["metric"],
            "before": shown["outcome_before"].fillna("-"),
            "after": shown["outcome_after"].fillna("-"),
            "seeds": [_seeds(r) for r in records],
            "diff": [_diffs(r) for r in records],
            "p_adj": [_p_pair(r) for r in records],
            # Seeds per agent for 80% power at the observed effect, where still inconclusive.
            "n80": [
                _fmt(r["seeds_needed"], ".0f") if r["outcome_after"] == "inconclusive" else ""
                for r in records
            ],
        }
    )
    print(table.to_string(index=False), flush=True)


def _fmt(value: Any, spec: str) -> str:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return "-"
    return "-" if math.isnan(number) else format(number, spec)


def _seeds(row: dict[str, Any]) -> str:
    sides = [
        f"{_fmt(row[f'n_candidate_{s}'], '.0f')}/{_fmt(row[f'n_baseline_{s}'], '.0f')}"
        for s in ("before", "after")
    ]
    return " -> ".join(sides)


def _diffs(row: dict[str, Any]) -> str:
    return " -> ".join(_fmt(row[f"mean_diff_{s}"], "+.4g") for s in ("before", "after"))


def _p_pair(row: dict[str, Any]) -> str:
    return " -> ".join(_fmt(row[f"p_adjusted_{s}"], ".2g") for s in ("before", "after"))


def reproduction_main(argv: Sequence[str] | None = None, prog: str = "ermrl reproduction") -> int:
    """Entry point of ``ermrl reproduction``."""
    from ermrl.analysis import (
        VerdictError,
        untraceable_tasks,
        verdict_changes,
        write_reproduction_page,
    )
    from ermrl.cli._common import quiet_libraries
    from ermrl.runner._experiment import ExperimentError, hypothesis_of, load_experiment

    parser = build_reproduction_parser(prog)
    args = parser.parse_args(argv)
    if args.changes and not args.compare:
        fail(prog, "--changes needs --compare BEFORE.csv")
    quiet_libraries()
    import pandas as pd

    from ermrl._io import write_atomic

    before = None
    if args.compare:
        try:
            before = pd.read_csv(args.compare)
        except (OSError, ValueError) as err:
            fail(prog, f"cannot read {args.compare}: {getattr(err, 'strerror', None) or err}")
    try:
        hypotheses = [hypothesis_of(load_experiment(f), f) for f in args.files]
    except ExperimentError as err:
        fail(prog, str(err))
    try:
        md, html = write_reproduction_page(hypotheses, Path(args.out), html_page=args.html)
    except OSError as err:
        fail(prog, f"cannot write {args.out}: {err.strerror or err}")
    except VerdictError as err:
        fail(prog, str(err))
    print(f"wrote {md}" + (f" and {html}" if html else ""), flush=True)
    if args.summary_in:
        from ermrl.analysis import results_summary, write_summary

        summary = results_summary(pd.read_csv(md.with_suffix(".csv")), hypotheses)
        for target in args.summary_in:
            try:
                changed = write_summary(target, summary)
            except OSError as err:
                fail(prog, f"cannot write {target}: {err.strerror or err}")
            except VerdictError as err:
                fail(prog, str(err))
            print(
                f"{'wrote' if changed else 'unchanged'}: the results table in {target}", flush=True
            )
    for line in untraceable_tasks(hypotheses):
        print(f"{prog}: not rendered, the tested trial is untraceable: {line}", file=sys.stderr)
    if before is not None:
        try:
            changes = verdict_changes(before, pd.read_csv(md.with_suffix(".csv")))
        except VerdictError as err:
            fail(prog, f"{args.compare}: {err}")
        _print_changes(changes, args.compare)
        if args.changes:
            try:
                write_atomic(Path(args.changes), changes.to_csv(index=False))
            except OSError as err:
                fail(prog, f"cannot write {args.changes}: {err.strerror or err}")
            print(f"wrote {args.changes}", flush=True)
    return 0
