"""A trained PPO policy as plain tensors: saved beside ``model.zip``, read back without pickles.

SB3's ``model.zip`` holds cloudpickled objects (``data``) and ``torch.save`` files that
``PPO.load`` unpickles: a crafted ``model.zip`` runs code when it is loaded. ermrl therefore
also saves every trained policy's weights as ``policy.pt``, a ``torch.save`` of the policy's
``state_dict()`` (names to tensors only), and reads policies back only from that file with
``torch.load(..., weights_only=True)``. The network is rebuilt from the run's PPO settings
([`PPOConfig`][ermrl.config.PPOConfig], plain JSON in the run folder) and the environment's spaces;
``model.zip`` is still written for users who want SB3's format, and ermrl never reads it.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ermrl._io import write_atomic

if TYPE_CHECKING:
    from stable_baselines3 import PPO

    from ermrl.config import PPOConfig

__all__ = ["POLICY_FILE", "load_policy", "policy_path", "save_policy"]

POLICY_FILE = "policy.pt"


def policy_path(model_path: str | Path) -> Path:
    """Where a model's plain policy weights live: ``policy.pt`` beside it.

    ``<folder>/model.zip`` gives ``<folder>/policy.pt``; any other model name
    ``<folder>/<name>.zip`` gives ``<folder>/<name>.policy.pt``.
    """
    path = Path(model_path)
    stem = path.name.removesuffix(".zip")
    return path.with_name(POLICY_FILE if stem == "model" else f"{stem}.{POLICY_FILE}")


def save_policy(model: PPO, path: str | Path) -> None:
    """Save ``model.policy.state_dict()`` (CPU tensors only) to ``path``, atomically.

    The file gets the usual permissions, ``0o666`` less the umask, as every file of a run
    folder (`ermrl._io.write_atomic`).

    Args:
        model: The trained model.
        path: The file (see [`policy_path`][ermrl.agents.policy_path]).
    """
    import torch

    state = {name: tensor.detach().cpu() for name, tensor in model.policy.state_dict().items()}
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_atomic(path, buffer.getvalue())


def load_policy(path: str | Path, ppo: PPOConfig, env: Any) -> PPO:
    """Rebuild a trained agent from its plain weights; nothing is unpickled.

    The agent is built as training built it (by the learner of ``ppo.learner``, on the CPU),
    then its policy takes the weights of ``path``, read with
    ``torch.load(..., weights_only=True)`` (tensors and plain containers only).

    Args:
        path: A ``policy.pt`` written by [`save_policy`][ermrl.agents.save_policy].
        ppo: The run's learner settings (its ``policy_kwargs`` fix the network's shape).
        env: A VecEnv with the observation and action spaces the agent trained on (wrapped by
            the learner's [`wrap_env`][ermrl.learners.Learner.wrap_env], as in training).

    Returns:
        The agent, ready for ``predict``; it is not meant to be trained further.

    Raises:
        ValueError: The file cannot be read (truncated, not a torch file, a pickle of objects
            other than tensors) or does not hold a state dict of this network.
        ConfigError: ``ppo`` does not build an agent (``policy_kwargs={net_arch: foo}``, a
            string where a number belongs, ...).
    """
    import pickle

    import torch

    from ermrl.config import ConfigError
    from ermrl.learners import get_learner

    try:
        with warnings.catch_warnings():  # torch's on a foreign pickle protocol: it refuses it
            warnings.simplefilter("ignore")
            state = torch.load(str(path), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:  # not torch's format, or objects other than tensors
        raise ValueError(
            f"{path} is not plain tensors (a damaged file, or a pickle of other objects, which "
            "is never loaded)"
        ) from None
    except Exception as err:  # noqa: BLE001 - whatever torch raises on a file it cannot read
        text = str(err).strip()
        first = text.splitlines()[0][:200] if text else type(err).__name__
        raise ValueError(f"{path} cannot be read as plain tensors ({first})") from None
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()
    ):
        raise ValueError(f"{path} does not hold a policy state dict (names to tensors)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # rollout-size hints about a buffer never filled here
            model = get_learner(ppo.learner).build(env, ppo, device="cpu")
    except Exception as err:  # noqa: BLE001 - whatever SB3 or torch refuses (net_arch: foo, ...)
        text = str(err).strip()
        first = text.splitlines()[0] if text else type(err).__name__
        raise ConfigError(
            f"the recorded {ppo.learner} settings cannot build the agent ({first})"
        ) from None
    try:
        model.policy.load_state_dict(state)
    except RuntimeError as err:  # torch's first line ends with ':', its second says what
        lines = [line.strip() for line in str(err).strip().splitlines() if line.strip()]
        first = " ".join(lines[:2])[:300]
        raise ValueError(
            f"{path} does not match the run's PPO settings and spaces: {first}"
        ) from None
    model.policy.set_training_mode(False)
    return model
