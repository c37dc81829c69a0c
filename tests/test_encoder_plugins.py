"""An encoder is one module plus one registry line: a toy encoder, written here in one place and
registered with one ``ENCODERS`` entry, is evolved by ``ermrl evolve --encoder toy``, stored and
read back, and tested by ``ermrl test`` with its own agents; nothing else in ermrl names it.

The toy is what docs/learners.md ("Adding an encoder") walks through: a fixed random projection
``tanh(scale * W u)`` of the observation with one evolved gene, ``scale``.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import optuna
import pandas as pd
import pytest
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnvWrapper

from ermrl._schema import option
from ermrl.config import AgentKind, ConfigError, Range
from ermrl.encoders import ENCODERS, EncoderConfig, PerReservoirSpace
from ermrl.encoders._base import Encoder

# -- the toy encoder: everything it is, in one place ----------------------------------------------


@dataclass(frozen=True)
class ToyParams:
    """One projection: ``width`` outputs, input weights ``N(0, 1 / d)`` times ``scale``."""

    width: int = 6
    scale: float = 1.0
    family: Literal["toy"] = "toy"

    def __post_init__(self) -> None:
        if not self.scale > 0:
            raise ConfigError(f"scale must be positive, got {self.scale}")

    @property
    def state_dim(self) -> int:
        return self.width


@dataclass(frozen=True)
class ToySpace(PerReservoirSpace):
    """One evolved gene per projection, ``scale`` (log scale); the reference is ``scale = 1``."""

    n_reservoirs: int = 1
    width: int = 6
    scale: Range = Range(0.1, 10.0)
    family: Literal["toy"] = "toy"

    def _per_reservoir(self) -> dict[str, Range]:
        return {"scale": self.scale}

    def _reference_values(self) -> dict[str, float]:
        return {"scale": 1.0}

    def reservoirs_from(self, params: Mapping[str, float]) -> tuple[ToyParams, ...]:
        return tuple(
            ToyParams(self.width, self._values(params, k)["scale"])
            for k in range(self.n_reservoirs)
        )

    def default_reservoirs(self) -> tuple[ToyParams, ...]:
        return (ToyParams(self.width),) * self.n_reservoirs


class _Projection(VecEnvWrapper):
    """The policy sees ``tanh(scale * W obs)`` per projection, concatenated."""

    def __init__(self, venv: Any, config: EncoderConfig, seed: int) -> None:
        d = int(np.prod(venv.observation_space.shape))
        rng = np.random.default_rng(seed)
        self.weights = [
            p.scale * rng.normal(0.0, 1.0 / math.sqrt(d), (p.width, d))  # type: ignore[attr-defined]
            for p in config.reservoirs
        ]
        width = sum(w.shape[0] for w in self.weights)
        space = spaces.Box(-1.0, 1.0, (width,), np.float32)
        super().__init__(venv, observation_space=space)

    def _encode(self, obs: np.ndarray) -> np.ndarray:
        flat = np.asarray(obs, np.float64).reshape(len(obs), -1)
        return np.concatenate([np.tanh(flat @ w.T) for w in self.weights], 1).astype(np.float32)

    def reset(self) -> np.ndarray:
        return self._encode(self.venv.reset())

    def step_wait(self) -> Any:
        obs, rewards, dones, infos = self.venv.step_wait()
        return self._encode(obs), rewards, dones, infos


@dataclass(frozen=True)
class ToySettings:
    """The toy's ``ermrl evolve`` settings: declared once, they reach the CLI, experiment
    files and Python."""

    toy_width: int | None = option(None, "--encoder toy: outputs per projection (default 6)", low=1)
    toy_scale_range: tuple[float, float] = option(
        (0.1, 10.0), "--encoder toy: range of the projection's scale (log scale)",
        metavar=("LOW", "HIGH"), above=0,
    )  # fmt: skip


class ToyEncoder(Encoder):
    name = "toy"
    description = "a fixed random projection tanh(scale * W u) (evolved scale); wraps the env"
    family = "toy"
    config_cls = EncoderConfig
    params_cls: ClassVar[type] = ToyParams
    space_cls: ClassVar[type] = ToySpace
    settings: ClassVar[type | None] = ToySettings
    space_fields: ClassVar[Mapping[str, str]] = {"toy_width": "width", "toy_scale_range": "scale"}
    agents: ClassVar[Mapping[str, AgentKind]] = {
        "toy-ppo": AgentKind(
            "evolved", None, "PPO on the evolved projection", None, "Toy-PPO", family="toy"
        ),
        "random-toy-ppo": AgentKind(
            "unevolved", None, "PPO on the reference projection", None, "Toy-PPO (ref.)",
            family="toy",
        ),
    }  # fmt: skip

    def wrap_env(self, venv: Any, config: EncoderConfig, seed: int) -> Any:
        return _Projection(venv, config, seed)


# -- the one registry line, and what follows from it ----------------------------------------------


@pytest.fixture
def toy(monkeypatch: pytest.MonkeyPatch) -> ToyEncoder:
    encoder = ToyEncoder()
    monkeypatch.setitem(ENCODERS, "toy", encoder)  # the registry line
    return encoder


TINY_PPO = ["--ppo", "n_steps=128", "batch_size=64", "n_epochs=1", "--n-envs", "1"]


def test_a_toy_encoder_is_a_choice_with_its_flags_agents_and_space(toy: ToyEncoder) -> None:
    from ermrl.cli._evolve import build_evolve_parser, space_from_args
    from ermrl.learners import AGENT_KINDS, default_agents, evolved_agent, unevolved_agent

    parser = build_evolve_parser()
    args = parser.parse_args(
        ["--env-id", "CartPole-v1", "--encoder", "toy", "--toy-width", "4"]
        + ["--toy-scale-range", "0.5", "2"]
    )
    space = space_from_args(args)
    assert space == ToySpace(width=4, scale=Range(0.5, 2.0))
    assert "toy-ppo" in AGENT_KINDS and AGENT_KINDS["toy-ppo"].family == "toy"
    assert (evolved_agent("toy"), unevolved_agent("toy")) == ("toy-ppo", "random-toy-ppo")
    assert default_agents("positions", "toy") == ("ppo", "ppo-full", "toy-ppo", "random-toy-ppo")
    help_text = " ".join(parser.format_help().split())
    assert "'toy': a fixed random projection" in help_text and "--toy-scale-range" in help_text
    # Another encoder's flag is refused, in one line naming its encoder.
    other = parser.parse_args(
        ["--env-id", "CartPole-v1", "--encoder", "toy", "--sr-range", "1", "2"]
    )
    with pytest.raises(ConfigError, match="--sr-range applies to --encoder reservoir"):
        space_from_args(other)
    back = parser.parse_args(["--env-id", "CartPole-v1", "--toy-width", "3"])
    with pytest.raises(ConfigError, match="--toy-width applies to --encoder toy"):
        space_from_args(back)


def test_a_toy_encoders_settings_reach_files_and_python_from_its_declaration(
    toy: ToyEncoder, tmp_path: Path
) -> None:
    import yaml

    from ermrl.runner import evolve_config
    from ermrl.runner._experiment import experiment_plan, load_experiment

    # Python: the keywords are the settings' names, checked by their declared types.
    config = evolve_config("CartPole-v1", encoder="toy", toy_width=4, toy_scale_range=[0.5, 2])
    assert config.space == ToySpace(width=4, scale=Range(0.5, 2.0))
    with pytest.raises(ConfigError, match="toy_width: must be positive, got 0"):
        evolve_config("CartPole-v1", encoder="toy", toy_width=0)
    with pytest.raises(ConfigError, match="unknown key 'toy_widht' .did you mean 'toy_width'"):
        evolve_config("CartPole-v1", encoder="toy", toy_widht=4)
    # An experiment file: the same keys, and the plan shows the command's flags.
    doc = {
        "name": "toy",
        "tasks": ["CartPole-v1"],
        "storage": f"sqlite:///{tmp_path}/toy.db",
        "evolve": {"encoder": "toy", "toy_width": "4", "toy_scale_range": [0.5, 2], "n_trials": 2},
    }
    (tmp_path / "toy.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    (step,) = experiment_plan(load_experiment(tmp_path / "toy.yaml"), build_agents=False)[:1]
    assert "--encoder toy --toy-width 4 --toy-scale-range 0.5 2 " in step.command_line
    assert step.request.config.space == ToySpace(width=4, scale=Range(0.5, 2.0))
    (tmp_path / "bad.yaml").write_text(
        yaml.safe_dump({**doc, "evolve": {"encoder": "toy", "toy_widht": 4}})
    )
    with pytest.raises(ConfigError, match="evolve: unknown key 'toy_widht' .did you mean"):
        experiment_plan(load_experiment(tmp_path / "bad.yaml"), build_agents=False)


def test_a_toy_encoder_added_in_one_place_is_evolved_stored_and_tested(
    toy: ToyEncoder, tmp_path: Path
) -> None:
    from ermrl.cli import main
    from ermrl.search import study_config

    url = f"sqlite:///{tmp_path}/toy.db"
    code = main(
        ["evolve", "--env-id", "CartPole-v1", "--observe", "positions", "--encoder", "toy"]
        + ["--toy-width", "5", "--n-trials", "2", "--n-seeds", "1", "--training-steps", "256"]
        + ["--storage", url, "--study-name", "toy", "--backend", "sb3", "--quiet", *TINY_PPO]
    )
    assert code == 0
    study = optuna.load_study(study_name="toy", storage=url)
    trials = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    assert len(trials) == 2 and all(math.isfinite(t.value) for t in trials)  # type: ignore[arg-type]
    assert trials[0].params == {"scale": 1.0}  # the reference trial
    assert all(0.1 <= t.params["scale"] <= 10.0 for t in trials)
    # The stored configuration reads back as the toy's own classes, through the registry.
    config = study_config(study)
    assert isinstance(config.space, ToySpace) and config.space.width == 5
    assert config.problem.encoder is not None
    assert config.problem.encoder.reservoirs == (ToyParams(5),)
    assert config.default_study_name.endswith("__toy")

    out = tmp_path / "out"
    code = main(
        ["test", "--study-name", "toy", "--storage", url, "--seeds", "9"]
        + ["--training-steps", "256", "--out", str(out), "--ppo", "n_steps=128", "n_envs=1"]
    )
    assert code == 0
    summary = pd.read_csv(out / "summary.csv")
    assert set(summary["agent"]) == {"ppo", "ppo-full", "toy-ppo", "random-toy-ppo"}
    settings = {
        agent: json.loads((out / "agents" / agent / "seed_9" / "settings.json").read_text())
        for agent in ("toy-ppo", "random-toy-ppo")
    }
    best = study.best_trial.params["scale"]
    assert settings["toy-ppo"]["encoder"]["reservoirs"] == [
        {"width": 5, "scale": best, "family": "toy"}
    ]
    assert settings["random-toy-ppo"]["encoder"]["reservoirs"][0]["scale"] == 1.0


def test_the_population_backend_refuses_an_encoder_it_does_not_step(
    toy: ToyEncoder, tmp_path: Path
) -> None:
    from ermrl.cli._evolve import build_evolve_parser, config_from_args

    args = build_evolve_parser().parse_args(
        ["--env-id", "CartPole-v1", "--encoder", "toy", "--training-steps", "256"]
        + ["--backend", "population", "--storage", f"sqlite:///{tmp_path}/p.db"]
    )
    with pytest.raises(ConfigError, match="does not step --encoder toy"):
        config_from_args(args, build_agent=False)
    notes: list[str] = []
    args = argparse.Namespace(**{**vars(args), "backend": None})
    config = config_from_args(args, build_agent=False, notes=notes)
    assert config.problem.ppo.backend == "sb3" and "--encoder toy" in notes[0]


def test_a_stored_family_no_encoder_has_is_refused_not_imported() -> None:
    from ermrl.config import EncoderConfig as StoredEncoder
    from ermrl.config import from_dict

    with pytest.raises(ConfigError, match="encoder family 'toy'"):
        from_dict(StoredEncoder, {"reservoirs": [{"width": 5, "scale": 1.0, "family": "toy"}]})


# -- a toy encoder with a bank: the population backend steps it, naming no family -----------------


@dataclass(frozen=True)
class ToyBankParams:
    """A memoryless reservoir ``x = tanh(scale * Win u)`` (``W = 0``, leak rate 1)."""

    units: int = 6
    scale: float = 1.0
    family: Literal["toybank"] = "toybank"

    @property
    def state_dim(self) -> int:
        return self.units


class ToyBankEncoder(Encoder):
    name = "toybank"
    description = "a memoryless projection tanh(scale * Win u) in a ReservoirBank; wraps the env"
    family = "toybank"
    config_cls = EncoderConfig
    params_cls: ClassVar[type] = ToyBankParams
    space_cls: ClassVar[type] = ToySpace
    agents: ClassVar[Mapping[str, AgentKind]] = {
        "toybank-ppo": AgentKind("evolved", None, "PPO", None, "TB", family="toybank"),
        "random-toybank-ppo": AgentKind("unevolved", None, "PPO", None, "TB0", family="toybank"),
    }
    population = True

    def bank(self, config: EncoderConfig, input_dim: int, seed: int) -> Any:
        from ermrl.encoders import ReservoirBank, ReservoirWeights, reservoir_seeds

        weights = []
        for p, s in zip(config.reservoirs, reservoir_seeds(seed, config.n_reservoirs)):
            rng = np.random.default_rng(s)
            units, scale = p.units, p.scale  # type: ignore[attr-defined]
            win = scale * rng.normal(0.0, 1.0 / math.sqrt(input_dim), (units, input_dim))
            weights.append(ReservoirWeights(np.zeros((units, units)), win, np.zeros(units), 1.0))
        return ReservoirBank(weights, dtype=config.dtype)

    def wrap_env(self, venv: Any, config: EncoderConfig, seed: int) -> Any:
        from ermrl.encoders import ReservoirVecEnv

        return ReservoirVecEnv(venv, config, seed=seed)


def test_an_encoder_with_a_bank_is_stepped_by_the_population_backend(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The population backend builds each agent's bank through the registry and steps them
    together (ReservoirBank.stack): its encodings equal the SB3 path's, and nothing in it
    names the encoder."""
    from ermrl.agents import make_vec_env, resolve_ppo_config
    from ermrl.config import TaskConfig
    from ermrl.population import PopulationEnvs, population_refusal

    monkeypatch.setitem(ENCODERS, "toybank", ToyBankEncoder())
    assert population_refusal(resolve_ppo_config("CartPole-v1"), encoder="toybank") is None
    task = TaskConfig("CartPole-v1", "positions")
    encoders = [
        EncoderConfig(reservoirs=(ToyBankParams(5, scale),), skip_connection=True)
        for scale in (0.5, 3.0)
    ]
    env_seeds, res_seeds = [1, 2], [7, 8]
    pop = PopulationEnvs(task, 2, env_seeds, encoders, res_seeds, None, 0.99)
    venvs = [make_vec_env(task, 2, env_seeds[p], encoders[p], res_seeds[p]) for p in range(2)]
    try:
        obs = pop.reset()
        for p, venv in enumerate(venvs):
            np.testing.assert_array_equal(obs[p], venv.reset())
        assert not np.array_equal(obs[0][:, :5], obs[1][:, :5])  # each agent its own scale
        rng = np.random.default_rng(0)
        ends = 0
        for _ in range(100):
            actions = rng.integers(0, 2, (2, 2))
            obs, _, _, dones, _, _ = pop.step(actions)
            for p, venv in enumerate(venvs):
                o, _, d, _ = venv.step(actions[p])
                np.testing.assert_array_equal(obs[p], o)
                np.testing.assert_array_equal(dones[p], d)
                ends += int(d.sum())
        assert ends > 0  # the reset path (step_agent) ran too
    finally:
        pop.close()
        for venv in venvs:
            venv.close()
