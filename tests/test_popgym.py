"""POPGym memory tasks through ermrl's env factory, reservoir encoder and PPO (real envs)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from gymnasium import spaces

from ermrl.agents import make_vec_env, resolve_ppo_config, train_agent
from ermrl.config import BudgetConfig, ConfigError, EncoderConfig, ReservoirParams, TaskConfig
from ermrl.envs import (
    UnknownEnvError,
    UnsupportedObserveError,
    check_env_id,
    make_env,
    observation_indices,
    observation_split,
    popgym_env_ids,
)

# The tasks of the paper (REFERENCES.md): id, flat observation length, fixed episode length.
NAMED = [
    ("popgym-RepeatFirstEasy-v0", 4, 51),  # Discrete(4): one-hot
    ("popgym-CountRecallEasy-v0", 4, 51),  # MultiDiscrete([2, 2]): two one-hots
    ("popgym-AutoencodeEasy-v0", 6, 103),  # Tuple(Discrete(2), Discrete(4))
    ("popgym-HigherLowerEasy-v0", 13, 51),  # Discrete(13)
]
# SB3 defaults (ppo.yml's default block) with a short rollout so the test stays small.
SMALL_PPO = {"n_steps": 128, "batch_size": 64, "n_epochs": 2}


def _run_episode(env_id: str, seed: int = 0) -> int:
    """Play one random episode, checking every observation; return its length."""
    env = make_env(env_id)
    space = env.observation_space
    assert isinstance(space, spaces.Box)
    assert len(space.shape) == 1 and space.dtype == np.float32
    obs, _ = env.reset(seed=seed)
    env.action_space.seed(seed)
    length, done = 0, False
    while not done:
        assert obs.dtype == np.float32 and obs.shape == space.shape and space.contains(obs)
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        assert np.isfinite(reward)
        length += 1
        done = terminated or truncated
        assert length < 10_000, f"{env_id} never ends"
    env.close()
    return length


@pytest.mark.parametrize(("env_id", "obs_dim", "episode_length"), NAMED)
def test_named_task_builds_flat_float_box_and_ends(
    env_id: str, obs_dim: int, episode_length: int
) -> None:
    env = make_env(env_id, "all")
    assert env.observation_space.shape == (obs_dim,)
    assert isinstance(env.action_space, spaces.Discrete)
    obs, _ = env.reset(seed=1)
    # Discrete parts are one-hot: one 1 per part (Autoencode and CountRecall have two parts).
    assert set(np.unique(obs)) <= {0.0, 1.0}
    assert _run_episode(env_id) == episode_length


def test_every_registered_popgym_task_builds_and_steps() -> None:
    ids = popgym_env_ids()
    assert len(ids) >= 42 and {name for name, _, _ in NAMED} <= set(ids)
    for env_id in ids:
        check_env_id(env_id)
        env = make_env(env_id)
        space = env.observation_space
        assert isinstance(space, spaces.Box) and space.dtype == np.float32, env_id
        assert isinstance(env.action_space, (spaces.Discrete, spaces.MultiDiscrete, spaces.Box))
        obs, _ = env.reset(seed=0)
        env.action_space.seed(0)
        for _ in range(3):
            obs, *_ = env.step(env.action_space.sample())
            assert obs.dtype == np.float32 and space.contains(obs), env_id
        env.close()


@pytest.mark.parametrize("observe", ["positions", "velocities"])
def test_masks_are_refused_in_one_line(observe: str) -> None:
    env_id = "popgym-RepeatFirstEasy-v0"
    for build in (
        lambda: make_env(env_id, observe),  # type: ignore[arg-type]
        lambda: observation_indices(env_id, observe),  # type: ignore[arg-type]
        lambda: observation_split(env_id),
    ):
        with pytest.raises(UnsupportedObserveError, match="partially observable by design") as err:
            build()
        assert "\n" not in str(err.value) and "--observe all" in str(err.value)
    assert observation_indices(env_id, "all") is None


@pytest.mark.parametrize(
    ("env_id", "match"),
    [
        ("popgym-RepeatFirst-v0", "did you mean: popgym-RepeatFirst"),  # not registered
        ("popgym-LabyrinthEscapeEasy-v0", "mazelib"),  # registered only with mazelib
    ],
)
def test_unavailable_ids_fail_in_one_line(env_id: str, match: str) -> None:
    with pytest.raises(UnknownEnvError, match=match) as err:
        make_env(env_id)
    assert "\n" not in str(err.value)


@pytest.mark.filterwarnings("ignore:.*render_mode.*:UserWarning")
def test_render_mode_the_env_does_not_take_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="cannot be built with") as err:
        make_env("popgym-RepeatFirstEasy-v0", render_mode="rgb_array")
    assert "\n" not in str(err.value)


def test_popgym_is_imported_only_for_a_popgym_id_and_runs_quietly() -> None:
    code = (
        "import sys\n"
        "from ermrl.envs import check_env_id, make_env\n"
        "make_env('CartPole-v1')\n"
        "assert 'popgym' not in sys.modules\n"
        "check_env_id('popgym-CountRecallEasy-v0')\n"
        "assert 'popgym' in sys.modules\n"
        "env = make_env('popgym-CountRecallEasy-v0')\n"
        "env.reset(seed=0)\n"
        "for _ in range(3): env.step(env.action_space.sample())\n"
    )
    done = subprocess.run(
        [sys.executable, "-W", "always", "-c", code], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout == ""
    assert "popgym" not in done.stderr and "WARN" not in done.stderr


def test_reservoir_encoder_steps_on_popgym() -> None:
    encoder = EncoderConfig(reservoirs=(ReservoirParams(units=20),))
    venv = make_vec_env(TaskConfig("popgym-RepeatFirstEasy-v0", "all"), 2, 0, encoder, 0)
    obs = venv.reset()
    assert obs.shape[0] == 2 and np.all(np.isfinite(obs))
    for _ in range(60):  # past the end of a 51-step episode
        obs, rewards, _, _ = venv.step(np.array([venv.action_space.sample() for _ in range(2)]))
        assert np.all(np.isfinite(obs)) and np.all(np.isfinite(rewards))
    venv.close()


@pytest.mark.parametrize(
    "encoder", [None, EncoderConfig(reservoirs=(ReservoirParams(units=20),))], ids=["ppo", "res"]
)
def test_ppo_trains_on_popgym(encoder: EncoderConfig | None) -> None:
    env_id = "popgym-RepeatFirstEasy-v0"
    ppo = resolve_ppo_config(env_id, SMALL_PPO)
    budget = BudgetConfig(training_steps=512, n_last_episodes=3, n_reports=0)
    result = train_agent(TaskConfig(env_id, "all"), encoder, ppo, budget, seed=0)
    assert len(result.episode_returns) >= 9  # 512 steps / 51 per episode
    assert all(-1.0 - 1e-6 <= r <= 1.0 + 1e-6 for r in result.episode_returns)
    assert np.isfinite(result.last_return)
