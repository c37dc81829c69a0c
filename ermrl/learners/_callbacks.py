"""SB3's callback protocol for the learners that are not SB3 algorithms (hebbian, BC, DAgger).

Their models' ``learn(total_timesteps, callback=...)`` takes what SB3's ``learn`` takes: one
``BaseCallback``, a list of them, or ``None``, so that ermrl's training loop
([`ermrl.agents`][ermrl.agents]) drives every learner with the same callbacks.
"""

from __future__ import annotations

from typing import Any

__all__ = ["as_callback"]


def as_callback(callback: Any) -> Any:
    """``learn``'s callback as one SB3 ``BaseCallback`` (a list becomes a ``CallbackList``).

    Args:
        callback: A ``BaseCallback``, a list of them, or ``None``.

    Returns:
        The callback, or ``None``.

    Raises:
        TypeError: ``callback`` is not an SB3 callback.
    """
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList

    if isinstance(callback, list):
        callback = CallbackList(callback)
    if callback is not None and not isinstance(callback, BaseCallback):
        raise TypeError(f"callback must be an SB3 BaseCallback, got {type(callback).__name__}")
    return callback
