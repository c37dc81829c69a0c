"""A malformed CMA-ES state in the storage never crashes a resume: it is ignored with one
warning and CMA-ES starts a new run, the trials already in the study kept."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import optuna
import pytest
from optuna.trial import TrialState

STUDY = "cma-bad-state"
EVOLVE = [
    *("--env-id", "Pendulum-v1", "--n-seeds", "1", "--training-steps", "256"),
    *("--popsize", "2", "--sampler-seed", "0", "--units", "10", "--n-envs", "1"),
    *("--ppo", "n_steps=128", "batch_size=64", "n_epochs=1"),
    *("--study-name", STUDY, "--quiet"),
]


def _evolve(db: Path, n_trials: int) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", "evolve", *EVOLVE, "--storage", f"sqlite:///{db}"]
        + ["--n-trials", str(n_trials)],
        cwd=db.parent,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def _corrupt(db: Path, trial_id: int, key: str, value: object) -> None:
    """Overwrite a system attribute of a finished trial (Optuna's storage API refuses to), as
    a bad write or a hand edit of the database would."""
    with contextlib.closing(sqlite3.connect(db)) as con, con:
        updated = con.execute(
            "UPDATE trial_system_attributes SET value_json = ? WHERE trial_id = ? AND key = ?",
            (json.dumps(value), trial_id, key),
        ).rowcount
    assert updated == 1


@pytest.fixture(scope="module")
def evolved(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three trials with popsize 2: the third one's sampling stored the optimizer state."""
    db = tmp_path_factory.mktemp("cma") / "study.db"
    result = _evolve(db, 3)
    assert result.returncode == 0, result.stderr
    return db


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("cma:state:0", '{"__cmaes__": "CMA", "attrs": {"_mean": '),  # cut short: not JSON
        ("cma:state:0", '{"__cmaes__": "CMA", "attrs": {}}'),  # a chunk replaced
        ("cma:restart_state", {"n_restarts": "many"}),
        ("cma:restart_state", "not a mapping"),
    ],
)
def test_resume_ignores_a_malformed_cma_state(
    evolved: Path, tmp_path: Path, key: str, value: object
) -> None:
    db = tmp_path / "study.db"
    shutil.copy(evolved, db)
    url = f"sqlite:///{db}"
    study = optuna.load_study(study_name=STUDY, storage=url)
    holders = [t for t in study.get_trials() if "cma:state:0" in t.system_attrs]
    assert len(holders) == 1  # the state the resume reads
    _corrupt(db, holders[0]._trial_id, key, value)

    result = _evolve(db, 5)

    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if "CMA-ES state" in line]
    assert len(warnings) == 1, result.stderr
    assert "Traceback" not in result.stderr
    trials = optuna.load_study(study_name=STUDY, storage=url).get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 5
    # The new trials come from a new CMA-ES run, not from the optimizer of the bad state.
    assert all(t.system_attrs["cma:n_restarts"] == 1 for t in trials[3:])


@pytest.mark.parametrize(
    "attrs",
    [
        {"cma:state:0": '{"__cmaes__": "CMA", "attrs": {}}'},  # JSON, but a hollow optimizer
        {"cma:state:0": '{"__cmaes__": "Popen", "attrs": {}}'},  # not a cmaes class
        {"cma:state:0": "{}", "cma:state:2": "}"},  # a chunk missing
        {"cma:state:0": "[1, 2]", "cma:restart_state": {"n_restarts": 1}},  # restart state short
    ],
)
def test_sampler_starts_a_new_run_after_a_malformed_state(
    attrs: dict[str, object], caplog: pytest.LogCaptureFixture
) -> None:
    from optuna.distributions import FloatDistribution

    from ermrl.search import RestartCmaEsSampler

    space = {
        "sr": FloatDistribution(1e-4, 1e2, log=True),
        "lr": FloatDistribution(1e-2, 1.0, log=True),
    }
    study = optuna.create_study(sampler=RestartCmaEsSampler(seed=0, search_space=space))
    labels = {"cma:n_restarts": 2, "cma:restart_2:generation": 5, "cma:popsize": 4}
    for i in range(3):
        study.add_trial(
            optuna.trial.create_trial(
                params={"sr": 1.0, "lr": 0.1},
                distributions=space,
                value=1.0,
                system_attrs={**labels, **(attrs if i == 2 else {})},
            )
        )
    with caplog.at_level("WARNING", logger="ermrl.search._samplers"):
        for _ in range(3):
            study.tell(study.ask(space), 0.5)
    assert caplog.text.count("malformed CMA-ES state") == 1
    new = study.get_trials()[3:]
    assert [t.system_attrs["cma:n_restarts"] for t in new] == [3, 3, 3]
    assert all(t.state == TrialState.COMPLETE for t in new)
