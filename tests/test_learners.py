"""Inner learners as plug-ins: the registry, the memory baselines, and a learner added in one place."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import ClassVar

import numpy as np
import optuna
import pytest
import yaml

from ermrl.agents import (
    check_ppo_config,
    load_policy,
    resolve_ppo_config,
    train_agent,
    with_overrides,
)
from ermrl.config import (
    AgentKind,
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    ReservoirParams,
    TaskConfig,
)
from ermrl.learners import AGENT_KINDS, LEARNERS, default_agents, get_learner, learner_names
from ermrl.learners._ppo import PPOLearner

ROOT = Path(__file__).resolve().parents[1]
TASK = TaskConfig("Pendulum-v1", "positions")
TINY = {"n_envs": 2, "n_steps": 128, "batch_size": 64, "n_epochs": 1}
BUDGET = BudgetConfig(training_steps=512, fitness="eval", n_eval_episodes=1, n_last_episodes=1)
ENCODER = EncoderConfig(reservoirs=(ReservoirParams(units=10),))


def tiny(learner: str, **extra: object) -> object:
    return with_overrides(resolve_ppo_config("Pendulum-v1", learner=learner), {**TINY, **extra})


def test_the_registry_names_every_learner_and_refuses_an_unknown_one() -> None:
    assert learner_names()[:3] == ("ppo", "lstm-ppo", "framestack-ppo")
    for name, learner in LEARNERS.items():
        assert learner.name == name and learner.description
    with pytest.raises(ConfigError, match=r"unknown learner 'nope'; choose from ppo, lstm-ppo"):
        get_learner("nope")


def test_every_agent_of_the_table_has_a_registered_learner_and_labels() -> None:
    for name, kind in AGENT_KINDS.items():
        assert kind.learner is None or kind.learner in LEARNERS, name
        assert kind.label and kind.short_label and kind.color, name
    assert len({k.color for k in AGENT_KINDS.values()}) == len(AGENT_KINDS)
    # The memory baselines are asked for, not trained by default (LSTM is ~4x slower).
    assert default_agents("positions") == ("ppo", "ppo-full", "res-ppo", "random-res-ppo")


@pytest.mark.parametrize("learner", ["ppo", "lstm-ppo", "framestack-ppo", "rtu-ppo"])
@pytest.mark.parametrize("encoder", [None, ENCODER], ids=["raw", "reservoir"])
def test_each_learner_trains_saves_and_reloads_the_same_policy(
    learner: str, encoder: EncoderConfig | None, tmp_path: Path
) -> None:
    ppo = tiny(learner)
    result = train_agent(TASK, encoder, ppo, BUDGET, 3, model_path=tmp_path / "model.zip")
    assert result.env_steps >= BUDGET.training_steps and np.isfinite(result.eval_return)
    assert (tmp_path / "policy.pt").is_file()
    # Rebuilt from plain weights on an env wrapped as in training: same actions.
    from ermrl.agents import frozen_normalize_env, load_normalize_stats, make_vec_env

    env = make_vec_env(TASK, 1, 0, encoder, 0)
    if ppo.normalize is not None:
        env = frozen_normalize_env(env, load_normalize_stats(tmp_path / "vecnormalize.json"))
    env = get_learner(learner).wrap_env(env, ppo)
    model = load_policy(tmp_path / "policy.pt", ppo, env)
    obs = env.reset()
    action, state = model.predict(obs, deterministic=True)
    again, _ = model.predict(obs, deterministic=True)
    assert np.array_equal(action, again)
    assert (state is not None) == get_learner(learner).recurrent
    env.close()


# rl-baselines3-zoo's hyperparams/ppo_lstm.yml, PendulumNoVel-v1 and CartPoleNoVel-v1:
# dict(ortho_init=False, activation_fn=nn.ReLU, lstm_hidden_size=64, enable_critic_lstm=True,
#      net_arch=dict(pi=[64], vf=[64]))
ZOO_NOVEL_POLICY = {
    "ortho_init": False,
    "activation_fn": "relu",
    "lstm_hidden_size": 64,
    "enable_critic_lstm": True,
    "net_arch": {"pi": [64], "vf": [64]},
}


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "CartPole-v1"])
def test_lstm_ppo_is_recurrent_ppo_with_the_zoo_settings(env_id: str) -> None:
    import sb3_contrib
    import stable_baselines3
    import torch
    from sb3_contrib import RecurrentPPO

    assert sb3_contrib.__version__.split(".")[:2] == stable_baselines3.__version__.split(".")[:2]
    ppo = resolve_ppo_config(env_id, learner="lstm-ppo")
    assert ppo.learner == "lstm-ppo" and ppo.normalize is not None
    assert ppo.n_envs == {"Pendulum-v1": 4, "CartPole-v1": 8}[env_id]
    assert ppo.hyperparams["policy_kwargs"] == ZOO_NOVEL_POLICY
    env_ppo = resolve_ppo_config(env_id)  # the zoo's NoVel settings are PPO's
    for key, value in env_ppo.hyperparams.items():
        assert ppo.hyperparams[key] == value, key
    from ermrl.agents import make_vec_env

    env = make_vec_env(TaskConfig(env_id, "positions"), 1, 0)
    model = get_learner("lstm-ppo").build(env, with_overrides(ppo, TINY))
    assert isinstance(model, RecurrentPPO)
    policy = model.policy
    assert policy.lstm_actor.hidden_size == 64 and policy.lstm_critic is not None
    assert policy.activation_fn is torch.nn.ReLU and policy.ortho_init is False
    # One ReLU layer of 64 in each head, after the LSTM (SB3's default: two tanh layers).
    for head in (policy.mlp_extractor.policy_net, policy.mlp_extractor.value_net):
        assert [type(m) for m in head] == [torch.nn.Linear, torch.nn.ReLU]
        assert (head[0].in_features, head[0].out_features) == (64, 64)
    env.close()


@pytest.mark.parametrize("name", ["nn.ReLU", "torch.nn.GELU", "os.system", "sigmoid", "3", "[]"])
def test_an_activation_is_a_name_from_a_fixed_table(name: str, tmp_path: Path) -> None:
    """Tables, --ppo and stored studies name an activation; anything else is refused, never
    imported or evaluated."""
    import torch

    from ermrl.agents import ACTIVATIONS, load_hyperparams_table, parse_overrides, ppo_kwargs

    assert set(ACTIVATIONS) == {"tanh", "relu", "elu", "leaky_relu"}
    good = parse_overrides(["policy_kwargs={activation_fn: leaky_relu, net_arch: [8]}"])
    kwargs = ppo_kwargs(with_overrides(tiny("ppo"), good))
    assert kwargs["policy_kwargs"] == {"activation_fn": torch.nn.LeakyReLU, "net_arch": [8]}
    valid = "tanh, relu, elu, leaky_relu"
    with pytest.raises(ConfigError, match=f"activation_fn .* is not one of {valid}"):
        parse_overrides([f"policy_kwargs={{activation_fn: {name}}}"])
    table = tmp_path / "ppo.yml"
    table.write_text(f"Pendulum-v1:\n  policy_kwargs: {{activation_fn: '{name}'}}\n")
    with pytest.raises(ConfigError, match=f"Pendulum-v1.*is not one of {valid}"):
        load_hyperparams_table(table)
    # A stored configuration bypasses both: the name is checked again when the agent is built.
    stored = with_overrides(tiny("ppo"), {"policy_kwargs": {"activation_fn": name}})
    with pytest.raises(ConfigError, match=f"is not one of {valid}"):
        ppo_kwargs(stored)


def test_framestack_ppo_stacks_k_observations_and_is_checked() -> None:
    from ermrl.agents import make_vec_env

    env = make_vec_env(TASK, 1, 0)
    learner = get_learner("framestack-ppo")
    assert learner.wrap_env(env, tiny("framestack-ppo")).observation_space.shape == (8,)
    assert learner.wrap_env(env, tiny("framestack-ppo", frame_stack=3)).observation_space.shape == (
        6,
    )
    env.close()
    with pytest.raises(ConfigError, match="frame_stack must be a whole number"):
        check_ppo_config(TASK, None, tiny("framestack-ppo", frame_stack=0))
    # Another learner's own setting is refused, not silently ignored.
    with pytest.raises(ConfigError, match=r"learner 'ppo' does not take frame_stack"):
        check_ppo_config(TASK, None, tiny("ppo", frame_stack=4))


class _SmallNetPPO(PPOLearner):
    """A toy learner: PPO with another network, as a new engineer would add one."""

    name = "small-ppo"
    description = "PPO with an 8-unit network"
    own_keys: ClassVar[dict[str, object]] = {}
    agents: ClassVar[dict[str, AgentKind]] = {
        "small-ppo": AgentKind("none", None, "PPO with an 8-unit network", "small-ppo")
    }

    def kwargs(self, config: object) -> dict[str, object]:
        return {**super().kwargs(config), "policy_kwargs": {"net_arch": [8]}}  # type: ignore[arg-type]


def test_a_learner_added_in_one_place_is_trained(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(LEARNERS, "small-ppo", _SmallNetPPO())  # type: ignore[index]
    ppo = with_overrides(resolve_ppo_config("Pendulum-v1", learner="ppo"), TINY)
    import dataclasses

    ppo = dataclasses.replace(ppo, learner="small-ppo")
    check_ppo_config(TASK, None, ppo)
    result = train_agent(TASK, None, ppo, BUDGET, 0)
    assert np.isfinite(result.eval_return)
    from ermrl.agents import make_vec_env

    model = get_learner("small-ppo").build(make_vec_env(TASK, 1, 0), ppo)
    assert model.policy.mlp_extractor.policy_net[0].out_features == 8
    # Its agent came with it: the test phase builds it with the learner's own settings, after
    # the agents registered before it; the PPO agents it would inherit are not declared again.
    from ermrl.test_phase import agent_specs, learner_settings_for

    assert list(AGENT_KINDS)[-1] == "small-ppo" and list(AGENT_KINDS).count("ppo") == 1
    base = resolve_ppo_config("Pendulum-v1", learner="ppo")
    (spec,) = agent_specs(
        ["small-ppo"], None, (), learner_settings=learner_settings_for(base, "Pendulum-v1")
    )
    assert spec.ppo is not None and spec.ppo.learner == "small-ppo"


def test_an_agent_declared_twice_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    class _Twin(PPOLearner):
        name = "twin"
        agents: ClassVar[dict[str, AgentKind]] = {"ppo": AgentKind("none", None, "again", "twin")}

    monkeypatch.setitem(LEARNERS, "twin", _Twin())  # type: ignore[index]
    with pytest.raises(
        ConfigError, match=r"agent 'ppo' is declared twice \(again by learner 'twin'\)"
    ):
        list(AGENT_KINDS)


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run(
        [sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600
    )


def test_an_lstm_study_is_tested_against_ppo_and_the_memory_baselines(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    tiny_args = ["--n-envs", "1", "--ppo", "n_steps=128", "batch_size=64", "n_epochs=1"]
    proc = _run(
        str(ROOT / "evolve_res.py"),
        *("--env-id", "Pendulum-v1", "--observe", "positions", "--learner", "lstm-ppo"),
        *("--n-trials", "2", "--n-seeds", "1", "--training-steps", "400", "--units", "10"),
        *("--storage", url, "--study-name", "lstm", *tiny_args),
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    from ermrl.search import study_config

    config = study_config(optuna.load_study(study_name="lstm", storage=url))
    assert config.problem.ppo.learner == "lstm-ppo"

    out = tmp_path / "out"
    proc = _run(
        str(ROOT / "test.py"),
        *("--study-name", "lstm", "--storage", url, "--seeds", "9", "--training-steps", "800"),
        *("--agents", "ppo", "lstm-ppo", "framestack-ppo", "res-ppo", "--out", str(out)),
        *("--ppo", "n_steps=128", "n_envs=1"),
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    doc = yaml.safe_load((out / "config.yaml").read_text())
    # The study's learner (lstm-ppo) trains res-ppo and lstm-ppo with the study's settings;
    # ppo and framestack-ppo take their own table's, with --ppo on top.
    assert set(doc["agent_ppo"]) == {"ppo", "framestack-ppo"}
    assert doc["agent_ppo"]["framestack-ppo"]["learner"] == "framestack-ppo"
    assert doc["agent_ppo"]["ppo"]["hyperparams"]["n_steps"] == 128
    import json

    learners = {
        agent: json.loads((out / "agents" / agent / "seed_9" / "settings.json").read_text())[
            "ppo"
        ].get("learner", "ppo")
        for agent in ("ppo", "lstm-ppo", "framestack-ppo", "res-ppo")
    }
    assert learners == {
        "ppo": "ppo",
        "lstm-ppo": "lstm-ppo",
        "framestack-ppo": "framestack-ppo",
        "res-ppo": "lstm-ppo",
    }
    summary = (out / "summary.csv").read_text()
    assert all(a in summary for a in ("lstm-ppo", "framestack-ppo", "res-ppo"))
    # The saved recurrent and stacked policies replay deterministically (the zoo's measure).
    proc = _run(
        str(ROOT / "benchmarks" / "eval_policies.py"),
        *(str(out), "--agents", "lstm-ppo", "framestack-ppo", "--episodes", "1"),
        *("--out", str(tmp_path / "eval.json")),
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    evaluated = json.loads((tmp_path / "eval.json").read_text())
    assert set(evaluated) == {"lstm-ppo", "framestack-ppo"}
    assert all(-2000 < a["mean"] <= 0 for a in evaluated.values())  # Pendulum returns


def test_the_reservoir_is_a_registered_encoder_that_decodes_plain_params() -> None:
    from ermrl.agents import make_vec_env
    from ermrl.config import ReservoirSpace
    from ermrl.encoders import ENCODERS, ReservoirVecEnv, encoder_for

    encoder = encoder_for(ENCODER)
    assert ENCODERS["reservoir"] is encoder and encoder.place == "env"
    space = ReservoirSpace(n_reservoirs=2, units=10)
    params = {name: 0.5 for name in space.param_names}
    decoded = encoder.decode(space, params, ENCODER)
    assert [(p.sr, p.lr, p.input_scaling) for p in decoded.reservoirs] == [(0.5, 0.5, 0.5)] * 2
    env = make_vec_env(TASK, 1, 0, decoded, 0)
    assert isinstance(env, ReservoirVecEnv) and env.observation_space.shape == (20,)
    env.close()
    with pytest.raises(TypeError, match="no registered encoder takes TaskConfig"):
        encoder_for(TASK)


def test_generalization_tasks_take_the_learners_own_table() -> None:
    from ermrl.cli._generalization import build_evolve_generalization_parser
    from ermrl.search import generalization_tasks

    tasks = generalization_tasks(["Swimmer-v5", "Hopper-v5"], learner="lstm-ppo")
    assert [t.ppo.learner for t in tasks] == ["lstm-ppo", "lstm-ppo"]
    # ppo_lstm.yml's default block, not ppo.yml's
    assert all(t.ppo.hyperparams["policy_kwargs"]["lstm_hidden_size"] == 64 for t in tasks)
    args = build_evolve_generalization_parser().parse_args(
        ["--env-ids", "Swimmer-v5", "--learner", "framestack-ppo"]
    )
    assert args.learner == "framestack-ppo"
