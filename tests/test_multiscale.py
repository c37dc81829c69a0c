"""Multi-timescale reservoirs (``ermrl evolve --multiscale``): an echo state network whose units
leak at rates spaced log-uniformly between two evolved bounds.

The spacing is the stated one; a step is the per-unit leaky update, and reservoirpy's own
``Reservoir`` with those rates computes the same states; both backends encode alike; the search
space keeps ``lr_min <= lr_max``; the settings round-trip through stored configurations; an
evolution and a test phase with ``res-ppo``, ``leaky-res-ppo`` and ``random-res-ppo`` run end to
end; and ``experiments/multiscale.yaml`` plans what it says.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import pytest
import yaml

from ermrl.agents import make_vec_env
from ermrl.config import (
    ConfigError,
    EncoderConfig,
    EvolveConfig,
    Range,
    ReservoirParams,
    TaskConfig,
    from_dict,
    to_dict,
)
from ermrl.encoders import (
    ReservoirBank,
    ReservoirEncoder,
    ReservoirSpace,
    reservoir_node,
    reservoir_weights,
)
from ermrl.encoders._reservoir import Ablation
from ermrl.population import PopulationEnvs
from ermrl.search._samplers import SamplerName

ROOT = Path(__file__).resolve().parents[1]

# A band of leak rates as evolution might select it, with a small spectral radius and a bias.
BAND = ReservoirParams(units=7, sr=0.05, lr=0.002, lr_max=0.6, input_scaling=0.7, bias_scaling=0.2)


def band_formula(lr_min: float, lr_max: float, units: int) -> np.ndarray:
    """The stated spacing, unit by unit: ``lr_i = lr_min (lr_max / lr_min)^(i / (units - 1))``."""
    return np.array([lr_min * (lr_max / lr_min) ** (i / (units - 1)) for i in range(units)])


# ------------------------------------------------------------------------------------------
# The reservoir


def test_the_leak_rates_are_log_uniformly_spaced_between_the_two_bounds() -> None:
    rates = BAND.leak_rates()
    np.testing.assert_allclose(rates, band_formula(0.002, 0.6, 7), rtol=1e-14, atol=0)
    assert rates[0] == 0.002 and rates[-1] == pytest.approx(0.6, rel=1e-15)
    ratios = rates[1:] / rates[:-1]  # one factor between neighbours: log-uniform spacing
    np.testing.assert_allclose(ratios, (0.6 / 0.002) ** (1 / 6), rtol=1e-12)
    # One leak rate for all: without lr_max, with lr_max = lr, and for a single unit.
    np.testing.assert_array_equal(ReservoirParams(units=4, lr=0.3).leak_rates(), [0.3] * 4)
    np.testing.assert_array_equal(
        ReservoirParams(units=4, lr=0.3, lr_max=0.3).leak_rates(), [0.3] * 4
    )
    np.testing.assert_array_equal(ReservoirParams(units=1, lr=0.3, lr_max=0.9).leak_rates(), [0.3])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"lr": 0.5, "lr_max": 0.4}, "lr_max must be in [lr = 0.5, 1]"),
        ({"lr": 0.5, "lr_max": 1.5}, "lr_max must be in [lr = 0.5, 1]"),
        ({"lr": 0.1, "lr_max": 0.5, "ablation": "ema"}, "'ema' ablation averages at one leak"),
    ],
)
def test_a_bad_band_is_refused_in_one_line(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("(", r"\(")):
        ReservoirParams(**kwargs)


def test_the_weights_are_the_plain_reservoirs_with_one_leak_rate_per_unit() -> None:
    """The same seed draws the same ``W``, ``Win`` and bias as the one-timescale reservoir."""
    band = reservoir_weights(BAND, 3, seed=5)
    plain = reservoir_weights(dataclasses.replace(BAND, lr_max=None), 3, seed=5)
    for name in ("W", "Win", "bias"):
        np.testing.assert_array_equal(getattr(band, name), getattr(plain, name))
    np.testing.assert_array_equal(band.lr, BAND.leak_rates())
    assert plain.lr == 0.002
    bank = ReservoirBank([band])
    np.testing.assert_array_equal(bank.leak, BAND.leak_rates())
    np.testing.assert_array_equal(bank.keep, 1 - BAND.leak_rates())


def test_one_step_is_each_units_leaky_update_written_out() -> None:
    """``x_i <- (1 - lr_i) x_i + lr_i tanh(W x + Win u + b)_i``, computed unit by unit."""
    w = reservoir_weights(BAND, 3, seed=5)
    assert np.any(w.W) and np.any(w.bias)
    bank = ReservoirBank([w])
    rng = np.random.default_rng(0)
    states, inputs = rng.uniform(-1, 1, (4, 7)), rng.normal(size=(4, 3))
    expected = np.empty_like(states)
    for row, (x, u) in enumerate(zip(states, inputs)):
        for i in range(7):
            drive = sum(w.W[i, j] * x[j] for j in range(7))
            drive += sum(w.Win[i, k] * u[k] for k in range(3)) + w.bias[i]
            lr_i = 0.002 * (0.6 / 0.002) ** (i / 6)
            expected[row, i] = (1 - lr_i) * x[i] + lr_i * np.tanh(drive)
    np.testing.assert_allclose(bank.step(states.copy(), inputs), expected, rtol=0, atol=1e-14)


def test_the_bank_runs_as_reservoirpys_reservoir_with_those_leak_rates() -> None:
    """reservoirpy's ``Reservoir`` takes one leak rate per unit: its states are the bank's."""
    inputs = np.random.default_rng(1).normal(size=(30, 3))
    node = reservoir_node(BAND, 3, seed=9)
    np.testing.assert_array_equal(node.lr, BAND.leak_rates())
    ours = ReservoirBank([reservoir_weights(BAND, 3, seed=9)]).run(inputs)
    np.testing.assert_allclose(ours, node.run(inputs), rtol=0, atol=1e-12)


def test_leaky_res_ppo_of_a_band_has_no_recurrence_and_the_same_leak_rates() -> None:
    leaky = dataclasses.replace(BAND, ablation="leaky")
    full, bare = (
        ReservoirBank([reservoir_weights(BAND, 3, 5)]),
        ReservoirBank([reservoir_weights(leaky, 3, 5)]),
    )
    assert not np.any(bare.W_T) and np.any(full.W_T)
    np.testing.assert_array_equal(bare.Win_T, full.Win_T)
    np.testing.assert_array_equal(bare.leak, full.leak)
    u = np.random.default_rng(2).normal(size=(1, 3))
    x = np.random.default_rng(3).uniform(-1, 1, (1, 7))
    lr = BAND.leak_rates()
    expected = (1 - lr) * x + lr * np.tanh(u @ full.Win_T + full.bias)
    np.testing.assert_allclose(bare.step(x.copy(), u), expected, rtol=0, atol=1e-15)


@pytest.mark.parametrize("ablation", ["none", "leaky"])
@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
def test_the_population_backend_encodes_as_the_sb3_wrapper(ablation: Ablation, env_id: str) -> None:
    """Two agents (different bands) stepped in one population see, step by step, what their
    own sb3 wrapper shows (over episode ends on CartPole)."""
    task = TaskConfig(env_id, "all")
    params = dataclasses.replace(BAND, ablation=ablation)
    encoders = [
        EncoderConfig(reservoirs=(dataclasses.replace(params, lr=lr, lr_max=top),))
        for lr, top in ((0.01, 0.9), (0.2, 0.5))
    ]
    env_seeds, res_seeds = [11, 222], [5, 66]
    pop = PopulationEnvs(task, 2, env_seeds, encoders, res_seeds, None, 0.99)
    venvs = [make_vec_env(task, 2, env_seeds[p], encoders[p], res_seeds[p]) for p in range(2)]
    try:
        obs = pop.reset()
        for p, venv in enumerate(venvs):
            np.testing.assert_array_equal(obs[p], venv.reset())
        rng = np.random.default_rng(0)
        for _ in range(80):
            if pop.discrete:
                actions = rng.integers(0, 2, (2, 2))
            else:
                actions = rng.uniform(-2, 2, (2, 2, 1)).astype(np.float32)
            obs, *_ = pop.step(actions)
            for p, venv in enumerate(venvs):
                np.testing.assert_array_equal(obs[p], venv.step(actions[p])[0])
    finally:
        pop.close()
        for venv in venvs:
            venv.close()


# ------------------------------------------------------------------------------------------
# The search space


def test_the_space_evolves_the_band_in_place_of_the_leak_rate() -> None:
    plain = ReservoirSpace()
    space = ReservoirSpace(multiscale=True)
    assert plain.param_names == ("sr", "lr", "input_scaling")
    assert space.param_names == ("sr", "lr_max", "lr_min_ratio", "input_scaling")
    assert space.ranges()["lr_max"] == Range(1e-3, 1.0) == space.ranges()["lr_min_ratio"]
    assert ReservoirSpace(multiscale=True, input_scaling=None, n_reservoirs=2).param_names == (
        "sr_0", "lr_max_0", "lr_min_ratio_0", "sr_1", "lr_max_1", "lr_min_ratio_1",
    )  # fmt: skip
    (one,) = space.reservoirs_from(
        {"sr": 0.2, "lr_max": 0.5, "lr_min_ratio": 0.01, "input_scaling": 2.0}
    )
    assert (one.sr, one.lr, one.lr_max, one.input_scaling) == (0.2, 0.005, 0.5, 2.0)


def test_the_reference_is_the_plain_echo_state_network() -> None:
    """Trial 0 and random-res-ppo: reservoirpy's defaults, every unit at leak rate 1."""
    space = ReservoirSpace(multiscale=True)
    assert space.reference_params() == {
        "sr": 1.0, "lr_max": 1.0, "lr_min_ratio": 1.0, "input_scaling": 1.0,
    }  # fmt: skip
    assert space.contains(space.reference_params())
    (ref,) = space.default_reservoirs()
    assert space.reservoirs_from(space.reference_params()) == (ref,)
    np.testing.assert_array_equal(ref.leak_rates(), np.ones(100))
    plain = ReservoirBank([reservoir_weights(ReservoirParams(), 4, 3)])
    band = ReservoirBank([reservoir_weights(ref, 4, 3)])
    np.testing.assert_array_equal(band.M, plain.M)
    np.testing.assert_array_equal(band.leak, plain.leak)


@pytest.mark.parametrize("sampler", ["cmaes", "random"])
def test_every_sampled_point_keeps_lr_min_below_lr_max(sampler: SamplerName) -> None:
    from ermrl.search import make_sampler
    from ermrl.search._study import search_distributions

    space = ReservoirSpace(multiscale=True, units=10)
    distributions = search_distributions(space)
    study = optuna.create_study(
        sampler=make_sampler(
            sampler, seed=0, search_space=distributions if sampler == "cmaes" else None
        ),
        direction="maximize",
    )
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    lows = []
    for _ in range(60):
        trial = study.ask(distributions)
        (params,) = space.reservoirs_from(trial.params)
        assert params.lr_max is not None
        assert 1e-6 * (1 - 1e-12) <= params.lr <= params.lr_max <= 1
        rates = params.leak_rates()
        assert np.all(np.diff(rates) >= 0) and rates[0] == params.lr
        lows.append(params.lr)
        # A fitness that pulls lr_min down: CMA-ES walks towards the box's corner.
        study.tell(trial, -np.log(params.lr))
    assert min(lows) < 1e-3  # the band reaches below the plain ESN's lower bound


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"lr_max": Range(1e-3, 2.0)}, "the lr_max range must stay within (0, 1]"),
        ({"lr_min_ratio": Range(0.0, 1.0, log=False)}, "the lr_min_ratio range must stay"),
    ],
)
def test_a_band_range_outside_0_1_is_refused(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace("]", r"\]")):
        ReservoirSpace(multiscale=True, **kwargs)


def test_stored_settings_round_trip_and_old_ones_are_unchanged() -> None:
    space = ReservoirSpace(multiscale=True, lr_max=Range(1e-2, 1.0))
    stored = json.loads(json.dumps(to_dict(space)))
    assert stored["multiscale"] is True and stored["lr_max"]["low"] == 1e-2
    assert "lr_min_ratio" not in stored  # at its default
    assert from_dict(ReservoirSpace, stored) == space
    encoder = EncoderConfig(reservoirs=(BAND,))
    stored_encoder = json.loads(json.dumps(to_dict(encoder)))
    assert stored_encoder["reservoirs"][0]["lr_max"] == 0.6
    assert from_dict(EncoderConfig, stored_encoder) == encoder
    # Without the option nothing new is written, and what was stored before reads back alike.
    assert {"multiscale", "lr_max", "lr_min_ratio"}.isdisjoint(to_dict(ReservoirSpace()))
    assert "lr_max" not in to_dict(ReservoirParams())
    assert from_dict(ReservoirParams, to_dict(ReservoirParams(lr=0.3))).lr_max is None


# ------------------------------------------------------------------------------------------
# The command line and the experiment file


def _config(*flags: str) -> EvolveConfig:
    from ermrl.cli._evolve import build_evolve_parser, config_from_args

    args = build_evolve_parser().parse_args(["--env-id", "Pendulum-v1", *flags])
    return config_from_args(args, build_agent=False)


def test_the_flags_build_the_space_and_name_the_study() -> None:
    config = _config("--multiscale", "--lr-max-range", "0.01", "0.5", "--observe", "positions")
    assert isinstance(config.space, ReservoirSpace) and config.space.multiscale
    assert config.space.lr_max == Range(0.01, 0.5)
    assert config.problem.encoder is not None
    assert config.problem.encoder.reservoirs == config.space.default_reservoirs()
    assert config.default_study_name == "Pendulum-v1__positions__300000steps__multiscale"
    assert _config().default_study_name == "Pendulum-v1__all__300000steps"
    assert ReservoirEncoder().describe(config.space) == "1 x 100 units, multi-timescale"
    assert EvolveConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--multiscale", "--lr-range", "0.1", "1"], "--lr-range is unused with --multiscale"),
        (["--lr-max-range", "0.1", "1"], "--lr-max-range is unused without --multiscale"),
        (["--encoder", "rtu", "--multiscale"], "--multiscale applies to --encoder reservoir"),
    ],
)
def test_flags_of_the_other_mode_are_refused(flags: list[str], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        _config(*flags)


def test_the_experiment_file_plans_both_tasks_at_the_paper_files_scale() -> None:
    from ermrl.runner import experiment_plan, load_experiment

    path = ROOT / "experiments" / "multiscale.yaml"
    steps = experiment_plan(load_experiment(path), build_agents=False)
    by = {(s.label, s.stage): s for s in steps}
    seeds = [str(s) for s in range(10, 30)]
    four = ["ppo", "res-ppo", "leaky-res-ppo", "random-res-ppo"]
    for env_id, observe, trials, test_steps, tested in (
        ("Ant-v5", "all", "60", "1000000", ["res-ppo", "leaky-res-ppo"]),
        ("Pendulum-v1", "positions", "100", "300000", four),
    ):
        evolve, test = by[(env_id, "evolve")].argv, by[(env_id, "test")].argv
        assert "--multiscale" in evolve and "--fixed-input-scaling" in evolve
        for flag, value in (
            ("--observe", observe), ("--n-trials", trials), ("--n-seeds", "3"),
            ("--training-steps", "300000"), ("--backend", "population"), ("--n-procs", "2"),
            ("--sampler", "cmaes"), ("--reevaluate-top", "3"), ("--reevaluate-seeds", "3"),
        ):  # fmt: skip
            assert evolve[evolve.index(flag) + 1] == value, (env_id, flag)
        assert evolve[-1].endswith("__multiscale")
        agents = test[test.index("--agents") + 1 : test.index("--agents") + 1 + len(tested)]
        assert agents == tested and test[test.index("--agents") + 1 + len(tested)].startswith("-")
        assert test[test.index("--seeds") + 1 : test.index("--seeds") + 21] == seeds
        assert test[test.index("--training-steps") + 1] == test_steps
    doc = yaml.safe_load(path.read_text())
    assert "Scale" in path.read_text().split("\nname:")[0]
    questions = doc["verdict"]["questions"]
    assert questions["multiscale-vs-leaky"]["compare"] == ["res-ppo - leaky-res-ppo"]
    assert questions["multiscale-vs-one-timescale"]["compare"] == [
        "res-ppo - one-timescale-res-ppo"
    ]
    # The one-timescale baseline is the paper files' published res-ppo runs: the same task,
    # observation and seeds as this file's test phase.
    ref = doc["verdict"]["references"]["one-timescale-res-ppo"]
    assert ref["agent"] == "res-ppo" and set(ref["tests"]) == {"Ant-v5", "Pendulum-v1"}
    # On Ant-v5, ppo and random-res-ppo are h2's published runs too (not re-run there).
    refs = doc["verdict"]["references"]
    assert {n: r["agent"] for n, r in refs.items()} == {
        "one-timescale-res-ppo": "res-ppo", "ppo": "ppo", "random-res-ppo": "random-res-ppo"}  # fmt: skip
    assert set(refs["ppo"]["tests"]) == set(refs["random-res-ppo"]["tests"]) == {"Ant-v5"}
    for name, r in refs.items():
        for env_id, folder in r["tests"].items():
            observe = "all" if env_id == "Ant-v5" else "positions"
            runs = sorted((ROOT / folder / "agents" / r["agent"]).glob("seed_*"))
            records = [json.loads((run / "result.json").read_text()) for run in runs]
            assert sorted(x["seed"] for x in records) == [int(s) for s in seeds], (name, env_id)
            assert {(x["env_id"], x.get("observe", "all")) for x in records} == {(env_id, observe)}
    quick = experiment_plan(load_experiment(path, variant="quick"), build_agents=False)
    evolve = next(s for s in quick if s.stage == "evolve").argv
    assert [s.label for s in quick if s.stage == "evolve"] == ["Pendulum-v1"]
    assert evolve[evolve.index("--observe") + 1] == "positions" and "--multiscale" in evolve


def _ermrl(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args], cwd=cwd, capture_output=True, text=True, timeout=900
    )


@pytest.mark.slow
def test_a_multiscale_study_is_evolved_and_tested_with_its_ablation(tmp_path: Path) -> None:
    """``ermrl evolve --multiscale`` (population backend: the reference then a CMA-ES trial),
    then ``ermrl test`` with res-ppo, leaky-res-ppo and random-res-ppo; the runs record their
    bands."""
    from ermrl.search import study_config

    storage = f"sqlite:///{tmp_path / 'ms.db'}"
    evolve = _ermrl(
        "evolve", "--env-id", "Pendulum-v1", "--observe", "positions", "--multiscale",
        "--units", "20", "--n-trials", "2", "--n-seeds", "1", "--training-steps", "2048",
        "--fixed-input-scaling", "--storage", storage, "--progress", "none", cwd=tmp_path,
    )  # fmt: skip
    assert evolve.returncode == 0, evolve.stderr
    name = "Pendulum-v1__positions__2048steps__multiscale"
    study = optuna.load_study(study_name=name, storage=storage)
    assert study_config(study).space == ReservoirSpace(
        units=20, multiscale=True, input_scaling=None
    )
    trials = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    assert len(trials) == 2
    assert trials[0].params == {"sr": 1.0, "lr_max": 1.0, "lr_min_ratio": 1.0}  # the reference
    evolved = trials[1].params
    assert set(evolved) == {"sr", "lr_max", "lr_min_ratio"} and evolved != trials[0].params
    out = tmp_path / "test"
    test = _ermrl(
        "test", "--study-name", name, "--storage", storage, "--seeds", "10", "--trial", "1",
        "--agents", "res-ppo", "leaky-res-ppo", "random-res-ppo", "--training-steps", "1024",
        "--out", str(out), "--no-save-models", cwd=tmp_path,
    )  # fmt: skip
    assert test.returncode == 0, test.stderr
    lr_max = evolved["lr_max"]
    lr = evolved["lr_min_ratio"] * lr_max
    expected = {
        "res-ppo": (lr, lr_max, None),
        "leaky-res-ppo": (lr, lr_max, "leaky"),
        "random-res-ppo": (1.0, 1.0, None),
    }
    for agent, (low, high, ablation) in expected.items():
        run = json.loads((out / "agents" / agent / "seed_10" / "settings.json").read_text())
        (res,) = run["encoder"]["reservoirs"]
        assert (res["lr"], res["lr_max"], res.get("ablation")) == (low, high, ablation), agent
        result = json.loads((out / "agents" / agent / "seed_10" / "result.json").read_text())
        assert np.isfinite(result["final_return"])


def test_report_labels_name_the_band_genes() -> None:
    """Figures and tables of a multiscale study label its genes in words, per reservoir too."""
    from ermrl.analysis import param_label

    assert param_label("lr_max") == "Highest leak rate lr_max"
    assert (
        param_label("lr_min_ratio_1") == "Lowest / highest leak rate lr_min_ratio_1 (reservoir 1)"
    )
    assert param_label("lr_0") == "Leak rate lr_0 (reservoir 0)"
