"""The NVAR encoder's core: settings, search space, the batched delay line and its monomials
against reservoirpy's ``NVAR`` node, the SB3 and population paths, and integer genes in CMA-ES."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import pytest
from optuna.distributions import FloatDistribution, IntDistribution
from reservoirpy.nodes import NVAR

from ermrl.agents import make_vec_env
from ermrl.config import (
    AgentKind,
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    PPOConfig,
    ReservoirParams,
    SearchConfig,
    TaskConfig,
)
from ermrl.encoders import ReservoirVecEnv
from ermrl.encoders._nvar import (
    AGENTS,
    NVAR_MAX_FEATURES,
    IntRange,
    NVARBank,
    NVAREncoder,
    NVARParams,
    NVARSettings,
    NVARSpace,
    check_nvar_size,
    encoder_input_dim,
    nvar_width,
)
from ermrl.population import (
    BatchedReservoir,
    PopulationEnvs,
    PopulationJob,
    encoder_structure,
    group_jobs,
    train_population,
    train_population_parallel,
)
from ermrl.search._samplers import RestartCmaEsSampler, _join_chunks, restore_optimizer
from ermrl.search._study import make_study_sampler, sample_params, search_distributions

optuna.logging.set_verbosity(optuna.logging.WARNING)


def nvar_encoder(*params: NVARParams, **options: Any) -> EncoderConfig:
    return EncoderConfig(reservoirs=params, **options)  # type: ignore[arg-type]


def reservoirpy_features(params: NVARParams, inputs: np.ndarray) -> np.ndarray:
    """reservoirpy's NVAR node, fresh (zero history), on the scaled inputs (float64)."""
    node = NVAR(delay=params.delay, order=params.order, strides=params.strides)
    return np.asarray(node.run(np.asarray(inputs, np.float64) * params.input_scaling))


PARAMS = [
    NVARParams(),  # the reference: delay 2, order 2, strides 1
    NVARParams(delay=3, order=2, strides=2, input_scaling=0.7),
    NVARParams(delay=1, order=3, strides=3, input_scaling=1.3),
    NVARParams(delay=4, order=1, strides=3, input_scaling=2.0),
    NVARParams(delay=2, order=3, strides=4, input_scaling=0.25),
]


# -- settings and sizes ---------------------------------------------------------------------------
def test_the_reference_is_reservoirpys_example_and_widths_are_reservoirpys() -> None:
    assert NVARParams() == NVARParams(delay=2, order=2, strides=1, input_scaling=1.0)
    for p in PARAMS:
        for d in (1, 3, 7):
            node = NVAR(delay=p.delay, order=p.order, strides=p.strides)
            node.initialize(np.zeros(d))
            assert p.state_dim_for(d) == node.output_dim == nvar_width(p.delay, p.order, d)
        assert p.state_dim == p.state_dim_for(1)  # the lower bound EncoderConfig checks
    assert NVARParams(delay=3, strides=4).window == 9


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"delay": 0}, "delay must be >= 1"),
        ({"order": 1.5}, "order must be an integer"),
        ({"strides": True}, "strides must be an integer"),
        ({"input_scaling": 0.0}, "input_scaling must be positive"),
        ({"delay": 500, "strides": 5}, "spans 2496 input steps"),
        ({"family": "esn"}, "family must be 'nvar'"),
    ],
)
def test_bad_nvar_params_are_refused_in_one_line(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        NVARParams(**kwargs)
    assert "\n" not in str(err.value)


def test_an_integral_float_is_taken_as_an_integer() -> None:
    p = NVARParams(delay=3.0, order=2.0)  # type: ignore[arg-type]
    assert p.delay == 3 and isinstance(p.delay, int)


def test_sizes_over_the_limit_are_refused_in_one_line_naming_delay_order_and_d() -> None:
    assert check_nvar_size([NVARParams()], 24) == 48 + 1176
    with pytest.raises(ConfigError) as err:
        check_nvar_size([NVARParams(delay=4, order=3)], 24)
    text = str(err.value)
    assert "\n" not in text
    assert "delay 4 and order 3" in text and "d = 24" in text and "152,192 features" in text
    assert f"{NVAR_MAX_FEATURES:,}" in text
    # Several NVARs count together.
    with pytest.raises(ConfigError, match=r"order 2 \(1,224\).* has 2,448 features"):
        check_nvar_size([NVARParams(), NVARParams()], 24)
    # The bank refuses before building anything.
    with pytest.raises(ConfigError, match="features"):
        NVARBank([NVARParams(delay=4, order=3)], 24)


def test_the_encoders_input_size_is_the_one_the_wrapper_builds() -> None:
    task = TaskConfig("CartPole-v1", "positions")
    enc = nvar_encoder(NVARParams())
    venv = NVAREncoder().wrap_env(make_vec_env(task, 1, 0), enc, 0)
    assert encoder_input_dim(task, enc) == venv.input_dim == 2 + 2 + 1
    no_feedback = nvar_encoder(NVARParams(), feed_action=False, feed_reward=False)
    assert encoder_input_dim(task, no_feedback) == 2
    venv.close()


# -- the search space -----------------------------------------------------------------------------
def test_int_ranges_are_linear_integer_intervals() -> None:
    r = IntRange(1, 4)
    assert not r.log and r.integer and r.center == 2.5 and IntRange(1, 3).center == 2
    assert r.contains(3) and r.contains(3.0) and not r.contains(2.5) and not r.contains(5)
    for bad in ({"low": 1.5, "high": 3}, {"low": 1, "high": 3, "log": True}, {"low": 3, "high": 3}):
        with pytest.raises(ConfigError) as err:
            IntRange(**bad)
        assert "\n" not in str(err.value)


def test_the_space_decodes_integer_genes_and_its_reference_is_inside() -> None:
    space = NVARSpace()
    assert space.param_names == ("delay", "order", "strides", "input_scaling")
    ref = space.reference_params()
    assert ref == {"delay": 2, "order": 2, "strides": 1, "input_scaling": 1.0}
    assert space.contains(ref) and space.reservoirs_from(ref) == space.default_reservoirs()
    centre = space.center_params()
    # The exact middles (a start, not a trial's values: half of its samples round each way).
    assert centre == {
        "delay": 2.5,
        "order": 1.5,
        "strides": 2.5,
        "input_scaling": pytest.approx(1.0),
    }
    assert not space.contains(centre)
    assert not space.contains({**ref, "delay": 2.5}) and not space.contains({**ref, "delay": 9})
    with pytest.raises(ConfigError, match="delay must be an integer"):
        space.reservoirs_from({**ref, "delay": 2.5})  # never rounded outside the search
    two = NVARSpace(n_reservoirs=2, input_scaling=None, fixed_input_scaling=0.5)
    assert two.param_names == ("delay_0", "order_0", "strides_0", "delay_1", "order_1", "strides_1")
    nvars = two.reservoirs_from({**two.reference_params(), "delay_1": 3})
    assert nvars[1].delay == 3 and nvars[0].input_scaling == 0.5
    with pytest.raises(ConfigError, match="integer range"):
        NVARSpace(delay=IntRange(1, 3), order=Range_(1.0, 3.0))  # type: ignore[arg-type]


def Range_(low: float, high: float) -> Any:  # noqa: N802 - a float range where an int one is due
    from ermrl.config import Range

    return Range(low, high, log=False)


def test_a_space_too_wide_for_the_task_is_refused_with_the_delay_that_fits() -> None:
    space = NVARSpace()  # delay up to 4, order up to 2
    space.check_input_dim(15)  # 60 + 1830 = 1890 features at the widest point
    with pytest.raises(ConfigError) as err:
        space.check_input_dim(24)  # a MuJoCo task's full observation, action and reward
    text = str(err.value)
    assert "\n" not in text and "delay 4 and order 2" in text and "d = 24" in text
    assert "a delay range up to 2 fits with order 2" in text
    with pytest.raises(ConfigError, match="no delay fits"):
        NVARSpace(order=IntRange(1, 3)).check_input_dim(30)


# -- the delay line and its monomials against reservoirpy -----------------------------------------
@pytest.mark.parametrize("params", PARAMS)
def test_the_bank_equals_reservoirpys_nvar_node(params: NVARParams) -> None:
    inputs = np.random.default_rng(1).normal(size=(40, 3))
    bank = NVARBank([params], 3)
    expected = reservoirpy_features(params, inputs)
    np.testing.assert_allclose(bank.features(bank.run(inputs)), expected, rtol=0, atol=1e-10)
    # float32 (ermrl's default dtype) follows within float32 rounding.
    bank32 = NVARBank([params], 3, dtype="float32")
    got = bank32.emitter()[0](bank32.run(inputs))
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6)


def test_the_step_is_the_product_with_a_fixed_0_1_matrix() -> None:
    params = NVARParams(delay=3, order=2, strides=2, input_scaling=0.5)
    bank = NVARBank([params, NVARParams(delay=2, order=3)], 4)
    M = bank.M
    assert M.shape == (bank.n_units + 4, bank.n_units)
    assert set(np.unique(M)) <= {0.0, 0.5, 1.0} and np.all((M != 0).sum(axis=0) == 1)
    xu = np.random.default_rng(0).normal(size=(5, bank.n_units + 4))
    expected = xu @ M
    bank.step_buffer(xu)
    np.testing.assert_array_equal(xu[:, : bank.n_units], expected)


def test_scaling_the_input_scales_each_feature_by_a_power_of_its_degree() -> None:
    """What makes input scaling inert under running observation normalization."""
    inputs = np.random.default_rng(2).normal(size=(10, 3))
    base, scaled = NVARParams(delay=2, order=3), NVARParams(delay=2, order=3, input_scaling=2.0)
    f1 = NVARBank([base], 3).features(NVARBank([base], 3).run(inputs))
    f2 = NVARBank([scaled], 3).features(NVARBank([scaled], 3).run(inputs))
    degree = np.r_[np.ones(6), np.full(f1.shape[1] - 6, 3)]
    np.testing.assert_allclose(f2, f1 * 2.0**degree, rtol=1e-12)


def test_several_nvars_show_their_features_one_after_the_other() -> None:
    a, b = NVARParams(delay=3, order=2, strides=2, input_scaling=0.5), NVARParams(delay=1, order=3)
    inputs = np.random.default_rng(4).normal(size=(15, 2))
    bank = NVARBank([a, b], 2)
    assert bank.out_units == (a.state_dim_for(2), b.state_dim_for(2))
    expected = np.concatenate([reservoirpy_features(a, inputs), reservoirpy_features(b, inputs)], 1)
    np.testing.assert_allclose(bank.features(bank.run(inputs)), expected, rtol=0, atol=1e-10)
    emit, width = bank.emitter(exposed_units=8)  # 6 linear features and 2 monomials of a; b's 6
    assert width == 8 + 6
    shown = emit(bank.run(inputs))
    n_a = a.state_dim_for(2)
    np.testing.assert_allclose(shown[:, :8], expected[:, :8], rtol=1e-6)
    np.testing.assert_allclose(shown[:, 8:], expected[:, n_a:], rtol=1e-6)


def test_padding_a_delay_line_changes_no_feature() -> None:
    params = NVARParams(delay=2, order=2, strides=2)
    inputs = np.random.default_rng(3).normal(size=(12, 2))
    own, padded = NVARBank([params], 2), NVARBank([params], 2, windows=[7])
    assert padded.n_units == 14 > own.n_units
    np.testing.assert_array_equal(
        own.features(own.run(inputs)), padded.features(padded.run(inputs))
    )


# -- the SB3 path: ReservoirVecEnv -----------------------------------------------------------------
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_wrapper_shows_reservoirpys_features_and_zero_history_after_a_reset(
    dtype: str,
) -> None:
    """Each env's features equal a reservoirpy NVAR node fed the same inputs
    ``[obs, previous action, previous reward]``, a fresh node at each episode start
    (reservoirpy 0.4's ``NVAR.reset()`` keeps its input history; ermrl's reset is a fresh node)."""
    params = NVARParams(delay=3, order=2, strides=2, input_scaling=0.8)
    task = TaskConfig("CartPole-v1", "positions")
    venv = NVAREncoder().wrap_env(make_vec_env(task, 2, 5), nvar_encoder(params, dtype=dtype), 0)
    assert isinstance(venv, ReservoirVecEnv) and isinstance(venv.bank, NVARBank)
    assert venv.observation_space.shape == (params.state_dim_for(5),)
    assert np.all(np.isinf(venv.observation_space.high))
    tol = {"rtol": 0, "atol": 1e-10} if dtype == "float64" else {"rtol": 1e-6, "atol": 1e-6}
    bank = venv.bank
    episodes: list[list[np.ndarray]] = [[], []]
    obs = venv.reset()
    for i in range(2):
        episodes[i].append(venv.get_inputs()[i].astype(np.float64))
    rng = np.random.default_rng(0)
    resets = 0
    for _ in range(120):
        features = bank.features(venv.get_states())  # in the state's dtype
        for i in range(2):
            expected = reservoirpy_features(params, episodes[i])[-1]
            np.testing.assert_allclose(features[i], expected, **tol)
            # The policy sees them as float32.
            np.testing.assert_allclose(obs[i], expected, rtol=1e-6, atol=1e-6)
        obs, _, dones, _ = venv.step(rng.integers(0, 2, 2))
        for i in range(2):
            if dones[i]:  # the next episode starts from zero history
                resets += 1
                episodes[i] = []
            episodes[i].append(venv.get_inputs()[i].astype(np.float64))
    assert resets > 0
    venv.close()


def test_skip_connection_and_exposed_units_follow_the_other_encoders() -> None:
    params = NVARParams(delay=2, order=2)
    task = TaskConfig("Pendulum-v1", "positions")  # d = 2 + 1 + 1
    full = NVAREncoder().wrap_env(make_vec_env(task, 1, 0), nvar_encoder(params), 0)
    width = params.state_dim_for(4)
    # exposed_units is bounded by the width for a 1-value input (EncoderConfig knows no ``d``).
    assert params.state_dim == 5
    enc = nvar_encoder(params, params, skip_connection=True, exposed_units=5)
    part = NVAREncoder().wrap_env(make_vec_env(task, 1, 0), enc, 0)
    assert part.observation_space.shape == (2 * 5 + 2 + 1 + 1,)
    a, b = full.reset(), part.reset()
    for _ in range(30):
        action = np.array([[0.3]])
        np.testing.assert_array_equal(b[:, :5], a[:, :5])  # the first 5 features of each NVAR
        np.testing.assert_array_equal(b[:, 5:10], a[:, :5])
        np.testing.assert_array_equal(b[:, 10:12], part.get_inputs()[:, :2])  # the observation
        a, _, _, _ = full.step(action)
        b, _, _, _ = part.step(action)
    assert a.shape == (1, width)
    # exposed_units beyond the features ``d = 1`` would give is refused (EncoderConfig's check).
    with pytest.raises(ConfigError, match="exposed_units"):
        nvar_encoder(params, exposed_units=params.state_dim + 1)
    full.close()
    part.close()


# -- the population path ---------------------------------------------------------------------------
def test_population_encodings_equal_the_sb3_paths_for_agents_with_other_genes() -> None:
    """Three agents, same delay and order, other strides and input scalings (one population,
    padded delay lines): observations and terminal encodings equal ReservoirVecEnv's exactly."""
    task = TaskConfig("CartPole-v1", "positions")
    encoders = [
        nvar_encoder(NVARParams(delay=3, order=2, strides=s, input_scaling=c), skip_connection=sk)
        for s, c, sk in ((1, 1.0, True), (3, 0.4, True), (2, 2.5, True))
    ]
    env_seeds, res_seeds = [11, 222, 3333], [5, 66, 777]
    pop = PopulationEnvs(task, 2, env_seeds, encoders, res_seeds, None, 0.99)
    venvs = [
        NVAREncoder().wrap_env(make_vec_env(task, 2, env_seeds[p]), encoders[p], res_seeds[p])
        for p in range(3)
    ]
    try:
        obs = pop.reset()
        for p, venv in enumerate(venvs):
            np.testing.assert_array_equal(obs[p], venv.reset())
        rng = np.random.default_rng(0)
        ends = 0
        for _ in range(200):
            actions = rng.integers(0, 2, (3, 2))
            obs, _, _, dones, _, _ = pop.step(actions)
            for p, venv in enumerate(venvs):
                o, _, d, _ = venv.step(actions[p])
                np.testing.assert_array_equal(obs[p], o)
                np.testing.assert_array_equal(dones[p], d)
                ends += int(d.sum())
        assert ends > 0
    finally:
        pop.close()
        for venv in venvs:
            venv.close()


def test_agents_of_other_delays_or_orders_are_other_populations() -> None:
    a = nvar_encoder(NVARParams(delay=2, order=2, strides=1))
    b = nvar_encoder(NVARParams(delay=2, order=2, strides=3, input_scaling=0.3))
    c = nvar_encoder(NVARParams(delay=3, order=2))
    assert encoder_structure(a) == encoder_structure(b) != encoder_structure(c)
    esn = EncoderConfig(reservoirs=(ReservoirParams(units=8),))
    assert encoder_structure(esn) != encoder_structure(a)
    with pytest.raises(ValueError, match="share the encoder's structure"):
        BatchedReservoir([a, c], [0, 1], 2, _box(), 1)
    jobs = [PopulationJob(e, s) for e, s in ((a, 0), (c, 1), (b, 2), (None, 3), (c, 4))]
    assert group_jobs(jobs) == [[0, 2], [1, 4], [3]]


def _box() -> Any:
    from gymnasium import spaces

    return spaces.Discrete(2)


def test_a_generation_of_mixed_structures_trains_group_by_group_as_alone() -> None:
    """train_population_parallel trains mixed NVAR structures (one population each); an agent's
    result is the one it gets trained alone."""
    task = TaskConfig("CartPole-v1", "positions")
    ppo = PPOConfig(hyperparams={"n_steps": 32, "batch_size": 32, "n_epochs": 1})
    budget = BudgetConfig(128, n_last_episodes=2)
    jobs = [
        PopulationJob(nvar_encoder(NVARParams(delay=2, order=2)), 0),
        PopulationJob(nvar_encoder(NVARParams(delay=1, order=3, strides=2)), 1),
        PopulationJob(nvar_encoder(NVARParams(delay=2, order=2, strides=2)), 2),
    ]
    mixed = train_population_parallel(task, ppo, budget, jobs)
    for job, result in zip(jobs, mixed):
        (alone,) = train_population(task, ppo, budget, [job])
        assert not isinstance(result, BaseException) and not isinstance(alone, BaseException)
        assert result.episode_returns == alone.episode_returns


# -- integer genes in the search ------------------------------------------------------------------
def test_integer_genes_become_int_distributions_and_trials_get_integers() -> None:
    space = NVARSpace()
    dists = search_distributions(space)
    assert dists["delay"] == IntDistribution(1, 4) and dists["order"] == IntDistribution(1, 2)
    assert dists["input_scaling"] == FloatDistribution(0.1, 10.0, log=True)
    sampler = make_study_sampler(SearchConfig(sampler_seed=0), space)
    assert isinstance(sampler, RestartCmaEsSampler) and sampler._with_margin
    study = optuna.create_study(sampler=sampler)
    for _ in range(12):
        trial = study.ask()
        params = sample_params(trial, space)
        nvar = space.reservoirs_from(params)[0]
        assert space.contains(params) and isinstance(params["delay"], int)
        assert nvar == NVAREncoder().decode(space, params, nvar_encoder(NVARParams())).reservoirs[0]
        study.tell(trial, float(nvar.delay + nvar.strides))


def _int_study(seed: int, with_margin: bool | None, n_trials: int = 30) -> list[int]:
    """CMA-ES on ``(k - 7)^2``, ``k`` in 1..9, from the box centre."""
    space = {"k": IntDistribution(1, 9)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        sampler = RestartCmaEsSampler(
            seed=seed, search_space=space, x0={"k": 5}, with_margin=with_margin
        )
    study = optuna.create_study(sampler=sampler)
    study.optimize(lambda t: (t.suggest_int("k", 1, 9) - 7) ** 2, n_trials=n_trials)
    return [t.params["k"] for t in study.trials]


@pytest.mark.parametrize("seed", range(5))
def test_cma_es_reaches_an_interior_integer_optimum_and_keeps_exploring(seed: int) -> None:
    ks = _int_study(seed, None)
    assert all(isinstance(k, int) and 1 <= k <= 9 for k in ks)
    assert 7 in ks
    # The margin keeps a neighbour in reach: the last two generations never collapse onto one.
    assert len(set(ks[-8:])) >= 2


def test_without_margin_cma_es_collapses_onto_one_integer() -> None:
    """The failure the margin prevents (Optuna's default rounding outside the search)."""
    collapsed = [seed for seed in range(20) if len(set(_int_study(seed, False)[-8:])) == 1]
    assert collapsed  # seeds 2, 12, 18 and 19 with this cmaes version
    assert all(len(set(_int_study(seed, None)[-8:])) >= 2 for seed in collapsed)


def _first_generations(x0: dict[str, float] | None, seed: int) -> list[dict[str, Any]]:
    """The NVAR genes of CMA-ES's first 5 generations (8 trials each) on a pure-noise fitness,
    started at ``x0`` (``None``: the study's start, :meth:`NVARSpace.center_params`)."""
    space = NVARSpace()
    sampler = make_study_sampler(SearchConfig(sampler_seed=seed), space)
    if x0 is not None:
        sampler._x0 = x0  # type: ignore[attr-defined]
    study = optuna.create_study(sampler=sampler)
    noise = np.random.default_rng(seed)
    params = []
    for _ in range(5 * 8):  # cmaes' default popsize for 4 genes: 4 + floor(3 ln 4) = 8
        trial = study.ask()
        params.append(sample_params(trial, space))
        study.tell(trial, float(noise.normal()))
    return params


def _shares_below_the_middle(x0: dict[str, float] | None) -> dict[str, float]:
    """Per integer gene, the share of values below its range's middle, over seeds 0-9."""
    ranges = NVARSpace().ranges()
    runs = [p for seed in range(10) for p in _first_generations(x0, seed)]
    return {
        name: float(np.mean([p[name] < (ranges[name].low + ranges[name].high) / 2 for p in runs]))
        for name in ("delay", "order", "strides")
    }


def test_integer_genes_start_unbiased_on_a_flat_fitness() -> None:
    """Started at the exact middle of each integer range, CMA-ES's first 5 generations draw
    each side of the middle about half the time on a pure-noise fitness: order 1 and 2 each
    0.5 +- 0.15, and likewise delay and strides in 1-2 against 3-4 (measured over seeds 0-9:
    order 1 0.445, delay 1-2 0.46, strides 1-2 0.485).

    The old start, the lower of two middle integers (delay 2, order 1, strides 2), fails it by
    far: order 1 0.90, delay 1-2 0.80, strides 1-2 0.86 (order 2 was drawn 39 times in 400).
    """
    shares = _shares_below_the_middle(None)
    assert shares == pytest.approx({"delay": 0.5, "order": 0.5, "strides": 0.5}, abs=0.15)
    old = _shares_below_the_middle({"delay": 2, "order": 1, "strides": 2, "input_scaling": 1.0})
    assert all(share > 0.65 for share in old.values()), old


def test_float_genes_next_to_integer_ones_still_converge() -> None:
    space = {"k": IntDistribution(1, 9), "x": FloatDistribution(0.01, 100.0, log=True)}
    sampler = RestartCmaEsSampler(seed=0, search_space=space, x0={"k": 2, "x": 1.0})
    assert sampler._with_margin
    study = optuna.create_study(sampler=sampler)

    def objective(t: optuna.Trial) -> float:
        x = t.suggest_float("x", 0.01, 100.0, log=True)
        return 100 * math.log10(x / 3) ** 2 + 0.3 * abs(t.suggest_int("k", 1, 9) - 7)

    study.optimize(objective, n_trials=60)
    xs = [t.params["x"] for t in study.trials]
    assert all(isinstance(x, float) and 0.01 <= x <= 100 for x in xs)
    assert len({round(x, 6) for x in xs}) == len(xs)  # not rounded to a grid
    assert abs(math.log10(study.best_params["x"] / 3)) < 0.1
    # A float-only space keeps plain CMA-ES (its studies' stored state is unchanged).
    floats = RestartCmaEsSampler(search_space={"x": space["x"]})
    assert not floats._with_margin and floats._attr_prefix == "cma:"


def test_an_enqueued_trial_is_told_at_its_own_integers() -> None:
    """The reference trial is queued with fixed parameters, and ermrl asks CMA-ES for it anyway
    (``claim``), so that it belongs to a generation: CMA-ES with margin must learn from its
    parameters, not from the point it asked for that trial."""
    space = {"k": IntDistribution(1, 10)}
    sampler = RestartCmaEsSampler(seed=0, search_space=space, x0={"k": 1}, popsize=4)
    study = optuna.create_study(sampler=sampler)
    study.enqueue_trial({"k": 10})
    for _ in range(5):
        trial = study.ask()
        _ = trial.relative_params  # as ermrl.search's claim does for the reference trial
        study.tell(trial, float(-trial.suggest_int("k", 1, 10)))
    first = study.trials[0]
    assert first.params == {"k": 10} and "x_for_tell" in first.system_attrs
    asked = first.system_attrs["x_for_tell"][0]
    assert asked < 0.5  # CMA-ES asked near its start (k = 1), not at 10
    attrs = study.trials[4].system_attrs
    chunks = {k: v for k, v in attrs.items() if k.startswith("cmawm:state:")}
    optimizer = restore_optimizer(json.loads(_join_chunks(chunks, "cmawm:state:")))
    assert optimizer.generation == 1
    # Told at k = 10 (1.0 in the unit box), the mean moves far from the start (0.0).
    assert optimizer.mean[0] > 0.3


# -- plain data for the registry ------------------------------------------------------------------
def test_the_agents_and_flags_are_ready_to_register() -> None:
    for name, fields in AGENTS.items():
        kind = AgentKind(**fields)
        assert kind.family == "nvar" and name.endswith("nvar-res-ppo")
    assert {a["reservoirs"] for a in AGENTS.values()} == {"evolved", "unevolved"}
    settings = dataclasses.fields(NVARSettings)
    assert {f.name for f in settings} == {"delay_range", "order_range", "strides_range"}
    defaults = NVARSpace()
    for setting in settings:
        low, high = setting.default
        assert getattr(defaults, setting.name.removesuffix("_range")) == IntRange(low, high)
    encoder = NVAREncoder()
    assert encoder.name == "nvar" and encoder.family == "nvar" and encoder.space_cls is NVARSpace
    assert encoder.accepts(nvar_encoder(NVARParams()))
    assert not encoder.accepts(EncoderConfig())


# -- registered: the CLI, the test phase and the report --------------------------------------------
def test_nvar_is_registered_with_its_agents_and_flags() -> None:
    from ermrl.encoders import ENCODERS, encoder_for
    from ermrl.learners import AGENT_KINDS, default_agents, evolved_agent, unevolved_agent

    assert isinstance(ENCODERS["nvar"], NVAREncoder)
    assert encoder_for(nvar_encoder(NVARParams())) is ENCODERS["nvar"]
    assert set(AGENTS) <= set(AGENT_KINDS)
    assert (evolved_agent("nvar"), unevolved_agent("nvar")) == tuple(AGENTS)
    assert default_agents("positions", "nvar") == ("ppo", "ppo-full", *AGENTS)
    # A stored NVAR study's encoder reads back as NVARs, through the registry.
    from ermrl.config import from_dict, to_dict

    encoder = nvar_encoder(NVARParams(delay=3, strides=2), NVARParams(order=1))
    assert from_dict(EncoderConfig, to_dict(encoder)) == encoder


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        ([], "an NVAR of delay 4 and order 2 on d = 24 inputs has 4,752 features"),
        (["--delay-range", "1", "2", "--order-range", "2", "3"], "lower the order range"),
        (["--units", "5"], "--units applies to --encoder reservoir or rtu, not to --encoder nvar"),
    ],
)
def test_the_cli_refuses_sizes_over_the_limit_in_one_line_before_anything_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], message: str
) -> None:
    from ermrl.cli._evolve import evolve_main

    db = tmp_path / "x.db"
    with pytest.raises(SystemExit) as exit_:
        evolve_main(["--env-id", "HalfCheetah-v5", "--encoder", "nvar", *flags,
                     "--storage", f"sqlite:///{db}"])  # fmt: skip
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not db.exists()


def _ermrl(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=900,
    )


def test_an_nvar_study_is_evolved_on_both_backends_tested_and_reported(tmp_path: Path) -> None:
    """``--encoder nvar`` on a partially observable task: evolution (sb3 and population), the
    test phase's default agents, and the report's replay of the evolved NVAR."""
    from ermrl.search import study_config

    storage = f"sqlite:///{tmp_path / 'nvar.db'}"
    tiny = ["--ppo", "n_steps=128", "batch_size=64", "n_epochs=1", "--n-envs", "1"]
    for backend in ("sb3", "population"):
        evolve = _ermrl(
            "evolve", "--env-id", "Pendulum-v1", "--observe", "positions", "--encoder", "nvar",
            "--delay-range", "1", "3", "--n-trials", "2", "--n-seeds", "1",
            "--training-steps", "256", "--backend", backend, *tiny,
            "--storage", storage, "--study-name", f"nvar-{backend}", "--progress", "none",
            cwd=tmp_path,
        )  # fmt: skip
        assert evolve.returncode == 0, evolve.stderr
        assert "delay=2 order=2 strides=1 input_scaling=1" in evolve.stdout  # the reference
        study = optuna.load_study(study_name=f"nvar-{backend}", storage=storage)
        config = study_config(study)
        assert isinstance(config.space, NVARSpace) and config.problem.ppo.backend == backend
        assert config.space.delay == IntRange(1, 3)
        done = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
        assert len(done) == 2 and all(isinstance(t.params["delay"], int) for t in done)
    out = tmp_path / "test"
    test = _ermrl(
        "test", "--study-name", "nvar-sb3", "--storage", storage, "--seeds", "10",
        "--training-steps", "256", "--ppo", "n_steps=128", "n_envs=1", "--out", str(out),
        cwd=tmp_path,
    )  # fmt: skip
    assert test.returncode == 0, test.stderr
    summary = (out / "summary.csv").read_text()
    for agent in ("ppo", "ppo-full", "nvar-res-ppo", "random-nvar-res-ppo"):
        assert agent in summary
    settings = json.loads(
        (out / "agents" / "random-nvar-res-ppo" / "seed_10" / "settings.json").read_text()
    )
    assert settings["encoder"]["reservoirs"] == [
        {"delay": 2, "order": 2, "strides": 1, "input_scaling": 1.0, "family": "nvar"}
    ]
    refused = _ermrl(
        "test", "--study-name", "nvar-sb3", "--storage", storage, "--seeds", "10",
        "--agents", "res-ppo", "--out", str(tmp_path / "refused"), cwd=tmp_path,
    )  # fmt: skip
    assert refused.returncode == 2 and "--encoder reservoir" in refused.stderr
    report = _ermrl(
        "report", "--study-name", "nvar-sb3", "--storage", storage, "--runs", str(out),
        "--out", str(tmp_path / "report"), cwd=tmp_path,
    )  # fmt: skip
    assert report.returncode == 0, report.stderr
    md = (tmp_path / "report" / "report.md").read_text()
    assert "1 x NVAR (delay 1-3, order 1-2, strides 1-4)" in md
    assert "### `nvar-res-ppo` against the baselines" in md
    assert list((tmp_path / "report" / "dynamics").glob("nvar-res-ppo_seed10_*.png"))
