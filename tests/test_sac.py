"""The ``sac`` learner: SB3's SAC on raw or reservoir-encoded observations.

Training through :func:`~ermrl.agents.train_agent`, the replay buffer of encoded observations
(the terminal ``next_observation`` included), plain-tensor saving and reloading, the zoo
defaults of ``ermrl/data/sac.yml``, refusals, and ``evolve --learner sac`` then
``test --agents sac res-sac`` end to end.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ermrl.config import (
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    PPOConfig,
    ReservoirParams,
    TaskConfig,
)
from ermrl.learners import AGENT_KINDS

PENDULUM = TaskConfig("Pendulum-v1", "positions")
ENCODER = EncoderConfig(reservoirs=(ReservoirParams(units=20),))
# Tiny SAC: a gradient step per env step from step 100 on, small batches and networks.
TINY = {
    "learning_starts": 100,
    "batch_size": 32,
    "buffer_size": 2000,
    "policy_kwargs": {"net_arch": [32, 32]},
}


def _tiny(n_envs: int = 1, **extra: Any) -> PPOConfig:
    from ermrl.agents import resolve_ppo_config

    return resolve_ppo_config("Pendulum-v1", {**TINY, **extra}, n_envs=n_envs, learner="sac")


def _learned(encoder: EncoderConfig | None, steps: int, env_seed: int = 5) -> tuple[Any, Any]:
    """A SAC agent trained ``steps`` steps on Pendulum (positions), and its env."""
    from ermrl.agents import make_vec_env
    from ermrl.learners import get_learner

    config = _tiny()
    env = make_vec_env(PENDULUM, 1, env_seed, encoder, reservoir_seed=3)
    model = get_learner("sac").build(env, config, seed=0)
    env.seed(env_seed)
    model.learn(steps)
    return model, config


@pytest.mark.parametrize(("encoder", "n_envs"), [(None, 1), (ENCODER, 1), (ENCODER, 2)])
def test_sac_trains_through_train_agent_exactly_and_reproducibly(
    encoder: EncoderConfig | None, n_envs: int
) -> None:
    from ermrl.agents import train_agent

    budget = BudgetConfig(training_steps=420, n_last_episodes=2)
    runs = [train_agent(PENDULUM, encoder, _tiny(n_envs), budget, seed=4) for _ in range(2)]
    first = runs[0]
    assert first.env_steps == 420  # one env step per call (train_freq 1), n_envs at a time
    # Pendulum episodes last 200 steps; each env takes 420 / n_envs of them.
    assert len(first.episode_returns) == n_envs * (420 // n_envs // 200)
    assert first.episode_steps == sorted(first.episode_steps)
    assert all(-2000 < r < 0 for r in first.episode_returns)
    assert first.last_return == pytest.approx(np.mean(first.episode_returns[-2:]))
    assert runs[1].episode_returns == first.episode_returns  # same seed, same run


def test_sac_evaluates_after_training_when_asked() -> None:
    from ermrl.agents import train_agent

    budget = BudgetConfig(training_steps=200, fitness="eval", n_eval_episodes=1)
    result = train_agent(PENDULUM, ENCODER, _tiny(), budget, seed=1)
    assert len(result.eval_returns) == 1 and result.eval_return == result.eval_returns[0]


def test_the_replay_buffer_holds_encoded_observations_and_the_encoded_terminal_state() -> None:
    """SAC's buffer holds the states the reservoir showed; at an episode's end (Pendulum
    truncates at 200 steps) ``next_observations`` is the encoded terminal state from
    ``infos[i]["terminal_observation"]``, not the raw observation nor the next episode's first
    state. Replaying the stored actions through a fresh env of the same seeds checks every
    transition."""
    from ermrl.agents import make_vec_env

    steps = 230
    model, _ = _learned(ENCODER, steps)
    buffer = model.replay_buffer
    assert buffer.pos == steps and buffer.observations.shape[1:] == (1, 20)
    obs_buf = buffer.observations[:steps, 0]
    next_buf = buffer.next_observations[:steps, 0]
    assert np.all(np.abs(obs_buf) <= 1) and np.all(np.abs(next_buf) <= 1)  # tanh states

    env = make_vec_env(PENDULUM, 1, 5, ENCODER, reservoir_seed=3)
    env.seed(5)
    obs = env.reset()
    actions = model.policy.unscale_action(buffer.actions[:steps, 0])  # what the env received
    terminal = None
    for t in range(steps):
        np.testing.assert_array_equal(obs_buf[t], obs[0])
        obs, _, dones, infos = env.step(actions[t : t + 1])
        if dones[0]:
            terminal = t
            assert infos[0]["terminal_observation"].shape == (20,)  # encoded by the wrapper
            np.testing.assert_array_equal(next_buf[t], infos[0]["terminal_observation"])
            assert buffer.timeouts[t, 0] == 1  # a truncation: SAC bootstraps from it
        else:
            np.testing.assert_array_equal(next_buf[t], obs[0])
    env.close()
    assert terminal == 199
    # The terminal state is not the next episode's first state.
    assert not np.allclose(next_buf[terminal], obs_buf[terminal + 1])


def test_a_saved_sac_policy_reloads_from_plain_tensors_and_acts_identically(
    tmp_path: Path,
) -> None:
    import torch

    from ermrl.agents import load_policy, make_vec_env, policy_path
    from ermrl.agents._train import save_trained

    model, config = _learned(ENCODER, 200)
    save_trained(model, tmp_path / "model.zip", None)
    weights = policy_path(tmp_path / "model.zip")
    state = torch.load(str(weights), map_location="cpu", weights_only=True)  # no pickle
    assert any(k.startswith("actor.") for k in state)

    env = make_vec_env(PENDULUM, 1, 0, ENCODER, reservoir_seed=3)
    reloaded = load_policy(weights, config, env)
    env.close()
    observations = model.replay_buffer.observations[:200, 0]
    mine, _ = model.predict(observations, deterministic=True)
    theirs, _ = reloaded.predict(observations, deterministic=True)
    np.testing.assert_array_equal(mine, theirs)
    assert np.ptp(mine) > 0  # the actions depend on the observation


@pytest.mark.parametrize(
    ("env_id", "expected"),
    [
        ("Hopper-v5", {"learning_starts": 10000}),
        ("HalfCheetah-v4", {"learning_starts": 10000}),
        ("Humanoid-v5", {"learning_starts": 10000}),
        ("Swimmer-v5", {"learning_starts": 10000, "gamma": 0.9999}),
        ("Pendulum-v1", {"learning_rate": 1e-3}),
        ("CartPole-v1", {}),
    ],
)
def test_the_zoo_defaults_resolve(env_id: str, expected: dict[str, Any]) -> None:
    from ermrl.agents import resolve_ppo_config

    config = resolve_ppo_config(env_id, learner="sac")
    assert dict(config.hyperparams) == expected
    assert config.learner == "sac" and config.n_envs == 1 and config.normalize is None


def test_the_tuned_zoo_entries_build() -> None:
    """MountainCarContinuous's tuned entry (gSDE, 32 steps per update, fixed ent_coef) and
    an ``[N, episode]`` train_freq are accepted by SAC itself."""
    from ermrl.agents import check_ppo_config, resolve_ppo_config

    task = TaskConfig("MountainCarContinuous-v0", "positions")
    config = resolve_ppo_config(task.env_id, learner="sac")
    assert config.hyperparams["train_freq"] == 32 and config.hyperparams["use_sde"] is True
    check_ppo_config(task, ENCODER, config)
    check_ppo_config(PENDULUM, None, _tiny(train_freq=[1, "episode"], ent_coef="auto_0.5"))


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("learning_starts=-1", "learning_starts must be a whole number >= 0"),
        ("gradient_steps=0", "gradient_steps must be"),
        ("tau=1.5", "tau must be a number in [0, 1]"),
        ("train_freq=[1,fortnight]", "train_freq must be"),
        ("ent_coef=autox", "ent_coef must be"),
        ("ent_coef=-0.1", "ent_coef must be"),
        ("buffer_size=0", "buffer_size must be"),
        ("nope=1", "unknown setting 'nope' of learner 'sac'"),
        ("n_epochs=3", "'n_epochs' is a setting of another learner (ppo"),  # not SAC's
        ("frame_stack=4", "a setting of another learner"),
    ],
)
def test_bad_sac_settings_are_refused_in_one_line_before_any_storage_exists(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], override: str, message: str
) -> None:
    from ermrl.cli._evolve import evolve_main

    db = tmp_path / "x.db"
    with pytest.raises(SystemExit) as exit_:
        evolve_main(
            ["--env-id", "Pendulum-v1", "--learner", "sac", "--ppo", override,
             "--storage", f"sqlite:///{db}"]
        )  # fmt: skip
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err, err
    assert not db.exists()


def test_sac_settings_are_refused_by_ppo() -> None:
    from ermrl.agents import check_ppo_config, resolve_ppo_config

    with pytest.raises(ConfigError, match="learning_starts"):
        check_ppo_config(PENDULUM, None, resolve_ppo_config("Pendulum-v1", {"learning_starts": 5}))
    with pytest.raises(ConfigError, match="ent_coef must be a number"):
        check_ppo_config(PENDULUM, None, resolve_ppo_config("Pendulum-v1", {"ent_coef": "auto"}))


def test_the_sac_agents_are_registered() -> None:
    from ermrl.learners import get_learner, learner_names

    assert "sac" in learner_names() and get_learner("sac").table == "sac.yml"
    sac, res_sac = AGENT_KINDS["sac"], AGENT_KINDS["res-sac"]
    assert (sac.reservoirs, sac.learner, sac.default) == ("none", "sac", False)
    assert (res_sac.reservoirs, res_sac.learner, res_sac.family) == ("evolved", "sac", "esn")
    assert not res_sac.default


def _cli(*args: str, timeout: int = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args], capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.slow
def test_evolve_with_sac_then_test_sac_and_res_sac(tmp_path: Path) -> None:
    """``evolve --learner sac`` on position-only Hopper, then ``test --agents sac res-sac``:
    both train SAC with the study's settings, ``res-sac`` on the selected evolved reservoir,
    and both replay from their plain-tensor policies."""
    import optuna

    storage = f"sqlite:///{tmp_path / 's.db'}"
    ppo = ["learning_starts=100", "batch_size=32", "buffer_size=1000",
           "policy_kwargs={net_arch: [32, 32]}"]  # fmt: skip
    evolve = _cli(
        "evolve", "--env-id", "Hopper-v5", "--observe", "positions", "--learner", "sac",
        "--ppo", *ppo, "--units", "16", "--n-trials", "2", "--n-seeds", "1",
        "--training-steps", "300", "--storage", storage, "--study-name", "s", "--quiet",
    )  # fmt: skip
    assert evolve.returncode == 0, evolve.stderr
    study = optuna.load_study(study_name="s", storage=storage)
    trials = study.get_trials()
    assert len(trials) == 2 and all(t.value is not None for t in trials)

    out = tmp_path / "test"
    test = _cli(
        "test", "--study-name", "s", "--storage", storage, "--training-steps", "300",
        "--seeds", "10", "--agents", "sac", "res-sac", "--out", str(out),
    )  # fmt: skip
    assert test.returncode == 0, test.stderr
    settings = {p.parent.parent.name: json.loads(p.read_text()) for p in out.rglob("settings.json")}
    assert set(settings) == {"sac", "res-sac"}
    for agent in ("sac", "res-sac"):
        learner = settings[agent]["ppo"]
        assert learner["learner"] == "sac"
        assert learner["hyperparams"]["learning_starts"] == 100  # the study's settings
    assert settings["sac"]["encoder"] is None
    reservoirs = settings["res-sac"]["encoder"]["reservoirs"]
    assert len(reservoirs) == 1 and reservoirs[0]["units"] == 16
    assert reservoirs[0]["sr"] == pytest.approx(study.best_trial.params["sr"])

    from ermrl.analysis import load_trained_agent, rollout

    plain = rollout(load_trained_agent(out, "sac", 10), max_steps=15)
    encoded = rollout(load_trained_agent(out, "res-sac", 10), max_steps=15)
    assert plain.states.shape == (plain.n_steps, 0)
    assert encoded.states.shape == (encoded.n_steps, 16)
    assert plain.observations.shape[1] == encoded.observations.shape[1] == 5  # Hopper qpos
    again = rollout(load_trained_agent(out, "res-sac", 10), max_steps=15)
    np.testing.assert_array_equal(again.actions, encoded.actions)  # deterministic replay
