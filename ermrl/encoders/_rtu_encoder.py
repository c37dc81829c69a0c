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

from collections.abc import Mapping
from typing import Any

from ermrl.config import EncoderConfig, RTUSpace
from ermrl.encoders._base import Encoder

__all__ = ["RTUEncoder"]


class RTUEncoder(Encoder):
    name = "rtu"
    description = "recurrent trace units with fixed random weights (a complex-diagonal reservoir)"
    place = "env"
    family = "rtu"
    config_cls = EncoderConfig
    space_cls = RTUSpace

    def decode(
        self, space: RTUSpace, params: Mapping[str, float], base: EncoderConfig
    ) -> EncoderConfig:
        return base.with_reservoirs(space.reservoirs_from(params))

    def wrap_env(self, venv: Any, config: EncoderConfig, seed: int) -> Any:
        from ermrl.encoders._vec_env import ReservoirVecEnv

        return ReservoirVecEnv(venv, config, seed=seed)
