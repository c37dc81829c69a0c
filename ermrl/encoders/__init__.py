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
    encoder_weights,
    reservoir_node,
    reservoir_seeds,
    reservoir_weights,
    rtu_weights,
)
from ermrl.encoders._reservoir_encoder import ReservoirEncoder
from ermrl.encoders._rtu_encoder import RTUEncoder
from ermrl.encoders._vec_env import ActionEncoder, ReservoirVecEnv

ENCODERS: Mapping[str, Encoder] = {e.name: e for e in (ReservoirEncoder(), RTUEncoder())}


def encoder_for(config: Any) -> Encoder:
    """The registered encoder whose settings class ``config`` is an instance of.

    Raises:
        TypeError: no registered encoder takes such settings.
    """
    for encoder in ENCODERS.values():
        if encoder.accepts(config):
            return encoder
    raise TypeError(f"no registered encoder takes {type(config).__name__} settings")


def get_encoder(name: str) -> Encoder:
    """The encoder registered as ``name``.

    Raises:
        ConfigError: no such encoder (the message lists the registered ones).
    """
    from ermrl.config import ConfigError

    encoder = ENCODERS.get(name)
    if encoder is None:
        raise ConfigError(f"unknown encoder {name!r}; choose from {', '.join(ENCODERS)}")
    return encoder


__all__ = [
    "ENCODERS",
    "ActionEncoder",
    "Encoder",
    "ReservoirEncoder",
    "RTUEncoder",
    "encoder_for",
    "encoder_weights",
    "get_encoder",
    "rtu_weights",
    "ReservoirBank",
    "ReservoirVecEnv",
    "ReservoirWeights",
    "reservoir_node",
    "reservoir_seeds",
    "reservoir_weights",
]
