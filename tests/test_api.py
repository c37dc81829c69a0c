"""The Python API at the package root: ``ermrl.Experiment``, ``ermrl.evolve``, ``ermrl.test``,
``ermrl.report``. The library code the commands run, returning results and raising the
project's errors instead of exiting. Real studies and real (tiny) training; nothing is mocked.
"""

from __future__ import annotations

import dataclasses
import io
import math
import subprocess
import sys
from pathlib import Path

import optuna
import pandas as pd
import pytest
import yaml

import ermrl
from ermrl.runner import NothingToReport, evolve_config
from ermrl.search import STUDY_COMMAND_ATTR, create_or_resume_study, select_trial
from ermrl.storage import load_study
from tests.test_run import TINY, write

ROOT = Path(__file__).resolve().parents[1]

# The evolve stage of TINY as keyword options: Pendulum with velocities hidden, 3 trials of
# one 256-step run each.
EVOLVE = dict(TINY["evolve"])


def test_import_ermrl_stays_light_and_resolves_the_api_on_first_use() -> None:
    code = (
        "import sys, ermrl\n"
        "print(sorted(m for m in ('ermrl.runner', 'torch', 'optuna', 'pandas') "
        "if m in sys.modules))\n"
        "import ermrl.runner as r\n"
        "print(ermrl.Experiment is r.Experiment and ermrl.evolve is r.evolve "
        "and ermrl.test is r.test and ermrl.report is r.report)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["[]", "True"]
    for name in ermrl.__all__:
        assert getattr(ermrl, name) is not None, name
    with pytest.raises(AttributeError, match="no attribute 'Experimnet'"):
        ermrl.Experimnet  # noqa: B018


def test_the_plan_of_a_file_is_the_dry_runs_and_writes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from ermrl.cli._run import run_main

    monkeypatch.chdir(tmp_path)  # the file's folders are relative to the working directory
    path = write(tmp_path, TINY)
    exp = ermrl.Experiment.load(path)
    assert exp.name == "tiny" and exp.out == Path("runs/tiny")
    plan = exp.plan()
    assert [s.stage for s in plan] == ["evolve", "reevaluate", "test", "report"]
    assert {s.task for s in plan} == {"Pendulum-v1"} and not any(s.done for s in plan)
    evolve, _, test, report = plan
    assert evolve.command.startswith("ermrl evolve --env-id Pendulum-v1 --observe positions")
    assert evolve.env_steps == 3 * 256 and evolve.seconds > 0 and evolve.status == "not started"
    assert test.folder == Path("runs/tiny/Pendulum-v1/test") and test.env_steps == 2 * 256
    assert report.env_steps == 0 and report.study_name == evolve.study_name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml"]
    assert run_main([str(path), "--dry-run"]) == 0
    printed = capsys.readouterr().out
    for step in (evolve, test, report):
        assert step.command in printed
    other = exp.plan(tasks=["CartPole-v1"])  # a task the file does not list: its settings
    assert {s.task for s in other} == {"CartPole-v1"}


def test_a_bad_file_raises_the_projects_error_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    path = write(tmp_path, {**TINY, "evolv": {}})
    with pytest.raises(ermrl.ExperimentError) as err:
        ermrl.Experiment.load(path)
    assert isinstance(err.value, ermrl.ConfigError)
    text = str(err.value)
    assert "\n" not in text and str(path) in text and "did you mean 'evolve'" in text
    with pytest.raises(ermrl.ExperimentError, match="no variant 'quik'"):
        ermrl.Experiment.load(write(tmp_path, TINY), variant="quik")
    # An option no command takes: the file loads, its plan and its run refuse it.
    bad = ermrl.Experiment.load(
        write(tmp_path, {**TINY, "evolve": {**EVOLVE, "n_trails": 3}}, "bad.yaml")
    )
    for call in (bad.plan, bad.run):
        with pytest.raises(ermrl.ExperimentError) as err:
            call()
        assert "\n" not in str(err.value) and "did you mean 'n_trials'" in str(err.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml", "exp.yaml"]


def test_a_run_returns_the_summary_and_the_selected_trial(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    exp = ermrl.Experiment.load(write(tmp_path, TINY))
    result = exp.run()
    assert capsys.readouterr().out == ""  # quiet: no plan, no stage lines, quiet commands
    assert result.name == "tiny" and result.out == Path("runs/tiny")
    assert (result.out / "experiment.resolved.yaml").is_file()
    task = result["Pendulum-v1"]
    assert task.study_name == "Pendulum-v1__positions__256steps"
    assert list(task.summary["agent"]) == ["ppo", "res-ppo"]
    assert all(math.isfinite(v) for v in task.summary["final_return_mean"])
    study = load_study(task.study_name, exp.storage)
    chosen, how = select_trial(study)
    assert task.trial == chosen.number and task.params == chosen.params
    assert "re-evaluated" in how  # the file re-evaluates the best: its ranking picks the trial
    assert task.test_folder == Path("runs/tiny/Pendulum-v1/test")
    assert task.report == Path("runs/tiny/Pendulum-v1/report/report.md")
    assert task.report.is_file()
    assert list(result.summary["task"]) == ["Pendulum-v1"] * 2
    assert all(s.done for s in exp.plan())
    # Again: every stage is done, and the run says so on the stream it is given.
    stream = io.StringIO()
    again = exp.run(quiet=False, stream=stream)
    assert stream.getvalue().count("skipped") == 4 and "total" in stream.getvalue()
    assert again["Pendulum-v1"].trial == task.trial
    pd.testing.assert_frame_equal(again["Pendulum-v1"].summary, task.summary)
    assert exp.result()["Pendulum-v1"].trial == task.trial
    with pytest.raises(KeyError, match="the tasks are Pendulum-v1"):
        result["CartPole-v1"]


def test_a_stage_that_fails_raises_stage_failed_and_leaves_nothing_behind(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The test stage before any evolution: the command stops (no study), the run raises
    instead of exiting, and removes the resolved file and the folders it created."""
    monkeypatch.chdir(tmp_path)
    exp = ermrl.Experiment.load(write(tmp_path, TINY))
    with pytest.raises(ermrl.StageFailed) as err:
        exp.run(stages=["test"])
    assert isinstance(err.value, ermrl.ExperimentError)
    assert (err.value.stage, err.value.label, err.value.code) == ("test", "Pendulum-v1", 2)
    assert str(err.value) == "stage test of Pendulum-v1 stopped (exit code 2)"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml"]


@pytest.fixture(scope="module")
def evolved(tmp_path_factory: pytest.TempPathFactory) -> ermrl.EvolveResult:
    storage = f"sqlite:///{tmp_path_factory.mktemp('evolve')}/ermrl.db"
    return ermrl.evolve("Pendulum-v1", storage, **EVOLVE, reevaluate_top=1, reevaluate_seeds=1)


def test_evolve_returns_the_studys_best_and_the_trial_a_test_selects(
    evolved: ermrl.EvolveResult,
) -> None:
    study = load_study(evolved.study_name, evolved.storage)
    assert isinstance(evolved.study, optuna.Study) and evolved.study.study_name == study.study_name
    assert evolved.study_name == "Pendulum-v1__positions__256steps"
    assert (
        evolved.n_trials == 3 == len(study.get_trials(states=(optuna.trial.TrialState.COMPLETE,)))
    )
    assert evolved.best_trial == study.best_trial.number
    assert evolved.best_params == study.best_params
    assert evolved.best_fitness == study.best_value
    chosen, how = select_trial(study)
    assert evolved.selected_trial == chosen.number and evolved.selection == how
    assert evolved.worker.trials_run == 3 and evolved.worker.completed == 3
    # The study keeps the command a shell would run to continue it.
    assert study.user_attrs[STUDY_COMMAND_ATTR].startswith(
        "ermrl evolve --env-id Pendulum-v1 --observe positions --units 20"
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        evolved.n_trials = 0  # type: ignore[misc]
    # Again on the finished study: nothing trains, the same answer.
    again = ermrl.evolve(
        "Pendulum-v1", evolved.storage, **EVOLVE, reevaluate_top=1, reevaluate_seeds=1
    )
    assert again.worker.trials_run == 0 and again.best_trial == evolved.best_trial


def test_evolve_takes_a_configuration_and_refuses_a_bad_option(tmp_path: Path) -> None:
    storage = f"sqlite:///{tmp_path}/x.db"
    with pytest.raises(ermrl.ExperimentError, match="did you mean 'n_trials'"):
        ermrl.evolve("Pendulum-v1", storage, n_trails=3)
    assert not (tmp_path / "x.db").exists()
    config = evolve_config("Pendulum-v1", **{**EVOLVE, "n_trials": 1})
    assert isinstance(config, ermrl.EvolveConfig) and config.search.n_trials == 1
    result = ermrl.evolve(config, storage, study_name="one")
    assert (result.study_name, result.n_trials) == ("one", 1)
    with pytest.raises(TypeError, match="n_trials"):
        ermrl.evolve(config, storage, n_trials=2)


@pytest.fixture(scope="module")
def tested(
    evolved: ermrl.EvolveResult, tmp_path_factory: pytest.TempPathFactory
) -> ermrl.TestResult:
    out = tmp_path_factory.mktemp("test") / "phase"
    return ermrl.test(
        evolved.study_name,
        evolved.storage,
        training_steps=256,
        seeds=[10, 11],
        agents=["ppo", "res-ppo"],
        out=out,
    )


def test_test_trains_the_selected_trial_and_holds_what_it_wrote(
    evolved: ermrl.EvolveResult, tested: ermrl.TestResult
) -> None:
    assert tested.study_name == evolved.study_name
    assert tested.trial == evolved.selected_trial
    assert (
        tested.params == load_study(evolved.study_name, evolved.storage).trials[tested.trial].params
    )
    assert tested.agents == ("ppo", "res-ppo") and tested.seeds == (10, 11)
    runs = sorted(zip(tested.returns["agent"], tested.returns["seed"]))
    assert runs == [("ppo", 10), ("ppo", 11), ("res-ppo", 10), ("res-ppo", 11)]
    assert all(math.isfinite(v) for v in tested.returns["final_return"])
    assert list(tested.summary["agent"]) == ["ppo", "res-ppo"]
    # The evolved agent against the others, as the report's comparison table.
    (row,) = tested.comparisons.itertuples(index=False)
    assert (row.candidate, row.baseline, row.n_candidate, row.n_baseline) == (
        "res-ppo", "ppo", 2, 2,
    )  # fmt: skip
    means = tested.returns.groupby("agent")["final_return"].mean()
    assert row.mean_diff == pytest.approx(means["res-ppo"] - means["ppo"])
    assert set(tested.files) == {
        "summary.csv", "curves.csv", "learning_curves.png", "config.yaml", "command.txt"
    }  # fmt: skip
    assert all(path.is_file() and path.parent == tested.out for path in tested.files.values())
    written = pd.read_csv(tested.files["summary.csv"])
    assert list(written["final_return_mean"]) == pytest.approx(
        list(tested.summary["final_return_mean"])
    )
    config = yaml.safe_load(tested.files["config.yaml"].read_text())
    assert config["trial"] == tested.trial and config["study_name"] == evolved.study_name
    # The same options as an object: the finished runs are kept, nothing trains again.
    options = ermrl.TestOptions(
        training_steps=256, seeds=[10, 11], agents=["ppo", "res-ppo"], out=tested.out
    )
    again = ermrl.test(evolved.study_name, evolved.storage, options)
    pd.testing.assert_frame_equal(again.returns, tested.returns)


def test_test_refuses_seeds_the_selection_used_and_writes_nothing(
    evolved: ermrl.EvolveResult, tmp_path: Path
) -> None:
    out = tmp_path / "phase"
    with pytest.raises(ermrl.ConfigError, match="test seeds already used"):
        ermrl.test(evolved.study_name, evolved.storage, training_steps=256, seeds=[0], out=out)
    with pytest.raises(
        ermrl.ConfigError, match=r"agents: invalid choice: 'res-pop' \(did you mean 'res-ppo'\?\)"
    ):
        ermrl.TestOptions(agents=["res-pop"])
    assert not out.exists()


def test_report_returns_the_paths_it_wrote(
    evolved: ermrl.EvolveResult, tested: ermrl.TestResult, tmp_path: Path
) -> None:
    result = ermrl.report(
        evolved.study_name,
        evolved.storage,
        runs=tested.out,
        out=tmp_path / "report",
        dynamics=False,
        interactive=False,
        html=False,
    )
    assert result.markdown == tmp_path / "report" / "report.md" and result.markdown.is_file()
    assert result.html is None
    assert {"optimization_history", "learning_curves", "final_returns"} <= set(result.figures)
    assert all(p.is_file() for p in [*result.figures.values(), *result.tables.values()])
    empty = f"sqlite:///{tmp_path}/empty.db"
    create_or_resume_study(None, empty, "empty")
    with pytest.raises(NothingToReport, match="no completed trial yet"):
        ermrl.report("empty", empty, out=tmp_path / "nothing")
    assert not (tmp_path / "nothing").exists()


@pytest.mark.slow
def test_the_example_script_runs_an_experiment_an_evolution_and_a_test(tmp_path: Path) -> None:
    """examples/run_demo.py on a tiny file with a `quick` variant (the demo's takes a minute)."""
    path = write(tmp_path, {**TINY, "variants": {"quick": {"reevaluate": {"top": 0}}}})
    done = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "run_demo.py"), str(path)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=900,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].split() == ["task", "agent", "final_return_mean"]
    assert any(line.startswith("best trial ") and "of 4" in line for line in lines)
    assert (tmp_path / "runs" / "tiny" / "quick" / "Pendulum-v1" / "test" / "summary.csv").is_file()
    assert (tmp_path / "runs" / "example.db").is_file()
    assert (tmp_path / "runs" / "CartPole-v1__all__2000steps" / "summary.csv").is_file()


def test_old_test_phase_package_name_warns_and_is_the_same_code():
    """``ermrl.experiments`` (the test phase's old name) still imports, with a warning, and its
    names and private modules are ``ermrl.test_phase``'s very objects (a script or a pickle that
    names the old module keeps working)."""
    import importlib
    import sys

    import ermrl.test_phase
    import ermrl.test_phase._test_phase

    for name in [
        m for m in sys.modules if m == "ermrl.experiments" or m.startswith("ermrl.experiments.")
    ]:
        del sys.modules[name]
    with pytest.warns(DeprecationWarning, match="renamed ermrl.test_phase"):
        old = importlib.import_module("ermrl.experiments")
    assert old.aggregate is ermrl.test_phase.aggregate
    assert old.__all__ == ermrl.test_phase.__all__
    assert importlib.import_module("ermrl.experiments._test_phase") is ermrl.test_phase._test_phase
