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


def test_the_readme_and_getting_started_agree_on_where_evolution_wins() -> None:
    """Both carry the results table `ermrl reproduction --summary-in` writes (that it is the
    page's is `tests/test_reproduction.py`'s), with no result typed around it."""
    from ermrl.analysis import read_summary

    readme = read_summary(ROOT / "README.md")
    assert readme is not None and "does evolution beat the unevolved reservoir?" in readme
    assert read_summary(ROOT / "docs" / "getting-started.md") == readme


def test_the_demo_time_is_said_once_the_same_everywhere() -> None:
    """The README, Getting started, the Makefile and the demo's file give one duration, and the
    pages say that results differ across CPUs but repeat on one machine."""
    said = {}
    for name in ("README.md", "docs/getting-started.md", "Makefile", "experiments/demo.yaml"):
        text = " ".join((ROOT / name).read_text(encoding="utf-8").replace("#", " ").split())
        said[name] = re.findall(r"(\d+ to \d+) minutes on 2 cores", text)
        assert len(said[name]) == 1, f"{name}: {said[name]}"
        if name.endswith(".md") or name.endswith(".yaml"):
            assert "differ across CPUs but repeat bit for bit on one machine" in text, name
    assert len({tuple(v) for v in said.values()}) == 1, said


def test_the_demo_plan_estimate_the_pages_quote_is_the_plans() -> None:
    """The pages quote ``ermrl run experiments/demo.yaml --dry-run``'s estimate: it is the plan's
    total (``ermrl/data/throughput.yml``), so a recalibration shows up here."""
    import ermrl
    from ermrl.runner._experiment import format_duration

    total = sum(
        step.seconds for step in ermrl.Experiment.load(ROOT / "experiments/demo.yaml").plan()
    )
    minutes, seconds = re.fullmatch(r"(\d+)m(\d+)s", format_duration(total)).groups()  # type: ignore[union-attr]
    quoted = f"--dry-run` estimates {int(minutes)} min {int(seconds)} s"
    for name in ("README.md", "docs/getting-started.md"):
        text = " ".join((ROOT / name).read_text(encoding="utf-8").split())
        assert quoted in text, f"{name} does not quote the plan's {quoted!r}"


def test_installing_without_make_puts_the_cpu_torch_first() -> None:
    """Without make, the pages install torch from PyTorch's CPU index before ermrl, so that pip
    does not pull a CUDA torch and its nvidia packages."""
    cpu = "pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu"
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    assert "TORCH_SPEC ?= torch==2.13.0" in makefile  # the same version as make installs
    for name in ("README.md", "docs/getting-started.md"):
        text = " ".join((ROOT / name).read_text(encoding="utf-8").split())
        assert cpu in text, name
        assert text.index(cpu) < text.index('pip install -e ".[dev]"', text.index(cpu)), name


def test_every_docs_page_is_in_the_nav() -> None:
    config = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    for page in (ROOT / "docs").rglob("*.md"):
        name = page.relative_to(ROOT / "docs").as_posix()
        assert f": {name}\n" in config, f"{name} is not in mkdocs.yml's nav"


# `--encoder {reservoir,rtu,nvar}` written in a page's prose or tables.
_CHOICE_LIST = re.compile(r"`(--[a-z][a-z0-9-]*) \{([^}]*)\}`")


def _choices_by_option() -> dict[str, list[tuple[str, ...]]]:
    """Every option with choices, in any command or subcommand: ``{option: [choices, ...]}``."""
    found: dict[str, list[tuple[str, ...]]] = {}
    pending = [parser for _, parser in cli_parsers()]
    while pending:
        parser = pending.pop()
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                pending.extend(action.choices.values())
            elif action.choices is not None:
                for option in action.option_strings:
                    found.setdefault(option, []).append(tuple(str(c) for c in action.choices))
    return found


def test_choice_lists_written_in_the_pages_are_the_parsers() -> None:
    """A list of choices written out in a page (`--encoder {reservoir,rtu,nvar}`) is the one the
    parsers read from their registry, so that a new encoder or learner cannot be left out."""
    choices = _choices_by_option()
    pages = [p for p in sorted((ROOT / "docs").glob("*.md")) if p != CLI_PAGE]
    checked = 0
    for page in [*pages, ROOT / "README.md"]:
        for option, written in _CHOICE_LIST.findall(page.read_text(encoding="utf-8")):
            assert option in choices, f"{page.name}: {option} has no choices in any parser"
            listed = {c.strip() for c in written.split(",")}
            assert listed in [set(c) for c in choices[option]], (
                f"{page.name} lists `{option} {{{written}}}`; the parsers have "
                + " or ".join("{" + ",".join(c) + "}" for c in set(choices[option]))
            )
            checked += 1
    assert checked >= 10  # the option table of docs/experiments.md


def test_the_learner_and_encoder_lists_of_the_experiments_page_are_the_registries() -> None:
    from ermrl.encoders import ENCODERS
    from ermrl.learners import LEARNERS

    page = (ROOT / "docs" / "experiments.md").read_text(encoding="utf-8")
    row = re.search(r"^\| `--learner` \|.*\): (`.*`) \|$", page, re.M)
    assert row, "docs/experiments.md has no --learner row"
    assert re.findall(r"`([^`]+)`", row.group(1)) == list(LEARNERS)
    assert f"`--encoder {{{','.join(ENCODERS)}}}`" in page


# A Sphinx role (:class:`X`): mkdocstrings prints it as it is; a docstring links with
# [`X`][ermrl.package.X] instead, or writes `X` where the site does not document X.
_SPHINX_ROLE = re.compile(r":(class|func|meth|attr|mod|data|exc|obj):`")


def _docstrings() -> list[tuple[Path, int, str]]:
    """Every docstring of ``ermrl/`` (modules, classes, functions and the strings under
    attributes), as ``(file, first line, text)``."""
    import ast

    found = []
    for path in sorted((ROOT / "ermrl").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (
                isinstance(node, ast.Expr)
                and isinstance(node.value, ast.Constant)
                and isinstance(node.value.value, str)
            ):
                found.append((path, node.lineno, node.value.value))
    return found


def _docstring_lines(pattern: re.Pattern[str]) -> list[str]:
    """``file:line: text`` of each docstring line of ``ermrl/`` that ``pattern`` matches."""
    hits = []
    for path, first, text in _docstrings():
        for offset, line in enumerate(text.splitlines()):
            if pattern.search(line):
                where = f"{path.relative_to(ROOT)}:{first + offset}"
                hits.append(f"{where}: {line.strip()}")
    return hits


def test_docstrings_link_with_markdown_not_sphinx_roles() -> None:
    hits = _docstring_lines(_SPHINX_ROLE)
    assert not hits, "Sphinx roles in docstrings (mkdocstrings prints them literally):\n" + (
        "\n".join(hits)
    )


def test_docstring_examples_are_examples_sections_without_doctest_directives() -> None:
    """griffe reads ``Examples:`` as a section of code blocks; a singular ``Example:`` (or the
    RST ``Example::``) is not one, and ``# doctest:`` directives would be printed."""
    hits = _docstring_lines(re.compile(r"^\s*Example::?\s*$|#\s*doctest:"))
    assert not hits, "write Examples: without doctest directives:\n" + "\n".join(hits)


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The site, built once with ``mkdocs build --strict``."""
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip("the dev extra's mkdocs")
    out = tmp_path_factory.mktemp("site") / "site"
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-4000:]
    return out


@pytest.mark.slow
def test_the_site_builds_strictly(site: Path) -> None:
    assert (site / "cli.html").is_file()
    assert (site / "api" / "index.html").is_file()
    assert (site / "api" / "runner.html").is_file()


@pytest.mark.slow
def test_the_site_links_work_from_disk_and_load_nothing_from_the_network(site: Path) -> None:
    """Opened from a folder (file://), a link to a directory shows a listing, not its page, and
    nothing can be fetched from a CDN: every page link names an .html file that exists, and
    every script and stylesheet is local. The search index is inlined (the offline plugin)."""
    assert (site / "search" / "search_index.js").read_text(encoding="utf-8").startswith("var ")
    for page in sorted([*site.glob("*.html"), *site.glob("api/*.html")]):
        if page.name == "404.html":  # served by a web server only, with absolute links
            continue
        text = page.read_text(encoding="utf-8")
        for tag, url in re.findall(r"<(script|link)\b[^>]*?(?:src|href)=\"([^\"]+)\"", text):
            if tag == "script" or url.endswith(".css"):
                assert not re.match(r"^(https?:)?//", url), f"{page.name} loads {url}"
        for target in re.findall(r'<a [^>]*href="([^"#?]+)[^"]*"', text):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):
                continue
            assert not target.endswith("/"), f"{page.name} links to the folder {target}"
            assert (page.parent / target).resolve().exists(), f"{page.name}: {target} is missing"


def _api_pages(site: Path) -> list[Path]:
    pages = sorted((site / "api").glob("*.html"))
    assert len(pages) >= 10, pages
    return pages


def _page_text(html_text: str) -> str:
    import html as html_module

    return html_module.unescape(re.sub(r"<[^>]+>", "", html_text))


@pytest.mark.slow
def test_the_api_pages_print_no_sphinx_roles_or_doctest_directives(site: Path) -> None:
    for page in _api_pages(site):
        text = _page_text(page.read_text(encoding="utf-8"))
        roles = sorted(set(re.findall(r":(?:class|func|meth|attr|mod|data|exc|obj):`?\S*", text)))
        assert not roles, f"api/{page.name} prints {len(roles)} Sphinx roles: {roles[:10]}"
        assert "doctest" not in text, f"api/{page.name} prints doctest directives"


@pytest.mark.slow
def test_the_api_pages_show_examples_as_code_blocks(site: Path) -> None:
    """Each Examples section is code (``<pre>``), not prose: no block quote (what Markdown makes
    of ``>>>`` lines outside a code block), no ``>>>`` outside ``<pre>``, and every page with
    examples shows them in a ``<pre>``."""
    with_examples = 0
    for page in _api_pages(site):
        html_text = page.read_text(encoding="utf-8")
        name = f"api/{page.name}"
        assert "<blockquote" not in html_text, f"{name}: a block quote (a doctest read as prose?)"
        assert '<details class="example"' not in html_text, f"{name}: an Example: admonition"
        outside = _page_text(re.sub(r"<pre\b.*?</pre>", "", html_text, flags=re.S))
        assert ">>>" not in outside, f"{name}: >>> outside a code block"
        sections = html_text.split('<span class="doc-section-title">Examples:</span>')[1:]
        for section in sections:
            body = re.split(r'doc-section-title|<div class="doc doc-object', section, maxsplit=1)[0]
            assert "<pre" in body, f"{name}: an Examples section without a code block"
        blocks = [_page_text(b) for b in re.findall(r"<pre\b.*?</pre>", html_text, flags=re.S)]
        if sections:
            with_examples += 1
            assert any(b.lstrip().startswith(">>>") for b in blocks), name
    assert with_examples >= 3
    runner = (site / "api" / "runner.html").read_text(encoding="utf-8")
    blocks = [_page_text(b) for b in re.findall(r"<pre\b.*?</pre>", runner, flags=re.S)]
    assert any(">>> import ermrl\n>>> exp = ermrl.Experiment.load(" in b for b in blocks)


# Run in the page after it loaded: types a query into the search box, then records the results,
# and the overflow of code blocks and tables, as an attribute of <html> (--dump-dom prints it).
_SITE_PROBE = """<script>
window.addEventListener('load', function () { setTimeout(function () {
  var input = document.querySelector('.md-search__input');
  input.focus(); input.value = 'spectral radius';
  input.dispatchEvent(new Event('input', {bubbles: true}));
  setTimeout(function () {
    var right = document.querySelector('.md-content__inner').getBoundingClientRect().right;
    var boxes = [];
    document.querySelectorAll('.md-typeset pre > code, .md-typeset__scrollwrap').forEach(function (b) {
      if (b.scrollWidth > b.clientWidth) {
        var s = getComputedStyle(b);
        boxes.push({overflow: s.overflowX, bar: s.scrollbarWidth, right: b.getBoundingClientRect().right});
      }
    });
    document.documentElement.setAttribute('data-probe', JSON.stringify({
      results: document.querySelectorAll('.md-search-result__item').length,
      right: right, boxes: boxes}));
  }, 3000);
}, 1000); });
</script>"""


@pytest.mark.slow
def test_the_site_opened_from_disk_searches_and_scrolls_wide_blocks(
    site: Path, tmp_path: Path
) -> None:
    """In headless Chromium from file://: the search box finds pages (the offline plugin's index
    and a local Web Worker shim), and a code block or table wider than the page scrolls, with a
    scroll bar, instead of being cut at the page's edge."""
    import html as html_module
    import json

    from tests.test_report_browser import _chromium_run, chromium

    binary = chromium()
    page = site / "experiments.html"
    probed = site / "experiments.probed.html"
    probed.write_text(
        page.read_text(encoding="utf-8").replace("</body>", _SITE_PROBE + "</body>"),
        encoding="utf-8",
    )
    proc = _chromium_run(
        binary, "--window-size=900,1200", "--dump-dom", probed.as_uri(), home=tmp_path / "dom"
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    found = re.search(r'<html[^>]*data-probe="([^"]*)"', proc.stdout)
    assert found, "the probe did not run"
    probe = json.loads(html_module.unescape(found.group(1)))
    assert probe["results"] > 0, "search finds nothing opened from disk"
    assert probe["boxes"], "no code block or table wider than the page at 900 px"
    for box in probe["boxes"]:
        assert box["overflow"] == "auto" and box["bar"] == "auto", box
        assert box["right"] <= probe["right"] + 1, box
