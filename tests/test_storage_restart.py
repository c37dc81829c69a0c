"""A real PostgreSQL restart under a worker that holds the claim lock.

The server is stopped and started again (``pg_ctlcluster``), so this file runs alone on its
xdist worker (``--dist loadfile``) and is marked ``slow``. Tests beside it (other xdist workers)
wait to connect while it is down (``POSTGRES_RESTART_MARK``, see ``conftest.py``), and the
storage calls of one already running ride out the 3 s outage. It is skipped
where the cluster cannot be controlled (not root, no ``pg_ctlcluster``), and the server is
always started again.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pytest
from optuna.trial import TrialState

from ermrl.storage import open_storage
from tests.conftest import POSTGRES_RESTART_MARK

pytestmark = [pytest.mark.slow, pytest.mark.services]

ROOT = Path(__file__).resolve().parents[1]
CLUSTER = os.environ.get("ERMRL_TEST_PG_CLUSTER", "15 main").split()

# A worker that holds the study lock most of the time (a claim that takes 0.3 s).
_WORKER = """
import sys, time
import optuna
from ermrl.storage import open_storage, study_lock

optuna.logging.set_verbosity(optuna.logging.WARNING)
study = optuna.create_study(study_name="s", storage=open_storage(sys.argv[1]), load_if_exists=True)
for i in range(int(sys.argv[2])):
    with study_lock(study):
        trial = study.ask()
        print("claimed", trial.number, flush=True)
        time.sleep(0.3)
    study.tell(trial, trial.suggest_float("x", 0, 1))
"""


def _cluster(action: str) -> None:
    subprocess.run(
        ["pg_ctlcluster", *CLUSTER, action, *(["-m", "fast"] if action == "stop" else [])],
        check=True,
        capture_output=True,
        timeout=60,
    )


@pytest.mark.timeout(120)
def test_a_worker_holding_the_claim_lock_survives_a_postgres_restart(postgres_url: str) -> None:
    """It died on ``OperationalError ... SELECT pg_advisory_unlock`` and left its trial
    RUNNING; now it warns that the lock was lost, rides out the restart and finishes."""
    if os.geteuid() != 0 or shutil.which("pg_ctlcluster") is None:
        pytest.skip("needs root and pg_ctlcluster to restart PostgreSQL")
    worker = subprocess.Popen(
        [sys.executable, "-c", _WORKER, postgres_url, "12"],
        env={**os.environ, "PYTHONPATH": str(ROOT), "ERMRL_STORAGE_RETRY_S": "60"},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert worker.stdout is not None
        worker.stdout.readline()  # the first claim is under way: the lock is held
        POSTGRES_RESTART_MARK.touch()  # the tests beside this one wait before they connect
        try:
            _cluster("stop")
            time.sleep(3)
        finally:
            _cluster("start")
            POSTGRES_RESTART_MARK.unlink(missing_ok=True)
        out, err = worker.communicate(timeout=90)
    finally:
        if worker.poll() is None:
            worker.kill()
            worker.wait()
    assert worker.returncode == 0, err
    assert "Traceback" not in err
    assert "reachable again" in err
    study = optuna.load_study(study_name="s", storage=open_storage(postgres_url))
    assert [t.state for t in study.get_trials()] == [TrialState.COMPLETE] * 12
