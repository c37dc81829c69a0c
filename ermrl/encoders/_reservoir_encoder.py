"""``reservoir``: echo state networks built with reservoirpy, frozen, wrapping the env.

The reference encoder. Its settings are :class:`~ermrl.config.EncoderConfig` (the reservoirs'
:class:`~ermrl.config.ReservoirParams` and the encoding options), its search space
:class:`~ermrl.config.ReservoirSpace` (spectral radius, leak rate, input scaling per reservoir),
and it wraps the env in a :class:`~ermrl.encoders.ReservoirVecEnv`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from ermrl.config import EncoderConfig, EncoderSpace, ReservoirSpace
from ermrl.encoders._base import Encoder

__all__ = ["ReservoirEncoder"]


class ReservoirEncoder(Encoder):
    name = "reservoir"
    description = "echo state network(s) initialized by reservoirpy; frozen, wraps the env"
    place = "env"
    family = "esn"
    config_cls = EncoderConfig
    space_cls: ClassVar[type] = ReservoirSpace

    def decode(
        self, space: EncoderSpace, params: Mapping[str, float], base: EncoderConfig
    ) -> EncoderConfig:
        return base.with_reservoirs(space.reservoirs_from(params))

    def wrap_env(self, venv: Any, config: EncoderConfig, seed: int) -> Any:
        from ermrl.encoders._vec_env import ReservoirVecEnv

        return ReservoirVecEnv(venv, config, seed=seed)
