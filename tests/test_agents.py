"""The inner loop: hyperparameter resolution, env pipeline, seeded PPO training."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

from ermrl.agents import (
    NoEpisodeFinished,
    TrainingDiverged,
    derive_seeds,
    load_hyperparams_table,
    make_vec_env,
    parse_overrides,
    ppo_kwargs,
    resolve_ppo_config,
    train_agent,
)
from ermrl.config import (
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    PPOConfig,
    ReservoirParams,
    TaskConfig,
)
from ermrl.encoders import ReservoirVecEnv

TINY_PPO = PPOConfig(n_envs=1, hyperparams={"n_steps": 128, "batch_size": 64, "n_epochs": 2})
SMALL_ENCODER = EncoderConfig(reservoirs=(ReservoirParams(units=20, sr=0.9, lr=0.5),))


class NaNAfterEnv(gym.Env):
    """Emits NaN observations after a few steps: training must fail cleanly."""

    observation_space = gym.spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)

    def __init__(self, render_mode: str | None = None) -> None:
        self.render_mode = render_mode
        self.t = 0

    def reset(self, *, seed=None, options=None):  # noqa: ANN001
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(3, np.float32), {}

    def step(self, action):  # noqa: ANN001
        self.t += 1
        obs = np.full(3, np.nan if self.t > 20 else 0.1, np.float32)
        return obs, 1.0, False, self.t >= 50, {}


if "ErmrlNaN-v0" not in gym.registry:
    gym.register("ErmrlNaN-v0", entry_point=NaNAfterEnv)


def test_packaged_table_defaults_are_sb3_for_mujoco() -> None:
    table = load_hyperparams_table()
    assert table["default"] == {}
    assert "HalfCheetah-v5" not in table  # the paper used SB3 defaults
    cfg = resolve_ppo_config("HalfCheetah-v5")
    assert cfg.n_envs == 1 and dict(cfg.hyperparams) == {}


def test_table_entry_and_overrides_merge() -> None:
    cfg = resolve_ppo_config("Pendulum-v1", parse_overrides(["learning_rate=1e-4", "gamma=0.95"]))
    assert cfg.n_envs == 4  # from the table
    assert cfg.hyperparams["learning_rate"] == pytest.approx(1e-4)  # override wins
    assert cfg.hyperparams["gae_lambda"] == 0.95  # table value kept
    assert resolve_ppo_config("Pendulum-v1", n_envs=2).n_envs == 2


def test_overrides_are_validated() -> None:
    with pytest.raises(ConfigError, match="unknown PPO hyperparameter"):
        parse_overrides(["lerning_rate=1e-3"])
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        parse_overrides(["learning_rate"])
    assert parse_overrides(["use_sde=true", "policy_kwargs={net_arch: [32, 32]}"]) == {
        "use_sde": True,
        "policy_kwargs": {"net_arch": [32, 32]},
    }


def test_linear_schedule_strings_become_callables(tmp_path) -> None:  # noqa: ANN001
    cfg = resolve_ppo_config("CartPole-v1")
    kwargs = ppo_kwargs(cfg)
    assert callable(kwargs["learning_rate"]) and kwargs["learning_rate"](0.5) == pytest.approx(5e-4)
    bad = tmp_path / "bad.yml"
    bad.write_text("Pendulum-v1: {n_stepz: 3}\n")
    with pytest.raises(ConfigError, match="n_stepz"):
        load_hyperparams_table(bad)


def test_derived_seeds_are_independent_and_stable() -> None:
    a, b = derive_seeds(0), derive_seeds(1)
    assert a == derive_seeds(0)
    assert len({a.reservoir, a.env, a.agent, a.eval_env}) == 4
    assert a != b


@pytest.mark.parametrize(
    "env_id",
    [
        "CartPole-v1",
        "Pendulum-v1",
        "MountainCarContinuous-v0",
        "LunarLander-v3",
        *[
            f"{name}-{v}"
            for name in ("Ant", "HalfCheetah", "Swimmer", "Hopper", "Walker2d")
            for v in ("v4", "v5")
        ],
    ],
)
def test_encoded_env_runs_on_every_supported_task(env_id: str) -> None:
    observe = "velocities"
    env = make_vec_env(TaskConfig(env_id, observe), 2, 0, SMALL_ENCODER, reservoir_seed=1)
    assert isinstance(env, ReservoirVecEnv)
    obs = env.reset()
    assert obs.shape == (2, 20) and obs.dtype == np.float32
    for _ in range(5):
        actions = np.array([env.action_space.sample() for _ in range(2)])
        obs, rewards, dones, infos = env.step(actions)
        assert np.all(np.isfinite(obs)) and np.all(np.abs(obs) <= 1)
    # the action really reaches the reservoir input
    action_block = env.get_inputs()[:, env.obs_dim : env.obs_dim + env.act_dim]
    assert np.any(action_block != 0)
    env.close()


def test_same_seed_same_returns_different_seed_differs() -> None:
    task = TaskConfig("Pendulum-v1", "positions")
    budget = BudgetConfig(training_steps=512, n_last_episodes=2)
    a = train_agent(task, SMALL_ENCODER, TINY_PPO, budget, seed=3)
    b = train_agent(task, SMALL_ENCODER, TINY_PPO, budget, seed=3)
    c = train_agent(task, SMALL_ENCODER, TINY_PPO, budget, seed=4)
    assert a.episode_returns == b.episode_returns and a.last_return == b.last_return
    assert a.episode_returns != c.episode_returns
    assert a.env_steps == 512 and len(a.episode_returns) == 2  # Pendulum: 200-step episodes
    assert a.last_return == pytest.approx(np.mean(a.episode_returns[-2:]))
    assert a.steps_per_second > 0


def test_eval_fitness_runs_deterministic_episodes(tmp_path) -> None:  # noqa: ANN001
    task = TaskConfig("CartPole-v1", "positions")
    budget = BudgetConfig(training_steps=256, fitness="eval", n_eval_episodes=3)
    result = train_agent(
        task, SMALL_ENCODER, TINY_PPO, budget, seed=0, model_path=tmp_path / "m.zip"
    )
    assert len(result.eval_returns) == 3 and result.eval_return == pytest.approx(
        np.mean(result.eval_returns)
    )
    assert result.fitness("eval") == result.eval_return
    assert (tmp_path / "m.zip").exists()


def test_plain_ppo_without_encoder() -> None:
    result = train_agent(
        TaskConfig("CartPole-v1"), None, TINY_PPO, BudgetConfig(training_steps=256), seed=0
    )
    assert result.episode_returns and math.isfinite(result.last_return)


def test_nan_training_raises_training_diverged() -> None:
    with pytest.raises(TrainingDiverged):
        train_agent(
            TaskConfig("ErmrlNaN-v0"), None, TINY_PPO, BudgetConfig(training_steps=256), seed=0
        )


def test_no_finished_episode_is_a_clear_error() -> None:
    with pytest.raises(NoEpisodeFinished, match="raise --training-steps"):
        train_agent(
            TaskConfig("HalfCheetah-v5"), None, TINY_PPO, BudgetConfig(training_steps=128), seed=0
        )
