"""The documentation: the generated CLI reference is current, the README links into the site,
and the site builds with ``mkdocs build --strict``."""

from __future__ import annotations

import argparse
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

from ermrl.cli import COMMANDS
from ermrl.cli._docs import _render_parser, cli_parsers, main, render_cli_reference

ROOT = Path(__file__).resolve().parents[1]
CLI_PAGE = ROOT / "docs" / "cli.md"


def test_the_cli_reference_is_current() -> None:
    assert CLI_PAGE.read_text(encoding="utf-8") == render_cli_reference(), (
        "docs/cli.md is stale: run make cli-docs (python -m ermrl.cli._docs docs/cli.md)"
    )


def test_every_command_and_subcommand_is_in_the_reference() -> None:
    page = render_cli_reference()
    parsers = dict(cli_parsers())
    assert list(parsers) == list(COMMANDS)
    for name in COMMANDS:
        assert f"## `ermrl {name}`" in page
    for action in ("create", "show", "export", "import", "fail-stale", "repair"):
        assert f"### `ermrl study {action}`" in page
    for action in ("train", "eval"):
        assert f"### `ermrl expert {action}`" in page


def test_each_option_appears_with_its_help_and_default() -> None:
    page = render_cli_reference()
    evolve = page.split("## `ermrl evolve`", 1)[1].split("\n## ", 1)[0]
    assert "- `--env-id ENV_ID` (required): gymnasium env id" in evolve
    assert "- `--observe {all,positions,velocities}` (default: `all`)" in evolve
    assert "`--reference-trial, --no-reference-trial` (default: `--reference-trial`)" in evolve
    assert "`-h, --help`" not in evolve


def test_a_toy_parser_renders_usage_groups_and_markup_safely() -> None:
    parser = argparse.ArgumentParser(prog="ermrl toy", description="Toy command.")
    parser.add_argument("--name", required=True, help="a <name> with *stars*")
    group = parser.add_argument_group("tuning")
    group.add_argument("--rate", type=float, default=0.5, help="rate in [0, 1]")
    group.add_argument("--seeds", type=int, nargs="+", default=[1, 2], help="seeds")
    group.add_argument("--flag", action=argparse.BooleanOptionalAction, default=True, help="f")
    group.add_argument("--hidden", help=argparse.SUPPRESS)
    sub = parser.add_subparsers(dest="action")
    sub.add_parser("go", help="go", description="Go somewhere.").add_argument("target")
    text = "\n".join(_render_parser("ermrl toy", parser, 2))
    assert "```text\nermrl toy --name NAME {go} ... [options]\n```" in text
    assert "- `--name NAME` (required): a &lt;name&gt; with \\*stars\\*" in text
    assert "**tuning**" in text
    assert "- `--rate RATE` (default: `0.5`): rate in \\[0, 1\\]" in text
    assert "- `--seeds SEEDS [SEEDS ...]` (default: `1 2`): seeds" in text
    assert "- `--flag, --no-flag` (default: `--flag`): f" in text
    assert "--hidden" not in text
    assert "### `ermrl toy go`" in text and "ermrl toy go target" in text


def test_the_script_checks_and_writes_the_page(tmp_path: Path) -> None:
    out = tmp_path / "cli.md"
    assert main(["--check", str(out)]) == 1
    assert main([str(out)]) == 0
    assert main(["--check", str(out)]) == 0
    out.write_text(out.read_text(encoding="utf-8") + "edited\n", encoding="utf-8")
    assert main(["--check", str(out)]) == 1


def test_the_readme_links_into_the_docs_and_uses_ermrl_commands() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 300, "the README is a front page; details go to docs/"
    for target in re.findall(r"\]\((docs/[^)#\s]+)", readme):
        assert (ROOT / target).is_file(), f"README links to missing {target}"
    for page in ("getting-started", "concepts", "cli", "storage", "learners", "analysis"):
        assert f"docs/{page}.md" in readme
    # commands are `ermrl ...`; the root scripts are named once, as equivalents
    # the quick start's test command is what CI runs first
    assert "make test   # sets up .venv and runs the test suite" in readme
    assert "run make test || exit $?" in (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    scripts = r"^python (evolve_res|test|evolve_generalization|test_generalization)\.py"
    assert not re.search(scripts, readme, flags=re.M)


def test_every_docs_page_is_in_the_nav() -> None:
    config = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    for page in (ROOT / "docs").glob("*.md"):
        assert f": {page.name}" in config, f"{page.name} is not in mkdocs.yml's nav"


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("mkdocs") is None, reason="the dev extra's mkdocs")
def test_the_site_builds_strictly(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-4000:]
    assert (tmp_path / "site" / "cli" / "index.html").is_file()
    assert (tmp_path / "site" / "api" / "index.html").is_file()
