"""One definition per configuration: typed dataclass fields that carry their option.

A stage's options are a frozen dataclass (such as `ermrl.test_phase.TestOptions`). Each field's
type says what it holds, and its metadata ([`option`][ermrl._schema.option]) what the command
line shows: the flag, the help, the choices, the smallest value. From that one definition:

- [`validate`][ermrl._schema.validate] checks a mapping of options: the keywords of a Python call
  or a stage of an experiment file, with one-line [`ConfigError`][ermrl.config.ConfigError]s
  (an unknown key with the nearest valid one, a wrong type, a value out of range);
- [`fields_of`][ermrl._schema.fields_of] lists each field's [`Spec`][ermrl._schema.Spec], from
  which the command line builds its parser (`ermrl.cli`), parsing each word with
  [`Spec.from_text`][ermrl._schema.Spec.from_text], the same code that reads a text value of a
  file;
- [`to_argv`][ermrl._schema.to_argv] renders the equivalent command line, for display only
  (`command.txt`, the plan): the library never parses an argv to call itself.

Values come from two kinds of source. Python keywords are typed: ``seeds="10"`` is refused, a
string is not a list of seeds. Text sources (command-line words, and an experiment file, where
YAML reads ``1e6`` as a string) are parsed as the command line parses them (``text=True``).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from ermrl._config_base import ConfigError

__all__ = [
    "Option", "Spec", "fields_of", "keys_of", "nearest", "option", "to_argv", "validate", "words_of",
]  # fmt: skip

_MISSING = dataclasses.MISSING


@dataclass(frozen=True)
class Option:
    """What the command line shows of one field.

    Attributes:
        help: The help text, or a function that builds it (from a registry, on first use).
        flag: The flag (default: ``--`` and the field's name with ``-`` for ``_``).
        metavar: The placeholder of its values in the help.
        choices: The valid values, or a function that lists them (a registry).
        low: The smallest valid number.
        above: A number the value must exceed (``0``: positive).
        negatable: A boolean's ``--no-`` form (``False``: the flag alone switches it on).
        words: ``KEY=VALUE`` words on the command line; a mapping in a file or a call.
        cli: Whether the command line has it.
        check: Checks (and may normalize) a value of the right type; raises
            [`ConfigError`][ermrl.config.ConfigError].
        key: Its key in an experiment file, when not the field's name (``eval`` for the
            field ``evaluate``: an experiment file spells options as their flags); both are
            accepted.
        group: The title of the help section the command line lists it in.
        const: The value of the flag given alone (``--fixed-input-scaling [VALUE]``); in a
            file or a call, ``true`` stands for it and ``false`` for nothing.
        required: The command line requires it.
    """

    help: str | Callable[[], str] = ""
    flag: str | None = None
    metavar: str | tuple[str, ...] | None = None
    choices: tuple[str, ...] | Callable[[], Iterable[str]] | None = None
    low: float | None = None
    above: float | None = None
    negatable: bool = True
    words: bool = False
    cli: bool = True
    check: Callable[[Any], Any] | None = None
    key: str | None = None
    group: str | None = None
    const: Any = None
    required: bool = False


def option(default: Any = _MISSING, help: str | Callable[[], str] = "", **kw: Any) -> Any:  # noqa: A002
    """A dataclass field with its [`Option`][ermrl._schema.Option] (``kw``: its attributes).

    A mutable default (a dict) becomes a ``default_factory``.
    """
    meta = {"option": Option(help=help, **kw)}
    if isinstance(default, dict):
        return dataclasses.field(default_factory=lambda: dict(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def nearest(word: str, choices: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``choices``, else the valid ones."""
    names = list(choices)
    match = difflib.get_close_matches(word, names, n=1, cutoff=0.5)
    return f" (did you mean {match[0]!r}?)" if match else f" (valid: {', '.join(sorted(names))})"


_PLURAL = {"int": "integers", "float": "numbers", "bool": "booleans", "str": "strings",
           "path": "paths"}  # fmt: skip


def _shown(value: Any) -> str:
    return f"{type(value).__name__} {value!r}"


@dataclass(frozen=True)
class Spec:
    """One field of a configuration, as the parsers see it.

    Attributes:
        name: The field's name (the key of a file, the keyword of a call).
        kind: ``int``, ``float``, ``bool``, ``str``, ``path`` (a string or a
            [`Path`][pathlib.Path]), ``words`` (``KEY=VALUE``) or ``mapping``.
        many: A list of values (``nargs="+"`` on the command line).
        optional: ``None`` is valid (the default decides).
        default: The field's default.
        option: What the command line shows.
        count: How many values a list holds, when fixed (``tuple[float, float]``: 2, as
            ``LOW HIGH``).
    """

    name: str
    kind: str
    many: bool
    optional: bool
    default: Any
    option: Option
    count: int | None = None

    @property
    def flag(self) -> str:
        return self.option.flag or "--" + self.name.replace("_", "-")

    @property
    def choices(self) -> tuple[str, ...] | None:
        choices = self.option.choices
        return tuple(choices()) if callable(choices) else choices

    @property
    def help(self) -> str:
        text = self.option.help
        return text() if callable(text) else text

    def from_text(self, text: str) -> Any:
        """One command-line word (or a text value of a file) as a value of this field.

        Raises:
            ConfigError: Not a value of this field (the message has no field name: the
                caller says where).
        """
        if self.kind == "int":
            try:
                number = float(text) if "e" in text.lower() else int(text)
            except ValueError:
                raise ConfigError(f"{text!r} is not an integer") from None
            if isinstance(number, float) and not (math.isfinite(number) and number.is_integer()):
                raise ConfigError(f"{text!r} is not an integer")
            return self._checked(int(number), text)
        if self.kind == "float":
            try:
                return self._checked(float(text), text)
            except ValueError:
                raise ConfigError(f"{text!r} is not a number") from None
        if self.kind == "bool":
            if text.lower() in ("true", "yes", "1"):
                return True
            if text.lower() in ("false", "no", "0"):
                return False
            raise ConfigError(f"true or false, got {text!r}")
        return self._choice(text)

    def _checked(self, value: float, text: str) -> Any:
        low, above = self.option.low, self.option.above
        if low is not None and value < low:
            bound = "positive" if low == 1 and self.kind == "int" else f">= {low:g}"
            raise ConfigError(f"must be {bound}, got {text}")
        if above is not None and not value > above:
            raise ConfigError(f"must be {'positive' if above == 0 else f'> {above:g}'}, got {text}")
        return value

    def _choice(self, value: str) -> str:
        choices = self.choices
        if choices is not None and value not in choices:
            match = difflib.get_close_matches(value, choices, n=1, cutoff=0.5)
            hint = f"did you mean {match[0]!r}?" if match else f"choose from {', '.join(choices)}"
            raise ConfigError(f"invalid choice: {value!r} ({hint})")
        return value

    def check(self, value: Any, *, text: bool) -> Any:
        """``value`` checked (and, for a text source, parsed) as a value of this field.

        Raises:
            ConfigError: The value's type or range, in one line without the field's name.
        """
        if value is None:
            if self.optional:
                return None
            raise ConfigError("a value is required, got nothing (null)")
        if self.option.const is not None and isinstance(value, bool):
            return self.option.const if value else None
        if self.kind == "words":
            return self._words(value)
        if self.kind == "mapping":
            if not isinstance(value, Mapping):
                raise ConfigError(f"a mapping is expected, got {_shown(value)}")
            check = self.option.check
            return dict(value) if check is None else check(value)
        if self.many:
            if text and isinstance(value, (str, int, float)) and not isinstance(value, bool):
                value = [value]  # one value where a list may stand, as on the command line
            if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, Sequence):
                raise ConfigError(
                    f"a list of {_PLURAL[self.kind]} is expected, got {_shown(value)}"
                )
            if not value:
                raise ConfigError("an empty list")
            if self.count is not None and len(value) != self.count:
                raise ConfigError(f"{self.count} values are expected, got {len(value)}")
            return tuple(self._one(v, text=text) for v in value)
        return self._one(value, text=text)

    def _one(self, value: Any, *, text: bool) -> Any:
        kind = self.kind
        if text and isinstance(value, str) and kind in ("int", "float", "bool"):
            return self.from_text(value)
        if kind == "bool":
            if isinstance(value, bool):
                return value
            raise ConfigError(f"true or false, got {_shown(value)}")
        if kind in ("int", "float"):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"a number is expected, got {_shown(value)}")
            if kind == "int":
                if not (math.isfinite(value) and float(value).is_integer()):
                    raise ConfigError(f"an integer is expected, got {value!r}")
                value = int(value)
            return self._checked(value, repr(value))
        if kind == "path" and isinstance(value, Path):
            return value
        if not isinstance(value, str):
            what = "a path" if kind == "path" else "a string"
            raise ConfigError(f"{what} is expected, got {_shown(value)}")
        return self._choice(value)

    @staticmethod
    def _words(value: Any) -> Any:
        if isinstance(value, Mapping):
            bad = [k for k in value if not isinstance(k, str)]
            if bad:
                raise ConfigError(f"setting names must be words, got {bad[0]!r}")
            return dict(value)
        if isinstance(value, str) or not isinstance(value, Sequence):
            raise ConfigError(
                f"a mapping {{KEY: VALUE}} (or KEY=VALUE words) is expected, got {_shown(value)}"
            )
        if not all(isinstance(v, str) for v in value):
            raise ConfigError("KEY=VALUE words are expected")
        return tuple(value)


def _kind(hint: Any) -> tuple[str, bool, bool]:
    """``(kind, many, optional)`` of a type hint."""
    args = typing.get_args(hint)
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        optional = len(rest) < len(args)
        if set(rest) == {str, Path}:
            return "path", False, optional
        if len(rest) == 2 and typing.get_origin(rest[0]) is Mapping:  # words or a mapping
            return "words", False, optional
        kind, many, _ = _kind(rest[0])
        return kind, many, optional
    if origin is Literal:
        return "str", False, False
    if origin in (Sequence, tuple, list):
        return _kind(args[0])[0], True, False
    if origin is Mapping:
        return "mapping", False, False
    names = {int: "int", float: "float", bool: "bool", str: "str", Path: "path"}
    return names[hint], False, False


def _count(hint: Any) -> int | None:
    """The length of a fixed-length tuple hint (``tuple[float, float]``: 2), else ``None``."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    args = typing.get_args(hint)
    if typing.get_origin(hint) is tuple and args and Ellipsis not in args:
        return len(args)
    return None


def fields_of(cls: type) -> tuple[Spec, ...]:
    """The [`Spec`][ermrl._schema.Spec] of each field of a configuration with options, in order."""
    cached = _SPECS.get(cls)
    if cached is not None:
        return cached
    fields = [f for f in dataclasses.fields(cls) if "option" in f.metadata]
    # The hints of these fields only: others may name types imported for type checkers alone.
    holder = type(cls.__name__, (), {"__annotations__": {f.name: f.type for f in fields}})
    holder.__module__ = cls.__module__
    hints = typing.get_type_hints(holder)
    specs = []
    for f in fields:
        opt = f.metadata["option"]
        default = f.default if f.default is not _MISSING else f.default_factory()  # type: ignore[operator]
        kind, many, optional = _kind(hints[f.name])
        literal = [h for h in (hints[f.name], *typing.get_args(hints[f.name]))
                   if typing.get_origin(h) is Literal]  # fmt: skip
        if opt.choices is None and literal:
            opt = dataclasses.replace(opt, choices=typing.get_args(literal[0]))
        count = _count(hints[f.name])
        specs.append(Spec(f.name, kind, many, optional or default is None, default, opt, count))
    _SPECS[cls] = result = tuple(specs)
    return result


def keys_of(*classes: type) -> dict[str, Spec]:
    """Every key the fields of ``classes`` accept (names and file keys) -> its field."""
    return {k: s for c in classes for s in fields_of(c) for k in (s.name, s.option.key) if k}


_SPECS: dict[type, tuple[Spec, ...]] = {}


def validate(
    cls: type, values: Mapping[str, Any], where: str = "", *, text: bool = False
) -> dict[str, Any]:
    """``values`` checked against the fields of ``cls``: the keyword arguments to build it.

    Args:
        cls: A configuration dataclass whose fields carry options.
        values: ``{field name: value}``; a field left out keeps its default.
        where: Names the options in errors (``"ermrl.test"``, ``"file.yaml: Pendulum-v1: test"``).
        text: Strings are parsed as the command line parses its words (an experiment file,
            where YAML leaves ``1e6`` a string); else Python types are required.

    Returns:
        The checked values, lists as tuples.

    Raises:
        ConfigError: An unknown key (with the nearest valid one) or a bad value, in one line
            that names it.
    """
    specs = keys_of(cls)
    prefix = f"{where}: " if where else ""
    out: dict[str, Any] = {}
    for key, value in values.items():
        spec = specs.get(key) if isinstance(key, str) else None
        if spec is None:
            raise ConfigError(f"{prefix}unknown key {key!r}{nearest(str(key), specs)}")
        try:
            out[spec.name] = spec.check(value, text=text)
        except ConfigError as err:
            raise ConfigError(f"{prefix}{key}: {err}") from None
    return out


def _word(value: Any) -> str:
    """A value as one command-line word (lists and mappings in YAML's flow style)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (Mapping, list, tuple)):
        import yaml

        plain = list(value) if isinstance(value, tuple) else value
        return yaml.safe_dump(plain, default_flow_style=True, width=10**6).strip()
    return str(value)


def _pairs(items: Iterable[tuple[Any, Any]]) -> list[str]:
    return [f"{k}={_word(v)}" for k, v in items]


def words_of(value: Mapping[str, Any] | Sequence[str] | None) -> list[str]:
    """``KEY=VALUE`` words of a ``words`` field, whether given as words or as a mapping (each
    value written as the command line would be given it)."""
    if value is None:
        return []
    return _pairs(value.items()) if isinstance(value, Mapping) else list(value)


def to_argv(
    classes: type | Sequence[type],
    given: Mapping[str, Any],
    values: Mapping[str, Any] | None = None,
) -> list[str]:
    """The command-line words that give these options, in the order ``given`` lists them: for
    display (``command.txt``, the plan), never parsed back.

    Args:
        classes: The configuration(s) whose fields the keys are.
        given: The options as given (their order, and their spelling of ``KEY=VALUE`` words).
        values: The same options checked by [`validate`][ermrl._schema.validate] (default:
            ``given``).
    """
    specs = keys_of(*([classes] if isinstance(classes, type) else classes))
    argv: list[str] = []
    for key in given:
        spec = specs[key]
        value = given[key] if values is None else values[spec.name]
        if value is None:
            continue
        if spec.option.const is not None and isinstance(given[key], bool):
            argv += [spec.flag] if given[key] else []
        elif spec.kind == "bool":
            if spec.option.negatable:
                argv.append(spec.flag if value else "--no-" + spec.flag[2:])
            elif value:
                argv.append(spec.flag)
        elif spec.kind == "words":
            pairs = value.items() if isinstance(value, Mapping) else None
            argv += [spec.flag, *(value if pairs is None else _pairs(pairs))]
        elif spec.kind == "mapping":
            for name, settings in value.items():
                argv += [spec.flag, str(name), *_pairs(settings.items())]
        elif spec.many:
            argv += [spec.flag, *map(_word, given[key] if isinstance(given[key], list) else value)]
        else:
            argv += [spec.flag, _word(given[key])]
    return argv
