"""The reference trial, the CMA-ES start and the re-evaluation of the best candidates."""

from __future__ import annotations

import dataclasses
import io
import math
import subprocess
import sys
from pathlib import Path

import optuna
import pytest
from optuna.trial import TrialState

from ermrl.config import ConfigError, EvolveConfig, ReservoirSpace, SearchConfig
from ermrl.runner._experiment import _reevaluate_status
from ermrl.search import (
    REEVALUATION_ATTR,
    FitnessResult,
    create_or_resume_study,
    reevaluate_study,
    reevaluation_seeds,
    reevaluation_study_name,
    run_evolution,
    select_trial,
    stale_ranking,
    top_candidates,
    used_reevaluation_seeds,
)
from ermrl.search._study import cma_start
from tests.test_search import make_config

optuna.logging.set_verbosity(optuna.logging.WARNING)
ROOT = Path(__file__).resolve().parents[1]


def stub_fitness(calls: list | None = None, noise: dict | None = None):  # noqa: ANN201
    """A fitness that peaks at sr = 1 and records the seeds it was asked for."""

    def evaluate(encoder, runner, report):  # noqa: ANN001, ANN202
        sr = encoder.reservoirs[0].sr
        value = -(math.log10(sr) ** 2) + (noise or {}).get(round(sr, 6), 0.0)
        if calls is not None:
            calls.append(round(sr, 6))
        return FitnessResult(fitness=value, mode="last", runs=[], wall_seconds=0.0)

    return evaluate


def test_reference_trial_competes_and_is_told_to_cma_es(tmp_path: Path) -> None:
    config = make_config(n_trials=5, popsize=4)
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")
    run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    trials = study.get_trials()
    assert trials[0].user_attrs["reference"] is True
    assert trials[0].params == {"sr": 1.0, "lr": 1.0, "input_scaling": 1.0}
    # Every trial, the reference included, belongs to a CMA-ES generation.
    assert [t.system_attrs["cma:restart_0:generation"] for t in trials] == [0, 0, 0, 0, 1]
    assert sum(bool(t.user_attrs.get("reference")) for t in trials) == 1
    # The reference is the optimum of this fitness: the study's best cannot be worse.
    assert study.best_value == pytest.approx(0.0)


def test_reference_outside_the_space_is_said_and_skipped(tmp_path: Path) -> None:
    config = make_config(n_trials=2)
    config = dataclasses.replace(
        config, space=dataclasses.replace(config.space, lr=config.space.lr.__class__(0.01, 0.5))
    )
    with pytest.warns(UserWarning, match="outside the search space"):
        study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")
    assert study.get_trials() == []
    no_ref = make_config(n_trials=2, reference_trial=False)
    study = create_or_resume_study(no_ref, f"sqlite:///{tmp_path}/s.db", "t")
    assert study.get_trials() == []


def test_cma_start_reference_or_center() -> None:
    space = ReservoirSpace()
    reference = SearchConfig(start="reference")
    assert cma_start(reference, space) == {"sr": 1.0, "lr": 1.0, "input_scaling": 1.0}
    centre = cma_start(SearchConfig(), space)  # the default
    assert centre == pytest.approx({"sr": 0.1, "lr": 0.1, "input_scaling": 1.0})
    narrow = dataclasses.replace(space, sr=space.sr.__class__(2.0, 10.0))
    assert cma_start(reference, narrow)["sr"] == 2.0  # clipped into the box


def test_old_stored_search_configs_read_as_what_they_were() -> None:
    data = make_config().to_dict()
    for key in ("start", "reference_trial", "reevaluate_top", "reevaluate_seeds"):
        data["search"].pop(key)
    old = EvolveConfig.from_dict(data)
    assert old.search.start == "center" and old.search.reference_trial is False
    assert old.search.reevaluate_top == 0


def test_trials_record_the_reservoir_dtype(tmp_path: Path) -> None:
    config = make_config(n_trials=1, steps=256, seeds=(0,))  # one 200-step episode ends
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")
    run_evolution(config, study, quiet=True)
    assert study.trials[0].state == TrialState.COMPLETE
    assert study.trials[0].user_attrs["dtype"] == "float32"


def test_top_candidates_are_distinct_and_include_the_reference(tmp_path: Path) -> None:
    config = make_config(n_trials=9, popsize=4)
    study = create_or_resume_study(config, f"sqlite:///{tmp_path}/s.db", "s")
    # The reference (sr = 1) is made the worst here, so it only enters as the reference.
    run_evolution(config, study, quiet=True, evaluate=stub_fitness(noise={1.0: -100.0}))
    top = top_candidates(study, 2)
    assert len(top) == 3
    values = [t.value for t in top[:2]]
    assert values == sorted(values, reverse=True)
    assert values[0] == study.best_value
    assert top[2].user_attrs["reference"] is True
    assert len({tuple(t.params.items()) for t in top}) == 3


def test_reevaluation_ranks_on_fresh_seeds_and_the_test_phase_uses_it(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    config = make_config(n_trials=6, popsize=4, reevaluate_top=2, reevaluate_seeds=2)
    study = create_or_resume_study(config, url, "s")
    run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    best_by_fitness, how = select_trial(study)
    assert "no re-evaluation" in how
    # Re-evaluation: the lucky evolution winner is beaten on fresh seeds.
    calls: list[float] = []
    lucky = round(best_by_fitness.params["sr"], 6)
    assert best_by_fitness.user_attrs["reference"] is True  # sr = 1 is the optimum
    factory_configs: list[EvolveConfig] = []

    def factory(rconfig: EvolveConfig):  # noqa: ANN202
        factory_configs.append(rconfig)
        return stub_fitness(calls, noise={lucky: -10.0})

    out = io.StringIO()
    doc = reevaluate_study(config, study, url, evaluator_factory=factory, stream=out)
    assert doc is not None and doc["complete"]
    rconfig = factory_configs[0]
    assert rconfig.problem.seeds == reevaluation_seeds(config.problem, 2) == (1001, 1002)
    assert not set(rconfig.problem.seeds) & set(config.problem.seeds)
    assert sorted(calls) == sorted({round(t.params["sr"], 6) for t in top_candidates(study, 2)})
    assert doc["best_trial"] != best_by_fitness.number
    assert study.user_attrs[REEVALUATION_ATTR]["best_trial"] == doc["best_trial"]
    chosen, how = select_trial(study)
    assert chosen.number == doc["best_trial"] and how.startswith("re-evaluated best of 2")
    # The report's best_params.csv names the trial the test phase tests, not the noisy maximum.
    from ermrl.analysis import best_params_table

    table = best_params_table(study, config)
    assert set(table["trial"]) == {doc["best_trial"]} and set(table["selection"]) == {how}
    assert dict(zip(table["parameter"], table["value"], strict=True)) == chosen.params
    assert "re-evaluated ranking" in out.getvalue()
    # Each run's line names the evolution trial it re-trains, not its number in the sibling
    # study (which would read as evolution trials 0 and 1), and so does the best so far.
    run_lines = [x for x in out.getvalue().splitlines() if x.startswith("[")]
    candidates = {t.number for t in top_candidates(study, 2)}
    assert len(run_lines) == 2
    for line in run_lines:
        assert line.startswith("[candidate #")
        named = int(line.split("#")[1].split(" ")[0])
        best = int(line.split("(#")[1].split(")")[0])
        assert named in candidates and best in candidates
    assert f"(#{doc['best_trial']})" in run_lines[-1]
    # An explicit trial wins over the ranking.
    assert select_trial(study, 0)[0].number == 0
    # Running it again re-trains nothing.
    calls.clear()
    reevaluate_study(config, study, url, evaluator_factory=factory, quiet=True)
    assert calls == []
    rstudy = optuna.load_study(study_name=reevaluation_study_name("s"), storage=url)
    assert len(rstudy.get_trials(states=(TrialState.COMPLETE,))) == 2


def test_a_failed_candidate_is_not_replaced_by_a_random_point(tmp_path: Path) -> None:
    from ermrl.agents import TrainingDiverged

    url = f"sqlite:///{tmp_path}/s.db"
    config = make_config(n_trials=4, popsize=4, reevaluate_top=1, reevaluate_seeds=1)
    study = create_or_resume_study(config, url, "s")
    run_evolution(config, study, quiet=True, evaluate=stub_fitness(noise={1.0: -100.0}))

    def diverge(encoder, runner, report):  # noqa: ANN001, ANN202
        raise TrainingDiverged("nan")

    doc = reevaluate_study(config, study, url, evaluator_factory=lambda c: diverge, quiet=True)
    # Both failed for good: ranked (last), so the ranking is complete, and nothing is selected.
    assert doc is not None and doc["complete"] and doc["best_trial"] is None
    assert [row["failed"] for row in doc["candidates"]] == [True, True]
    rstudy = optuna.load_study(study_name=reevaluation_study_name("s"), storage=url)
    assert len(rstudy.trials) == 2  # the two candidates, both FAIL; no new point was asked
    assert {t.state for t in rstudy.trials} == {TrialState.FAIL}
    with pytest.raises(ConfigError, match="every re-evaluated candidate .* failed"):
        select_trial(study)
    # Running it again re-trains nothing: a diverged candidate is not queued again.
    reevaluate_study(config, study, url, evaluator_factory=lambda c: diverge, quiet=True)
    assert len(rstudy.get_trials()) == 2
    # ermrl run's plan counts the stage as done (nothing to rerun) and says why the test stops.
    done, left, text = _reevaluate_status(url, "s")()
    assert done and left == 0.0 and "all 2 candidates failed" in text and "--trial" in text


def test_a_candidate_that_fails_its_reevaluation_is_ranked_last_and_never_selected(
    tmp_path: Path,
) -> None:
    """The evolution winner diverges on the fresh seeds: the ranking still completes, with the
    winner last and its reason, and the test phase takes the best measured candidate."""
    from ermrl.agents import TrainingDiverged

    url = f"sqlite:///{tmp_path}/s.db"
    config = make_config(n_trials=6, popsize=4, reevaluate_top=2, reevaluate_seeds=1)
    study = create_or_resume_study(config, url, "s")
    run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    winner, _ = select_trial(study)  # the noisy evolution maximum
    sr_winner = round(winner.params["sr"], 6)

    def diverge_on_winner(encoder, runner, report):  # noqa: ANN001, ANN202
        if round(encoder.reservoirs[0].sr, 6) == sr_winner:
            raise TrainingDiverged("NaN in the policy loss")
        return stub_fitness()(encoder, runner, report)

    out = io.StringIO()
    doc = reevaluate_study(
        config, study, url, evaluator_factory=lambda c: diverge_on_winner, stream=out
    )
    assert doc is not None and doc["complete"] and doc["pending"] == 0
    last = doc["candidates"][-1]
    assert last["trial"] == winner.number and last["failed"] and last["fitness"] is None
    assert "NaN in the policy loss" in last["fail_reason"]
    assert not any(row.get("failed") for row in doc["candidates"][:-1])
    assert doc["best_trial"] not in (None, winner.number)
    assert f"trial {winner.number}" in out.getvalue() and "FAILED" in out.getvalue()
    assert study.user_attrs[REEVALUATION_ATTR] == doc
    chosen, how = select_trial(study)
    assert chosen.number == doc["best_trial"] != winner.number
    n = len(doc["candidates"])
    assert how.startswith(f"re-evaluated best of {n}") and "1 failed, ranked last" in how
    done, _, text = _reevaluate_status(url, "s")()
    assert done and f"best trial {doc['best_trial']}; 1 failed, ranked last" in text
    # An incomplete ranking falls back to the evolution fitness, but never to a failed candidate.
    study.set_user_attr(REEVALUATION_ATTR, {**doc, "complete": False})
    chosen, how = select_trial(study)
    assert chosen.number != winner.number and "skipped: failed re-evaluation" in how


def test_an_interrupted_reevaluation_run_is_queued_again_by_the_next_call(tmp_path: Path) -> None:
    """Ctrl-C is not a failure of the candidate: re-running the command finishes the ranking."""
    url = f"sqlite:///{tmp_path}/s.db"
    config = make_config(n_trials=4, popsize=4, reevaluate_top=1, reevaluate_seeds=1)
    study = create_or_resume_study(config, url, "s")
    run_evolution(config, study, quiet=True, evaluate=stub_fitness(noise={1.0: -100.0}))

    def interrupt(encoder, runner, report):  # noqa: ANN001, ANN202
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        reevaluate_study(config, study, url, evaluator_factory=lambda c: interrupt, quiet=True)
    doc = reevaluate_study(config, study, url, evaluator_factory=lambda c: stub_fitness())
    assert doc is not None and doc["complete"] and len(doc["candidates"]) == 2
    assert not any(row.get("failed") for row in doc["candidates"])


def test_a_ranking_from_before_the_study_grew_is_stale_and_recomputed(tmp_path: Path) -> None:
    """More trials after the re-evaluation (a larger --n-trials, evolution resumed): the stored
    ranking no longer covers the best candidates; select_trial does not use it, the test phase
    says so on stderr, and the next re-evaluation re-ranks, reusing the finished runs."""
    url = f"sqlite:///{tmp_path}/s.db"
    config = make_config(n_trials=6, popsize=4, reevaluate_top=1, reevaluate_seeds=1)
    study = create_or_resume_study(config, url, "s")
    run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    calls: list[float] = []
    doc = reevaluate_study(
        config, study, url, evaluator_factory=lambda c: stub_fitness(calls), quiet=True
    )
    assert doc is not None and doc["complete"]
    assert doc["n_complete"] == 6 and doc["top_k"] == 1
    assert doc["top_trials"] == [t.number for t in top_candidates(study, 1)]
    assert stale_ranking(study) is None
    # The study grows, and its new trials beat every ranked candidate.
    grown = dataclasses.replace(config, search=dataclasses.replace(config.search, n_trials=9))

    def better(encoder, runner, report):  # noqa: ANN001, ANN202
        result = stub_fitness()(encoder, runner, report)
        return dataclasses.replace(result, fitness=result.fitness + 100.0)

    run_evolution(grown, study, quiet=True, evaluate=better)
    new_best = study.best_trial
    assert new_best.number >= 6
    stale = stale_ranking(study)
    assert stale is not None and "6 complete trials" in stale and "now has 9" in stale
    # ermrl run's plan sees it too: the stage is not done, so the run re-ranks.
    done, _, text = _reevaluate_status(url, "s")()
    assert not done and "stale" in text
    chosen, how = select_trial(study)
    assert chosen.number == new_best.number and "ranked trials" in how and "stale" in how
    # ermrl test says it in one stderr line (the training itself is skipped here).
    import ermrl.cli._test
    import ermrl.runner._commands

    out = tmp_path / "run"
    argv = ["--study-name", "s", "--storage", url, "--agents", "res-ppo", "--seeds", "5",
            "--training-steps", "64", "--quiet", "--out", str(out)]  # fmt: skip
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ermrl.runner._commands, "run_test_phase", lambda *a, **k: object())
        err = io.StringIO()
        mp.setattr(sys, "stderr", err)
        assert ermrl.cli._test.test_main(argv) == 0
    lines = err.getvalue().strip().splitlines()
    assert len(lines) == 1 and "ranking is stale" in lines[0]
    assert f"testing trial {new_best.number}" in lines[0]
    # The next re-evaluation re-ranks; the finished run of a candidate still ranked is reused.
    calls.clear()
    doc = reevaluate_study(
        grown, study, url, evaluator_factory=lambda c: stub_fitness(calls), quiet=True
    )
    assert doc is not None and doc["complete"] and doc["n_complete"] == 9
    assert new_best.number in doc["top_trials"]
    assert calls == [round(new_best.params["sr"], 6)]
    assert stale_ranking(study) is None
    assert select_trial(study)[1].startswith("re-evaluated best of")


@pytest.mark.parametrize(
    ("seeds", "used_by"), [(["1001"], "re-evaluation"), (["7", "0"], "by evolution")]
)
def test_test_seeds_used_by_evolution_or_reevaluation_are_refused(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    seeds: list[str],
    used_by: str,
) -> None:
    """The selection saw those seeds: one line, exit 2, nothing written."""
    import ermrl.runner._commands
    from ermrl.cli._test import test_main

    monkeypatch.setattr(
        ermrl.runner._commands, "run_test_phase", lambda *a, **k: object()
    )  # no training
    url = f"sqlite:///{tmp_path}/s.db"
    config = make_config(n_trials=4, popsize=4, reevaluate_top=1, reevaluate_seeds=2)
    study = create_or_resume_study(config, url, "s")
    run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    reevaluate_study(config, study, url, evaluator_factory=lambda c: stub_fitness(), quiet=True)
    assert used_reevaluation_seeds(study) == (1001, 1002)
    capsys.readouterr()
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exc:
        test_main(["--study-name", "s", "--storage", url, "--agents", "ppo", "--seeds", *seeds,
                   "--training-steps", "64", "--quiet", "--out", str(out)])  # fmt: skip
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and used_by in err, err
    assert not out.exists()


def test_reevaluation_waits_for_an_unfinished_study(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    config = make_config(n_trials=4, reevaluate_top=1)
    study = create_or_resume_study(config, url, "s")
    out = io.StringIO()
    assert reevaluate_study(config, study, url, stream=out) is None
    assert "waits for the study to finish" in out.getvalue()


def test_cli_reevaluates_and_test_phase_says_which_trial_it_used(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    tiny = ["--env-id", "Pendulum-v1", "--observe", "positions", "--units", "20", "--n-envs", "1",
            "--ppo", "n_steps=128", "batch_size=64", "n_epochs=1"]  # fmt: skip
    evolve = subprocess.run(
        [sys.executable, str(ROOT / "evolve_res.py"), *tiny, "--n-trials", "3", "--n-seeds", "1",
         "--training-steps", "256", "--popsize", "2", "--sampler-seed", "0",
         "--reevaluate-top", "1", "--reevaluate-seeds", "1", "--reevaluate-steps", "384",
         "--storage", url, "--study-name", "s"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert evolve.returncode == 0, evolve.stdout + evolve.stderr
    assert "re-evaluated ranking" in evolve.stdout
    study = optuna.load_study(study_name="s", storage=url)
    doc = study.user_attrs[REEVALUATION_ATTR]
    assert doc["complete"] and doc["training_steps"] == 384 and doc["seeds"] == [1000]
    test = subprocess.run(
        [sys.executable, str(ROOT / "test.py"), "--study-name", "s", "--storage", url,
         "--training-steps", "256", "--seeds", "5", "--agents", "res-ppo", "--no-save-models",
         "--out", str(tmp_path / "run")],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert test.returncode == 0, test.stdout + test.stderr
    assert f"trial {doc['best_trial']}" in test.stdout
    assert "re-evaluated best of" in test.stdout
    config_yaml = (tmp_path / "run" / "config.yaml").read_text()
    assert "selection: re-evaluated best of" in config_yaml
    show = subprocess.run(
        [sys.executable, "-m", "ermrl", "study", "show", "--storage", url, "--study-name", "s"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    assert show.returncode == 0, show.stderr
    assert "re-evaluated on 1 fresh seed x 384 steps (study 's.reeval')" in show.stdout


def test_a_crashed_reevaluation_run_is_queued_again_by_the_next_call(tmp_path: Path) -> None:
    """A run that raised (a bug, a worker that died, code changed under a running command) is
    not a measurement of its candidate: the next call runs it again and completes the ranking."""
    url = f"sqlite:///{tmp_path}/s.db"
    config = make_config(n_trials=4, popsize=4, reevaluate_top=1, reevaluate_seeds=1)
    study = create_or_resume_study(config, url, "s")
    run_evolution(config, study, quiet=True, evaluate=stub_fitness(noise={1.0: -100.0}))

    def crash(encoder, runner, report):  # noqa: ANN001, ANN202
        raise ValueError("not enough values to unpack (expected 7, got 6)")

    with pytest.raises(ValueError, match="unpack"):
        reevaluate_study(config, study, url, evaluator_factory=lambda c: crash, quiet=True)
    rstudy = optuna.load_study(study_name=reevaluation_study_name("s"), storage=url)
    (crashed,) = rstudy.get_trials(states=(TrialState.FAIL,))[:1]
    assert (
        crashed.user_attrs["crashed"] is True and "ValueError" in crashed.user_attrs["fail_reason"]
    )
    doc = reevaluate_study(config, study, url, evaluator_factory=lambda c: stub_fitness())
    assert doc is not None and doc["complete"] and len(doc["candidates"]) == 2
    assert not any(row.get("failed") for row in doc["candidates"])


@pytest.mark.parametrize("backend", ["sb3", "population"])
def test_a_test_phase_trains_once_the_runs_two_agents_share(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, backend: str
) -> None:
    """When the selection chose the unevolved reference, res-ppo and random-res-ppo are the
    same run (the same reservoirs, settings and seed): it is trained once, and both agents'
    folders hold it, models included, as two trainings would have made them."""
    import json

    import pandas as pd

    import ermrl.population as population
    import ermrl.test_phase._test_phase as test_phase
    from ermrl.config import EncoderConfig, PPOConfig, ReservoirParams, TaskConfig
    from ermrl.test_phase import AgentSpec, TestSettings, run_comparison

    trained: list[tuple[str, int]] = []  # (backend, seed) of each run actually trained
    train_agent = test_phase.train_agent
    train_population = population.train_population_parallel

    def counting_agent(task, encoder, ppo, budget, seed, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        trained.append(("sb3", seed))
        return train_agent(task, encoder, ppo, budget, seed, *args, **kwargs)

    def counting_population(task, ppo, budget, runs, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        trained.extend(("population", run.seed) for run in runs)
        return train_population(task, ppo, budget, runs, *args, **kwargs)

    monkeypatch.setattr(test_phase, "train_agent", counting_agent)
    monkeypatch.setattr(population, "train_population_parallel", counting_population)
    reference = (ReservoirParams(units=20, sr=1.0, lr=1.0),)
    ppo = PPOConfig(hyperparams={"n_steps": 128, "batch_size": 64, "n_epochs": 2}, backend=backend)
    out = tmp_path / "test"
    stream = io.StringIO()
    run_comparison(
        TaskConfig("Pendulum-v1", "positions"),
        EncoderConfig(reservoirs=reference),
        ppo,
        [AgentSpec("random-res-ppo", reference), AgentSpec("res-ppo", reference)],
        TestSettings(training_steps=256, seeds=(3, 4), out=out),
        stream=stream,
    )
    assert sorted(trained) == [(backend, 3), (backend, 4)]  # two runs trained, not four
    assert "res-ppo = random-res-ppo" in stream.getvalue()
    lines = [line for line in stream.getvalue().splitlines() if line.startswith("[run ")]
    assert len(lines) == 4
    if backend == "population":  # one population, so each of its runs' lines: nothing left
        assert all(line.endswith("ETA 0m00s") for line in lines), lines
    for seed in (3, 4):
        a, b = (out / "agents" / name / f"seed_{seed}" for name in ("random-res-ppo", "res-ppo"))
        assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())
        assert (b / "model.zip").is_file() and (b / "policy.pt").is_file()
        pd.testing.assert_frame_equal(
            pd.read_csv(a / "episodes.csv"), pd.read_csv(b / "episodes.csv")
        )
        record = json.loads((b / "result.json").read_text())
        assert record["agent"] == "res-ppo" and record["seed"] == seed
        assert json.loads((b / "settings.json").read_text())["agent"] == "res-ppo"
    summary = pd.read_csv(out / "summary.csv").set_index("agent")
    assert summary.loc["res-ppo", "n_seeds"] == 2


def test_a_study_without_a_finished_trial_says_what_to_run(tmp_path: Path) -> None:
    """``ermrl test`` on a study whose evolution has not finished a trial: the trials by state
    and the command that evolves it, not only "no COMPLETE trial"."""
    from ermrl.search import create_or_resume_study

    url = f"sqlite:///{tmp_path}/s.db"
    command = "ermrl evolve --env-id Pendulum-v1 --study-name s"
    study = create_or_resume_study(make_config(n_trials=1), url, "s", command=command)
    with pytest.raises(ConfigError, match=r"no COMPLETE trial yet \(1 waiting\)"):
        select_trial(study)  # the reference trial, queued
    study.tell(study.ask(), state=TrialState.FAIL)
    with pytest.raises(ConfigError) as err:
        select_trial(study)
    message = str(err.value)
    assert "no COMPLETE trial yet (1 failed)" in message, message
    assert f"`{command}`" in message and "resumes" in message and "ermrl study show" in message
    bare = optuna.create_study(study_name="bare", storage=url)
    with pytest.raises(ConfigError, match=r"\(no trial at all\): run the evolution .*ermrl evolve"):
        select_trial(bare)
