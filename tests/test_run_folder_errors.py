"""Damaged test-phase folders: ``ermrl report`` and ``ermrl dynamics`` stop in one line.

A real tiny test-phase folder (shared with test_report.py) is copied per case and one of its
files is damaged. Each command must exit with code 2 and one stderr line naming that file,
and write nothing: no report folder, no dynamics folder.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from ermrl.analysis import RunFolderError, check_run_folder, load_curves, load_run_config
from tests._analysis_data import TinyStudy, build_tiny_study

pytestmark = pytest.mark.slow

RUN = "agents/res-ppo/seed_10"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> TinyStudy:
    return build_tiny_study(tmp_path_factory.getbasetemp())


def _replace(text: str) -> Callable[[str], str]:
    return lambda _old: text


def _without(key: str) -> Callable[[str], str]:
    def damage(old: str) -> str:
        record = json.loads(old)
        del record[key]
        return json.dumps(record)

    return damage


def _with(key: str, value: object) -> Callable[[str], str]:
    def damage(old: str) -> str:
        return json.dumps({**json.loads(old), key: value})

    return damage


# (file, damage): the report reads all of them; dynamics all but episodes.csv.
CASES: dict[str, tuple[str, Callable[[str], str]]] = {
    "config-not-yaml": ("config.yaml", _replace("task: [unclosed\n  - {\n")),
    "config-a-list": ("config.yaml", _replace("- task\n- ppo\n")),
    "config-no-task": ("config.yaml", _replace("agents: {}\nppo: {}\n")),
    "config-task-not-mapping": ("config.yaml", _replace("task: 5\nppo: {}\n")),
    "config-binary": ("config.yaml", _replace("\udcff")),
    "episodes-empty": (f"{RUN}/episodes.csv", _replace("")),
    "episodes-no-columns": (f"{RUN}/episodes.csv", _replace("step,return\n1,2.0\n")),
    "episodes-not-numbers": (
        f"{RUN}/episodes.csv",
        _replace("env_step,episode_return\n100,1.5\n200,lots\n"),
    ),
    "result-not-json": (f"{RUN}/result.json", _replace("{not json")),
    "result-a-list": (f"{RUN}/result.json", _replace("[1, 2, 3]")),
    "result-no-agent": (f"{RUN}/result.json", _without("agent")),
    "result-no-final-return": (f"{RUN}/result.json", _without("final_return")),
    "result-seed-text": (f"{RUN}/result.json", _with("seed", "ten")),
    "result-final-return-text": (f"{RUN}/result.json", _with("final_return", "high")),
    "settings-garbage": (f"{RUN}/settings.json", _replace("\x00\x01garbage")),
    "settings-a-list": (f"{RUN}/settings.json", _replace("[]")),
    "settings-ppo-not-mapping": (f"{RUN}/settings.json", _with("ppo", 5)),
}
DYNAMICS_CASES = [name for name, (rel, _) in CASES.items() if not rel.endswith("episodes.csv")]


def _damaged(tiny: TinyStudy, tmp_path: Path, case: str) -> tuple[Path, Path]:
    runs = tmp_path / "runs"
    shutil.copytree(tiny.runs, runs)
    rel, damage = CASES[case]
    path = runs / rel
    text = damage(path.read_text())
    path.write_bytes(text.encode("utf-8", "surrogateescape"))
    return runs, path


def _ermrl(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )


def _assert_one_line(proc: subprocess.CompletedProcess[str], path: Path) -> None:
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert str(path) in lines[0] and "Traceback" not in proc.stderr


@pytest.mark.parametrize("case", list(CASES))
def test_report_of_a_damaged_run_folder_is_one_line_and_writes_nothing(
    tiny: TinyStudy, tmp_path: Path, case: str
) -> None:
    runs, path = _damaged(tiny, tmp_path, case)
    out = tmp_path / "report"
    proc = _ermrl(
        "report",
        "--study-name",
        tiny.study_name,
        "--storage",
        tiny.storage,
        "--runs",
        str(runs),
        "--out",
        str(out),
        "--quiet",
        cwd=tmp_path,
    )
    _assert_one_line(proc, path)
    assert not out.exists()


@pytest.mark.parametrize("case", DYNAMICS_CASES)
def test_dynamics_of_a_damaged_run_folder_is_one_line_and_writes_nothing(
    tiny: TinyStudy, tmp_path: Path, case: str
) -> None:
    runs, path = _damaged(tiny, tmp_path, case)
    out = tmp_path / "dynamics"
    proc = _ermrl(
        "dynamics",
        "--run",
        str(runs),
        "--agent",
        "res-ppo",
        "--seed",
        "10",
        "--max-steps",
        "5",
        "--out",
        str(out),
        cwd=tmp_path,
    )
    _assert_one_line(proc, path)
    assert not out.exists() and not (runs / "dynamics").exists()


def test_the_loaders_raise_run_folder_error_naming_the_file(
    tiny: TinyStudy, tmp_path: Path
) -> None:
    runs, path = _damaged(tiny, tmp_path, "episodes-not-numbers")
    with pytest.raises(RunFolderError, match="lots") as err:
        load_curves(runs)
    assert err.value.path == path
    with pytest.raises(RunFolderError):
        check_run_folder(runs)
    assert load_run_config(runs)["task"]["env_id"] == "HalfCheetah-v5"
    assert isinstance(err.value, ValueError)  # callers that catch ValueError still do


def test_an_undamaged_folder_passes_the_checks(tiny: TinyStudy) -> None:
    check_run_folder(tiny.runs)
    assert not load_curves(tiny.runs).empty


@pytest.mark.parametrize(
    "case",
    ["episodes-not-numbers", "result-not-json", "result-no-final-return", "settings-garbage"],
)
def test_test_phase_rerun_on_a_damaged_finished_run_is_one_line_and_writes_nothing(
    tiny: TinyStudy, tmp_path: Path, case: str
) -> None:
    """A rerun of ``ermrl test`` keeps its finished runs and reads them back for the summary:
    a damaged one stops it before anything is trained or written."""
    from tests._analysis_data import STEPS, TEST_SEEDS

    runs, path = _damaged(tiny, tmp_path, case)
    before = {p: p.stat().st_mtime_ns for p in runs.rglob("*")}
    proc = _ermrl(
        "test",
        "--training-steps",
        str(STEPS),
        "--seeds",
        *map(str, TEST_SEEDS),
        "--out",
        str(runs),
        "--storage",
        tiny.storage,
        "--study-name",
        tiny.study_name,
        "--quiet",
        cwd=tmp_path,
    )
    _assert_one_line(proc, path)
    assert "--overwrite" in proc.stderr
    assert {p: p.stat().st_mtime_ns for p in runs.rglob("*")} == before


def test_a_settings_record_that_is_a_device_is_not_read_to_its_end(tmp_path: Path) -> None:
    """finished_backend reads settings.json as every record is read (capped, regular files):
    a device there is skipped, not read until memory runs out."""
    from ermrl.test_phase._test_phase import finished_backend

    run = tmp_path / "agents" / "ppo" / "seed_1"
    run.mkdir(parents=True)
    (run / "result.json").write_text("{}")
    (run / "settings.json").symlink_to("/dev/zero")
    assert finished_backend(tmp_path, "ppo") is None
