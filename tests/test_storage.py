"""ermrl.storage: URLs, locks, heartbeats and retries on every backend; the ``ermrl study`` CLI."""

from __future__ import annotations

import io
import json
import math
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import optuna
import pandas as pd
import pytest
import redis
from optuna.distributions import FloatDistribution
from optuna.storages import fail_stale_trials
from optuna.trial import TrialState, create_trial

from ermrl.cli._study import parse_duration, study_main
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
from ermrl.search import FitnessResult, Interrupted, create_or_resume_study, run_evolution
from ermrl.search._evolve import PopulationWarning, cma_popsize
from ermrl.storage import (
    HEARTBEAT_ATTR,
    LockTimeout,
    RetryStaleTrial,
    StorageError,
    fail_stale,
    find_stale_trials,
    normalize_url,
    open_storage,
    parse_storage_url,
    storage_kind,
    storage_lock,
    storage_url,
)
from ermrl.storage import _locks as locks_module
from ermrl.storage import fail_stale_trials as ermrl_fail_stale_trials

optuna.logging.set_verbosity(optuna.logging.WARNING)

SERVER_KINDS = [
    pytest.param("postgresql", marks=pytest.mark.services),
    pytest.param("mysql", marks=pytest.mark.services),
    pytest.param("redis", marks=pytest.mark.services),
]
ALL_KINDS = ["sqlite", "journal", *SERVER_KINDS]


def tiny_config(n_trials: int = 4, **search: object) -> EvolveConfig:
    """A configuration whose fitness the tests compute with a stub (nothing is trained)."""
    space = ReservoirSpace(units=10)
    problem = Problem(
        task=TaskConfig("Pendulum-v1", "positions"),
        encoder=EncoderConfig(reservoirs=space.default_reservoirs()),
        ppo=PPOConfig(hyperparams={"n_steps": 128, "batch_size": 64}),
        budget=BudgetConfig(training_steps=256),
        seeds=(0,),
    )
    return EvolveConfig(
        problem=problem, space=space, search=SearchConfig(n_trials=n_trials, **search)
    )


def stub_fitness(delay: float = 0.0, hook=None):  # noqa: ANN001, ANN201
    """An ``evaluate`` for run_evolution: a smooth function of sr, after ``delay`` seconds."""

    def evaluate(encoder, runner, report):  # noqa: ANN001, ANN202
        if hook is not None:
            hook()
        time.sleep(delay)
        value = -((math.log10(encoder.reservoirs[0].sr) - 0.0) ** 2)
        return FitnessResult(fitness=value, mode="last", runs=[], wall_seconds=max(delay, 1e-3))

    return evaluate


# -- URLs ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("url", "kind"),
    [
        ("sqlite:///x.db", "sqlite"),
        ("postgresql://u@h/db", "postgresql"),
        ("postgres://u@h/db", "postgresql"),
        ("postgresql+psycopg2://u@h/db", "postgresql"),
        ("mysql://root@h/db", "mysql"),
        ("mysql+pymysql://root@h/db", "mysql"),
        ("journal:///tmp/x.log", "journal"),
        ("studies.log", "journal"),
        ("redis://localhost:6379", "redis"),
    ],
)
def test_storage_kind(url: str, kind: str) -> None:
    assert storage_kind(url) == kind


def test_bad_urls_and_paths_give_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(StorageError, match="unsupported storage URL"):
        storage_kind("ftp://x")
    with pytest.raises(StorageError, match="does not exist"):
        open_storage(f"sqlite:///{tmp_path}/missing/s.db")
    with pytest.raises(StorageError, match="does not exist"):
        open_storage(f"{tmp_path}/missing/s.log")
    with pytest.raises(StorageError, match="longer than the heartbeat"):
        open_storage(f"sqlite:///{tmp_path}/s.db", heartbeat_interval=10, grace_period=5)
    with pytest.raises(StorageError, match="cannot open storage"):
        open_storage("postgresql://nobody@127.0.0.1:1/none")


def test_normalize_url() -> None:
    assert normalize_url("postgres://u@h/db").startswith("postgresql")
    assert normalize_url("postgres://u@h/db").endswith("://u@h/db")
    assert normalize_url("mysql://root@h/db").startswith("mysql+")
    assert normalize_url("sqlite:///x.db") == "sqlite:///x.db"


@pytest.mark.parametrize("fresh_storage", ALL_KINDS, indirect=True)
def test_every_backend_opens_with_heartbeats_and_retries(fresh_storage: str) -> None:
    storage = open_storage(fresh_storage, heartbeat_interval=1, grace_period=2, max_retry=2)
    assert storage_url(storage) == fresh_storage
    study = optuna.create_study(study_name="s", storage=storage, direction="maximize")
    assert storage_url(study._storage) == fresh_storage  # also through Optuna's cache wrapper
    assert study._storage.get_heartbeat_interval() == 1
    callback = study._storage.get_heartbeat_stale_trial_callback()
    assert isinstance(callback, RetryStaleTrial) and callback.max_retry == 2
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
    assert len(study.get_trials(states=[TrialState.COMPLETE])) == 2


@pytest.mark.parametrize("fresh_storage", ALL_KINDS, indirect=True)
def test_storage_lock_is_exclusive(fresh_storage: str) -> None:
    open_storage(fresh_storage)  # creates the file or schema
    held, release = threading.Event(), threading.Event()

    def hold() -> None:
        with storage_lock(fresh_storage, "study-a"):
            held.set()
            release.wait(10)

    thread = threading.Thread(target=hold)
    thread.start()
    assert held.wait(10)
    try:
        with pytest.raises(LockTimeout):
            with storage_lock(fresh_storage, "study-a", timeout=0.3):
                pass
    finally:
        release.set()
        thread.join()
    with storage_lock(fresh_storage, "study-a", timeout=5):
        pass


def test_a_journal_lock_whose_owner_is_gone_is_broken_after_the_grace_period(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # What an older ermrl left: a link to <log>.ermrl, a file that never exists. Optuna's stale
    # check stats that target and retried at once forever, at full CPU.
    monkeypatch.setattr(locks_module, "_JOURNAL_LOCK_GRACE_S", 0.5)
    url = f"{tmp_path}/l.log"
    open_storage(url)
    link = tmp_path / "l.log.ermrl.lock"
    link.symlink_to(tmp_path / "l.log.ermrl")
    took: list[float] = []

    def take() -> None:
        start = time.monotonic()
        with storage_lock(url, "s", timeout=20):
            took.append(time.monotonic() - start)

    thread = threading.Thread(target=take, daemon=True)
    thread.start()
    thread.join(15)
    assert not thread.is_alive(), "the stale lock was never broken"
    assert took and 0.5 <= took[0] < 5
    assert not os.path.lexists(link)  # released after use
    assert [p.name for p in tmp_path.iterdir() if "aside" in p.name] == []


@pytest.mark.slow
def test_evolve_on_a_journal_with_a_dead_workers_lock_goes_on(tmp_path: Path) -> None:
    (tmp_path / "l.log.ermrl.lock").symlink_to(tmp_path / "l.log.ermrl")
    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", "import sys; from ermrl.cli import main; sys.exit(main())"]
        + ["evolve", "--env-id", "Pendulum-v1", "--n-trials", "1", "--n-seeds", "1"]
        + ["--training-steps", "256", "--n-envs", "1", "--units", "20"]
        + ["--ppo", "n_steps=128", "batch_size=64", "n_epochs=2"]
        + ["--storage", "l.log", "--study-name", "s"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 0, done.stderr
    assert time.monotonic() - start >= 30  # the documented grace period
    assert "broke the lock" in done.stderr
    study = optuna.load_study(study_name="s", storage=open_storage(f"{tmp_path}/l.log"))
    assert [t.state for t in study.trials] == [TrialState.COMPLETE]


# -- heartbeats and retries ---------------------------------------------------------------------


def _running_trial(study: optuna.Study) -> int:
    """A RUNNING trial with two parameters and CMA-ES-like system attributes."""
    trial = study.ask()
    trial.suggest_float("sr", 1e-4, 1e2, log=True)
    trial.suggest_float("lr", 1e-2, 1.0, log=True)
    study._storage.set_trial_system_attr(trial._trial_id, "cma:restart_0:generation", 3)
    study._storage.set_trial_system_attr(trial._trial_id, "cma:optimizer:0", "deadbeef")
    trial.set_user_attr("worker_pid", 12345)
    trial.set_user_attr("fail_reason", "old")
    return trial.number


@pytest.mark.parametrize(
    "fresh_storage",
    ["journal", "sqlite", pytest.param("postgresql", marks=pytest.mark.services)],
    indirect=True,
)
def test_stale_trial_is_failed_and_retried_with_the_same_params(fresh_storage: str) -> None:
    storage = open_storage(fresh_storage, heartbeat_interval=1, grace_period=2, max_retry=1)
    study = optuna.create_study(study_name="s", storage=storage)
    # SQLite's CURRENT_TIMESTAMP (the heartbeat clock) has a resolution of one second.
    beyond_grace = 3.1 if storage_kind(fresh_storage) == "sqlite" else 2.3
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        number = _running_trial(study)
        storage.record_heartbeat(study.trials[number]._trial_id)
        fail_stale_trials(study)
        assert study.trials[number].state == TrialState.RUNNING  # heartbeat is fresh
        time.sleep(beyond_grace)
        fail_stale_trials(study)
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.FAIL, TrialState.WAITING]
    failed, retry = trials
    assert retry.params == failed.params
    assert retry.system_attrs["failed_trial"] == number
    assert retry.system_attrs["cma:restart_0:generation"] == 3
    assert not any(":optimizer:" in k or k == HEARTBEAT_ATTR for k in retry.system_attrs)
    assert retry.user_attrs["retry_of"] == number and "fail_reason" not in retry.user_attrs
    assert "worker_pid" not in retry.user_attrs  # the worker that runs it records itself

    # The retry is picked by the next ask(); with max_retry=1 it is not retried again.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = study.ask()
        assert again.number == retry.number and again.params == failed.params
        storage.record_heartbeat(again._trial_id)
        time.sleep(beyond_grace)
        fail_stale_trials(study)
    assert [t.state for t in study.get_trials()] == [TrialState.FAIL, TrialState.FAIL]


@pytest.mark.parametrize(
    "fresh_storage",
    ["sqlite", pytest.param("postgresql", marks=pytest.mark.services)],
    indirect=True,
)
def test_a_trial_whose_worker_died_before_its_first_heartbeat_is_failed_and_retried(
    fresh_storage: str,
) -> None:
    # Optuna's RDB check ignores a RUNNING trial without any heartbeat: a worker killed between
    # ask() and its first heartbeat left the trial RUNNING forever, and the other workers waited.
    storage = open_storage(fresh_storage, heartbeat_interval=1, grace_period=2, max_retry=1)
    study = optuna.create_study(study_name="s", storage=storage)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        number = _running_trial(study)  # no heartbeat, ever
        assert ermrl_fail_stale_trials(study) == []  # younger than the grace period
        time.sleep(3.2)
        failed = ermrl_fail_stale_trials(study)
    assert [t.number for t in failed] == [number]
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.FAIL, TrialState.WAITING]
    assert trials[0].user_attrs["fail_reason"].endswith(f"retried as trial {trials[1].number}")
    assert trials[1].params == trials[0].params


def test_a_journal_heartbeat_on_a_full_disk_is_logged_not_raised(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The heartbeat thread of a journal study on a full disk wrote a thread traceback
    (``OSError: No space left on device``) over the worker's one-line error."""
    log = tmp_path / "s.log"
    storage = open_storage(str(log), heartbeat_interval=60)
    study = optuna.create_study(study_name="s", storage=storage)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trial = study.ask()
    log.unlink()
    log.symlink_to("/dev/full")  # every write: ENOSPC, as on a full disk
    with caplog.at_level("WARNING", logger="ermrl.storage"):
        storage.record_heartbeat(trial._trial_id)
    assert f"missed a heartbeat of trial id {trial._trial_id}" in caplog.text
    assert "No space left on device" in caplog.text


def test_fail_stale_uses_heartbeats_else_start_time(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    study = optuna.create_study(study_name="s", storage=open_storage(url, heartbeat_interval=60))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        alive = study.ask()
        study._storage.record_heartbeat(alive._trial_id)
        silent = study.ask()
    silent.suggest_float("x", 0, 1)
    time.sleep(2.5)
    # The alive trial's heartbeat is refreshed right before each look, so that a slow machine
    # cannot age it past the threshold between two calls.
    study._storage.record_heartbeat(alive._trial_id)
    stale = find_stale_trials(study, older_than=2.0)
    assert [t.number for t in stale] == [silent.number]
    study._storage.record_heartbeat(alive._trial_id)
    dry = fail_stale(study, 2.0, retry=RetryStaleTrial(3), dry_run=True)
    assert [(t.number, r) for t, r in dry] == [(silent.number, True)]
    assert study.trials[silent.number].state == TrialState.RUNNING
    study._storage.record_heartbeat(alive._trial_id)
    done = fail_stale(study, 2.0, retry=RetryStaleTrial(3))
    assert [(t.number, r) for t, r in done] == [(silent.number, True)]
    states = [t.state for t in study.get_trials()]
    assert states == [TrialState.RUNNING, TrialState.FAIL, TrialState.WAITING]
    assert study.trials[silent.number].user_attrs["fail_reason"].startswith("stale")


# -- the worker loop ----------------------------------------------------------------------------


def test_budget_is_exact_and_waiting_trials_are_claimed(tmp_path: Path) -> None:
    url = f"journal:///{tmp_path}/s.log"
    config = tiny_config(n_trials=4, sampler="random", sampler_seed=0)
    study = create_or_resume_study(config, url, "s", heartbeat_interval=1, grace_period=3)
    dist = {"sr": FloatDistribution(1e-4, 1e2, log=True)}
    study.add_trial(
        create_trial(
            state=TrialState.WAITING,
            params={"sr": 2.0},
            distributions=dist,
        )
    )
    summary = run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    trials = study.get_trials()
    assert summary.completed == 4 and len(trials) == 4
    assert all(t.state == TrialState.COMPLETE for t in trials)
    # The queued trials ran first: the reference reservoir (queued when the study was created),
    # then the one added here.
    assert trials[0].user_attrs["reference"] is True and trials[0].params["sr"] == 1.0
    assert trials[1].params["sr"] == 2.0
    # Nothing left to do: a second worker stops at once.
    assert run_evolution(config, study, quiet=True, evaluate=stub_fitness()).trials_run == 0


def test_worker_waits_for_a_dead_workers_trial_and_retries_it(tmp_path: Path) -> None:
    url = f"journal:///{tmp_path}/s.log"
    config = tiny_config(n_trials=2, sampler="random", sampler_seed=0)
    study = create_or_resume_study(config, url, "s", heartbeat_interval=1, grace_period=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dead = _running_trial(study)  # a worker that died: it never sends a heartbeat
        study._storage.record_heartbeat(study.trials[dead]._trial_id)
    lines = []

    class Stream:
        def write(self, text: str) -> None:
            lines.append(text)

        def flush(self) -> None:
            pass

    summary = run_evolution(config, study, stream=Stream(), evaluate=stub_fitness())  # type: ignore[arg-type]
    states = [t.state for t in study.get_trials()]
    assert states.count(TrialState.COMPLETE) == 2 and states.count(TrialState.FAIL) == 1
    assert summary.completed == 2
    assert any("waiting for 1 running trial" in line for line in lines)
    assert any(f"retry of #{dead}" in line for line in lines)


@pytest.mark.parametrize("fresh_storage", ["journal", "sqlite"], indirect=True)
@pytest.mark.parametrize("max_retry", [1, 0])
def test_a_dead_workers_trial_is_failed_with_a_reason(fresh_storage: str, max_retry: int) -> None:
    config = tiny_config(n_trials=2, sampler="random", sampler_seed=0)
    study = create_or_resume_study(
        config, fresh_storage, "s", heartbeat_interval=1, grace_period=2, max_retry=max_retry
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dead = _running_trial(study)  # a worker killed with kill -9: no more heartbeats
        study._storage.record_heartbeat(study.trials[dead]._trial_id)
    time.sleep(3.1)  # SQLite's heartbeat clock has a resolution of one second
    run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    trials = study.get_trials()
    failed = trials[dead]
    assert failed.state == TrialState.FAIL
    if max_retry:
        (retry,) = [t for t in trials if t.user_attrs.get("retry_of") == dead]
        assert retry.state == TrialState.COMPLETE
        expected = f"heartbeat lost (none for 2 s), retried as trial {retry.number}"
    else:
        assert not any("retry_of" in t.user_attrs for t in trials)
        expected = "heartbeat lost (none for 2 s), not retried"
    assert failed.user_attrs["fail_reason"] == expected


def test_waiting_worker_sees_another_workers_trial_end_within_a_second(tmp_path: Path) -> None:
    """At the budget, a worker waits for the others' running trials; it must notice one that
    ends soon at once (it used to sleep half the heartbeat interval, up to 5 s, per look)."""
    url = f"sqlite:///{tmp_path}/s.db"
    config = tiny_config(n_trials=1, sampler="random", sampler_seed=0)
    study = create_or_resume_study(config, url, "s", heartbeat_interval=60, grace_period=300)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        number = _running_trial(study)  # the other worker's live trial
        other = study.trials[number]
        study._storage.record_heartbeat(other._trial_id)

    def other_worker_finishes() -> None:
        time.sleep(1.0)
        study._storage.set_trial_state_values(other._trial_id, TrialState.COMPLETE, [1.0])

    finisher = threading.Thread(target=other_worker_finishes)
    start = time.monotonic()
    finisher.start()
    summary = run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    elapsed = time.monotonic() - start
    finisher.join()
    assert summary.trials_run == 0
    assert study.trials[other.number].state == TrialState.COMPLETE
    assert 1.0 <= elapsed < 3.0, f"the waiting worker exited {elapsed:.2f} s after the start"


def test_a_sigterm_dropped_before_the_wait_stops_the_waiting_worker(tmp_path: Path) -> None:
    """SIGTERM at a command's start-up, whose exception a weakref callback dropped, was noted
    but only a training loop raised it again: a worker with nothing to train waited for the
    others' trials (here until the other trial was stale, then ran its retry) and exited 0."""
    import sys
    import weakref

    from ermrl._interrupt import catch_sigterm

    url = f"sqlite:///{tmp_path}/s.db"
    config = tiny_config(n_trials=1, sampler="random", sampler_seed=0)
    study = create_or_resume_study(config, url, "s", heartbeat_interval=1, grace_period=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _running_trial(study)  # the other worker's trial: the budget is spent

    def in_a_callback(_: object) -> None:
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(100):  # the handler runs here, and its exception is dropped
            pass

    handler, hook = signal.getsignal(signal.SIGTERM), sys.unraisablehook
    try:
        catch_sigterm()  # as every command does at its start
        thing = type("Thing", (), {})()
        ref = weakref.ref(thing, in_a_callback)
        del thing, ref  # the signal lands in the callback
        with pytest.raises(Interrupted) as caught:
            run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    finally:
        signal.signal(signal.SIGTERM, handler)
        sys.unraisablehook = hook
    assert caught.value.trial_number is None  # between trials: nothing was running
    assert [t.state for t in study.get_trials()] == [TrialState.RUNNING]


def test_sigterm_closes_the_trial_queues_it_again_and_exits(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    config = tiny_config(n_trials=3, sampler="random", sampler_seed=0)
    study = create_or_resume_study(config, url, "s")
    calls = []

    def terminate() -> None:
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGTERM)

    # What this process had before (a command run in-process earlier in the same pytest
    # worker may have left its own handler: run_command's).
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted):
        run_evolution(config, study, quiet=True, evaluate=stub_fitness(0.5, terminate))
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.COMPLETE, TrialState.FAIL, TrialState.WAITING]
    assert trials[1].user_attrs["fail_reason"] == "interrupted by SIGTERM"
    assert trials[2].params == trials[1].params
    assert signal.getsignal(signal.SIGTERM) is before  # handler restored

    # A restarted worker runs the queued trial first and finishes the budget.
    run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    states = [t.state for t in study.get_trials()]
    assert states.count(TrialState.COMPLETE) == 3 and states.count(TrialState.FAIL) == 1
    assert study.get_trials()[2].params == trials[1].params


@pytest.mark.parametrize("signame", ["SIGTERM", "SIGINT"])
def test_a_signal_in_a_generation_names_every_trial_it_closed(tmp_path: Path, signame: str) -> None:
    """The population backend trains a generation at once and a signal closes all its trials;
    the last line named only one ("trial #6 was closed" when 7 were)."""
    import dataclasses

    from ermrl.runner._commands import _ctrl_c_message, interrupted_message

    config = tiny_config(n_trials=3, sampler="random", sampler_seed=0)
    ppo = dataclasses.replace(config.problem.ppo, backend="population")
    config = dataclasses.replace(config, problem=dataclasses.replace(config.problem, ppo=ppo))
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")

    def generation(encoders, runner):  # noqa: ANN001, ANN202
        os.kill(os.getpid(), getattr(signal, signame))
        time.sleep(10)

    with pytest.raises(KeyboardInterrupt) as caught:
        run_evolution(config, study, quiet=True, evaluate_generation=generation)
    message = (
        interrupted_message(caught.value)
        if isinstance(caught.value, Interrupted)
        else _ctrl_c_message(caught.value)
    )
    assert message.endswith(
        "; the 3 running trials #0, #1, #2 were closed as FAIL and queued again"
    ), message
    assert [t.state for t in study.get_trials()] == [TrialState.FAIL] * 3 + [TrialState.WAITING] * 3


@pytest.mark.parametrize("signame", ["SIGTERM", "SIGINT"])
def test_a_signal_dropped_in_a_weakref_callback_still_stops_the_training(
    tmp_path: Path, signame: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """A signal whose exception Python drops ("Exception ignored in ... WeakKeyDictionary
    ... remove") let a generation train to its end (42 s after SIGTERM, measured), then said
    that no trial was running; its training loop now raises it again at its next step."""
    import dataclasses
    import weakref

    from ermrl._interrupt import raise_swallowed_signal
    from ermrl.runner._commands import _ctrl_c_message, interrupted_message

    config = tiny_config(n_trials=2, sampler="random", sampler_seed=0)
    ppo = dataclasses.replace(config.problem.ppo, backend="population")
    config = dataclasses.replace(config, problem=dataclasses.replace(config.problem, ppo=ppo))
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")

    def in_a_callback(_: object) -> None:
        os.kill(os.getpid(), getattr(signal, signame))
        for _ in range(100):  # the handler runs here, and its exception is dropped
            pass

    def generation(encoders, runner):  # noqa: ANN001, ANN202
        thing = type("Thing", (), {})()
        ref = weakref.ref(thing, in_a_callback)
        del thing, ref  # the callback runs now
        for _ in range(100):  # a training loop: 10 s
            raise_swallowed_signal()
            time.sleep(0.1)
        return [FitnessResult(fitness=0.0, mode="last", runs=[], wall_seconds=1.0)] * len(encoders)

    start = time.monotonic()
    with pytest.raises(KeyboardInterrupt) as caught:
        run_evolution(config, study, quiet=True, evaluate_generation=generation)
    assert time.monotonic() - start < 5
    assert isinstance(caught.value, Interrupted) == (signame == "SIGTERM")
    message = (
        interrupted_message(caught.value)
        if isinstance(caught.value, Interrupted)
        else _ctrl_c_message(caught.value)
    )
    assert "the 2 running trials #0, #1 were closed as FAIL and queued again" in message
    reason = "interrupted" if signame == "SIGINT" else "interrupted by SIGTERM"
    trials = study.get_trials()
    assert [t.user_attrs.get("fail_reason") for t in trials[:2]] == [reason] * 2
    assert "Exception ignored" not in capsys.readouterr().err


@pytest.mark.parametrize("cause", ["SIGINT", "SIGTERM", "crash"])
def test_any_interruption_of_the_reference_trial_queues_it_again(
    tmp_path: Path, cause: str
) -> None:
    """Ctrl-C, SIGTERM or an error of the program in the reference trial (trial 0, the
    unevolved reservoir): it is closed as FAIL and queued again, and the rerun trains it."""
    url = f"sqlite:///{tmp_path}/s.db"
    config = tiny_config(n_trials=2, sampler="random", sampler_seed=0)
    study = create_or_resume_study(config, url, "s")

    def cut_short() -> None:
        if cause == "crash":
            raise RuntimeError("a bug")
        os.kill(os.getpid(), getattr(signal, cause))

    expected = RuntimeError if cause == "crash" else KeyboardInterrupt
    with pytest.raises(expected):
        run_evolution(config, study, quiet=True, evaluate=stub_fitness(0.5, cut_short))
    trials = study.get_trials()
    assert [t.state for t in trials] == [TrialState.FAIL, TrialState.WAITING]
    assert trials[1].user_attrs["reference"] and trials[1].user_attrs["retry_of"] == 0
    run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    (reference,) = study.get_trials(states=[TrialState.COMPLETE])[:1]
    assert reference.number == 1 and reference.params == trials[0].params
    assert reference.params == config.space.reference_params()


def test_a_reference_trial_every_run_cut_short_is_queued_again(tmp_path: Path) -> None:
    """A study whose reference trial was closed without a retry (an older ermrl closed Ctrl-C's
    trials so) gets it queued again by the next worker, and only while no run of it finished."""
    url = f"sqlite:///{tmp_path}/s.db"
    config = tiny_config(n_trials=2, sampler="random", sampler_seed=0)
    study = create_or_resume_study(config, url, "s")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trial = study.ask()
    trial.set_user_attr("fail_reason", "interrupted")
    study.tell(trial, state=TrialState.FAIL)
    out = io.StringIO()
    run_evolution(config, study, stream=out, evaluate=stub_fitness())
    assert "the reference trial #0 was cut short by every run; queued again" in out.getvalue()
    complete = study.get_trials(states=[TrialState.COMPLETE])
    assert complete[0].params == config.space.reference_params()
    assert complete[0].user_attrs["retry_of"] == 0 and len(complete) == 2
    run_evolution(config, study, stream=out, evaluate=stub_fitness())  # nothing queued twice
    assert len(study.get_trials()) == 3


OTHER_CODE = {"version": "0.0.1", "commit": "0123456789ab", "dirty": False, "source": "f" * 64}


def test_workers_of_other_code_are_told_everywhere_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A newer worker joins a study: the older one was not told, ``study show`` and the report
    did not say that the trials mix code versions, and the newer one's warning took 2 lines."""
    url = f"sqlite:///{tmp_path}/s.db"
    config = tiny_config(n_trials=3, sampler="random", sampler_seed=0)
    study = create_or_resume_study(config, url, "s")  # the older worker: this code
    distributions = {"sr": FloatDistribution(0.01, 10.0, log=True)}
    study.add_trial(  # a trial of a newer worker, on other code
        create_trial(params={"sr": 1.0}, distributions=distributions, value=-1.0,
                     user_attrs={"ermrl_code": OTHER_CODE})
    )  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    told = [w for w in caught if "mix code versions" in str(w.message)]
    assert len(told) == 1, [str(w.message) for w in caught]  # once, not at every claim
    assert "holds trials of ermrl 0.0.1 at 0123456789" in str(told[0].message)
    text = warnings.formatwarning(told[0].message, told[0].category, told[0].filename,
                                  told[0].lineno, told[0].line)  # fmt: skip
    assert text.count("\n") == 1, text

    # The newer worker joining a study created by other code: one line too.
    study.set_user_attr("ermrl_code", OTHER_CODE)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        create_or_resume_study(config, url, "s")
    (joined,) = [w for w in caught if "mix code versions" in str(w.message)]
    text = warnings.formatwarning(joined.message, joined.category, joined.filename,
                                  joined.lineno, joined.line)  # fmt: skip
    assert "was created by ermrl 0.0.1" in text and text.count("\n") == 1, text

    assert study_main(["show", "--storage", url, "--study-name", "s"]) == 0
    out = capsys.readouterr().out
    (line,) = [line for line in out.splitlines() if line.startswith("code: ")]
    assert line.startswith("code: trials come from 2 code versions"), out
    assert "ermrl 0.0.1 at 0123456789, source ffffffffff (1 trial)" in line
    assert study_main(["show", "--storage", url, "--study-name", "s", "--json"]) == 0
    code = json.loads(capsys.readouterr().out)["code"]
    assert [entry["trials"] for entry in code] == [2, 1]
    assert code[1]["commit"] == "0123456789ab"

    from ermrl.analysis import write_report

    report = write_report(
        "s", url, runs=tmp_path / "none", out=tmp_path / "r", interactive=False, html_page=False
    )
    assert [w.split(":")[0] for w in report.warnings] == [
        "trials come from 2 code versions, so their results may not compare"
    ]
    assert "**Warning:** trials come from 2 code versions" in report.markdown.read_text()


def test_popsize_smaller_than_workers_warns(tmp_path: Path) -> None:
    config = tiny_config(n_trials=1, popsize=4)
    assert cma_popsize(config) == 4
    assert cma_popsize(tiny_config()) == 4 + math.floor(3 * math.log(3))
    assert cma_popsize(tiny_config(sampler="tpe")) is None
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")
    with pytest.warns(PopulationWarning, match="--popsize 20"):
        run_evolution(config, study, quiet=True, evaluate=stub_fitness(), n_workers=20)


# -- the ermrl study CLI ------------------------------------------------------------------------


def test_parse_duration() -> None:
    assert parse_duration("90") == 90
    assert parse_duration("30m") == 1800
    assert parse_duration("2h") == 7200
    assert parse_duration("1.5d") == 1.5 * 86400


def _filled_study(url: str) -> optuna.Study:
    config = tiny_config(n_trials=3, sampler="random", sampler_seed=0)
    study = create_or_resume_study(config, url, "demo")
    run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    return study


def test_study_cli_create_list_show_export_delete(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    assert study_main(["create", "--storage", url, "--study-name", "bare"]) == 0
    assert "created" in capsys.readouterr().out
    _filled_study(url)

    assert study_main(["list", "--storage", url]) == 0
    out = capsys.readouterr().out
    assert "bare" in out and "demo" in out and "3/3" in out

    assert study_main(["show", "--storage", url, "--study-name", "demo"]) == 0
    out = capsys.readouterr().out
    assert "3/3 done" in out and "best: trial" in out and "workers (1)" in out
    assert study_main(["show", "--storage", url, "--study-name", "demo", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["counts"]["COMPLETE"] == 3 and info["budget"] == 3

    for name in ("t.csv", "t.parquet"):
        assert (
            study_main(
                ["export", "--storage", url, "--study-name", "demo", "--out", str(tmp_path / name)]
            )
            == 0
        )
    capsys.readouterr()
    csv = pd.read_csv(tmp_path / "t.csv")
    parquet = pd.read_parquet(tmp_path / "t.parquet")
    for frame in (csv, parquet):
        assert len(frame) == 3 and set(frame["state"]) == {"COMPLETE"}
        assert {"params_sr", "params_lr", "user_attrs_worker_pid", "value"} <= set(frame.columns)

    with pytest.raises(SystemExit) as err:
        study_main(["delete", "--storage", url, "--study-name", "demo"])
    assert err.value.code == 2 and "--yes" in capsys.readouterr().err
    assert study_main(["delete", "--storage", url, "--study-name", "demo", "--yes"]) == 0
    assert optuna.get_all_study_names(url) == ["bare"]


def test_study_show_when_workers_ran_with_different_budgets(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    small = tiny_config(n_trials=1, sampler="random", sampler_seed=0)
    study = create_or_resume_study(small, url, "demo")  # the first worker stores n_trials=1
    run_evolution(small, study, quiet=True, evaluate=stub_fitness())
    run_evolution(tiny_config(n_trials=4), study, quiet=True, evaluate=stub_fitness())

    assert study_main(["show", "--storage", url, "--study-name", "demo"]) == 0
    out = capsys.readouterr().out
    assert "4/1" not in out and "trials: 4 done" in out
    assert "--n-trials 4 (3 trials), 1 (1 trial); the study's configuration says 1" in out
    assert study_main(["show", "--storage", url, "--study-name", "demo", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["worker_budgets"] == {"4": 3, "1": 1}
    assert study_main(["list", "--storage", url]) == 0
    assert "4/1,4" in capsys.readouterr().out
    assert [t.user_attrs["worker_n_trials"] for t in study.trials] == [1, 4, 4, 4]


def test_study_cli_create_with_a_configuration_and_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    args = ["create", "--storage", url, "--study-name", "p", "--env-id", "Pendulum-v1"]
    assert study_main([*args, "--training-steps", "256", "--n-trials", "5"]) == 0
    study = optuna.load_study(study_name="p", storage=url)
    assert study.user_attrs["ermrl_config"]["search"]["n_trials"] == 5
    for bad in (
        [*args, "--training-steps", "512"],  # another configuration
        ["show", "--storage", url, "--study-name", "nope"],
        ["fail-stale", "--storage", url, "--study-name", "p", "--older-than", "soon"],
        ["export", "--storage", url, "--study-name", "p", "--out", str(tmp_path / "t.xlsx")],
    ):
        with pytest.raises(SystemExit) as err:
            study_main(bad)
        assert err.value.code == 2
        message = capsys.readouterr().err.strip()
        assert message.startswith("ermrl study") and "\n" not in message


def test_study_cli_fail_stale_on_a_journal(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"{tmp_path}/s.log"
    study = optuna.create_study(study_name="j", storage=open_storage(url))
    number = _running_trial(study)
    assert (
        study_main(["fail-stale", "--storage", url, "--study-name", "j", "--older-than", "1h"]) == 0
    )
    assert "0 stale trial(s)" in capsys.readouterr().out
    time.sleep(1.2)
    argv = ["fail-stale", "--storage", url, "--study-name", "j", "--older-than", "1s"]
    assert study_main([*argv, "--dry-run"]) == 0
    assert f"would fail and retry trial {number}" in capsys.readouterr().out
    assert study_main(argv) == 0
    assert f"failed and retry trial {number}" in capsys.readouterr().out
    states = [t.state for t in optuna.load_study(study_name="j", storage=open_storage(url)).trials]
    assert states == [TrialState.FAIL, TrialState.WAITING]


class _RunsCode:
    """A pickle that runs a shell command when it is loaded (what a snapshot key may hold)."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (os.system, (self.command,))


@pytest.mark.services
def test_a_redis_snapshot_is_never_unpickled_and_the_log_is_replayed(
    redis_url: str, tmp_path: Path
) -> None:
    optuna.create_study(study_name="kept", storage=open_storage(redis_url))
    spec = parse_storage_url(redis_url)
    marker = tmp_path / "ran"
    client = redis.Redis.from_url(spec.url)
    client.set(f"{spec.prefix}:snapshot", pickle.dumps(_RunsCode(f"touch {marker}")))
    client.close()

    done = subprocess.run(
        [sys.executable, "-c", "import sys; from ermrl.cli import main; sys.exit(main())"]
        + ["study", "list", "--storage", redis_url],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert not marker.exists()
    assert "kept" in done.stdout
    warning = [line for line in done.stderr.splitlines() if "snapshot" in line]
    assert len(warning) == 1 and f"{spec.prefix}:snapshot" in warning[0], done.stderr
