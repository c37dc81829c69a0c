"""The rtu-ppo learner: real-time PPO with RTUs, trained through ermrl's own entry points."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch as th

from ermrl.agents import (
    check_ppo_config,
    load_policy,
    make_vec_env,
    resolve_ppo_config,
    train_agent,
)
from ermrl.agents._train import save_trained
from ermrl.config import BudgetConfig, ConfigError, PPOConfig, TaskConfig
from ermrl.learners import get_learner, learner_names
from ermrl.learners._rtu import RTUPPO, RTUCarry

PENDULUM = TaskConfig("Pendulum-v1")
CARTPOLE = TaskConfig("CartPole-v1")
TINY = {"n_steps": 64, "batch_size": 16, "n_epochs": 2, "d_rec": 8}
BUDGET = BudgetConfig(training_steps=256, fitness="last", n_last_episodes=1)


def tiny(env_id: str = "Pendulum-v1", **extra: Any) -> PPOConfig:
    return resolve_ppo_config(env_id, {**TINY, **extra}, learner="rtu-ppo")


def _model(task: TaskConfig, ppo: PPOConfig, seed: int = 0) -> RTUPPO:
    model = get_learner("rtu-ppo").build(make_vec_env(task, ppo.n_envs, seed), ppo, seed=seed)
    assert isinstance(model, RTUPPO)
    return model


def _collect(model: RTUPPO, steps: int) -> None:
    """One rollout of ``steps`` steps per env, without training."""
    _, callback = model._setup_learn(steps, None, reset_num_timesteps=model.num_timesteps == 0)
    assert model.env is not None
    assert model.collect_rollouts(model.env, callback, model.rollout_buffer, steps)


def _assert_carries_follow_the_rollout(model: RTUPPO) -> None:
    """Stored carry t+1 is one step of the current network from carry t, zero at a start."""
    buffer = model.rollout_buffer
    starts = buffer.episode_starts
    with th.no_grad():
        for step in range(buffer.buffer_size - 1):
            obs = th.as_tensor(buffer.observations[step])
            _, after = model.policy.trunk(obs, buffer.carry_at(step))
            expected = after.reset(th.as_tensor(starts[step + 1]))
            for name, want, have in zip(RTUCarry._fields, expected, buffer.carry_at(step + 1)):
                th.testing.assert_close(have, want, rtol=1e-5, atol=1e-6, msg=name)


def test_rtu_ppo_is_registered_with_the_papers_settings() -> None:
    assert "rtu-ppo" in learner_names()
    learner = get_learner("rtu-ppo")
    assert learner.recurrent and learner.table == "rtu_ppo.yml"
    ppo = resolve_ppo_config("Ant-v5", learner="rtu-ppo")
    assert ppo.n_envs == 1 and ppo.normalize is not None
    assert ppo.normalize.norm_obs and ppo.normalize.norm_reward
    h = ppo.hyperparams
    assert (h["d_rec"], h["stale_gradient"], h["learning_rate"], h["max_grad_norm"]) == (
        192,
        True,
        1e-4,
        0.5,
    )
    assert (h["n_steps"], h["n_epochs"], h["batch_size"], h["clip_range"]) == (2048, 4, 64, 0.2)
    assert (h["gamma"], h["gae_lambda"]) == (0.99, 0.95)
    model = _model(PENDULUM, resolve_ppo_config("Pendulum-v1", {"n_steps": 64}, learner="rtu-ppo"))
    policy = model.policy
    assert policy.rtu.units == 192 and policy.rtu.input_dim == 64
    assert policy.encoder.in_features == 3 and policy.actor[0].in_features == 2 * 192
    # The official trunk Dense: flax's lecun_normal (truncated at 2 std), zero bias.
    assert policy.encoder.weight.abs().max() <= 2 * (1 / 3) ** 0.5 / 0.8796 + 1e-6
    assert not policy.encoder.bias.any() and not policy.actor[0].bias.any()
    assert policy.optimizer.defaults["eps"] == 1e-5 and policy.optimizer.defaults["lr"] == 1e-4
    assert model.stale_gradient and model.max_grad_norm == 0.5


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ({"d_rec": 0}, r"d_rec must be a whole number in \[1, 4096\], got 0"),
        ({"d_rec": 5000}, "d_rec must be a whole number"),
        ({"d_rec": 8.5}, "d_rec must be a whole number"),
        ({"d_rec": True}, "d_rec must be a whole number"),
        ({"stale_gradient": "no"}, "stale_gradient must be true or false, got 'no'"),
        ({"use_sde": True}, "does not support use_sde"),
    ],
)
def test_bad_settings_are_one_line_config_errors(override: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        check_ppo_config(PENDULUM, None, tiny(**override))
    assert "\n" not in str(err.value)


def test_other_learners_refuse_the_rtu_settings() -> None:
    ppo = resolve_ppo_config("Pendulum-v1", {"d_rec": 8}, learner="ppo")
    with pytest.raises(ConfigError, match=r"learner 'ppo' does not take d_rec"):
        check_ppo_config(PENDULUM, None, ppo)


def test_training_records_episodes_is_seeded_and_stale_gradient_matters(tmp_path: Path) -> None:
    runs = [
        train_agent(PENDULUM, None, tiny(), BUDGET, 5, model_path=tmp_path / "model.zip"),
        train_agent(PENDULUM, None, tiny(), BUDGET, 5),
        train_agent(PENDULUM, None, tiny(stale_gradient=False), BUDGET, 5),
    ]
    first, again, fresh = runs
    assert len(first.episode_returns) == 1 and first.episode_steps == [200]
    assert first.env_steps == 256 and np.isfinite(first.last_return)
    assert first.episode_returns == again.episode_returns  # same seed, same returns
    # Re-scanned carries give other gradients in the second epoch, so other actions.
    assert fresh.episode_returns != first.episode_returns
    assert np.isfinite(fresh.last_return)
    for name in ("model.zip", "policy.pt", "vecnormalize.json"):
        assert (tmp_path / name).is_file(), name


def test_the_saved_policy_reloads_and_acts_identically_with_its_state(tmp_path: Path) -> None:
    ppo = tiny()
    model = _model(PENDULUM, ppo, seed=1)
    model.learn(128)
    save_trained(model, tmp_path / "model.zip", None)
    env = make_vec_env(PENDULUM, 1, 7)
    loaded = load_policy(tmp_path / "policy.pt", ppo, env)
    assert isinstance(loaded, RTUPPO)
    obs = env.reset()
    state_a = state_b = None
    stateful, memoryless = [], []
    for step in range(20):
        start = np.array([step == 0])
        action_a, state_a = model.predict(obs, state_a, start, deterministic=True)
        action_b, state_b = loaded.predict(obs, state_b, start, deterministic=True)
        assert np.array_equal(action_a, action_b) and np.array_equal(state_a, state_b)
        stateful.append(action_a)
        memoryless.append(loaded.predict(obs, None, start, deterministic=True)[0])
        assert state_a.shape == (1, 2, 8)
        obs, _, _, _ = env.step(action_a)
    # The state matters: acting from zeros every step gives other actions.
    assert np.array_equal(stateful[0], memoryless[0])
    assert not np.allclose(np.concatenate(stateful[1:]), np.concatenate(memoryless[1:]))
    # An episode start zeroes the state.
    _, restart = loaded.predict(obs, state_a, np.array([True]), deterministic=True)
    _, fresh = loaded.predict(obs, None, None, deterministic=True)
    assert np.array_equal(restart, fresh)
    env.close()


def test_stored_carries_reset_at_episode_starts_and_run_on_across_rollouts() -> None:
    model = _model(CARTPOLE, tiny("CartPole-v1", n_steps=96), seed=2)
    _collect(model, 96)
    buffer = model.rollout_buffer
    starts = buffer.episode_starts[:, 0].astype(bool)
    assert starts[0] and starts[1:].sum() >= 2  # CartPole's random policy ends episodes fast
    for step in np.flatnonzero(starts):
        assert not any(t.any() for t in buffer.carry_at(int(step)))
    for step in np.flatnonzero(~starts):  # (the theta traces are zero one step after a start)
        assert buffer.carry_at(int(step)).h.any() and buffer.carry_at(int(step)).w.any()
    _assert_carries_follow_the_rollout(model)
    # The next rollout starts from the carry the last one ended with (zero after a done).
    last_obs = th.as_tensor(buffer.observations[-1])
    with th.no_grad():
        _, last = model.policy.trunk(last_obs, buffer.carry_at(buffer.buffer_size - 1))
    _collect(model, 96)
    expected = last.reset(th.as_tensor(buffer.episode_starts[0]))
    for want, have in zip(expected, buffer.carry_at(0)):
        th.testing.assert_close(have, want)


def test_stale_gradient_false_rescans_the_rollout_with_the_new_parameters() -> None:
    model = _model(CARTPOLE, tiny("CartPole-v1", n_steps=96, stale_gradient=False), seed=3)
    _collect(model, 96)
    buffer = model.rollout_buffer
    before = RTUCarry(*(t.clone() for t in buffer.carries))
    with th.no_grad():
        for p in model.policy.rtu.parameters():
            p.add_(0.05 * th.randn_like(p))
    model.refresh_carries()
    _assert_carries_follow_the_rollout(model)
    for old, new in zip(before, buffer.carries):
        assert th.equal(old[0], new[0])  # the rollout's first carry is kept
        assert not th.allclose(old[1:], new[1:])
    # train() re-scans after every epoch but the last; stale_gradient=True never does.
    calls: list[int] = []
    model.refresh_carries = lambda: calls.append(1)  # type: ignore[method-assign]
    model.train()
    assert len(calls) == model.n_epochs - 1
    model.stale_gradient = True
    model.train()
    assert len(calls) == model.n_epochs - 1


def test_a_single_step_minibatch_gets_the_full_rtrl_gradient() -> None:
    """One step from its stored carry gives the RTU parameters the gradient of autograd
    through the whole unrolled episode (parameters fixed, stale gradient)."""
    model = _model(PENDULUM, tiny(), seed=4)
    _collect(model, 64)  # Pendulum's episodes last 200 steps: one episode from step 0
    buffer = model.rollout_buffer
    assert buffer.episode_starts[0, 0] == 1 and not buffer.episode_starts[1:].any()
    policy = model.policy
    picked = [5, 23, 63]
    batch = buffer._get_samples(np.array(picked))
    values, log_prob, _ = policy.evaluate_actions(batch.observations, batch.carries, batch.actions)
    rtu_params = list(policy.rtu.parameters())
    loss_fn = lambda v, lp: (v.flatten() ** 2).sum() - lp.sum()  # noqa: E731
    rtrl = th.autograd.grad(loss_fn(values, log_prob), rtu_params)
    # BPTT: unroll the plain recurrence from the episode's start through every picked step.
    obs = th.as_tensor(buffer.observations[:, 0])
    inputs = policy._input(obs).detach()  # layers below the RTU: not part of this comparison
    h = th.zeros(1, 2, policy.rtu.units)
    total = th.zeros(())
    for step in range(max(picked) + 1):
        latent, h = policy.rtu.state_step(inputs[step : step + 1], h)
        if step in picked:
            dist = policy._distribution(latent)
            action = th.as_tensor(buffer.actions[step])
            total = total + loss_fn(policy.critic(latent), dist.log_prob(action))
    bptt = th.autograd.grad(total, rtu_params)
    for name, want, have in zip(("nu_log", "theta_log", "w1", "w2"), bptt, rtrl):
        assert want.abs().max() > 1e-4, name
        th.testing.assert_close(have, want, rtol=2e-4, atol=1e-5, msg=name)


def test_a_policy_that_outputs_nan_raises_a_value_error() -> None:
    model = _model(PENDULUM, tiny(), seed=5)
    with th.no_grad():
        model.policy.encoder.weight.fill_(float("nan"))
    with pytest.raises(ValueError, match="nan"):
        model.learn(64)


def test_truncated_episodes_bootstrap_from_their_own_state() -> None:
    """SB3's timeout bootstrapping: the reward of a truncated step gets gamma V(terminal obs),
    the value seen from the episode's own carry after that step (not a reset one)."""
    from stable_baselines3.common.callbacks import BaseCallback

    seen: list[tuple[float, Any, th.Tensor]] = []

    class Spy(BaseCallback):
        def _on_step(self) -> bool:
            info = self.locals["infos"][0]
            if self.locals["dones"][0]:
                h = self.model._last_carry.h.clone()
                seen.append((float(self.locals["rewards"][0]), info["terminal_observation"], h))
            return True

    model = _model(PENDULUM, tiny(n_steps=256), seed=6)
    _, callback = model._setup_learn(256, Spy())
    assert model.env is not None
    model.collect_rollouts(model.env, callback, model.rollout_buffer, 256)
    assert len(seen) == 1  # Pendulum truncates at 200 steps
    raw, terminal, h = seen[0]
    with th.no_grad():
        value = model.policy.predict_values(th.as_tensor(terminal[None]), h)
    stored = model.rollout_buffer.rewards[199, 0]
    assert abs(value.item()) > 1e-3
    np.testing.assert_allclose(stored, raw + model.gamma * value.item(), rtol=1e-5)
    with th.no_grad():
        reset_value = model.policy.predict_values(th.as_tensor(terminal[None]), h * 0)
    assert not np.isclose(stored, raw + model.gamma * reset_value.item(), rtol=1e-5)


def test_training_on_reservoir_states_and_evaluating_with_state() -> None:
    from ermrl.config import EncoderConfig, ReservoirParams

    encoder = EncoderConfig(reservoirs=(ReservoirParams(units=10),))
    budget = BudgetConfig(training_steps=128, fitness="eval", n_eval_episodes=1)
    result = train_agent(TaskConfig("Pendulum-v1", "positions"), encoder, tiny(), budget, 0)
    assert result.env_steps == 128 and result.eval_return is not None
    assert np.isfinite(result.eval_return) and len(result.eval_returns) == 1
