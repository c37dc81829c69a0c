"""The command line, run as a user runs it: subprocesses on a temporary SQLite study."""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--n-envs", "1", "--ppo", "n_steps=128", "batch_size=64", "n_epochs=2", "--units", "20"]


def run(*args: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )


@pytest.fixture(scope="module")
def evolved(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A 3-trial evolution on Pendulum with velocities hidden, made by evolve_res.py."""
    tmp = tmp_path_factory.mktemp("cli")
    url = f"sqlite:///{tmp}/s.db"
    proc = run(
        str(ROOT / "evolve_res.py"),
        *("--env-id", "Pendulum-v1", "--observe", "positions", "--n-trials", "3", "--n-seeds", "2"),
        *(
            "--training-steps",
            "400",
            "--storage",
            url,
            "--study-name",
            "check",
            "--sampler-seed",
            "1",
        ),
        *TINY,
        cwd=tmp,
    )
    assert proc.returncode == 0, proc.stderr
    return tmp, url


def test_evolve_records_complete_trials(evolved: tuple[Path, str]) -> None:
    tmp, url = evolved
    study = optuna.load_study(study_name="check", storage=url)
    complete = study.get_trials(states=[optuna.trial.TrialState.COMPLETE])
    assert len(complete) == 3
    for trial in complete:
        assert {"sr", "lr", "input_scaling"} == set(trial.params)
        assert len(trial.user_attrs["returns_last"]) == 2
        assert trial.user_attrs["versions"]["gymnasium"]
    assert "evolve_res.py" in study.user_attrs["ermrl_command"]


def test_test_phase_writes_all_outputs(evolved: tuple[Path, str]) -> None:
    tmp, url = evolved
    out = tmp / "run"
    args = ["--study-name", "check", "--storage", url, "--training-steps", "400", "--out", str(out)]
    proc = run(str(ROOT / "test.py"), *args, "--seeds", "10", "11", cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    summary = pd.read_csv(out / "summary.csv")
    assert list(summary["agent"]) == ["ppo", "res-ppo", "random-res-ppo"]
    assert set(summary["n_seeds"]) == {2}
    curves = pd.read_csv(out / "curves.csv")
    assert list(curves.columns) == ["agent", "seed", "env_step", "episode_return"]
    assert set(curves["seed"]) == {10, 11} and len(curves) == 3 * 2 * 2
    assert (out / "learning_curves.png").stat().st_size > 10_000
    assert (out / "config.yaml").exists() and "test.py" in (out / "command.txt").read_text()
    assert (out / "agents" / "res-ppo" / "seed_10" / "model.zip").exists()

    # Re-running resumes: finished runs are skipped, not retrained.
    again = run(str(ROOT / "test.py"), *args, "--seeds", "10", "11", cwd=tmp)
    assert again.returncode == 0 and again.stdout.count("[skip]") == 6

    # A SLURM array task runs the seed at its index.
    env_task = run(
        "-c",
        "import os, sys; os.environ['SLURM_ARRAY_TASK_ID'] = '1'; sys.argv = ['test.py'] + sys.argv[1:];"
        "from ermrl.cli import test_main; raise SystemExit(test_main(prog='test.py'))",
        *args[:-1],
        str(tmp / "slurm_run"),
        "--seeds",
        "20",
        "21",
        "--agents",
        "ppo",
        cwd=tmp,
    )
    assert env_task.returncode == 0, env_task.stderr
    assert [p.name for p in (tmp / "slurm_run" / "agents" / "ppo").iterdir()] == ["seed_21"]


def test_default_test_seeds_avoid_evolution_seeds(evolved: tuple[Path, str]) -> None:
    tmp, url = evolved
    proc = run(
        str(ROOT / "test.py"),
        *("--study-name", "check", "--storage", url, "--training-steps", "200"),
        *("--agents", "ppo", "--out", str(tmp / "defaults"), "--no-save-models"),
        cwd=tmp,
    )
    assert proc.returncode == 0, proc.stderr
    seeds = sorted(int(p.name.split("_")[1]) for p in (tmp / "defaults/agents/ppo").iterdir())
    assert seeds == [2, 3, 4, 5, 6]  # evolution trained on 0 and 1


def _n_trials(db: Path) -> int:
    if not db.exists():
        return 0
    with sqlite3.connect(db) as con:
        try:
            return con.execute("select count(*) from trials").fetchone()[0]
        except sqlite3.OperationalError:  # the file exists before its schema does
            return 0


@pytest.mark.parametrize(
    "args, message",
    [
        (["--env-id", "HalfCheetah-v9"], "unknown env id"),
        (["--env-id", "Blackjack-v1", "--observe", "positions"], "supported ids"),
        (["--env-id", "Pendulum-v1", "--sr-range", "10", "1"], "inverted range"),
        (["--env-id", "Pendulum-v1", "--lr-range", "0.5", "0.5"], "empty or inverted range"),
        (["--env-id", "Pendulum-v1", "--training-steps", "0"], "must be positive"),
        (["--env-id", "Pendulum-v1", "--n-trials", "-3"], "must be positive"),
        (["--env-id", "Pendulum-v1", "--observe", "hidden"], "invalid choice"),
        (["--env-id", "Pendulum-v1", "--ppo", "lerning_rate=3"], "unknown PPO hyperparameter"),
        (
            ["--env-id", "Pendulum-v1", "--storage", "postgresql://nobody@127.0.0.1:1/none"],
            "cannot open storage",
        ),
        (["--env-id", "Pendulum-v1", "--storage", "sqlite:////no/such/dir/x.db"], "does not exist"),
    ],
)
def test_bad_evolve_input_is_one_line_exit_2_and_writes_nothing(
    tmp_path: Path, args: list[str], message: str
) -> None:
    db = tmp_path / "s.db"
    if "--storage" not in args:
        args = [*args, "--storage", f"sqlite:///{db}"]
    proc = run(str(ROOT / "evolve_res.py"), *args, "--n-seeds", "1", cwd=tmp_path, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr
    assert lines[0].startswith("evolve_res.py: error:")
    assert not db.exists() and _n_trials(db) == 0


def test_bad_test_input(evolved: tuple[Path, str], tmp_path: Path) -> None:
    _, url = evolved
    cases = [
        (["--study-name", "nope", "--storage", url], "no study named 'nope'; studies there: check"),
        (["--study-name", "check", "--storage", url, "--training-steps", "0"], "must be positive"),
        (
            ["--study-name", "check", "--storage", "postgresql://nobody@127.0.0.1:1/x"],
            "cannot open storage",
        ),
        (["--study-name", "check", "--storage", url, "--trial", "99"], "has no trial 99"),
    ]
    for args, message in cases:
        proc = run(
            str(ROOT / "test.py"), *args, "--out", str(tmp_path / "o"), cwd=tmp_path, timeout=120
        )
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and message in lines[0], (args, proc.stderr)
    assert not (tmp_path / "o").exists()


def test_help_and_root_scripts_are_the_same_entry_points(tmp_path: Path) -> None:
    top = run("-m", "ermrl", "--help", cwd=tmp_path)
    assert top.returncode == 0 and "evolve" in top.stdout and "test" in top.stdout
    for script, command in (("evolve_res.py", "evolve"), ("test.py", "test")):
        root = run(str(ROOT / script), "--help", cwd=tmp_path)
        sub = run("-m", "ermrl", command, "--help", cwd=tmp_path)
        assert root.returncode == sub.returncode == 0

        def words(text: str, script: str = script, command: str = command) -> list[str]:
            return text.replace(f"ermrl {command}", "PROG").replace(script, "PROG").split()

        assert words(root.stdout) == words(sub.stdout)
    assert "--n-envs" in run(str(ROOT / "evolve_res.py"), "--help", cwd=tmp_path).stdout
    unknown = run("-m", "ermrl", "evolv", cwd=tmp_path)
    assert unknown.returncode == 2 and "unknown command" in unknown.stderr


@pytest.mark.slow
def test_ctrl_c_marks_the_running_trial_failed_and_exits(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    cmd = [
        sys.executable,
        str(ROOT / "evolve_res.py"),
        "--env-id",
        "Pendulum-v1",
        "--n-trials",
        "50",
        "--n-seeds",
        "1",
        "--training-steps",
        "100000",
        "--storage",
        url,
        "--study-name",
        "c",
        *TINY,
    ]
    proc = subprocess.Popen(
        cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    deadline = time.time() + 120
    while time.time() < deadline and _n_trials(tmp_path / "s.db") == 0:
        time.sleep(0.5)
    time.sleep(2)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    study = optuna.load_study(study_name="c", storage=url)
    states = [t.state for t in study.get_trials()]
    assert states == [optuna.trial.TrialState.FAIL]
    assert study.get_trials()[0].user_attrs["fail_reason"] == "interrupted"
