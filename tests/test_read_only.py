"""Commands that only read a study create nothing: no storage file, lock file or output folder."""

from __future__ import annotations

import time
from pathlib import Path

import optuna
import pytest

from ermrl.cli import main
from ermrl.storage import StorageError, load_study, open_storage

optuna.logging.set_verbosity(optuna.logging.WARNING)

READERS = [
    ["test", "--study-name", "X"],
    ["test-generalization", "--study-name", "X", "--env-id", "Pendulum-v1"],
    ["study", "show", "--study-name", "X"],
    ["study", "list"],
    ["study", "export", "--study-name", "X", "--out", "t.csv"],
    ["study", "fail-stale", "--study-name", "X", "--older-than", "1h"],
    ["report", "--study-name", "X"],
]


def _files(where: Path) -> list[str]:
    return sorted(str(p.relative_to(where)) for p in where.rglob("*"))


def _fails_in_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as err:
        main(argv)
    assert err.value.code == 2
    message = capsys.readouterr().err.strip()
    assert "\n" not in message
    return message


@pytest.mark.parametrize("argv", READERS, ids=lambda a: " ".join(a[:2]))
@pytest.mark.parametrize("storage", [None, "sqlite:///nosuch.db", "nosuch.log"])
def test_readers_on_a_missing_storage_fail_and_create_nothing(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    argv: list[str],
    storage: str | None,
) -> None:
    monkeypatch.chdir(tmp_path)
    extra = [] if storage is None else ["--storage", storage]
    message = _fails_in_one_line([*argv, *extra], capsys)
    name = "nosuch.log" if storage == "nosuch.log" else "nosuch.db" if storage else "ermrl.db"
    assert name in message
    assert _files(tmp_path) == []


@pytest.mark.parametrize("storage", ["sqlite:///s.db", "s.log"])
def test_readers_on_an_unknown_study_create_nothing(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    storage: str,
) -> None:
    monkeypatch.chdir(tmp_path)
    study = optuna.create_study(study_name="demo", storage=open_storage(storage))
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1)
    before = _files(tmp_path)
    for argv in READERS:
        if argv[1:2] == ["list"]:
            continue
        assert "no study named 'X'" in _fails_in_one_line([*argv, "--storage", storage], capsys)
    assert main(["study", "show", "--study-name", "demo", "--storage", storage]) == 0
    assert main(["study", "list", "--storage", storage]) == 0
    assert _files(tmp_path) == before  # no ermrl.db, no .lock, no reports/X


def test_report_refuses_a_missing_runs_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    optuna.create_study(study_name="demo", storage=open_storage("sqlite:///s.db"))
    argv = ["report", "--study-name", "demo", "--storage", "sqlite:///s.db"]
    message = _fails_in_one_line([*argv, "--runs", str(tmp_path / "missing")], capsys)
    assert "missing" in message
    assert _files(tmp_path) == ["s.db", "s.db.lock"]


@pytest.mark.parametrize("command", ["dynamics", "video"])
def test_run_folder_readers_refuse_a_missing_run(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    command: str,
) -> None:
    monkeypatch.chdir(tmp_path)
    assert "missing" in _fails_in_one_line([command, "--run", "missing"], capsys)
    assert _files(tmp_path) == []


def test_load_study_reads_only_and_workers_still_create(tmp_path: Path) -> None:
    for url in (f"sqlite:///{tmp_path}/s.db", f"{tmp_path}/s.log"):
        with pytest.raises(StorageError, match="no (SQLite database|journal file)"):
            load_study("s", url)
        assert _files(tmp_path) == []
        with pytest.raises(StorageError, match="no (SQLite database|journal file)"):
            open_storage(url, mode="write")
    open_storage(f"sqlite:///{tmp_path}/s.db")  # the default mode creates, as workers need
    open_storage(f"{tmp_path}/s.log")
    assert {"s.db", "s.log"} <= set(_files(tmp_path))


@pytest.mark.parametrize("url", ["sqlite://", "sqlite:///:memory:"])
@pytest.mark.parametrize(
    "argv",
    [
        ["evolve", "--env-id", "Pendulum-v1", "--training-steps", "256", "--n-trials", "1"],
        ["evolve-generalization", "--env-id", "Pendulum-v1", "--training-steps", "256"],
        ["study", "create", "--study-name", "X"],
        ["study", "repair"],
        *READERS,
    ],
    ids=lambda a: " ".join(a[:2]),
)
def test_an_in_memory_sqlite_storage_is_refused(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    argv: list[str],
    url: str,
) -> None:
    monkeypatch.chdir(tmp_path)
    message = _fails_in_one_line([*argv, "--storage", url], capsys)
    assert "in-memory" in message
    with pytest.raises(StorageError, match="in-memory"):
        open_storage(url)


@pytest.mark.parametrize(
    "url",
    [
        "sqlite:///file::memory:?cache=shared&uri=true",
        "sqlite:///file:memdb1?uri=true&cache=shared&mode=memory",
        "sqlite:///:MEMORY:",
    ],
)
@pytest.mark.parametrize(
    "argv",
    [
        ["evolve", "--env-id", "Pendulum-v1", "--training-steps", "256", "--n-trials", "1"],
        ["study", "create", "--study-name", "X"],
        ["study", "list"],
    ],
    ids=lambda a: " ".join(a[:2]),
)
def test_every_spelling_of_an_in_memory_sqlite_database_is_refused_writing_nothing(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    argv: list[str],
    url: str,
) -> None:
    monkeypatch.chdir(tmp_path)
    message = _fails_in_one_line([*argv, "--storage", url], capsys)
    assert "in-memory" in message
    assert _files(tmp_path) == []  # no .lock file, no run folder


def _tables(url: str) -> list[str]:
    import sqlalchemy

    from ermrl.storage import normalize_url

    engine = sqlalchemy.create_engine(normalize_url(url))
    try:
        return sorted(sqlalchemy.inspect(engine).get_table_names())
    finally:
        engine.dispose()


@pytest.mark.parametrize(
    "kind",
    [
        "sqlite",
        pytest.param("postgresql", marks=pytest.mark.services),
        pytest.param("mysql", marks=pytest.mark.services),
    ],
)
def test_readers_on_an_empty_database_leave_it_empty(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    request: pytest.FixtureRequest,
    kind: str,
) -> None:
    """A 0-byte SQLite file, or a server database without tables: every reader (and delete)
    says in one line that it holds no ermrl study, and creates no Optuna schema there."""
    monkeypatch.chdir(tmp_path)
    if kind == "sqlite":
        (tmp_path / "empty.db").touch()
        url = "sqlite:///empty.db"
    else:
        url = request.getfixturevalue({"postgresql": "postgres_url", "mysql": "mysql_url"}[kind])
    for argv in [*READERS, ["study", "delete", "--study-name", "X", "--yes"]]:
        message = _fails_in_one_line([*argv, "--storage", url], capsys)
        assert "holds no ermrl study" in message, argv
        if kind == "sqlite":
            assert _files(tmp_path) == ["empty.db"], argv
            assert (tmp_path / "empty.db").stat().st_size == 0, argv
        else:
            assert _tables(url) == [], argv
    with pytest.raises(StorageError, match="holds no ermrl study"):
        load_study("X", url)
    open_storage(url)  # workers still create the schema
    assert "studies" in _tables(url)


def test_a_reader_waits_for_a_schema_being_created_and_never_stamps_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A reader opened between a worker's CREATE TABLE and its Alembic stamp (a periodic
    snapshot as an evolution starts) used to stamp the revision itself, outside the schema
    lock, and the worker then failed on 'UNIQUE constraint failed: alembic_version'. It now
    waits for the worker's stamp, and says so in one line when none comes."""
    import threading

    import sqlalchemy
    from optuna.storages._rdb import models

    import ermrl.storage._open as storage_open

    url = f"sqlite:///{tmp_path / 'half.db'}"
    engine = sqlalchemy.create_engine(url)
    models.BaseModel.metadata.create_all(engine)  # a worker's CREATE TABLE, not stamped yet
    monkeypatch.setattr(storage_open, "SCHEMA_WAIT_S", 0.5)
    with pytest.raises(StorageError, match="half-made schema"):
        open_storage(url, mode="read")
    with engine.connect() as connection:
        assert not sqlalchemy.inspect(connection).has_table("alembic_version")  # left as it was

    def worker_finishes() -> None:  # the worker's stamp, as RDBStorage writes it
        time.sleep(0.5)
        optuna.storages.RDBStorage(url)

    monkeypatch.setattr(storage_open, "SCHEMA_WAIT_S", 30)
    worker = threading.Thread(target=worker_finishes)
    worker.start()
    open_storage(url, mode="read")  # waits for the stamp, then opens
    worker.join()
    with engine.connect() as connection:
        rows = connection.execute(sqlalchemy.text("SELECT * FROM alembic_version")).all()
    assert len(rows) == 1
    engine.dispose()
