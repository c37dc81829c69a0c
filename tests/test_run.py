"""``ermrl run EXPERIMENT.yaml``: plans, refusals before anything is written, resumption.

Real CLI processes on real SQLite studies with real (tiny) training; nothing is mocked.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import optuna
import pytest
import yaml
from optuna.trial import TrialState

from ermrl.config import ConfigError
from ermrl.runner._experiment import ExperimentError, experiment_plan, load_experiment
from ermrl.storage import open_storage

ROOT = Path(__file__).resolve().parents[1]
PAPER = sorted((ROOT / "experiments" / "paper").glob("*.yaml"))


def ermrl(cwd: Path, *args: str, timeout: float = 900) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=timeout,
    )


def write(tmp_path: Path, doc: dict, name: str = "exp.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


# A tiny single-task experiment: Pendulum with velocities hidden, a few hundred steps per agent.
TINY = {
    "name": "tiny",
    "tasks": ["Pendulum-v1"],
    "evolve": {
        "observe": "positions",
        "units": 20,
        "n_trials": 3,
        "n_seeds": 1,
        "training_steps": 256,
        "n_envs": 1,
        "ppo": {"n_steps": 128, "batch_size": 64, "n_epochs": 2},
    },
    "reevaluate": {"top": 1, "seeds": 1},
    "test": {"agents": ["ppo", "res-ppo"], "seeds": [10], "training_steps": 256},
    "report": {"dynamics": False, "interactive": False, "html": False},
}


def test_paper_files_exist_with_a_quick_variant() -> None:
    names = {p.stem for p in PAPER}
    assert {"h1_partial_observability", "h2_locomotion", "h3_generalization"} <= names
    for path in PAPER:
        doc = yaml.safe_load(path.read_text())
        assert "quick" in doc["variants"], path
        # The header states the scale and how it differs from the paper's.
        head = path.read_text().split("\nname:")[0]
        assert "Scale" in head and "Differences from the paper" in head, path


def _run_counting_cpu(cmd: list[str], cwd: Path) -> tuple[subprocess.CompletedProcess[str], float]:
    """Run `cmd` and return it with the CPU seconds (user + system) it took: the work it did,
    whatever else the host runs at the same time."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, timeout=900)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return done, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


# What `ermrl run` imports before it plans: torch (through SB3), scipy, optuna, pandas.
LIBRARY = (
    "import ermrl.cli, ermrl.runner, ermrl.agents, ermrl.search, ermrl.test_phase, ermrl.analysis"
)


@pytest.mark.parametrize("path", PAPER, ids=lambda p: p.stem)
def test_dry_run_prints_the_plan_quickly_and_writes_nothing(tmp_path: Path, path: Path) -> None:
    done, cpu = _run_counting_cpu(
        [sys.executable, "-m", "ermrl", "run", str(path), "--dry-run"], tmp_path
    )
    # The library's import, measured side by side: on a 2-core host it is ~4 of the plan's
    # ~4.5 CPU seconds, and a slower or busier host scales both (one CI host took 10.4 s for
    # the whole plan). The plan's own work (reading the file, the agents' settings, the study
    # if there is one, the estimates) is what this test bounds.
    loaded, imports = _run_counting_cpu([sys.executable, "-c", LIBRARY], tmp_path)
    assert loaded.returncode == 0, loaded.stderr
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert "evolve" in out and "test" in out and "report" in out
    assert "ermrl evolve" in out and "--training-steps 300000" in out
    assert "M env steps" in out and "total" in out and "left" in out
    assert list(tmp_path.iterdir()) == []  # nothing written, no storage created
    # Target: the plan itself under 3 CPU seconds beyond the import (~0.5 s here).
    assert cpu - imports < 3, (cpu, imports)


def test_the_demo_is_an_experiment_file_the_makefile_runs() -> None:
    """make demo runs experiments/demo.yaml: its plan is the population backend end to end,
    with the unevolved reference among the candidates and in the test phase, at a budget the
    throughput table puts near 4 minutes on 2 cores."""
    makefile = (ROOT / "Makefile").read_text()
    assert "-m ermrl run experiments/demo.yaml" in makefile
    exp = load_experiment(ROOT / "experiments" / "demo.yaml")
    steps = experiment_plan(exp, build_agents=False)
    assert [s.stage for s in steps] == ["evolve", "reevaluate", "test", "report"]
    evolve, _, test, _ = steps
    for step in (evolve, test):
        assert step.argv[step.argv.index("--backend") + 1] == "population", step.argv
    assert "--no-reference-trial" not in evolve.argv
    assert {"random-res-ppo", "res-ppo", "ppo"} <= set(test.argv)
    assert 120 < sum(s.seconds for s in steps) < 360


def test_the_plan_counts_env_steps_from_the_file(tmp_path: Path) -> None:
    exp = load_experiment(ROOT / "experiments" / "paper" / "h2_locomotion.yaml")
    steps = experiment_plan(exp, tasks=["Swimmer-v5"], build_agents=False)
    by_stage = {s.stage: s for s in steps}
    # Each run trains whole rollouts of PPO's 2048 steps x 1 env (the paper's settings), as
    # SB3 does: 300,000 steps are 301,056 and 1,000,000 are 1,001,472, and the plan says so.
    assert by_stage["evolve"].env_steps == 100 * 3 * 301_056
    assert "budget of 300,000 steps rounds up to 301,056" in by_stage["evolve"].note
    assert by_stage["reevaluate"].env_steps == (3 + 1) * 3 * 301_056
    assert by_stage["test"].env_steps == 5 * 20 * 1_001_472  # 5 agents x seeds 10-29
    assert "rounds up to 1,001,472" in by_stage["test"].note
    assert by_stage["evolve"].seconds > 0
    # Per-task overrides change the scale of that task only.
    ant = experiment_plan(exp, tasks=["Ant-v5"], build_agents=False)[0]
    assert ant.env_steps == 60 * 3 * 301_056
    # A task the file does not list runs with the file's settings.
    hopper = experiment_plan(exp, tasks=["Hopper-v5"], build_agents=False)
    assert [s.label for s in hopper] == ["Hopper-v5"] * 4
    assert hopper[0].env_steps == 100 * 3 * 301_056 and "--fixed-input-scaling" in hopper[0].argv
    with pytest.raises(ExperimentError, match="NoSuchEnv-v0"):
        experiment_plan(exp, tasks=["NoSuchEnv-v0"], build_agents=False)
    gen = load_experiment(ROOT / "experiments" / "paper" / "h3_generalization.yaml")
    tests = [
        s for s in experiment_plan(gen, tasks=["Ant-v5"], build_agents=False) if s.stage == "test"
    ]
    assert [(s.command, s.label) for s in tests] == [("test-generalization", "Ant-v5")]


def test_a_variant_goes_to_its_own_folder_and_storage(tmp_path: Path) -> None:
    path = ROOT / "experiments" / "paper" / "h2_locomotion.yaml"
    full = load_experiment(path)
    quick = load_experiment(path, "quick")
    assert quick.out == full.out / "quick"
    assert quick.storage != full.storage
    assert quick.publish is None  # CI-sized results are never published
    assert [t.env_id for t in quick.tasks] == ["Swimmer-v5"]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"nmae": "x"}, "unknown key 'nmae' (did you mean 'name'?)"),
        (
            {"evolve": {**TINY["evolve"], "n_trails": 4}},
            "unknown key 'n_trails' (did you mean 'n_trials'?)",
        ),
        ({"evolve": {**TINY["evolve"], "n_trials": 0}}, "n_trials: must be positive, got 0"),
        ({"evolve": {**TINY["evolve"], "sr_rnage": [1, 2]}}, "(did you mean 'sr_range'?)"),
        ({"evolve": {**TINY["evolve"], "sampler": "annealing"}}, "invalid choice: 'annealing'"),
        ({"evolve": {**TINY["evolve"], "units": 20000}}, "units must be in [1, 10000]"),
        ({"test": {**TINY["test"], "agents": ["res-pop"]}}, "res-pop"),
        ({"reevaluate": {"tops": 2}}, "did you mean 'top'?"),
        ({"report": {"dynamic": True}}, "did you mean 'dynamics'?"),
        ({"tasks": ["NoSuchEnv-v0"]}, "NoSuchEnv-v0"),
        ({"tasks": []}, "tasks"),
        ({"evolve": {**TINY["evolve"], "storage": "sqlite:///x.db"}}, "set by ermrl run"),
        ({"evolve": {**TINY["evolve"], "fixed_input_scaling": "yes"}}, "'yes' is not a number"),
    ],
)
def test_a_bad_file_fails_in_one_line_before_anything_is_written(
    tmp_path: Path, change: dict, message: str
) -> None:
    path = write(tmp_path, {**TINY, **change})
    done = ermrl(tmp_path, "run", str(path))
    assert done.returncode == 2, done.stdout + done.stderr
    assert message in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml"]


def test_an_unknown_variant_and_an_unreadable_file_are_one_line(tmp_path: Path) -> None:
    path = write(tmp_path, TINY)
    done = ermrl(tmp_path, "run", str(path), "--variant", "qiuck")
    assert done.returncode == 2 and "no variant 'qiuck'" in done.stderr
    (tmp_path / "bad.yaml").write_text("name: [unclosed\n")
    done = ermrl(tmp_path, "run", "bad.yaml")
    assert done.returncode == 2 and "not valid YAML" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    done = ermrl(tmp_path, "run", "missing.yaml")
    assert done.returncode == 2 and "cannot read" in done.stderr


def test_a_file_that_contradicts_the_stored_study_is_refused(tmp_path: Path) -> None:
    path = write(tmp_path, TINY)
    exp = load_experiment(path)
    (step,) = [s for s in experiment_plan(exp, build_agents=False) if s.stage == "evolve"]
    # The same study, created with 30 units instead of the file's 20.
    argv = [a if a != "20" else "30" for a in step.argv]
    os.makedirs(tmp_path / "runs" / "tiny")
    created = ermrl(tmp_path, "study", "create", *argv)
    assert created.returncode == 0, created.stderr
    before = sorted(p.name for p in (tmp_path / "runs" / "tiny").iterdir())
    done = ermrl(tmp_path, "run", str(path))
    assert done.returncode == 2, done.stdout + done.stderr
    assert "evolved with other settings" in done.stderr and "units" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in (tmp_path / "runs" / "tiny").iterdir()) == before


def test_options_become_the_commands_own_flags() -> None:
    from ermrl._schema import to_argv, validate
    from ermrl.cli._evolve import build_evolve_parser
    from ermrl.runner._evolve_options import evolve_options

    cls = evolve_options()
    given = {
        "observe": "positions",
        "n_trials": 5,
        "fixed_input_scaling": True,
        "reference_trial": False,
        "sr_range": [0.01, 10],
        "ppo": {"learning_rate": 1.0e-4, "n_steps": 64},
    }
    values = validate(cls, given, "here", text=True)
    argv = to_argv(cls, given, values)
    assert argv == [
        "--observe", "positions", "--n-trials", "5", "--fixed-input-scaling",
        "--no-reference-trial", "--sr-range", "0.01", "10",
        "--ppo", "learning_rate=0.0001", "n_steps=64",
    ]  # fmt: skip
    args = build_evolve_parser().parse_args(["--env-id", "Pendulum-v1", *argv])
    assert isinstance(args, argparse.Namespace) and args.fixed_input_scaling == 1.0
    assert values["fixed_input_scaling"] == 1.0 and values["sr_range"] == (0.01, 10.0)
    with pytest.raises(ConfigError, match="here: reference_trial: true or false"):
        validate(cls, {"reference_trial": 3}, "here", text=True)
    with pytest.raises(ConfigError, match="here: n_trials: a number is expected, got list"):
        validate(cls, {"n_trials": [1, 2]}, "here", text=True)
    with pytest.raises(ConfigError, match="here: sr_range: 2 values are expected, got 3"):
        validate(cls, {"sr_range": [1, 2, 3]}, "here", text=True)


def _load(url: str, name: str) -> optuna.Study:
    return optuna.load_study(study_name=name, storage=open_storage(url))


def test_a_piece_of_the_test_phase_plans_only_its_runs() -> None:
    from ermrl.runner._run import check_test_piece, plan_experiment

    exp = load_experiment(ROOT / "experiments" / "paper" / "h2_locomotion.yaml")

    def test_step(**piece: list) -> object:  # noqa: ANN003
        _, steps, _ = plan_experiment(exp, tasks=["Swimmer-v5"], build_agents=False, **piece)
        return next(s for s in steps if s.stage == "test")

    whole = test_step()
    piece = test_step(test_agents=["leaky-res-ppo", "res-ppo"], test_seeds=[15, 10])
    # The file's order, whatever the order given; only the piece's runs are counted.
    assert piece.argv[piece.argv.index("--agents") + 1 :][:3] == ["res-ppo", "leaky-res-ppo",
                                                                   "--seeds"]  # fmt: skip
    assert piece.argv[piece.argv.index("--seeds") + 1 :][:3] == ["10", "15", "--eval"]
    assert piece.env_steps == 2 * 2 * 1_001_472 and whole.env_steps == 5 * 20 * 1_001_472
    # The report replays the whole phase's first seed: a piece trains it again only if it
    # holds that run.
    assert whole.replayed == (("res-ppo", 10), ("random-res-ppo", 10))
    assert piece.replayed == (("res-ppo", 10),)
    assert test_step(test_seeds=[15]).replayed == ()
    with pytest.raises(ExperimentError, match=r"--agents lstm-ppo: not in the stage's agents"):
        test_step(test_agents=["res-ppo", "lstm-ppo"])
    with pytest.raises(ExperimentError, match=r"--seeds 3 99: not in the stage's seeds \(10 "):
        test_step(test_seeds=[3, 99, 10])
    check_test_piece(["test"], ["ppo"], [])
    for stages in (None, ["test", "report"], ["evolve"]):
        with pytest.raises(ExperimentError, match="give --stage test alone"):
            check_test_piece(stages, [], [10])


def test_the_pieces_of_a_test_phase_add_to_its_records(tmp_path: Path) -> None:
    """Each piece's config.yaml, command.txt and summary used to describe that piece alone, so
    a phase run in pieces published files that listed its last piece's agents and seeds."""
    import pandas as pd

    from ermrl.config import ConfigError, EncoderConfig, PPOConfig, ReservoirParams, TaskConfig
    from ermrl.test_phase import AgentSpec, TestSettings, run_comparison

    task = TaskConfig("Pendulum-v1", "positions")
    reservoirs = (ReservoirParams(units=10, sr=0.5, lr=0.5),)
    ppo = PPOConfig(hyperparams={"n_steps": 128, "batch_size": 64, "n_epochs": 1})
    meta = {"study_name": "s", "trial": 3}

    def piece(agent: AgentSpec, seed: int, steps: int = 256, command: str = "") -> pd.DataFrame:
        return run_comparison(
            task, EncoderConfig(reservoirs=reservoirs), ppo, [agent],
            TestSettings(training_steps=steps, seeds=(seed,), out=tmp_path),
            metadata=meta, quiet=True, command=command or f"ermrl test {agent.name} {seed}",
        )  # fmt: skip

    piece(AgentSpec("res-ppo", reservoirs), 2)
    meta = {"study_name": "s", "trial": None}  # a piece of agents without the selection
    summary = piece(AgentSpec("ppo", None), 1)
    meta = {"study_name": "s", "trial": 3}
    config = yaml.safe_load((tmp_path / "config.yaml").read_text())
    # The registry's order, whatever the pieces' order; every piece's seeds.
    assert list(config["agents"]) == ["ppo", "res-ppo"] and config["settings"]["seeds"] == [1, 2]
    assert config["agents"]["res-ppo"][0]["sr"] == 0.5 and config["trial"] == 3
    assert list(summary["agent"]) == ["ppo", "res-ppo"]
    assert list(pd.read_csv(tmp_path / "summary.csv")["agent"]) == ["ppo", "res-ppo"]
    lines = (tmp_path / "command.txt").read_text().splitlines()
    assert lines == ["ermrl test res-ppo 2", "ermrl test ppo 1"]
    piece(AgentSpec("ppo", None), 1)  # the same piece again: nothing new to record
    assert yaml.safe_load((tmp_path / "config.yaml").read_text())["trial"] == 3
    assert (tmp_path / "command.txt").read_text().splitlines() == lines
    # Another budget is another phase, refused while the folder holds this one's runs.
    other = AgentSpec("random-res-ppo", (ReservoirParams(units=10),))
    with pytest.raises(ConfigError, match="other settings"):
        piece(other, 4, steps=512)
    # Another selected trial: its records replace the folder's, as before pieces existed.
    meta["trial"] = 4
    summary = piece(other, 4, command="ermrl test other")
    config = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert list(config["agents"]) == ["random-res-ppo"] and config["settings"]["seeds"] == [4]
    assert list(summary["agent"]) == ["random-res-ppo"] and config["trial"] == 4
    assert (tmp_path / "command.txt").read_text() == "ermrl test other\n"


def test_a_test_phase_run_in_pieces_then_whole(tmp_path: Path) -> None:
    path = write(tmp_path, {**TINY, "test": {**TINY["test"], "seeds": [10, 11]}})
    refused = ermrl(tmp_path, "run", str(path), "--agents", "ppo")
    assert refused.returncode == 2 and "give --stage test alone" in refused.stderr
    assert refused.stderr.count("\n") == 1 and not (tmp_path / "runs").exists()
    evolved = ermrl(tmp_path, "run", str(path), "--stage", "evolve", "--progress", "none")
    assert evolved.returncode == 0, evolved.stderr
    piece = ermrl(tmp_path, "run", str(path), "--stage", "test", "--agents", "ppo", "--seeds",
                  "11", "--progress", "none")  # fmt: skip
    assert piece.returncode == 0, piece.stdout + piece.stderr
    runs = tmp_path / "runs" / "tiny" / "Pendulum-v1" / "test" / "agents"
    trained = sorted(p.parent.relative_to(runs).as_posix() for p in runs.rglob("result.json"))
    assert trained == ["ppo/seed_11"]
    # The same piece again is done; the whole file then trains the other runs and reports.
    again = ermrl(tmp_path, "run", str(path), "--stage", "test", "--agents", "ppo", "--seeds",
                  "11", "--dry-run")  # fmt: skip
    assert "[done] test" in again.stdout and "1/1 runs" in again.stdout, again.stdout
    whole = ermrl(tmp_path, "run", str(path), "--progress", "none")
    assert whole.returncode == 0, whole.stdout + whole.stderr
    assert "[skip] ppo seed 11" in whole.stdout, whole.stdout
    trained = sorted(p.parent.relative_to(runs).as_posix() for p in runs.rglob("result.json"))
    assert trained == ["ppo/seed_10", "ppo/seed_11", "res-ppo/seed_10", "res-ppo/seed_11"]
    assert (tmp_path / "runs" / "tiny" / "Pendulum-v1" / "report" / "report.md").exists()


def test_a_run_finishes_every_stage_then_skips_them_all(tmp_path: Path) -> None:
    path = write(tmp_path, TINY)
    done = ermrl(tmp_path, "run", str(path), "--progress", "none")
    assert done.returncode == 0, done.stdout + done.stderr
    # --progress reaches the evolve and test commands (a pipe's default would be lines).
    # A progress line reads "[label] done/total steps (pct%) | rate | ETA"; trial and run summary
    # lines (printed in every mode) have no "(pct%)".
    progress_line = re.compile(r"/[\d,]+ steps[^|\n]* \(\d+%\) \|")
    assert not progress_line.search(done.stdout) and "[run 2/2]" in done.stdout, done.stdout
    out = tmp_path / "runs" / "tiny"
    # The plan is printed at the start of the real run too.
    assert done.stdout.index("total") < done.stdout.index("[evolve Pendulum-v1]")
    resolved = yaml.safe_load((out / "experiment.resolved.yaml").read_text())
    evolve = resolved["commands"][0]
    # Every default is filled in, not only what the file set.
    assert evolve["options"]["sampler"] == "cmaes" and evolve["options"]["n_trials"] == 3
    assert evolve["options"]["reevaluate_top"] == 1 and "grace_period" in evolve["options"]
    assert (out / "Pendulum-v1" / "test" / "summary.csv").exists()
    assert (out / "Pendulum-v1" / "report" / "report.md").exists()
    # The test folder records the command that made it, not `ermrl run FILE`.
    command = (out / "Pendulum-v1" / "test" / "command.txt").read_text()
    assert command.startswith("ermrl test ") and "--study-name" in command, command
    study = _load(f"sqlite:///{out}/ermrl.db", "Pendulum-v1__positions__256steps")
    assert study.user_attrs["ermrl_reevaluation"]["complete"]
    again = ermrl(tmp_path, "run", str(path))
    assert again.returncode == 0, again.stderr
    assert again.stdout.count("skipped, already done: ") == 4, again.stdout
    # The rerun shows the results again: the summary table and where the report is.
    assert f"results of Pendulum-v1: {Path('runs/tiny/Pendulum-v1/test/summary.csv')}" in (
        again.stdout
    )
    assert re.search(r"^  +agent +n_seeds +final_return_mean", again.stdout, re.M), again.stdout
    assert "report of Pendulum-v1: runs/tiny/Pendulum-v1/report/report" in again.stdout
    assert len(_load(f"sqlite:///{out}/ermrl.db", study.study_name).get_trials()) == 3


def _wait_for(predicate, timeout: float, log: Path, proc=None) -> None:  # noqa: ANN001
    """Poll ``predicate``; fail at ``timeout``, or at once when ``proc`` has ended first."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        if proc is not None and proc.poll() is not None:
            raise AssertionError(
                f"the run ended (exit {proc.returncode}) first; log:\n{log.read_text()}"
            )
        time.sleep(0.2)
    raise AssertionError(f"timed out; log:\n{log.read_text()}")


def _start(tmp_path: Path, args: list[str], log_name: str) -> tuple[subprocess.Popen, Path]:
    log_path = tmp_path / log_name
    log = open(log_path, "w")  # noqa: SIM115 (closed by the process's end)
    proc = subprocess.Popen(
        [sys.executable, "-m", "ermrl", *args],
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        cwd=tmp_path,
    )
    return proc, log_path


@pytest.mark.slow
def test_a_quick_paper_file_survives_kill_9_in_evolution_and_in_the_test(tmp_path: Path) -> None:
    """Killed during evolution and again during the test, the rerun trains nothing twice."""
    path = ROOT / "experiments" / "paper" / "h1_partial_observability.yaml"
    exp = load_experiment(path, "quick")
    out = tmp_path / exp.out
    url = f"sqlite:///{out}/ermrl.db"
    name = "Pendulum-v1__positions__2048steps"
    args = ["run", str(path), "--variant", "quick"]

    def running() -> bool:
        try:
            return bool(_load(url, name).get_trials(states=[TrialState.RUNNING]))
        except Exception:  # the study does not exist yet
            return False

    proc, log = _start(tmp_path, args, "first.log")
    _wait_for(running, 300, log, proc)
    time.sleep(1.0)  # inside the generation's training
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)
    killed = {t.number for t in _load(url, name).get_trials(states=[TrialState.RUNNING])}
    assert killed

    test_dir = out / "Pendulum-v1" / "test" / "agents"

    def some_runs_done() -> bool:
        return len(list(test_dir.glob("*/seed_*/result.json"))) >= 2

    proc, log = _start(tmp_path, args, "second.log")
    _wait_for(some_runs_done, 600, log, proc)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)
    finished = {p: p.stat().st_mtime_ns for p in test_dir.glob("*/seed_*/result.json")}
    total = 4 * 2  # the quick variant: 4 agents x 2 seeds
    assert 2 <= len(finished) < total, finished

    done = ermrl(tmp_path, *args)
    assert done.returncode == 0, done.stdout + done.stderr
    trials = _load(url, name).get_trials()
    states = Counter(t.state for t in trials)
    # The killed generation's trials failed and were retried; no finished trial ran again.
    assert states[TrialState.COMPLETE] == 3, states
    assert {t.number for t in trials if t.state == TrialState.FAIL} == killed
    complete = [t for t in trials if t.state == TrialState.COMPLETE]
    assert len({tuple(sorted(t.params.items())) for t in complete}) == 3
    # The test runs that had finished were not trained again; the others were.
    after = {p: p.stat().st_mtime_ns for p in test_dir.glob("*/seed_*/result.json")}
    assert len(after) == total
    assert all(after[p] == mtime for p, mtime in finished.items())
    assert "skip" in done.stdout
    assert (out / "Pendulum-v1" / "report" / "report.md").exists()


def test_a_snapshot_carries_an_unfinished_evolution_to_a_fresh_machine(tmp_path: Path) -> None:
    """Stop part-way, snapshot to the published folder, lose runs/: the run resumes from it."""
    path = write(tmp_path, {**TINY, "publish": "published"})
    exp = load_experiment(path)
    (step,) = [s for s in experiment_plan(exp, build_agents=False) if s.stage == "evolve"]
    # Two of the three trials, by the evolve command the file composes.
    partial = [a if a != "3" else "2" for a in step.argv]
    (tmp_path / "runs" / "tiny").mkdir(parents=True)
    done = ermrl(tmp_path, "evolve", *partial)
    assert done.returncode == 0, done.stderr
    snap = ermrl(tmp_path, "run", str(path), "--snapshot")
    assert snap.returncode == 0, snap.stderr
    snapshot = tmp_path / "published" / "Pendulum-v1" / "study.json"
    assert snapshot.exists() and "2 trials" in snap.stdout
    original = {
        t.number: t.params
        for t in _load(f"sqlite:///{tmp_path}/runs/tiny/ermrl.db", step.study_name).get_trials()
    }
    # A fresh machine: the committed files only.
    import shutil

    shutil.rmtree(tmp_path / "runs")
    plan = ermrl(tmp_path, "run", str(path), "--dry-run")
    assert plan.returncode == 0 and "2 finished trials, imported when run" in plan.stdout
    assert not (tmp_path / "runs").exists()
    done = ermrl(tmp_path, "run", str(path))
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"imported {snapshot.relative_to(tmp_path)}" in done.stdout
    trials = _load(f"sqlite:///{tmp_path}/runs/tiny/ermrl.db", step.study_name).get_trials()
    assert [t.number for t in trials] == [0, 1, 2]
    assert all(t.state == TrialState.COMPLETE for t in trials)
    assert {t.number: t.params for t in trials if t.number < 2} == original
    # The evolution went on from the stored CMA-ES state, not from a new start.
    assert trials[2].system_attrs.get("cma:n_restarts", 0) == 0
    assert (tmp_path / "published" / "Pendulum-v1" / "test" / "summary.csv").exists()
    assert (tmp_path / "published" / "Pendulum-v1" / "report" / "report.md").exists()


@pytest.mark.slow
def test_a_snapshot_carries_an_unfinished_test_phase_to_a_fresh_machine(tmp_path: Path) -> None:
    """The finished test runs go with the snapshot; on a fresh machine they are not retrained,
    except the runs whose models the report replays (a published run has no model)."""
    doc = {
        **TINY,
        "publish": "published",
        "test": {"agents": ["ppo", "random-res-ppo", "res-ppo"], "seeds": [10, 11],
                 "training_steps": 256},
        "report": {"dynamics": True, "interactive": False, "html": False},
    }  # fmt: skip
    path = write(tmp_path, doc)
    evolved = ermrl(tmp_path, "run", str(path), "--stage", "evolve")
    assert evolved.returncode == 0, evolved.stdout + evolved.stderr
    exp = load_experiment(path)
    (test,) = [s for s in experiment_plan(exp, build_agents=False) if s.stage == "test"]
    assert test.replayed == (("res-ppo", 10), ("random-res-ppo", 10))
    # Half of the test phase (seed 10 of each agent), by the test command the file composes.
    i = test.argv.index("--seeds")
    half = test.argv[: i + 1] + ["10"] + test.argv[i + 3 :]
    done = ermrl(tmp_path, "test", *half)
    assert done.returncode == 0, done.stdout + done.stderr
    snap = ermrl(tmp_path, "run", str(path), "--snapshot")
    assert snap.returncode == 0, snap.stderr
    assert "published 3 finished test runs of Pendulum-v1" in snap.stdout
    published = tmp_path / "published" / "Pendulum-v1" / "test" / "agents"
    assert sorted(p.parent.parent.name for p in published.glob("*/seed_10/result.json")) == [
        "ppo", "random-res-ppo", "res-ppo",
    ]  # fmt: skip
    assert not list(published.rglob("*.zip")) and not list(published.rglob("*.pt"))
    kept = (published / "ppo" / "seed_10" / "result.json").read_text()
    replayed = (published / "res-ppo" / "seed_10" / "result.json").read_text()

    import shutil

    shutil.rmtree(tmp_path / "runs")  # a fresh machine: the committed files only
    done = ermrl(tmp_path, "run", str(path))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "restored 1 finished test run of Pendulum-v1" in done.stdout
    assert "trained again for the model the report replays, their published results kept: " \
        "random-res-ppo seed 10, res-ppo seed 10" in done.stdout  # fmt: skip
    assert "[skip] ppo seed 10" in done.stdout
    runs = tmp_path / "runs" / "tiny" / "Pendulum-v1" / "test" / "agents"
    assert (runs / "ppo" / "seed_10" / "result.json").read_text() == kept
    assert len(list(runs.glob("*/seed_*/result.json"))) == 6
    assert (runs / "res-ppo" / "seed_10" / "policy.pt").exists()
    assert (runs / "res-ppo" / "seed_10" / "result.json").read_text() == replayed
    assert (runs / "res-ppo" / "seed_10" / "replay-model.json").is_file()
    report = tmp_path / "runs" / "tiny" / "Pendulum-v1" / "report"
    assert list((report / "dynamics").glob("res-ppo_seed10_*")), sorted(report.rglob("*"))
    # The report says the replayed policy is a retrained one, and both returns.
    again = json.loads((runs / "res-ppo" / "seed_10" / "replay-model.json").read_text())
    text = " ".join((report / "report.md").read_text().split())
    assert (
        f"`res-ppo` seed 10's model was trained again for this replay (same settings and seed; "
        f"published runs carry no model): its training ended at a return of "
        f"{again['final_return']:.4g}, the published run's at "
        f"{json.loads(replayed)['final_return']:.4g}"
    ) in text
    assert "`random-res-ppo` seed 10's model was trained again" in text


@pytest.mark.slow
def test_a_run_killed_in_its_test_phase_has_already_published_its_finished_runs(
    tmp_path: Path,
) -> None:
    """--snapshot-every: a run killed with -9 (a sitting's end) loses at most that much."""
    doc = {
        **TINY,
        "publish": "published",
        # 16k steps: each group of runs trains for seconds, several snapshot ticks, so the
        # check below sees the first group published while the second still trains (at 2048
        # steps the whole phase could end inside one tick).
        "test": {"agents": ["ppo", "random-res-ppo", "res-ppo"], "seeds": [10, 11, 12],
                 "training_steps": 16384, "n_procs": 1},
    }  # fmt: skip
    path = write(tmp_path, doc)
    runs = tmp_path / "runs" / "tiny" / "Pendulum-v1" / "test" / "agents"
    published = tmp_path / "published" / "Pendulum-v1"

    def published_mid_test() -> bool:
        finished = len(list(runs.glob("*/seed_*/result.json")))
        carried = len(list((published / "test" / "agents").glob("*/seed_*/result.json")))
        return carried >= 1 and finished < 9

    proc, log = _start(tmp_path, ["run", str(path), "--snapshot-every", "0.5"], "run.log")
    _wait_for(published_mid_test, 600, log, proc)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)
    # The evolution's study and the finished runs are in the published folder, each run whole.
    assert (published / "study.json").exists()
    carried = [p.parent for p in (published / "test" / "agents").glob("*/seed_*/result.json")]
    assert carried
    for run in carried:
        assert sorted(f.name for f in run.iterdir()) == [
            "episodes.csv", "result.json", "settings.json",
        ], run  # fmt: skip
    assert not (published / "test" / "summary.csv").exists()  # the phase did not finish
    assert (published / "test" / "config.yaml").exists()  # what it trains, for the page
    bad = ermrl(tmp_path, "run", str(path), "--snapshot-every", "-1")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
    assert "--snapshot-every" in bad.stderr


@pytest.mark.slow
def test_a_run_stopped_with_ctrl_c_snapshots_what_finished_since_the_last_tick(
    tmp_path: Path,
) -> None:
    """Ctrl-C between two snapshot ticks (an hour apart here): the run writes one more
    snapshot on its way out, so the trials finished since the last tick are not lost."""
    doc = {**TINY, "publish": "published", "evolve": {**TINY["evolve"], "n_trials": 500}}
    path = write(tmp_path, doc)
    proc, log = _start(tmp_path, ["run", str(path), "--snapshot-every", "3600"], "run.log")
    _wait_for(lambda: "[trial 1 |" in log.read_text(), 600, log, proc)
    os.killpg(proc.pid, signal.SIGINT)
    assert proc.wait(60) == 130, log.read_text()
    snapshot = json.loads((tmp_path / "published" / "Pendulum-v1" / "study.json").read_text())
    complete = [t["number"] for t in snapshot["trials"] if t["state"] == "COMPLETE"]
    assert {0, 1} <= set(complete), log.read_text()
    assert len(snapshot["trials"]) < 500


def test_a_run_with_a_file_too_large_to_publish_is_not_carried(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run is carried whole or not at all: a result.json without its episodes would be
    a damaged run on the next machine."""
    import ermrl.runner._publish as publish

    monkeypatch.chdir(tmp_path)  # the file's folders are relative to the working directory
    path = write(tmp_path, {**TINY, "publish": "published"})
    exp = load_experiment(path)
    (test,) = [s for s in experiment_plan(exp, build_agents=False) if s.stage == "test"]
    assert test.folder is not None
    for agent, size in (("ppo", 10), ("res-ppo", 5000)):
        run = test.folder / "agents" / agent / "seed_10"
        run.mkdir(parents=True)
        (run / "settings.json").write_text("{}")
        (run / "episodes.csv").write_text("x" * size)
        (run / "result.json").write_text("{}")
        (run / "policy.pt").write_bytes(b"model")
    (test.folder / "agents" / "ppo" / "seed_11").mkdir()  # unfinished: no result.json
    (test.folder / "config.yaml").write_text("trial: 7\n")  # written as the phase starts
    monkeypatch.setattr(publish, "PUBLISH_MAX_BYTES", 1000)
    assert publish.publish_finished_runs(exp, test) == 1
    assert (tmp_path / "published" / "Pendulum-v1" / "test" / "config.yaml").read_text() == (
        "trial: 7\n"
    )
    dest = tmp_path / "published" / "Pendulum-v1" / "test" / "agents"
    assert sorted(p.name for p in (dest / "ppo" / "seed_10").iterdir()) == [
        "episodes.csv", "result.json", "settings.json",
    ]  # fmt: skip
    assert not (dest / "res-ppo").exists() and not (dest / "ppo" / "seed_11").exists()


def test_a_run_trained_again_for_its_model_keeps_its_published_result(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A published run has no model, so the run the report replays is trained again on the next
    machine. Its published records are kept and put back as that training ends: the same seed
    trained in another population layout returned -662 where the published run had -1136 (H1
    Pendulum), and that second value silently replaced the first."""

    import ermrl.runner._publish as publish
    from ermrl.test_phase._results import keep_published_record

    monkeypatch.chdir(tmp_path)
    path = write(tmp_path, {**TINY, "publish": "published",
                            "report": {"dynamics": True, "interactive": False, "html": False}})  # fmt: skip
    exp = load_experiment(path)
    (test,) = [s for s in experiment_plan(exp, build_agents=False) if s.stage == "test"]
    assert test.folder is not None and ("res-ppo", 10) in test.replayed
    published = tmp_path / "published" / "Pendulum-v1" / "test" / "agents"
    for agent, ret in (("ppo", -1500.0), ("res-ppo", -1136.0)):
        run = published / agent / "seed_10"
        run.mkdir(parents=True)
        (run / "settings.json").write_text(json.dumps({"agent": agent}))
        (run / "episodes.csv").write_text(f"env_step,episode_return\n200,{ret}\n")
        (run / "result.json").write_text(json.dumps({"agent": agent, "final_return": ret}))

    assert publish.restore_finished_runs(exp, test) == (1, [("res-ppo", 10)])
    target = test.folder / "agents" / "res-ppo" / "seed_10"
    assert not (target / "result.json").exists()  # to be trained: its model is needed
    # The new training ends; a periodic snapshot before the records are back publishes nothing
    # of it.
    (target / "settings.json").write_text(json.dumps({"agent": "res-ppo"}))
    (target / "episodes.csv").write_text("env_step,episode_return\n200,-662.0\n")
    (target / "result.json").write_text(json.dumps({"agent": "res-ppo", "final_return": -662.0}))
    (target / "model.zip").write_bytes(b"model")
    publish.publish_finished_runs(exp, test)
    assert (
        json.loads((published / "res-ppo" / "seed_10" / "result.json").read_text())["final_return"]
        == -1136.0
    )
    assert keep_published_record(target) == -1136.0  # what the test phase does as it ends
    assert json.loads((target / "result.json").read_text())["final_return"] == -1136.0
    assert "-1136" in (target / "episodes.csv").read_text()
    assert (target / "model.zip").read_bytes() == b"model"  # the replay's model stays
    assert json.loads((target / "replay-model.json").read_text())["final_return"] == -662.0
    assert not (target / "published-record").exists()
    assert keep_published_record(target) is None  # done once
    publish.publish_finished_runs(exp, test)
    carried = published / "res-ppo" / "seed_10"
    assert json.loads((carried / "result.json").read_text())["final_return"] == -1136.0
    assert (carried / "replay-model.json").is_file() and not (carried / "model.zip").exists()


def test_a_piece_on_a_fresh_machine_adds_to_the_published_phase_records(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A phase's config.yaml and command.txt go with its published runs and come back with
    them. Before, a piece run on a fresh machine found its run folders restored but no
    config.yaml, so its records (the agents and seeds config.yaml lists, the summary's agents,
    command.txt) described that piece alone: H2 Ant-v5's seeds 22-29 piece published a
    summary without ppo and a command.txt without the earlier pieces."""

    import pandas as pd

    import ermrl.runner._publish as publish
    from ermrl.config import EncoderConfig, PPOConfig, ReservoirParams, TaskConfig
    from ermrl.test_phase import AgentSpec, TestSettings, run_comparison

    monkeypatch.chdir(tmp_path)
    path = write(tmp_path, {**TINY, "publish": "published"})
    exp = load_experiment(path)
    (test,) = [s for s in experiment_plan(exp, build_agents=False) if s.stage == "test"]
    assert test.folder is not None
    task = TaskConfig("Pendulum-v1", "positions")
    reservoirs = (ReservoirParams(units=10, sr=0.5, lr=0.5),)
    ppo = PPOConfig(hyperparams={"n_steps": 128, "batch_size": 64, "n_epochs": 1})

    def piece(agent: AgentSpec, seed: int) -> pd.DataFrame:
        return run_comparison(
            task, EncoderConfig(reservoirs=reservoirs), ppo, [agent],
            TestSettings(training_steps=256, seeds=(seed,), out=test.folder),
            metadata={"study_name": "s", "trial": 3}, quiet=True,
            command=f"ermrl test {agent.name} {seed}",
        )  # fmt: skip

    piece(AgentSpec("ppo", None), 10)  # the first sitting: one piece, then a snapshot
    assert publish.publish_finished_runs(exp, test) == 1
    source = tmp_path / "published" / "Pendulum-v1" / "test"
    assert (source / "command.txt").read_text() == "ermrl test ppo 10\n"

    import shutil

    shutil.rmtree(tmp_path / "runs")  # a fresh machine: the committed files only
    assert publish.restore_finished_runs(exp, test) == (1, [])
    assert (test.folder / "config.yaml").read_bytes() == (source / "config.yaml").read_bytes()
    summary = piece(AgentSpec("res-ppo", reservoirs), 11)  # the next sitting's piece
    assert list(summary["agent"]) == ["ppo", "res-ppo"]
    config = yaml.safe_load((test.folder / "config.yaml").read_text())
    assert list(config["agents"]) == ["ppo", "res-ppo"] and config["settings"]["seeds"] == [10, 11]
    lines = (test.folder / "command.txt").read_text().splitlines()
    assert lines == ["ermrl test ppo 10", "ermrl test res-ppo 11"]
    # Records the folder already has are its own: a restore leaves them alone.
    (test.folder / "command.txt").write_text("ermrl test mine\n")
    publish.restore_finished_runs(exp, test)
    assert (test.folder / "command.txt").read_text() == "ermrl test mine\n"
    assert json.loads((source / "agents" / "ppo" / "seed_10" / "result.json").read_text())


def test_the_test_phase_puts_a_kept_record_back_before_its_summary(tmp_path: Path) -> None:
    """The run trained again for its model ends with its published records back, so the
    summary, the curves and the page read the published result."""
    import io

    import pandas as pd

    from ermrl.config import EncoderConfig, PPOConfig, ReservoirParams, TaskConfig
    from ermrl.test_phase import AgentSpec, TestSettings, run_comparison

    reservoirs = (ReservoirParams(units=20, sr=0.9, lr=0.5),)
    kept = tmp_path / "test" / "agents" / "res-ppo" / "seed_3" / "published-record"
    kept.mkdir(parents=True)
    (kept / "settings.json").write_text(json.dumps({"agent": "res-ppo"}))
    (kept / "episodes.csv").write_text("env_step,episode_return\n256,-1.5\n")
    (kept / "result.json").write_text(
        json.dumps({"agent": "res-ppo", "seed": 3, "final_return": -1.5})
    )
    stream = io.StringIO()
    summary = run_comparison(
        TaskConfig("Pendulum-v1", "positions"),
        EncoderConfig(reservoirs=reservoirs),
        PPOConfig(hyperparams={"n_steps": 128, "batch_size": 64, "n_epochs": 2}, backend="sb3"),
        [AgentSpec("res-ppo", reservoirs)],
        TestSettings(training_steps=256, seeds=(3,), out=tmp_path / "test"),
        stream=stream,
    )
    assert summary.set_index("agent").loc["res-ppo", "final_return_mean"] == -1.5
    assert "published run's -1.5 kept" in stream.getvalue()
    run = kept.parent
    assert (run / "model.zip").is_file() and not kept.exists()
    assert json.loads((run / "replay-model.json").read_text())["final_return"] != -1.5
    assert pd.read_csv(tmp_path / "test" / "curves.csv")["episode_return"].tolist() == [-1.5]


def test_the_plan_counts_a_snapshots_finished_trials_as_done(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run that continues from a snapshot is estimated for the trials still to train only."""

    from ermrl.runner._run import step_status as _status

    monkeypatch.chdir(tmp_path)  # the file's paths are relative to where ermrl runs
    path = write(tmp_path, {**TINY, "publish": "published"})
    exp = load_experiment(path)
    (step,) = [s for s in experiment_plan(exp, build_agents=False) if s.stage == "evolve"]
    snapshot = tmp_path / "published" / "Pendulum-v1" / "study.json"
    snapshot.parent.mkdir(parents=True)
    states = ["COMPLETE", "COMPLETE", "RUNNING"]
    snapshot.write_text(json.dumps({"trials": [{"state": s} for s in states]}))
    done, left, text = _status(exp, step)
    assert not done
    assert left == pytest.approx(1 / 3)  # 2 of the 3 trials finished; the running one is redone
    assert "2 finished trials" in text
    snapshot.write_text("{not json")
    assert _status(exp, step)[1] == 1.0 and "unreadable" in _status(exp, step)[2]


def test_the_plan_counts_published_test_runs_as_done_but_the_replayed_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a fresh clone the test phase's published runs are put back when it runs: the plan's
    estimate is for the runs still to train, the report's replayed run among them."""
    from ermrl.runner._run import step_status as _status

    monkeypatch.chdir(tmp_path)
    test = {**TINY["test"], "seeds": [10, 11]}
    doc = {**TINY, "test": test, "publish": "published",
           "report": {**TINY["report"], "dynamics": True}}  # fmt: skip
    exp = load_experiment(write(tmp_path, doc))
    (step,) = [s for s in experiment_plan(exp, build_agents=False) if s.stage == "test"]
    assert step.replayed == (("res-ppo", 10),)
    assert _status(exp, step) == (False, 1.0, "not started")
    published = tmp_path / "published" / "Pendulum-v1" / "test" / "agents"
    for agent, seed in (("ppo", 10), ("ppo", 11), ("res-ppo", 10)):
        (published / agent / f"seed_{seed}").mkdir(parents=True)
        (published / agent / f"seed_{seed}" / "result.json").write_text("{}")
    done, left, text = _status(exp, step)
    # res-ppo seed 10 is trained again for its model; res-ppo seed 11 was never published.
    assert not done and left == pytest.approx(2 / 4)
    assert text.startswith("2/4 runs, 2 of them published in published/Pendulum-v1/test"), text
    local = step.folder / "agents" / "res-ppo" / "seed_11"
    local.mkdir(parents=True)
    (local / "result.json").write_text("{}")
    assert _status(exp, step)[:2] == (False, pytest.approx(1 / 4))


def test_publishing_leaves_out_files_over_the_size_limit(tmp_path: Path) -> None:
    """The published folder is for version control: a report's self-contained HTML over the
    limit stays in the results folder, said in the return value; the rest is copied."""
    from ermrl.runner._experiment import Step
    from ermrl.runner._publish import publish_step

    exp = load_experiment(write(tmp_path, {**TINY, "publish": str(tmp_path / "published")}))
    folder = tmp_path / "out" / "report"
    (folder / "figures").mkdir(parents=True)
    (folder / "report.md").write_text("# report\n")
    (folder / "figures" / "curve.png").write_bytes(b"\x89PNG" + b"0" * 100)
    (folder / "report.html").write_bytes(b"<html>" + b"x" * 5000)
    (folder / "model.zip").write_bytes(b"PK")  # never published: not a plain file
    step = Step("report", "Pendulum-v1", "report", [], 0, 1.0, lambda: (True, 0.0, ""), "s", folder)
    written, left_out = publish_step(exp, step, max_bytes=1000)
    dest = tmp_path / "published" / "Pendulum-v1" / "report"
    assert sorted(written) == [dest / "figures" / "curve.png", dest / "report.md"]
    assert left_out == [folder / "report.html"] and not (dest / "report.html").exists()
    written, left_out = publish_step(exp, step)  # the default limit (1 MiB) takes all three
    assert (dest / "report.html").exists() and left_out == []


def test_a_publish_folder_read_only_or_full_is_one_line_and_the_next_run_publishes(
    tmp_path: Path,
) -> None:
    """Publishing copies results that exist locally: a read-only or full published folder (real
    tmpfs mounts) is one line per step, the experiment goes on to its test and report, no
    published file is ever partial (each is renamed into place whole), and a rerun publishes.
    It used to stop with an OSError traceback after the evolution, on every rerun, and a
    nearly full disk left a truncated ``learning_curves.png`` under its final name."""
    from tests.test_bad_input import _tmpfs

    path = write(tmp_path, {**TINY, "publish": "published"})
    out = tmp_path / "runs" / "tiny" / "Pendulum-v1"
    with _tmpfs(tmp_path / "published", "ro", "size=1m") as published:
        done = ermrl(tmp_path, "run", str(path), "--progress", "none")
        assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
        lines = [line for line in done.stderr.splitlines() if line.startswith("not published")]
        assert [line.split(" to ")[0] for line in lines] == [
            f"not published: the {what} of Pendulum-v1"
            for what in ("study snapshot", "test", "report")
        ], done.stderr
        assert "(Read-only file system); kept in sqlite:///runs/tiny/ermrl.db" in lines[0]
        assert lines[1].endswith("kept in runs/tiny, the next run publishes it")
        assert (out / "test" / "summary.csv").exists() and (out / "report" / "report.md").exists()

        def remount(*options: str) -> None:
            mount = ["mount", "-o", ",".join(("remount", *options)), str(published)]
            subprocess.run(mount, check=True)

        remount("rw", "size=128k")  # room for the snapshot and part of the rest
        again = ermrl(tmp_path, "run", str(path), "--progress", "none")
        assert again.returncode == 0 and "Traceback" not in again.stderr, again.stderr
        assert "(No space left on device)" in again.stderr, again.stderr
        copies = [f for f in published.rglob("*") if f.is_file()]
        assert copies and not [f for f in copies if f.name.startswith(".")], copies
        for copy in copies:  # each whole: the snapshot, or a copy of its local file
            rel = copy.relative_to(published / "Pendulum-v1")
            if rel.name == "study.json":
                assert len(json.loads(copy.read_text())["trials"]) == 3
            else:
                assert copy.read_bytes() == (out / rel).read_bytes(), rel

        remount("size=16m")
        last = ermrl(tmp_path, "run", str(path), "--progress", "none")
        assert last.returncode == 0 and "not published" not in last.stderr, last.stderr
        for name in ("test/summary.csv", "test/learning_curves.png", "report/report.md"):
            assert (published / "Pendulum-v1" / name).read_bytes() == (out / name).read_bytes()


# -- files that are not plain short YAML, and settings that are not folders ------------------


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"name: tiny\ndescription: caf\xe9\n", "not UTF-8 text (byte 0xe9"),
        (b"name: tiny\nname: other\n", "key 'name' appears twice in one mapping"),
        (b"name: tiny\nevolve: {units: 10, units: 20}\n", "key 'units' appears twice"),
        (b"name: tiny\nout: {a: 1}\ntasks: [Pendulum-v1]\n", "out: a folder path (a string)"),
        (b"name: tiny\npublish: 5\ntasks: [Pendulum-v1]\n", "publish: a folder path (a string)"),
        (b"name: tiny\nstorage: [x]\ntasks: [Pendulum-v1]\n", "storage: a storage URL"),
        (b"name: tiny\n" + b"#" * (1 << 20) + b"\n", "larger than 1 MiB"),
    ],
    ids=["latin-1", "duplicate", "nested-duplicate", "out", "publish", "storage", "huge"],
)
def test_a_file_that_is_not_short_plain_yaml_is_one_line(
    tmp_path: Path, content: bytes, message: str
) -> None:
    path = tmp_path / "exp.yaml"
    path.write_bytes(content)
    with pytest.raises(ExperimentError) as info:
        load_experiment(path)
    assert message in str(info.value) and "\n" not in str(info.value)
    assert str(path) in str(info.value)


def test_a_device_is_not_read_to_its_end() -> None:
    with pytest.raises(ExperimentError, match="/dev/zero: larger than 1 MiB"):
        load_experiment("/dev/zero")


def test_keys_a_merge_brings_in_may_be_overridden(tmp_path: Path) -> None:
    text = "name: tiny\ntasks: [Pendulum-v1]\nevolve: &e {units: 10}\ntest: {<<: *e, units: 20}\n"
    path = tmp_path / "exp.yaml"
    path.write_text(text)
    assert load_experiment(path).stages["test"] == {"units": 20}


def _tiny_study(tmp_path: Path, ranking: dict | None = None) -> Path:
    """TINY's study in its storage, as its evolve step creates it (nothing trained), with a
    re-evaluation ranking recorded when given."""
    from ermrl.cli._evolve import build_evolve_parser, config_from_args
    from ermrl.search import create_or_resume_study

    path = write(tmp_path, TINY)
    (step,) = [s for s in experiment_plan(load_experiment(path), build_agents=False)
               if s.stage == "evolve"]  # fmt: skip
    args = build_evolve_parser().parse_args(step.argv)
    config = config_from_args(args, build_agent=False)
    (tmp_path / "runs" / "tiny").mkdir(parents=True)
    study = create_or_resume_study(config, args.storage, args.study_name)
    if ranking is not None:
        study.set_user_attr("ermrl_reevaluation", ranking)
    return path


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"evolve": {**TINY["evolve"], "popsize": 4}}, "evolve.popsize: 7 in the study, 4 now"),
        ({"evolve": {**TINY["evolve"], "sampler_seed": 3}}, "evolve.sampler_seed: None in the"),
        ({"reevaluate": {"top": 2, "seeds": 1}}, "reevaluate.top: 1 in the study, 2 now"),
        ({"reevaluate": {"top": 1, "seeds": 1, "steps": 512}}, "reevaluate.steps: 256 in the"),
        ({"reevaluate": {"top": 1, "seeds": 2}}, "reevaluate.seeds: 1 in the study, 2 now"),
        ({"evolve": {**TINY["evolve"], "popsize": 7}}, None),  # the default, spelled out
        ({"evolve": {**TINY["evolve"], "n_trials": 5}}, None),  # a larger budget resumes
    ],
    ids=["popsize", "sampler-seed", "top", "steps", "seeds", "same-popsize", "n-trials"],
)
def test_changing_the_search_or_a_finished_reevaluation_mid_study_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, change: dict, message: str | None
) -> None:
    monkeypatch.chdir(tmp_path)  # the file's storage is runs/tiny/ermrl.db
    ranking = {"complete": True, "top_k": 1, "training_steps": 256, "seeds": [1000],
               "candidates": [], "best_trial": 0}  # fmt: skip
    _tiny_study(tmp_path, ranking)
    path = write(tmp_path, {**TINY, **change})
    if message is None:
        experiment_plan(load_experiment(path), build_agents=False)
        return
    with pytest.raises(ExperimentError) as info:
        experiment_plan(load_experiment(path), build_agents=False)
    text = str(info.value)
    assert message in text and "\n" not in text and "change the file back" in text


def test_a_failed_run_leaves_no_resolved_file_behind(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``ermrl run FILE --stage test`` before any evolution: the test stage fails (no study),
    and the run removes the resolved file and the folder it created for it."""
    from ermrl.cli._run import run_main

    path = write(tmp_path, TINY)
    monkeypatch.chdir(tmp_path)
    code = run_main([str(path), "--stage", "test", "--quiet"])
    assert code != 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.yaml"]


@pytest.mark.slow
def test_a_generalization_file_runs_its_stages_through_the_library(tmp_path: Path) -> None:
    """``ermrl run`` of H3's quick variant: the evolution on a task set and the test on an unseen
    task run as library calls (no command's ``main(argv)``), print the command lines a user can
    paste, and the test folder keeps that line, not ``ermrl run ...``."""
    path = ROOT / "experiments" / "paper" / "h3_generalization.yaml"
    exp = load_experiment(path, "quick")
    done = subprocess.run(
        [sys.executable, "-m", "ermrl", "run", str(path), "--variant", "quick",
         "--stage", "evolve", "reevaluate", "test"],
        cwd=tmp_path, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("[")]
    evolve = next(ln for ln in lines if ln.startswith("[evolve "))
    test = next(ln for ln in lines if ln.startswith("[test Hopper-v5] "))
    assert " ermrl evolve-generalization --suite cheetah_swimmer " in evolve
    assert "normalized fitness" in done.stdout  # the generalization worker's summary
    db = tmp_path / exp.out / "ermrl.db"
    study = optuna.load_study(study_name=_only_study(db), storage=f"sqlite:///{db}")
    assert len(study.get_trials(states=[TrialState.COMPLETE])) >= 2
    folder = tmp_path / exp.out / "test" / "Hopper-v5"
    summary = (folder / "summary.csv").read_text()
    assert "final_return_normalized_mean" in summary  # Hopper-v5 has reference scores
    recorded = (folder / "command.txt").read_text().strip()
    assert recorded == test.split("] ", 1)[1]
    assert recorded.startswith("ermrl test-generalization --env-id Hopper-v5 ")


def _only_study(db: Path) -> str:
    names = [s.study_name for s in optuna.get_all_study_summaries(f"sqlite:///{db}")]
    main = [n for n in names if not n.endswith(".reeval")]
    assert len(main) == 1, names
    return main[0]


def test_a_test_stage_without_progress_shows_progress_for_where_stdout_goes() -> None:
    """The plan resolves a test stage's progress as ``ermrl test`` does (lines when stdout is
    not a terminal), not the library's quiet default: ``ermrl run`` must still print them."""
    from ermrl._progress import default_mode
    from ermrl.runner import experiment_plan, load_experiment

    steps = experiment_plan(load_experiment(ROOT / "experiments" / "demo.yaml"), build_agents=False)
    (test,) = [s for s in steps if s.stage == "test"]
    assert test.request.options.progress == default_mode() != "none"
