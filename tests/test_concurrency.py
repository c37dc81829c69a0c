"""Many workers on one study: simultaneous starts, kill -9, SIGTERM.

The fast tests fork worker processes that run the real worker loop (create the study, claim,
heartbeat, retry) with a stub fitness, so eight of them start at the same instant at no import
cost. The CLI tests start real ``evolve_res.py`` workers that train tiny PPO agents.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import signal
import subprocess
import sys
import time
import traceback
from collections import Counter
from pathlib import Path

import optuna
import pytest
from optuna.trial import TrialState

from ermrl.config import (
    BudgetConfig,
    EncoderConfig,
    EvolveConfig,
    PPOConfig,
    Problem,
    ReservoirSpace,
    SearchConfig,
    TaskConfig,
)
from ermrl.search import FitnessResult, create_or_resume_study, run_evolution
from ermrl.storage import open_storage

optuna.logging.set_verbosity(optuna.logging.WARNING)

ROOT = Path(__file__).resolve().parents[1]
FORK = multiprocessing.get_context("fork")
LOCK_ERRORS = ("database is locked", "already exists", "deadlock", "could not serialize")
# Real CLI workers: Pendulum with velocities hidden, a few hundred steps per trial.
# The workers claim one trial at a time (--backend sb3): the kill -9 tests count on exactly one
# trial dying with its worker. The population backend's whole-generation claims survive kill -9
# and SIGTERM in tests/test_population_cli.py.
TINY = [
    "--env-id", "Pendulum-v1", "--observe", "positions", "--n-seeds", "1", "--units", "20",
    "--n-envs", "1", "--ppo", "n_steps=128", "batch_size=64", "n_epochs=2", "--backend", "sb3",
]  # fmt: skip


def stub_config(n_trials: int, sampler_seed: int | None = None) -> EvolveConfig:
    space = ReservoirSpace(units=10)
    problem = Problem(
        task=TaskConfig("Pendulum-v1", "positions"),
        encoder=EncoderConfig(reservoirs=space.default_reservoirs()),
        ppo=PPOConfig(),
        budget=BudgetConfig(training_steps=256),
        seeds=(0,),
    )
    search = SearchConfig(n_trials=n_trials, sampler_seed=sampler_seed)
    return EvolveConfig(problem=problem, space=space, search=search)


def _stub_worker(url: str, n_trials: int, delay: float, go, errors, heartbeat, seed=None) -> None:  # noqa: ANN001
    """One worker process: wait for the start signal, then the real create + worker loop."""

    def evaluate(encoder, runner, report):  # noqa: ANN001, ANN202
        time.sleep(delay)
        value = -(math.log10(encoder.reservoirs[0].sr) ** 2)
        return FitnessResult(fitness=value, mode="last", runs=[], wall_seconds=delay)

    try:
        go.wait(60)
        config = stub_config(n_trials, seed)
        study = create_or_resume_study(
            config, url, "race", heartbeat_interval=heartbeat[0], grace_period=heartbeat[1]
        )
        run_evolution(config, study, quiet=True, evaluate=evaluate)
    except BaseException:
        errors.put(traceback.format_exc())
        os._exit(1)


def start_stub_workers(
    url: str,
    n_workers: int,
    n_trials: int,
    delay: float,
    heartbeat: tuple[int, int] = (60, 300),
    sampler_seed: int | None = None,
) -> tuple[list, object]:  # noqa: ANN001
    go, errors = FORK.Event(), FORK.Queue()
    args = (url, n_trials, delay, go, errors, heartbeat, sampler_seed)
    procs = [FORK.Process(target=_stub_worker, args=args) for _ in range(n_workers)]
    for proc in procs:
        proc.start()
    go.set()  # all at the same instant
    return procs, errors


def join_all(procs: list, timeout: float) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout
    for proc in procs:
        proc.join(max(deadline - time.monotonic(), 0.1))
    alive = [p.pid for p in procs if p.is_alive()]
    for proc in procs:
        if proc.is_alive():
            proc.kill()
    assert not alive, f"workers {alive} still running after {timeout} s"


def drain(errors) -> list[str]:  # noqa: ANN001
    out = []
    while not errors.empty():
        out.append(errors.get())
    return out


def load(url: str, name: str = "race") -> optuna.Study:
    return optuna.load_study(study_name=name, storage=open_storage(url))


def assert_exactly(study: optuna.Study, n: int, n_fail: int = 0) -> list[optuna.trial.FrozenTrial]:
    trials = study.get_trials()
    states = Counter(t.state for t in trials)
    assert states[TrialState.COMPLETE] == n, states
    assert states[TrialState.FAIL] == n_fail, states
    assert set(states) <= {TrialState.COMPLETE, TrialState.FAIL}, states
    numbers = [t.number for t in trials]
    assert sorted(numbers) == list(range(len(trials))), numbers  # unique, no gaps
    return trials


@pytest.mark.parametrize(
    "fresh_storage",
    [
        "sqlite",
        "journal",
        pytest.param("postgresql", marks=pytest.mark.services),
        pytest.param("mysql", marks=pytest.mark.services),
        pytest.param("redis", marks=pytest.mark.services),
    ],
    indirect=True,
)
def test_eight_workers_starting_at_once_on_a_fresh_storage(fresh_storage: str) -> None:
    n_trials = 16
    procs, errors = start_stub_workers(fresh_storage, 8, n_trials, delay=0.2)
    join_all(procs, timeout=120)
    assert drain(errors) == []
    assert [p.exitcode for p in procs] == [0] * 8
    trials = assert_exactly(load(fresh_storage), n_trials)
    workers = Counter(t.user_attrs["worker_pid"] for t in trials)
    assert len(workers) >= 2, workers


@pytest.mark.services
def test_kill_9_mid_trial_the_stale_trial_is_retried(postgres_url: str) -> None:
    n_trials = 4
    procs, errors = start_stub_workers(postgres_url, 2, n_trials, delay=2.0, heartbeat=(1, 3))
    victim = procs[1]
    deadline = time.monotonic() + 60
    study = None
    while time.monotonic() < deadline:
        try:
            study = load(postgres_url)
        except Exception:  # the study does not exist yet
            time.sleep(0.2)
            continue
        running = study.get_trials(states=[TrialState.RUNNING])
        if any(t.user_attrs.get("worker_pid") == victim.pid for t in running):
            break
        time.sleep(0.1)
    else:
        pytest.fail("the victim never ran a trial")
    os.kill(victim.pid, signal.SIGKILL)
    join_all(procs, timeout=90)
    assert drain(errors) == []
    assert victim.exitcode == -signal.SIGKILL and procs[0].exitcode == 0
    trials = assert_exactly(load(postgres_url), n_trials, n_fail=1)
    failed = next(t for t in trials if t.state == TrialState.FAIL)
    assert failed.user_attrs["worker_pid"] == victim.pid
    retried = [t for t in trials if t.user_attrs.get("retry_of") == failed.number]
    assert len(retried) == 1 and retried[0].state == TrialState.COMPLETE
    assert retried[0].params == failed.params
    assert retried[0].user_attrs["worker_pid"] == procs[0].pid


# -- real CLI workers ---------------------------------------------------------------------------


def start_cli_worker(url: str, log: Path, *args: str) -> subprocess.Popen:
    handle = open(log, "w")  # noqa: SIM115  (closed with the process)
    return subprocess.Popen(
        [sys.executable, str(ROOT / "evolve_res.py"), *TINY, "--storage", url, *args],
        stdout=handle,
        stderr=subprocess.STDOUT,
        start_new_session=True,  # its own process group, like a SLURM task
        cwd=log.parent,
    )


def wait_running(url: str, name: str, pid: int, timeout: float = 120) -> optuna.trial.FrozenTrial:
    """Wait until the worker ``pid`` has a RUNNING trial."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            study = load(url, name)
        except Exception:
            time.sleep(0.3)
            continue
        for trial in study.get_trials(states=[TrialState.RUNNING]):
            if trial.user_attrs.get("worker_pid") == pid:
                return trial
        time.sleep(0.2)
    raise AssertionError(f"worker {pid} never ran a trial")


def test_sigterm_mid_trial_with_a_process_pool_exits_fast_and_loses_nothing(
    tmp_path: Path,
) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    args = ["--study-name", "t", "--n-trials", "2", "--training-steps", "2048"]
    args += ["--n-seeds", "2", "--n-procs", "2"]
    worker = start_cli_worker(url, tmp_path / "w1.log", *args)
    trial = wait_running(url, "t", worker.pid)
    time.sleep(1.0)  # the seeds are training in the pool
    sent = time.monotonic()
    os.killpg(worker.pid, signal.SIGTERM)  # the whole group, as SLURM does
    code = worker.wait(30)
    took = time.monotonic() - sent
    log = (tmp_path / "w1.log").read_text()
    assert code == 143, log
    assert took < 5, f"exit took {took:.1f} s"
    assert "stopped by SIGTERM" in log and "Traceback" not in log, log
    trials = load(url, "t").get_trials()
    closed = trials[trial.number]
    assert closed.state == TrialState.FAIL
    assert closed.user_attrs["fail_reason"] == "interrupted by SIGTERM"
    queued = [t for t in trials if t.state == TrialState.WAITING]
    assert len(queued) == 1 and queued[0].params == closed.params

    # A restarted worker runs the queued trial and finishes the budget.
    again = start_cli_worker(url, tmp_path / "w2.log", *args)
    assert again.wait(300) == 0, (tmp_path / "w2.log").read_text()
    final = assert_exactly(load(url, "t"), 2, n_fail=1)
    assert any(t.user_attrs.get("retry_of") == trial.number for t in final)


def test_a_worker_exits_within_a_second_or_so_of_sigterm(tmp_path: Path) -> None:
    """Its trial was closed and its line printed within 0.2 s of SIGTERM, but the process
    took 3 to 4 s more to exit (Python's last garbage collection) where the docs said "a
    second or two"; now 0.4 to 1.4 s (2 busy cores)."""
    url = f"sqlite:///{tmp_path}/s.db"
    args = ["--study-name", "t", "--n-trials", "1", "--training-steps", "100000"]
    worker = start_cli_worker(url, tmp_path / "w.log", *args)
    wait_running(url, "t", worker.pid)
    time.sleep(1.0)  # training
    sent = time.monotonic()
    os.killpg(worker.pid, signal.SIGTERM)
    code = worker.wait(30)
    took = time.monotonic() - sent
    log = (tmp_path / "w.log").read_text()
    assert code == 143 and "stopped by SIGTERM; the running trial #0" in log, log
    assert took < 2.5, f"exit took {took:.1f} s"


def assert_cma_first_points(trials: list[optuna.trial.FrozenTrial], n_workers: int) -> None:
    """Every trial was sampled (or, for the reference, told) by CMA-ES; each worker's first
    point differs from the others'."""
    missing = [t.number for t in trials if "cma:restart_0:generation" not in t.system_attrs]
    assert missing == [], f"trials without CMA-ES attributes: {missing}"
    first: dict[int, tuple[float, ...]] = {}
    for t in sorted(trials, key=lambda t: t.number):
        first.setdefault(t.user_attrs["worker_pid"], tuple(sorted(t.params.items())))
    assert len(first) == n_workers, first
    assert len(set(first.values())) == n_workers, first
    references = [t for t in trials if t.user_attrs.get("reference")]
    assert len(references) == 1
    assert references[0].params == {"sr": 1.0, "lr": 1.0, "input_scaling": 1.0}


def test_four_workers_with_one_sampler_seed_draw_distinct_cma_points(tmp_path: Path) -> None:
    # Each trial takes long enough that all four workers ask before any trial completes: with
    # Optuna's fallback these first points came from one random sampler seeded alike.
    url = f"sqlite:///{tmp_path}/s.db"
    procs, errors = start_stub_workers(url, 4, 8, delay=1.5, sampler_seed=0)
    join_all(procs, timeout=120)
    assert drain(errors) == []
    trials = assert_exactly(load(url), 8)
    assert_cma_first_points(trials, 4)


@pytest.mark.slow
def test_four_cli_workers_at_once_on_a_fresh_sqlite_study(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    args = ["--study-name", "t", "--n-trials", "8", "--training-steps", "256"]
    args += ["--sampler-seed", "0"]
    workers = [start_cli_worker(url, tmp_path / f"w{i}.log", *args) for i in range(4)]
    codes = [w.wait(600) for w in workers]
    logs = "".join((tmp_path / f"w{i}.log").read_text() for i in range(4))
    assert codes == [0] * 4, logs
    assert not any(e in logs for e in LOCK_ERRORS), logs
    trials = assert_exactly(load(url, "t"), 8)
    assert len({t.user_attrs["worker_pid"] for t in trials}) >= 2
    assert all("cma:restart_0:generation" in t.system_attrs for t in trials)
    # Workers that start together draw distinct first points.
    first = {}
    for t in sorted(trials, key=lambda t: t.number):
        first.setdefault(t.user_attrs["worker_pid"], tuple(sorted(t.params.items())))
    assert len(set(first.values())) == len(first), first


@pytest.mark.slow
@pytest.mark.services
def test_kill_9_a_cli_worker_on_postgresql(postgres_url: str, tmp_path: Path) -> None:
    # 8192 steps: a trial runs for seconds, so the poll sees the victim's trial RUNNING even on
    # a loaded machine (at 1024 steps a trial lasted about half a second, and the poll missed
    # both of the victim's trials once).
    args = ["--study-name", "t", "--n-trials", "4", "--training-steps", "8192"]
    args += ["--heartbeat-interval", "1", "--grace-period", "4"]
    survivor = start_cli_worker(postgres_url, tmp_path / "w1.log", *args)
    victim = start_cli_worker(postgres_url, tmp_path / "w2.log", *args)
    wait_running(postgres_url, "t", victim.pid)
    os.killpg(victim.pid, signal.SIGKILL)
    victim.wait(10)
    assert survivor.wait(600) == 0, (tmp_path / "w1.log").read_text()
    trials = assert_exactly(load(postgres_url, "t"), 4, n_fail=1)
    failed = next(t for t in trials if t.state == TrialState.FAIL)
    assert any(t.user_attrs.get("retry_of") == failed.number for t in trials)
