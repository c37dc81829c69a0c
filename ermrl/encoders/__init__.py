"""Encoders of observations, and the registry; the reservoir (reservoirpy-initialized echo state
networks, batched over a ``VecEnv``) is the reference one.

Each encoder is one module holding an :class:`Encoder` subclass (see
:mod:`ermrl.encoders._reservoir_encoder`); a line of :data:`ENCODERS` registers it.
"""

from collections.abc import Mapping
from typing import Any

from ermrl.encoders._base import Encoder
from ermrl.encoders._reservoir import (
    ReservoirBank,
    ReservoirWeights,
    reservoir_node,
    reservoir_seeds,
    reservoir_weights,
)
from ermrl.encoders._reservoir_encoder import ReservoirEncoder
from ermrl.encoders._vec_env import ActionEncoder, ReservoirVecEnv

ENCODERS: Mapping[str, Encoder] = {e.name: e for e in (ReservoirEncoder(),)}


def encoder_for(config: Any) -> Encoder:
    """The registered encoder whose settings class ``config`` is an instance of.

    Raises:
        TypeError: no registered encoder takes such settings.
    """
    for encoder in ENCODERS.values():
        if isinstance(config, encoder.config_cls):
            return encoder
    raise TypeError(f"no registered encoder takes {type(config).__name__} settings")


__all__ = [
    "ENCODERS",
    "ActionEncoder",
    "Encoder",
    "ReservoirEncoder",
    "encoder_for",
    "ReservoirBank",
    "ReservoirVecEnv",
    "ReservoirWeights",
    "reservoir_node",
    "reservoir_seeds",
    "reservoir_weights",
]
