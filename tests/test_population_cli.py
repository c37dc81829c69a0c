"""The population backend through the command line: evolution, refusals, kill -9, test phase.

Real CLI workers on a real SQLite study with real (tiny) training; nothing is mocked.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import optuna
import pandas as pd
import pytest
from optuna.trial import TrialState

from ermrl.search import study_config
from ermrl.storage import open_storage

ROOT = Path(__file__).resolve().parents[1]
# Pendulum with velocities hidden, a few hundred steps per agent.
TINY = [
    "--env-id", "Pendulum-v1", "--observe", "positions", "--units", "20",
    "--n-envs", "1", "--ppo", "n_steps=128", "batch_size=64", "n_epochs=2",
    "--training-steps", "256", "--backend", "population",
]  # fmt: skip


def evolve(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(ROOT / "evolve_res.py"), *args],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=600,
    )


def load(url: str, name: str) -> optuna.Study:
    return optuna.load_study(study_name=name, storage=open_storage(url))


def test_an_evolution_trains_whole_generations_and_records_the_backend(tmp_path: Path) -> None:
    """Each generation's trials complete with per-seed records, the backend and its size."""
    url = f"sqlite:///{tmp_path}/s.db"
    common = [*TINY, "--storage", url, "--study-name", "p", "--popsize", "3", "--n-seeds", "2"]
    done = evolve(tmp_path, *common, "--n-trials", "5")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "population backend: generations of up to 3 candidates x 2 seeds" in done.stdout
    study = load(url, "p")
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 5
    for t in trials:
        assert t.user_attrs["backend"] == "population"
        assert len(t.user_attrs["returns_last"]) == 2
        assert all(r is not None for r in t.user_attrs["returns_last"])
    # The first generation has 3 candidates x 2 seeds, the second the 2 trials left.
    assert [t.user_attrs["population"] for t in trials] == [6, 6, 6, 4, 4]
    assert study_config(study).problem.ppo.backend == "population"
    # Resuming with the other backend is refused: a study never mixes backends.
    other = [a if a != "population" else "sb3" for a in common]
    refused = evolve(tmp_path, *other, "--n-trials", "6")
    assert refused.returncode != 0
    assert "backend" in (refused.stdout + refused.stderr)
    assert len(load(url, "p").get_trials()) == 5


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--pruner", "median"], "--pruner none with --backend population"),
        (["--learner", "lstm-ppo"], "ppo learner only"),
        (["--ppo", "target_kl=0.01"], "target_kl"),
    ],
)
def test_combinations_the_population_backend_cannot_train_are_refused(
    tmp_path: Path, extra: list[str], message: str
) -> None:
    """A pruner, another learner or an unimplemented PPO setting: one line, no study."""
    url = f"sqlite:///{tmp_path}/s.db"
    done = evolve(tmp_path, *TINY, *extra, "--storage", url, "--n-trials", "2")
    assert done.returncode == 2, done.stdout + done.stderr
    assert message in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert not (tmp_path / "s.db").exists()


@pytest.mark.slow
def test_kill_9_during_a_generation_fails_and_retries_its_trials(tmp_path: Path) -> None:
    """Every trial of a killed worker's generation ends FAIL and is retried by another worker."""
    url = f"sqlite:///{tmp_path}/s.db"
    args = [*TINY, "--storage", url, "--study-name", "k", "--popsize", "3", "--n-trials", "6"]
    args += ["--training-steps", "20000", "--heartbeat-interval", "1", "--grace-period", "4"]
    log = open(tmp_path / "victim.log", "w")  # noqa: SIM115 (closed below)
    victim = subprocess.Popen(
        [sys.executable, str(ROOT / "evolve_res.py"), *args],
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        cwd=tmp_path,
    )
    deadline = time.monotonic() + 120
    running: list[int] = []
    while time.monotonic() < deadline and len(running) < 3:
        time.sleep(0.3)
        try:
            trials = load(url, "k").get_trials(states=[TrialState.RUNNING])
        except Exception:  # the study does not exist yet
            continue
        running = [t.number for t in trials if t.user_attrs.get("worker_pid") == victim.pid]
    assert len(running) == 3, (tmp_path / "victim.log").read_text()
    time.sleep(1.0)  # inside the generation's training
    os.killpg(victim.pid, signal.SIGKILL)
    victim.wait(10)
    log.close()
    survivor = evolve(tmp_path, *args)
    assert survivor.returncode == 0, survivor.stdout + survivor.stderr
    trials = load(url, "k").get_trials()
    states = Counter(t.state for t in trials)
    assert states == {TrialState.COMPLETE: 6, TrialState.FAIL: 3}, states
    failed = sorted(t.number for t in trials if t.state == TrialState.FAIL)
    assert failed == sorted(running)
    retried = {t.user_attrs.get("retry_of") for t in trials if t.state == TrialState.COMPLETE}
    assert set(failed) <= retried
    # The retries train the killed trials' own candidates.
    by_number = {t.number: t for t in trials}
    for t in trials:
        if t.user_attrs.get("retry_of") is not None:
            assert t.params == by_number[t.user_attrs["retry_of"]].params


@pytest.mark.slow
def test_ctrl_c_in_the_first_generation_queues_it_again_reference_first(tmp_path: Path) -> None:
    """Ctrl-C (to the whole process group, as a terminal sends it) while generation 0 trains:
    every trial of it is closed and queued again, the reference first, and the rerun trains the
    unevolved reference (sr = lr = input_scaling = 1) to COMPLETE."""
    url = f"sqlite:///{tmp_path}/s.db"
    args = [*TINY, "--storage", url, "--study-name", "c", "--popsize", "3", "--n-trials", "3"]
    args += ["--training-steps", "4096", "--n-seeds", "1"]
    log = open(tmp_path / "victim.log", "w")  # noqa: SIM115 (closed below)
    victim = subprocess.Popen(
        [sys.executable, str(ROOT / "evolve_res.py"), *args],
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        cwd=tmp_path,
    )
    deadline = time.monotonic() + 120
    running: list[optuna.trial.FrozenTrial] = []
    while time.monotonic() < deadline and len(running) < 3 and victim.poll() is None:
        time.sleep(0.1)
        try:
            running = load(url, "c").get_trials(states=[TrialState.RUNNING])
        except Exception:  # the study does not exist yet
            continue
    assert len(running) == 3, (tmp_path / "victim.log").read_text()
    os.killpg(victim.pid, signal.SIGINT)
    victim.wait(60)
    log.close()
    text = (tmp_path / "victim.log").read_text()
    assert victim.returncode == 130 and "Traceback" not in text, text
    trials = load(url, "c").get_trials()
    assert [t.state for t in trials] == [TrialState.FAIL] * 3 + [TrialState.WAITING] * 3, text
    assert trials[3].user_attrs.get("reference") and trials[3].user_attrs["retry_of"] == 0
    rerun = evolve(tmp_path, *args)
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    trials = load(url, "c").get_trials()
    assert [t.state for t in trials] == [TrialState.FAIL] * 3 + [TrialState.COMPLETE] * 3
    reference = [t for t in trials if t.params == {"sr": 1.0, "lr": 1.0, "input_scaling": 1.0}]
    assert [t.state for t in reference] == [TrialState.FAIL, TrialState.COMPLETE]
    assert sorted(t.user_attrs["retry_of"] for t in trials[3:]) == [0, 1, 2]


def test_the_test_phase_trains_under_both_backends(tmp_path: Path) -> None:
    """test.py runs a population-evolved study's agents under population and sb3."""
    url = f"sqlite:///{tmp_path}/s.db"
    done = evolve(tmp_path, *TINY, "--storage", url, "--study-name", "t", "--n-trials", "2")
    assert done.returncode == 0, done.stdout + done.stderr
    summaries = {}
    for backend in ("population", "sb3"):
        out = tmp_path / backend
        run = subprocess.run(
            [
                sys.executable, str(ROOT / "test.py"), "--study-name", "t", "--storage", url,
                "--training-steps", "256", "--seeds", "10", "11", "--agents", "res-ppo", "ppo",
                "--ppo", "n_steps=128", "batch_size=64", "n_epochs=2", "--backend", backend,
                "--out", str(out), "--save-models",
            ],
            capture_output=True, text=True, cwd=tmp_path, timeout=600,
        )  # fmt: skip
        assert run.returncode == 0, run.stdout + run.stderr
        assert ("[population]" in run.stdout) == (backend == "population")
        assert (out / "agents" / "res-ppo" / "seed_10" / "policy.pt").exists()
        summaries[backend] = pd.read_csv(out / "summary.csv").set_index("agent")
    for summary in summaries.values():
        assert set(summary.index) == {"res-ppo", "ppo"}
        assert (summary["n_seeds"] == 2).all()


@pytest.mark.parametrize("backend", ["population", "sb3"])
def test_a_killed_test_phase_resumes_its_runs_from_their_checkpoints(
    backend: str, tmp_path: Path
) -> None:
    """kill -9 during training: the rerun resumes from the checkpoints (not from step 0), says
    so, finishes every run, and removes the checkpoints."""
    url = f"sqlite:///{tmp_path}/s.db"
    done = evolve(tmp_path, *TINY, "--storage", url, "--study-name", "c", "--n-trials", "1")
    assert done.returncode == 0, done.stdout + done.stderr
    out = tmp_path / "test"
    # A population trains its runs in lockstep; sb3 trains one run after another.
    steps, seeds, agents = (
        ("40000", ["10", "11"], ["res-ppo", "ppo"])
        if backend == "population"
        else ("8000", ["10"], ["ppo"])
    )
    command = [
        sys.executable, str(ROOT / "test.py"), "--study-name", "c", "--storage", url,
        "--training-steps", steps, "--seeds", *seeds, "--agents", *agents,
        "--ppo", "n_steps=128", "batch_size=64", "n_epochs=2", "--backend", backend,
        "--n-procs", "1", "--checkpoint-every", "512", "--out", str(out), "--progress", "lines",
    ]  # fmt: skip
    log = open(tmp_path / "victim.log", "w")  # noqa: SIM115 (closed below)
    victim = subprocess.Popen(
        command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, cwd=tmp_path
    )
    saved = "checkpoints/*.npz" if backend == "population" else "agents/*/*/checkpoints/state.json"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and not list(out.glob(saved)):
        assert victim.poll() is None, (tmp_path / "victim.log").read_text()
        time.sleep(0.2)
    time.sleep(0.5)  # a few more saves
    os.killpg(victim.pid, signal.SIGKILL)
    victim.wait(10)
    log.close()
    assert list(out.glob(saved)), (tmp_path / "victim.log").read_text()
    rerun = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    resumed = [line for line in rerun.stdout.splitlines() if "resumed from" in line]
    assert resumed, rerun.stdout
    step = int(resumed[0].rsplit(" at ", 1)[1].split()[0].replace(",", ""))
    assert 0 < step < int(steps)
    summary = pd.read_csv(out / "summary.csv").set_index("agent")
    assert set(summary.index) == set(agents) and (summary["n_seeds"] == len(seeds)).all()
    assert not list(out.rglob("checkpoints"))


def test_a_generalization_evolution_trains_each_task_as_a_population(tmp_path: Path) -> None:
    """evolve-generalization: each task's candidates x seeds train together; per-task records."""
    url = f"sqlite:///{tmp_path}/g.db"
    done = subprocess.run(
        [
            sys.executable, str(ROOT / "evolve_generalization.py"),
            "--env-ids", "Hopper-v5", "Swimmer-v5", "--observe", "positions",
            "--backend", "population", "--n-trials", "3", "--popsize", "3", "--n-seeds", "2",
            "--training-steps", "512", "--fitness", "eval", "--n-eval-episodes", "1",
            "--ppo", "n_steps=128", "batch_size=64", "n_epochs=2", "--units", "20",
            "--storage", url, "--study-name", "g",
        ],
        capture_output=True, text=True, cwd=tmp_path, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert "(2 task(s))" in done.stdout
    trials = load(url, "g").get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 3
    for t in trials:
        assert t.user_attrs["backend"] == "population"
        assert t.user_attrs["population"] == 6
        assert set(t.user_attrs["task_seed_returns"]) == {"Hopper-v5", "Swimmer-v5"}
        assert all(len(v) == 2 for v in t.user_attrs["task_seed_returns"].values())


# -- the default backend ------------------------------------------------------------------------
def evolve_args(*extra: str) -> argparse.Namespace:
    from ermrl.cli._evolve import build_evolve_parser

    base = ["--env-id", "Pendulum-v1", "--observe", "positions", "--units", "20"]
    return build_evolve_parser().parse_args([*base, "--storage", "sqlite:///unused.db", *extra])


@pytest.mark.parametrize(
    "extra",
    [[], ["--encoder", "rtu"], ["--tensorboard", "tb"]],
    ids=["esn", "rtu", "tensorboard"],
)
def test_population_is_the_default_for_ppo_on_reservoir_states(extra: list[str]) -> None:
    """No --backend: PPO on an ESN's or an RTU layer's states trains with population, silently
    (with --tensorboard too: a generation's runs log for TensorBoard themselves)."""
    from ermrl.cli._evolve import config_from_args

    notes: list[str] = []
    config = config_from_args(evolve_args(*extra), build_agent=False, notes=notes)
    assert config.problem.ppo.backend == "population"
    assert notes == []
    explicit = config_from_args(evolve_args(*extra, "--backend", "sb3"), build_agent=False)
    assert explicit.problem.ppo.backend == "sb3"


FALLBACKS = {
    "another-learner": (["--learner", "lstm-ppo"], "trains the ppo learner only, not 'lstm-ppo'"),
    "target_kl": (["--ppo", "target_kl=0.01"], "does not implement target_kl"),
    "pruner": (["--pruner", "median"], "no intermediate returns to --pruner median"),
}


@pytest.mark.parametrize("case", list(FALLBACKS))
def test_the_default_falls_back_to_sb3_with_the_reason(case: str) -> None:
    """No --backend where population cannot train the runs: sb3, and one reason to print."""
    from ermrl.cli._evolve import config_from_args

    extra, message = FALLBACKS[case]
    notes: list[str] = []
    config = config_from_args(evolve_args(*extra), build_agent=False, notes=notes)
    assert config.problem.ppo.backend == "sb3"
    assert len(notes) == 1 and message in notes[0] and "\n" not in notes[0]
    assert "--backend sb3" not in notes[0]  # a reason, not an error's hint


def spend(url: str, name: str, argv: list[str]) -> None:
    """Create the study these options make, with its one-trial budget already spent (resuming
    it trains nothing)."""
    from ermrl.cli._evolve import build_evolve_parser, config_from_args
    from ermrl.search import create_or_resume_study

    config = config_from_args(build_evolve_parser().parse_args(argv), build_agent=False)
    study = create_or_resume_study(config, url, name)
    study.add_trial(optuna.trial.create_trial(value=0.0))


def test_a_study_created_with_sb3_resumes_with_sb3_when_no_backend_is_given(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The stored backend wins over the default; an explicit other backend is refused."""
    from ermrl.cli._evolve import evolve_main

    url = f"sqlite:///{tmp_path}/s.db"
    argv = [*TINY[:-2], "--storage", url, "--study-name", "old", "--n-trials", "1", "--quiet"]
    spend(url, "old", [*argv, "--backend", "sb3"])
    assert evolve_main(argv) == 0
    err = capsys.readouterr().err.strip()
    assert err == (
        "ermrl evolve: training with the sb3 backend: study 'old' was created with it "
        "(a study never mixes backends)"
    )
    assert study_config(load(url, "old")).problem.ppo.backend == "sb3"
    with pytest.raises(SystemExit) as refused:
        evolve_main([*argv, "--backend", "population"])
    assert refused.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "already exists with another configuration" in err and "backend" in err
    assert "\n" not in err


def test_the_fallback_is_one_line_and_a_population_study_resumes_silently(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """evolve with a pruner and no --backend: one stderr line with the reason; a study made
    with the default (population) resumes with it and prints nothing."""
    from ermrl.cli._evolve import evolve_main

    url = f"sqlite:///{tmp_path}/s.db"
    argv = [*TINY[:-2], "--storage", url, "--n-trials", "1", "--quiet"]
    pruned = [*argv, "--study-name", "pruned", "--pruner", "median"]
    spend(url, "pruned", pruned)
    assert evolve_main(pruned) == 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("ermrl evolve: training with the sb3 backend: ")
    assert "--pruner median" in err and "\n" not in err
    default = [*argv, "--study-name", "new"]
    spend(url, "new", default)
    assert study_config(load(url, "new")).problem.ppo.backend == "population"
    assert evolve_main(default) == 0
    assert capsys.readouterr().err == ""


def test_an_rtu_evolution_with_no_backend_trains_with_population(tmp_path: Path) -> None:
    """ermrl evolve --encoder rtu, no --backend: whole generations on the population backend."""
    url = f"sqlite:///{tmp_path}/s.db"
    done = evolve(
        tmp_path, *TINY[:-2], "--encoder", "rtu", "--storage", url, "--study-name", "r",
        "--popsize", "2", "--n-seeds", "1", "--n-trials", "2",
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert "population backend: generations of up to 2 candidates" in done.stdout
    assert done.stderr == ""
    study = load(url, "r")
    assert study_config(study).problem.ppo.backend == "population"
    assert study_config(study).space.family == "rtu"
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE] * 2
    assert all(t.user_attrs["backend"] == "population" for t in trials)


def test_the_test_phase_defaults_to_population_where_it_applies(tmp_path: Path) -> None:
    """No --backend in a test phase: population (with --tensorboard too: its runs log for
    themselves); sb3 with a reason for --wandb, another learner, or an --out whose finished runs
    were made with sb3 (not with --overwrite)."""
    import json

    from ermrl.agents import resolve_ppo_config
    from ermrl.config import TaskConfig
    from ermrl.test_phase import TestOptions
    from ermrl.test_phase._prepare import with_backend

    task = TaskConfig("Pendulum-v1", "positions")
    ppo = resolve_ppo_config("Pendulum-v1", backend="population")  # a study evolved so

    def choose(base: object = ppo, out: Path | None = None, **flags: object) -> tuple[str, list]:
        options = TestOptions(**flags)  # type: ignore[arg-type]
        notes: list[str] = []
        return with_backend(base, options, task=task, out=out, notes=notes).backend, notes

    assert choose() == ("population", [])
    assert choose(backend="sb3") == ("sb3", [])
    # A study evolved with sb3 keeps it (one of an older ermrl tests to the same returns).
    assert choose(resolve_ppo_config("Pendulum-v1", backend="sb3")) == ("sb3", [])
    assert choose(resolve_ppo_config("Pendulum-v1", backend="sb3"), backend="population")[0] == (
        "population"
    )
    assert choose(tensorboard="tb") == ("population", [])
    backend, notes = choose(wandb="project")
    assert backend == "sb3" and len(notes) == 1 and "--wandb" in notes[0]
    lstm = resolve_ppo_config("Pendulum-v1", learner="lstm-ppo")
    backend, notes = choose(lstm)
    assert backend == "sb3" and len(notes) == 1 and "ppo learner only" in notes[0]
    # An --out with a finished sb3 run of this learner keeps sb3; another learner's does not count.
    run = tmp_path / "agents" / "ppo" / "seed_10"
    run.mkdir(parents=True)
    (run / "settings.json").write_text(json.dumps({"ppo": {"hyperparams": {}}}))
    assert choose(out=tmp_path) == ("population", [])  # not finished: no result.json
    (run / "result.json").write_text("{}")
    backend, notes = choose(out=tmp_path)
    assert backend == "sb3" and len(notes) == 1 and "finished runs" in notes[0]
    assert choose(out=tmp_path, overwrite=True) == ("population", [])
    (run / "settings.json").write_text(json.dumps({"ppo": {"learner": "lstm-ppo"}}))
    assert choose(out=tmp_path) == ("population", [])
