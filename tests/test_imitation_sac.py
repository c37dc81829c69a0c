"""The ``imitation-sac`` learner: its three phases, their step counts, save/reload, settings."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from ermrl.agents import load_policy, policy_path, resolve_ppo_config
from ermrl.agents._train import (
    NoEpisodeFinished,
    derive_seeds,
    make_vec_env,
    save_trained,
    train_agent,
)
from ermrl.config import BudgetConfig, ConfigError, EncoderConfig, ReservoirParams, TaskConfig
from ermrl.learners import get_learner
from ermrl.learners._imitation import beta
from ermrl.test_phase._results import write_run

PENDULUM = "Pendulum-v1"
LEARNER = "imitation-sac"


@pytest.fixture
def expert(tiny_expert: Path) -> Path:
    """The session's 300-step SAC Pendulum expert (tests/conftest.py)."""
    return tiny_expert


def _config(expert: Path | None, **overrides: object) -> object:
    settings = dict(overrides)
    if expert is not None:
        settings["expert"] = str(expert)
    return resolve_ppo_config(PENDULUM, settings, learner=LEARNER)


SMALL = {
    "pretrain_steps": 600,
    "steps_per_iteration": 200,
    "beta_iterations": 2,
    "critic_warmup_steps": 50,
    "anchor_iterations": 1,
    "batch_size": 64,
}


def _built(expert: Path, observe: str = "positions", **overrides: object) -> object:
    venv = make_vec_env(TaskConfig(PENDULUM, observe), 1, 0)
    return get_learner(LEARNER).build(venv, _config(expert, **{**SMALL, **overrides}), seed=3)


def test_phases_count_their_steps(expert: Path) -> None:
    model = _built(expert)
    model.learn(1000)
    phases = model.phase_steps
    assert model.num_timesteps == 1000
    assert phases["pretrain_env_steps"] == 600
    assert phases["sac_env_steps"] == 400
    assert phases["pretrain_fits"] == 3  # one per DAgger iteration of 200 steps
    assert phases["critic_warmup_gradient_steps"] == 50
    # anchor_iterations 1 (linear): SAC's first block is a DAgger iteration, none after it
    assert phases["dagger_blocks"] == 1
    assert phases["dagger_block_env_steps"] == 200
    assert phases["expert_labels"] == 600 + 200
    assert model._n_updates == 400  # one SAC gradient step per env step after pretraining
    assert phases["expert_training_steps"] == 300
    # the mixture executed the expert exactly where the replayed draws say so
    draws = np.random.default_rng(np.random.SeedSequence(3).spawn(3)[0])
    expected = sum(int(draws.random(1)[0] < beta("linear", step // 200, 2)) for step in range(600))
    assert phases["expert_executed_steps"] == expected
    assert 200 <= expected < 400  # iteration 0: always the expert; iteration 2: never
    model.env.close()


def test_pretraining_regresses_the_actor_onto_the_expert(expert: Path) -> None:
    from ermrl.learners._imitation_sac_model import ActorMean

    model = _built(expert, observe="all", critic_warmup_steps=0)
    obs = np.random.default_rng(0).uniform(-1, 1, (500, 3)).astype(np.float32)
    obs[:, 2] *= 8.0
    labels = np.clip(model.expert.predict(obs), -2.0, 2.0) / 2.0  # Pendulum's torque in [-2, 2]

    def error() -> float:
        with torch.no_grad():
            mean = ActorMean(model.actor)(torch.as_tensor(obs)).numpy()
        return float(np.mean((mean - labels) ** 2))

    before = error()
    model.learn(600)  # pretraining only
    assert model._n_updates == 0  # no SAC gradient step during pretraining
    assert error() < 0.5 * before
    model.env.close()


def test_critic_warm_up_moves_the_critic_not_the_actor(expert: Path) -> None:
    model = _built(expert, critic_warmup_steps=0)
    model.learn(600)
    actor = {k: v.clone() for k, v in model.actor.state_dict().items()}
    critic = {k: v.clone() for k, v in model.critic.state_dict().items()}
    model.imitation["critic_warmup_steps"] = 20
    model._warmed_up = False
    model._warm_up()
    assert model.phase_steps["critic_warmup_gradient_steps"] == 20
    for key, value in model.actor.state_dict().items():
        if key.startswith("log_std"):
            continue
        assert torch.equal(value, actor[key]), key
    assert torch.all(model.actor.log_std.weight == 0)
    assert torch.all(model.actor.log_std.bias == -1.5)  # the table's initial_log_std
    assert any(not torch.equal(v, critic[k]) for k, v in model.critic.state_dict().items())
    model.env.close()


def test_the_anchor_term_is_added_only_in_dagger_blocks(expert: Path) -> None:
    # anchor_iterations 2 (linear): block 0 surely, block 1 with p = 0.5, none after
    model = _built(expert, anchor_iterations=2, pretrain_steps=200, critic_warmup_steps=0)
    bc_calls: list[int] = []
    real = model._bc_term

    def counting(batch_size: int) -> torch.Tensor:
        bc_calls.append(model._block)
        return real(batch_size)

    model._bc_term = counting
    model.learn(1200)
    blocks = sorted(set(bc_calls))
    assert blocks[0] == 0 and set(blocks) <= {0, 1}
    assert model.phase_steps["dagger_blocks"] == len(blocks)
    assert model.phase_steps["dagger_block_env_steps"] == 200 * len(blocks)
    model.env.close()


@pytest.mark.parametrize(
    "encoder",
    [None, EncoderConfig(reservoirs=(ReservoirParams(units=20),))],
    ids=["raw", "reservoir"],
)
def test_through_train_agent_and_reload(
    expert: Path, encoder: EncoderConfig | None, tmp_path: Path
) -> None:
    ppo = _config(expert, **SMALL)
    task = TaskConfig(PENDULUM, "positions")
    budget = BudgetConfig(training_steps=800, fitness="eval", n_eval_episodes=1)
    result = train_agent(task, encoder, ppo, budget, seed=1, model_path=tmp_path / "model.zip")
    assert result.env_steps == 800
    # Pendulum episodes are 200 steps: the first two are partly the expert's (beta 1, then 0.5)
    # and are no training episodes; the actor acts alone from step 400 on
    assert result.episode_steps == [600, 800]
    assert result.eval_return is not None and np.isfinite(result.eval_return)
    assert result.phase_steps is not None and result.phase_steps["pretrain_env_steps"] == 600
    write_run(tmp_path / "run", LEARNER, result)  # the test phase's record of a run
    record = json.loads((tmp_path / "run" / "result.json").read_text())
    assert record["phase_steps"] == result.phase_steps
    with zipfile.ZipFile(tmp_path / "model.zip") as archive:
        data = json.loads(archive.read("data"))
    assert "expert" not in data and "_label_obs" not in data  # nothing of the expert pickled
    seeds = derive_seeds(1)
    env = make_vec_env(task, 1, seeds.eval_env, encoder, seeds.reservoir)
    try:
        assert env.observation_space.shape == ((2,) if encoder is None else (20,))
        reloaded = load_policy(policy_path(tmp_path / "model.zip"), ppo, env)
        obs = env.reset()
        for _ in range(5):
            action, _ = reloaded.predict(obs, deterministic=True)
            obs, *_ = env.step(action)
    finally:
        env.close()


def test_save_reload_gives_identical_actions(expert: Path, tmp_path: Path) -> None:
    model = _built(expert)
    model.learn(700)
    save_trained(model, tmp_path / "model.zip", None)
    reloaded = load_policy(policy_path(tmp_path / "model.zip"), _config(expert, **SMALL), model.env)
    obs = np.random.default_rng(0).uniform(-1, 1, (50, 2)).astype(np.float32)
    np.testing.assert_array_equal(
        model.predict(obs, deterministic=True)[0], reloaded.predict(obs, deterministic=True)[0]
    )
    model.env.close()


@pytest.mark.parametrize(
    ("key", "value", "match"),
    [
        ("learning_starts", 100, "does not take learning_starts"),
        ("use_sde", True, "does not take use_sde"),
        ("pretrain_steps", -1, "pretrain_steps must be"),
        ("steps_per_iteration", 0, "steps_per_iteration must be"),
        ("anchor_schedule", "cosine", "anchor_schedule must be one of"),
        ("beta_schedule", "step", "beta_schedule must be one of"),
        ("bc_weight", -0.1, "bc_weight must be"),
        ("bc_learning_rate", 0, "bc_learning_rate must be"),
        ("initial_log_std", 5, "initial_log_std must be"),
        ("critic_warmup_steps", 1.5, "critic_warmup_steps must be"),
        ("tau", 2.0, "tau must be"),  # SAC's own checks still apply
        ("n_expert_transitions", 10, "does not take"),  # bc's key
    ],
)
def test_bad_settings_are_refused_in_one_line(
    expert: Path, key: str, value: object, match: str
) -> None:
    with pytest.raises(ConfigError, match=match) as err:
        get_learner(LEARNER).check(_config(expert, **{key: value}))  # type: ignore[arg-type]
    assert "\n" not in str(err.value)


def test_missing_expert_is_refused_in_one_line() -> None:
    with pytest.raises(ConfigError, match="needs an expert") as err:
        get_learner(LEARNER).check(_config(None))  # type: ignore[arg-type]
    assert "\n" not in str(err.value)


def test_sac_refuses_the_imitation_keys(expert: Path) -> None:
    with pytest.raises(ConfigError, match="does not take"):
        get_learner("sac").check(resolve_ppo_config(PENDULUM, {"bc_weight": 1.0}, learner="sac"))


@pytest.mark.slow
def test_pretrained_actor_swings_up_before_sac_starts(good_expert: Path) -> None:
    # pretraining alone (2000 DAgger steps, then the critic warm-up): the actor already imitates
    ppo = _config(good_expert, pretrain_steps=2000)
    budget = BudgetConfig(training_steps=2000, fitness="eval", n_eval_episodes=10)
    # the full observation: Pendulum's swing-up needs the angular velocity the expert acts on
    result = train_agent(TaskConfig(PENDULUM, "all"), None, ppo, budget, seed=0)
    print("imitation-sac after pretraining: eval", result.eval_return)
    assert result.eval_return is not None and result.eval_return > -600  # random: about -1200


def test_pretraining_by_the_expert_alone_gives_no_training_fitness(expert: Path) -> None:
    # one DAgger iteration of beta 1 fills the budget: every episode is the expert's
    ppo = _config(expert, **{**SMALL, "pretrain_steps": 600, "steps_per_iteration": 600})
    budget = BudgetConfig(training_steps=600, fitness="last")
    with pytest.raises(NoEpisodeFinished, match="none of the 3 episodes .* learner's alone"):
        train_agent(TaskConfig(PENDULUM), None, ppo, budget, seed=1)


def test_an_episode_reaching_back_into_mixed_pretraining_is_no_training_episode(
    expert: Path,
) -> None:
    # pretraining ends at step 300, mid-episode: the episode of steps 201-400 had beta 1 (the
    # expert) then SAC, so only the episodes ending at 600 and 800 are the actor's alone
    ppo = _config(expert, **{**SMALL, "pretrain_steps": 300, "steps_per_iteration": 300})
    budget = BudgetConfig(training_steps=800, fitness="last")
    result = train_agent(TaskConfig(PENDULUM), None, ppo, budget, seed=1)
    assert result.episode_steps == [600, 800]


def test_several_envs_count_every_env_step(expert: Path) -> None:
    venv = make_vec_env(TaskConfig(PENDULUM, "positions"), 2, 0)
    ppo = _config(expert, **{**SMALL, "n_envs": 2, "pretrain_steps": 400})
    model = get_learner(LEARNER).build(venv, ppo, seed=3)
    model.learn(800)
    phases = model.phase_steps
    assert model.num_timesteps == 800
    assert phases["pretrain_env_steps"] == 400 and phases["sac_env_steps"] == 400
    assert phases["pretrain_fits"] == 2  # at 200 and 400 env steps (100 steps of each env)
    assert phases["expert_labels"] == 400 + phases["dagger_block_env_steps"]
    assert model._label_arrays()[0].shape == (phases["expert_labels"], 2)
    venv.close()
