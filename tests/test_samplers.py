"""Tests for ermrl.search._samplers: CMA-ES restarts that really happen, state in storage."""

from __future__ import annotations

import json
import math
import pickle
import warnings
from pathlib import Path
from typing import Any

import cmaes
import numpy as np
import optuna
import pytest
from optuna._transform import _SearchSpaceTransform
from optuna.distributions import BaseDistribution, FloatDistribution
from optuna.samplers import CmaEsSampler, RandomSampler, TPESampler
from optuna.study import StudyDirection
from optuna.trial import FrozenTrial, Trial

from ermrl.search._samplers import (
    RESTART_STRATEGIES,
    SAMPLERS,
    RestartCmaEsSampler,
    cma_generation_info,
    make_sampler,
    optimizer_state,
    restore_optimizer,
)

optuna.logging.set_verbosity(optuna.logging.WARNING)

POPSIZE = 4
# On a flat objective in 2-D, cmaes stops on its `tolfun` criterion once
# generation > 10 + ceil(30 * 2 / popsize): 26 generations of popsize 4 = 104 trials. Trial 0 is
# sampled independently, so the first restart happens while sampling trial 1 + 104 = 105.
FIRST_RESTART_TRIAL = 1 + POPSIZE * (10 + math.ceil(30 * 2 / POPSIZE) + 1)
DEFAULT_SIGMA = 1.0 / 6.0  # min range / 6 in the [0, 1] transformed space


def flat(trial: Trial) -> float:
    """Constant objective over two log-float parameters (like the reservoir search space)."""
    trial.suggest_float("sr", 1e-4, 1e2, log=True)
    trial.suggest_float("lr", 1e-2, 1.0, log=True)
    return 0.0


def sphere(trial: Trial) -> float:
    """Shifted sphere, minimum 0 at (1, -2)."""
    x = trial.suggest_float("x", -5.0, 5.0)
    y = trial.suggest_float("y", -5.0, 5.0)
    return (x - 1.0) ** 2 + (y + 2.0) ** 2


def expected_run_generation(number: int, inc_popsize: int = 2) -> tuple[int, int]:
    """(restart, generation) of trial ``number`` on ``flat`` with IPOP before its 2nd restart."""
    if number < FIRST_RESTART_TRIAL:
        return 0, (number - 1) // POPSIZE
    return 1, (number - FIRST_RESTART_TRIAL) // (POPSIZE * inc_popsize)


def run(sampler: optuna.samplers.BaseSampler, objective: Any, n_trials: int, **kw: Any) -> Any:
    study = optuna.create_study(sampler=sampler, **kw)
    study.optimize(objective, n_trials=n_trials)
    return study


def first_row_of_restart(rows: list[dict[str, Any]], restart: int) -> dict[str, Any]:
    return next(r for r in rows if r["restart"] == restart)


def stored_optimizer(trial: FrozenTrial, prefix: str = "cma:") -> Any:
    return _stored_optimizer(trial.system_attrs, prefix)


# --------------------------------------------------------------------------- restarts


@pytest.mark.parametrize("inc_popsize", [2, 3])
def test_ipop_restarts_with_increased_popsize(inc_popsize: int) -> None:
    sampler = RestartCmaEsSampler(
        restart_strategy="ipop", popsize=POPSIZE, inc_popsize=inc_popsize, seed=0
    )
    n_trials = FIRST_RESTART_TRIAL + POPSIZE * inc_popsize + 2
    study = run(sampler, flat, n_trials)
    rows = cma_generation_info(study)
    trials = study.get_trials(deepcopy=False)

    assert rows[0]["restart"] is None  # first trial: search space unknown -> independent
    restart_row = first_row_of_restart(rows, 1)
    assert restart_row["number"] == FIRST_RESTART_TRIAL
    before = rows[FIRST_RESTART_TRIAL - 1]
    assert (before["restart"], before["popsize"]) == (0, POPSIZE)
    assert restart_row["popsize"] == POPSIZE * inc_popsize
    assert restart_row["generation"] == 0
    for r in rows[1:]:
        assert (r["restart"], r["generation"]) == expected_run_generation(r["number"], inc_popsize)
        assert r["popsize"] == (POPSIZE if r["restart"] == 0 else POPSIZE * inc_popsize)
        assert r["regime"] == "large"
    gg = [r["global_generation"] for r in rows[1:]]
    assert gg == sorted(gg) and gg[-1] == 26 + 1

    # The restart is recorded with the new optimizer on the trial that triggered it.
    attrs = trials[FIRST_RESTART_TRIAL].system_attrs
    assert attrs["cma:n_restarts"] == 1
    assert attrs["cma:restart_1:generation"] == 0
    assert "cma:restart_0:generation" not in attrs
    state = attrs["cma:restart_state"]
    assert state["n_restarts"] == 1 and state["popsize"] == POPSIZE * inc_popsize
    assert state["n_evals_large"] == FIRST_RESTART_TRIAL - 1
    new_opt = stored_optimizer(trials[FIRST_RESTART_TRIAL])
    assert new_opt.population_size == POPSIZE * inc_popsize and new_opt.generation == 0
    assert new_opt._sigma == pytest.approx(DEFAULT_SIGMA)

    # The first generation of the new run is told with trials of the new run only.
    told = trials[FIRST_RESTART_TRIAL + POPSIZE * inc_popsize]
    opt = stored_optimizer(told)
    assert (opt.generation, opt.population_size) == (1, POPSIZE * inc_popsize)
    assert told.system_attrs["cma:restart_1:generation"] == 1


def test_none_never_restarts() -> None:
    study = run(RestartCmaEsSampler(restart_strategy="none", popsize=POPSIZE, seed=0), flat, 220)
    rows = cma_generation_info(study)[1:]
    assert {r["restart"] for r in rows} == {0}
    assert {r["popsize"] for r in rows} == {POPSIZE}
    assert [r["generation"] for r in rows] == [(r["number"] - 1) // POPSIZE for r in rows]
    assert rows[-1]["generation"] > 26  # well past the point where IPOP restarts
    for t in study.get_trials(deepcopy=False):
        assert t.system_attrs.get("cma:restart_state", {"n_restarts": 0})["n_restarts"] == 0


def test_bipop_alternates_regimes() -> None:
    sampler = RestartCmaEsSampler(restart_strategy="bipop", popsize=POPSIZE, seed=3)
    study = run(sampler, flat, 320)
    rows = [r for r in cma_generation_info(study) if r["restart"] is not None]
    trials = study.get_trials(deepcopy=False)

    runs: dict[int, dict[str, Any]] = {}
    for r in rows:
        run_info = runs.setdefault(
            r["restart"],
            {"first": r["number"], "popsize": r["popsize"], "regime": r["regime"], "gens": set()},
        )
        assert (r["popsize"], r["regime"]) == (run_info["popsize"], run_info["regime"])
        run_info["gens"].add(r["generation"])
    assert len(runs) >= 4, runs
    assert runs[0]["regime"] == "large" and runs[0]["popsize"] == POPSIZE
    assert {info["regime"] for info in runs.values()} == {"large", "small"}
    assert runs[1]["first"] == FIRST_RESTART_TRIAL

    # Replay the budget rule from what the trials show; every finished run is fully told.
    evals = {"large": 0, "small": 0}
    large_popsize = POPSIZE
    for k in range(1, len(runs)):
        prev = runs[k - 1]
        evals[prev["regime"]] += prev["popsize"] * len(prev["gens"])
        info = runs[k]
        opt = stored_optimizer(trials[info["first"]])
        assert opt.generation == 0 and opt.population_size == info["popsize"]
        if evals["small"] < evals["large"]:
            assert info["regime"] == "small"
            # floor(popsize0 * (0.5 * large / popsize0) ** (U ** 2)), U in [0, 1]
            low = max(2, math.floor(POPSIZE * 0.5 * large_popsize / POPSIZE))
            assert low <= info["popsize"] <= POPSIZE * max(1.0, 0.5 * large_popsize / POPSIZE)
            assert DEFAULT_SIGMA * 1e-2 <= opt._sigma <= DEFAULT_SIGMA
        else:
            assert info["regime"] == "large"
            large_popsize *= 2
            assert info["popsize"] == large_popsize
            assert opt._sigma == pytest.approx(DEFAULT_SIGMA)
        state = trials[info["first"]].system_attrs["cma:restart_state"]
        assert (state["n_evals_large"], state["n_evals_small"]) == (
            evals["large"],
            evals["small"],
        )
    assert large_popsize == 2 * POPSIZE  # a large restart with a doubled popsize happened


# --------------------------------------------------------------------------- storage


def test_state_lives_in_storage_two_workers(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'study.db'}"
    worker_a = optuna.create_study(
        study_name="s",
        storage=url,
        sampler=RestartCmaEsSampler(restart_strategy="ipop", popsize=POPSIZE, seed=1),
    )
    worker_a.optimize(flat, n_trials=30)

    # A fresh sampler instance on the reloaded study continues the same run and generation.
    worker_b = optuna.load_study(
        study_name="s",
        storage=url,
        sampler=RestartCmaEsSampler(restart_strategy="ipop", popsize=POPSIZE, seed=2),
    )
    worker_b.optimize(flat, n_trials=1)
    last = cma_generation_info(worker_b)[-1]
    assert last["number"] == 30
    assert (last["restart"], last["generation"]) == expected_run_generation(30) == (0, 7)

    # Two workers alternate trials (ask/tell) across the restart.
    workers = {"a": worker_a, "b": worker_b}
    n_trials = FIRST_RESTART_TRIAL + 3 * 2 * POPSIZE
    for number in range(31, n_trials):
        name = "ab"[number % 2]
        trial = workers[name].ask()
        assert trial.number == number
        trial.set_user_attr("worker", name)
        workers[name].tell(trial, flat(trial))

    # A third, fresh sampler after the restart continues restart 1 (not restart 0 / gen 0).
    worker_c = optuna.load_study(
        study_name="s",
        storage=url,
        sampler=RestartCmaEsSampler(restart_strategy="ipop", popsize=POPSIZE, seed=3),
    )
    worker_c.optimize(flat, n_trials=1)

    rows = cma_generation_info(optuna.load_study(study_name="s", storage=url))
    assert len(rows) == n_trials + 1
    for r in rows[1:]:
        assert (r["restart"], r["generation"]) == expected_run_generation(r["number"])
        assert r["popsize"] == (POPSIZE if r["restart"] == 0 else 2 * POPSIZE)
    assert rows[-1]["restart"] == 1 and rows[-1]["generation"] == 3
    trials = worker_c.get_trials(deepcopy=False)
    by_worker = {t.user_attrs.get("worker") for t in trials[FIRST_RESTART_TRIAL:-1]}
    assert by_worker == {"a", "b"}
    assert trials[FIRST_RESTART_TRIAL].system_attrs["cma:restart_state"]["n_restarts"] == 1


def test_seeded_determinism_across_restart() -> None:
    def params(seed: int) -> list[tuple[float, float]]:
        sampler = RestartCmaEsSampler(restart_strategy="ipop", popsize=POPSIZE, seed=seed)
        study = run(sampler, flat, FIRST_RESTART_TRIAL + 6)
        return [(t.params["sr"], t.params["lr"]) for t in study.trials]

    first = params(7)
    assert first == params(7)
    assert first != params(8)


# --------------------------------------------------------------------------- sampling paths


class CountingSampler(RandomSampler):
    """RandomSampler counting independent samples."""

    def __init__(self, seed: int | None = None) -> None:
        super().__init__(seed=seed)
        self.calls: list[int] = []

    def sample_independent(
        self,
        study: optuna.Study,
        trial: FrozenTrial,
        param_name: str,
        param_distribution: BaseDistribution,
    ) -> Any:
        self.calls.append(trial.number)
        return super().sample_independent(study, trial, param_name, param_distribution)


@pytest.mark.parametrize("n_startup_trials", [0, 5])
def test_no_independent_fallback_on_fixed_space(n_startup_trials: int) -> None:
    counter = CountingSampler(seed=0)
    sampler = RestartCmaEsSampler(
        restart_strategy="bipop",
        seed=0,
        n_startup_trials=n_startup_trials,
        independent_sampler=counter,
    )
    study = run(sampler, flat, 25)
    n_independent = max(1, n_startup_trials)
    assert counter.calls == [n for n in range(n_independent) for _ in range(2)]
    rows = cma_generation_info(study)
    assert all(r["restart"] is None for r in rows[:n_independent])
    cma_rows = rows[n_independent:]
    assert all(r["restart"] == 0 and r["popsize"] == 6 for r in cma_rows)  # 4 + floor(3 ln 2)
    assert [r["generation"] for r in cma_rows] == [i // 6 for i in range(len(cma_rows))]


def test_no_warnings_by_default() -> None:
    with pytest.warns(FutureWarning):  # why this module exists: Optuna ignores restarts
        CmaEsSampler(restart_strategy="ipop")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        RestartCmaEsSampler()
        for strategy in RESTART_STRATEGIES:
            RestartCmaEsSampler(restart_strategy=strategy, popsize=POPSIZE)  # type: ignore[arg-type]
            make_sampler("cmaes", seed=0, restart=strategy)  # type: ignore[arg-type]
        for name in SAMPLERS:
            make_sampler(name, seed=0)  # type: ignore[arg-type]
        # Small BIPOP runs use popsize 2-3, for which cmaes would divide by zero.
        run(RestartCmaEsSampler(restart_strategy="bipop", popsize=POPSIZE, seed=3), flat, 200)


@pytest.mark.parametrize("direction", ["minimize", "maximize"])
def test_make_sampler_cmaes_improves(direction: str) -> None:
    sign = 1.0 if direction == "minimize" else -1.0
    sampler = make_sampler("cmaes", seed=0)
    study = run(sampler, lambda t: sign * sphere(t), 60, direction=direction)
    values = [sign * t.value for t in study.trials]  # sphere values, lower is better
    assert min(values) < min(values[:6])
    assert min(values) < 0.5
    assert {r["restart"] for r in cma_generation_info(study)[1:]} == {0}


def test_make_sampler_classes() -> None:
    cma = make_sampler("cmaes", seed=1, restart="bipop", popsize=8, inc_popsize=3)
    assert isinstance(cma, RestartCmaEsSampler) and isinstance(cma, CmaEsSampler)
    assert (cma.restart_strategy, cma.inc_popsize, cma._popsize) == ("bipop", 3, 8)
    assert isinstance(make_sampler("cmaes"), RestartCmaEsSampler)
    assert make_sampler("cmaes").restart_strategy == "none"  # type: ignore[attr-defined]
    assert type(make_sampler("tpe", seed=1)) is TPESampler
    assert type(make_sampler("random", seed=1)) is RandomSampler
    assert SAMPLERS == ("cmaes", "tpe", "random")
    assert RESTART_STRATEGIES == ("none", "ipop", "bipop")


@pytest.mark.parametrize(
    ("name", "kwargs", "match"),
    [
        ("gp", {}, "Unknown sampler"),
        ("CMAES", {}, "Unknown sampler"),
        ("cmaes", {"restart": "lrpop"}, "Unknown restart strategy"),
        ("tpe", {"restart": "ipop"}, "only supported by the 'cmaes'"),
        ("random", {"restart": "bipop"}, "only supported by the 'cmaes'"),
        ("tpe", {"popsize": 8}, "popsize is only supported"),
        ("cmaes", {"popsize": 1}, "popsize must be >= 2"),
        ("cmaes", {"popsize": 0}, "popsize must be >= 2"),
        ("cmaes", {"popsize": 4.5}, "popsize must be an integer"),
        ("cmaes", {"inc_popsize": 1}, "inc_popsize must be an integer >= 2"),
    ],
)
def test_make_sampler_errors(name: str, kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make_sampler(name, **kwargs)  # type: ignore[arg-type]


def test_sampler_errors() -> None:
    with pytest.raises(ValueError, match="Unknown restart strategy"):
        RestartCmaEsSampler(restart_strategy="IPOP")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="popsize must be >= 2"):
        RestartCmaEsSampler(popsize=1)
    with pytest.raises(ValueError, match="inc_popsize"):
        RestartCmaEsSampler(restart_strategy="ipop", inc_popsize=0)


# --------------------------------------------------------------------------- pruned trials


def _generations(study: optuna.Study) -> set[int]:
    """CMA-ES generations (run 0) that sampled some trial, COMPLETE or PRUNED."""
    key = "cma:restart_0:generation"
    return {int(t.system_attrs[key]) for t in study.trials if key in t.system_attrs}


@pytest.mark.parametrize("consider", [False, True])
def test_pruned_trials_fill_generations_only_when_considered(consider: bool) -> None:
    """Half the trials pruned (as with --pruner): CMA-ES must still move from generation to
    generation, using a pruned trial's last intermediate value as its fitness."""

    def objective(trial: Trial) -> float:
        value = sphere(trial)
        trial.report(value + 1.0, step=1)  # worse earlier in "training"
        if trial.number % 2 == 1:
            raise optuna.TrialPruned()
        return value

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no experimental-argument warning leaks to users
        sampler = make_sampler("cmaes", seed=0, popsize=POPSIZE, consider_pruned_trials=consider)
    study = run(sampler, objective, 1 + 6 * POPSIZE)
    generations = _generations(study)
    if consider:
        # Trial 0 is independent; then every POPSIZE trials make a generation, pruned or not.
        assert generations == set(range(6))
        assert [t.state for t in study.trials].count(optuna.trial.TrialState.PRUNED) == 12
    else:
        # Only the 12 COMPLETE trials count: about half as many generations.
        assert max(generations) <= 3


def test_study_sampler_considers_pruned_trials_with_a_pruner() -> None:
    from ermrl.config import SearchConfig
    from ermrl.search._study import make_study_sampler

    assert make_study_sampler(SearchConfig(pruner="median"))._consider_pruned_trials
    assert not make_study_sampler(SearchConfig())._consider_pruned_trials


# -- a fixed search space, per-trial streams, restarts shared by concurrent workers -----------

SPACE = {
    "sr": FloatDistribution(1e-4, 1e2, log=True),
    "lr": FloatDistribution(1e-2, 1.0, log=True),
}


def _system_attrs(study: optuna.Study, trial: Trial) -> dict[str, Any]:
    return study._storage.get_trial(trial._trial_id).system_attrs


def _stored_optimizer(attrs: dict[str, Any], prefix: str = "cma:") -> Any:
    assert not any(k.startswith(prefix + "optimizer:") for k in attrs)  # no pickle is stored
    chunks = {k: v for k, v in attrs.items() if k.startswith(prefix + "state:")}
    text = "".join(chunks[f"{prefix}state:{i}"] for i in range(len(chunks)))
    return restore_optimizer(json.loads(text))


def test_fixed_space_first_trials_come_from_cma_es_and_differ_per_trial() -> None:
    # Four workers (samplers) with the same seed ask before any trial has completed.
    storage = optuna.storages.InMemoryStorage()
    samplers = [RestartCmaEsSampler(seed=0, search_space=SPACE) for _ in range(4)]
    first = optuna.create_study(storage=storage, sampler=samplers[0], study_name="s")
    studies = [first] + [
        optuna.load_study(study_name="s", storage=storage, sampler=s) for s in samplers[1:]
    ]
    trials = [study.ask(SPACE) for study in studies]
    for study, trial in zip(studies, trials):
        attrs = _system_attrs(study, trial)
        assert attrs["cma:restart_0:generation"] == 0
        assert attrs["cma:n_restarts"] == 0
    points = {tuple(t.params.values()) for t in trials}
    assert len(points) == 4, points


def test_same_seed_and_trial_number_give_the_same_point() -> None:
    def first_points(seed: int) -> list[tuple[float, ...]]:
        study = optuna.create_study(sampler=RestartCmaEsSampler(seed=seed, search_space=SPACE))
        return [tuple(study.ask(SPACE).params.values()) for _ in range(3)]

    assert first_points(0) == first_points(0)
    assert first_points(0) != first_points(1)


def test_start_point_is_the_given_x0() -> None:
    x0 = {"sr": 1.0, "lr": 1.0}
    sampler = RestartCmaEsSampler(seed=0, search_space=SPACE, x0=x0)
    trans = _SearchSpaceTransform(SPACE, transform_0_1=True)
    optimizer = sampler._init_optimizer(trans, StudyDirection.MAXIMIZE)
    np.testing.assert_allclose(optimizer._mean, trans.transform(x0))
    centre = RestartCmaEsSampler(seed=0, search_space=SPACE)._init_optimizer(
        trans, StudyDirection.MAXIMIZE
    )
    np.testing.assert_allclose(centre._mean, [0.5, 0.5])
    with pytest.raises(ValueError, match="x0 must name"):
        RestartCmaEsSampler(search_space=SPACE, x0={"sr": 1.0})


@pytest.mark.parametrize("strategy", ["ipop", "bipop"])
def test_workers_restarting_at_once_build_the_same_run(
    strategy: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Two workers without a seed both find generation 0 complete and both restart before
    # either of their trials completes. Each must build the same restart (start point, popsize,
    # step size), so that every trial labelled "restart 1, generation 0" has one distribution.
    monkeypatch.setattr(cmaes.CMA, "should_stop", lambda self: True)
    storage = optuna.storages.InMemoryStorage()
    a = RestartCmaEsSampler(restart_strategy=strategy, popsize=4, search_space=SPACE)
    b = RestartCmaEsSampler(restart_strategy=strategy, popsize=4, search_space=SPACE)
    study_a = optuna.create_study(storage=storage, sampler=a, study_name="s")
    study_b = optuna.load_study(study_name="s", storage=storage, sampler=b)
    for i in range(4):
        trial = study_a.ask(SPACE)
        study_a.tell(trial, float(i))
    trial_a, trial_b = study_a.ask(SPACE), study_b.ask(SPACE)
    attrs_a, attrs_b = _system_attrs(study_a, trial_a), _system_attrs(study_b, trial_b)
    for attrs in (attrs_a, attrs_b):
        assert attrs["cma:n_restarts"] == 1
        assert attrs["cma:restart_1:generation"] == 0
    assert attrs_a["cma:restart_state"] == attrs_b["cma:restart_state"]
    opt_a, opt_b = _stored_optimizer(attrs_a), _stored_optimizer(attrs_b)
    np.testing.assert_array_equal(opt_a._mean, opt_b._mean)
    assert opt_a._sigma == opt_b._sigma
    assert opt_a.population_size == opt_b.population_size
    # ... while their points still come from each trial's own stream.
    assert trial_a.params != trial_b.params


# --------------------------------------------------------------------------- plain-data state


def _told_optimizers() -> list[Any]:
    bounds = np.array([[0.0, 1.0]] * 3)
    cma = cmaes.CMA(mean=np.full(3, 0.5), sigma=0.2, bounds=bounds, seed=1, lr_adapt=True)
    sep = cmaes.SepCMA(mean=np.full(3, 0.5), sigma=0.2, bounds=bounds, seed=2)
    margin = cmaes.CMAwM(
        mean=np.full(3, 0.5), sigma=0.2, bounds=bounds, steps=np.array([0.0, 0.1, 0.0]), seed=3
    )
    for optimizer in (cma, sep, margin):
        for _ in range(3):  # a few generations
            told = []
            for _ in range(optimizer.population_size):
                x = optimizer.ask()
                x_tell = x[1] if isinstance(x, tuple) else x
                told.append((x_tell, float(np.sum((x_tell - 0.3) ** 2))))
            optimizer.tell(told)
    return [cma, sep, margin]


@pytest.mark.parametrize("index", [0, 1, 2], ids=["CMA", "SepCMA", "CMAwM"])
def test_plain_state_continues_exactly_like_the_pickled_optimizer(index: int) -> None:
    original = _told_optimizers()[index]
    text = json.dumps(optimizer_state(original), allow_nan=False)  # plain JSON, nothing else
    restored = restore_optimizer(json.loads(text))
    pickled = pickle.loads(pickle.dumps(original))  # what the old storage format gave back
    assert type(restored) is type(original)
    for optimizer in (original, restored, pickled):
        optimizer._rng.seed(7)  # the sampler reseeds for every trial
    for _ in range(2):
        told = []
        for _ in range(original.population_size):
            a, b, c = original.ask(), restored.ask(), pickled.ask()
            for x, y in ((a, b), (a, c)):
                for u, v in zip(np.atleast_1d(x), np.atleast_1d(y)):  # CMAwM: (x, x_for_tell)
                    np.testing.assert_allclose(u, v, rtol=0, atol=1e-12)
            x_tell = a[1] if isinstance(a, tuple) else a
            told.append((x_tell, float(np.sum(x_tell**2))))
        for optimizer in (original, restored, pickled):
            optimizer.tell(told)
    inner = (lambda o: o._cma) if index == 2 else (lambda o: o)
    for name in ("_mean", "_C", "_p_sigma", "_pc"):
        np.testing.assert_allclose(
            getattr(inner(restored), name), getattr(inner(original), name), rtol=0, atol=1e-12
        )
    assert inner(restored)._sigma == inner(original)._sigma
    assert restored.generation == original.generation == 5


def test_plain_state_keeps_the_random_generator() -> None:
    original = _told_optimizers()[0]
    restored = restore_optimizer(json.loads(json.dumps(optimizer_state(original))))
    np.testing.assert_array_equal(restored.ask(), original.ask())


@pytest.mark.parametrize(
    "state",
    [
        {"__cmaes__": "Popen", "attrs": {}},
        {"__ndarray__": "", "dtype": "O", "shape": [0]},
        {"__pickle__": "80"},
        [1, 2],
    ],
)
def test_restore_refuses_anything_but_plain_optimizer_state(state: Any) -> None:
    with pytest.raises(ValueError):
        restore_optimizer(state if isinstance(state, dict) else {"__list__": state})


class _Marker:
    """Unpickling an instance creates a file: stands for code an attacker stored."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (Path(self.path),))


def test_pickled_optimizer_in_the_storage_is_never_unpickled(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A study as an older ermrl wrote it (or as anyone with write access to the storage can
    # write it): the optimizer pickled in `cma:optimizer:*` on the latest trial.
    marker = tmp_path / "executed"
    study = optuna.create_study(sampler=RestartCmaEsSampler(seed=0, search_space=SPACE))
    old_run = {"n_restarts": 2, "regime": "large", "popsize": 4, "popsize0": 4, "large_popsize": 4}
    for i in range(3):
        attrs: dict[str, Any] = {
            "cma:n_restarts": 2,
            "cma:restart_2:generation": 5,
            "cma:popsize": 4,
            "cma:regime": "large",
        }
        if i == 2:
            attrs["cma:optimizer:0"] = pickle.dumps(_Marker(str(marker))).hex()
            attrs["cma:restart_state"] = old_run
        study.add_trial(
            optuna.trial.create_trial(
                params={"sr": 1.0, "lr": 0.1}, distributions=SPACE, value=1.0, system_attrs=attrs
            )
        )

    with caplog.at_level("WARNING", logger="ermrl.search._samplers"):
        trial = study.ask(SPACE)
    assert not marker.exists()
    assert "pickled by an older ermrl" in caplog.text and "never unpickled" in caplog.text
    new_attrs = _system_attrs(study, trial)
    assert new_attrs["cma:n_restarts"] == 3 and new_attrs["cma:restart_3:generation"] == 0
    assert new_attrs["cma:popsize"] == 4
    study.tell(trial, 0.5)
    # The study goes on: the new run completes a generation and stores plain state.
    for _ in range(4):
        study.tell(study.ask(SPACE), 0.5)
    assert not marker.exists()
    told = [t for t in study.get_trials(deepcopy=False) if "cma:state:0" in t.system_attrs]
    assert len(told) == 1 and stored_optimizer(told[0]).generation == 1
    assert told[0].system_attrs["cma:restart_state"]["n_restarts"] == 3
