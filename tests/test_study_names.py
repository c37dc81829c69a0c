"""Study names cannot lead out of a results folder or rewrite a terminal.

A name is refused where ermrl creates or imports a study; a study named by another tool (Optuna
itself, a shared database) is printed escaped, and no default folder is built from its name
unless that folder stays inside ``runs/`` or ``reports/``.
"""

from __future__ import annotations

import json
from pathlib import Path

import optuna
import pytest

import ermrl
from ermrl.cli import _test as test_command
from ermrl.cli._evolve import evolve_main
from ermrl.cli._report import report_main
from ermrl.cli._study import study_main
from ermrl.storage import (
    StudyNameError,
    check_study_name,
    folder_for,
    printable_name,
    write_snapshot,
)
from tests.test_bad_input import _refused

ESCAPES = "../../x/ü y"
TERMINAL = "a\nb\x1b[31mred"
BAD = [
    (ESCAPES, "path separator"),
    ("..", "'..'"),
    ("a..b", "'..'"),
    ("a\\b", "path separator"),
    (TERMINAL, "U+000A"),
    ("right\u202eleft", "U+202E"),
    ("", "empty"),
    ("   ", "empty"),
    ("x" * 513, "513 characters"),
]
TINY = [
    *("--env-id", "Pendulum-v1", "--n-trials", "1", "--n-seeds", "1"),
    *("--training-steps", "400", "--units", "10", "--n-envs", "1", "--quiet"),
    *("--ppo", "n_steps=64", "batch_size=32", "n_epochs=1"),
]


@pytest.mark.parametrize(("name", "reason"), BAD)
def test_bad_names_are_refused_with_the_reason(name: str, reason: str) -> None:
    with pytest.raises(StudyNameError, match=reason.replace("+", r"\+")) as err:
        check_study_name(name)
    message = str(err.value)
    assert "\n" not in message and "\x1b" not in message and "\u202e" not in message


@pytest.mark.parametrize("name", ["Pendulum-v1__positions__5000steps", "ü y", "pend.reeval"])
def test_good_names_pass(name: str) -> None:
    assert check_study_name(name) == name
    assert folder_for("runs", name) == Path("runs") / name


def test_a_name_that_is_not_a_string_is_refused() -> None:
    with pytest.raises(StudyNameError, match="not int"):
        check_study_name(42)


def test_printable_name_escapes_control_and_format_characters() -> None:
    shown = printable_name(TERMINAL + "\u202e")
    assert shown == "a\\nb\\x1b[31mred\\u202e"
    assert shown.isprintable()
    assert printable_name("ü y") == "ü y"


@pytest.mark.parametrize("name", [ESCAPES, "..", ".", TERMINAL])
def test_no_folder_is_built_outside_its_base(name: str) -> None:
    with pytest.raises(StudyNameError, match="--out"):
        folder_for("runs", name)


@pytest.mark.parametrize(("name", "reason"), [(ESCAPES, "path separator"), (TERMINAL, "U+000A")])
def test_evolve_refuses_the_name_before_the_storage_exists(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, reason: str
) -> None:
    db = tmp_path / "s.db"
    err = _refused(
        evolve_main, [*TINY, "--storage", f"sqlite:///{db}", "--study-name", name], capsys
    )
    assert reason in err and "\x1b" not in err
    assert not db.exists()


def test_python_evolve_refuses_the_name_before_the_storage_exists(tmp_path: Path) -> None:
    db = tmp_path / "s.db"
    with pytest.raises(ermrl.ConfigError, match="path separator"):
        ermrl.evolve("Pendulum-v1", f"sqlite:///{db}", ESCAPES, n_trials=1, training_steps=128)
    assert not db.exists()


@pytest.fixture(scope="module")
def shared(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A one-trial study, copied by Optuna itself (as another tool sharing the database could)
    under a name that leads out of ``runs/`` and one that holds terminal escapes."""
    tmp = tmp_path_factory.mktemp("names")
    url = f"sqlite:///{tmp}/s.db"
    assert evolve_main([*TINY, "--storage", url, "--study-name", "good"]) == 0
    for name in (ESCAPES, TERMINAL):
        optuna.copy_study(from_study_name="good", from_storage=url, to_storage=url,
                          to_study_name=name)  # fmt: skip
    return tmp, url


def test_test_and_report_build_no_folder_from_an_escaping_name(
    shared: tuple[Path, str], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    tmp, url = shared
    cwd = tmp / "a" / "b"
    cwd.mkdir(parents=True)
    monkeypatch.chdir(cwd)
    before = sorted(tmp.rglob("*"))
    common = ["--storage", url, "--study-name", ESCAPES]
    err = _refused(
        test_command.test_main, [*common, "--training-steps", "128", "--seeds", "20"], capsys
    )
    assert "--out" in err and "path separator" in err
    err = _refused(report_main, [*common, "--quiet"], capsys)
    assert "--out" in err
    assert sorted(tmp.rglob("*")) == before  # nothing written, inside or outside runs/


def test_study_list_and_show_print_names_escaped(
    shared: tuple[Path, str], capsys: pytest.CaptureFixture[str]
) -> None:
    _, url = shared
    assert study_main(["list", "--storage", url]) == 0
    listed = capsys.readouterr().out
    assert "\x1b" not in listed and "a\\nb\\x1b[31mred" in listed
    assert study_main(["show", "--storage", url, "--study-name", TERMINAL]) == 0
    assert "\x1b" not in capsys.readouterr().out


@pytest.mark.parametrize(("name", "reason"), [(ESCAPES, "path separator"), ("x" * 3000, "3000")])
def test_study_import_refuses_a_snapshot_with_a_bad_name(
    shared: tuple[Path, str], tmp_path: Path, capsys: pytest.CaptureFixture[str],
    name: str, reason: str,
) -> None:  # fmt: skip
    _, url = shared
    path = tmp_path / "snap.json"
    write_snapshot(optuna.load_study(study_name="good", storage=url), path)
    doc = json.loads(path.read_text())
    doc["study_name"] = name
    path.write_text(json.dumps(doc))
    target = tmp_path / "t.db"
    err = _refused(study_main, ["import", "--storage", f"sqlite:///{target}", "--snapshot",
                                str(path)], capsys)  # fmt: skip
    assert reason in err
    err = _refused(study_main, ["import", "--storage", f"sqlite:///{target}", "--snapshot",
                                str(path.with_name("none.json")), "--study-name", ESCAPES], capsys)  # fmt: skip
    assert "path separator" in err
    assert not target.exists() or not optuna.get_all_study_names(f"sqlite:///{target}")
