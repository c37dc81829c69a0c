"""What every encoder's settings share: the encoding options
([`EncoderConfig`][ermrl.encoders.EncoderConfig]), what the generic code reads of one reservoir's
settings ([`EncoderParams`][ermrl.encoders.EncoderParams]) and of a search space
([`EncoderSpace`][ermrl.encoders.EncoderSpace]), and the per-reservoir naming of evolved parameters
([`PerReservoirSpace`][ermrl.encoders.PerReservoirSpace]).

An encoder's own settings class ([`ReservoirParams`][ermrl.encoders.ReservoirParams],
[`RTUParams`][ermrl.encoders.RTUParams], ...) and search space live in its module; nothing here
names one, except the default reservoir of [`EncoderConfig`][ermrl.encoders.EncoderConfig]
(reservoirpy's defaults).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, Protocol, runtime_checkable

from ermrl._config_base import (
    MAX_UNITS,
    RESET_MODES,
    ConfigError,
    Range,
    ResetMode,
    SearchSpace,
    _box_center,
    _box_contains,
)
from ermrl.encoders._reservoir import ReservoirParams

__all__ = ["EncoderConfig", "EncoderParams", "EncoderSpace", "PerReservoirSpace"]


@runtime_checkable
class EncoderParams(Protocol):
    """What generic code reads of one reservoir's settings (one ESN, RTU layer, NVAR, ...).

    Attributes:
        family: The encoder family the settings belong to (`ermrl.encoders.Encoder.family`);
            stored with the settings where two encoders' settings could be confused.
        state_dim: Width of the state the policy can see (a lower bound where it depends on the
            task's input size, as an NVAR's).
    """

    @property
    def family(self) -> str: ...

    @property
    def state_dim(self) -> int: ...


@runtime_checkable
class EncoderSpace(SearchSpace, Protocol):
    """What generic code reads of an encoder's search space, on top of
    [`SearchSpace`][ermrl.config.SearchSpace]."""

    @property
    def n_reservoirs(self) -> int: ...

    @property
    def family(self) -> str: ...

    def reservoirs_from(self, params: Mapping[str, float]) -> tuple[Any, ...]: ...

    def default_reservoirs(self) -> tuple[Any, ...]: ...


class PerReservoirSpace:
    """What the search spaces share: each reservoir has the same evolved parameters, named
    ``name`` with one reservoir and ``name_0``, ``name_1``, ... with several."""

    n_reservoirs: int

    def _per_reservoir(self) -> dict[str, Range]:
        """One reservoir's evolved parameters and their ranges, in order."""
        raise NotImplementedError

    def _reference_values(self) -> dict[str, float]:
        """One unevolved reference reservoir's evolved parameters."""
        raise NotImplementedError

    @property
    def evolved(self) -> tuple[str, ...]:
        """Names of the evolved hyperparameters of one reservoir."""
        return tuple(self._per_reservoir())

    def param_name(self, name: str, index: int) -> str:
        return name if self.n_reservoirs == 1 else f"{name}_{index}"

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(self.param_name(n, k) for k in range(self.n_reservoirs) for n in self.evolved)

    def ranges(self) -> dict[str, Range]:
        """Search ranges keyed by Optuna parameter name, in a fixed order."""
        per = self._per_reservoir()
        return {self.param_name(n, k): r for k in range(self.n_reservoirs) for n, r in per.items()}

    def _values(self, params: Mapping[str, float], k: int) -> dict[str, float]:
        """Reservoir ``k``'s evolved values in a trial's parameters.

        Raises:
            ConfigError: a parameter of this space is missing.
        """
        try:
            return {n: float(params[self.param_name(n, k)]) for n in self.evolved}
        except KeyError as err:
            raise ConfigError(f"parameter {err.args[0]!r} missing from {dict(params)}") from err

    def reference_params(self) -> dict[str, float]:
        """The unevolved reference reservoirs (``default_reservoirs()``) as trial parameters."""
        one = self._reference_values()
        return {self.param_name(n, k): one[n] for k in range(self.n_reservoirs) for n in one}

    def contains(self, params: Mapping[str, float]) -> bool:
        """Whether ``params`` name exactly this space's parameters, each within its range."""
        return _box_contains(self.ranges(), params)

    def center_params(self) -> dict[str, float]:
        """The centre of the box (geometric mean of the bounds on a log scale): the paper's start."""
        return _box_center(self.ranges())


@dataclass(frozen=True)
class EncoderConfig:
    """How the reservoir(s) turn observations into the policy's input.

    Attributes:
        reservoirs: One registered encoder's settings per reservoir (an echo state network's
            [`ReservoirParams`][ermrl.encoders.ReservoirParams], ...), all of one family; their
            states are concatenated.
        skip_connection: The policy sees ``[state, observation, action, reward]``, not only the state.
        reset: ``"episode"`` zeroes a row's state when its episode ends; ``"never"`` carries it.
        exposed_units: Expose only the first N units of each reservoir to the policy (``None``: all).
        reward_scale: Factor applied to the previous reward before it enters the reservoir.
        feed_action: Feed the previous action (one-hot or scaled to [-1, 1]) to the reservoir.
        feed_reward: Feed the previous reward to the reservoir.
        dtype: Float type of the reservoir state and weights. ``float32`` (default) is about
            twice as cheap per step. How closely it follows float64 depends on the dynamics
            (100 units, lr 1, 100 steps of N(0, 1) input, worst of 5 seeds): within ~1e-6 up to
            sr 1.5, up to 6e-4 at sr 2, and from sr ~2.5 the two trajectories decorrelate
            (sr 3: 3e-2 apart by step 50, 2.0, the whole tanh range, by step 100). There the
            reservoir is chaotic and any rounding change separates trajectories; the states
            stay statistically alike but are not reservoirpy's. ``float64`` reproduces
            reservoirpy's own states to 1e-10.
    """

    reservoirs: tuple[EncoderParams, ...] = (ReservoirParams(),)
    skip_connection: bool = False
    reset: ResetMode = "episode"
    exposed_units: int | None = None
    reward_scale: float = 1.0
    feed_action: bool = True
    feed_reward: bool = True
    dtype: Literal["float64", "float32"] = "float32"

    def __post_init__(self) -> None:
        if self.dtype not in ("float64", "float32"):
            raise ConfigError(f"dtype must be float64 or float32, got {self.dtype!r}")
        if not self.reservoirs:
            raise ConfigError("an encoder needs at least one reservoir")
        if len({p.family for p in self.reservoirs}) > 1:
            raise ConfigError("the reservoirs of one encoder must all be of one family")
        if self.total_units > MAX_UNITS:
            raise ConfigError(
                f"the reservoirs have {self.total_units} units together; at most {MAX_UNITS} "
                "are allowed"
            )
        if self.reset not in RESET_MODES:
            raise ConfigError(f"reset must be one of {RESET_MODES}, got {self.reset!r}")
        if self.exposed_units is not None:
            smallest = min(p.state_dim for p in self.reservoirs)
            if not (1 <= self.exposed_units <= smallest):
                raise ConfigError(
                    f"exposed_units must be in [1, {smallest}] (state size per reservoir), "
                    f"got {self.exposed_units}"
                )
        if not math.isfinite(self.reward_scale):
            raise ConfigError(f"reward_scale must be finite, got {self.reward_scale}")

    @property
    def n_reservoirs(self) -> int:
        return len(self.reservoirs)

    @property
    def family(self) -> str:
        """The reservoirs' family (``"esn"``, ``"rtu"``, ...): which encoder takes them."""
        return self.reservoirs[0].family

    @property
    def total_units(self) -> int:
        """Width of the concatenated states (an RTU's complex unit counts twice)."""
        return sum(p.state_dim for p in self.reservoirs)

    @property
    def exposed_total(self) -> int:
        if self.exposed_units is None:
            return self.total_units
        return self.exposed_units * self.n_reservoirs

    def with_reservoirs(self, reservoirs: tuple[EncoderParams, ...]) -> EncoderConfig:
        """Return a copy with other reservoir hyperparameters (same encoding options)."""
        return dataclasses.replace(self, reservoirs=tuple(reservoirs))
