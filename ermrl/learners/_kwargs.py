"""A learner's algorithm arguments from its settings: schedules and activations by name.

[`PPOConfig`][ermrl.config.PPOConfig] holds plain data read from YAML, ``--ppo`` or a study; this
module turns it into the keyword arguments of the algorithm (``PPO(...)``, ``SAC(...)``): a
``lin_X`` string becomes a linear schedule, a ``policy_kwargs`` ``activation_fn`` name its torch
class. Resolving the settings themselves (tables, overrides, checks) is
[`ermrl.agents`][ermrl.agents]'s work.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from torch import nn

from ermrl.config import ConfigError, PPOConfig

__all__ = ["ACTIVATIONS", "ERMRL_KEYS", "activation_fn", "linear_schedule", "ppo_kwargs"]

# Keys that ermrl itself reads (never passed to PPO(...)): the number of envs, and
# rl-baselines3-zoo's `normalize` (VecNormalize).
ERMRL_KEYS = frozenset({"n_envs", "normalize"})

# The activations a table or --ppo may name as ``policy_kwargs: {activation_fn: relu}``.
# rl-baselines3-zoo writes ``activation_fn=nn.ReLU`` and evaluates it; ermrl looks the name up
# here and never imports or evaluates what a file says.
ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
    "relu": nn.ReLU,
    "elu": nn.ELU,
    "leaky_relu": nn.LeakyReLU,
}


def activation_fn(name: Any, where: str = "policy_kwargs") -> type[nn.Module]:
    """The torch module class of an activation named in ``policy_kwargs`` (`ACTIVATIONS`).

    Args:
        name: The name read from a table, ``--ppo`` or a study (``"relu"``).
        where: Where the value comes from, for the message.

    Returns:
        Its class (``nn.ReLU``), for SB3's ``policy_kwargs``.

    Raises:
        ConfigError: any other value, listing the valid names.
    """
    if isinstance(name, str) and name in ACTIVATIONS:
        return ACTIVATIONS[name]
    raise ConfigError(
        f"{where}: policy_kwargs activation_fn {name!r} is not one of {', '.join(ACTIVATIONS)}"
    )


def linear_schedule(initial: float) -> Callable[[float], float]:
    """A schedule that goes linearly from ``initial`` to 0 over training."""

    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule


def ppo_kwargs(config: PPOConfig) -> dict[str, Any]:
    """Keyword arguments for ``PPO(...)`` from a config (``lin_X`` strings become schedules,
    a ``policy_kwargs`` ``activation_fn`` name its class from `ACTIVATIONS`)."""
    kwargs: dict[str, Any] = {}
    for key, value in config.hyperparams.items():
        if key in ERMRL_KEYS:
            continue  # read by ermrl (PPOConfig fields), not a PPO(...) argument
        if key == "policy_kwargs" and isinstance(value, Mapping) and "activation_fn" in value:
            value = {**value, "activation_fn": activation_fn(value["activation_fn"], "PPO")}
        if isinstance(value, str) and value.startswith("lin_"):
            try:
                value = linear_schedule(float(value[4:]))
            except ValueError:
                raise ConfigError(
                    f"PPO {key}={value!r}: a linear schedule is lin_<number>, e.g. lin_3e-4"
                ) from None
        kwargs[key] = value
    return kwargs
