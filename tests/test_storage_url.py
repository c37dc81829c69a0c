"""ermrl.storage._url: storage URLs parsed once into a frozen :class:`StorageURL`."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import optuna
import pytest

import ermrl.storage
from ermrl.storage import (
    LockTimeout,
    StorageError,
    StorageKind,
    StorageURL,
    load_study,
    normalize_url,
    open_storage,
    parse_storage_url,
    storage_kind,
    storage_lock,
    storage_url,
    study_lock,
)
from ermrl.storage import _url as url_module
from ermrl.storage._locks import journal_path, redis_parts, sqlite_path

optuna.logging.set_verbosity(optuna.logging.WARNING)


@pytest.mark.parametrize(
    ("raw", "kind", "url", "path", "prefix"),
    [
        ("sqlite:///x.db", "sqlite", "sqlite:///x.db", Path("x.db"), ""),
        (
            "sqlite:////tmp/a.db?timeout=5",
            "sqlite",
            "sqlite:////tmp/a.db?timeout=5",
            Path("/tmp/a.db"),
            "",
        ),
        ("journal:///tmp/x.log", "journal", "journal:///tmp/x.log", Path("/tmp/x.log"), ""),
        ("journal://~/x.log", "journal", "journal://~/x.log", Path.home() / "x.log", ""),
        ("studies.log", "journal", "studies.log", Path("studies.log"), ""),
        ("redis://localhost:6379", "redis", "redis://localhost:6379", None, ""),
        ("redis://h:6379/0?prefix=a", "redis", "redis://h:6379/0", None, "a"),
        (
            "redis://h:6379/0?prefix=a&ssl_cert_reqs=none",
            "redis",
            "redis://h:6379/0?ssl_cert_reqs=none",
            None,
            "a",
        ),
        ("postgresql+psycopg2://u@h/db", "postgresql", "postgresql+psycopg2://u@h/db", None, ""),
        ("mysql+pymysql://root@h/db", "mysql", "mysql+pymysql://root@h/db", None, ""),
    ],
)
def test_each_kind_is_parsed_into_its_parts(
    raw: str, kind: StorageKind, url: str, path: Path | None, prefix: str
) -> None:
    spec = parse_storage_url(raw)
    assert spec == StorageURL(raw=raw, kind=kind, url=url, path=path, prefix=prefix)
    assert str(spec) == raw
    assert spec.is_rdb == (kind in ("sqlite", "postgresql", "mysql"))


@pytest.mark.parametrize(
    ("raw", "with_driver", "without_driver"),
    [
        ("postgres://u@h/db", "postgresql://u@h/db", "postgresql+psycopg2://u@h/db"),
        ("postgresql://u@h/db", "postgresql://u@h/db", "postgresql+psycopg2://u@h/db"),
        ("POSTGRES://u@h/db", "postgresql://u@h/db", "postgresql+psycopg2://u@h/db"),
        (
            "postgres+psycopg2://u@h/db",
            "postgresql+psycopg2://u@h/db",
            "postgresql+psycopg2://u@h/db",
        ),
        ("mysql://root@h/db", "mysql://root@h/db", "mysql+pymysql://root@h/db"),
        ("mysql+mysqldb://root@h/db", "mysql+mysqldb://root@h/db", "mysql+mysqldb://root@h/db"),
    ],
)
@pytest.mark.parametrize("installed", [True, False], ids=["default-driver", "no-default-driver"])
def test_server_urls_get_the_sqlalchemy_dialect_and_an_installed_driver(
    monkeypatch: pytest.MonkeyPatch,
    raw: str,
    with_driver: str,
    without_driver: str,
    installed: bool,
) -> None:
    # psycopg 3 (SQLAlchemy's default for postgresql://) or mysqlclient (for mysql://) present?
    monkeypatch.setattr(url_module, "_installed", lambda module: installed)
    spec = parse_storage_url(raw)
    assert spec.url == (with_driver if installed else without_driver)
    assert spec.path is None and spec.prefix == "" and spec.raw == raw
    assert normalize_url(raw) == spec.url


def test_the_value_is_frozen_hashable_and_round_trips() -> None:
    spec = parse_storage_url("redis://h:6379/0?prefix=a")
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.kind = "sqlite"  # type: ignore[misc]  # assigning is what is tested
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.prefix = "b"  # type: ignore[misc]  # assigning is what is tested
    assert parse_storage_url(spec.raw) == spec
    assert parse_storage_url(str(spec)) == spec
    assert {spec, parse_storage_url(spec.raw)} == {spec}


UNSUPPORTED = (
    "unsupported storage URL {url!r}; use sqlite:///file.db, postgresql://..., mysql://..., "
    "journal:///file.log (or file.log) or redis://host:port"
)


@pytest.mark.parametrize("url", ["ftp://x", "x.db", "", "http://h/x.log", "journal"])
def test_an_unsupported_url_gives_todays_one_line_error(url: str) -> None:
    with pytest.raises(StorageError) as caught:
        parse_storage_url(url)
    assert str(caught.value) == UNSUPPORTED.format(url=url)
    with pytest.raises(StorageError, match="^unsupported storage URL"):
        storage_kind(url)
    assert normalize_url(url) == url  # documented: other URLs are returned unchanged


IN_MEMORY = [
    "sqlite://",
    "sqlite:///",
    "sqlite:///:memory:",
    "sqlite:///?mode=ro",
    # However spelled: case, percent-encoding, SQLite URI filenames, query order, memdb VFS.
    "SQLITE:///:MEMORY:",
    "sqlite:///%3Amemory%3A",
    "sqlite:///file::memory:?cache=shared&uri=true",
    "sqlite:///FILE::Memory:?uri=true",
    "sqlite:///file:memdb1?mode=memory&cache=shared&uri=true",
    "sqlite:///file:memdb1?uri=true&cache=shared&Mode=MEMORY",
    "sqlite+pysqlite:///file:memdb1?mode=memory&uri=true",
    "sqlite:///file:/x.db?vfs=memdb&uri=true",
]


@pytest.mark.parametrize("url", IN_MEMORY)
def test_an_in_memory_sqlite_database_is_refused_in_one_line(url: str) -> None:
    with pytest.raises(StorageError, match="in-memory SQLite database") as caught:
        parse_storage_url(url)
    assert "\n" not in str(caught.value)
    assert str(caught.value).startswith(f"{url} is an in-memory")
    assert sqlite_path(url) is None


@pytest.mark.parametrize(
    ("url", "message"),
    [
        # In memory behind two layers of percent-escapes (SQLAlchemy decodes one, SQLite the
        # other): they were accepted, and the trials went to a file of another name.
        ("sqlite:///%253Amemory%253A", "is an in-memory SQLite database"),
        ("sqlite:///file:x.db?uri=true&mode=memor%2579", "is an in-memory SQLite database"),
        ("sqlite:///file:x.db?uri=true&vfs=%256Demdb", "is an in-memory SQLite database"),
        ("sqlite:///file:x.db?mode%253Dmemory&uri=true", "is an in-memory SQLite database"),
        # A file SQLite would name otherwise than the path ermrl reads from the URL.
        ("sqlite:///file:%3A?uri=true", "percent-escapes"),
        ("sqlite:///my%20study.db", "percent-escapes"),
        ("sqlite:///file:x.db?uri=true", "SQLite URI filename"),
    ],
)
def test_a_sqlite_url_whose_file_sqlite_would_name_otherwise_is_refused(
    url: str, message: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from ermrl.storage import open_storage

    monkeypatch.chdir(tmp_path)
    with pytest.raises(StorageError, match=message) as caught:
        parse_storage_url(url)
    assert "\n" not in str(caught.value) and str(caught.value).startswith(url)
    with pytest.raises(StorageError):
        open_storage(url)
    assert list(tmp_path.iterdir()) == []  # no database, no lock file


@pytest.mark.parametrize(
    "raw",
    [
        "sqlite:///x.db",
        "journal:///tmp/x.log",
        "x.log",
        "redis://h:1/2?prefix=p",
        "postgres://u@h/d",
    ],
)
def test_the_older_helpers_are_views_of_the_parsed_value(raw: str) -> None:
    spec = parse_storage_url(raw)
    assert storage_kind(raw) == spec.kind
    if spec.kind == "sqlite":
        assert sqlite_path(raw) == spec.path
    if spec.kind == "journal":
        assert journal_path(raw) == spec.path
    if spec.kind == "redis":
        assert redis_parts(raw) == (spec.url, spec.prefix)
    assert normalize_url(raw) == (spec.url if spec.is_rdb else raw)


def test_storage_opened_from_a_parsed_value_remembers_it(tmp_path: Path) -> None:
    spec = parse_storage_url(f"sqlite:///{tmp_path}/s.db")
    storage = open_storage(spec)
    assert storage_url(storage) == spec.raw
    optuna.create_study(study_name="s", storage=storage)
    study = load_study("s", spec)  # a parsed value also opens read-only
    assert storage_url(study._storage) == spec.raw
    assert (tmp_path / "s.db.lock").exists()  # the schema lock sits next to spec.path
    with pytest.raises(StorageError, match="no SQLite database"):
        load_study("s", parse_storage_url(f"sqlite:///{tmp_path}/other.db"))


def test_a_missing_relative_sqlite_file_is_named_with_its_full_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Run from another folder, ``sqlite:///ermrl.db`` is looked up there: the line names the
    file it looked for and the folder it was relative to."""
    from ermrl.storage import repair_sqlite

    monkeypatch.chdir(tmp_path)
    expected = (
        f"no SQLite database {tmp_path / 'ermrl.db'} (ermrl.db is relative to the current "
        f"folder {tmp_path}; check --storage)"
    )
    with pytest.raises(StorageError) as err:
        load_study("s", "sqlite:///ermrl.db")
    assert str(err.value) == expected
    with pytest.raises(StorageError) as err:
        repair_sqlite("sqlite:///ermrl.db")
    assert str(err.value) == expected
    with pytest.raises(StorageError) as err:
        load_study("s", f"sqlite:///{tmp_path}/other.db")
    assert str(err.value) == f"no SQLite database {tmp_path / 'other.db'} (check --storage)"


@pytest.mark.parametrize(
    "fresh_storage",
    [
        "sqlite",
        pytest.param("postgresql", marks=pytest.mark.services),
        pytest.param("mysql", marks=pytest.mark.services),
        pytest.param("redis", marks=pytest.mark.services),
    ],
    indirect=True,
)
def test_study_lock_and_storage_lock_of_the_parsed_value_are_one_lock(
    fresh_storage: str,
) -> None:
    spec = parse_storage_url(fresh_storage)
    study = optuna.create_study(study_name="s", storage=open_storage(spec))
    with study_lock(study, timeout=1) as locked:
        assert locked
        with pytest.raises(LockTimeout), storage_lock(spec, "s", timeout=1):
            pass
        with pytest.raises(LockTimeout), storage_lock(fresh_storage, "s", timeout=1):
            pass
    with storage_lock(spec, "s", timeout=1):  # released
        pass


def test_no_module_of_ermrl_storage_imports_one_that_imports_it_back() -> None:
    """The import graph of ermrl/storage (module level and inside functions) has no cycle."""
    package = Path(ermrl.storage.__file__).parent
    names = {
        ("ermrl.storage" if p.stem == "__init__" else f"ermrl.storage.{p.stem}"): p
        for p in package.glob("*.py")
    }
    graph: dict[str, set[str]] = {}
    for name, path in names.items():
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                assert node.level == 0, f"{path.name}: use absolute imports"
                base = node.module or ""
                targets |= {base, *(f"{base}.{alias.name}" for alias in node.names)}
            elif isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
        graph[name] = {t for t in targets if t in names and t != name}
    assert graph["ermrl.storage._url"] == set()  # the leaf every other module may import

    def reaches(start: str, goal: str, seen: frozenset[str] = frozenset()) -> bool:
        return any(
            step == goal or (step not in seen and reaches(step, goal, seen | {step}))
            for step in graph[start]
        )

    cycles = sorted(name for name in graph if reaches(name, name))
    assert cycles == [], f"import cycles through {cycles}: {graph}"
