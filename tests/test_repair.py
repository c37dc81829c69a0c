"""Damaged storages: unreadable journal records (file or Redis) are set aside by a repair, a record
is never glued to a partial one, and a damaged journal or database stops a command in one line."""

from __future__ import annotations

import errno
import json
import os
import random
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Literal

import optuna
import pytest
import redis
from optuna.trial import TrialState

from ermrl.cli._study import study_main
from ermrl.storage import StorageError, open_storage, repair_journal, repair_sqlite, torn_tail

optuna.logging.set_verbosity(optuna.logging.WARNING)

ROOT = Path(__file__).resolve().parents[1]


def _journal_study(path: Path, n_trials: int = 3) -> list[float]:
    """A journal study ``s`` with ``n_trials`` complete trials of a stub objective."""
    study = optuna.create_study(study_name="s", storage=open_storage(str(path)))
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=n_trials)
    return [t.value for t in study.trials]


def _values(path: Path) -> list[float]:
    study = optuna.load_study(study_name="s", storage=open_storage(str(path)))
    return [t.value for t in study.get_trials(states=(TrialState.COMPLETE,))]


def _asides(path: Path) -> list[Path]:
    return sorted(path.parent.glob(f"{path.name}.torn-*"))


def test_a_cut_last_line_is_set_aside_and_the_study_goes_on(tmp_path: Path) -> None:
    path = tmp_path / "s.log"
    values = _journal_study(path)
    size = path.stat().st_size
    with open(path, "r+b") as f:  # cut the last record short, as a full disk does
        f.truncate(size - 7)
    assert torn_tail(path) > 0

    # The next worker appends its records after the complete ones, not after the partial one.
    study = optuna.load_study(study_name="s", storage=open_storage(str(path)))
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    assert torn_tail(path) == 0
    for line in path.read_bytes().splitlines():
        json.loads(line)
    (aside,) = _asides(path)
    assert not aside.read_bytes().endswith(b"\n") and len(aside.read_bytes()) > 0
    # The first trials whose records were complete are all still there, and the new ones.
    again = _values(path)
    assert len(again) >= len(values) - 1 + 2
    assert again[: len(values) - 1] == values[: len(values) - 1]


def test_an_intact_journal_is_left_alone(tmp_path: Path) -> None:
    path = tmp_path / "s.log"
    _journal_study(path, n_trials=1)
    before = path.read_bytes()
    assert repair_journal(path) is None
    assert path.read_bytes() == before and not _asides(path)


def test_study_repair_command(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "s.log"
    _journal_study(path, n_trials=2)
    assert study_main(["repair", "--storage", f"journal://{path}"]) == 0
    assert "intact" in capsys.readouterr().out
    with open(path, "ab") as f:
        f.write(b'{"op_code":5,"worker_id":"x","trial_id":1,"s')
    assert study_main(["repair", "--storage", str(path)]) == 0
    (aside,) = _asides(path)
    out = capsys.readouterr().out
    assert str(aside) in out and "partial" in out
    assert aside.read_bytes() == b'{"op_code":5,"worker_id":"x","trial_id":1,"s'
    assert len(_values(path)) == 2
    with pytest.raises(SystemExit) as err:
        study_main(["repair", "--storage", f"sqlite:///{tmp_path}/s.db"])
    assert err.value.code == 2 and "no SQLite database" in capsys.readouterr().err
    assert not (tmp_path / "s.db").exists()
    with pytest.raises(SystemExit) as err:
        study_main(["repair", "--storage", "postgresql://nobody@127.0.0.1:1/none"])
    assert err.value.code == 2 and "only journals and SQLite" in capsys.readouterr().err


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 1 MiB tmpfs (needs root and ``mount``)."""
    where = tmp_path / f"disk-{uuid.uuid4().hex[:6]}"
    where.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(where)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs to fill: {done.stderr.strip() or done.returncode}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def _fill(path: Path) -> None:
    """Write to ``path`` until the file system is full."""
    with open(path, "wb", buffering=0) as f:
        block = b"\0" * 4096
        while True:
            try:
                f.write(block)
            except OSError as err:
                assert err.errno == errno.ENOSPC
                break
        for size in (512, 64, 1):
            while True:
                try:
                    f.write(b"\0" * size)
                except OSError:
                    break


def test_a_full_disk_during_a_write_tears_the_journal_and_the_next_worker_repairs_it(
    small_disk: Path,
) -> None:
    path = small_disk / "s.log"
    values = _journal_study(path, n_trials=3)
    study = optuna.load_study(study_name="s", storage=open_storage(str(path)))
    trial = study.ask()
    while path.stat().st_size % 4096 in (0, 4095):  # leave room in the last page: a torn write
        trial.set_user_attr("pad", "x" * 10)
    _fill(small_disk / "filler")
    with pytest.raises(OSError) as err:
        trial.set_user_attr("big", "y" * 20000)  # a worker records a large attribute
    assert err.value.errno == errno.ENOSPC
    assert torn_tail(path) > 0  # the record stopped mid-way

    # While the disk is full, the partial record cannot be set aside: a one-line error.
    with pytest.raises(Exception, match="ermrl study repair"):
        open_storage(str(path))
    assert torn_tail(path) > 0 and not _asides(path)

    os.remove(small_disk / "filler")
    study = optuna.load_study(study_name="s", storage=open_storage(str(path)))
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1)
    assert torn_tail(path) == 0 and len(_asides(path)) == 1
    assert _values(path)[:3] == values
    assert len(_values(path)) == 4


# -- a damaged SQLite database --------------------------------------------------------------------


def _ermrl(*args: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", "import sys; from ermrl.cli import main; sys.exit(main())", *args],
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.fixture(scope="module")
def damaged_db(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of a small study database with 4 KiB of random bytes written into its middle."""
    where = tmp_path_factory.mktemp("damaged")
    path = where / "s.db"
    study = optuna.create_study(study_name="demo", storage=f"sqlite:///{path}")

    def objective(trial: optuna.Trial) -> float:
        trial.set_user_attr("returns", list(range(50)))
        return trial.suggest_float("x", 0, 1)

    study.optimize(objective, n_trials=40)
    del study
    middle = path.stat().st_size // 2 // 4096 * 4096
    with open(path, "r+b") as f:
        f.seek(middle)
        f.write(random.Random(0).randbytes(4096))
    return path


@pytest.mark.parametrize(
    "command",
    [
        ["study", "show", "--study-name", "demo"],
        ["study", "list"],
        ["evolve", "--env-id", "Pendulum-v1", "--study-name", "demo", "--training-steps", "256"],
    ],
    ids=["show", "list", "evolve"],
)
def test_a_damaged_sqlite_database_is_one_line_and_exit_2(
    damaged_db: Path, command: list[str]
) -> None:
    done = _ermrl(*command, "--storage", f"sqlite:///{damaged_db}", cwd=damaged_db.parent)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr
    assert "is damaged" in lines[0] and '".recover"' in lines[0] and "backup" in lines[0]


# A writer that spills its cache mid-transaction (2 pages) and is killed there leaves a hot
# rollback journal: the database file holds half a transaction that only the journal undoes.
_DYING_WRITER = """
import sqlite3, sys, time
con = sqlite3.connect(sys.argv[1], isolation_level=None)
con.execute("PRAGMA cache_size=2")
con.execute("BEGIN")
for i in range(2000):
    con.execute(
        "INSERT INTO study_user_attributes (study_id, key, value_json) VALUES (1, ?, ?)",
        (f"half-written {i}", '"' + "x" * 200 + '"'),
    )
print("mid-transaction", flush=True)
time.sleep(60)
"""


@pytest.fixture
def hot_journal_db(tmp_path: Path) -> Path:
    """A 2-trial SQLite study whose writer was killed (SIGKILL) mid-transaction."""
    path = tmp_path / "s.db"
    study = optuna.create_study(study_name="s", storage=f"sqlite:///{path}")
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    del study
    writer = subprocess.Popen(
        [sys.executable, "-c", _DYING_WRITER, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert writer.stdout is not None and writer.stdout.readline() == "mid-transaction\n"
    finally:
        writer.kill()  # SIGKILL: no rollback, no cleanup
        writer.wait()
    journal = Path(f"{path}-journal")
    assert journal.stat().st_size > 0
    return path


def test_a_hot_journal_is_rolled_back_not_called_damaged(
    hot_journal_db: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{hot_journal_db}"
    assert study_main(["show", "--storage", url, "--study-name", "s"]) == 0
    assert "damaged" not in capsys.readouterr().err
    assert not Path(f"{hot_journal_db}-journal").exists()
    assert not Path(f"{hot_journal_db}.lock").exists()  # a reader creates nothing
    study = optuna.load_study(study_name="s", storage=url)
    assert len(study.get_trials(states=(TrialState.COMPLETE,))) == 2
    assert study.user_attrs == {}  # the half-written transaction is undone


def test_study_repair_rolls_back_a_hot_journal(
    hot_journal_db: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{hot_journal_db}"
    assert study_main(["repair", "--storage", url]) == 0
    assert "rolled back the transaction a writer left unfinished" in capsys.readouterr().out
    assert not Path(f"{hot_journal_db}-journal").exists()
    assert study_main(["repair", "--storage", url]) == 0
    assert "intact" in capsys.readouterr().out
    study = optuna.load_study(study_name="s", storage=open_storage(url, mode="write"))
    assert len(study.get_trials(states=(TrialState.COMPLETE,))) == 2


NOT_JOURNALS = {
    "text": b"2026-11-25 15:00:01 INFO server started\nsecond line\n",
    "one line, no newline": b"x" * 111,
    "json lines": b'{"level":"info","msg":"hi"}\n{"op_code":0}\n',
    "binary": bytes(range(256)),
}


@pytest.mark.parametrize("content", NOT_JOURNALS.values(), ids=NOT_JOURNALS)
@pytest.mark.parametrize(
    "command",
    [
        ["study", "repair"],
        ["study", "list"],
        ["study", "create", "--study-name", "X"],
        ["evolve", "--env-id", "Pendulum-v1", "--training-steps", "256", "--n-trials", "1"],
    ],
    ids=lambda c: " ".join(c[:2]),
)
def test_a_file_that_is_not_a_journal_is_refused_untouched(
    tmp_path: Path, content: bytes, command: list[str]
) -> None:
    path = tmp_path / "some.log"
    path.write_bytes(content)
    done = _ermrl(*command, "--storage", str(path), cwd=tmp_path)
    assert done.returncode == 2, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "not an Optuna journal" in lines[0], done.stderr
    assert path.read_bytes() == content
    assert sorted(p.name for p in tmp_path.iterdir()) == ["some.log"]


def test_a_journal_whose_first_record_was_cut_short_is_still_repaired(tmp_path: Path) -> None:
    path = tmp_path / "s.log"
    path.write_bytes(b'{"op_code":0,"worker_id":"a-0","study_na')
    assert repair_journal(path) is not None
    assert path.read_bytes() == b""
    _journal_study(path, n_trials=1)


@pytest.mark.parametrize("mode", ["create", "write", "read"])
def test_a_storage_path_that_is_a_directory_says_so_and_leaves_no_lock(
    tmp_path: Path, mode: Literal["create", "write", "read"]
) -> None:
    for url in (f"{tmp_path}/d.log", f"sqlite:///{tmp_path}/d.db"):
        where = Path(url.removeprefix("sqlite:///"))
        where.mkdir()
        with pytest.raises(StorageError, match="is a directory") as caught:
            open_storage(url, mode=mode)
        assert "free some space" not in str(caught.value) and "\n" not in str(caught.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.db", "d.log"]


# -- unreadable records anywhere in a journal file -----------------------------------------------

_TORN = b'{"op_code":8,"worker_id":"other-0","trial_id":0,"user_attr":{"k'


def _say_set_aside(out: str, n: int) -> None:
    lines = out.strip().splitlines()
    assert len(lines) == 1 and f"set aside {n} unreadable record" in lines[0], out


def test_a_torn_record_of_another_process_is_never_glued_to_the_next_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "s.log"
    study = optuna.create_study(study_name="s", storage=open_storage(str(path)))
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    with open(path, "ab") as f:  # another process dies mid-write while this worker runs
        f.write(_TORN)

    # The worker's next record starts on a line of its own; its next read stops in one line.
    with pytest.raises(StorageError, match="ermrl study repair") as caught:
        study.set_user_attr("after", 1)
    assert "\n" not in str(caught.value)
    assert _TORN + b"\n" in path.read_bytes().splitlines(keepends=True)

    assert study_main(["repair", "--storage", str(path)]) == 0
    _say_set_aside(capsys.readouterr().out, 1)
    (aside,) = _asides(path)
    assert aside.read_bytes() == _TORN + b"\n"
    for line in path.read_bytes().splitlines():
        json.loads(line)
    again = optuna.load_study(study_name="s", storage=open_storage(str(path)))
    assert again.user_attrs == {"after": 1} and len(_values(path)) == 2
    again.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1)
    assert len(_values(path)) == 3


def _garbage_last_line(lines: list[bytes]) -> list[bytes]:
    return [*lines, b"not a record\n"]


def _garbage_middle_line(lines: list[bytes]) -> list[bytes]:
    return [*lines[:4], b'{"op_code":5,"worker_id":\x00\xff\n', *lines[4:]]


def _glued_records(lines: list[bytes]) -> list[bytes]:
    """What an older ermrl wrote: a torn record, the next one glued onto it."""
    return [*lines[:-1], _TORN + lines[-1]]


def _json_but_no_record(lines: list[bytes]) -> list[bytes]:
    return [*lines[:3], b'{"level":"info"}\n', *lines[3:]]


DAMAGE = {
    "garbage last line": (_garbage_last_line, b"not a record\n"),
    "garbage middle line": (_garbage_middle_line, b'{"op_code":5,"worker_id":\x00\xff\n'),
    "glued records": (_glued_records, _TORN + b"\n"),
    "json but no record": (_json_but_no_record, b'{"level":"info"}\n'),
}


def _damaged_journal(
    tmp_path: Path, damage: tuple[object, bytes]
) -> tuple[Path, list[bytes], list[float]]:
    """A 3-trial journal damaged by ``damage``; its path, intact lines and trial values."""
    damage_fn, _ = damage
    path = tmp_path / "s.log"
    values = _journal_study(path, n_trials=3)
    lines = path.read_bytes().splitlines(keepends=True)
    path.write_bytes(b"".join(damage_fn(lines)))  # type: ignore[operator]
    return path, lines, values


@pytest.mark.parametrize("damage", DAMAGE.values(), ids=DAMAGE)
def test_study_repair_sets_aside_unreadable_records_anywhere(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], damage: tuple[object, bytes]
) -> None:
    _, set_aside = damage
    path, lines, values = _damaged_journal(tmp_path, damage)
    assert study_main(["repair", "--storage", f"journal://{path}"]) == 0
    _say_set_aside(capsys.readouterr().out, 1)
    (aside,) = _asides(path)
    assert aside.read_bytes() == set_aside
    assert path.read_bytes().splitlines(keepends=True) == lines  # every record is kept
    assert _values(path) == values
    assert study_main(["repair", "--storage", str(path)]) == 0
    assert "intact" in capsys.readouterr().out


@pytest.mark.parametrize("damage", DAMAGE.values(), ids=DAMAGE)
def test_a_worker_that_resumes_sets_aside_unreadable_records_first(
    tmp_path: Path, damage: tuple[object, bytes]
) -> None:
    path, _, values = _damaged_journal(tmp_path, damage)
    study = optuna.load_study(study_name="s", storage=open_storage(str(path)))
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1)
    assert _values(path)[:3] == values and len(_values(path)) == 4
    assert len(_asides(path)) == 1


def _glue_after_trial_creation(lines: list[bytes]) -> list[bytes]:
    """``sed -i '/"op_code":4/{N;s/\\n//}'``: each trial's creation record and the record after
    it on one line (a newline lost)."""
    glued: list[bytes] = []
    rest = iter(lines)
    for line in rest:
        glued.append(line[:-1] + next(rest, b"") if b'"op_code":4' in line else line)
    return glued


@pytest.mark.parametrize("how", ["study repair", "a worker opens it"])
def test_records_glued_together_are_split_and_every_trial_is_kept(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], how: str
) -> None:
    path = tmp_path / "s.log"
    values = _journal_study(path, n_trials=2)
    lines = path.read_bytes().splitlines(keepends=True)
    glued = _glue_after_trial_creation(lines)
    assert len(glued) == len(lines) - 2
    path.write_bytes(b"".join(glued))
    if how == "study repair":
        assert study_main(["repair", "--storage", str(path)]) == 0
        out = capsys.readouterr().out.strip().splitlines()
        assert len(out) == 1 and "split 2 lines of glued records" in out[0], out
        assert "set aside" not in out[0]
    else:
        open_storage(str(path), mode="write")
    assert path.read_bytes().splitlines(keepends=True) == lines
    assert not _asides(path)  # nothing was unreadable
    assert _values(path) == values and len(values) == 2


def test_only_what_cannot_be_read_is_set_aside_from_a_glued_line(tmp_path: Path) -> None:
    path = tmp_path / "s.log"
    values = _journal_study(path, n_trials=2)
    lines = path.read_bytes().splitlines(keepends=True)
    i = next(i for i, line in enumerate(lines) if b'"op_code":4' in line)
    garbage = b'{"op_code":5,"worker_id":"x","tri'
    damaged = [*lines[:i], lines[i][:-1] + garbage + b"  " + lines[i + 1], *lines[i + 2 :]]
    path.write_bytes(b"".join(damaged))
    repair = repair_journal(path)
    assert repair is not None and (repair.n_records, repair.n_split) == (1, 1)
    (aside,) = _asides(path)
    assert aside.read_bytes() == garbage + b"  \n"  # the bytes up to the next record
    assert path.read_bytes().splitlines(keepends=True) == lines
    assert _values(path) == values


def test_a_journal_with_an_unreadable_middle_record_is_one_line_and_exit_2(
    tmp_path: Path,
) -> None:
    path = tmp_path / "s.log"
    _journal_study(path, n_trials=2)
    lines = path.read_bytes().splitlines(keepends=True)
    path.write_bytes(b"".join(_garbage_middle_line(lines)))
    done = _ermrl("study", "show", "--study-name", "s", "--storage", str(path), cwd=tmp_path)
    assert done.returncode == 2, done.stdout + done.stderr
    lines_err = done.stderr.strip().splitlines()
    assert len(lines_err) == 1 and "Traceback" not in done.stderr
    assert f"ermrl study repair --storage {path}" in lines_err[0]


# -- Redis journals --------------------------------------------------------------------------------


def _redis_records(url: str) -> tuple[redis.Redis, str, list[bytes]]:
    """A client on the journal's database, its key prefix and its records in order."""
    from ermrl.storage import parse_storage_url

    spec = parse_storage_url(url)
    client = redis.Redis.from_url(spec.url)
    last = int(client.get(f"{spec.prefix}:log_number") or -1)
    records = [client.get(f"{spec.prefix}:log:{n}") for n in range(last + 1)]
    assert all(r is not None for r in records)
    return client, spec.prefix, [r for r in records if r is not None]


def _rewrite(client: redis.Redis, prefix: str, records: list[bytes | None], last: int) -> None:
    for key in client.scan_iter(f"{prefix}:log:*"):
        client.delete(key)
    for n, record in enumerate(records):
        if record is not None:
            client.set(f"{prefix}:log:{n}", record)
    client.set(f"{prefix}:log_number", last)


_Damaged = tuple[list[bytes | None], int, list[bytes]]  # records, log_number, set aside
_TORN_REDIS = b'{"op_code": 4, "worker_id": "x", "st'
_GARBAGE = b"\x00garbage"


def _redis_torn_last(records: list[bytes]) -> _Damaged:
    return [*records, _TORN_REDIS], len(records), [_TORN_REDIS]


def _redis_garbage_middle(records: list[bytes]) -> _Damaged:
    return [*records[:3], _GARBAGE, *records[3:]], len(records), [_GARBAGE]


def _redis_log_number_ahead(records: list[bytes]) -> _Damaged:
    return list(records), len(records) + 4, []


def _redis_missing_and_ahead(records: list[bytes]) -> _Damaged:
    """A record number never written (a lost write), a record after it, then nothing."""
    after = b'{"op_code": 2, "worker_id": "x", "study_id": 0, "user_attr": {"after": 1}}'
    return [*records, None, after], len(records) + 3, []


REDIS_DAMAGE = {
    "torn last record": _redis_torn_last,
    "garbage middle record": _redis_garbage_middle,
    "log_number ahead": _redis_log_number_ahead,
    "missing record": _redis_missing_and_ahead,
}


@pytest.mark.services
@pytest.mark.parametrize("damage", REDIS_DAMAGE.values(), ids=REDIS_DAMAGE)
def test_a_damaged_redis_journal_is_one_line_then_study_repair_fixes_it(
    redis_url: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    damage: object,
) -> None:
    study = optuna.create_study(study_name="s", storage=open_storage(redis_url))
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=3)
    values = [t.value for t in study.trials]
    client, prefix, records = _redis_records(redis_url)
    damaged, last, aside = damage(records)  # type: ignore[operator]
    _rewrite(client, prefix, damaged, last)

    # Every command stops in one line (none hangs), and says how to repair.
    for command in (["study", "list"], ["study", "show", "--study-name", "s"]):
        done = _ermrl(*command, "--storage", redis_url, cwd=tmp_path, timeout=60)
        assert done.returncode == 2, done.stdout + done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
        assert f"ermrl study repair --storage {redis_url}" in lines[0]

    assert study_main(["repair", "--storage", redis_url]) == 0
    out = capsys.readouterr().out
    assert len(out.strip().splitlines()) == 1 and redis_url in out, out
    if aside:
        assert f"set aside {len(aside)} unreadable record" in out
        (side,) = client.keys(f"{prefix}:torn-*")
        assert sorted(client.hgetall(side).values()) == aside
    else:
        assert not client.keys(f"{prefix}:torn-*")
    n_kept = len([d for d in damaged if d is not None]) - len(aside)
    assert int(client.get(f"{prefix}:log_number") or -2) == n_kept - 1
    assert study_main(["repair", "--storage", redis_url]) == 0
    assert "intact" in capsys.readouterr().out

    again = optuna.load_study(study_name="s", storage=open_storage(redis_url))
    assert [t.value for t in again.trials] == values
    again.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1)
    assert len(again.get_trials(states=(TrialState.COMPLETE,))) == 4
    client.close()


@pytest.mark.parametrize("when", ["creating", "running"])
def test_evolve_on_a_full_disk_under_its_journal(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], when: str
) -> None:
    """A journal file on a full disk (a real tmpfs, filled up): one line and exit 2, whether the
    study cannot be created or a running worker cannot append; finished trials are kept."""
    from ermrl.cli._evolve import evolve_main
    from tests.test_bad_input import FAST, _fill, _tmpfs

    with _tmpfs(tmp_path / "mnt", "size=256k") as folder:
        journal = folder / "j.log"
        argv = ["--env-id", "Pendulum-v1", *FAST, "--storage", str(journal), "--quiet"]
        if when == "running":
            assert evolve_main([*argv, "--n-trials", "1"]) == 0
            before = journal.read_bytes()
        _fill(folder)
        with pytest.raises(SystemExit) as exc:
            evolve_main([*argv, "--n-trials", "2"])
        assert exc.value.code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1, err
        assert f"cannot write to {journal}" in err and "No space left on device" in err
        if when == "running":
            assert journal.read_bytes().startswith(before)  # the finished trial is kept
            assert "finished trials are kept" in err
        else:
            assert "was not created" in err


# A live writer in its commit: it holds SQLite's EXCLUSIVE lock and its journal for 2 s.
_LIVE_WRITER = """
import sqlite3, sys, time
con = sqlite3.connect(sys.argv[1], isolation_level=None)
con.execute("BEGIN EXCLUSIVE")
con.execute("INSERT INTO study_user_attributes (study_id, key, value_json) VALUES (1, 'k', '1')")
print("writing", flush=True)
time.sleep(2)
con.execute("COMMIT")
"""


def test_a_live_writers_journal_is_not_rolled_back(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Two ``ermrl run`` of one file at once: one said "rolled back the transaction a writer
    left unfinished" after waiting for the other's commit, though no writer died."""
    path = tmp_path / "s.db"
    optuna.create_study(study_name="s", storage=f"sqlite:///{path}")
    writer = subprocess.Popen(
        [sys.executable, "-c", _LIVE_WRITER, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert writer.stdout is not None and writer.stdout.readline() == "writing\n"
        assert Path(f"{path}-journal").stat().st_size > 0
        with caplog.at_level("WARNING", logger="ermrl.storage"):
            assert repair_sqlite(f"sqlite:///{path}") is False
    finally:
        writer.wait(timeout=30)
    assert writer.returncode == 0
    assert "rolled back" not in caplog.text
    study = optuna.load_study(study_name="s", storage=f"sqlite:///{path}")
    assert study.user_attrs == {"k": 1}  # the writer's transaction is kept
