"""``ermrl report``: figures, tables and report.md of a study and its test phase.

The command's options are defined in `ermrl.runner._parsers` (experiment files check their
``report:`` stage with the same parser).
"""

from __future__ import annotations

from collections.abc import Sequence

from ermrl.cli._common import exit_on_failure, quiet_libraries
from ermrl.runner import _commands
from ermrl.runner._parsers import build_report_parser

__all__ = ["build_report_parser", "report_main"]


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
