"""The ``hebbian`` learner: leak factors, the rule's gradient, its bookkeeping, and ermrl's plumbing."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import DummyVecEnv

from ermrl.agents import (
    check_ppo_config,
    load_policy,
    make_vec_env,
    resolve_ppo_config,
    train_agent,
    with_overrides,
)
from ermrl.config import BudgetConfig, ConfigError, TaskConfig
from ermrl.learners._hebbian import HebbianLearner
from ermrl.learners._hebbian_model import HebbianAgent, load_npz

HEBBIAN = HebbianLearner()
PENDULUM = TaskConfig("Pendulum-v1", "positions")


def settings(env_id: str = "Pendulum-v1", **overrides: Any) -> dict[str, Any]:
    config = resolve_ppo_config(env_id, overrides, learner="hebbian")
    return HEBBIAN.settings(config)


class ContextBandit(gym.Env[np.ndarray, np.ndarray]):
    """A two-armed contextual bandit: context +-1, arm = sign of the action, reward 1 when the arm
    matches the context; one step per episode (or ``length`` steps with a new context each)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, length: int = 1) -> None:
        self.length = length

    def _context(self) -> np.ndarray:
        self.context = float(self.np_random.choice([-1.0, 1.0]))
        return np.array([self.context], np.float32)

    def reset(self, *, seed: int | None = None, options: Any = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t = 0
        return self._context(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        reward = float(np.sign(action[0]) == self.context)
        self.t += 1
        return self._context(), reward, self.t >= self.length, False, {}


def bandit_agent(n_envs: int, seed: int = 0, length: int = 1, **overrides: Any) -> HebbianAgent:
    env = DummyVecEnv([lambda: ContextBandit(length)] * n_envs)
    env.seed(seed)
    base = {"units": 20, "input_scaling": 1.0, "spectral_radius": 0.5}
    return HebbianAgent(env, settings(**{**base, **overrides}), seed=seed)


def test_leak_factors_are_exp_minus_dt_over_tau_log_uniform() -> None:
    for tau_min, tau_max, dt in ((2.5, 10.0, 1.0), (1.0, 100.0, 0.5)):
        agent = bandit_agent(1, units=50, tau_min=tau_min, tau_max=tau_max, dt=dt)
        alpha = agent.policy.alpha
        tau = -dt / np.log(alpha)
        assert tau.min() == pytest.approx(tau_min) and tau.max() == pytest.approx(tau_max)
        np.testing.assert_allclose(np.diff(np.log(np.sort(tau))), math.log(tau_max / tau_min) / 49)
    # The original fed natural logs to np.logspace: tau ~ 1e-6 and alpha ~ 0 (no memory).
    defaults = bandit_agent(1, units=500).policy.alpha
    assert np.exp(-1 / 2.5) == pytest.approx(defaults.min()) and defaults.max() < 0.91


def test_recurrent_weights_have_the_spectral_radius_and_a_zero_diagonal() -> None:
    J = bandit_agent(1, units=60, spectral_radius=0.8).policy.J
    assert np.all(np.diag(J) == 0.0)
    assert np.max(np.abs(np.linalg.eigvals(J))) == pytest.approx(0.8)
    same = bandit_agent(1, units=60, spectral_radius=0.8).policy.J
    assert np.array_equal(J, same)  # the agent seed fixes the weights


def true_gradient(agent: HebbianAgent) -> np.ndarray:
    """d E[reward] / d J_out of the bandit: P(correct | c) = Phi(c mu(c) / sigma)."""
    sigma = agent.settings["sigma"]
    gradient = np.zeros_like(agent.policy.J_out)
    for context in (-1.0, 1.0):
        h = agent.policy.recur(np.zeros((1, agent.policy.J.shape[0])), np.array([[context]]))
        mu = agent.policy.mean(h)[0]
        density = np.exp(-0.5 * (mu / sigma) ** 2) / math.sqrt(2 * math.pi)
        gradient += 0.5 * (context * density / sigma * (1 - mu**2))[:, None] * h
    return gradient


@pytest.mark.parametrize("baseline", ["mean", "critic", "none"])
def test_the_expected_update_climbs_the_policy_gradient(baseline: str) -> None:
    # A bias and saturating inputs: h(+1) and h(-1) are not opposite; mu is away from 0.
    agent = bandit_agent(
        64, seed=1, baseline=baseline, bias_scaling=1.0, readout_scaling=0.5, input_scaling=3.0
    )
    updates: list[np.ndarray] = []

    def record() -> None:  # keep J_out fixed: collect G instead of applying it
        updates.append(agent.G / agent.n_envs)
        agent.G[...] = 0.0

    agent._apply_update = record  # type: ignore[method-assign]
    agent.learn(64 * 100)
    assert len(updates) == 100
    expected, truth = np.mean(updates, axis=0), true_gradient(agent)
    cosine = float(np.sum(expected * truth) / np.linalg.norm(expected) / np.linalg.norm(truth))
    assert cosine > 0.95
    # Unbiased, not just aligned: the 1/sigma^2 factor is there and each step counts once.
    assert np.linalg.norm(expected - truth) < 0.15 * np.linalg.norm(truth)


class DelayedBandit(gym.Env[np.ndarray, np.ndarray]):
    """A two-step MDP: context +-1 at step 0 (reward 0); the second observation says whether the
    first action's sign matched the context (+1) or not (-1); step 1 pays 1 if it did, and ends."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed: int | None = None, options: Any = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.t = 0
        self.context = float(self.np_random.choice([-1.0, 1.0]))
        return np.array([self.context], np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self.t == 0:
            self.t, self.correct = 1, bool(np.sign(action[0]) == self.context)
            return np.array([1.0 if self.correct else -1.0], np.float32), 0.0, False, False, {}
        return np.array([self.context], np.float32), float(self.correct), True, False, {}


@pytest.mark.parametrize("baseline", ["critic", "td"])
def test_the_critics_expected_update_is_the_discounted_policy_gradient(baseline: str) -> None:
    """Actor-critic with eligibility traces (Sutton and Barto 2018, 13.6) on a two-step MDP.

    With lambda = 1 the actor's trace decays by gamma, so each step's eligibility psi_k h_k is
    modulated by sum_{t>=k} gamma^(t-k) delta_t = G_k - V(h_k): unbiased for any critic. The
    only reward is gamma r_1, set by a_0, so E[update] = gamma dP(correct)/dJ_out, whatever
    the (fixed, wrong) critic says. The old rules were not: ``critic`` modulated psi_0 h_0 by
    r_1 - V(h_1), and V(h_1) depends on a_0; ``td`` decayed the trace by lambda, not gamma lambda.
    """
    gamma = 0.5
    env = DummyVecEnv([DelayedBandit] * 64)
    env.seed(1)
    config = {"units": 20, "spectral_radius": 0.5, "bias_scaling": 1.0, "readout_scaling": 0.5}
    config |= {"input_scaling": 3.0, "baseline": baseline, "trace_decay": 1.0, "gamma": gamma}
    agent = HebbianAgent(env, settings(**config, critic_lr=1e-300), seed=1)
    critic = np.random.default_rng(0).normal(0.0, 1.0, agent.policy.critic_w.shape)
    agent.policy.critic_w[...] = critic  # a fixed critic (critic_lr ~ 0) whose V(h_1) varies
    agent.policy.critic_b[...] = 0.3
    updates: list[np.ndarray] = []

    def record() -> None:  # keep J_out fixed: collect G instead of applying it
        updates.append(agent.G / agent.n_envs)
        agent.G[...] = 0.0

    agent._apply_update = record  # type: ignore[method-assign]
    agent.learn(64 * 2 * 1000)
    assert len(updates) == 1000  # one update per episode end (every env ends at step 2)
    np.testing.assert_array_equal(agent.policy.critic_w, critic)
    expected, truth = np.mean(updates, axis=0), gamma * true_gradient(agent)
    assert np.linalg.norm(expected - truth) < 0.15 * np.linalg.norm(truth)


def success_rate(agent: HebbianAgent) -> float:
    """Expected success of the stochastic policy over both contexts."""
    sigma = agent.settings["sigma"]
    rates = []
    for context in (-1.0, 1.0):
        h = agent.policy.recur(np.zeros((1, agent.policy.J.shape[0])), np.array([[context]]))
        mu = float(agent.policy.mean(h)[0, 0])
        rates.append(0.5 * (1 + math.erf(context * mu / sigma / math.sqrt(2))))
    return float(np.mean(rates))


def test_a_short_training_solves_the_contextual_bandit() -> None:
    agent = bandit_agent(16, seed=2, learning_rate=0.02)
    assert abs(success_rate(agent) - 0.5) < 0.1
    agent.learn(16 * 150)
    assert success_rate(agent) > 0.95


class Recorder(BaseCallback):
    def __init__(self) -> None:
        super().__init__()
        self.steps: list[dict[str, Any]] = []

    def _on_step(self) -> bool:
        local = self.locals
        self.steps.append(
            {k: np.array(local[k]) for k in ("h_start", "mu", "actions", "reward", "dones")}
        )
        return True


@pytest.mark.parametrize("baseline", ["none", "mean"])
def test_the_eligibility_counts_each_step_once(baseline: str) -> None:
    sigma, decay, lam = 0.5, 0.9, 0.8
    agent = bandit_agent(
        1,
        seed=3,
        length=50,
        sigma=sigma,
        trace_decay=lam,
        baseline=baseline,
        baseline_decay=decay,
        update_every=1000,
    )
    recorder = Recorder()
    agent.learn(6, callback=recorder)
    assert recorder.num_timesteps == 6 and not any(s["dones"].any() for s in recorder.steps)
    e = np.zeros_like(agent.G)
    G = np.zeros_like(agent.G)
    total = weight = 0.0
    for s in recorder.steps:
        a, mu, h, r = s["actions"][0], s["mu"][0], s["h_start"][0], float(s["reward"][0])
        e = lam * e + np.outer((a - mu) * (1 - mu**2) / sigma**2, h)
        b = total / weight if baseline == "mean" and weight else 0.0
        G += (r - b) * e
        total, weight = decay * total + (1 - decay) * r, decay * weight + (1 - decay)
    np.testing.assert_allclose(agent.G, G, rtol=1e-10, atol=1e-14)
    assert np.abs(G).max() > 0


def test_non_finite_weights_are_reported_as_nan() -> None:
    agent = bandit_agent(2)
    agent.policy.J_out[0, 0] = np.nan
    with pytest.raises(ValueError, match="nan"):
        agent.learn(10)


def test_training_through_train_agent_saves_plain_arrays_that_reload(tmp_path: Path) -> None:
    ppo = resolve_ppo_config("Pendulum-v1", {"units": 40}, learner="hebbian")
    budget = BudgetConfig(training_steps=600, n_last_episodes=2)
    result = train_agent(PENDULUM, None, ppo, budget, 5, model_path=tmp_path / "model.zip")
    again = train_agent(PENDULUM, None, ppo, budget, 5)
    assert len(result.episode_returns) == 3 and result.episode_steps == [200, 400, 600]
    assert result.episode_returns == again.episode_returns
    assert result.env_steps == 600 and math.isfinite(result.last_return)
    config, arrays = load_npz((tmp_path / "model.zip").read_bytes())  # no pickle allowed
    assert config["num_timesteps"] == 600 and config["adam_t"] == 3
    assert config["settings"]["units"] == 40 and arrays["J_out"].shape == (1, 40)

    env = make_vec_env(PENDULUM, 1, 0)
    model = load_policy(tmp_path / "policy.pt", ppo, env)
    for name in ("J", "J_in", "b", "alpha", "J_out"):
        assert np.array_equal(getattr(model.policy, name), arrays[name]), name
    obs = env.reset()
    # The recurrence and the readout by hand, from the saved arrays; actions scaled to [-2, 2].
    h = np.zeros((1, 40))
    state = None
    for step in range(3):
        h = arrays["alpha"] * h + (1 - arrays["alpha"]) * np.tanh(
            h @ arrays["J"].T + obs @ arrays["J_in"].T + arrays["b"]
        )
        expected = 2.0 * np.clip(np.tanh(h @ arrays["J_out"].T), -1, 1)
        action, state = model.predict(
            obs, state=state, episode_start=np.array([step == 0]), deterministic=True
        )
        np.testing.assert_allclose(action, expected, rtol=1e-5)
        np.testing.assert_allclose(state, h, rtol=1e-10)
        obs, _, _, _ = env.step(action)
    env.close()


@pytest.mark.slow
def test_a_tiny_ant_run_learns_from_the_x_velocity(tmp_path: Path) -> None:
    task = TaskConfig("Ant-v5", "positions")
    ppo = resolve_ppo_config(
        "Ant-v5", {"units": 16, "reward": "x_velocity", "update_every": 50}, learner="hebbian"
    )
    budget = BudgetConfig(training_steps=300, fitness="eval", n_eval_episodes=1)
    result = train_agent(task, None, ppo, budget, 0, model_path=tmp_path / "model.zip")
    assert result.env_steps == 300 and math.isfinite(result.eval_return or math.nan)
    config, arrays = load_npz((tmp_path / "model.zip").read_bytes())
    assert config["adam_t"] == 6 and arrays["J_out"].shape == (8, 16)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ({"units": 0}, r"hebbian units must be a whole number in \[1, 4096\], got 0"),
        ({"sigma": 0}, "hebbian sigma must be > 0, got 0"),
        ({"trace_decay": 1.5}, "hebbian trace_decay must be >= 0 and <= 1, got 1.5"),
        ({"tau_min": 5.0, "tau_max": 2.0}, r"hebbian tau_max \(2\) must be >= tau_min \(5\)"),
        ({"baseline": "median"}, "hebbian baseline must be one of none, mean, critic, td"),
        ({"reward": "speed"}, "hebbian reward must be one of task, x_velocity"),
        ({"adam_betas": [0.9, 1.0]}, r"hebbian adam_betas must be two numbers in \[0, 1\)"),
        ({"update_every": -1}, "hebbian update_every must be a whole number >= 0"),
        ({"n_steps": 64}, "learner 'hebbian' does not take n_steps"),
    ],
)
def test_bad_settings_are_refused_in_one_line(override: dict[str, Any], message: str) -> None:
    config = with_overrides(resolve_ppo_config("Pendulum-v1", learner="hebbian"), override)
    with pytest.raises(ConfigError, match=message) as err:
        check_ppo_config(PENDULUM, None, config)
    assert "\n" not in str(err.value)


def test_other_learners_refuse_hebbian_settings() -> None:
    ppo = with_overrides(resolve_ppo_config("Pendulum-v1"), {"units": 5})
    with pytest.raises(ConfigError, match="learner 'ppo' does not take units"):
        check_ppo_config(PENDULUM, None, ppo)


class DiscreteBandit(ContextBandit):
    """The contextual bandit with two discrete arms: arm 1 is right for context +1."""

    action_space = gym.spaces.Discrete(2)  # type: ignore[assignment]

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        reward = float((2 * int(action) - 1) == self.context)
        self.t += 1
        return self._context(), reward, self.t >= self.length, False, {}


def test_discrete_actions_follow_the_softmax_policy_gradient() -> None:
    def agent_for(seed: int, **overrides: Any) -> HebbianAgent:
        env = DummyVecEnv([DiscreteBandit] * 64)
        env.seed(seed)
        base = {"units": 20, "input_scaling": 3.0, "bias_scaling": 1.0, "readout_scaling": 0.5}
        return HebbianAgent(env, settings(**{**base, **overrides}), seed=seed)

    agent = agent_for(1)
    updates: list[np.ndarray] = []

    def record() -> None:
        updates.append(agent.G / agent.n_envs)
        agent.G[...] = 0.0

    agent._apply_update = record  # type: ignore[method-assign]
    agent.learn(64 * 100)
    truth = np.zeros_like(agent.G)  # d/dJ_out of 0.5 sum_c p_c(right arm)
    for context in (-1.0, 1.0):
        h = agent.policy.recur(np.zeros((1, 20)), np.array([[context]]))
        p = agent.policy.probabilities(h)[0]
        right = int(context > 0)
        truth += 0.5 * p[right] * np.outer(np.eye(2)[right] - p, h[0])
    expected = np.mean(updates, axis=0)
    assert np.linalg.norm(expected - truth) < 0.15 * np.linalg.norm(truth)

    trained = agent_for(2, learning_rate=0.02)
    trained.learn(64 * 100)
    obs = np.array([[1.0], [-1.0]])
    actions, _ = trained.predict(obs, deterministic=True)
    assert actions.tolist() == [1, 0]
    sampled, _ = trained.predict(np.repeat(obs, 200, axis=0))
    assert np.mean(sampled[:200] == 1) > 0.9 and np.mean(sampled[200:] == 0) > 0.9


def test_cartpole_trains_through_train_agent(tmp_path: Path) -> None:
    task = TaskConfig("CartPole-v1", "all")
    ppo = resolve_ppo_config("CartPole-v1", {"units": 20}, learner="hebbian", n_envs=2)
    budget = BudgetConfig(training_steps=400, fitness="eval", n_eval_episodes=1)
    result = train_agent(task, None, ppo, budget, 0, model_path=tmp_path / "model.zip")
    assert result.episode_returns and result.eval_return is not None
    env = make_vec_env(task, 1, 0)
    model = load_policy(tmp_path / "policy.pt", ppo, env)
    action, state = model.predict(env.reset(), deterministic=True)
    assert action.dtype == np.int64 and action.shape == (1,) and state.shape == (1, 20)
    env.close()
