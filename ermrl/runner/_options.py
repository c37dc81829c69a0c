"""The command options that the CLI and experiment files share: parser, formatter, types, flags.

Each option of ``ermrl evolve``, ``ermrl test``, ``ermrl report`` and the generalization commands
is also a key of an experiment file's stage, so their definitions live in the library, below the
CLI: `ermrl.runner._parsers` builds the commands' parsers from these pieces, the CLI
(``ermrl.cli``) parses argv with them, and the experiment-file plan
(`ermrl.runner._experiment`) checks each stage's options with them.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NoReturn

from ermrl._config_base import ConfigError
from ermrl._schema import Spec, fields_of
from ermrl.storage import DEFAULT_STORAGE

__all__ = [
    "ArgumentParser",
    "HelpFormatter",
    "PROGRESS_DEFAULT_HELP",
    "add_progress_arg",
    "positive_int",
    "nonneg_int",
    "storage_arg",
    "study_name_arg",
    "existing_study_name_arg",
    "add_storage_args",
    "add_schema_args",
    "ForLearnerAction",
]

# The exit code of bad input (ermrl.runner._commands.EXIT_USAGE, as argparse's own).
_EXIT_USAGE = 2


class ArgumentParser(argparse.ArgumentParser):
    """``argparse`` with one-line errors (``prog: error: ... (see --help)``) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: error: {message} (see --help)", file=sys.stderr)
        raise SystemExit(_EXIT_USAGE)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Shows defaults and keeps the description's line breaks.

    A help text that already says what its default is ("default: the packaged table") gets no
    second one, and an option whose default is ``None`` (not given: its help says what happens)
    gets no literal "(default: None)".
    """

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if "default" in text.lower() or action.default is None:
            return text
        return super()._get_help_string(action)


PROGRESS_DEFAULT_HELP = "default: bar when stdout is a terminal, lines otherwise"


def add_progress_arg(
    parser: argparse.ArgumentParser,
    *,
    inside: str = "trial (or generation)",
    finished: str = "trial",
) -> None:
    """``--progress bar|lines|none``: a live bar or progress lines for each run, or none.

    The default (``None``) is resolved once the arguments are parsed, for where stdout goes
    (`ermrl._progress.default_mode`).

    Args:
        parser: The command's parser.
        inside: What the runs are part of ("" for none), for the help.
        finished: What ``none`` still prints a line for, once finished.
    """
    from ermrl._progress import PROGRESS_MODES

    where = f" inside each {inside}" if inside else ""
    parser.add_argument(
        "--progress",
        choices=PROGRESS_MODES,
        default=None,
        help=f"bar: a live bar per run (or population){where}, with its rate (from its first "
        "step: start-up excluded) and ETA, a population split over processes printing lines "
        "from each part; lines: a line per run every tenth of its steps or 30 s, with the same "
        f"rate and ETA; none: a line per finished {finished} only ({PROGRESS_DEFAULT_HELP})",
    )


def positive_int(text: str) -> int:
    try:
        value = int(float(text)) if "e" in text.lower() else int(text)
    except (ValueError, OverflowError) as err:  # OverflowError: "1e400" is infinite
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from err
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def nonneg_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from err
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def storage_arg(text: str) -> str:
    """An ``argparse`` type for ``--storage``: a supported URL, not an in-memory database.

    Checked while parsing, so that a bad URL stops a command before it builds anything.
    """
    from ermrl.storage import StorageError, storage_kind

    try:
        storage_kind(text)
    except StorageError as err:
        raise argparse.ArgumentTypeError(str(err)) from err
    return text


def study_name_arg(text: str) -> str:
    """An ``argparse`` type for ``--study-name``: the rules of
    [`check_study_name`][ermrl.storage.check_study_name] (not blank, at most 512 characters,
    no path separator, no ``..``, no control character), checked before any storage is opened.
    """
    from ermrl.storage import StudyNameError, check_study_name

    try:
        return check_study_name(text)
    except StudyNameError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def existing_study_name_arg(text: str) -> str:
    """An ``argparse`` type for the ``--study-name`` of a study that is read, not created: any
    non-blank name, so that a study another tool named can still be shown, tested or deleted
    (its name is printed escaped, and no folder is derived from it unchecked)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("the study name is empty")
    return text


def add_storage_args(
    parser: argparse.ArgumentParser, *, study_required: bool, creates: bool | None = None
) -> None:
    """``--storage`` and ``--study-name``; a command that ``creates`` a study (default: one
    whose name is optional, ``ermrl evolve``) checks the name with `study_name_arg`, others
    with `existing_study_name_arg`."""
    creates = not study_required if creates is None else creates
    parser.add_argument(
        "--storage",
        type=storage_arg,
        default=DEFAULT_STORAGE,
        help="Optuna storage URL: sqlite:///file.db (embedded default), postgresql://user@host/db, "
        "mysql+pymysql://..., journal:///file.log (or file.log), redis://host:port",
    )
    parser.add_argument(
        "--study-name",
        type=study_name_arg if creates else existing_study_name_arg,
        required=study_required,
        default=None,
        help="study name"
        + ("" if study_required else " (default: derived from env, mask and budget)"),
    )


class ForLearnerAction(argparse.Action):
    """Appends each ``--for-learner`` as ``(learner, settings)``, checked while parsing."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: str | Sequence[Any] | None,
        option_string: str | None = None,
    ) -> None:
        from ermrl.test_phase import parse_for_learner

        words = [values] if isinstance(values, str) else list(values or [])
        try:
            parsed = parse_for_learner(words)
        except ConfigError as err:
            raise argparse.ArgumentError(None, str(err)) from None
        setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), parsed])


def _text_type(spec: Spec) -> Callable[[str], Any]:
    """An ``argparse`` type that reads a word as the schema reads a text value."""

    def parse(text: str) -> Any:
        try:
            return spec.from_text(text)
        except ConfigError as err:
            raise argparse.ArgumentTypeError(str(err)) from None

    parse.__name__ = spec.kind
    return parse


def _container(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup, title: str | None
) -> argparse.ArgumentParser | argparse._ArgumentGroup:
    """The group of ``parser`` titled ``title`` (made on first use), or ``parser`` itself."""
    if title is None or not isinstance(parser, argparse.ArgumentParser):
        return parser
    for group in parser._action_groups:
        if group.title == title:
            return group
    return parser.add_argument_group(title)


def add_schema_args(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    names: Sequence[str],
    helps: Mapping[str, str] | None = None,
) -> None:
    """The options of fields ``names`` of configuration ``cls``, generated from its schema
    (`ermrl._schema`): flag, type, choices, default, help and help section, each field's value
    under its own name.

    Args:
        parser: The command's parser (or one of its groups: then every option goes in it).
        cls: A configuration dataclass whose fields carry options.
        names: The fields to add, in this order.
        helps: Help texts of this command that differ from the field's.
    """
    specs = {spec.name: spec for spec in fields_of(cls)}
    for name in names:
        spec = specs[name]
        opt = spec.option
        kw: dict[str, Any] = {"dest": spec.name, "help": (helps or {}).get(name, spec.help)}
        if opt.metavar is not None:
            kw["metavar"] = opt.metavar
        if opt.required:
            kw["required"] = True
        if spec.kind == "bool":
            kw["action"] = argparse.BooleanOptionalAction if opt.negatable else "store_true"
            if opt.negatable:
                kw["default"] = spec.default
        elif spec.kind == "words":
            kw.update(nargs="+", default=[])
        elif spec.kind == "mapping":
            kw.update(action=ForLearnerAction, nargs="+", default=[])
        else:
            default = spec.default
            kw["default"] = list(default) if isinstance(default, tuple) else default
            if spec.kind in ("int", "float"):
                kw["type"] = _text_type(spec)
            if spec.choices is not None:
                kw["choices"] = spec.choices
            if spec.many:
                kw["nargs"] = spec.count or "+"
            elif opt.const is not None:
                kw.update(nargs="?", const=opt.const)
        _container(parser, opt.group).add_argument(spec.flag, **kw)
