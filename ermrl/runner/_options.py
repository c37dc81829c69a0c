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
from collections.abc import Sequence
from typing import Any, NoReturn

from ermrl.storage import DEFAULT_STORAGE

__all__ = [
    "ArgumentParser",
    "HelpFormatter",
    "PROGRESS_DEFAULT_HELP",
    "add_progress_arg",
    "positive_int",
    "nonneg_int",
    "positive_float",
    "storage_arg",
    "study_name_arg",
    "existing_study_name_arg",
    "add_storage_args",
    "add_stale_gradient_arg",
    "FOR_LEARNER_HELP",
    "parse_for_learner",
    "ForLearnerAction",
    "add_for_learner_arg",
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


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from err
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
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


def add_stale_gradient_arg(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--stale-gradient/--no-stale-gradient``: the rtu-ppo learner's ``stale_gradient``."""
    parser.add_argument(
        "--stale-gradient",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="rtu-ppo only: keep each stored RTU carry as it was collected (the default, the "
        "paper's stale gradient), or re-scan the rollout with the new parameters after each "
        "epoch (--no-stale-gradient, about half as fast)",
    )


FOR_LEARNER_HELP = (
    "settings of one learner only, on top of its table and --ppo: the first word names the "
    "learner, the rest are KEY=VALUE as in --ppo (values read as YAML). Repeatable; a later "
    "flag wins per key. Use it for what other learners refuse, e.g. the dagger learner's "
    "expert: --for-learner dagger expert=experts/hopper steps_per_iteration=500"
)


def parse_for_learner(values: Sequence[str]) -> tuple[str, dict[str, Any]]:
    """One ``--for-learner LEARNER KEY=VALUE [KEY=VALUE ...]``: the learner and its settings.

    Values are read as ``--ppo`` values are
    ([`ermrl.agents.parse_overrides`][ermrl.agents.parse_overrides]: YAML, ``1e-4`` a number,
    ``[64, 64]`` a list).

    Args:
        values: The flag's words, the learner's name first.

    Returns:
        The learner's name and its settings.

    Raises:
        ConfigError: an unregistered learner, no ``KEY=VALUE``, a malformed one or an unknown
            key (one line, starting ``--for-learner LEARNER:``).

    Examples:
        >>> parse_for_learner(["dagger", "expert=experts/hopper", "epochs=3"])
        ('dagger', {'expert': 'experts/hopper', 'epochs': 3})
    """
    from ermrl.agents import parse_overrides
    from ermrl.config import ConfigError
    from ermrl.learners import learner_names

    name, *items = values
    where = f"--for-learner {name}"
    if name not in learner_names():
        raise ConfigError(
            f"{where}: unknown learner {name!r}; choose from {', '.join(learner_names())}"
        )
    if not items:
        raise ConfigError(f"{where}: give at least one KEY=VALUE after the learner's name")
    settings: dict[str, Any] = {}
    for item in items:
        key, sep, _ = item.replace(":", "=", 1).partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"{where}: {item!r} is not KEY=VALUE (or KEY:VALUE)")
        try:
            settings.update(parse_overrides([item], name))
        except ConfigError as err:
            raise ConfigError(f"{where}: {str(err).removeprefix('--ppo: ')}") from None
    return name, settings


class ForLearnerAction(argparse.Action):
    """Appends each ``--for-learner`` as ``(learner, settings)``, checked while parsing."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: str | Sequence[Any] | None,
        option_string: str | None = None,
    ) -> None:
        from ermrl.config import ConfigError

        words = [values] if isinstance(values, str) else list(values or [])
        try:
            parsed = parse_for_learner(words)
        except ConfigError as err:
            raise argparse.ArgumentError(None, str(err)) from None
        setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), parsed])


def add_for_learner_arg(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--for-learner LEARNER KEY=VALUE [KEY=VALUE ...]``: settings of one learner only."""
    parser.add_argument(
        "--for-learner",
        action=ForLearnerAction,
        nargs="+",
        default=[],
        metavar=("LEARNER", "KEY=VALUE"),
        help=FOR_LEARNER_HELP,
    )
