"""A study as one plain JSON file: export it from one storage, import it into another.

Databases stay out of git, plain files go in. A long evolution that spans several sittings (and
machines) is carried over as a *snapshot*: ``ermrl study export --out pend.json`` at the end of a
sitting, commit the file, ``ermrl study import --snapshot pend.json`` on the next machine, and
``ermrl evolve`` resumes where it stopped. The search state goes with it: CMA-ES keeps its
optimizer in trial system attributes as plain JSON (``cma:state:*``, see
`ermrl.search._samplers`), and a snapshot keeps every system attribute.

A snapshot (format ``ermrl-study-snapshot``, version 1) is one JSON object::

    {"format": "ermrl-study-snapshot", "version": 1,
     "exported_at": "2026-11-25T15:03:42.164614",   # local time, as Optuna's trial times
     "ermrl_version": "...", "optuna_version": "...",  # informational
     "study_name": "pend", "directions": ["MAXIMIZE"],
     "user_attrs": {...}, "system_attrs": {...},
     "trials": [{"number": 0, "state": "COMPLETE", "values": [-812.5],
                 "datetime_start": "...", "datetime_complete": "...",
                 "params": {"sr": 0.93}, "distributions": {"sr": {"name": "FloatDistribution",
                 "attributes": {...}}}, "user_attrs": {...}, "system_attrs": {...},
                 "intermediate_values": {"4096": -1210.0}}, ...],
     "related": {"pend.reeval": {"study_name": ..., "directions": ..., "user_attrs": ...,
                                 "system_attrs": ..., "trials": [...]}}}

Distributions are Optuna's own JSON (`optuna.distributions.distribution_to_json`, kept as
an object). Non-finite floats are written as Python's `json` writes them (``NaN``,
``Infinity``), as Optuna stores attributes. ``related`` holds the sibling studies stored beside
the study (its re-evaluation study ``<name>.reeval``), so that importing restores them too.

Nothing in a snapshot is unpickled, evaluated or imported: it is read with `json.loads`
and every field is checked ([`read_snapshot`][ermrl.storage.read_snapshot]) before anything is
written. A hand-edited snapshot is refused where ermrl would not have written it: a study that
does not maximize (every ermrl study maximizes its fitness), or a trial value that is not
finite (an ``Infinity`` would become the best trial).

Importing ([`import_snapshot`][ermrl.storage.import_snapshot]) keeps trial numbers, states, values,
times, parameters and their distributions, every attribute and the intermediate values, as
`optuna.copy_study` does. A trial that was RUNNING when the snapshot was taken has no worker any
more: it is imported as FAIL (``fail_reason`` says why) and retried as a WAITING copy with the same
parameters ([`RetryStaleTrial`][ermrl.storage.RetryStaleTrial], as for a worker that died), which
the next ``ermrl evolve`` runs first. WAITING trials (queued parameters) stay WAITING.
"""

from __future__ import annotations

import copy
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import optuna
from optuna.distributions import BaseDistribution, distribution_to_json, json_to_distribution
from optuna.storages import BaseStorage, InMemoryStorage
from optuna.study import StudyDirection
from optuna.trial import FrozenTrial, TrialState

from ermrl._io import write_atomic
from ermrl.storage._heartbeat import RetryStaleTrial
from ermrl.storage._locks import storage_lock
from ermrl.storage._names import StudyNameError, check_study_name
from ermrl.storage._open import DEFAULT_MAX_RETRY, open_storage, study_names
from ermrl.storage._url import StorageURL, parse_storage_url

__all__ = [
    "RELATED_SUFFIXES",
    "SNAPSHOT_FORMAT",
    "SNAPSHOT_VERSION",
    "Snapshot",
    "SnapshotError",
    "SnapshotImport",
    "StudyExists",
    "StudySnapshot",
    "import_snapshot",
    "load_snapshot",
    "parse_snapshot",
    "read_snapshot",
    "snapshot_counts",
    "study_to_snapshot",
    "write_snapshot",
]

SNAPSHOT_FORMAT = "ermrl-study-snapshot"
SNAPSHOT_VERSION = 1
# Sibling studies that travel with a study: ``<name><suffix>`` in the same storage. ".reeval" is
# ermrl.search.reevaluation_study_name's suffix (storage must not import search; a test checks).
RELATED_SUFFIXES: tuple[str, ...] = (".reeval",)

_TOP_KEYS = ("format", "version", "exported_at", "related")
_STUDY_KEYS = ("study_name", "directions", "user_attrs", "system_attrs", "trials")
_TRIAL_KEYS = (
    "number",
    "state",
    "values",
    "datetime_start",
    "datetime_complete",
    "params",
    "distributions",
    "user_attrs",
    "system_attrs",
    "intermediate_values",
)


class SnapshotError(ValueError):
    """A file that is not a valid study snapshot (bad JSON, unknown format or version, ...)."""


class StudyExists(ValueError):
    """The target storage already holds a study of that name, with other contents."""


@dataclass(frozen=True)
class StudySnapshot:
    """One study of a snapshot, checked and ready to add to a storage.

    Attributes:
        study_name: The study's name when it was exported.
        directions: Its optimization directions.
        user_attrs: Study user attributes (the ermrl configuration, the launch command, ...).
        system_attrs: Study system attributes.
        trials: Every trial, ordered by number (0, 1, ...), as exported (RUNNING ones included).
    """

    study_name: str
    directions: tuple[StudyDirection, ...]
    user_attrs: dict[str, Any]
    system_attrs: dict[str, Any]
    trials: tuple[FrozenTrial, ...]


@dataclass(frozen=True)
class Snapshot:
    """A checked snapshot file (see [`read_snapshot`][ermrl.storage.read_snapshot]).

    Attributes:
        study: The exported study.
        related: Its sibling studies (the re-evaluation study ``<name>.reeval``), by name.
        exported_at: When it was exported (local time, as Optuna's trial times).
        version: The format version.
        source: Where it was read from (for messages).
    """

    study: StudySnapshot
    related: dict[str, StudySnapshot]
    exported_at: datetime
    version: int = SNAPSHOT_VERSION
    source: str = "<snapshot>"

    def target_names(self, study_name: str | None = None) -> dict[str, str]:
        """Exported name -> name in the target storage, for the study and its siblings.

        Args:
            study_name: The new name of the study (``None``: keep it). A sibling
                ``<old><suffix>`` becomes ``<new><suffix>``.
        """
        old = self.study.study_name
        new = study_name or old
        names = {old: new}
        for name in self.related:
            names[name] = new + name[len(old) :] if name.startswith(old) else name
        return names


@dataclass(frozen=True)
class SnapshotImport:
    """What [`import_snapshot`][ermrl.storage.import_snapshot] did.

    Attributes:
        study: The imported (or already identical) study, loaded from the target storage.
        created: Names of the studies created.
        identical: Names of the studies that were already there with the same contents.
        interrupted: ``(study name, trial number, retry number or None)`` of every trial that
            was RUNNING at export, imported as FAIL (and retried as that WAITING trial).
        n_trials: Trials of each of those studies in the target storage now, by name.
    """

    study: optuna.Study
    created: tuple[str, ...]
    identical: tuple[str, ...]
    interrupted: tuple[tuple[str, int, int | None], ...]
    n_trials: dict[str, int]


# -- export ------------------------------------------------------------------------------------


def _iso(moment: datetime | None) -> str | None:
    return None if moment is None else moment.isoformat()


def _trial_doc(trial: FrozenTrial) -> dict[str, Any]:
    return {
        "number": trial.number,
        "state": trial.state.name,
        "values": None if trial.values is None else [float(v) for v in trial.values],
        "datetime_start": _iso(trial.datetime_start),
        "datetime_complete": _iso(trial.datetime_complete),
        "params": dict(trial.params),
        "distributions": {
            name: json.loads(distribution_to_json(dist))
            for name, dist in trial.distributions.items()
        },
        "user_attrs": trial.user_attrs,
        "system_attrs": trial.system_attrs,
        "intermediate_values": {str(k): v for k, v in sorted(trial.intermediate_values.items())},
    }


def _study_doc(storage: BaseStorage, name: str) -> dict[str, Any]:
    study_id = storage.get_study_id_from_name(name)
    return {
        "study_name": name,
        "directions": [d.name for d in storage.get_study_directions(study_id)],
        "user_attrs": storage.get_study_user_attrs(study_id),
        "system_attrs": storage.get_study_system_attrs(study_id),
        "trials": [_trial_doc(t) for t in storage.get_all_trials(study_id, deepcopy=False)],
    }


def study_to_snapshot(study: optuna.Study, *, related: bool = True) -> dict[str, Any]:
    """A study, and its sibling studies, as one plain-JSON document.

    Args:
        study: The study (any storage).
        related: Include the sibling studies of `RELATED_SUFFIXES` that exist in the
            same storage (``<name>.reeval``).

    Returns:
        The snapshot (see the module docstring); `json.dump` writes it as it is.

    Examples:
        >>> import optuna
        >>> study = optuna.create_study(study_name="demo", direction="maximize")
        >>> study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
        >>> doc = study_to_snapshot(study)
        >>> doc["format"], doc["version"], len(doc["trials"]), doc["trials"][0]["state"]
        ('ermrl-study-snapshot', 1, 2, 'COMPLETE')
    """
    from ermrl import __version__

    storage = study._storage
    doc: dict[str, Any] = {
        "format": SNAPSHOT_FORMAT,
        "version": SNAPSHOT_VERSION,
        "exported_at": datetime.now().isoformat(),
        "ermrl_version": __version__,
        "optuna_version": optuna.__version__,
        **_study_doc(storage, study.study_name),
        "related": {},
    }
    if related:
        present = set(study_names(storage))
        for suffix in RELATED_SUFFIXES:
            name = study.study_name + suffix
            if name in present:
                doc["related"][name] = _study_doc(storage, name)
    return doc


def _dumps(doc: Mapping[str, Any], indent: int | None = None) -> str:
    return json.dumps(doc, sort_keys=True, indent=indent)


def write_snapshot(study: optuna.Study, path: str | os.PathLike[str]) -> dict[str, Any]:
    """Write [`study_to_snapshot`][ermrl.storage.study_to_snapshot] to ``path`` atomically (a
    temporary file, renamed).

    Args:
        study: The study.
        path: The JSON file (its folder is created if needed).

    Returns:
        The document written.

    Raises:
        OSError: the file cannot be written (nothing is left half-written).
    """
    doc = study_to_snapshot(study)
    write_atomic(Path(path), _dumps(doc, indent=1) + "\n")
    return doc


# -- reading and checking ------------------------------------------------------------------------


def _get(doc: Mapping[str, Any], key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if key not in doc:
        raise SnapshotError(f"{where} has no {key!r}")
    value = doc[key]
    if not isinstance(value, kind) or isinstance(value, bool) and bool not in _types(kind):
        names = " or ".join(t.__name__ for t in _types(kind))
        raise SnapshotError(f"{where}: {key!r} must be {names}, got {type(value).__name__}")
    return value


def _types(kind: type | tuple[type, ...]) -> tuple[type, ...]:
    return kind if isinstance(kind, tuple) else (kind,)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SnapshotError(f"{where} must be a number, got {value!r}")
    return float(value)


def _datetime(value: Any, where: str) -> datetime | None:
    if value is None:
        return None
    if not isinstance(value, str):
        raise SnapshotError(f"{where} must be an ISO date and time or null, got {value!r}")
    try:
        moment = datetime.fromisoformat(value)
    except ValueError as err:
        raise SnapshotError(f"{where}: {err}") from err
    if moment.tzinfo is not None:  # Optuna's times are naive local times
        moment = moment.astimezone().replace(tzinfo=None)
    return moment


def _distribution(value: Any, where: str) -> BaseDistribution:
    try:
        return json_to_distribution(json.dumps(value))
    except Exception as err:  # noqa: BLE001 (KeyError, TypeError, ValueError: all one refusal)
        detail = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise SnapshotError(
            f"{where} is not a distribution Optuna can read ({type(err).__name__}: {detail})"
        ) from err


def _trial(doc: Any, index: int, n_objectives: int, where: str) -> FrozenTrial:
    where = f"{where}, trial {index}"
    if not isinstance(doc, dict):
        raise SnapshotError(f"{where} is not an object")
    for key in _TRIAL_KEYS:
        if key not in doc:
            raise SnapshotError(f"{where} has no {key!r}")
    number = _get(doc, "number", int, where)
    if number != index:
        raise SnapshotError(f"{where} has number {number}: trials must be numbered 0, 1, ...")
    state_name = _get(doc, "state", str, where)
    if state_name not in TrialState.__members__:
        states = ", ".join(TrialState.__members__)
        raise SnapshotError(f"{where}: unknown state {state_name!r} (one of {states})")
    raw_values = doc["values"]
    values = None
    if raw_values is not None:
        if not isinstance(raw_values, list) or len(raw_values) != n_objectives:
            raise SnapshotError(f"{where}: 'values' must be null or {n_objectives} number(s)")
        values = [_number(v, f"{where}, values") for v in raw_values]
        if not all(math.isfinite(v) for v in values):  # NaN, or an Infinity that would be best
            raise SnapshotError(f"{where}: 'values' must be finite, got {raw_values!r:.80}")
    params = _get(doc, "params", dict, where)
    raw_dists = _get(doc, "distributions", dict, where)
    distributions = {
        name: _distribution(value, f"{where}, distribution {name!r}")
        for name, value in raw_dists.items()
    }
    intermediate: dict[int, float] = {}
    for text, value in _get(doc, "intermediate_values", dict, where).items():
        try:
            step = int(text)
        except ValueError as err:
            raise SnapshotError(f"{where}: intermediate step {text!r} is not an integer") from err
        intermediate[step] = _number(value, f"{where}, intermediate value {text}")
    try:
        trial = FrozenTrial(
            number=number,
            state=TrialState[state_name],
            value=None,
            values=values,
            datetime_start=_datetime(doc["datetime_start"], f"{where}, datetime_start"),
            datetime_complete=_datetime(doc["datetime_complete"], f"{where}, datetime_complete"),
            params=params,
            distributions=distributions,
            user_attrs=_get(doc, "user_attrs", dict, where),
            system_attrs=_get(doc, "system_attrs", dict, where),
            intermediate_values=intermediate,
            trial_id=number,
        )
        trial._validate()
    except (ValueError, TypeError) as err:
        raise SnapshotError(f"{where}: {err}") from err
    return trial


def _study(doc: Any, where: str) -> StudySnapshot:
    if not isinstance(doc, dict):
        raise SnapshotError(f"{where} is not an object")
    name = _get(doc, "study_name", str, where)
    try:
        check_study_name(name)
    except StudyNameError as err:
        raise SnapshotError(f"{where}: {err}") from None
    where = f"{where} {name!r}"
    raw_directions = _get(doc, "directions", list, where)
    if raw_directions != [StudyDirection.MAXIMIZE.name]:  # what every ermrl study is
        raise SnapshotError(
            f"{where}: 'directions' is {raw_directions!r:.80}; ermrl's studies maximize "
            "their fitness (['MAXIMIZE'])"
        )
    directions = (StudyDirection.MAXIMIZE,)
    trials = tuple(
        _trial(t, i, len(directions), where) for i, t in enumerate(_get(doc, "trials", list, where))
    )
    return StudySnapshot(
        study_name=name,
        directions=directions,
        user_attrs=_get(doc, "user_attrs", dict, where),
        system_attrs=_get(doc, "system_attrs", dict, where),
        trials=trials,
    )


def parse_snapshot(doc: Any, source: str = "<snapshot>") -> Snapshot:
    """Check a snapshot document (as [`study_to_snapshot`][ermrl.storage.study_to_snapshot] returns
    it).

    Args:
        doc: The decoded JSON.
        source: Where it came from, for messages.

    Raises:
        SnapshotError: unknown format or version, a missing or ill-typed field, a direction
            other than ``MAXIMIZE``, a trial value that is not finite, a distribution
            Optuna cannot read, a trial Optuna would refuse (a parameter outside its
            distribution, a COMPLETE trial without values, ...).
    """
    where = f"{source}:"
    if not isinstance(doc, dict):
        raise SnapshotError(f"{where} not a study snapshot (a JSON object is expected)")
    if doc.get("format") != SNAPSHOT_FORMAT:
        raise SnapshotError(
            f"{where} not a study snapshot ('format' is {doc.get('format')!r}, "
            f"expected {SNAPSHOT_FORMAT!r})"
        )
    for key in _TOP_KEYS:
        if key not in doc:
            raise SnapshotError(f"{where} the snapshot has no {key!r}")
    version = doc["version"]
    if version != SNAPSHOT_VERSION or isinstance(version, bool):
        raise SnapshotError(
            f"{where} snapshot format version {version!r} is not supported (this ermrl reads "
            f"version {SNAPSHOT_VERSION}; a newer ermrl may have written it)"
        )
    exported_at = _datetime(doc["exported_at"], f"{where} 'exported_at'")
    if exported_at is None:
        raise SnapshotError(f"{where} 'exported_at' is null")
    study = _study(doc, f"{source}: study")
    related_doc = _get(doc, "related", dict, f"{source}:")
    related = {}
    for name, value in related_doc.items():
        part = _study(value, f"{source}: related study")
        if part.study_name != name or name == study.study_name:
            raise SnapshotError(f"{where} related study {name!r} is named {part.study_name!r}")
        related[name] = part
    return Snapshot(
        study=study, related=related, exported_at=exported_at, version=version, source=source
    )


def read_snapshot(path: str | os.PathLike[str]) -> Snapshot:
    """Read and check a snapshot file; nothing in it is unpickled, evaluated or imported.

    Args:
        path: A file written by [`write_snapshot`][ermrl.storage.write_snapshot]
            (``ermrl study export --out X.json``).

    Returns:
        The checked snapshot.

    Raises:
        SnapshotError: the file is missing, not JSON, or not a valid snapshot (one-line message).
    """
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        detail = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise SnapshotError(f"cannot read snapshot {source}: {detail}") from err
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        raise SnapshotError(f"{source} is not JSON ({err})") from err
    except RecursionError as err:
        raise SnapshotError(f"{source} is nested too deeply to be a snapshot") from err
    return parse_snapshot(doc, source)


# -- import --------------------------------------------------------------------------------------


def _to_add(
    part: StudySnapshot, exported_at: datetime, retry: RetryStaleTrial | None
) -> tuple[list[FrozenTrial], list[FrozenTrial], list[tuple[int, int | None]]]:
    """The trials to add (RUNNING ones closed as FAIL), the failed ones to retry, and
    ``(number, retry number or None)`` of each RUNNING one."""
    trials: list[FrozenTrial] = []
    to_retry: list[FrozenTrial] = []
    interrupted: list[tuple[int, int | None]] = []
    when = exported_at.isoformat(sep=" ", timespec="seconds")
    for trial in part.trials:
        if trial.state != TrialState.RUNNING:
            trials.append(trial)
            continue
        retried = retry is not None and retry.would_retry(trial)
        number = len(part.trials) + len(to_retry) if retried else None
        if number is not None:
            then = f"retried as trial {number}"
        elif retry is None:
            then = "not retried"
        else:
            then = f"not retried (max_retry {retry.max_retry} reached)"
        closed = copy.deepcopy(trial)
        closed.state = TrialState.FAIL
        closed.values = None
        closed.datetime_complete = max(exported_at, trial.datetime_start or exported_at)
        closed.user_attrs = {
            **trial.user_attrs,
            "fail_reason": f"running when the study was exported ({when}); imported as FAIL, "
            + then,
        }
        trials.append(closed)
        interrupted.append((trial.number, number))
        if retried:
            to_retry.append(closed)
    return trials, to_retry, interrupted


def _add_study(
    storage: BaseStorage,
    part: StudySnapshot,
    name: str,
    exported_at: datetime,
    retry: RetryStaleTrial | None,
) -> list[tuple[int, int | None]]:
    """Create study ``name`` in ``storage`` with the contents of ``part``."""
    study = optuna.create_study(storage=storage, study_name=name, directions=part.directions)
    for key, value in part.user_attrs.items():
        storage.set_study_user_attr(study._study_id, key, value)
    for key, value in part.system_attrs.items():
        storage.set_study_system_attr(study._study_id, key, value)
    trials, to_retry, interrupted = _to_add(part, exported_at, retry)
    study.add_trials(trials)
    for trial in to_retry:
        assert retry is not None
        retry(study, trial)
    return interrupted


def _canonical(value: Any) -> Any:
    """``value`` with ``-0.0`` as ``0.0`` (SQLite stores both as one) and tuples as lists."""
    if isinstance(value, float):
        return 0.0 if value == 0 else value
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    return value


def _same(a: Any, b: Any) -> bool:
    """Whether two documents are equal as a storage keeps them (NaN equals NaN)."""
    return _dumps(_canonical(a)) == _dumps(_canonical(b))


def _first_difference(have: dict[str, Any], want: dict[str, Any]) -> str:
    for key in ("directions", "user_attrs", "system_attrs"):
        if not _same(have[key], want[key]):
            return f"its study {key.replace('_', ' ')} differ"
    for old, new in zip(have["trials"], want["trials"]):
        if not _same(old, new):
            return f"its trial {old['number']} differs"
    if len(have["trials"]) != len(want["trials"]):
        return f"it has {len(have['trials'])} trials, the import would have {len(want['trials'])}"
    return "it differs"  # not reached: the caller compared the whole documents


def _expected_doc(part: StudySnapshot, name: str, snapshot: Snapshot, max_retry: int | None) -> Any:
    """The study ``name`` would be after the import (built in memory, by the same code)."""
    memory = InMemoryStorage()
    _add_study(memory, part, name, snapshot.exported_at, _retry(max_retry))
    return _study_doc(memory, name)


def _retry(max_retry: int | None) -> RetryStaleTrial | None:
    return RetryStaleTrial(max_retry) if max_retry is None or max_retry > 0 else None


def import_snapshot(
    snapshot: Snapshot | str | os.PathLike[str],
    storage: str | StorageURL,
    study_name: str | None = None,
    *,
    max_retry: int | None = DEFAULT_MAX_RETRY,
) -> SnapshotImport:
    """Create the study of a snapshot (and its sibling studies) in a storage.

    Trial numbers, states, values, times, parameters with their distributions, user and system
    attributes (the CMA-ES state among them) and intermediate values are kept. A trial RUNNING
    at export is added as FAIL and retried as a WAITING copy (see the module docstring); WAITING
    trials stay WAITING.

    Importing the same snapshot twice is safe: a study that is already there with exactly the
    contents the import would give is left as it is. A study of that name with other contents
    is refused before anything is written.

    Args:
        snapshot: A snapshot from [`read_snapshot`][ermrl.storage.read_snapshot], or the path of a
            snapshot file.
        storage: The target storage URL (see [`open_storage`][ermrl.storage.open_storage]; a missing
            SQLite or journal file is created).
        study_name: Import the study under this name (default: its exported name); its
            siblings ``<old>.reeval`` become ``<new>.reeval``.
        max_retry: Retries of one trial at most, counting earlier retries recorded in the
            trial (``None``: no limit; 0: a RUNNING trial is only failed).

    Returns:
        What was done, with the study loaded from the target storage.

    Raises:
        SnapshotError: the file is not a valid snapshot.
        StudyNameError: ``study_name`` is not a name ermrl creates a study of.
        StudyExists: a study of a target name exists with other contents (nothing written).
        StorageError: the storage cannot be opened.
        LockTimeout: a study's lock could not be taken.

    Examples:
        >>> # ermrl study export --storage sqlite:///old.db --study-name pend --out pend.json
        >>> result = import_snapshot("pend.json", "sqlite:///new.db")
        >>> result.study.trials[-1].number
        41
    """
    if not isinstance(snapshot, Snapshot):
        snapshot = read_snapshot(snapshot)
    spec = storage if isinstance(storage, StorageURL) else parse_storage_url(storage)
    target = open_storage(spec)
    names = snapshot.target_names(study_name)
    for name in names.values():  # a new name, and the siblings it renames
        check_study_name(name)
    parts = {snapshot.study.study_name: snapshot.study, **snapshot.related}
    expected = {
        old: _expected_doc(part, names[old], snapshot, max_retry) for old, part in parts.items()
    }

    def state(old: str) -> str:
        """``absent``, ``identical``, or the refusal message."""
        new = names[old]
        if new not in study_names(target):
            return "absent"
        have = _study_doc(target, new)
        if _same(have, expected[old]):
            return "identical"
        return (
            f"study {new!r} already exists in {spec} and {_first_difference(have, expected[old])}"
            f" from the snapshot {snapshot.source}; delete it (ermrl study delete --yes) or "
            "import under another --study-name"
        )

    def refuse_if_differs(states: dict[str, str]) -> None:
        for message in states.values():
            if message not in ("absent", "identical"):
                raise StudyExists(message)

    states = {old: state(old) for old in parts}
    refuse_if_differs(states)  # before anything is written
    created: list[str] = []
    identical = [names[old] for old, s in states.items() if s == "identical"]
    interrupted: list[tuple[str, int, int | None]] = []
    for old, part in parts.items():
        if states[old] != "absent":
            continue
        with storage_lock(spec, names[old]):  # the lock workers create the study under
            now = state(old)
            refuse_if_differs({old: now})
            if now == "identical":  # another import got there first
                identical.append(names[old])
                continue
            done = _add_study(target, part, names[old], snapshot.exported_at, _retry(max_retry))
        created.append(names[old])
        interrupted += [(names[old], number, retried) for number, retried in done]
    study = optuna.load_study(study_name=names[snapshot.study.study_name], storage=target)
    n_trials = {
        name: len(target.get_all_trials(target.get_study_id_from_name(name), deepcopy=False))
        for name in names.values()
    }
    return SnapshotImport(
        study=study,
        created=tuple(created),
        identical=tuple(identical),
        interrupted=tuple(interrupted),
        n_trials=n_trials,
    )


def load_snapshot(
    path: str | os.PathLike[str] | Snapshot,
    storage_url: str,
    study_name: str | None = None,
    *,
    max_retry: int | None = DEFAULT_MAX_RETRY,
) -> optuna.Study:
    """Import a snapshot file into a storage and return the study (see
    [`import_snapshot`][ermrl.storage.import_snapshot]).

    Args:
        path: The snapshot file (or a snapshot from [`read_snapshot`][ermrl.storage.read_snapshot]).
        storage_url: The target storage.
        study_name: A new name for the study (default: its exported name).
        max_retry: Retries of one trial at most (``None``: no limit; 0: none).

    Returns:
        The study in the target storage.

    Raises:
        SnapshotError: not a valid snapshot.
        StudyExists: a study of that name exists there with other contents.
        StorageError: the storage cannot be opened.
    """
    return import_snapshot(path, storage_url, study_name, max_retry=max_retry).study


def snapshot_counts(doc: Mapping[str, Any]) -> dict[str, int]:
    """Trials per study of a snapshot document (the study first, then its siblings)."""
    related: Mapping[str, Any] = doc.get("related") or {}
    counts = {str(doc["study_name"]): len(doc["trials"])}
    counts.update({name: len(part["trials"]) for name, part in related.items()})
    return counts
