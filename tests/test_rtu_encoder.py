"""The frozen RTU encoder (``--encoder rtu``): weights, update, search space, CLI and test phase."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ermrl.config import (
    ConfigError,
    EncoderConfig,
    EvolveConfig,
    ReservoirParams,
    ReservoirSpace,
    RTUParams,
    RTUSpace,
    from_dict,
    to_dict,
)
from ermrl.encoders import ReservoirBank, encoder_for, rtu_weights
from ermrl.learners import default_agents, evolved_agent, unevolved_agent


def _rtu_reference(params: RTUParams, weights_seed: int, inputs: np.ndarray) -> np.ndarray:
    """The RTU equations written out per unit, from the same random draws as rtu_weights."""
    recurrent, input_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(weights_seed).spawn(2)
    )
    n, d = params.units, inputs.shape[1]
    r = np.sqrt(recurrent.uniform(params.r_min**2, params.r_max**2, n))
    theta = recurrent.uniform(0.0, params.theta_max, n)
    w = input_rng.normal(0.0, params.input_scaling / math.sqrt(d), (2 * n, d))
    w1, w2 = w[:n], w[n:]
    c1, c2 = np.zeros(n), np.zeros(n)
    out = []
    for x in inputs:
        g, phi, gamma = r * np.cos(theta), r * np.sin(theta), np.sqrt(1 - r**2)
        c1, c2 = g * c1 - phi * c2 + gamma * (w1 @ x), g * c2 + phi * c1 + gamma * (w2 @ x)
        out.append(np.concatenate([c1, c2]))
    return np.array(out)


def test_the_bank_follows_the_rtu_equations() -> None:
    params = RTUParams(units=7, r_min=0.3, r_max=0.95, theta_max=2.0, input_scaling=1.7)
    inputs = np.random.default_rng(1).normal(size=(40, 5))
    bank = ReservoirBank([rtu_weights(params, 5, seed=11)])
    np.testing.assert_allclose(bank.run(inputs), _rtu_reference(params, 11, inputs), atol=1e-12)


def test_rtu_weights_draw_decays_and_frequencies_from_their_ranges() -> None:
    params = RTUParams(units=200, r_min=0.5, r_max=0.8, theta_max=0.3)
    weights = rtu_weights(params, 3, seed=0)
    eig = np.linalg.eigvals(weights.W)
    assert np.all(np.abs(eig) >= 0.5 - 1e-12) and np.all(np.abs(eig) <= 0.8 + 1e-12)
    assert np.all(np.abs(np.angle(eig)) <= 0.3 + 1e-12)
    # Same seed, another input size: the same recurrence (as reservoirpy's W for an ESN).
    np.testing.assert_array_equal(rtu_weights(params, 9, seed=0).W, weights.W)
    assert not np.array_equal(rtu_weights(params, 3, seed=1).W, weights.W)


def test_rtu_params_refuse_bad_ranges_in_one_line() -> None:
    for bad in (dict(r_max=1.5), dict(r_min=0.9, r_max=0.5), dict(theta_max=0.0), dict(units=0)):
        with pytest.raises(ConfigError) as err:
            RTUParams(**bad)
        assert "\n" not in str(err.value)


def test_the_encoder_wraps_an_env_and_shows_tanh_of_its_states() -> None:
    from ermrl.agents import make_vec_env
    from ermrl.config import TaskConfig

    encoder = EncoderConfig(reservoirs=(RTUParams(units=10),))
    assert encoder_for(encoder).name == "rtu"
    assert encoder_for(EncoderConfig()).name == "reservoir"
    venv = make_vec_env(TaskConfig("CartPole-v1", "positions"), 2, 0, encoder, reservoir_seed=3)
    obs = venv.reset()
    assert obs.shape == (2, 20) and obs.dtype == np.float32
    for _ in range(60):
        obs, _, dones, _ = venv.step(np.array([venv.action_space.sample() for _ in range(2)]))
        np.testing.assert_allclose(obs, np.tanh(venv.get_states()), rtol=1e-6)
    assert np.all(np.abs(obs) < 1)
    venv.close()


def test_an_encoder_cannot_mix_families() -> None:
    with pytest.raises(ConfigError, match="one family"):
        EncoderConfig(reservoirs=(ReservoirParams(), RTUParams()))


def test_rtu_space_reference_is_the_papers_initialization_and_inside_the_box() -> None:
    space = RTUSpace()
    ref = space.reference_params()
    assert ref == {"r_max": 1.0, "r_min_ratio": 0.0, "theta_max": 2 * math.pi, "input_scaling": 1.0}
    assert space.contains(ref) and space.contains(space.center_params())
    assert space.reservoirs_from(ref) == space.default_reservoirs() == (RTUParams(units=50),)
    two = RTUSpace(n_reservoirs=2, input_scaling=None, fixed_input_scaling=0.5)
    assert two.param_names == (
        "r_max_0", "r_min_ratio_0", "theta_max_0", "r_max_1", "r_min_ratio_1", "theta_max_1"
    )  # fmt: skip
    layers = two.reservoirs_from({**two.center_params(), "r_min_ratio_1": 0.5, "r_max_1": 0.6})
    assert layers[1].r_min == pytest.approx(0.3) and layers[0].input_scaling == 0.5
    with pytest.raises(ConfigError, match="missing"):
        space.reservoirs_from({"r_max": 0.5})


def test_an_rtu_study_configuration_round_trips_and_esn_dicts_are_unchanged(
    tmp_path: Path,
) -> None:
    from ermrl.config import BudgetConfig, PPOConfig, Problem, SearchConfig, TaskConfig

    space = RTUSpace(units=8)
    problem = Problem(
        TaskConfig("CartPole-v1", "positions"),
        EncoderConfig(reservoirs=space.default_reservoirs()),
        PPOConfig(),
        BudgetConfig(1000),
    )
    config = EvolveConfig(problem, space, SearchConfig())
    data = config.to_dict()
    assert data["space"]["family"] == "rtu"
    assert EvolveConfig.from_dict(data) == config
    assert config.default_study_name.endswith("__rtu")
    esn = to_dict(ReservoirSpace())
    assert "family" not in esn and "family" not in to_dict(ReservoirParams())
    assert from_dict(ReservoirSpace, esn) == ReservoirSpace()
    with pytest.raises(ConfigError, match="different families"):
        EvolveConfig(problem, ReservoirSpace(), SearchConfig())
    # The population backend runs RTU encoders too.
    population = PPOConfig(backend="population")
    EvolveConfig(
        Problem(problem.task, problem.encoder, population, problem.budget), space, SearchConfig()
    )


def test_agents_follow_the_studys_encoder_family() -> None:
    from ermrl.test_phase import agent_specs

    assert evolved_agent("rtu") == "rtu-res-ppo" and unevolved_agent("rtu") == "random-rtu-res-ppo"
    assert evolved_agent() == "res-ppo"
    assert "rtu-res-ppo" in default_agents("positions", "rtu")
    assert "res-ppo" not in default_agents("positions", "rtu")
    assert "rtu-res-ppo" not in default_agents("positions")
    with pytest.raises(ConfigError, match="--encoder rtu"):
        agent_specs(["rtu-res-ppo"], None, ReservoirSpace().default_reservoirs())
    specs = agent_specs(["random-rtu-res-ppo"], None, RTUSpace().default_reservoirs())
    assert specs[0].reservoirs == RTUSpace().default_reservoirs()


def test_evolve_and_test_an_rtu_study_from_the_command_line(tmp_path: Path) -> None:
    """A real evolution with --encoder rtu on a partially observable task, then its test phase."""
    storage = f"sqlite:///{tmp_path / 'rtu.db'}"
    run = [sys.executable, "-m", "ermrl"]
    evolve = subprocess.run(
        [*run, "evolve", "--env-id", "CartPole-v1", "--observe", "positions", "--encoder", "rtu",
         "--units", "8", "--n-trials", "3", "--n-seeds", "1", "--training-steps", "600",
         "--storage", storage, "--study-name", "rtu"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert evolve.returncode == 0, evolve.stderr
    assert "r_max=1 r_min_ratio=0 theta_max=6.28 input_scaling=1" in evolve.stdout  # reference
    test = subprocess.run(
        [*run, "test", "--study-name", "rtu", "--storage", storage, "--training-steps", "300",
         "--seeds", "10", "--agents", "rtu-res-ppo", "random-rtu-res-ppo",
         "--out", str(tmp_path / "test")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert test.returncode == 0, test.stderr
    summary = (tmp_path / "test" / "summary.csv").read_text()
    assert "rtu-res-ppo" in summary and "random-rtu-res-ppo" in summary
    refused = subprocess.run(
        [*run, "test", "--study-name", "rtu", "--storage", storage, "--training-steps", "300",
         "--seeds", "10", "--agents", "res-ppo", "--out", str(tmp_path / "refused")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert refused.returncode == 2
    assert refused.stderr.strip().count("\n") == 0 and "--encoder reservoir" in refused.stderr


def test_the_test_phase_trains_rtu_ppo_next_to_ppo_with_its_own_flag(tmp_path: Path) -> None:
    """``--agents ppo rtu-ppo res-ppo`` on an ESN study; --no-stale-gradient reaches rtu-ppo only,
    and evolve refuses it for another learner in one line."""
    import json

    storage = f"sqlite:///{tmp_path / 'esn.db'}"
    run = [sys.executable, "-m", "ermrl"]
    evolve = subprocess.run(
        [*run, "evolve", "--env-id", "CartPole-v1", "--observe", "positions", "--units", "10",
         "--n-trials", "1", "--n-seeds", "1", "--training-steps", "300", "--storage", storage,
         "--study-name", "esn"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert evolve.returncode == 0, evolve.stderr
    test = subprocess.run(
        [*run, "test", "--study-name", "esn", "--storage", storage, "--training-steps", "300",
         "--seeds", "10", "--agents", "ppo", "rtu-ppo", "res-ppo", "--no-stale-gradient",
         "--ppo", "d_rec=8", "--out", str(tmp_path / "test")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    # d_rec is rtu-ppo's own setting: --ppo gives it to every agent, and PPO refuses it.
    assert test.returncode == 2 and "d_rec" in test.stderr, test.stderr
    test = subprocess.run(
        [*run, "test", "--study-name", "esn", "--storage", storage, "--training-steps", "300",
         "--seeds", "10", "--agents", "ppo", "rtu-ppo", "res-ppo", "--no-stale-gradient",
         "--out", str(tmp_path / "test")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert test.returncode == 0, test.stderr
    settings = {
        p.parent.parent.name: json.loads(p.read_text())
        for p in (tmp_path / "test").rglob("settings.json")
    }
    assert set(settings) == {"ppo", "rtu-ppo", "res-ppo"}, settings.keys()
    assert settings["rtu-ppo"]["ppo"]["learner"] == "rtu-ppo"
    assert settings["rtu-ppo"]["ppo"]["hyperparams"]["stale_gradient"] is False
    assert "stale_gradient" not in settings["ppo"]["ppo"]["hyperparams"]
    refused = subprocess.run(
        [*run, "evolve", "--env-id", "CartPole-v1", "--no-stale-gradient", "--storage", storage],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert refused.returncode == 2
    assert refused.stderr.strip().endswith("--stale-gradient applies to --learner rtu-ppo only")


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--r-max-range", "0.5", "1.5"], "the r_max range must stay within (0, 1]"),
        (["--units", "6000"], "at most 10000 state values"),
        (["--theta-max-range", "2", "1"], "low must be < high"),
    ],
)
def test_bad_rtu_settings_are_refused_in_one_line_before_any_storage_exists(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], message: str
) -> None:
    from ermrl.cli._evolve import evolve_main

    db = tmp_path / "x.db"
    with pytest.raises(SystemExit) as exit_:
        evolve_main(["--env-id", "CartPole-v1", "--encoder", "rtu", *flags,
                     "--storage", f"sqlite:///{db}"])  # fmt: skip
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not db.exists()
