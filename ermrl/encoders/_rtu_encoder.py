"""``rtu``: frozen recurrent trace units, a complex-diagonal reservoir that evolution shapes.

The units of Elelimy et al. (2024) with fixed random weights
([`RTUParams`][ermrl.encoders.RTUParams]): a linear recurrence of damped rotations, each unit with
its own decay ``r`` and frequency ``theta``. Evolution searches the ranges those are drawn from, and
the input scaling ([`RTUSpace`][ermrl.encoders.RTUSpace]), exactly as it searches an ESN's spectral
radius and leak rate; the learner (PPO by default) reads ``tanh`` of the states. It wraps the env in
the same [`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv] as the ESN (same inputs, resets and
encoding options), with the linear update of [`rtu_weights`][ermrl.encoders.rtu_weights]. This
module holds its search space, its ``ermrl evolve`` settings (`RTUSettings`), its agents (`AGENTS`) and
the encoder; the layer's settings live with its weights in `ermrl.encoders._reservoir`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar, Literal

from ermrl._config_base import MAX_UNITS, AgentKind, ConfigError, Range
from ermrl._schema import option
from ermrl.encoders._reservoir import RTUParams
from ermrl.encoders._reservoir_encoder import ReservoirEncoder
from ermrl.encoders._settings import PerReservoirSpace

__all__ = ["AGENTS", "RTUEncoder", "RTUParams", "RTUSettings", "RTUSpace"]


@dataclass(frozen=True)
class RTUSpace(PerReservoirSpace):
    """The evolved search space of frozen recurrent trace units (``--encoder rtu``).

    Evolution shapes the ranges the units' parameters are drawn from, as it shapes an ESN's
    spectral radius: the upper decay rate ``r_max`` (linear scale), the lower one as a fraction
    of it, ``r_min_ratio`` (linear; ``r_min = r_min_ratio * r_max`` keeps the range ordered in a
    box), the largest rotation frequency ``theta_max`` (log scale) and the input scaling (log
    scale). The reference is the paper's initialization: ``r in (0, 1)``, ``theta in (0, 2 pi)``,
    input scaling 1.

    Attributes:
        n_reservoirs: RTU layers per agent, each with its own ranges and weights.
        units: Complex units per layer (the policy sees ``2 * units`` values per layer).
        r_max: Range of ``r_max``, within (0, 1].
        r_min_ratio: Range of ``r_min / r_max``, within [0, 1].
        theta_max: Range of ``theta_max``.
        input_scaling: Input-scaling range, or ``None`` to fix it at ``fixed_input_scaling``.
        fixed_input_scaling: The value used when ``input_scaling`` is ``None``.
        family: Always ``"rtu"`` (stored, so that a study's space reads back as this class).
    """

    n_reservoirs: int = 1
    units: int = 50
    r_max: Range = Range(0.05, 1.0, log=False)
    r_min_ratio: Range = Range(0.0, 1.0, log=False)
    theta_max: Range = Range(1e-2, 2 * math.pi)
    input_scaling: Range | None = Range(1e-1, 10.0)
    fixed_input_scaling: float = 1.0
    family: Literal["rtu"] = "rtu"

    def __post_init__(self) -> None:
        if self.family != "rtu":
            raise ConfigError(f"RTUSpace family must be 'rtu', got {self.family!r}")
        if self.n_reservoirs < 1:
            raise ConfigError(f"n_reservoirs must be >= 1, got {self.n_reservoirs}")
        if self.n_reservoirs * 2 * self.units > MAX_UNITS:
            raise ConfigError(
                f"{self.n_reservoirs} RTU layers of {self.units} complex units: at most "
                f"{MAX_UNITS} state values are allowed in all"
            )
        if not (0 < self.r_max.low and self.r_max.high <= 1):
            raise ConfigError(f"the r_max range must stay within (0, 1], got {self.r_max}")
        if not (0 <= self.r_min_ratio.low and self.r_min_ratio.high <= 1):
            raise ConfigError(
                f"the r_min_ratio range must stay within [0, 1], got {self.r_min_ratio}"
            )
        RTUParams(units=self.units, input_scaling=self.fixed_input_scaling)

    def _per_reservoir(self) -> dict[str, Range]:
        per = {"r_max": self.r_max, "r_min_ratio": self.r_min_ratio, "theta_max": self.theta_max}
        if self.input_scaling is not None:
            per["input_scaling"] = self.input_scaling
        return per

    def _reference_values(self) -> dict[str, float]:
        one = self.default_reservoirs()[0]
        ref = {"r_max": one.r_max, "r_min_ratio": one.r_min / one.r_max}
        ref["theta_max"] = one.theta_max
        if self.input_scaling is not None:
            ref["input_scaling"] = one.input_scaling
        return ref

    def _reservoir(self, values: Mapping[str, float]) -> RTUParams:
        return RTUParams(
            units=self.units,
            r_min=values["r_min_ratio"] * values["r_max"],
            r_max=values["r_max"],
            theta_max=values["theta_max"],
            input_scaling=values.get("input_scaling", self.fixed_input_scaling),
        )

    def reservoirs_from(self, params: Mapping[str, float]) -> tuple[RTUParams, ...]:
        """Build the RTU layers described by a trial's parameters.

        Raises:
            ConfigError: a parameter of this space is missing.
        """
        return tuple(self._reservoir(self._values(params, k)) for k in range(self.n_reservoirs))

    def default_reservoirs(self) -> tuple[RTUParams, ...]:
        """Unevolved RTU layers: the paper's initialization ranges, input scaling 1."""
        one = RTUParams(
            units=self.units,
            input_scaling=self.fixed_input_scaling if self.input_scaling is None else 1.0,
        )
        return (one,) * self.n_reservoirs


@dataclass(frozen=True)
class RTUSettings:
    """The ``ermrl evolve`` settings of ``--encoder rtu`` (`ermrl._schema` fields): each sets
    the [`RTUSpace`][ermrl.encoders.RTUSpace] field of its name, a ``<name>_range`` the range
    ``<name>``."""

    units: int | None = option(
        None, "--encoder rtu: complex units per layer, each showing the policy 2 values "
        "(default 50)", low=1,
    )  # fmt: skip
    r_max_range: tuple[float, float] = option(
        (0.05, 1.0), "--encoder rtu: range of the largest decay rate r_max (linear, within "
        "(0, 1])", metavar=("LOW", "HIGH"),
    )  # fmt: skip
    theta_max_range: tuple[float, float] = option(
        (1e-2, 2 * math.pi), "--encoder rtu: range of the largest rotation frequency theta_max "
        "(log scale, radians per step)", metavar=("LOW", "HIGH"), above=0,
    )  # fmt: skip


# Test-phase agents of ``--encoder rtu`` studies.
AGENTS: dict[str, AgentKind] = {
    "rtu-res-ppo": AgentKind(
        "evolved", None,
        "the study's learner on the selected evolved frozen RTU layer(s) (--encoder rtu studies)",
        None, "RTU-RES-PPO (evolved RTU)", "RTU-RES\n(evolved)", "tab:red", family="rtu",
    ),
    "random-rtu-res-ppo": AgentKind(
        "unevolved", None,
        "the study's learner on frozen RTUs of the paper's initialization (--encoder rtu studies)",
        None, "RTU-RES-PPO (unevolved RTU)", "RTU-RES\n(unevolved)", "tab:pink", family="rtu",
    ),
}  # fmt: skip


class RTUEncoder(ReservoirEncoder):
    """The reservoir encoder's decoding and wrapper, with RTU layers and their search space."""

    name = "rtu"
    description = (
        "recurrent trace units with fixed random weights, a complex-diagonal reservoir (evolved "
        "r_max, r_min_ratio, theta_max, input_scaling)"
    )
    family = "rtu"
    params_cls: ClassVar[type] = RTUParams
    space_cls: ClassVar[type] = RTUSpace
    settings: ClassVar[type | None] = RTUSettings
    agents: ClassVar[Mapping[str, AgentKind]] = AGENTS
