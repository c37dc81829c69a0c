"""Named task suites for generalization experiments (``--suite NAME``).

The packaged suites (``ermrl/data/suites.yml``) are the task sets of the original ER-MRL code:
``ant_swimmer``, ``ant_cheetah``, ``cheetah_swimmer``, the five leave-one-out sets of
{Ant, HalfCheetah, Hopper, Swimmer, Walker2d} named by the task left out (``no_ant``,
``no_halfcheetah``, ``no_hopper``, ``no_swimmer``, ``no_walker2d``) and ``forward_mujoco``
(all five). Users add their own in a YAML file of the same format.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from ermrl._config_base import ConfigError
from ermrl._io import load_yaml

__all__ = [
    "Suite",
    "UnknownSuiteError",
    "get_suite",
    "load_suites",
    "with_env_version",
]

_VERSION = re.compile(r"^v?(\d+)$")
_ID_VERSION = re.compile(r"-v\d+$")


class UnknownSuiteError(ConfigError):
    """No suite of that name (the message lists the available ones)."""


@dataclass(frozen=True)
class Suite:
    """A named set of tasks.

    Attributes:
        name: Lower-case name (``forward_mujoco``).
        env_ids: Gymnasium ids, in order.
        description: One line for ``--help`` and the README.
        aliases: Other accepted names (the original ER-MRL names, e.g. ``Ant_4_tr_envs``).
        source: The YAML file that defined it (``packaged`` for ``ermrl/data/suites.yml``).
    """

    name: str
    env_ids: tuple[str, ...]
    description: str = ""
    aliases: tuple[str, ...] = ()
    source: str = "packaged"


def _parse(data: Any, source: str) -> dict[str, Suite]:
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"suite file {source} must map suite names to env ids")
    out: dict[str, Suite] = {}
    for name, entry in data.items():
        where = f"suite {name!r} in {source}"
        if isinstance(entry, Sequence) and not isinstance(entry, str):
            entry = {"env_ids": list(entry)}
        if not isinstance(entry, Mapping):
            raise ConfigError(f"{where}: expected a list of env ids or a mapping with env_ids")
        unknown = set(entry) - {"env_ids", "description", "aliases"}
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}")
        env_ids = entry.get("env_ids")
        if (
            not isinstance(env_ids, Sequence)
            or isinstance(env_ids, str)
            or not all(isinstance(e, str) and e for e in env_ids)
        ):
            raise ConfigError(f"{where}: env_ids must be a list of env ids")
        if not env_ids:
            raise ConfigError(f"{where}: the suite has no task")
        if len(set(env_ids)) != len(env_ids):
            raise ConfigError(f"{where}: an env id is listed twice")
        aliases = entry.get("aliases") or []
        if isinstance(aliases, str):
            aliases = [aliases]
        out[str(name).lower()] = Suite(
            name=str(name).lower(),
            env_ids=tuple(env_ids),
            description=str(entry.get("description") or ""),
            aliases=tuple(str(a) for a in aliases),
            source=source,
        )
    return out


def load_suites(path: str | os.PathLike[str] | None = None) -> dict[str, Suite]:
    """The packaged suites, plus (and overridden by) those of a user YAML file.

    Args:
        path: A YAML file mapping suite names to ``{env_ids: [...], description: ...,
            aliases: [...]}`` or to a plain list of env ids.

    Returns:
        Suites keyed by lower-case name.

    Raises:
        ConfigError: the file cannot be read or is malformed.
    """
    text = resources.files("ermrl").joinpath("data/suites.yml").read_text()
    suites = _parse(load_yaml(text), "packaged")
    if path is not None:
        try:
            user_text = Path(path).read_text()
        except OSError as err:
            raise ConfigError(f"cannot read suite file {path}: {err.strerror}") from err
        except UnicodeDecodeError:
            raise ConfigError(f"suite file {path} is not a text (UTF-8) file") from None
        try:
            user = load_yaml(user_text)
        except yaml.YAMLError as err:
            # PyYAML's message spans several lines (the offending line and a caret).
            message = " ".join(str(err).split())
            raise ConfigError(f"suite file {path} is not valid YAML: {message}") from None
        suites.update(_parse(user, str(path)))
    return suites


def with_env_version(env_ids: Sequence[str], version: str) -> tuple[str, ...]:
    """Rewrite the ``-vN`` suffix of every id: ``with_env_version(["Ant-v5"], "v4") == ("Ant-v4",)``.

    Raises:
        ConfigError: ``version`` is not ``vN`` or ``N``.
    """
    match = _VERSION.match(version.strip())
    if match is None:
        raise ConfigError(f"env version must look like v4 or v5, got {version!r}")
    suffix = f"-v{match.group(1)}"
    return tuple(
        _ID_VERSION.sub(suffix, e) if _ID_VERSION.search(e) else e + suffix for e in env_ids
    )


def get_suite(
    name: str, path: str | os.PathLike[str] | None = None, *, env_version: str | None = None
) -> Suite:
    """Look a suite up by name or alias (case-insensitive).

    Args:
        name: Suite name, e.g. ``forward_mujoco`` or ``Ant_Swimmer``.
        path: Optional user YAML file (see [`load_suites`][ermrl.envs.load_suites]).
        env_version: Rewrite the suite's ids to this version (``v4``).

    Raises:
        UnknownSuiteError: no such suite; the message lists the available ones.
    """
    suites = load_suites(path)
    key = name.lower()
    suite = suites.get(key)
    if suite is None:
        suite = next((s for s in suites.values() if key in {a.lower() for a in s.aliases}), None)
    if suite is None:
        raise UnknownSuiteError(f"unknown suite {name!r}; available: {', '.join(sorted(suites))}")
    if env_version is not None:
        suite = Suite(
            name=suite.name,
            env_ids=with_env_version(suite.env_ids, env_version),
            description=suite.description,
            aliases=suite.aliases,
            source=suite.source,
        )
    return suite
