"""``ermrl report``: figures, tables and report.md of a study and its test phase."""

from __future__ import annotations

import argparse
import textwrap
from collections.abc import Sequence

from ermrl.cli._common import (
    ArgumentParser,
    HelpFormatter,
    add_storage_args,
    exit_on_failure,
    quiet_libraries,
)
from ermrl.runner import _commands

__all__ = ["build_report_parser", "report_main"]

DESCRIPTION = textwrap.dedent(
    """\
    Write the report of a study: evolution figures (optimization history, parameter importances,
    sr/lr/input_scaling against fitness, contour of the two main parameters, fitness per CMA-ES
    generation), interactive HTML versions, the test phase (learning curves with 95% CI bands,
    final returns per agent, Welch t-test and bootstrap CI of res-ppo against the baselines),
    per-task scores of generalization studies, and the reservoir dynamics of one res-ppo episode
    (states, power spectra, dominant frequency). Everything is gathered in report.md and
    report.html. Reads only the study storage and the test-phase folder; runs headless.

    example:
      ermrl report --study-name S --storage sqlite:///ermrl.db --runs runs/S --out reports/S
    """
)


def build_report_parser(prog: str = "ermrl report") -> ArgumentParser:
    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    add_storage_args(parser, study_required=True)
    parser.add_argument(
        "--runs",
        default=None,
        help="test-phase folder (--out of ermrl test; default: runs/<study name> if it exists)",
    )
    parser.add_argument("--out", default=None, help="report folder (default: reports/<study name>)")
    parser.add_argument(
        "--band",
        choices=("ci95", "std", "sem", "none"),
        default="ci95",
        help="learning-curve band across seeds: Student-t 95%% CI of the mean, std or s.e.m.",
    )
    parser.add_argument(
        "--dynamics",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="record one res-ppo episode for the reservoir-dynamics section",
    )
    parser.add_argument(
        "--interactive",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also write interactive plotly HTML figures of the search",
    )
    parser.add_argument(
        "--html",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also write report.html next to report.md",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


def report_main(argv: Sequence[str] | None = None, prog: str = "ermrl report") -> int:
    """Entry point of ``ermrl report``."""
    parser = build_report_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    request = _commands.ReportRequest(
        args.study_name, args.storage, runs=args.runs, out=args.out, band=args.band,
        dynamics=args.dynamics, interactive=args.interactive, html=args.html, quiet=args.quiet,
    )  # fmt: skip
    return exit_on_failure(prog, lambda: _commands.run_report(request, prog))
