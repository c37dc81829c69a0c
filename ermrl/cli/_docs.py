"""The CLI reference (``docs/cli.md``), rendered from the argparse parsers themselves.

Every subcommand of `ermrl.cli.COMMANDS` has a ``build_<name>_parser`` function beside its
``*_main`` (``evolve-generalization``: ``build_evolve_generalization_parser``). The reference walks
those parsers and their subparsers (``ermrl study create``, ``ermrl expert train``, ...) and lists,
per command, its usage, its description and each option with its help, choices and default. The
parsers are the only source, so ``--help`` and the page cannot disagree; ``tests/test_docs.py``
fails when the committed page is stale.

Run ``python -m ermrl.cli._docs docs/cli.md`` (``make cli-docs``) to rewrite it, or with
``--check`` to only compare.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["cli_parsers", "render_cli_reference", "main"]

HEADER = """\
# CLI reference

<!-- Generated from the argparse parsers by `make cli-docs` (python -m ermrl.cli._docs
docs/cli.md); do not edit by hand: tests/test_docs.py fails when this page is stale. -->

Every command is `ermrl COMMAND [options]`, also runnable as `python -m ermrl COMMAND`. The four
main ones have root-script equivalents that take the same options: `python evolve_res.py`
(`ermrl evolve`), `python test.py` (`ermrl test`), `python evolve_generalization.py`
(`ermrl evolve-generalization`) and `python test_generalization.py`
(`ermrl test-generalization`). Bad input is one line on stderr and exit code 2. This page is the
output of `--help`, rendered from the same parsers.
"""

# Characters that Markdown would read as markup in help text (backslash escapes work both in
# Python-Markdown and on GitHub); `<` and `>` become entities so that `<agent>` is not HTML.
_ESCAPE = re.compile(r"([\\`*_\[\]{}#|])")


def _escape(text: str) -> str:
    text = _ESCAPE.sub(r"\\\1", text)
    return text.replace("<", "&lt;").replace(">", "&gt;")


def _builder_name(command: str) -> str:
    return "build_" + command.replace("-", "_") + "_parser"


def cli_parsers() -> list[tuple[str, argparse.ArgumentParser]]:
    """The parser of every ``ermrl`` subcommand, in the order of `ermrl.cli.COMMANDS`.

    Returns:
        ``[(command, parser), ...]``, each parser built with ``prog="ermrl COMMAND"``.
    """
    from ermrl.cli import COMMANDS

    parsers = []
    for name, (target, _) in COMMANDS.items():
        module = importlib.import_module(target.partition(":")[0])
        build = getattr(module, _builder_name(name))
        parsers.append((name, build(prog=f"ermrl {name}")))
    return parsers


def _subparsers(parser: argparse.ArgumentParser) -> list[tuple[str, argparse.ArgumentParser]]:
    found: list[tuple[str, argparse.ArgumentParser]] = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            found.extend(action.choices.items())
    return found


def _format_value(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return " ".join(str(v) for v in value)
    return str(value)


def _metavar(action: argparse.Action) -> str:
    if action.metavar is not None:
        metavar = action.metavar
        if isinstance(metavar, tuple):
            return " ".join(metavar)
        return str(metavar)
    if action.choices is not None:
        return "{" + ",".join(str(c) for c in action.choices) + "}"
    return action.dest.upper() if action.option_strings else action.dest


def _argument(action: argparse.Action) -> str:
    """The option as typed: ``--seeds SEEDS [SEEDS ...]``, ``--flag, --no-flag``."""
    if action.nargs == 0:
        return ", ".join(action.option_strings)
    metavar = _metavar(action)
    if action.nargs == "?":
        value = f"[{metavar}]"
    elif action.nargs == "*":
        value = f"[{metavar} ...]"
    elif action.nargs == "+":
        value = f"{metavar} [{metavar} ...]"
    elif isinstance(action.nargs, int) and action.nargs > 1:
        names = metavar.split() if " " in metavar else [metavar] * action.nargs
        value = " ".join(names)
    else:
        value = metavar
    if not action.option_strings:
        return value
    return ", ".join(f"{option} {value}" for option in action.option_strings)


# Python 3.10's BooleanOptionalAction appends this to its help; later versions do not. Left out
# so that the page is the same on every supported Python (the default is listed apart).
_BOOLEAN_DEFAULT = " (default: %(default)s)"


def _raw_help(action: argparse.Action) -> str:
    text = action.help or ""
    if isinstance(action, argparse.BooleanOptionalAction) and text.endswith(_BOOLEAN_DEFAULT):
        text = text[: -len(_BOOLEAN_DEFAULT)]
    return text


def _help(action: argparse.Action, prog: str) -> str:
    """The help text with ``%(default)s``-style fields filled in, as ``--help`` shows it."""
    text = _raw_help(action)
    if not text:
        return ""
    params = dict(vars(action), prog=prog)
    for name in list(params):
        if params[name] is argparse.SUPPRESS:
            del params[name]
        elif hasattr(params[name], "__name__"):
            params[name] = params[name].__name__
    if params.get("choices") is not None:
        params["choices"] = ", ".join(str(c) for c in params["choices"])
    return " ".join((text % params).split())


def _default(action: argparse.Action) -> str | None:
    default = action.default
    if default is None or default is argparse.SUPPRESS or action.required:
        return None
    if "%(default)" in _raw_help(action):
        return None  # the help text already says it
    if isinstance(action, argparse.BooleanOptionalAction):
        return action.option_strings[0] if default else action.option_strings[-1]
    if action.nargs == 0:
        return None  # a plain flag: off unless given
    if isinstance(default, (list, tuple)) and not default:
        return None
    return _format_value(default)


def _usage(prog: str, parser: argparse.ArgumentParser) -> str:
    parts = [prog]
    optional = False
    for action in parser._actions:
        if action.help is argparse.SUPPRESS or isinstance(action, argparse._HelpAction):
            continue
        if isinstance(action, argparse._SubParsersAction):
            parts.append(_metavar(action) + " ...")
        elif not action.option_strings:
            parts.append(_argument(action))
        elif action.required:
            parts.append(f"{action.option_strings[0]} {_metavar(action)}")
        else:
            optional = True
    if optional:
        parts.append("[options]")
    return " ".join(parts)


def _render_parser(prog: str, parser: argparse.ArgumentParser, level: int) -> list[str]:
    lines = [f"{'#' * level} `{prog}`", "", "```text", _usage(prog, parser), "```", ""]
    if parser.description:
        lines += ["```text", parser.description.strip("\n"), "```", ""]
    for group in parser._action_groups:
        actions = [
            a
            for a in group._group_actions
            if a.help is not argparse.SUPPRESS
            and not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))
        ]
        if not actions:
            continue
        title = group.title or "options"
        lines += [f"**{_escape(title)}**", ""]
        for action in actions:
            item = f"- `{_argument(action)}`"
            notes = []
            if action.required and action.option_strings:
                notes.append("required")
            default = _default(action)
            if default is not None:
                notes.append(f"default: `{default}`")
            if notes:
                item += f" ({', '.join(notes)})"
            text = _help(action, prog)
            if text:
                item += f": {_escape(text)}"
            lines.append(item)
        lines.append("")
    for name, sub in _subparsers(parser):
        lines += _render_parser(f"{prog} {name}", sub, level + 1)
    return lines


def render_cli_reference(
    parsers: Sequence[tuple[str, argparse.ArgumentParser]] | None = None,
) -> str:
    """Render the CLI reference page.

    Args:
        parsers: ``[(command, parser), ...]``; by default `cli_parsers`.

    Returns:
        The Markdown text of ``docs/cli.md``.
    """
    from ermrl.cli import COMMANDS

    parsers = cli_parsers() if parsers is None else parsers
    lines = [HEADER, "| command | what it does |", "|---|---|"]
    for name, _ in parsers:
        anchor = "ermrl-" + name
        lines.append(f"| [`ermrl {name}`](#{anchor}) | {_escape(COMMANDS[name][1])} |")
    lines.append("")
    for name, parser in parsers:
        lines += _render_parser(f"ermrl {name}", parser, 2)
    while lines and not lines[-1]:
        lines.pop()
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m ermrl.cli._docs [--check] [OUT]``: write (or compare) the CLI reference."""
    parser = argparse.ArgumentParser(
        prog="python -m ermrl.cli._docs", description="Write the CLI reference page."
    )
    parser.add_argument("out", nargs="?", default="docs/cli.md", help="page to write")
    parser.add_argument(
        "--check", action="store_true", help="only compare: exit 1 when the page is stale"
    )
    args = parser.parse_args(argv)
    text = render_cli_reference()
    out = Path(args.out)
    if args.check:
        if not out.exists() or out.read_text(encoding="utf-8") != text:
            print(f"{out} is stale: run make cli-docs", file=sys.stderr)
            return 1
        return 0
    out.write_text(text, encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
