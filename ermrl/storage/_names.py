"""Study names: what a study may be called, how a name is printed, and the folders named after it.

A study's name comes from whoever created it, and a study may be shared: another user's worker,
a snapshot from elsewhere, or Optuna itself may have named it. So a name is checked where ermrl
creates or imports a study (`check_study_name`), printed escaped everywhere (`printable_name`),
and never becomes a path without a check that the path stays inside its folder (`folder_for`).
"""

from __future__ import annotations

import os
import unicodedata
from pathlib import Path

from ermrl._config_base import ConfigError

__all__ = [
    "MAX_STUDY_NAME_LENGTH",
    "StudyNameError",
    "check_study_name",
    "folder_for",
    "printable_name",
]

# Optuna's `studies.study_name` column is a VARCHAR(512): MySQL refuses a longer name with a
# DataError (SQLite would store it, so a study could not move to a server later).
MAX_STUDY_NAME_LENGTH = 512

# Unicode categories a name may not hold: control characters (newline, escape: a name printed
# raw could rewrite a terminal), format characters (bidirectional overrides that show text in
# another order than it is stored), surrogates, and line and paragraph separators.
_UNPRINTABLE = {"Cc", "Cf", "Cs", "Zl", "Zp"}


class StudyNameError(ConfigError):
    """A study name that ermrl does not create, import or turn into a folder."""


def _unprintable(char: str) -> bool:
    return unicodedata.category(char) in _UNPRINTABLE


def printable_name(name: str) -> str:
    """``name`` with every control or format character escaped (``\\n``, ``\\x1b``,
    ``\\u202e``), so that printing it cannot move the cursor, recolour or reorder a terminal.

    Examples:
        >>> printable_name("pendulum")
        'pendulum'
        >>> printable_name("a\\nb\\x1b[31m")
        'a\\\\nb\\\\x1b[31m'
    """
    if not any(_unprintable(c) for c in name):
        return name
    return "".join(repr(c)[1:-1] if _unprintable(c) else c for c in name)


def check_study_name(name: object) -> str:
    """``name``, if ermrl may create or import a study of that name; else one-line refusal.

    A name is a non-blank string of at most 512 characters, without a path separator (``/``,
    ``\\``), without ``..``, and without control or format characters.

    Raises:
        StudyNameError: The name breaks one of these rules (the message says which).
    """
    if not isinstance(name, str):
        raise StudyNameError(f"a study name is a string, not {type(name).__name__}")
    shown = printable_name(name)
    if not name.strip():
        raise StudyNameError("the study name is empty")
    if len(name) > MAX_STUDY_NAME_LENGTH:
        raise StudyNameError(
            f"the study name has {len(name)} characters; Optuna stores at most "
            f"{MAX_STUDY_NAME_LENGTH} characters"
        )
    bad = next((c for c in name if _unprintable(c)), None)
    if bad is not None:
        raise StudyNameError(
            f"the study name {shown!r} holds the control character U+{ord(bad):04X}; "
            "use letters, digits and punctuation"
        )
    for part, what in (("/", "a path separator '/'"), ("\\", "a path separator '\\'"),
                       ("..", "'..'")):  # fmt: skip
        if part in name:
            raise StudyNameError(
                f"the study name {shown!r} holds {what}: it names folders of results, "
                "so it may not lead out of them"
            )
    return name


def folder_for(base: str | Path, name: str, option: str = "--out") -> Path:
    """``base / name``, the default folder of study ``name`` (``runs/<name>``), after checking
    that it lies directly inside ``base`` (a check of the path as written: a symbolic link the
    user made inside ``base`` is followed as usual).

    Args:
        base: The parent folder (``runs``, ``reports``).
        name: The study's (or experiment's) name.
        option: How the user gives the folder instead, for the message.

    Raises:
        StudyNameError: ``name`` would lead outside ``base`` (a study created outside ermrl
            may hold any name): give the folder explicitly.
    """
    try:
        check_study_name(name)
    except StudyNameError as err:
        raise StudyNameError(f"{err}; give the output folder explicitly ({option})") from None
    folder = Path(base) / name
    if os.path.dirname(os.path.normpath(folder)) != os.path.normpath(base):  # defensive
        raise StudyNameError(
            f"the study name {printable_name(name)!r} does not name a folder inside {base}/; "
            f"give the output folder explicitly ({option})"
        )
    return folder
