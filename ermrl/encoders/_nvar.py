"""``nvar``: a next-generation reservoir (nonlinear vector autoregression), frozen, wrapping the env.

Gauthier et al. (2021), "Next generation reservoir computing", Nature Communications 12, 5564
(https://doi.org/10.1038/s41467-021-25801-2), as reservoirpy 0.4 builds it
(``reservoirpy.nodes.NVAR(delay, order, strides)``). With input ``u_t`` of size ``d``, the
features are the linear part

.. code-block:: text

    lin_t = [u_t, u_{t-s}, u_{t-2s}, ..., u_{t-(k-1)s}]          (k * d values)

(``k`` the delay, ``s`` the strides), followed by every unique monomial of degree exactly ``n``
(the order) of ``lin_t``, in ``itertools.combinations_with_replacement`` order: ``k d +
C(k d + n - 1, n)`` features in all. Before the first input the history is zero, as reservoirpy's
``store``. There is no constant feature (the paper's ``c``): the policy's layers have biases.

It gets what an echo state network gets ([`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv]): the
input ``u = [observation, previous action, previous reward * reward_scale] * input_scaling``, zero
history at each episode start with ``reset="episode"``, the skip connection and ``exposed_units``
(the first features of each NVAR).

The delay line is a linear shift register: a state of ``((k - 1) s + 1) d`` values steps as
``x <- [x | u] M`` with a fixed ``M`` that has one nonzero per column (1 for a shifted value,
``input_scaling`` for a new input), so `NVARBank` steps it as the equivalent gather,
``x <- [x | u][:, src] * scale``, exactly (``M`` is built on demand for inspection). The state
holds the ``k`` slots the features read first (slot ``0, s, 2s, ...``), so the linear features
are a slice of it whatever the strides. The emission replaces the ESN's ``tanh``: the linear
features, then each monomial as the product of its ``n`` gathered columns (precomputed index
arrays).

The output width grows fast with the delay and the order; it also depends on the input size
``d`` (the task's observation and action sizes), which an `NVARParams` does not know.
`check_nvar_size` refuses more than `NVAR_MAX_FEATURES` features in one line, and
`NVARSpace.check_input_dim` refuses a search space whose largest corner would, before a
study is created.

This module is the whole encoder but its batched computation (`ermrl.encoders._nvar_bank`,
below the env wrapper): its search space, its ``ermrl evolve`` settings (`NVARSettings`), its
test-phase agents (`AGENTS`) and `NVAREncoder`, registered by one line of
`ENCODERS`.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, cast

import numpy as np

from ermrl._config_base import AgentKind, ConfigError, Range, TaskConfig, _box_center
from ermrl._schema import option
from ermrl.encoders._base import Encoder
from ermrl.encoders._nvar_bank import (
    NVAR_MAX_FEATURES,
    NVAR_MAX_WINDOW,
    NVARBank,
    NVARParams,
    _size_text,
    check_nvar_size,
    nvar_structure,
    nvar_width,
)
from ermrl.encoders._settings import EncoderConfig, PerReservoirSpace

__all__ = [
    "AGENTS",
    "NVARSettings",
    "NVAR_MAX_FEATURES",
    "NVAR_MAX_WINDOW",
    "IntRange",
    "NVARBank",
    "NVAREncoder",
    "NVARParams",
    "NVARSpace",
    "check_nvar_size",
    "encoder_input_dim",
    "nvar_width",
]


def encoder_input_dim(task: TaskConfig, encoder: EncoderConfig) -> int:
    """The size ``d`` of the input an encoder gets on ``task``: the (masked) observation, the
    encoded previous action (``feed_action``) and the previous reward (``feed_reward``), as
    [`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv] builds it. Makes (and closes) one env."""
    from ermrl.encoders._vec_env import ActionEncoder
    from ermrl.envs import make_env

    env = make_env(task.env_id, task.observe)
    try:
        obs_dim = int(np.prod(env.observation_space.shape or (0,)))
        act_dim = ActionEncoder(env.action_space).dim if encoder.feed_action else 0
    finally:
        env.close()
    return obs_dim + act_dim + (1 if encoder.feed_reward else 0)


# -- integer genes -------------------------------------------------------------------------------


@dataclass(frozen=True)
class IntRange(Range):
    """A closed interval of integers, searched on a linear scale.

    The search asks it with ``trial.suggest_int`` (an ``optuna`` ``IntDistribution``), and
    CMA-ES then searches it with margin ([`RestartCmaEsSampler`][ermrl.search.RestartCmaEsSampler]):
    the rounding is part of the search distribution, not applied to its samples afterwards.
    """

    low: int
    high: int
    log: bool = False

    integer: ClassVar[bool] = True

    def __post_init__(self) -> None:
        for name in ("low", "high"):
            value = getattr(self, name)
            if isinstance(value, bool) or not float(value).is_integer():
                raise ConfigError(f"an integer range needs integer bounds, got {name} {value}")
            object.__setattr__(self, name, int(value))
        if self.log:
            raise ConfigError("an integer range is searched on a linear scale (log=False)")
        super().__post_init__()

    def contains(self, value: float) -> bool:
        """Whether ``value`` is an integer within the bounds."""
        return float(value).is_integer() and self.low <= value <= self.high

    @property
    def center(self) -> float:
        """The exact middle of the range, ``(low + high) / 2``: the middle integer for an odd
        number of values, halfway between the two middle integers for an even number. A
        search started there rounds half of its first samples down and half up: starting at
        one of two middle integers (the lower one, as before) put ``order`` in 1..2 at its
        lower edge, and on a pure-noise fitness 9 samples in 10 of the first 5 generations
        kept ``order`` 1."""
        return (self.low + self.high) / 2


# -- search space --------------------------------------------------------------------------------


@dataclass(frozen=True)
class NVARSpace(PerReservoirSpace):
    """The evolved search space of NVARs (``--encoder nvar``): data, not code.

    The delay, the order and the strides are integer genes (`IntRange`); the input scaling
    is log-scale (or fixed, with ``input_scaling=None``: it is inert under observation
    normalization, see `NVARParams`). The reference point is `NVARParams`'
    defaults (delay 2, order 2, strides 1, input scaling 1: the paper's and reservoirpy's
    example). The default ranges keep the largest NVAR (delay 4, order 2) within
    `NVAR_MAX_FEATURES` for inputs of up to 15 values; a wider input (a MuJoCo task's
    full observation) needs a narrower delay range, which `check_input_dim` says.

    Attributes:
        n_reservoirs: NVARs per agent, each with its own genes (their features are
            concatenated).
        delay: Range of the delay.
        order: Range of the order.
        strides: Range of the strides.
        input_scaling: Input-scaling range, or ``None`` to fix it at ``fixed_input_scaling``.
        fixed_input_scaling: The value used when ``input_scaling`` is ``None``.
        family: Always ``"nvar"`` (stored, so that a study's space reads back as this class).
    """

    n_reservoirs: int = 1
    delay: IntRange = IntRange(1, 4)
    order: IntRange = IntRange(1, 2)
    strides: IntRange = IntRange(1, 4)
    input_scaling: Range | None = Range(1e-1, 10.0)
    fixed_input_scaling: float = 1.0
    family: Literal["nvar"] = "nvar"

    def __post_init__(self) -> None:
        if self.family != "nvar":
            raise ConfigError(f"NVARSpace family must be 'nvar', got {self.family!r}")
        if self.n_reservoirs < 1:
            raise ConfigError(f"n_reservoirs must be >= 1, got {self.n_reservoirs}")
        for name in ("delay", "order", "strides"):
            r = getattr(self, name)
            if not isinstance(r, IntRange):
                raise ConfigError(f"the {name} range must be an integer range, got {r}")
            if r.low < 1:
                raise ConfigError(f"the {name} range must start at 1 or more, got {r.low}")
        NVARParams(  # fail early on a bad fixed value or a delay line too long
            delay=self.delay.high,
            strides=self.strides.high,
            input_scaling=self.fixed_input_scaling,
        )

    def _per_reservoir(self) -> dict[str, Range]:
        per: dict[str, Range] = {"delay": self.delay, "order": self.order, "strides": self.strides}
        if self.input_scaling is not None:
            per["input_scaling"] = self.input_scaling
        return per

    def _reference_values(self) -> dict[str, float]:
        one = NVARParams()
        ref: dict[str, float] = {"delay": one.delay, "order": one.order, "strides": one.strides}
        if self.input_scaling is not None:
            ref["input_scaling"] = one.input_scaling
        return ref

    def reference_params(self) -> dict[str, float]:
        """The reference NVAR (delay 2, order 2, strides 1, input scaling 1) as trial
        parameters, clipped into the box (so that it can be queued as a trial)."""
        ranges = self.ranges()
        return {
            name: type(value)(min(max(value, ranges[name].low), ranges[name].high))
            for name, value in super().reference_params().items()
        }

    def center_params(self) -> dict[str, float]:
        """The centre of the box: the exact middle of each integer gene's range
        (`IntRange.center`, halfway between two integers for an even number of values,
        so not a point `contains` accepts: it is CMA-ES's start, never a trial's
        values), the geometric mean of the input scaling's bounds."""
        return {
            name: r.center if isinstance(r, IntRange) else _box_center({name: r})[name]
            for name, r in self.ranges().items()
        }

    def contains(self, params: Mapping[str, float]) -> bool:
        """Whether ``params`` name exactly this space's parameters, each in its range (an integer
        gene's value an integer)."""
        ranges = self.ranges()
        return set(params) == set(ranges) and all(
            r.contains(params[n]) if isinstance(r, IntRange) else r.low <= params[n] <= r.high
            for n, r in ranges.items()
        )

    def _reservoir(self, values: Mapping[str, float]) -> NVARParams:
        return NVARParams(
            delay=cast("int", values["delay"]),
            order=cast("int", values["order"]),
            strides=cast("int", values["strides"]),
            input_scaling=values.get("input_scaling", self.fixed_input_scaling),
        )

    def reservoirs_from(self, params: Mapping[str, float]) -> tuple[NVARParams, ...]:
        """Build the NVARs described by a trial's parameters.

        Raises:
            ConfigError: a parameter of this space is missing, or an integer gene is not an
                integer (values are never rounded here: the search proposes integers).
        """
        return tuple(self._reservoir(self._values(params, k)) for k in range(self.n_reservoirs))

    def default_reservoirs(self) -> tuple[NVARParams, ...]:
        """Unevolved NVARs: the reference (delay 2, order 2, strides 1), input scaling 1 (or the
        fixed one)."""
        scaling = self.fixed_input_scaling if self.input_scaling is None else 1.0
        return (NVARParams(input_scaling=scaling),) * self.n_reservoirs

    def largest(self) -> tuple[NVARParams, ...]:
        """The NVARs of the box's widest corner (largest delay and order; strides and input
        scaling do not change the width)."""
        one = NVARParams(
            delay=self.delay.high, order=self.order.high, input_scaling=self.fixed_input_scaling
        )
        return (one,) * self.n_reservoirs

    def check_input_dim(self, input_dim: int) -> None:
        """Refuse a space whose widest corner exceeds `NVAR_MAX_FEATURES` on ``input_dim``
        inputs, before any trial exists (a study must not fail trial by trial on its size).

        Raises:
            ConfigError: one line with the widest corner's size and the largest delay that fits.
        """
        widest = self.largest()
        total = sum(p.state_dim_for(input_dim) for p in widest)
        if total > NVAR_MAX_FEATURES:
            fits = [
                k
                for k in range(1, self.delay.high)
                if self.n_reservoirs * nvar_width(k, self.order.high, input_dim)
                <= NVAR_MAX_FEATURES
            ]
            hint = (
                f"a delay range up to {fits[-1]} fits with order {self.order.high}"
                if fits
                else f"no delay fits with order {self.order.high}; lower the order range"
            )
            raise ConfigError(
                f"the search space's widest point is too large: "
                f"{_size_text(widest, input_dim, total)}; {hint}"
            )


# -- for the registry: settings and test-phase agents --------------------------------


def _int_range(field: str, default: tuple[int, int], help: str) -> Any:
    """The ``<field>_range`` setting (``--<field>-range LOW HIGH``) of an integer gene."""
    text = f"--encoder nvar: range of the {field}, {help} (integers)"
    return option(default, text, metavar=("LOW", "HIGH"))


@dataclass(frozen=True)
class NVARSettings:
    """The ``ermrl evolve`` settings of ``--encoder nvar`` (`ermrl._schema` fields), each the
    range of the `NVARSpace` field of its name less ``_range``.
    The shared ``--n-reservoirs``, ``--input-scaling-range`` and ``--fixed-input-scaling``
    apply too."""

    delay_range: tuple[int, int] = _int_range("delay", (1, 4), "the inputs in the linear part")
    order_range: tuple[int, int] = _int_range("order", (1, 2), "the degree of the monomials")
    strides_range: tuple[int, int] = _int_range(
        "strides", (1, 4), "the steps between delayed inputs"
    )


# Test-phase agents of ``--encoder nvar`` studies, as [`AgentKind`][ermrl.config.AgentKind] fields.
AGENTS: dict[str, dict[str, Any]] = {
    "nvar-res-ppo": {
        "reservoirs": "evolved",
        "observe": None,
        "description": "the study's learner on the selected evolved NVAR(s) "
        "(--encoder nvar studies)",
        "learner": None,
        "label": "NVAR-RES-PPO (evolved NVAR)",
        "short_label": "NVAR-RES\n(evolved)",
        "color": "darkcyan",
        "default": True,
        "family": "nvar",
    },
    "random-nvar-res-ppo": {
        "reservoirs": "unevolved",
        "observe": None,
        "description": "the study's learner on the reference NVAR (delay 2, order 2, strides 1, "
        "input scaling 1; --encoder nvar studies)",
        "learner": None,
        "label": "NVAR-RES-PPO (reference NVAR)",
        "short_label": "NVAR-RES\n(reference)",
        "color": "yellowgreen",
        "default": True,
        "family": "nvar",
    },
}


# -- the encoder ---------------------------------------------------------------------------------
class NVAREncoder(Encoder):
    """The NVAR encoder: decoding of a trial's genes, its flags and agents, the size check made
    before a study exists, and the env wrapper ([`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv]
    with an `NVARBank`)."""

    name = "nvar"
    description = (
        "next-generation reservoir (NVAR: delayed inputs and their monomials, reservoirpy; "
        "evolved delay, order, strides, input_scaling); frozen, wraps the env"
    )
    place = "env"
    family = "nvar"
    config_cls = EncoderConfig
    params_cls: ClassVar[type] = NVARParams
    space_cls: ClassVar[type] = NVARSpace
    settings: ClassVar[type | None] = NVARSettings
    agents: ClassVar[Mapping[str, AgentKind]] = {n: AgentKind(**f) for n, f in AGENTS.items()}
    population = True

    def check(self, task: TaskConfig, config: EncoderConfig, space: NVARSpace) -> None:
        """Refuse a space whose widest point, or a study whose reference NVAR(s), would exceed
        `NVAR_MAX_FEATURES` features on ``task``'s input (one line, before anything is
        written)."""
        input_dim = encoder_input_dim(task, config)
        space.check_input_dim(input_dim)
        check_nvar_size(cast("tuple[NVARParams, ...]", config.reservoirs), input_dim)

    def describe(self, space: NVARSpace) -> str:
        genes = ", ".join(
            f"{name} {r.low}-{r.high}"
            for name, r in (
                ("delay", space.delay),
                ("order", space.order),
                ("strides", space.strides),
            )
        )
        return f"{space.n_reservoirs} x NVAR ({genes})"

    def layout(self, params: NVARParams) -> Hashable:
        return nvar_structure(params)

    def bank(self, config: EncoderConfig, input_dim: int, seed: int) -> NVARBank:
        """No random weights (``seed`` unused): the delay line and its monomials."""
        reservoirs = cast("tuple[NVARParams, ...]", config.reservoirs)
        return NVARBank(reservoirs, input_dim, dtype=config.dtype)

    def population_banks(
        self, configs: Sequence[EncoderConfig], seeds: Sequence[int], input_dim: int
    ) -> list[NVARBank]:
        """One layout for all: each delay line padded (with zeros) to the population's longest
        window, so agents with the same delay and order but other strides share it."""
        params = [cast("tuple[NVARParams, ...]", c.reservoirs) for c in configs]
        windows = [max(p[r].window for p in params) for r in range(len(params[0]))]
        return [NVARBank(p, input_dim, configs[0].dtype, windows) for p in params]

    def wrap_env(self, venv: Any, config: EncoderConfig, seed: int) -> Any:
        from ermrl.encoders._vec_env import ReservoirVecEnv

        return ReservoirVecEnv(venv, config, seed=seed)
