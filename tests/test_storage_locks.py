"""Stale journal locks: a lock link left by a dead process, or one that points nowhere, never
hangs a worker or a repair. It is broken once unchanged for the grace period (30 s, shortened
here) with a warning, for Optuna's ``<log>.lock`` and ermrl's ``<log>.ermrl.lock`` alike."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import optuna
import pytest

from ermrl.storage import open_storage

ROOT = Path(__file__).resolve().parents[1]

# Run in a fresh process, so a lock that is never broken (Optuna's own acquire spins at full CPU
# on a dangling link, forever) ends in a timeout instead of a hung test run.
_WORKER = """
import sys
import optuna
import ermrl.storage._locks as locks
from ermrl.cli._study import study_main
from ermrl.storage import open_storage, study_lock

optuna.logging.set_verbosity(optuna.logging.WARNING)
locks._JOURNAL_LOCK_GRACE_S = 0.5
path, action = sys.argv[1], sys.argv[2]
if action == "evolve":
    study = optuna.create_study(study_name="s", storage=open_storage(path), load_if_exists=True)
    with study_lock(study):  # a worker's claim: <log>.ermrl.lock
        trial = study.ask()
    study.tell(trial, trial.suggest_float("x", 0, 1))  # appends under <log>.lock
    print(len(study.trials))
else:
    sys.exit(study_main(["repair", "--storage", path]))
"""


def _journal(path: Path, garbage: bool) -> None:
    """A journal with one study and one trial, and a garbage line (a repair's work) if asked."""
    study = optuna.create_study(study_name="s", storage=open_storage(str(path)))
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1)
    if garbage:
        with open(path, "ab") as f:
            f.write(b"garbage\n")


@pytest.mark.parametrize(
    ("action", "lock"),
    [
        ("evolve", "s.log.lock"),  # Optuna's append lock
        ("evolve", "s.log.ermrl.lock"),  # ermrl's claim lock
        ("repair", "s.log.lock"),
    ],
)
def test_a_dangling_journal_lock_is_broken_after_the_grace_period(
    tmp_path: Path, action: str, lock: str
) -> None:
    path = tmp_path / "s.log"
    _journal(path, garbage=action == "repair")
    (tmp_path / lock).symlink_to("/nonexistent")  # ln -s /nonexistent s.log.lock
    done = subprocess.run(
        [sys.executable, "-c", _WORKER, str(path), action],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=30,  # hung for good before
    )
    assert done.returncode == 0, done.stderr
    if action == "evolve":
        assert done.stdout.split() == ["2"]
    else:
        assert "set aside 1 unreadable record" in done.stdout
    assert f"broke the lock {tmp_path / lock}" in done.stderr
    assert not os.path.lexists(tmp_path / lock)
    assert "Traceback" not in done.stderr
