"""A trained agent as an object: ``predict``, ``save`` and a matching ``load``, with no pickle.

A [`Model`][ermrl.agents.Model] is a learner trained on one seed in front of an encoder (or on
the raw observations): the Stable-Baselines3 algorithm, and the plain settings that rebuild the
environment it acts in (task, encoder, learner, seed). ``save`` writes a folder of plain files:
``policy.pt`` (the policy's ``state_dict``, tensors only: [`save_policy`][ermrl.agents.save_policy]),
``model.json`` (the settings) and, when the learner normalizes observations,
``vecnormalize.json``. ``load`` reads them back as every file ermrl reads is read: tensors with
``torch.load(..., weights_only=True)``, the env id only when it is registered, nothing
unpickled. The reservoir weights are not stored: they are re-created from the seed, as training
created them ([`derive_seeds`][ermrl.agents.derive_seeds]), as a test phase's replay does.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ermrl._io import write_atomic
from ermrl.config import BudgetConfig, ConfigError, EncoderConfig, PPOConfig, TaskConfig

if TYPE_CHECKING:
    import numpy as np

    from ermrl.agents._train import RunResult

__all__ = ["MODEL_FORMAT", "Model", "train_model"]

MODEL_FORMAT = "ermrl-model/1"
_SETTINGS = "model.json"
_POLICY = "policy.pt"
_STATS = "vecnormalize.json"


class Model:
    """A trained learner with SB3's ``predict``, and a pickle-free ``save`` and ``load``.

    Its ``predict`` takes the observations of [`get_env`][ermrl.agents.Model.get_env]: the
    task's, encoded by the reservoir the model trained with (the reservoir reads the previous
    action and reward too, which an observation alone does not hold), normalized as training
    ended. Stable-Baselines3's helpers that take a model (``evaluate_policy``) take it.

    Attributes:
        agent: The Stable-Baselines3 algorithm (``PPO``, ...) that acts.
        task: The task and its observation mask.
        encoder: The encoder's settings (``None``: the learner sees the raw observations).
        ppo: The learner's settings.
        seed: The run's seed; the reservoir weights derive from it.
        normalize: The observation normalization's statistics (``None``: no normalization).
        result: What training measured (``episode_returns``, ``env_steps``, ...;
            ``None`` for a loaded model).
    """

    def __init__(
        self,
        agent: Any,
        task: TaskConfig,
        encoder: EncoderConfig | None,
        ppo: PPOConfig,
        seed: int,
        normalize: dict[str, Any] | None = None,
        result: RunResult | None = None,
    ) -> None:
        self.agent = agent
        self.task = task
        self.encoder = encoder
        self.ppo = ppo
        self.seed = int(seed)
        self.normalize = normalize
        self.result = result

    def __repr__(self) -> str:
        encoder = "raw observations" if self.encoder is None else f"{self.encoder.family} encoder"
        return f"Model({self.ppo.learner} on {self.task.label}, {encoder}, seed {self.seed})"

    def get_env(self, n_envs: int = 1, seed: int | None = None) -> Any:
        """A fresh environment the model acts in, built as training built it.

        Args:
            n_envs: Environments of the ``VecEnv``.
            seed: Seed of the episodes (``None``: the run's evaluation seed).

        Returns:
            A ``VecEnv``: the task, the encoder with the run's reservoir weights, the
            normalization frozen at training's end, the learner's own wrappers.
        """
        from ermrl.agents._normalize import frozen_normalize_env
        from ermrl.agents._train import derive_seeds, make_vec_env
        from ermrl.learners import get_learner

        seeds = derive_seeds(self.seed)
        env_seed = seeds.eval_env if seed is None else seed
        env = make_vec_env(self.task, n_envs, env_seed, self.encoder, seeds.reservoir)
        if self.normalize is not None:
            env = frozen_normalize_env(env, self.normalize)
        return get_learner(self.ppo.learner).wrap_env(env, self.ppo)

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """The action for an observation of [`get_env`][ermrl.agents.Model.get_env], as SB3's
        ``predict``: ``(action, state)``; a recurrent learner carries its ``state``."""
        return self.agent.predict(
            observation, state=state, episode_start=episode_start, deterministic=deterministic
        )

    def evaluate(
        self, n_episodes: int = 10, *, deterministic: bool = True, seed: int | None = None
    ) -> list[float]:
        """The returns of ``n_episodes`` episodes on a fresh [`get_env`][ermrl.agents.Model.get_env]
        (the same seed: the same returns)."""
        from stable_baselines3.common.evaluation import evaluate_policy

        env = self.get_env(seed=seed)
        try:
            returns, _ = evaluate_policy(
                self, env, n_eval_episodes=n_episodes, deterministic=deterministic,
                return_episode_rewards=True,
            )  # fmt: skip
        finally:
            env.close()
        assert isinstance(returns, list)
        return [float(r) for r in returns]

    def save(self, path: str | Path) -> Path:
        """Write the model to the folder ``path``: ``policy.pt`` (tensors), ``model.json``
        (the settings) and ``vecnormalize.json`` (with normalization); no pickle.

        Returns:
            The folder.
        """
        from ermrl.config import to_dict
        from ermrl.learners._policy_io import save_policy

        folder = Path(path)
        folder.mkdir(parents=True, exist_ok=True)
        settings = {
            "format": MODEL_FORMAT,
            "task": to_dict(self.task),
            "encoder": None if self.encoder is None else to_dict(self.encoder),
            "ppo": to_dict(self.ppo),
            "seed": self.seed,
        }
        save_policy(self.agent, folder / _POLICY)
        (folder / _STATS).unlink(missing_ok=True)
        if self.normalize is not None:
            write_atomic(folder / _STATS, json.dumps(self.normalize, indent=1) + "\n")
        write_atomic(folder / _SETTINGS, json.dumps(settings, indent=1) + "\n")
        return folder

    @classmethod
    def load(cls, path: str | Path) -> Model:
        """Read a model written by [`save`][ermrl.agents.Model.save]; nothing is unpickled.

        Raises:
            ConfigError: In one line naming the file: no saved model there, settings that are
                not ermrl's or do not build, an unregistered env id, or a ``policy.pt`` that is
                not plain tensors of this network.
        """
        from ermrl.agents._normalize import load_normalize_stats
        from ermrl.config import from_dict
        from ermrl.envs import UnknownEnvError, check_registered_env_id
        from ermrl.learners._policy_io import load_policy

        folder = Path(path)
        where = folder / _SETTINGS
        try:
            data = json.loads(where.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ConfigError(f"{folder} holds no saved model (no {_SETTINGS})") from None
        except (OSError, ValueError) as err:
            raise ConfigError(f"{where}: not a JSON file ({_first_line(err)})") from None
        if not isinstance(data, dict) or data.get("format") != MODEL_FORMAT:
            raise ConfigError(f"{where}: not an ermrl model ({MODEL_FORMAT})")
        try:
            check_registered_env_id((data.get("task") or {}).get("env_id"), where)
            task = from_dict(TaskConfig, data["task"])
            encoder = None if data["encoder"] is None else from_dict(EncoderConfig, data["encoder"])
            ppo = from_dict(PPOConfig, data["ppo"])
            seed = data["seed"]
            if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
                raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
            stats = load_normalize_stats(folder / _STATS) if (folder / _STATS).is_file() else None
        except UnknownEnvError as err:
            raise ConfigError(str(err)) from None
        except Exception as err:  # noqa: BLE001 - any damage: wrong types, keys, nesting
            raise ConfigError(f"{where}: its settings do not build ({_first_line(err)})") from None
        if ppo.normalize is not None and stats is None:
            raise ConfigError(f"{folder / _STATS} not found: the model normalizes observations")
        model = cls(None, task, encoder, ppo, seed, stats)
        env = model.get_env()
        try:
            model.agent = load_policy(folder / _POLICY, ppo, env)
        except (ValueError, FileNotFoundError) as err:
            raise ConfigError(_first_line(err)) from None
        finally:
            env.close()
        return model


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0][:300] if text else type(err).__name__


def train_model(
    task: TaskConfig,
    encoder: EncoderConfig | None,
    ppo: PPOConfig,
    total_timesteps: int,
    seed: int = 0,
) -> Model:
    """Train a learner on ``task`` in front of ``encoder`` for one seed, as a run of the test
    phase trains it ([`train_agent`][ermrl.agents.train_agent]), and keep it as a [`Model`][ermrl.agents.Model].

    Args:
        task: The task and its mask.
        encoder: The encoder's settings (``None``: the raw observations).
        ppo: The learner's settings.
        total_timesteps: Env steps (an on-policy learner rounds up to whole rollouts).
        seed: Seeds the reservoir weights, the environments and the learner.

    Raises:
        ConfigError: ``total_timesteps`` or ``seed`` out of range.
        TrainingDiverged: NaN or infinite values appeared in training.
    """
    from stable_baselines3.common.callbacks import BaseCallback

    from ermrl.agents._normalize import normalize_stats
    from ermrl.agents._train import train_agent

    for name, value, low in (("total_timesteps", total_timesteps, 1), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ConfigError(f"{name} must be an integer >= {low}, got {value!r}")
    # "eval" with evaluate=False: no measure is needed, so no episode has to end.
    budget = BudgetConfig(training_steps=total_timesteps, fitness="eval", n_reports=0)
    kept: dict[str, Any] = {}

    class Keep(BaseCallback):
        def _on_step(self) -> bool:
            return True

        def _on_training_end(self) -> None:
            kept["agent"] = self.model
            normalized = self.model.get_vec_normalize_env()
            kept["stats"] = None if normalized is None else normalize_stats(normalized)

    result = train_agent(task, encoder, ppo, budget, seed, evaluate=False, callbacks=[Keep()])
    return Model(kept["agent"], task, encoder, ppo, seed, kept["stats"], result)
