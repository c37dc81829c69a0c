"""A retried trial never inherits the CMA-ES optimizer state of the trial it replaces."""

from __future__ import annotations

import optuna
from optuna.trial import TrialState

from ermrl.storage import RetryStaleTrial


def test_retry_drops_the_stored_cma_es_state() -> None:
    study = optuna.create_study()
    trial = study.ask()
    trial.suggest_float("sr", 1e-4, 1e2, log=True)
    storage = study._storage
    for key, value in {
        "cma:restart_0:generation": 3,
        "cma:state:0": "{}",
        "sepcma:state:1": "{}",
        "cma:optimizer:0": "deadbeef",
        "cma:restart_state": {"n_restarts": 0},
    }.items():
        storage.set_trial_system_attr(trial._trial_id, key, value)
    storage.set_trial_state_values(trial._trial_id, TrialState.FAIL)
    RetryStaleTrial(max_retry=1)(study, storage.get_trial(trial._trial_id))
    retry = study.get_trials(states=(TrialState.WAITING,))[0]
    assert retry.system_attrs["cma:restart_0:generation"] == 3
    kept = sorted(k for k in retry.system_attrs if k.startswith(("cma:", "sepcma:")))
    assert kept == ["cma:restart_0:generation"]
