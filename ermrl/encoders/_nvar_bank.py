"""The NVAR's settings and batched computation (no env, no encoder): what
[`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv] and the population backend step.

`ermrl.encoders._nvar` describes the model (Gauthier et al. 2021, as reservoirpy 0.4's
``NVAR`` node builds it) and holds the encoder; this module sits below
`ermrl.encoders._vec_env`, which the encoder wraps the env in.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ermrl._config_base import ConfigError
from ermrl.encoders._reservoir import StackedBanks, StepBank

__all__ = [
    "NVAR_MAX_FEATURES",
    "NVAR_MAX_WINDOW",
    "NVARBank",
    "NVARParams",
    "check_nvar_size",
    "nvar_structure",
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

    The output width depends on the input size ``d`` of the task (`nvar_width`), which these
    settings do not hold: `state_dim_for` gives it; `state_dim`, what
    [`EncoderConfig`][ermrl.config.EncoderConfig] checks ``exposed_units`` and its unit count
    against, is the width for ``d = 1``, the smallest any task gives. The real size is checked where
    ``d`` is known (`check_nvar_size`).

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
        """Features for a one-dimensional input, a lower bound of `state_dim_for`."""
        return self.state_dim_for(1)

    def state_dim_for(self, input_dim: int) -> int:
        """Features the policy sees for inputs of size ``input_dim``."""
        return nvar_width(self.delay, self.order, input_dim)


def check_nvar_size(reservoirs: Sequence[NVARParams], input_dim: int) -> int:
    """Refuse NVARs with more than `NVAR_MAX_FEATURES` features on ``input_dim`` inputs.

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


@dataclass(frozen=True)
class _Segment:
    """The features of one NVAR in a fused state: ``states[..., lin]``, then the product over
    the columns of each row of ``monomials`` (absolute state columns)."""

    lin: slice
    monomials: np.ndarray  # (n_monomials, order), int64


class NVARBank(StepBank):
    """Several NVARs on the same input, fused into one state and one gather per step.

    The same interface as [`ReservoirBank`][ermrl.encoders.ReservoirBank] (``buffer``,
    ``step_buffer``, ``emitter``, ``run``), so [`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv]
    and the population backend step it as they step an echo state network. Reservoir ``r``'s delay
    line holds ``window_r * d`` values: first the ``delay`` slots its features read (the newest
    input, then ``strides`` steps back, ...), then the slots in between, then (``windows``) padding
    that stays zero.

    Args:
        reservoirs: The NVARs' hyperparameters.
        input_dim: Size ``d`` of the input ``u``.
        dtype: Floating type of the state (float64 matches reservoirpy to rounding).
        windows: Per NVAR, the slots its delay line gets (at least its own window; the extra
            ones stay zero). Agents of a population with different strides then share one state
            layout. ``None``: each NVAR's own window.

    Raises:
        ConfigError: more than `NVAR_MAX_FEATURES` features.
    """

    # Features are unbounded (an RTU layer's tanh is not).
    out_bound: float = math.inf

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

    @classmethod
    def stack(cls, banks: Sequence[Any]) -> StackedBanks:
        """The NVARs of ``P`` agents (one layout: the same delay, order and padded windows,
        `population_banks`), stepped together."""
        return _StackedNVARs(banks)

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


class _StackedNVARs(StackedBanks):
    """The NVARs of ``P`` agents: one batched gather shifts every delay line, each agent with
    its own source columns and input scaling (as each agent's `NVARBank.step_buffer`)."""

    per_agent = ("src", "scale")

    def __init__(self, banks: Sequence[NVARBank]) -> None:
        super().__init__(banks)
        if len({b.n_units for b in banks}) != 1:
            raise ValueError("the NVARs of a population must share one state layout")
        self.src = np.stack([b.src for b in banks])  # [P, N]
        self.scale = np.stack([b.scale for b in banks])  # [P, N]
        self.n_units = banks[0].n_units

    def step(self, xu: np.ndarray) -> None:
        new = np.take_along_axis(xu, self.src[:, None, :], axis=2)
        new *= self.scale[:, None, :]
        xu[..., : self.n_units] = new


def nvar_structure(params: NVARParams) -> tuple[int, int]:
    """What fixes an NVAR's feature layout: ``(delay, order)`` (strides and input scaling only
    change which inputs fill it, so agents that differ in those share a population)."""
    return params.delay, params.order


# -- the encoder ---------------------------------------------------------------------------------
