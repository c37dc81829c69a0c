"""VecNormalize (rl-baselines3-zoo's ``normalize`` key) with its statistics kept as plain data.

Training wraps the (reservoir-encoded) ``VecEnv`` in SB3's ``VecNormalize``, outermost, as the
zoo wraps the env it gives PPO. Evaluation and replays wrap theirs in a frozen copy: the running
statistics reached at the end of training, not updated (``training=False``), with raw rewards
(``norm_reward=False``).

The statistics are saved as JSON next to the model ([`stats_path`][ermrl.agents.stats_path]), never
with SB3's own ``VecNormalize.save``, which pickles the wrapper: reading a pickle can run code.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, cast

import numpy as np

from ermrl.config import PPOConfig
from ermrl.learners._normalize_stats import STATS_FORMAT, load_normalize_stats

__all__ = [
    "STATS_FORMAT",
    "normalize_env",
    "frozen_normalize_env",
    "normalize_stats",
    "stats_path",
    "save_normalize_stats",
    "load_normalize_stats",
]

SB3_DEFAULT_GAMMA = 0.99  # PPO's default discount, also VecNormalize's


def _gamma(ppo: PPOConfig) -> float:
    """The discount of reward normalization: PPO's own ``gamma``, as in rl-baselines3-zoo."""
    return float(ppo.hyperparams.get("gamma", SB3_DEFAULT_GAMMA))


def normalize_env(venv: Any, ppo: PPOConfig) -> Any:
    """Wrap a training ``VecEnv`` in ``VecNormalize`` when ``ppo.normalize`` asks for it.

    Args:
        venv: The training environments (reservoir-encoded or raw).
        ppo: PPO settings; ``ppo.normalize`` gives the wrapper's options.

    Returns:
        ``venv`` itself when ``ppo.normalize`` is ``None``, else a ``VecNormalize`` around it that
        updates its statistics.
    """
    if ppo.normalize is None:
        return venv
    from stable_baselines3.common.vec_env import VecNormalize

    n = ppo.normalize
    return VecNormalize(
        venv,
        training=True,
        norm_obs=n.norm_obs,
        norm_reward=n.norm_reward,
        clip_obs=float(n.clip_obs),
        clip_reward=float(n.clip_reward),
        gamma=_gamma(ppo),
        epsilon=float(n.epsilon),
    )


def normalize_stats(venv: Any) -> dict[str, Any]:
    """The settings and running statistics of a ``VecNormalize`` as plain JSON-ready data.

    Args:
        venv: A ``VecNormalize`` with a ``Box`` observation space.

    Returns:
        ``format``, the flags ``norm_obs``/``norm_reward``, ``clip_obs``, ``clip_reward``,
        ``gamma``, ``epsilon``, and ``obs_rms``/``ret_rms`` as ``{mean, var, count}`` (lists of
        floats for the observation, floats for the return). Floats are written with full
        precision, so a reload normalizes exactly as the original.
    """

    def rms(stats: Any) -> dict[str, Any]:
        return {
            "mean": np.asarray(stats.mean, np.float64).tolist(),
            "var": np.asarray(stats.var, np.float64).tolist(),
            "count": float(stats.count),
        }

    return {
        "format": STATS_FORMAT,
        "norm_obs": bool(venv.norm_obs),
        "norm_reward": bool(venv.norm_reward),
        "clip_obs": float(venv.clip_obs),
        "clip_reward": float(venv.clip_reward),
        "gamma": float(venv.gamma),
        "epsilon": float(venv.epsilon),
        "obs_rms": rms(venv.obs_rms) if venv.norm_obs else None,
        "ret_rms": rms(venv.ret_rms),
    }


def frozen_normalize_env(venv: Any, stats: dict[str, Any]) -> Any:
    """Wrap an evaluation or replay ``VecEnv`` with fixed statistics from training.

    Args:
        venv: The environments, built as in training (same mask, encoder and weights).
        stats: From [`normalize_stats`][ermrl.agents.normalize_stats] or
            [`load_normalize_stats`][ermrl.agents.load_normalize_stats].

    Returns:
        A ``VecNormalize`` that normalizes observations as training ended, never updates its
        statistics, and returns raw rewards.

    Raises:
        ValueError: the statistics do not fit the environment's observation size.
    """
    from stable_baselines3.common.running_mean_std import RunningMeanStd
    from stable_baselines3.common.vec_env import VecNormalize

    wrapped = VecNormalize(
        venv,
        training=False,
        norm_obs=bool(stats["norm_obs"]),
        norm_reward=False,
        clip_obs=float(stats["clip_obs"]),
        clip_reward=float(stats["clip_reward"]),
        gamma=float(stats["gamma"]),
        epsilon=float(stats["epsilon"]),
    )
    if stats["norm_obs"]:
        shape = tuple(venv.observation_space.shape)
        rms = RunningMeanStd(shape=shape)
        set_running_stats(rms, stats["obs_rms"])
        if rms.mean.shape != shape or rms.var.shape != shape:
            raise ValueError(
                f"normalization statistics of shape {rms.mean.shape} do not fit the "
                f"observation shape {shape}"
            )
        # SB3 infers ``obs_rms`` from its Dict-space branch (a dict of RunningMeanStd); for a Box
        # observation space it holds one RunningMeanStd, as here.
        wrapped.obs_rms = cast("dict[str, RunningMeanStd]", rms)
    set_running_stats(wrapped.ret_rms, stats["ret_rms"])
    return wrapped


def set_running_stats(rms: Any, stats: dict[str, Any]) -> None:
    """Set an SB3 ``RunningMeanStd`` to saved ``{mean, var, count}`` (float64 arrays, 0-d for the
    return's, as ``RunningMeanStd`` holds them)."""
    rms.mean = np.asarray(stats["mean"], np.float64)
    rms.var = np.asarray(stats["var"], np.float64)
    rms.count = float(stats["count"])


def stats_path(model_path: str | Path) -> Path:
    """Where the statistics of a model's normalization live: ``vecnormalize.json`` beside it.

    ``<folder>/model.zip`` gives ``<folder>/vecnormalize.json``; any other model name
    ``<folder>/<name>.zip`` gives ``<folder>/<name>.vecnormalize.json``.
    """
    path = Path(model_path)
    stem = path.name.removesuffix(".zip")
    return path.with_name("vecnormalize.json" if stem == "model" else f"{stem}.vecnormalize.json")


def save_normalize_stats(venv: Any, path: str | Path) -> None:
    """Write [`normalize_stats`][ermrl.agents.normalize_stats] of ``venv`` as JSON to ``path``."""
    Path(path).write_text(json.dumps(normalize_stats(venv), indent=1) + "\n")
