"""The optuna-dashboard command an evolution prints: right for each storage, and it really serves
the study (a real optuna-dashboard process over a real SQLite database and journal file)."""

from __future__ import annotations

import importlib.util
import json
import shlex
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import optuna
import pytest

from ermrl.storage import dashboard_command, open_storage

ROOT = Path(__file__).resolve().parents[1]


def test_command_per_storage_kind() -> None:
    assert dashboard_command("sqlite:///runs/a b.db") == "optuna-dashboard 'sqlite:///runs/a b.db'"
    assert dashboard_command("journal:///tmp/j.log") == "optuna-dashboard /tmp/j.log"
    assert dashboard_command("runs/j.log") == "optuna-dashboard runs/j.log"
    pg = dashboard_command("postgres://u@127.0.0.1/test")
    assert pg is not None and pg.startswith("optuna-dashboard postgresql")  # spelled for SQLAlchemy
    assert (
        dashboard_command("redis://127.0.0.1:6379/0") == "optuna-dashboard redis://127.0.0.1:6379/0"
    )
    # optuna-dashboard reads a Redis journal without a key prefix only; no URL: no command
    assert dashboard_command("redis://127.0.0.1:6379?prefix=mine") is None
    assert dashboard_command("sqlite://") is None
    assert dashboard_command("ftp://x") is None


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _served_study_names(command: str, cwd: Path) -> list[str]:
    """Run ``command`` (as printed) on a free port; return the study names its API lists."""
    port = _free_port()
    argv = shlex.split(command)
    exe = Path(sys.executable).with_name(argv[0])
    proc = subprocess.Popen(
        [str(exe), *argv[1:], "--port", str(port), "--quiet"],
        cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/studies", timeout=5) as r:
                    return [s["study_name"] for s in json.load(r)["study_summaries"]]
            except OSError as err:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise AssertionError(f"not served: {proc.communicate()}") from err
                time.sleep(0.3)
    finally:
        proc.terminate()
        proc.communicate(timeout=30)


@pytest.mark.skipif(
    importlib.util.find_spec("optuna_dashboard") is None,
    reason="optuna-dashboard is not installed (pip install 'ermrl[viz]'; the dev extra has it)",
)
@pytest.mark.parametrize("url", ["sqlite:///s.db", "runs/s.log"])
def test_printed_command_serves_the_study(
    tmp_path: Path, url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # relative paths, as a user types them
    (tmp_path / "runs").mkdir()
    study = optuna.create_study(
        study_name="watched", storage=open_storage(url), direction="maximize"
    )
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    command = dashboard_command(url)
    assert command is not None
    assert _served_study_names(command, tmp_path) == ["watched"]


def test_evolution_prints_the_dashboard_command(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "ermrl", "evolve", "--env-id", "CartPole-v1", "--n-trials", "1",
         "--n-seeds", "1", "--training-steps", "128", "--n-envs", "1", "--units", "10",
         "--ppo", "n_steps=64", "batch_size=32", "n_epochs=1", "--storage", "sqlite:///e.db"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stdout.splitlines() if line.startswith("live view: ")]
    assert (
        len(lines) == 1 and lines[0].split("  (")[0] == "live view: optuna-dashboard sqlite:///e.db"
    )


@pytest.mark.skipif(
    importlib.util.find_spec("optuna_dashboard") is None,
    reason="optuna-dashboard is not installed (pip install 'ermrl[viz]'; the dev extra has it)",
)
def test_the_dashboard_shows_what_the_objective_measures(tmp_path: Path) -> None:
    """The objective is named ``fitness``; what it measures is the study's ``ermrl_metric``
    user attribute, which optuna-dashboard's study page lists (its API, served in-process)."""
    import io

    import optuna_dashboard

    from ermrl.search import create_or_resume_study
    from tests.test_search import make_config

    study = create_or_resume_study(make_config(n_trials=1), f"sqlite:///{tmp_path}/s.db", "s")
    app = optuna_dashboard.wsgi(study._storage)
    status: list[str] = []
    environ = {
        "REQUEST_METHOD": "GET", "PATH_INFO": f"/api/studies/{study._study_id}",
        "QUERY_STRING": "", "SERVER_NAME": "localhost", "SERVER_PORT": "80",
        "wsgi.url_scheme": "http", "wsgi.input": io.BytesIO(), "wsgi.errors": sys.stderr,
    }  # fmt: skip
    body = b"".join(app(environ, lambda s, headers, exc_info=None: status.append(s)))
    assert status == ["200 OK"], body[:500]
    shown = {a["key"]: a["value"] for a in json.loads(body)["user_attrs"]}
    assert shown["ermrl_metric"] == (
        "fitness: mean return of the last 2 training episodes, mean over seeds"
    )
