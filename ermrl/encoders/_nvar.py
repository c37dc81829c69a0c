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

It gets what an echo state network gets (:class:`~ermrl.encoders.ReservoirVecEnv`): the input
``u = [observation, previous action, previous reward * reward_scale] * input_scaling``, zero
history at each episode start with ``reset="episode"``, the skip connection and
``exposed_units`` (the first features of each NVAR).

The delay line is a linear shift register: a state of ``((k - 1) s + 1) d`` values steps as
``x <- [x | u] M`` with a fixed ``M`` that has one nonzero per column (1 for a shifted value,
``input_scaling`` for a new input), so :class:`NVARBank` steps it as the equivalent gather,
``x <- [x | u][:, src] * scale``, exactly (``M`` is built on demand for inspection). The state
holds the ``k`` slots the features read first (slot ``0, s, 2s, ...``), so the linear features
are a slice of it whatever the strides. The emission replaces the ESN's ``tanh``: the linear
features, then each monomial as the product of its ``n`` gathered columns (precomputed index
arrays).

The output width grows fast with the delay and the order; it also depends on the input size
``d`` (the task's observation and action sizes), which an :class:`NVARParams` does not know.
:func:`check_nvar_size` refuses more than :data:`NVAR_MAX_FEATURES` features in one line, and
:meth:`NVARSpace.check_input_dim` refuses a search space whose largest corner would, before a
study is created.

Its settings and agents are plain data here (:data:`CLI_FLAGS`, :data:`AGENTS`); the encoder is
not registered yet.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, cast

import numpy as np

from ermrl.config import (
    ConfigError,
    EncoderConfig,
    Range,
    TaskConfig,
    _box_center,
    _PerReservoirSpace,
)
from ermrl.encoders._base import Encoder

__all__ = [
    "AGENTS",
    "CLI_FLAGS",
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

# The most features one agent's NVAR(s) may show the policy, all reservoirs together. At 2,000 a
# policy's first layer (64 units) has 128k weights and a 2048-step rollout holds 16 MB of
# features per agent; beyond, a typo (a delay of 40) would exhaust memory before training.
NVAR_MAX_FEATURES = 2_000
# The most input steps one delay line may span, ``(delay - 1) * strides + 1``: a typo guard.
NVAR_MAX_WINDOW = 1_000


def nvar_width(delay: int, order: int, input_dim: int) -> int:
    """Features of ``NVAR(delay, order)`` on ``input_dim`` inputs:
    ``k d + C(k d + n - 1, n)`` (the linear part and the monomials of degree ``n``)."""
    linear = delay * input_dim
    return linear + math.comb(linear + order - 1, order)


def _check_int(name: str, value: Any, low: int) -> int:
    """``value`` as an int >= ``low`` (an integral float is accepted), else a ConfigError."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(f"{name} must be an integer, got {value!r}")
    if not float(value).is_integer():
        raise ConfigError(f"{name} must be an integer, got {value}")
    if int(value) < low:
        raise ConfigError(f"{name} must be >= {low}, got {int(value)}")
    return int(value)


@dataclass(frozen=True)
class NVARParams:
    """Hyperparameters of one NVAR (reservoirpy ``NVAR(delay, order, strides)`` arguments).

    The defaults, ``delay=2, order=2, strides=1``, are the paper's Lorenz-63 forecaster (the
    current and the previous input, quadratic monomials) and reservoirpy's own example, with
    ``input_scaling=1``: the unevolved reference of ``--encoder nvar`` (``random-nvar-res-ppo``).

    Input scaling: the input is multiplied by ``input_scaling`` before the delay line, so a
    degree-``k`` feature is multiplied by ``input_scaling ** k`` (``k = 1`` for the linear part).
    That is a constant per feature. Where the policy's input is normalized by running
    statistics (``normalize`` with ``norm_obs``, SB3's ``VecNormalize``, which ermrl's MuJoCo
    settings use), the normalization divides it out (up to its ``epsilon`` of ``1e-8`` and
    ``clip_obs``): input scaling is then inert, and evolving it only adds a flat dimension. Without
    normalization it sets the scale of the features the policy sees (and the balance between the
    linear part and the monomials).

    The output width depends on the input size ``d`` of the task (:func:`nvar_width`), which these
    settings do not hold: :meth:`state_dim_for` gives it; :attr:`state_dim`, what
    :class:`~ermrl.config.EncoderConfig` checks ``exposed_units`` and its unit count against,
    is the width for ``d = 1``, the smallest any task gives. The real size is checked where ``d``
    is known (:func:`check_nvar_size`).

    Attributes:
        delay: Inputs in the linear part (``k``: the current one and ``k - 1`` earlier ones).
        order: Degree of the monomials (``n``; 1 repeats the linear part, as reservoirpy does).
        strides: Steps between the inputs of the linear part (``s``).
        input_scaling: Factor applied to the input before the delay line.
        family: Always ``"nvar"`` (tells stored configurations apart from other encoders).
    """

    delay: int = 2
    order: int = 2
    strides: int = 1
    input_scaling: float = 1.0
    family: Literal["nvar"] = "nvar"

    def __post_init__(self) -> None:
        if self.family != "nvar":
            raise ConfigError(f"NVARParams family must be 'nvar', got {self.family!r}")
        for name in ("delay", "order", "strides"):
            object.__setattr__(self, name, _check_int(name, getattr(self, name), 1))
        if self.window > NVAR_MAX_WINDOW:
            raise ConfigError(
                f"an NVAR of delay {self.delay} and strides {self.strides} spans {self.window} "
                f"input steps; at most {NVAR_MAX_WINDOW} are allowed"
            )
        if not (self.input_scaling > 0 and math.isfinite(self.input_scaling)):
            raise ConfigError(f"input_scaling must be positive, got {self.input_scaling}")

    @property
    def window(self) -> int:
        """Input steps the delay line holds: ``(delay - 1) * strides + 1``."""
        return (self.delay - 1) * self.strides + 1

    @property
    def state_dim(self) -> int:
        """Features for a one-dimensional input, a lower bound of :meth:`state_dim_for`."""
        return self.state_dim_for(1)

    def state_dim_for(self, input_dim: int) -> int:
        """Features the policy sees for inputs of size ``input_dim``."""
        return nvar_width(self.delay, self.order, input_dim)


def check_nvar_size(reservoirs: Sequence[NVARParams], input_dim: int) -> int:
    """Refuse NVARs with more than :data:`NVAR_MAX_FEATURES` features on ``input_dim`` inputs.

    Args:
        reservoirs: One agent's NVARs.
        input_dim: Size ``d`` of their input.

    Returns:
        Their features, all NVARs together.

    Raises:
        ConfigError: too many features (one line naming the delay, order, ``d`` and the size).
    """
    total = sum(p.state_dim_for(input_dim) for p in reservoirs)
    if total > NVAR_MAX_FEATURES:
        raise ConfigError(
            f"{_size_text(reservoirs, input_dim, total)} (lower the delay or the order)"
        )
    return total


def _size_text(reservoirs: Sequence[NVARParams], input_dim: int, total: int) -> str:
    if len(reservoirs) == 1:
        parts = f"delay {reservoirs[0].delay} and order {reservoirs[0].order}"
    else:
        parts = ", ".join(
            f"delay {p.delay} and order {p.order} ({p.state_dim_for(input_dim):,})"
            for p in reservoirs
        )
    return (
        f"an NVAR of {parts} on d = {input_dim} inputs has {total:,} features; at most "
        f"{NVAR_MAX_FEATURES:,} are allowed"
    )


def encoder_input_dim(task: TaskConfig, encoder: EncoderConfig) -> int:
    """The size ``d`` of the input an encoder gets on ``task``: the (masked) observation, the
    encoded previous action (``feed_action``) and the previous reward (``feed_reward``), as
    :class:`~ermrl.encoders.ReservoirVecEnv` builds it. Makes (and closes) one env."""
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
    CMA-ES then searches it with margin (:class:`~ermrl.search.RestartCmaEsSampler`): the
    rounding is part of the search distribution, not applied to its samples afterwards.
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
    def center(self) -> int:
        """The middle integer (the lower one of two)."""
        return (self.low + self.high) // 2


# -- search space --------------------------------------------------------------------------------


@dataclass(frozen=True)
class NVARSpace(_PerReservoirSpace):
    """The evolved search space of NVARs (``--encoder nvar``): data, not code.

    The delay, the order and the strides are integer genes (:class:`IntRange`); the input scaling
    is log-scale (or fixed, with ``input_scaling=None``: it is inert under observation
    normalization, see :class:`NVARParams`). The reference point is :class:`NVARParams`'
    defaults (delay 2, order 2, strides 1, input scaling 1: the paper's and reservoirpy's
    example). The default ranges keep the largest NVAR (delay 4, order 2) within
    :data:`NVAR_MAX_FEATURES` for inputs of up to 15 values; a wider input (a MuJoCo task's
    full observation) needs a narrower delay range, which :meth:`check_input_dim` says.

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
        """The centre of the box: the middle integer of each integer gene (the lower of two),
        the geometric mean of the input scaling's bounds."""
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
        """Refuse a space whose widest corner exceeds :data:`NVAR_MAX_FEATURES` on ``input_dim``
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


# -- the batched computation ---------------------------------------------------------------------


@dataclass(frozen=True)
class _Segment:
    """The features of one NVAR in a fused state: ``states[..., lin]``, then the product over
    the columns of each row of ``monomials`` (absolute state columns)."""

    lin: slice
    monomials: np.ndarray  # (n_monomials, order), int64


class NVARBank:
    """Several NVARs on the same input, fused into one state and one gather per step.

    The same interface as :class:`~ermrl.encoders.ReservoirBank` (``buffer``, ``step_buffer``,
    ``emitter``, ``run``), so :class:`~ermrl.encoders.ReservoirVecEnv` and the population backend
    step it as they step an echo state network. Reservoir ``r``'s delay line holds
    ``window_r * d`` values: first the ``delay`` slots its features read (the newest input,
    then ``strides`` steps back, ...), then the slots in between, then (``windows``) padding that
    stays zero.

    Args:
        reservoirs: The NVARs' hyperparameters.
        input_dim: Size ``d`` of the input ``u``.
        dtype: Floating type of the state (float64 matches reservoirpy to rounding).
        windows: Per NVAR, the slots its delay line gets (at least its own window; the extra
            ones stay zero). Agents of a population with different strides then share one state
            layout. ``None``: each NVAR's own window.

    Raises:
        ConfigError: more than :data:`NVAR_MAX_FEATURES` features.
    """

    # Features are unbounded (an RTU layer's tanh is not).
    out_bound: ClassVar[float] = math.inf

    def __init__(
        self,
        reservoirs: Sequence[NVARParams],
        input_dim: int,
        dtype: type | str = np.float64,
        windows: Sequence[int] | None = None,
    ) -> None:
        if not reservoirs:
            raise ValueError("an NVARBank needs at least one NVAR")
        if input_dim < 1:
            raise ValueError(f"input_dim must be >= 1, got {input_dim}")
        check_nvar_size(reservoirs, input_dim)
        windows = [p.window for p in reservoirs] if windows is None else list(windows)
        if len(windows) != len(reservoirs) or any(
            w < p.window for w, p in zip(windows, reservoirs)
        ):
            raise ValueError(f"windows {windows} must hold each NVAR's own window")
        self.reservoirs = tuple(reservoirs)
        self.dtype = np.dtype(dtype)
        self.input_dim = d = input_dim
        self.linear = True  # x <- [x | u] M: no tanh, no leak
        self.units = tuple(w * d for w in windows)  # state values per NVAR
        self.n_units = N = sum(self.units)
        self.out_units = tuple(p.state_dim_for(d) for p in reservoirs)  # features per NVAR
        src = np.arange(N)  # padding maps onto itself, with scale 0: it stays zero
        scale = np.zeros(N)
        self._segments: list[_Segment] = []
        offset = 0
        for p, w in zip(reservoirs, windows):
            # State slot of each input lag j (0 = now): the feature lags first, then the others.
            lags = [j * p.strides for j in range(p.delay)]
            lags += [j for j in range(p.window) if j % p.strides or j // p.strides >= p.delay]
            slot = {lag: i for i, lag in enumerate(lags)}
            for lag, i in slot.items():
                cols = offset + i * d + np.arange(d)
                if lag == 0:
                    src[cols], scale[cols] = N + np.arange(d), p.input_scaling
                else:
                    src[cols], scale[cols] = offset + slot[lag - 1] * d + np.arange(d), 1.0
            n_lin = p.delay * d
            combos = itertools.combinations_with_replacement(range(n_lin), p.order)
            monomials = np.array(list(combos), np.int64).reshape(-1, p.order) + offset
            self._segments.append(_Segment(slice(offset, offset + n_lin), monomials))
            offset += w * d
        self.src = src
        self.scale = scale.astype(self.dtype)

    @property
    def M(self) -> np.ndarray:
        """The step as a matrix, ``x <- [x | u] M``: shape ``(N + input_dim, N)``, one nonzero
        per column (built on demand; the step itself is the equivalent gather)."""
        M = np.zeros((self.n_units + self.input_dim, self.n_units), self.dtype)
        M[self.src, np.arange(self.n_units)] = self.scale
        return M

    def buffer(self, n: int) -> np.ndarray:
        """A zeroed ``[x | u]`` buffer for ``n`` rows, shape ``(n, N + input_dim)``."""
        return np.zeros((n, self.n_units + self.input_dim), self.dtype)

    def step_buffer(self, xu: np.ndarray) -> None:
        """Shift the delay lines held in ``xu[:, :N]`` and take in the inputs ``xu[:, N:]``.

        Args:
            xu: Shape ``(n, N + input_dim)``; its state columns are updated in place.
        """
        new = xu[:, self.src]
        new *= self.scale
        xu[:, : self.n_units] = new

    def emitter(
        self, exposed_units: int | None = None
    ) -> tuple[Callable[[np.ndarray], np.ndarray], int]:
        """What the policy sees of a state: ``(emit, width)``.

        ``emit(states)`` maps states of shape ``(..., N)`` to float32 features ``(..., width)``:
        per NVAR, its linear features then its monomials, only the first ``exposed_units`` of
        each NVAR when given.
        """
        plan: list[tuple[slice, np.ndarray]] = []
        for seg, n_out in zip(self._segments, self.out_units):
            keep = n_out if exposed_units is None else min(exposed_units, n_out)
            n_lin = seg.lin.stop - seg.lin.start
            lin = slice(seg.lin.start, seg.lin.start + min(keep, n_lin))
            plan.append((lin, seg.monomials[: max(keep - n_lin, 0)]))
        width = sum(lin.stop - lin.start + len(mono) for lin, mono in plan)

        def emit(states: np.ndarray) -> np.ndarray:
            out = np.empty((*states.shape[:-1], width), np.float32)
            at = 0
            for lin, mono in plan:
                n_lin = lin.stop - lin.start
                out[..., at : at + n_lin] = states[..., lin]
                at += n_lin
                if len(mono):
                    product = states[..., mono[:, 0]]
                    for k in range(1, mono.shape[1]):
                        product *= states[..., mono[:, k]]
                    out[..., at : at + len(mono)] = product
                    at += len(mono)
            return out

        return emit, width

    def emit(self, states: np.ndarray) -> np.ndarray:
        """All features of ``states`` (shape ``(..., N)``), as a new float32 array."""
        return self.emitter()[0](states)

    def step(self, states: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """Advance every state row by one step, in place (``states`` ``(n, N)``, ``inputs``
        ``(n, input_dim)``); returns ``states``."""
        xu = np.concatenate([states, inputs], axis=1).astype(self.dtype, copy=False)
        self.step_buffer(xu)
        states[:] = xu[:, : self.n_units]
        return states

    def run(self, inputs: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
        """Run one sequence through the delay lines (for tests and analysis, not the hot path).

        Args:
            inputs: Shape ``(T, input_dim)``.
            state: Initial state, shape ``(N,)`` (zero history by default).

        Returns:
            States, shape ``(T, N)`` (:meth:`features` gives what the policy sees of them).
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

    def features(self, states: np.ndarray) -> np.ndarray:
        """All features of ``states`` (shape ``(..., N)``) in the state's dtype: the emitter's
        arithmetic without its float32 cast."""
        parts = []
        for seg in self._segments:
            parts.append(states[..., seg.lin])
            product = states[..., seg.monomials[:, 0]]
            for k in range(1, seg.monomials.shape[1]):
                product *= states[..., seg.monomials[:, k]]
            parts.append(product)
        return np.concatenate(parts, axis=-1)


def nvar_structure(params: NVARParams) -> tuple[int, int]:
    """What fixes an NVAR's feature layout: ``(delay, order)`` (strides and input scaling only
    change which inputs fill it, so agents that differ in those share a population)."""
    return params.delay, params.order


# -- the encoder ---------------------------------------------------------------------------------


class NVAREncoder(Encoder):
    """The NVAR encoder: decoding of a trial's genes, and the env wrapper
    (:class:`~ermrl.encoders.ReservoirVecEnv` with an :class:`NVARBank`)."""

    name = "nvar"
    description = (
        "next-generation reservoir (NVAR: delayed inputs and their monomials, reservoirpy); "
        "frozen, wraps the env"
    )
    place = "env"
    family = "nvar"
    config_cls = EncoderConfig
    space_cls: ClassVar[type] = NVARSpace

    def decode(
        self, space: NVARSpace, params: Mapping[str, float], base: EncoderConfig
    ) -> EncoderConfig:
        # EncoderConfig's annotation does not list NVARParams until the encoder is registered.
        return dataclasses.replace(base, reservoirs=space.reservoirs_from(params))  # type: ignore[arg-type]

    def wrap_env(self, venv: Any, config: EncoderConfig, seed: int) -> Any:
        from ermrl.encoders._vec_env import ReservoirVecEnv

        return ReservoirVecEnv(venv, config, seed=seed)


# -- plain data for the registry: CLI flags and test-phase agents --------------------------------

# ``ermrl evolve`` flags of ``--encoder nvar`` (argparse ``add_argument`` keywords as data). The
# shared ``--n-reservoirs``, ``--input-scaling-range`` and ``--fixed-input-scaling`` apply too.
CLI_FLAGS: tuple[dict[str, Any], ...] = (
    {
        "flags": ("--delay-range",),
        "dest": "delay_range",
        "nargs": 2,
        "type": int,
        "default": (1, 4),
        "metavar": ("LOW", "HIGH"),
        "space_field": "delay",
        "help": "--encoder nvar: range of the delay, the inputs in the linear part (integers)",
    },
    {
        "flags": ("--order-range",),
        "dest": "order_range",
        "nargs": 2,
        "type": int,
        "default": (1, 2),
        "metavar": ("LOW", "HIGH"),
        "space_field": "order",
        "help": "--encoder nvar: range of the order, the degree of the monomials (integers)",
    },
    {
        "flags": ("--strides-range",),
        "dest": "strides_range",
        "nargs": 2,
        "type": int,
        "default": (1, 4),
        "metavar": ("LOW", "HIGH"),
        "space_field": "strides",
        "help": "--encoder nvar: range of the strides, the steps between delayed inputs (integers)",
    },
)

# Test-phase agents of ``--encoder nvar`` studies, as ``ermrl.config.AgentKind`` fields.
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
