"""Encoders of observations, and the registry; the reservoir (reservoirpy-initialized echo state
networks, batched over a ``VecEnv``) is the reference one.

Each encoder is one module holding an [`Encoder`][ermrl.encoders.Encoder] subclass with its
settings, search space, ``ermrl evolve`` flags and test-phase agents (see
`ermrl.encoders._reservoir_encoder`); a line of `ENCODERS` registers it. The ``--encoder`` choices
and flags, the test phase's agents, the stored configurations and the report read this table.
"""

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from ermrl._config_base import AgentKind, ConfigError
from ermrl.encoders._base import Encoder
from ermrl.encoders._nvar import NVAREncoder
from ermrl.encoders._reservoir import (
    BIAS_INITS,
    ReservoirBank,
    ReservoirParams,
    ReservoirWeights,
    RTUParams,
    encoder_weights,
    reservoir_node,
    reservoir_seeds,
    reservoir_weights,
    rtu_weights,
)
from ermrl.encoders._reservoir_encoder import ReservoirEncoder, ReservoirSpace
from ermrl.encoders._rtu_encoder import RTUEncoder, RTUSpace
from ermrl.encoders._settings import EncoderConfig, EncoderParams, EncoderSpace, PerReservoirSpace

if TYPE_CHECKING:
    from ermrl.encoders._vec_env import ActionEncoder, ReservoirVecEnv

# Imported on first use (stable-baselines3 and torch under them): the CLI, the configuration
# and a plan read this package without wrapping an env.
_LAZY = {"ActionEncoder": "ermrl.encoders._vec_env", "ReservoirVecEnv": "ermrl.encoders._vec_env"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# One line per encoder (and its import above); the first is the reference, which a stored
# configuration without a ``family`` is read as. The order is the CLI's and the docs'.
ENCODERS: dict[str, Encoder] = {
    e.name: e for e in (ReservoirEncoder(), RTUEncoder(), NVAREncoder())
}


def encoder_for(config: object) -> Encoder:
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
    encoder = ENCODERS.get(name)
    if encoder is None:
        raise ConfigError(f"unknown encoder {name!r}; choose from {', '.join(ENCODERS)}")
    return encoder


def encoder_of_family(family: str | None) -> Encoder | None:
    """The registered encoder of ``family`` (``None``: the reference, the first registered);
    ``None`` when no encoder has that family (a learner's name, for a study of its genes)."""
    if family is None:
        return reference_encoder()
    return next((e for e in ENCODERS.values() if e.family == family), None)


def reference_encoder() -> Encoder:
    """The reference encoder, the first registered: what a configuration stored without a
    ``family`` is read as, and the family a study's name leaves out."""
    return next(iter(ENCODERS.values()))


def encoder_families() -> tuple[str, ...]:
    """The registered encoders' families, in registry order."""
    return tuple(e.family for e in ENCODERS.values())


def encoder_agents() -> Mapping[str, AgentKind]:
    """Every registered encoder's test-phase agents (name -> ``AgentKind``), in registry order."""
    return {name: kind for e in ENCODERS.values() for name, kind in e.agents.items()}


__all__ = [
    "BIAS_INITS",
    "ENCODERS",
    "ActionEncoder",
    "Encoder",
    "EncoderConfig",
    "EncoderParams",
    "EncoderSpace",
    "PerReservoirSpace",
    "ReservoirEncoder",
    "ReservoirParams",
    "ReservoirSpace",
    "RTUEncoder",
    "RTUParams",
    "RTUSpace",
    "encoder_agents",
    "encoder_families",
    "encoder_for",
    "encoder_of_family",
    "encoder_weights",
    "get_encoder",
    "reference_encoder",
    "rtu_weights",
    "ReservoirBank",
    "ReservoirVecEnv",
    "ReservoirWeights",
    "reservoir_node",
    "reservoir_seeds",
    "reservoir_weights",
]
