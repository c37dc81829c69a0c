"""A malformed CMA-ES state in the storage never crashes a resume: it is ignored with one
warning and CMA-ES starts a new run, the trials already in the study kept."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import sqlite3
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import pytest
from optuna.trial import TrialState

from ermrl.search._samplers import _encode, _join_chunks

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


def _edit_attrs(**attrs: object) -> Callable[[dict[str, Any]], str]:
    """A state edit: replace some attributes of the stored optimizer (already encoded)."""

    def edit(state: dict[str, Any]) -> str:
        state["attrs"].update(attrs)
        return json.dumps(state)

    return edit


def _array(values: object) -> dict[str, Any]:
    """An array in the stored state's plain form."""
    encoded = _encode(np.asarray(values, dtype=float))
    assert isinstance(encoded, dict)
    return encoded


_DEEP = 50_000
BAD_STATES: dict[str, Callable[[dict[str, Any]], str]] = {
    "popsize 0": _edit_attrs(_popsize=0),
    "NaN mean": _edit_attrs(_mean=_array([math.nan, 0.5])),
    "mean of the wrong length": _edit_attrs(_mean=_array([0.5, 0.5, 0.5])),
    "covariance of the wrong shape": _edit_attrs(_C=_array(np.eye(3))),
    "string sigma": _edit_attrs(_sigma="big"),
    "negative sigma": _edit_attrs(_sigma=-0.1),
    "weights of the wrong length": _edit_attrs(_weights=_array([0.5])),
    "nested 50k deep": lambda state: (
        '{"__cmaes__": "CMA", "attrs": {"_x": ' + '{"__list__": [' * _DEEP + "]}" * _DEEP + "}}"
    ),
}


@pytest.mark.parametrize("edit", BAD_STATES.values(), ids=BAD_STATES)
def test_a_resume_restarts_cma_es_on_an_invalid_state(
    edit: Callable[[dict[str, Any]], str], caplog: pytest.LogCaptureFixture
) -> None:
    """A state that decodes but cannot go on (wrong shapes, not finite, not positive, nested
    too deep) is checked as a whole: one warning, a new CMA-ES run from the stored trials, and
    no trial left RUNNING, where each of them raised on every resume."""
    from optuna.distributions import FloatDistribution

    from ermrl.search import RestartCmaEsSampler

    space = {
        "sr": FloatDistribution(1e-4, 1e2, log=True),
        "lr": FloatDistribution(1e-2, 1.0, log=True),
    }
    first = optuna.create_study(sampler=RestartCmaEsSampler(seed=0, popsize=2, search_space=space))
    for value in (1.0, 2.0, 3.0):
        first.tell(first.ask(space), value)
    (holder,) = [t for t in first.trials if "cma:state:0" in t.system_attrs]
    chunks = {k: v for k, v in holder.system_attrs.items() if k.startswith("cma:state:")}
    text = edit(json.loads(_join_chunks(chunks, "cma:state:")))
    attrs = {k: v for k, v in holder.system_attrs.items() if k not in chunks}
    attrs.update(
        {f"cma:state:{i}": text[j : j + 2045] for i, j in enumerate(range(0, len(text), 2045))}
    )

    study = optuna.create_study(sampler=RestartCmaEsSampler(seed=0, popsize=2, search_space=space))
    for t in first.trials:
        study.add_trial(
            optuna.trial.create_trial(
                params=t.params,
                distributions=t.distributions,
                value=t.value,
                system_attrs=attrs if t.number == holder.number else t.system_attrs,
            )
        )
    with caplog.at_level("WARNING", logger="ermrl.search._samplers"):
        for value in (4.0, 5.0, 6.0):
            study.tell(study.ask(space), value)
    assert caplog.text.count("malformed CMA-ES state") == 1, caplog.text
    new = study.get_trials()[3:]
    assert [t.state for t in new] == [TrialState.COMPLETE] * 3
    assert [t.system_attrs["cma:n_restarts"] for t in new] == [1, 1, 1]
