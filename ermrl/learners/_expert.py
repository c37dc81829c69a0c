"""A trained expert as imitation learners read it: its folder of plain files, loaded without pickles.

An expert folder holds:

- ``expert.json``: `ExpertInfo` (env id, algorithm, the learner settings used, steps,
  seed, wall time, the evaluation returns, library versions, observation and action shapes);
- ``policy.pt``: the policy's ``state_dict()`` as plain tensors, read with
  ``torch.load(..., weights_only=True)``
  ([`ermrl.learners._policy_io.load_policy`][ermrl.agents.load_policy]);
- ``vecnormalize.json``: only when the settings use ``normalize``, the observation statistics
  reached at the end of training ([`ermrl.agents.normalize_stats`][ermrl.agents.normalize_stats]).

Nothing in it is a pickle, so loading an expert someone else trained cannot run code. The
expert always sees the task's full observation (``observe="all"``): imitation learners that see
a masked observation (`ermrl.learners._dagger_model`) query it on the full one. Loading
lives here, below the training loop, because those learners load their expert when they are
built; training and evaluating experts is `ermrl.experts`'s work, which re-exports
everything here.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pickle  # only for its error class: nothing here unpickles
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ermrl.config import ConfigError, PPOConfig, from_dict, to_dict

__all__ = [
    "EXPERT_FILE",
    "EXPERT_FORMAT",
    "NORMALIZE_FILE",
    "Expert",
    "ExpertInfo",
    "expert_algos",
    "is_expert_folder",
    "load_expert",
]

EXPERT_FORMAT = "ermrl.expert/1"
EXPERT_FILE = "expert.json"
NORMALIZE_FILE = "vecnormalize.json"


def expert_algos() -> tuple[str, ...]:
    """The learners an expert can be trained with, in registry order.

    Those whose agents are plain SB3 policies acting on one observation: not recurrent, no
    settings of their own and no wrapper of their own (``ppo`` and ``sac``).
    """
    from ermrl.learners import LEARNERS, Learner

    return tuple(
        name
        for name, learner in LEARNERS.items()
        if not learner.recurrent
        and not learner.own_keys
        and type(learner).wrap_env is Learner.wrap_env
        and type(learner).build is Learner.build
    )


def is_expert_folder(path: str | Path) -> bool:
    """Whether ``path`` is a folder holding an expert (its ``expert.json``)."""
    return (Path(path) / EXPERT_FILE).is_file()


@dataclass(frozen=True)
class ExpertInfo:
    """What ``expert.json`` records about an expert.

    Attributes:
        env_id: The task (the expert sees its full observation).
        algo: The learner that trained it (a name of `expert_algos`).
        ppo: The learner settings used (``ppo.learner == algo``).
        steps: Training steps asked for.
        env_steps: Environment steps actually taken (PPO rounds up to whole rollouts).
        seed: The training seed ([`ermrl.agents.derive_seeds`][ermrl.agents.derive_seeds]); the
            recorded evaluation is `evaluate_expert` with this seed.
        wall_seconds: Wall-clock time of training and evaluation.
        eval_returns: Returns of the deterministic evaluation episodes, in order.
        train_returns: Returns of the last (at most 10) training episodes.
        observation_shape: Shape of one full observation.
        action_shape: Shape of one action.
        versions: Library versions (``ermrl``, ``stable_baselines3``, ``torch``, ...).
        command: The command line that trained it, if any.
    """

    env_id: str
    algo: str
    ppo: PPOConfig
    steps: int
    env_steps: int
    seed: int
    wall_seconds: float
    eval_returns: tuple[float, ...]
    train_returns: tuple[float, ...]
    observation_shape: tuple[int, ...]
    action_shape: tuple[int, ...]
    versions: Mapping[str, str]
    command: str | None = None

    @property
    def eval_mean(self) -> float:
        """Mean evaluation return."""
        return float(np.mean(self.eval_returns)) if self.eval_returns else math.nan

    @property
    def eval_std(self) -> float:
        """Standard deviation of the evaluation returns (``np.std``, as SB3 reports it)."""
        return float(np.std(self.eval_returns)) if self.eval_returns else math.nan

    @property
    def normalized(self) -> bool:
        """Whether the policy reads normalized observations (``vecnormalize.json``)."""
        return self.ppo.normalize is not None

    def to_dict(self) -> dict[str, Any]:
        """The JSON document of ``expert.json`` (with the derived eval mean and std)."""
        return {
            "format": EXPERT_FORMAT,
            "env_id": self.env_id,
            "observe": "all",
            "algo": self.algo,
            "ppo": to_dict(self.ppo),
            "steps": self.steps,
            "env_steps": self.env_steps,
            "seed": self.seed,
            "wall_seconds": self.wall_seconds,
            "eval": {
                "n_episodes": len(self.eval_returns),
                "seed": self.seed,
                "deterministic": True,
                "mean": self.eval_mean,
                "std": self.eval_std,
                "returns": list(self.eval_returns),
            },
            "train_returns": list(self.train_returns),
            "observation_shape": list(self.observation_shape),
            "action_shape": list(self.action_shape),
            "versions": dict(self.versions),
            "command": self.command,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ExpertInfo:
        """Read [`to_dict`][ermrl.config.to_dict]'s document.

        Raises:
            ValueError: it is not an expert document of this format.
        """
        if not isinstance(data, Mapping) or data.get("format") != EXPERT_FORMAT:
            raise ValueError(f"not an ermrl expert ({EXPERT_FORMAT})")
        try:
            return cls(
                env_id=str(data["env_id"]),
                algo=str(data["algo"]),
                ppo=from_dict(PPOConfig, data["ppo"]),
                steps=int(data["steps"]),
                env_steps=int(data["env_steps"]),
                seed=int(data["seed"]),
                wall_seconds=float(data["wall_seconds"]),
                eval_returns=tuple(float(r) for r in data["eval"]["returns"]),
                train_returns=tuple(float(r) for r in data.get("train_returns", ())),
                observation_shape=tuple(int(n) for n in data["observation_shape"]),
                action_shape=tuple(int(n) for n in data["action_shape"]),
                versions={str(k): str(v) for k, v in data.get("versions", {}).items()},
                command=data.get("command"),
            )
        except (KeyError, TypeError, ValueError, AttributeError, ConfigError) as err:
            raise ValueError(f"malformed expert document ({type(err).__name__}: {err})") from None


class Expert:
    """A trained expert, rebuilt from plain files; it acts on the task's full observation.

    Attributes:
        path: The expert folder.
        info: What ``expert.json`` records (`ExpertInfo`).
        env_id: The task.
        algo: The learner that trained it.
        normalize_stats: The observation statistics `predict` applies (``None`` without
            ``normalize``).
    """

    def __init__(
        self,
        path: Path,
        info: ExpertInfo,
        model: Any,
        normalize_stats: dict[str, Any] | None,
    ) -> None:
        self.path = path
        self.info = info
        self.env_id = info.env_id
        self.algo = info.algo
        self.normalize_stats = normalize_stats
        self._model = model
        self._obs_mean: np.ndarray | None = None
        self._obs_scale: np.ndarray | None = None
        if normalize_stats is not None and normalize_stats["norm_obs"]:
            obs = normalize_stats["obs_rms"]
            self._obs_mean = np.asarray(obs["mean"], np.float64)
            self._obs_scale = np.sqrt(
                np.asarray(obs["var"], np.float64) + float(normalize_stats["epsilon"])
            )
            if self._obs_mean.shape != info.observation_shape:
                raise ValueError(
                    f"{path}: normalization statistics of shape {self._obs_mean.shape} do not "
                    f"fit the observation shape {info.observation_shape}"
                )

    @property
    def policy(self) -> Any:
        """The SB3 policy (a ``torch.nn.Module``, in evaluation mode)."""
        return self._model.policy

    def normalize(self, observation: np.ndarray) -> np.ndarray:
        """The policy's input for raw observations, as ``VecNormalize`` makes it.

        Args:
            observation: Shape ``(obs_dim,)`` or ``(n, obs_dim)``, raw.

        Returns:
            The same shape, normalized and clipped (``float32``) when the expert trained with
            ``normalize``; otherwise ``observation`` unchanged.
        """
        if self._obs_mean is None or self._obs_scale is None or self.normalize_stats is None:
            return observation
        clip = float(self.normalize_stats["clip_obs"])
        normalized = np.clip((observation - self._obs_mean) / self._obs_scale, -clip, clip)
        return normalized.astype(np.float32)

    def predict(self, observation: np.ndarray, deterministic: bool = True) -> np.ndarray:
        """The expert's actions for raw full observations.

        Args:
            observation: One observation, shape ``(obs_dim,)``, or a batch ``(n, obs_dim)``;
                raw (the expert applies its own normalization).
            deterministic: The policy's mean action (``False`` samples).

        Returns:
            Actions of shape ``action_shape`` or ``(n, *action_shape)``, within the action
            space (SB3's ``predict``: scaled back for SAC, clipped for PPO).
        """
        obs = np.asarray(observation)
        if obs.shape[-len(self.info.observation_shape) :] != self.info.observation_shape:
            raise ValueError(
                f"expected observations of shape {self.info.observation_shape} or "
                f"(n, {', '.join(map(str, self.info.observation_shape))}), got {obs.shape}"
            )
        actions, _ = self._model.predict(self.normalize(obs), deterministic=deterministic)
        return np.asarray(actions)

    def __repr__(self) -> str:
        return (
            f"Expert({self.env_id!r}, algo={self.algo!r}, eval {self.info.eval_mean:.1f} ± "
            f"{self.info.eval_std:.1f}, path={str(self.path)!r})"
        )


def _read_info(path: Path) -> ExpertInfo:
    """Read ``expert.json`` of ``path``; its env id must be registered (never imported).

    Raises:
        FileNotFoundError: no such folder or no ``expert.json``.
        ValueError: the document is malformed, or its env id is not a registered id
            ([`ermrl.envs.UnknownEnvError`][ermrl.envs.UnknownEnvError], naming the file).
    """
    from ermrl.envs import check_registered_env_id

    file = path / EXPERT_FILE
    if not path.is_dir():
        raise FileNotFoundError(f"no expert folder {str(path)!r}")
    if not file.is_file():
        raise FileNotFoundError(f"{str(path)!r} holds no expert ({EXPERT_FILE} is missing)")
    try:
        data = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{file}: not a JSON file ({err})") from None
    try:
        info = ExpertInfo.from_dict(data)
    except ValueError as err:
        raise ValueError(f"{file}: {err}") from None
    check_registered_env_id(info.env_id, file)  # never import a module the file names
    return info


def _loading_config(ppo: PPOConfig) -> PPOConfig:
    """The settings to rebuild the network with: an off-policy replay buffer of one entry.

    The buffer (10⁶ transitions in the zoo's SAC settings) does not shape the network, and a
    loaded expert never trains.
    """
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

    from ermrl.learners import get_learner

    if issubclass(get_learner(ppo.learner).algorithm(), OffPolicyAlgorithm):
        return dataclasses.replace(ppo, hyperparams={**ppo.hyperparams, "buffer_size": 1})
    return ppo


def _full_observation_env(env_id: str) -> Any:
    """One environment of ``env_id`` on its full observation, as training wraps it (a
    ``Monitor`` in a ``DummyVecEnv``): the spaces the expert's network is rebuilt on."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    from ermrl.envs import make_env

    return DummyVecEnv([lambda: Monitor(make_env(env_id, "all"))])


def load_expert(path: str | Path) -> Expert:
    """Load an expert folder (written by `ermrl.experts.train_expert`); nothing is
    unpickled.

    Args:
        path: The expert folder.

    Returns:
        The expert, ready for `Expert.predict`.

    Raises:
        FileNotFoundError: the folder or one of its files is missing.
        ValueError: a file is corrupt or does not fit the recorded settings.
    """
    from ermrl.learners._normalize_stats import load_normalize_stats
    from ermrl.learners._policy_io import POLICY_FILE, load_policy

    folder = Path(path)
    info = _read_info(folder)
    if info.algo not in expert_algos() or info.ppo.learner != info.algo:
        raise ValueError(f"{folder / EXPERT_FILE}: unknown expert algorithm {info.algo!r}")
    policy_file = folder / POLICY_FILE
    if not policy_file.is_file():
        raise FileNotFoundError(f"{str(folder)!r} holds no {POLICY_FILE}")
    stats = None
    if info.normalized:
        stats_file = folder / NORMALIZE_FILE
        if not stats_file.is_file():
            raise FileNotFoundError(f"{str(folder)!r} holds no {NORMALIZE_FILE}")
        stats = load_normalize_stats(stats_file)
    env = _full_observation_env(info.env_id)
    try:
        shape = tuple(env.observation_space.shape)
        if shape != info.observation_shape:
            raise ValueError(
                f"{folder / EXPERT_FILE}: recorded observation shape {info.observation_shape} "
                f"but {info.env_id} has {shape}"
            )
        try:
            model = load_policy(policy_file, _loading_config(info.ppo), env)
        except ConfigError as err:  # settings that do not build: the fault of expert.json
            raise ValueError(f"{folder / EXPERT_FILE}: {err}") from None
        except (RuntimeError, EOFError, OSError, pickle.UnpicklingError) as err:  # not torch's
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ValueError(f"{policy_file}: not a policy file ({first})") from None
    finally:
        env.close()
    return Expert(folder, info, model, stats)
