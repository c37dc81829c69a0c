"""The fitness of a reservoir and the evolution loop over a real SQLite study."""

from __future__ import annotations

import dataclasses
import io
import subprocess
import sys
import time
import warnings

import optuna
import pytest
from optuna.trial import TrialState

import tests.test_agents  # noqa: F401  (registers the ErmrlNaN-v0 env)
from ermrl.config import (
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    EvolveConfig,
    PPOConfig,
    Problem,
    Range,
    ReservoirParams,
    ReservoirSpace,
    SearchConfig,
    TaskConfig,
)
from ermrl.search import (
    SeedRunner,
    create_or_resume_study,
    evaluate_encoder,
    pool_size,
    run_evolution,
    study_config,
)
from ermrl.search._study import metric_description

TINY_PPO = PPOConfig(n_envs=1, hyperparams={"n_steps": 128, "batch_size": 64, "n_epochs": 2})


def make_config(
    env_id: str = "Pendulum-v1",
    observe: str = "positions",
    n_trials: int = 3,
    seeds: tuple[int, ...] = (0, 1),
    steps: int = 256,
    **search: object,
) -> EvolveConfig:
    space = ReservoirSpace(units=20)
    problem = Problem(
        task=TaskConfig(env_id, observe),  # type: ignore[arg-type]
        encoder=EncoderConfig(reservoirs=space.default_reservoirs()),
        ppo=TINY_PPO,
        budget=BudgetConfig(training_steps=steps, n_last_episodes=2),
        seeds=seeds,
    )
    return EvolveConfig(
        problem=problem,
        space=space,
        search=SearchConfig(n_trials=n_trials, sampler_seed=0, **search),
    )


def test_config_round_trip_and_names() -> None:
    config = make_config()
    assert EvolveConfig.from_dict(config.to_dict()) == config
    assert config.default_study_name == "Pendulum-v1__positions__256steps"
    multi = ReservoirSpace(n_reservoirs=2, input_scaling=None)
    assert multi.param_names == ("sr_0", "lr_0", "sr_1", "lr_1")
    assert ReservoirSpace().param_names == ("sr", "lr", "input_scaling")
    res = multi.reservoirs_from({"sr_0": 1.0, "lr_0": 0.5, "sr_1": 2.0, "lr_1": 0.1})
    assert [r.sr for r in res] == [1.0, 2.0] and all(r.input_scaling == 1.0 for r in res)


@pytest.mark.parametrize(
    "make",
    [
        lambda: Range(10.0, 1.0),
        lambda: Range(1.0, 1.0),
        lambda: Range(0.0, 1.0),
        lambda: BudgetConfig(training_steps=0),
        lambda: SearchConfig(n_trials=0),
        lambda: SearchConfig(sampler="tpe", restart="ipop"),
        lambda: ReservoirSpace(lr=Range(0.1, 2.0)),
        lambda: ReservoirParams(lr=0.0),
    ],
)
def test_bad_configs_raise(make) -> None:  # noqa: ANN001
    with pytest.raises(ConfigError):
        make()


def test_same_trial_same_seed_same_fitness_in_and_across_processes() -> None:
    problem = make_config().problem
    reservoirs = (ReservoirParams(units=20, sr=0.7, lr=0.3, input_scaling=2.0),)
    encoder = problem.encoder.with_reservoirs(reservoirs)
    a = evaluate_encoder(encoder, problem)
    b = evaluate_encoder(encoder, problem)
    with SeedRunner(2) as runner:
        c = evaluate_encoder(encoder, problem, runner=runner)
    assert a.fitness == b.fitness == c.fitness
    assert [r.episode_returns for r in a.runs] == [r.episode_returns for r in c.runs]
    other = evaluate_encoder(
        problem.encoder.with_reservoirs((dataclasses.replace(reservoirs[0], sr=5.0),)), problem
    )
    assert other.fitness != a.fitness
    assert a.fitness == pytest.approx(sum(r.last_return for r in a.runs) / 2)


def _waves(n_jobs: int, n_procs: int, q: int) -> float:
    """Run-times that ``n_jobs`` equal runs take in a pool of ``q`` processes on ``n_procs`` cores."""
    waves, rest = divmod(n_jobs, q)
    return waves * max(1.0, q / n_procs) + (max(1.0, rest / n_procs) if rest else 0.0)


@pytest.mark.parametrize(
    ("n_jobs", "n_procs", "expected"),
    [
        (3, 1, 1),  # one core: runs stay in this process
        (1, 4, 1),  # one run: no pool
        (2, 2, 2),
        (3, 4, 3),  # never more processes than runs
        (3, 2, 3),  # the paper's 3 seeds on 2 cores: no core idles during the third seed
        (4, 2, 2),  # divides evenly: one process per core
        (6, 2, 2),
        (5, 2, 3),
        (7, 2, 4),
        (10, 4, 5),
        (15, 2, 3),  # 5 tasks x 3 seeds: capped at twice the cores
    ],
)
def test_pool_size_keeps_cores_busy(n_jobs: int, n_procs: int, expected: int) -> None:
    q = pool_size(n_jobs, n_procs)
    assert q == expected
    assert q <= max(1, min(n_jobs, 2 * n_procs))
    if n_procs > 1 and n_jobs > 1:
        # Never slower than one process per core, and optimal among pools up to 2x the cores.
        plain = min(n_procs, n_jobs)
        assert _waves(n_jobs, n_procs, q) <= _waves(n_jobs, n_procs, plain)
        pools = range(min(n_procs, n_jobs), min(n_jobs, 2 * n_procs) + 1)
        best = min(_waves(n_jobs, n_procs, k) for k in pools)
        assert _waves(n_jobs, n_procs, q) == pytest.approx(best)


def test_seed_runner_balances_three_seeds_on_two_cores() -> None:
    """3 seeds on 2 cores run in 3 processes, with the same fitness as in this process."""
    problem = dataclasses.replace(make_config().problem, seeds=(0, 1, 2))
    reservoirs = (ReservoirParams(units=20, sr=0.7, lr=0.3),)
    here = evaluate_encoder(problem.encoder.with_reservoirs(reservoirs), problem)
    with SeedRunner(2) as runner:
        assert runner.processes_for(3) == 3 and runner.processes_for(4) == 2
        assert runner.start(3) == 3
        assert len(runner._pool._processes) == 3  # type: ignore[union-attr]  # all started
        pool = evaluate_encoder(problem.encoder.with_reservoirs(reservoirs), problem, runner=runner)
        assert runner.n_processes == 3
    assert runner.n_processes == 0  # closed
    assert [r.episode_returns for r in pool.runs] == [r.episode_returns for r in here.runs]
    assert pool.fitness == here.fitness
    with SeedRunner(2, balance=False) as fixed:
        assert fixed.processes_for(3) == 2


def test_evolution_says_how_seeds_are_placed(tmp_path) -> None:  # noqa: ANN001
    config = dataclasses.replace(make_config(n_trials=1, seeds=(0, 1, 2)), n_procs=2)
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")
    out = io.StringIO()
    assert run_evolution(config, study, stream=out).completed == 1
    assert "3 training runs per trial on 2 cores: 3 single-threaded processes" in out.getvalue()


def test_evolution_records_trials_and_resumes(tmp_path) -> None:  # noqa: ANN001
    url = f"sqlite:///{tmp_path}/s.db"
    config = make_config(n_trials=2)
    study = create_or_resume_study(config, url, "s", command="evolve_res.py --x")
    out = io.StringIO()
    summary = run_evolution(config, study, stream=out)
    assert summary.completed == 2
    lines = out.getvalue().splitlines()
    assert len(lines) == 2 and "fitness" in lines[0] and "best" in lines[0] and "ETA" in lines[0]

    trials = study.get_trials(states=[TrialState.COMPLETE])
    assert len(trials) == 2
    attrs = trials[0].user_attrs
    assert set(trials[0].params) == {"sr", "lr", "input_scaling"}
    assert attrs["seeds"] == [0, 1] and len(attrs["returns_last"]) == 2
    assert attrs["env_steps"] == 512 and attrs["steps_per_second"] > 0
    assert {"ermrl", "gymnasium", "stable_baselines3"} <= set(attrs["versions"])
    assert attrs["worker_pid"] > 0 and attrs["worker_hostname"]
    from ermrl._code import code_identity

    assert attrs["ermrl_code"] == code_identity() == study.user_attrs["ermrl_code"]
    assert trials[0].value == pytest.approx(sum(attrs["returns_last"]) / 2)
    # The training curve is stored as intermediate values (no pruner): optuna-dashboard draws
    # it; its last point is the fitness, and the objective has a name.
    curve = trials[0].intermediate_values
    assert len(curve) >= 2 and max(curve) == 256, curve  # each seed's 256 steps
    assert curve[256] == pytest.approx(trials[0].value)
    assert study.metric_names == ["fitness"]
    assert study.user_attrs["ermrl_metric"] == (
        "fitness: mean return of the last 2 training episodes, mean over seeds"
    )

    # the study stores its config and command: the test phase needs nothing else
    reloaded = optuna.load_study(study_name="s", storage=url)
    assert study_config(reloaded) == config
    assert reloaded.user_attrs["ermrl_command"] == "evolve_res.py --x"

    # the same command with a larger budget resumes; quiet prints nothing
    bigger = dataclasses.replace(config, search=dataclasses.replace(config.search, n_trials=3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same code: no warning
        study2 = create_or_resume_study(bigger, url, "s")
    # A study created by other code: resumed, with one line saying so.
    study2.set_user_attr("ermrl_code", {"version": "0.0.1", "commit": "0123456789ab",
                                        "dirty": False, "source": "f" * 64})  # fmt: skip
    with pytest.warns(UserWarning, match="created by ermrl 0.0.1 at 0123456789, source ffff"):
        create_or_resume_study(bigger, url, "s")
    out2 = io.StringIO()
    assert run_evolution(bigger, study2, stream=out2, quiet=True).completed == 1
    assert out2.getvalue() == ""
    assert len(study2.get_trials(states=[TrialState.COMPLETE])) == 3


def test_the_objective_has_a_short_name_and_its_description_is_an_attribute(
    tmp_path,  # noqa: ANN001
) -> None:
    study = create_or_resume_study(make_config(n_trials=1), f"sqlite:///{tmp_path}/s.db", "s")
    assert study.metric_names == ["fitness"]
    assert "value_fitness" in study.trials_dataframe(multi_index=False).columns
    assert study.user_attrs["ermrl_metric"] == (
        "fitness: mean return of the last 2 training episodes, mean over seeds"
    )
    evaluated = dataclasses.replace(
        make_config(),
        problem=dataclasses.replace(
            make_config().problem,
            budget=dataclasses.replace(
                make_config().problem.budget, fitness="eval", n_eval_episodes=3
            ),
        ),
    )
    assert metric_description(evaluated) == (
        "fitness: mean return of 3 deterministic episodes after training, mean over seeds"
    )


def test_a_study_named_with_the_former_long_metric_name_still_loads(tmp_path) -> None:  # noqa: ANN001
    """Studies made before the short name keep theirs; they load and export as before."""
    from ermrl.analysis import trials_table

    url = f"sqlite:///{tmp_path}/old.db"
    old = optuna.create_study(study_name="old", storage=url, direction="maximize")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        old.set_metric_names(
            ["fitness (mean return of the last 10 training episodes, mean over seeds)"]
        )
    old.add_trial(optuna.trial.create_trial(params={}, distributions={}, value=-1.5))
    loaded = create_or_resume_study(None, url, "old")
    assert loaded.metric_names == old.metric_names
    assert list(trials_table(loaded)["value"]) == [-1.5]


def test_resuming_with_another_problem_is_refused(tmp_path) -> None:  # noqa: ANN001
    url = f"sqlite:///{tmp_path}/s.db"
    create_or_resume_study(make_config(), url, "s")
    with pytest.raises(ConfigError, match="training_steps"):
        create_or_resume_study(make_config(steps=512), url, "s")


def test_diverging_trial_fails_and_the_run_goes_on(tmp_path) -> None:  # noqa: ANN001
    config = make_config(env_id="ErmrlNaN-v0", observe="all", n_trials=2, seeds=(0,))
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "nan")
    summary = run_evolution(config, study, quiet=True)
    assert summary.failed == 2
    failed = study.get_trials(states=[TrialState.FAIL])
    assert len(failed) == 2 and "diverged" in failed[0].user_attrs["fail_reason"]


def test_ctrl_c_closes_the_running_trial_and_keeps_the_rest(tmp_path) -> None:  # noqa: ANN001
    config = make_config(n_trials=5, seeds=(0,))
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")
    calls = []

    def evaluate(encoder, runner, report):  # noqa: ANN001, ANN202
        calls.append(encoder)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return evaluate_encoder(encoder, config.problem, runner=runner)

    with pytest.raises(KeyboardInterrupt):
        run_evolution(config, study, quiet=True, evaluate=evaluate)
    trials = study.get_trials()
    states = [t.state for t in trials]
    assert states == [TrialState.COMPLETE, TrialState.COMPLETE, TrialState.FAIL, TrialState.WAITING]
    assert trials[2].user_attrs["fail_reason"] == "interrupted"
    assert trials[3].params == trials[2].params and trials[3].user_attrs["retry_of"] == 2


def test_cmaes_restart_option_reaches_the_study(tmp_path) -> None:  # noqa: ANN001
    config = make_config(restart="ipop", popsize=4)
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")
    from ermrl.search import RestartCmaEsSampler

    assert isinstance(study.sampler, RestartCmaEsSampler)
    assert study.sampler.restart_strategy == "ipop"


class AlwaysPrune(optuna.pruners.BasePruner):
    def prune(self, study: optuna.Study, trial: optuna.trial.FrozenTrial) -> bool:
        return True


def test_pruned_trials_report_returns_and_record_env_steps(tmp_path) -> None:  # noqa: ANN001
    config = make_config(n_trials=2, seeds=(0, 1), steps=512, pruner="median")
    config = dataclasses.replace(
        config,
        problem=dataclasses.replace(
            config.problem, budget=dataclasses.replace(config.problem.budget, n_reports=1)
        ),
    )
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")
    assert isinstance(study.pruner, optuna.pruners.MedianPruner)
    study.pruner = AlwaysPrune()
    summary = run_evolution(config, study, quiet=True)
    assert summary.pruned == 2 and summary.completed == 0
    trial = study.get_trials()[0]
    assert trial.state == TrialState.PRUNED
    ((step, value),) = trial.intermediate_values.items()  # pruned at the first report
    assert step == 256 and trial.user_attrs["env_steps"] == step  # half of the first seed
    assert value == pytest.approx(trial.intermediate_values[256])
    with pytest.raises(ConfigError, match="--n-procs 1"):
        dataclasses.replace(config, n_procs=2)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux-only")
def test_training_processes_die_with_their_worker(tmp_path) -> None:  # noqa: ANN001
    """kill -9 of a worker (or the OOM killer) must not leave its seed processes training."""
    script = tmp_path / "worker.py"
    script.write_text(
        "import multiprocessing, time\n"
        "from ermrl.search import SeedRunner\n"
        "if __name__ == '__main__':\n"
        "    runner = SeedRunner(2)\n"
        "    runner.start(3)\n"
        "    pids = [p.pid for p in multiprocessing.active_children()]\n"
        "    print(' '.join(map(str, pids)), flush=True)\n"
        "    time.sleep(120)\n"
    )
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        children = [int(pid) for pid in proc.stdout.readline().split()]  # type: ignore[union-attr]
        assert len(children) == 3
        assert all(_alive(pid) for pid in children)
    finally:
        proc.kill()  # SIGKILL: no Python cleanup runs in the worker
        proc.wait()
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in children), "orphaned training processes"


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"  # a zombie has exited
    except FileNotFoundError:
        return False


def test_learning_curve_is_the_last_measure_taken_early() -> None:
    from ermrl.agents import RunResult
    from ermrl.search._objective import FitnessResult

    a = RunResult(
        seed=0, episode_returns=[1.0, 3.0, 5.0], episode_steps=[30, 60, 100], env_steps=100
    )
    b = RunResult(seed=1, episode_returns=[2.0, 4.0], episode_steps=[50, 100], env_steps=100)
    result = FitnessResult(fitness=4.0, mode="last", runs=[a, b], n_last=2)
    curve = dict(result.learning_curve(n_points=5))
    # Step 20: no episode ended; step 40: seed 1 has none yet; then the last-2 means.
    assert list(curve) == [60, 80, 100]
    assert curve[60] == pytest.approx(((1 + 3) / 2 + 2) / 2)
    assert curve[100] == pytest.approx(((3 + 5) / 2 + (2 + 4) / 2) / 2)
    assert FitnessResult(fitness=0.0, mode="last", runs=[RunResult(seed=0)]).learning_curve() == []
