"""Generalization: suites, the multi-task config and fitness, the same reservoir across tasks, and
the evolve-generalization / test-generalization CLIs."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import optuna
import pandas as pd
import pytest

from ermrl.agents import derive_seeds, make_vec_env
from ermrl.cli._generalization import (
    evolve_generalization_main,
    overlap_warning,
    test_generalization_main,
)
from ermrl.config import (
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    EvolveConfig,
    GeneralizationTask,
    PPOConfig,
    ReservoirSpace,
    SearchConfig,
    TaskConfig,
    to_dict,
)
from ermrl.envs import UnknownEnvError, UnknownSuiteError, get_suite, load_suites, with_env_version
from ermrl.search import (
    MissingScoreError,
    create_or_resume_generalization_study,
    create_or_resume_study,
    evaluate_generalization,
    generalization_config,
    generalization_tasks,
    study_config,
)
from ermrl.search._scores import ReferenceScore, write_scores

ROOT = Path(__file__).resolve().parents[1]
TINY = {"n_steps": 512, "batch_size": 64, "n_epochs": 1}
TASKS = ("Swimmer-v5", "Hopper-v5")
LEAVE_ONE_OUT = ("no_ant", "no_halfcheetah", "no_hopper", "no_swimmer", "no_walker2d")
FORWARD = ("Ant-v5", "HalfCheetah-v5", "Hopper-v5", "Swimmer-v5", "Walker2d-v5")


# -- suites ---------------------------------------------------------------------------------------


def test_packaged_suites_are_the_original_sets() -> None:
    suites = load_suites()
    assert {"ant_swimmer", "ant_cheetah", "cheetah_swimmer", "forward_mujoco"} <= set(suites)
    assert suites["forward_mujoco"].env_ids == FORWARD
    for name in LEAVE_ONE_OUT:
        left_out = next(e for e in FORWARD if e.lower().startswith(name[3:]))
        assert set(suites[name].env_ids) == set(FORWARD) - {left_out}
    assert suites["ant_swimmer"].env_ids == ("Ant-v5", "Swimmer-v5")


@pytest.mark.parametrize(
    ("name", "expected"),
    [("Ant_Swimmer", "ant_swimmer"), ("Cheetah_4_tr_envs", "no_halfcheetah"), ("NO_ANT", "no_ant")],
)
def test_suite_lookup_accepts_original_names(name: str, expected: str) -> None:
    assert get_suite(name).name == expected


def test_env_version_and_unknown_suite() -> None:
    assert get_suite("ant_cheetah", env_version="v4").env_ids == ("Ant-v4", "HalfCheetah-v4")
    assert with_env_version(["Pendulum"], "1") == ("Pendulum-v1",)
    with pytest.raises(ConfigError, match="v4 or v5"):
        with_env_version(["Ant-v5"], "four")
    with pytest.raises(UnknownSuiteError, match="available: ant_cheetah, ant_swimmer"):
        get_suite("nope")


def test_user_suites_file(tmp_path: Path) -> None:
    path = tmp_path / "suites.yml"
    path.write_text(
        "mine: [Swimmer-v5, Hopper-v5]\nforward_mujoco:\n  env_ids: [Ant-v5]\n  aliases: fm\n"
    )
    assert get_suite("mine", path).env_ids == TASKS
    assert get_suite("fm", path).env_ids == ("Ant-v5",)  # a user suite replaces a packaged one
    assert get_suite("no_ant", path).source == "packaged"
    for text, message in [
        ("empty: []\n", "has no task"),
        ("twice: [Ant-v5, Ant-v5]\n", "listed twice"),
        ("bad: {env_ids: [Ant-v5], typo: 1}\n", "unknown key"),
        ("- Ant-v5\n", "must map suite names"),
    ]:
        path.write_text(text)
        with pytest.raises(ConfigError, match=message):
            load_suites(path)


# -- configuration -------------------------------------------------------------------------------


def _config(tasks: tuple[GeneralizationTask, ...], **kwargs: object) -> EvolveConfig:
    space = ReservoirSpace(n_reservoirs=2, units=20)
    return generalization_config(
        tasks,
        encoder=EncoderConfig(reservoirs=space.default_reservoirs()),
        budget=BudgetConfig(training_steps=1024, n_last_episodes=2, n_reports=0),
        seeds=(0,),
        space=space,
        search=SearchConfig(n_trials=2, sampler_seed=0),
        ppo_overrides=TINY,
        **kwargs,  # type: ignore[arg-type]
    )


def test_tasks_carry_ppo_settings_and_references() -> None:
    tasks = generalization_tasks(TASKS, ppo_overrides=TINY)
    assert [t.task.env_id for t in tasks] == list(TASKS)
    assert all(t.ppo.n_envs == 1 and dict(t.ppo.hyperparams) == TINY for t in tasks)
    swimmer = tasks[0]
    assert swimmer.target_return == pytest.approx(281.561)
    assert swimmer.normalize(swimmer.random_return) == 0.0
    assert swimmer.normalize(swimmer.target_return) == pytest.approx(1.0)
    provisional = generalization_tasks(TASKS, target_column="provisional_target")
    assert provisional[0].target_return == 60.0


def test_config_round_trips_and_single_task_dict_is_unchanged() -> None:
    config = _config(generalization_tasks(TASKS, ppo_overrides=TINY), suite="mine")
    data = json.loads(json.dumps(to_dict(config)))  # what the study stores
    assert EvolveConfig.from_dict(data) == config
    assert [t["task"]["env_id"] for t in data["generalization"]["tasks"]] == list(TASKS)
    single = dataclasses.replace(config, generalization=None)
    assert "generalization" not in single.to_dict()
    assert EvolveConfig.from_dict(single.to_dict()) == single


def test_bad_task_sets_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="task set is empty"):
        generalization_tasks([])
    with pytest.raises(ConfigError, match="repeated: Hopper-v5"):
        generalization_tasks(["Hopper-v5", "Swimmer-v5", "Hopper-v5"])
    with pytest.raises(UnknownEnvError, match="did you mean"):
        generalization_tasks(["Hoper-v5"])
    with pytest.raises(
        MissingScoreError,
        match="`ermrl scores --env-ids Acrobot-v1 --out scores.csv` to measure it and pass --scores scores.csv",
    ):
        generalization_tasks(["Acrobot-v1"])
    scores = tmp_path / "scores.csv"
    write_scores({"Hopper-v5": ReferenceScore("Hopper-v5", random_mean=5.0, target=5.0)}, scores)
    with pytest.raises(MissingScoreError, match="equals its random return"):
        generalization_tasks(["Hopper-v5"], scores=str(scores))
    task = GeneralizationTask(TaskConfig("Hopper-v5"), PPOConfig(), 0.0, 1.0)
    with pytest.raises(ConfigError, match="equals the random return"):
        dataclasses.replace(task, target_return=0.0)


# -- the same reservoir on every task ------------------------------------------------------------


def test_same_seed_gives_same_recurrent_weights_on_tasks_of_different_sizes() -> None:
    space = ReservoirSpace(n_reservoirs=2, units=20)
    encoder = EncoderConfig(reservoirs=space.reservoirs_from({
        "sr_0": 0.9, "lr_0": 0.5, "input_scaling_0": 2.0,
        "sr_1": 3.0, "lr_1": 0.1, "input_scaling_1": 0.3,
    }))  # fmt: skip
    seed = derive_seeds(4).reservoir  # what train_agent uses for training seed 4
    swimmer = make_vec_env(TaskConfig("Swimmer-v5"), 1, 0, encoder, seed)
    hopper = make_vec_env(TaskConfig("Hopper-v5"), 1, 0, encoder, seed)
    try:
        assert swimmer.input_dim == 8 + 2 + 1 and hopper.input_dim == 11 + 3 + 1
        for a, b in zip(swimmer.weights, hopper.weights):
            np.testing.assert_array_equal(a.W, b.W)
            np.testing.assert_array_equal(a.bias, b.bias)
            assert a.Win.shape == (20, 11) and b.Win.shape == (20, 15)
        # The two reservoirs of one agent are different reservoirs.
        assert not np.array_equal(swimmer.weights[0].W != 0, swimmer.weights[1].W != 0)
    finally:
        swimmer.close()
        hopper.close()


# -- the multi-task fitness ----------------------------------------------------------------------


def test_fitness_is_mean_normalized_return_and_reports_normalized_values() -> None:
    tasks = generalization_tasks(TASKS, ppo_overrides=TINY)
    config = _config(tasks)
    problem = dataclasses.replace(
        config.problem, budget=dataclasses.replace(config.problem.budget, n_reports=2)
    )
    reports: list[tuple[int, float]] = []
    result = evaluate_generalization(
        config.problem.encoder.with_reservoirs(config.space.default_reservoirs()),
        problem,
        tasks,
        report=lambda step, value: reports.append((step, value)),
    )
    swimmer, hopper = result.tasks
    assert swimmer.seed_returns == [result.runs[0].last_return]
    expected = np.mean([t.normalize(o.mean_return) for t, o in zip(tasks, result.tasks)])
    assert result.fitness == pytest.approx(expected)
    attrs = json.loads(json.dumps(result.user_attrs()))
    assert attrs["tasks"] == list(TASKS)
    assert attrs["fitness"] == pytest.approx(result.fitness)
    assert attrs["task_returns"]["Hopper-v5"] == pytest.approx(hopper.mean_return)
    assert attrs["task_normalized"]["Swimmer-v5"] == pytest.approx(swimmer.normalized)
    assert attrs["task_seed_returns"]["Hopper-v5"] == pytest.approx(hopper.seed_returns)
    assert attrs["env_steps"] == sum(attrs["task_env_steps"].values()) >= 2048
    # Hopper's reports come after Swimmer's budget and are normalized by Hopper's references.
    hopper_reports = [(s, v) for s, v in reports if s > 1024]
    assert hopper_reports and all(-1 < v < 1 for _, v in hopper_reports)


def test_resuming_needs_the_same_task_set(tmp_path: Path) -> None:
    storage = f"sqlite:///{tmp_path / 'g.db'}"
    tasks = generalization_tasks(TASKS, ppo_overrides=TINY)
    config = _config(tasks)
    study = create_or_resume_generalization_study(config, storage, "g")
    assert study.user_attrs["ermrl_kind"] == "evolve-generalization"
    assert study_config(study) == config
    create_or_resume_generalization_study(config, storage, "g")  # same config: resumes
    other = _config(tasks, target_column="provisional_target")
    with pytest.raises(ConfigError, match="generalization.target_column"):
        create_or_resume_generalization_study(other, storage, "g")
    single = dataclasses.replace(config, generalization=None)
    create_or_resume_study(single, storage, "single")
    with pytest.raises(ConfigError, match="not a generalization study"):
        create_or_resume_generalization_study(config, storage, "single")


def test_overlap_warning() -> None:
    assert "NOT a generalization test" in (overlap_warning("Hopper-v5", TASKS, "s") or "")
    assert "another version" in (overlap_warning("Hopper-v4", TASKS, "s") or "")
    assert overlap_warning("HalfCheetah-v5", TASKS, "s") is None


# -- command line ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--suite", "nope"], "unknown suite 'nope'; available:"),
        (["--env-ids", "Hoper-v5"], "unknown env id 'Hoper-v5'"),
        (["--env-ids", "Acrobot-v1"], "run `ermrl scores --env-ids Acrobot-v1 --out scores.csv`"),
        (["--env-ids", "Hopper-v5", "Hopper-v5"], "each task may appear once"),
        (["--env-ids", "Hopper-v5", "--env-version", "v4"], "--env-version applies to --suite"),
        (["--env-ids"], "expected at least one argument"),
        ([], "one of the arguments --env-ids --suite is required"),
    ],
)
def test_evolve_cli_bad_input(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        evolve_generalization_main([*argv, "--storage", f"sqlite:///{tmp_path / 's.db'}"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_evolve_cli_target_equal_random_and_empty_suite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scores = tmp_path / "scores.csv"
    write_scores({"Hopper-v5": ReferenceScore("Hopper-v5", random_mean=7.0, target=7.0)}, scores)
    suites = tmp_path / "suites.yml"
    suites.write_text("empty: []\n")
    for argv, message in [
        (["--env-ids", "Hopper-v5", "--scores", str(scores)], "equals its random return"),
        (["--suite", "empty", "--suites-file", str(suites)], "has no task"),
    ]:
        with pytest.raises(SystemExit) as exc:
            evolve_generalization_main(argv)
        assert exc.value.code == 2 and message in capsys.readouterr().err


def _run(script: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(ROOT / script), *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.slow
def test_cli_smoke_evolve_then_test_on_an_unseen_task(tmp_path: Path) -> None:
    storage = f"sqlite:///{tmp_path / 'g.db'}"
    evolve = _run(
        "evolve_generalization.py",
        *("--env-ids", *TASKS, "--n-reservoirs", "2", "--n-trials", "2", "--n-seeds", "1"),
        *("--training-steps", "1024", "--units", "20", "--storage", storage, "--study-name", "g"),
        *("--ppo", "n_steps=512", "batch_size=64", "n_epochs=1"),
    )
    assert evolve.returncode == 0, evolve.stderr
    study = optuna.load_study(study_name="g", storage=storage)
    trials = study.get_trials(states=[optuna.trial.TrialState.COMPLETE])
    assert len(trials) == 2
    for trial in trials:
        assert set(trial.params) == {
            f"{n}_{k}" for n in ("sr", "lr", "input_scaling") for k in (0, 1)
        }
        assert set(trial.user_attrs["task_normalized"]) == set(TASKS)
        assert set(trial.user_attrs["task_returns"]) == set(TASKS)
        assert all(len(v) == 1 for v in trial.user_attrs["task_seed_returns"].values())
        assert trial.value == pytest.approx(
            np.mean(list(trial.user_attrs["task_normalized"].values()))
        )

    out = tmp_path / "test"
    test = _run(
        "test_generalization.py",
        *("--study-name", "g", "--storage", storage, "--env-id", "Walker2d-v5", "--seeds", "5"),
        *("--training-steps", "512", "--out", str(out), "--no-save-models"),
        *("--ppo", "n_steps=256", "batch_size=64", "n_epochs=1"),
    )
    assert test.returncode == 0, test.stderr
    assert "WARNING" not in test.stderr
    summary = pd.read_csv(out / "summary.csv")
    assert list(summary["agent"]) == ["ppo", "res-ppo", "random-res-ppo"]
    assert "final_return_normalized_mean" in summary
    assert (out / "curves.csv").exists() and (out / "learning_curves.png").exists()
    best = study.best_trial
    result = json.loads((out / "agents" / "res-ppo" / "seed_5" / "result.json").read_text())
    assert result["env_id"] == "Walker2d-v5"
    assert [r["sr"] for r in result["reservoirs"]] == [best.params["sr_0"], best.params["sr_1"]]


def test_test_cli_warns_loudly_on_an_evolution_task(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    storage = f"sqlite:///{tmp_path / 'g.db'}"
    config = _config(generalization_tasks(TASKS, ppo_overrides=TINY))
    create_or_resume_generalization_study(config, storage, "g")
    monkeypatch.chdir(tmp_path)
    # Default seeds follow the evolution seeds (0): 1..5; the array index picks the second.
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "1")
    code = test_generalization_main(
        ["--study-name", "g", "--storage", storage, "--env-id", "Hopper-v5", "--agents", "ppo"]
        + ["--training-steps", "256", "--no-save-models", "--ppo", "n_steps=256", "--quiet"]
    )
    assert code == 0
    err = capsys.readouterr().err
    assert "WARNING: Hopper-v5 was one of the evolution tasks" in err
    assert "NOT a generalization test" in err
    out = tmp_path / "runs" / "g__Hopper-v5"
    assert "in_evolution_set: true" in (out / "config.yaml").read_text()
    assert pd.read_csv(out / "summary.csv")["seeds"].tolist() == [2]


def test_test_cli_refuses_a_rerun_with_other_settings(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    storage = f"sqlite:///{tmp_path / 'g.db'}"
    create_or_resume_generalization_study(
        _config(generalization_tasks(TASKS, ppo_overrides=TINY)), storage, "g"
    )
    out = tmp_path / "out"
    args = ["--study-name", "g", "--storage", storage, "--env-id", "Walker2d-v5", "--agents", "ppo"]
    args += ["--seeds", "4", "--training-steps", "256", "--out", str(out), "--no-save-models"]
    args += ["--quiet", "--ppo", "n_steps=256"]
    assert test_generalization_main(args) == 0
    assert (out / "agents/ppo/seed_4/settings.json").is_file()
    assert test_generalization_main(args) == 0  # same settings: skipped
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        test_generalization_main([*args, "gamma=0.9"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(err) == 1
    assert "ppo seed 4 differs in ppo.hyperparams.gamma" in err[0]
    assert test_generalization_main([*args, "gamma=0.9", "--overwrite"]) == 0
