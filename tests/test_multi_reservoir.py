"""Several reservoirs per agent in the single-task pipeline: evolve ``sr_0, sr_1, ...``, then the
test phase rebuilds every reservoir from the study."""

from __future__ import annotations

import json
from pathlib import Path

import optuna
import pytest

from ermrl.cli import evolve_main, test_main
from ermrl.config import ReservoirSpace
from ermrl.search import study_config

PARAMS = ("sr", "lr", "input_scaling")


def test_multi_reservoir_parameter_names() -> None:
    assert ReservoirSpace(n_reservoirs=1).param_names == PARAMS
    assert ReservoirSpace(n_reservoirs=3).param_names == tuple(
        f"{name}_{k}" for k in range(3) for name in PARAMS
    )


def test_evolve_and_test_with_two_reservoirs(tmp_path: Path) -> None:
    storage = f"sqlite:///{tmp_path / 'm.db'}"
    tiny = ["--n-envs", "1", "--ppo", "n_steps=128", "batch_size=64", "n_epochs=1"]
    code = evolve_main(
        ["--env-id", "Pendulum-v1", "--n-reservoirs", "2", "--units", "20", "--n-trials", "2"]
        + ["--n-seeds", "1", "--training-steps", "256", "--n-last-episodes", "1"]
        + ["--storage", storage, "--study-name", "m", "--sampler-seed", "0", "--quiet", *tiny]
    )
    assert code == 0
    study = optuna.load_study(study_name="m", storage=storage)
    config = study_config(study)
    assert config.space.n_reservoirs == 2 and config.problem.encoder.n_reservoirs == 2
    trials = study.get_trials(states=[optuna.trial.TrialState.COMPLETE])
    assert len(trials) == 2
    expected_names = {f"{name}_{k}" for k in (0, 1) for name in PARAMS}
    assert all(set(t.params) == expected_names for t in trials)

    out = tmp_path / "test"
    code = test_main(
        ["--study-name", "m", "--storage", storage, "--agents", "res-ppo", "--seeds", "7"]
        + ["--training-steps", "256", "--out", str(out), "--no-save-models", "--quiet"]
    )
    assert code == 0
    best = study.best_trial.params
    result = json.loads((out / "agents" / "res-ppo" / "seed_7" / "result.json").read_text())
    reservoirs = result["reservoirs"]
    assert len(reservoirs) == 2
    for k, reservoir in enumerate(reservoirs):
        assert reservoir["units"] == 20
        for name in PARAMS:
            assert reservoir[name] == pytest.approx(best[f"{name}_{k}"])
