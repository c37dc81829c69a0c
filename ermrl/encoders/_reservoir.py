"""Reservoir weights from reservoirpy's initializers, and a batched leaky-ESN update.

The update rule is reservoirpy's ``Reservoir`` rule, applied to ``n_envs`` state rows at once::

    x <- (1 - lr) * x + lr * tanh(W x + Win u + b)

``lr`` is one leak rate for every unit, or one per unit: a multi-timescale reservoir
(`ReservoirParams.lr_max`) spaces its units' leak rates log-uniformly between two bounds.

A frozen layer of recurrent trace units ([`RTUParams`][ermrl.encoders.RTUParams]) is the linear case
``x <- W x + Win u`` with a block-rotation ``W`` (see [`rtu_weights`][ermrl.encoders.rtu_weights]);
the policy then sees ``tanh(x)``.

Several reservoirs are fused into one block-diagonal system, so one step is one matrix product
for all reservoirs and all environments: there is no per-step reservoirpy ``Node`` call.

An NVAR (`NVARBank`) has no random weights: its delay line is the
same update with a fixed 0/1 ``M``, and it emits the delayed inputs and their monomials; it
offers the same interface (``buffer``, ``step_buffer``, ``emitter``, ``out_units``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import numpy as np

from ermrl._config_base import ConfigError, _check_units

if TYPE_CHECKING:
    from reservoirpy.nodes import Reservoir

__all__ = [
    "ABLATIONS",
    "Ablation",
    "BIAS_INITS",
    "BiasInit",
    "ReservoirParams",
    "RTUParams",
    "ReservoirWeights",
    "ReservoirBank",
    "StackedBanks",
    "StepBank",
    "encoder_weights",
    "reservoir_weights",
    "reservoir_seeds",
    "rtu_weights",
]

BiasInit = Literal["none", "original"]
BIAS_INITS: tuple[str, ...] = ("none", "original")
Ablation = Literal["none", "leaky", "ema"]
ABLATIONS: tuple[str, ...] = ("none", "leaky", "ema")


@dataclass(frozen=True)
class ReservoirParams:
    """Hyperparameters of one echo state network (reservoirpy ``Reservoir`` arguments).

    The defaults are reservoirpy's own, which is what ``random-res-ppo`` uses as the unevolved
    reference reservoir.

    Attributes:
        units: Number of reservoir neurons.
        sr: Spectral radius of the recurrent matrix ``W``.
        lr: Leak rate in (0, 1]: ``x <- (1 - lr) x + lr tanh(W x + Win u + b)``; with
            ``lr_max``, the smallest of the units' leak rates (``lr_min``).
        input_scaling: Scale of the input matrix ``Win`` (Bernoulli +-input_scaling entries).
        rc_connectivity: Density of ``W``.
        input_connectivity: Density of ``Win``.
        bias_scaling: Scale of a dense Bernoulli bias (every unit +-bias_scaling); 0 means no
            bias (reservoirpy 0.4's default).
        bias_init: ``"none"``: the bias above. ``"original"``: reservoirpy 0.3's default bias,
            which the original ER-MRL code used: Bernoulli +-1 on ``input_connectivity`` of
            the units (10 of 100), zero elsewhere; needs ``bias_scaling`` 0. Left out of
            [`to_dict`][ermrl.config.to_dict] while ``"none"``, so configs stored before it existed
            are unchanged.
        ablation: What is left of the reservoir (the test phase's ablation agents);
            ``"none"``: the whole echo state network. ``"leaky"``: its recurrent weights
            removed (``W = 0``), the same ``Win``, bias and leak rate (the same seed draws
            them): ``x <- (1 - lr) x + lr tanh(Win u + b)``, a leaky integrator of a random
            projection. ``"ema"``: no reservoir at all, the input next to its exponential
            moving average at the leak rate, ``e <- (1 - lr) e + lr u`` (the state is
            ``[e; u]``, two values per input, shown as it is: no weights, no tanh; ``units``,
            ``sr``, ``input_scaling`` and the connectivities are unused). Left out of
            [`to_dict`][ermrl.config.to_dict] while ``"none"``.
        lr_max: A multi-timescale reservoir: the largest of its units' leak rates, in
            ``[lr, 1]``. Unit ``i`` of ``n`` leaks at
            ``lr_i = lr * (lr_max / lr) ** (i / (n - 1))``
            ([`leak_rates`][ermrl.encoders.ReservoirParams.leak_rates]): log-uniformly spaced from
            ``lr`` (unit 0) to ``lr_max`` (unit ``n - 1``), fixed by the two bounds, not drawn, so
            the same settings give the same reservoir; each unit then updates
            ``x_i <- (1 - lr_i) x_i + lr_i tanh(W x + Win u + b)_i``. The weights are drawn as
            without it (the same seed gives the same ``W``, ``Win`` and bias). ``None``: every unit
            leaks at ``lr``. Not with the ``"ema"`` ablation (one leak rate). Left out of
            [`to_dict`][ermrl.config.to_dict] while ``None``.
    """

    units: int = 100
    sr: float = 1.0
    lr: float = 1.0
    input_scaling: float = 1.0
    rc_connectivity: float = 0.1
    input_connectivity: float = 0.1
    bias_scaling: float = 0.0
    bias_init: BiasInit = field(default="none", metadata={"omit_if_default": True})
    ablation: Ablation = field(default="none", metadata={"omit_if_default": True})
    lr_max: float | None = field(default=None, metadata={"omit_if_default": True})

    family: ClassVar[str] = "esn"

    def leak_rates(self) -> np.ndarray:
        """Every unit's leak rate, shape ``(units,)``: ``lr`` for all, or with ``lr_max``
        ``lr_i = lr * (lr_max / lr) ** (i / (units - 1))`` (one unit: ``lr``)."""
        if self.lr_max is None or self.units == 1:
            return np.full(self.units, float(self.lr))
        steps = np.arange(self.units) / (self.units - 1)
        return float(self.lr) * (float(self.lr_max) / float(self.lr)) ** steps

    @property
    def state_dim(self) -> int:
        """Width of the state the policy can see: one value per unit (an ``"ema"`` ablation's
        is twice its input's width, which only the task gives: ``units`` stands for it here)."""
        return self.units

    def __post_init__(self) -> None:
        if self.ablation not in ABLATIONS:
            raise ConfigError(f"ablation must be one of {ABLATIONS}, got {self.ablation!r}")
        if self.bias_init not in BIAS_INITS:
            raise ConfigError(f"bias_init must be one of {BIAS_INITS}, got {self.bias_init!r}")
        if self.bias_init == "original" and self.bias_scaling > 0:
            raise ConfigError(
                "bias_init 'original' draws reservoirpy 0.3's +-1 sparse bias; it cannot be "
                f"combined with bias_scaling {self.bias_scaling} (a dense bias)"
            )
        _check_units(self.units)
        if not (self.sr > 0 and math.isfinite(self.sr)):
            raise ConfigError(f"spectral radius sr must be positive, got {self.sr}")
        if not (0 < self.lr <= 1):
            raise ConfigError(f"leak rate lr must be in (0, 1], got {self.lr}")
        if self.lr_max is not None:
            if not (self.lr <= self.lr_max <= 1):
                raise ConfigError(
                    f"the largest leak rate lr_max must be in [lr = {self.lr}, 1], "
                    f"got {self.lr_max}"
                )
            if self.ablation == "ema":
                raise ConfigError(
                    "the 'ema' ablation averages at one leak rate; a multi-timescale reservoir "
                    f"(lr {self.lr} to lr_max {self.lr_max}) has one per unit"
                )
        if not (self.input_scaling > 0 and math.isfinite(self.input_scaling)):
            raise ConfigError(f"input_scaling must be positive, got {self.input_scaling}")
        for name in ("rc_connectivity", "input_connectivity"):
            value = getattr(self, name)
            if not (0 < value <= 1):
                raise ConfigError(f"{name} must be in (0, 1], got {value}")
        if not (self.bias_scaling >= 0 and math.isfinite(self.bias_scaling)):
            raise ConfigError(f"bias_scaling must be finite and >= 0, got {self.bias_scaling}")


@dataclass(frozen=True)
class RTUParams:
    """Hyperparameters of one frozen layer of recurrent trace units (a complex-diagonal reservoir).

    The units of Elelimy et al. (2024), with fixed random weights: each of the ``units`` complex
    units holds ``(c1, c2)``; with ``g = r cos(theta)``, ``phi = r sin(theta)`` and
    ``gamma = sqrt(1 - r^2)``:

        c1 <- g c1 - phi c2 + gamma (W1 u)
        c2 <- g c2 + phi c1 + gamma (W2 u)

    The policy sees ``tanh([c1; c2])`` (``2 * units`` values). ``r^2 ~ U(r_min^2, r_max^2)`` and
    ``theta ~ U(0, theta_max)`` per unit; ``W1`` and ``W2`` are dense ``N(0, input_scaling^2 /
    input_dim)``. The defaults are the paper's initialization (r in (0, 1), theta in (0, 2 pi)),
    the unevolved reference of ``--encoder rtu``.

    Attributes:
        units: Complex units (the state has ``2 * units`` values).
        r_min: Lower bound of the decay rates' range, in [0, r_max].
        r_max: Upper bound of the decay rates' range, in (0, 1].
        theta_max: Upper bound of the rotation frequencies' range (radians per step).
        input_scaling: Scale of ``W1`` and ``W2``.
        family: Always ``"rtu"`` (tells stored configurations apart from echo state networks).
    """

    units: int = 50
    r_min: float = 0.0
    r_max: float = 1.0
    theta_max: float = 2 * math.pi
    input_scaling: float = 1.0
    family: Literal["rtu"] = "rtu"

    @property
    def state_dim(self) -> int:
        """Width of the state the policy can see: two values per complex unit."""
        return 2 * self.units

    def __post_init__(self) -> None:
        if self.family != "rtu":
            raise ConfigError(f"RTUParams family must be 'rtu', got {self.family!r}")
        _check_units(2 * self.units)
        if not (0 < self.r_max <= 1):
            raise ConfigError(f"r_max must be in (0, 1], got {self.r_max}")
        if not (0 <= self.r_min <= self.r_max):
            raise ConfigError(f"r_min must be in [0, r_max = {self.r_max}], got {self.r_min}")
        if not (self.theta_max > 0 and math.isfinite(self.theta_max)):
            raise ConfigError(f"theta_max must be positive, got {self.theta_max}")
        if not (self.input_scaling > 0 and math.isfinite(self.input_scaling)):
            raise ConfigError(f"input_scaling must be positive, got {self.input_scaling}")


@dataclass(frozen=True)
class ReservoirWeights:
    """Dense weights of one reservoir.

    Attributes:
        W: Recurrent matrix, shape ``(units, units)``.
        Win: Input matrix, shape ``(units, input_dim)``.
        bias: Bias vector, shape ``(units,)``.
        lr: Leak rate: one for every unit, or one per unit, shape ``(units,)``.
        linear: The update is ``x <- W x + Win u`` (no tanh, no leak; an RTU layer) and the
            policy sees ``tanh(x)``.
        raw: With ``linear``, the policy sees the whole state as it is, without tanh (an
            exponential moving average of the inputs: ``exposed_units`` does not apply).
    """

    W: np.ndarray
    Win: np.ndarray
    bias: np.ndarray
    lr: float | np.ndarray
    linear: bool = False
    raw: bool = False

    @property
    def units(self) -> int:
        return int(self.W.shape[0])

    @property
    def input_dim(self) -> int:
        return int(self.Win.shape[1])


def _dense(matrix: object) -> np.ndarray:
    toarray = getattr(matrix, "toarray", None)
    return np.asarray(toarray() if toarray is not None else matrix, dtype=np.float64)


def reservoir_node(params: ReservoirParams, input_dim: int, seed: int) -> Reservoir:
    """An initialized reservoirpy ``Reservoir`` with these hyperparameters and seed.

    Its initializers are reservoirpy's defaults: ``W`` normal then rescaled to spectral radius
    ``sr``, ``Win`` Bernoulli(+-input_scaling) on ``input_connectivity`` of its entries, and the
    bias zero, or dense Bernoulli(+-bias_scaling) on every unit (reservoirpy 0.4 calls the bias
    initializer with ``connectivity=1``), or with ``bias_init="original"`` reservoirpy 0.3's
    default: Bernoulli(+-1) on ``input_connectivity`` of the units, zero elsewhere (0.3 drew the
    bias with ``bias_scaling=1`` and the input connectivity; a connectivity given to the
    initializer itself wins over the one 0.4 passes). reservoirpy spawns independent generators
    for ``Win``, ``W`` and the bias from ``seed``, so the same seed gives the same ``W`` and bias
    for any ``input_dim`` (this is what "the same reservoir on another task" means in ermrl).
    A multi-timescale reservoir's node gets its units' leak rates (reservoirpy takes one per
    unit: [`ReservoirParams.leak_rates`][ermrl.encoders.ReservoirParams.leak_rates]).
    """
    # reservoirpy (and scipy.stats under it) is imported here, not with this module: the CLI,
    # the configuration and a plan read this module without building a reservoir.
    from reservoirpy import mat_gen
    from reservoirpy.nodes import Reservoir

    bias: object = 0.0
    if params.bias_init == "original":
        bias = mat_gen.bernoulli(input_scaling=1.0, connectivity=params.input_connectivity)
    elif params.bias_scaling > 0:
        bias = mat_gen.bernoulli(input_scaling=params.bias_scaling)
    node = Reservoir(
        units=params.units,
        sr=params.sr,
        lr=params.lr if params.lr_max is None else params.leak_rates(),
        input_scaling=params.input_scaling,
        rc_connectivity=params.rc_connectivity,
        input_connectivity=params.input_connectivity,
        bias=bias,
        input_dim=input_dim,
        seed=seed,
    )
    node.initialize(np.zeros(input_dim))
    return node


def reservoir_weights(params: ReservoirParams, input_dim: int, seed: int) -> ReservoirWeights:
    """Generate one reservoir's weights with reservoirpy's own initializers.

    Args:
        params: Hyperparameters.
        input_dim: Size of the input vector ``u``.
        seed: Seed of the weights.

    Returns:
        Dense float64 weights, with one leak rate per unit for a multi-timescale reservoir
        ([`ReservoirParams.leak_rates`][ermrl.encoders.ReservoirParams.leak_rates]). An ablation
        (`ReservoirParams.ablation`): ``"leaky"``, the same weights with ``W`` zero; ``"ema"``, the
        linear update of ``x = [e; u]``, ``e <- (1 - lr) e + lr u`` next to the current input ``u``
        (``W = diag((1 - lr) I, 0)``, ``Win = [lr I; I]``, no bias), shown raw.
    """
    if input_dim < 1:
        raise ValueError(f"input_dim must be >= 1, got {input_dim}")
    if params.ablation == "ema":
        # State [e; u]: e <- (1 - lr) e + lr u, then the current input u itself (W's second
        # block is zero, Win's is the identity), so the policy sees the input and its average.
        eye, zero = np.eye(input_dim), np.zeros((input_dim, input_dim))
        return ReservoirWeights(
            W=np.block([[(1.0 - params.lr) * eye, zero], [zero, zero]]),
            Win=np.vstack([params.lr * eye, eye]),
            bias=np.zeros(2 * input_dim),
            lr=1.0,  # the leak is in W and Win
            linear=True,
            raw=True,
        )
    node = reservoir_node(params, input_dim, seed)
    bias = np.broadcast_to(_dense(node.bias).ravel(), (params.units,)).copy()
    W = _dense(node.W)
    if params.ablation == "leaky":
        W = np.zeros_like(W)
    lr = float(params.lr) if params.lr_max is None else params.leak_rates()
    return ReservoirWeights(W=W, Win=_dense(node.Win), bias=bias, lr=lr)


def rtu_weights(params: RTUParams, input_dim: int, seed: int) -> ReservoirWeights:
    """One frozen RTU layer as a linear reservoir over the state ``x = [c1; c2]``.

    Per complex unit ``i``: ``r_i = sqrt(U(r_min^2, r_max^2))``, ``theta_i = U(0, theta_max)``,
    ``g = r cos(theta)``, ``phi = r sin(theta)``, ``gamma = sqrt(1 - r^2)``, and
    ``W = [[diag g, -diag phi], [diag phi, diag g]]``, ``Win = [gamma W1; gamma W2]`` with ``W1``,
    ``W2`` dense ``N(0, input_scaling^2 / input_dim)``. ``r`` and ``theta`` come from one child
    stream of ``seed`` and the input weights from another, so the same seed gives the same
    recurrence for any ``input_dim`` (as reservoirpy does for an ESN's ``W``).
    """
    if input_dim < 1:
        raise ValueError(f"input_dim must be >= 1, got {input_dim}")
    recurrent, inputs = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
    n = params.units
    r = np.sqrt(recurrent.uniform(params.r_min**2, params.r_max**2, n))
    theta = recurrent.uniform(0.0, params.theta_max, n)
    g, phi, gamma = r * np.cos(theta), r * np.sin(theta), np.sqrt(np.maximum(1.0 - r**2, 0.0))
    W = np.block([[np.diag(g), -np.diag(phi)], [np.diag(phi), np.diag(g)]])
    scale = params.input_scaling / np.sqrt(input_dim)
    W12 = inputs.normal(0.0, scale, (2 * n, input_dim))
    Win = np.concatenate([gamma, gamma])[:, None] * W12
    return ReservoirWeights(W=W, Win=Win, bias=np.zeros(2 * n), lr=1.0, linear=True)


def encoder_weights(params: object, input_dim: int, seed: int) -> ReservoirWeights:
    """The weights of one reservoir of either family
    ([`reservoir_weights`][ermrl.encoders.reservoir_weights] or
    [`rtu_weights`][ermrl.encoders.rtu_weights]).

    Raises:
        TypeError: ``params`` are neither an ESN's nor an RTU layer's settings.
    """
    if isinstance(params, RTUParams):
        return rtu_weights(params, input_dim, seed)
    if isinstance(params, ReservoirParams):
        return reservoir_weights(params, input_dim, seed)
    raise TypeError(f"no reservoir weights for {type(params).__name__} settings")


def reservoir_seeds(seed: int, n_reservoirs: int) -> list[int]:
    """Independent weight seeds for ``n_reservoirs`` reservoirs derived from one seed."""
    children = np.random.SeedSequence(seed).spawn(n_reservoirs)
    return [int(c.generate_state(1, dtype=np.uint32)[0]) for c in children]


class StepBank:
    """What every bank of [`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv] shares: stepping whole
    state arrays and running one sequence, through the bank's own ``buffer`` and ``step_buffer``
    (the ``[x | u]`` buffer and its in-place update).

    A bank the population backend can step for many agents at once also defines
    `stack` ([`ReservoirBank`][ermrl.encoders.ReservoirBank] and `NVARBank` do)."""

    n_units: int
    dtype: np.dtype
    units: tuple[int, ...]  # state values per reservoir
    linear: bool  # x <- [x | u] M (an RTU layer's, an NVAR's step)
    out_bound: float  # the bound of what the policy sees

    def emitter(
        self, exposed_units: int | None = None
    ) -> tuple[Callable[[np.ndarray], np.ndarray], int]:
        """What the policy sees of a state: ``(emit, width)``."""
        raise NotImplementedError

    @classmethod
    def stack(cls, banks: Sequence[Any]) -> StackedBanks:
        """The banks of ``P`` agents (all of this class and of one layout), stepped together.

        Raises:
            NotImplementedError: this bank has no batched step.
        """
        raise NotImplementedError(f"{cls.__name__} has no batched step for a population")

    def buffer(self, n: int) -> np.ndarray:
        raise NotImplementedError

    def step_buffer(self, xu: np.ndarray) -> None:
        raise NotImplementedError

    def step(self, states: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """Advance every state row by one step, in place.

        Args:
            states: Shape ``(n, N)``; updated in place and returned.
            inputs: Shape ``(n, input_dim)``.

        Returns:
            ``states``.
        """
        xu = np.concatenate([states, inputs], axis=1).astype(self.dtype, copy=False)
        self.step_buffer(xu)
        states[:] = xu[:, : self.n_units]
        return states

    def run(self, inputs: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
        """Run one sequence through the bank (for tests and analysis, not the hot path).

        Args:
            inputs: Shape ``(T, input_dim)``.
            state: Initial state, shape ``(N,)`` (zeros by default).

        Returns:
            States, shape ``(T, N)``.
        """
        xu = self.buffer(1)
        if state is not None:
            xu[0, : self.n_units] = state
        out = np.empty((len(inputs), self.n_units), self.dtype)
        for t, u in enumerate(np.asarray(inputs, self.dtype)):
            xu[0, self.n_units :] = u
            self.step_buffer(xu)
            out[t] = xu[0, : self.n_units]
        return out


class StackedBanks:
    """The banks of ``P`` agents stepped together on a ``[P, E, N + D]`` buffer ``[x | u]``
    ([`BatchedReservoir`][ermrl.population.BatchedReservoir]): `step` advances every row of every
    agent; `step_agent` advances rows of one agent with that agent's own bank, which
    computes the same values; `keep` drops agents. A subclass stacks the per-agent arrays
    named in `per_agent` (each with a leading agent axis)."""

    per_agent: tuple[str, ...] = ()

    def __init__(self, banks: Sequence[StepBank]) -> None:
        self.banks = list(banks)

    def step(self, xu: np.ndarray) -> None:
        """Advance the states ``xu[..., :N]`` of every agent on the inputs ``xu[..., N:]``."""
        raise NotImplementedError

    def step_agent(self, p: int, xu: np.ndarray) -> None:
        """Advance rows of agent ``p`` (``xu``: shape ``(n, N + D)``, updated in place)."""
        self.banks[p].step_buffer(xu)

    def keep(self, idx: np.ndarray) -> None:
        """Keep agents ``idx`` only, in that order."""
        for name in self.per_agent:
            setattr(self, name, getattr(self, name)[idx].copy())
        self.banks = [self.banks[i] for i in idx]


class _StackedReservoirs(StackedBanks):
    """Echo state networks or frozen RTU layers of ``P`` agents: one stacked ``matmul`` of
    ``[x | u]`` with each agent's ``M``, which numpy computes slice by slice, as each agent's
    [`ReservoirBank.step_buffer`][ermrl.encoders.ReservoirBank.step_buffer] would."""

    per_agent = ("M", "bias", "leak", "keep_rate")

    def __init__(self, banks: Sequence[ReservoirBank]) -> None:
        super().__init__(banks)
        self.M = np.stack([b.M for b in banks])
        self.bias = np.stack([b.bias for b in banks])[:, None, :]
        self.leak = np.stack([b.leak for b in banks])[:, None, :]
        self.keep_rate = np.stack([b.keep for b in banks])[:, None, :]
        self.has_bias = bool(np.any(self.bias))
        self.linear = banks[0].linear
        self.n_units = banks[0].n_units

    def step(self, xu: np.ndarray) -> None:
        pre = np.matmul(xu, self.M)
        if self.linear:
            xu[..., : self.n_units] = pre
            return
        if self.has_bias:
            pre += self.bias
        np.tanh(pre, out=pre)
        pre *= self.leak
        x = xu[..., : self.n_units]
        x *= self.keep_rate
        x += pre


class ReservoirBank(StepBank):
    """Several reservoirs fused into one batched leaky-ESN update.

    The fused system has ``N = sum(units)`` units: ``W`` is block-diagonal, the input matrices
    are stacked and the leak rate is a per-unit vector (each reservoir's one rate repeated, or
    its own per-unit rates). Recurrent and input weights are stacked
    into one matrix ``M = [W.T; Win.T]`` of shape ``(N + input_dim, N)``, so a step is a single
    matrix product of the buffer ``[x | u]`` (shape ``(n, N + input_dim)``) with ``M``.

    Args:
        weights: One [`ReservoirWeights`][ermrl.encoders.ReservoirWeights] per reservoir, all with
            the same ``input_dim``.
        dtype: Floating type of the state and weights (float64 matches reservoirpy exactly).
    """

    out_bound: float = 1.0  # the policy sees values in [-1, 1] (states or their tanh)

    def __init__(self, weights: Sequence[ReservoirWeights], dtype: type | str = np.float64) -> None:
        if not weights:
            raise ValueError("a ReservoirBank needs at least one reservoir")
        dims = {w.input_dim for w in weights}
        if len(dims) != 1:
            raise ValueError(f"all reservoirs must share input_dim, got {sorted(dims)}")
        if len({(w.linear, w.raw) for w in weights}) != 1:
            raise ValueError(
                "a ReservoirBank cannot mix linear (RTU), tanh and moving-average reservoirs"
            )
        self.linear = weights[0].linear
        # An EMA's state is shown whole and as it is: its values are the inputs' (unbounded).
        self.raw = weights[0].linear and weights[0].raw
        self.squash = self.linear and not self.raw
        if self.raw:
            self.out_bound = math.inf
        self.weights = tuple(weights)
        self.dtype = np.dtype(dtype)
        self.units = tuple(w.units for w in weights)
        self.n_units = sum(self.units)
        self.out_units = self.units  # what the policy sees: one value per unit
        self.input_dim = dims.pop()
        W = np.zeros((self.n_units, self.n_units))
        start = 0
        for w in weights:
            W[start : start + w.units, start : start + w.units] = w.W
            start += w.units
        Win = np.vstack([w.Win for w in weights])
        # Row-vector convention: [x | u] (n, N + D) @ M (N + D, N) = x W.T + u Win.T.
        self.M = np.ascontiguousarray(np.vstack([W.T, Win.T]), dtype=self.dtype)
        self.bias = np.concatenate([w.bias for w in weights]).astype(self.dtype)
        self.leak = np.concatenate(
            [np.broadcast_to(np.asarray(w.lr, np.float64), (w.units,)) for w in weights]
        ).astype(self.dtype)
        self.keep = (1.0 - self.leak).astype(self.dtype)
        self._has_bias = bool(np.any(self.bias))

    @classmethod
    def stack(cls, banks: Sequence[Any]) -> StackedBanks:
        """The reservoirs of ``P`` agents (same units and family), stepped together."""
        return _StackedReservoirs(banks)

    @property
    def W_T(self) -> np.ndarray:
        """The fused recurrent matrix, transposed: shape ``(N, N)``."""
        return self.M[: self.n_units]

    @property
    def Win_T(self) -> np.ndarray:
        """The stacked input matrix, transposed: shape ``(input_dim, N)``."""
        return self.M[self.n_units :]

    def buffer(self, n: int) -> np.ndarray:
        """A zeroed ``[x | u]`` buffer for ``n`` rows, shape ``(n, N + input_dim)``."""
        return np.zeros((n, self.n_units + self.input_dim), self.dtype)

    def step_buffer(self, xu: np.ndarray) -> None:
        """Advance the states held in ``xu[:, :N]`` by one step on the inputs in ``xu[:, N:]``.

        Args:
            xu: Shape ``(n, N + input_dim)``; its state columns are updated in place.
        """
        pre = np.matmul(xu, self.M)  # the function: ~0.5 us less per call than `@`
        if self.linear:
            xu[:, : self.n_units] = pre
            return
        if self._has_bias:
            pre += self.bias
        np.tanh(pre, out=pre)
        pre *= self.leak
        x = xu[:, : self.n_units]
        x *= self.keep
        x += pre

    def emit(self, states: np.ndarray) -> np.ndarray:
        """What the policy sees of ``states``, as a new float32 array: the states themselves
        (ESN, already in (-1, 1); an EMA) or their tanh (linear RTU layers, whose states are
        unbounded)."""
        if self.squash:
            return np.tanh(states).astype(np.float32)
        return states.astype(np.float32)

    def emitter(
        self, exposed_units: int | None = None
    ) -> tuple[Callable[[np.ndarray], np.ndarray], int]:
        """What the policy sees of a state: ``(emit, width)``.

        ``emit(states)`` maps states of shape ``(..., N)`` to a new float32 array of shape
        ``(..., width)``: [`emit`][ermrl.encoders.ReservoirBank.emit] of the first ``exposed_units``
        units of each reservoir (all units when ``None``, or for EMAs, whose values are the
        inputs').
        """
        if exposed_units is None or self.raw:
            index = None
            width = self.n_units
        else:
            starts = np.cumsum((0,) + self.units[:-1])
            index = np.concatenate([np.arange(s, s + exposed_units) for s in starts])
            width = len(index)
        squash = self.squash

        def emit(states: np.ndarray) -> np.ndarray:
            x = states if index is None else states[..., index]
            return np.tanh(x).astype(np.float32) if squash else x.astype(np.float32)

        return emit, width
