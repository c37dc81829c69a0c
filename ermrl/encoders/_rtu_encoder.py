"""``rtu``: frozen recurrent trace units, a complex-diagonal reservoir that evolution shapes.

The units of Elelimy et al. (2024) with fixed random weights (:class:`~ermrl.config.RTUParams`):
a linear recurrence of damped rotations, each unit with its own decay ``r`` and frequency
``theta``. Evolution searches the ranges those are drawn from, and the input scaling
(:class:`~ermrl.config.RTUSpace`), exactly as it searches an ESN's spectral radius and leak rate;
the learner (PPO by default) reads ``tanh`` of the states. It wraps the env in the same
:class:`~ermrl.encoders.ReservoirVecEnv` as the ESN (same inputs, resets and encoding options),
with the linear update of :func:`~ermrl.encoders.rtu_weights`.
"""

from __future__ import annotations

from ermrl.config import RTUSpace
from ermrl.encoders._reservoir_encoder import ReservoirEncoder

__all__ = ["RTUEncoder"]


class RTUEncoder(ReservoirEncoder):
    """The reservoir encoder's decoding and wrapper, with RTU layers and their search space."""

    name = "rtu"
    description = "recurrent trace units with fixed random weights (a complex-diagonal reservoir)"
    family = "rtu"
    space_cls = RTUSpace
