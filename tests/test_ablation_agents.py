"""The ablation agents of a reservoir study: ``leaky-res-ppo`` (the selected reservoir with
``W = 0``) and ``ema-ppo`` (the reservoir's input next to its moving average at the selected
leak rate).

Each computes its equation, on both backends, and trains in a test phase next to ``res-ppo``.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from ermrl.agents import make_vec_env
from ermrl.config import EncoderConfig, PPOConfig, ReservoirParams, TaskConfig
from ermrl.encoders import ReservoirBank, ReservoirEncoder
from ermrl.learners import AGENT_KINDS
from ermrl.population import PopulationEnvs
from ermrl.test_phase import TestSettings, agent_specs, run_comparison

# A reservoir as evolution selects them: small spectral radius, a leak rate below 1, a bias.
SELECTED = ReservoirParams(units=6, sr=0.05, lr=0.3, input_scaling=0.7, bias_scaling=0.2)
LEAKY = dataclasses.replace(SELECTED, ablation="leaky")
EMA = dataclasses.replace(SELECTED, ablation="ema")


def bank(params: ReservoirParams, input_dim: int, seed: int, **options: Any) -> ReservoirBank:
    """The bank a float64 encoder of ``params`` steps (what either backend builds)."""
    config = EncoderConfig(reservoirs=(params,), dtype="float64", **options)
    return ReservoirEncoder().bank(config, input_dim, seed)


def test_the_agents_take_the_selected_reservoir_with_its_ablation() -> None:
    for name in ("leaky-res-ppo", "ema-ppo"):  # asked for, never trained by default
        kind = AGENT_KINDS[name]
        assert kind.reservoirs == "evolved" and kind.family == "esn" and not kind.default
    specs = agent_specs(
        ["res-ppo", "leaky-res-ppo", "ema-ppo"], evolved=(SELECTED,), unevolved=(ReservoirParams(),)
    )
    assert [s.reservoirs for s in specs] == [(SELECTED,), (LEAKY,), (EMA,)]


def test_leaky_res_ppo_is_the_selected_reservoir_without_recurrence() -> None:
    """``x <- (1 - lr) x + lr tanh(Win u + b)`` with the selected reservoir's own ``Win`` and
    ``b`` (the same seed draws them), ``W`` zero."""
    full, leaky = bank(SELECTED, 3, seed=5), bank(LEAKY, 3, seed=5)
    np.testing.assert_array_equal(leaky.Win_T, full.Win_T)
    np.testing.assert_array_equal(leaky.bias, full.bias)
    assert np.any(full.W_T) and not np.any(leaky.W_T) and np.any(full.bias)
    Win, b, lr = full.Win_T.T, full.bias, SELECTED.lr
    inputs = np.random.default_rng(0).normal(size=(5, 3))
    x, expected = np.zeros(6), []
    for u in inputs:
        x = (1 - lr) * x + lr * np.tanh(Win @ u + b)
        expected.append(x)
    np.testing.assert_allclose(leaky.run(inputs), expected, rtol=1e-12, atol=1e-15)
    assert not np.allclose(full.run(inputs), expected)  # the recurrence did matter


def test_ema_ppo_is_the_input_next_to_its_moving_average_shown_as_it_is() -> None:
    """``e <- (1 - lr) e + lr u`` per input; the policy sees ``[e; u]`` whole (no tanh; the
    study's ``exposed_units`` concerns reservoir units, not these), unbounded."""
    ema = bank(EMA, 4, seed=5, exposed_units=2)
    inputs = np.random.default_rng(1).normal(scale=3.0, size=(5, 4))
    e, expected = np.zeros(4), []
    for u in inputs:
        e = (1 - EMA.lr) * e + EMA.lr * u
        expected.append(np.concatenate([e, u]))
    states = ema.run(inputs)
    np.testing.assert_allclose(states, expected, rtol=1e-12, atol=1e-15)
    emit, width = ema.emitter(2)
    assert width == 8 and ema.out_bound == np.inf
    np.testing.assert_array_equal(emit(states), np.asarray(expected, np.float32))
    assert np.abs(states).max() > 1  # no tanh


def test_ema_ppo_averages_observation_action_and_reward_and_resets_with_episodes() -> None:
    """Through the sb3 wrapper on CartPole: the EMA of ``v = [observation, one-hot previous
    action, previous reward]`` next to ``v`` itself, the EMA zeroed at each episode start (the
    first input has no action or reward)."""
    task = TaskConfig("CartPole-v1", "all")
    venv = make_vec_env(task, 1, 3, EncoderConfig(reservoirs=(EMA,), dtype="float64"), 7)
    raw = make_vec_env(task, 1, 3, None, 0)  # the same env, unencoded
    lr = EMA.lr
    rng = np.random.default_rng(0)
    obs, plain = venv.reset(), raw.reset()
    v = np.concatenate([plain[0], [0.0, 0.0], [0.0]])
    e = lr * v
    np.testing.assert_allclose(obs[0], np.concatenate([e, v]), rtol=1e-6)
    ends = 0
    for _ in range(60):
        action = rng.integers(0, 2, 1)
        obs, _, done, infos = venv.step(action)
        plain, reward, raw_done, _ = raw.step(action)
        assert done == raw_done
        if done[0]:
            ends += 1
            v = np.concatenate([plain[0], [0.0, 0.0], [0.0]])
            e = lr * v
        else:
            v = np.concatenate([plain[0], np.eye(2)[action[0]], reward])
            e = (1 - lr) * e + lr * v
        expected = np.concatenate([e, v]).astype(np.float32)
        np.testing.assert_allclose(obs[0], expected, rtol=1e-6, atol=1e-7)
    assert ends > 0
    venv.close()
    raw.close()


@pytest.mark.parametrize("params", [LEAKY, EMA], ids=["leaky", "ema"])
@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
def test_the_population_backend_encodes_as_the_sb3_wrapper(
    params: ReservoirParams, env_id: str
) -> None:
    """Two agents (different leak rates) stepped in one population see, step by step, what
    their own sb3 wrapper shows (over episode ends on CartPole)."""
    task = TaskConfig(env_id, "all")
    encoders = [
        EncoderConfig(reservoirs=(dataclasses.replace(params, lr=lr),), skip_connection=skip)
        for lr, skip in ((0.3, False), (0.8, False))
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


def test_the_agents_are_listed_in_the_test_commands_help(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "ermrl", "test", "--help"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        check=True,
    )
    assert "leaky-res-ppo:" in done.stdout and "ema-ppo:" in done.stdout


@pytest.mark.parametrize("backend", ["population", "sb3"])
def test_a_test_phase_trains_them_next_to_res_ppo(backend: str, tmp_path: Path) -> None:
    names = ["res-ppo", "leaky-res-ppo", "ema-ppo"]
    selected = (ReservoirParams(units=20, sr=0.01, lr=0.4),)
    agents = agent_specs(names, evolved=selected, unevolved=(ReservoirParams(units=20),))
    summary = run_comparison(
        TaskConfig("CartPole-v1", "positions"),
        EncoderConfig(reservoirs=selected),
        PPOConfig(hyperparams={"n_steps": 64, "batch_size": 64, "n_epochs": 1}, backend=backend),
        agents,
        TestSettings(training_steps=1024, seeds=(0,), out=tmp_path, save_models=False),
        quiet=True,
    )
    assert sorted(summary["agent"]) == sorted(names)
    for name in names:
        result = json.loads((tmp_path / "agents" / name / "seed_0" / "result.json").read_text())
        assert result["agent"] == name and np.isfinite(result["final_return"])
    stored = yaml.safe_load((tmp_path / "config.yaml").read_text())["agents"]
    assert [r.get("ablation") for r in (stored[n][0] for n in names)] == [None, "leaky", "ema"]
    for name, ablation in zip(names, [None, "leaky", "ema"]):  # each trained on its own
        run = json.loads((tmp_path / "agents" / name / "seed_0" / "settings.json").read_text())
        assert run["encoder"]["reservoirs"][0].get("ablation") == ablation
