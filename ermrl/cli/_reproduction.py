"""``ermrl reproduction``: the reproduction page of experiment files, from their published files."""

from __future__ import annotations

import argparse
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path

from ermrl.cli._common import fail
from ermrl.runner._options import ArgumentParser, HelpFormatter

__all__ = ["build_reproduction_parser", "reproduction_main"]

DESCRIPTION = textwrap.dedent(
    """\
    Write the reproduction page (Markdown and HTML) of experiment files: for each hypothesis
    and task, the claim, mean and std over the test seeds, bootstrap CIs of res-ppo - ppo and
    res-ppo - random-res-ppo (independent and paired by seed), learning curves, the selected
    reservoir, env steps and wall time, and verdicts under each file's `verdict:` rule
    (supported, contradicted or inconclusive after Holm's correction, under three metrics). A
    task whose tested trial cannot be traced to a recorded selection in its study snapshot is
    not rendered: the page and stderr say what is missing. It reads only the plain files that
    `ermrl run` published (the experiment's `publish:` folder), so anyone can recompute it
    from a clone.

    example:
      ermrl reproduction experiments/paper/*.yaml --out docs/reproduction.md
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
    return parser


def reproduction_main(argv: Sequence[str] | None = None, prog: str = "ermrl reproduction") -> int:
    """Entry point of ``ermrl reproduction``."""
    from ermrl.analysis import VerdictError, untraceable_tasks, write_reproduction_page
    from ermrl.cli._common import quiet_libraries
    from ermrl.runner._experiment import ExperimentError, hypothesis_of, load_experiment

    parser = build_reproduction_parser(prog)
    args = parser.parse_args(argv)
    quiet_libraries()
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
    for line in untraceable_tasks(hypotheses):
        print(f"{prog}: not rendered, the tested trial is untraceable: {line}", file=sys.stderr)
    return 0
