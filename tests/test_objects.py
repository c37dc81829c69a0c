"""The object API at the package root: ``ermrl.Evolution`` (a study trials are added to),
its ``Candidate`` (the selected encoder, which trains a learner) and the ``Model`` it returns
(``predict``, a pickle-free ``save`` and ``load``). Real studies and tiny real training."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import optuna
import pytest

import ermrl
from ermrl.search import decode_candidate, select_trial
from tests.test_api import EVOLVE

# The options of tests/test_api.py's tiny study, less its budget: optimize() gives that.
OPTIONS = {k: v for k, v in EVOLVE.items() if k != "n_trials"}


@pytest.fixture(scope="module")
def evolution(tmp_path_factory: pytest.TempPathFactory) -> ermrl.Evolution:
    storage = f"sqlite:///{tmp_path_factory.mktemp('objects')}/ermrl.db"
    evolution = ermrl.Evolution("Pendulum-v1", storage, **OPTIONS)
    evolution.optimize(n_trials=2)
    return evolution


def _finished(study: optuna.Study) -> int:
    states = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)
    return len(study.get_trials(deepcopy=False, states=states))


def test_an_evolution_is_a_study_that_trials_are_added_to(evolution: ermrl.Evolution) -> None:
    study = evolution.study
    assert isinstance(study, optuna.Study)
    assert study.study_name == "Pendulum-v1__positions__256steps" and _finished(study) == 2
    # Another process's view of the same study: it adds exactly the trials asked for.
    other = ermrl.Evolution.load(study.study_name, evolution.storage)
    assert other.config == evolution.config
    result = other.optimize(n_trials=1)
    assert result.n_trials == 3 and result.worker.trials_run == 1
    assert _finished(evolution.study) == 3  # the storage is shared
    assert isinstance(result.study, optuna.Study) and result.study.study_name == study.study_name
    frame = evolution.trials_dataframe()
    assert list(frame["number"]) == [0, 1, 2]
    assert {"fitness", "sr", "lr", "input_scaling"} <= set(frame.columns)
    assert list(frame["fitness"]) == [t.value for t in evolution.study.trials]
    assert set(result.best_params) == {"sr", "lr", "input_scaling"}  # the docstring's keys


def test_bad_inputs_raise_the_projects_error_in_one_line(
    evolution: ermrl.Evolution, tmp_path: Path
) -> None:
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ermrl.ConfigError, match="n_trials must be a positive integer"):
            evolution.optimize(n_trials=bad)  # type: ignore[arg-type]
    with pytest.raises(ermrl.ExperimentError, match="did you mean 'n_seeds'"):
        ermrl.Evolution("Pendulum-v1", f"sqlite:///{tmp_path}/x.db", n_sedes=1)
    assert not (tmp_path / "x.db").exists()
    with pytest.raises(ermrl.ConfigError, match="has no trial 99"):
        evolution.selected(trial=99)
    candidate = evolution.selected()
    for steps, seed, message in (
        (0, 0, "total_timesteps must be an integer >= 1, got 0"),
        ("256", 0, "total_timesteps must be an integer >= 1, got '256'"),
        (256, -1, "seed must be an integer >= 0, got -1"),
    ):
        with pytest.raises(ermrl.ConfigError) as err:
            candidate.learn(steps, seed=seed)  # type: ignore[arg-type]
        assert str(err.value) == message


def test_the_candidate_is_the_selected_trial_and_builds_its_encoder(
    evolution: ermrl.Evolution,
) -> None:
    import gymnasium as gym

    candidate = evolution.selected()
    chosen, how = select_trial(evolution.study)
    assert (candidate.number, candidate.params, candidate.selection) == (
        chosen.number, chosen.params, how,
    )  # fmt: skip
    assert candidate.fitness == chosen.value
    config = evolution.config
    assert candidate.encoder == decode_candidate(config.space, chosen.params, config.problem)[0]
    assert evolution.selected(trial=0).params == evolution.study.trials[0].params
    # The encoder as a wrapper: the same reservoir weights as the run of that seed.
    env = candidate.make_env(seed=3)
    wrapped = candidate.wrap(gym.make("Pendulum-v1"), seed=3)
    assert wrapped.observation_space == env.observation_space
    assert [np.array_equal(a.W, b.W) for a, b in zip(wrapped.weights, env.weights)] == [True]
    env.close()
    wrapped.close()


def test_a_saved_model_loads_without_pickle_and_predicts_the_same(
    evolution: ermrl.Evolution, tmp_path: Path
) -> None:
    model = evolution.selected().learn(256, seed=3)
    assert model.result is not None and model.result.env_steps == 256
    env = model.get_env(n_envs=2)
    obs = np.concatenate([env.reset(), env.step(np.zeros((2, 1)))[0]])
    env.close()
    folder = model.save(tmp_path / "model")
    assert sorted(p.name for p in folder.iterdir()) == ["model.json", "policy.pt"]
    loaded = ermrl.Model.load(folder)
    assert (loaded.task, loaded.encoder, loaded.seed) == (model.task, model.encoder, 3)
    np.testing.assert_array_equal(
        model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0]
    )
    weights = model.agent.policy.state_dict()
    assert all(v.equal(weights[k]) for k, v in loaded.agent.policy.state_dict().items())
    assert loaded.evaluate(2) == model.evaluate(2)


class _Payload:
    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (print, ("unpickled",))


def test_a_damaged_or_foreign_model_is_refused_in_one_line(
    evolution: ermrl.Evolution, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import torch

    good = evolution.selected().learn(256, seed=4).save(tmp_path / "good")
    with pytest.raises(ermrl.ConfigError, match="holds no saved model"):
        ermrl.Model.load(tmp_path / "nowhere")

    def tampered(name: str, edit: object) -> Path:
        folder = tmp_path / name
        shutil.copytree(good, folder)
        if callable(edit):
            edit(folder)
        return folder

    settings = json.loads((good / "model.json").read_text())
    cases = {
        "pickle": (
            lambda f: torch.save({"w": _Payload()}, f / "policy.pt"),
            "policy.pt is not plain tensors",
        ),
        "json": (lambda f: (f / "model.json").write_text("{not json"), "not a JSON file"),
        "format": (
            lambda f: (f / "model.json").write_text(json.dumps({**settings, "format": "zip"})),
            "not an ermrl model",
        ),
        "env": (
            lambda f: (f / "model.json").write_text(
                json.dumps({**settings, "task": {"env_id": "os:system"}})
            ),
            "os:system",
        ),
        "ppo": (
            lambda f: (f / "model.json").write_text(json.dumps({**settings, "ppo": 3})),
            "its settings do not build",
        ),
    }
    for name, (edit, message) in cases.items():
        with pytest.raises(ermrl.ConfigError, match=message) as err:
            ermrl.Model.load(tampered(name, edit))
        assert "\n" not in str(err.value), name
    assert "unpickled" not in capsys.readouterr().out
