"""Reservoir encoders: reservoirpy-initialized echo state networks, batched over a ``VecEnv``."""

from ermrl.encoders._reservoir import (
    ReservoirBank,
    ReservoirWeights,
    reservoir_node,
    reservoir_seeds,
    reservoir_weights,
)
from ermrl.encoders._vec_env import ActionEncoder, ReservoirVecEnv

__all__ = [
    "ActionEncoder",
    "ReservoirBank",
    "ReservoirVecEnv",
    "ReservoirWeights",
    "reservoir_node",
    "reservoir_seeds",
    "reservoir_weights",
]
