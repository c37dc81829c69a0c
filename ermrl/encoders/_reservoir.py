"""Reservoir weights from reservoirpy's initializers, and a batched leaky-ESN update.

The update rule is reservoirpy's ``Reservoir`` rule, applied to ``n_envs`` state rows at once::

    x <- (1 - lr) * x + lr * tanh(W x + Win u + b)

Several reservoirs are fused into one block-diagonal system, so one step is one matrix product
for all reservoirs and all environments: there is no per-step reservoirpy ``Node`` call.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from reservoirpy import mat_gen
from reservoirpy.nodes import Reservoir

from ermrl.config import ReservoirParams

__all__ = ["ReservoirWeights", "ReservoirBank", "reservoir_weights", "reservoir_seeds"]


@dataclass(frozen=True)
class ReservoirWeights:
    """Dense weights of one reservoir.

    Attributes:
        W: Recurrent matrix, shape ``(units, units)``.
        Win: Input matrix, shape ``(units, input_dim)``.
        bias: Bias vector, shape ``(units,)``.
        lr: Leak rate.
    """

    W: np.ndarray
    Win: np.ndarray
    bias: np.ndarray
    lr: float

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
    ``sr``, ``Win`` Bernoulli(+-input_scaling), the bias Bernoulli(+-bias_scaling) or zero.
    reservoirpy spawns independent generators for ``Win``, ``W`` and the bias from ``seed``, so
    the same seed gives the same ``W`` and bias for any ``input_dim`` (this is what "the same
    reservoir on another task" means in ermrl).
    """
    bias: object = 0.0
    if params.bias_scaling > 0:
        bias = mat_gen.bernoulli(input_scaling=params.bias_scaling)
    node = Reservoir(
        units=params.units,
        sr=params.sr,
        lr=params.lr,
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
        Dense float64 weights.
    """
    if input_dim < 1:
        raise ValueError(f"input_dim must be >= 1, got {input_dim}")
    node = reservoir_node(params, input_dim, seed)
    bias = np.broadcast_to(_dense(node.bias).ravel(), (params.units,)).copy()
    return ReservoirWeights(W=_dense(node.W), Win=_dense(node.Win), bias=bias, lr=float(params.lr))


def reservoir_seeds(seed: int, n_reservoirs: int) -> list[int]:
    """Independent weight seeds for ``n_reservoirs`` reservoirs derived from one seed."""
    children = np.random.SeedSequence(seed).spawn(n_reservoirs)
    return [int(c.generate_state(1, dtype=np.uint32)[0]) for c in children]


class ReservoirBank:
    """Several reservoirs fused into one batched leaky-ESN update.

    The fused system has ``N = sum(units)`` units: ``W`` is block-diagonal, the input matrices
    are stacked and the leak rate is a per-unit vector.

    Args:
        weights: One :class:`ReservoirWeights` per reservoir, all with the same ``input_dim``.
        dtype: Floating type of the state and weights (float64 matches reservoirpy exactly).
    """

    def __init__(self, weights: Sequence[ReservoirWeights], dtype: type = np.float64) -> None:
        if not weights:
            raise ValueError("a ReservoirBank needs at least one reservoir")
        dims = {w.input_dim for w in weights}
        if len(dims) != 1:
            raise ValueError(f"all reservoirs must share input_dim, got {sorted(dims)}")
        self.units = tuple(w.units for w in weights)
        self.n_units = sum(self.units)
        self.input_dim = dims.pop()
        W = np.zeros((self.n_units, self.n_units))
        start = 0
        for w in weights:
            W[start : start + w.units, start : start + w.units] = w.W
            start += w.units
        # Row-vector convention: X (n, N) @ W.T (N, N) + U (n, D) @ Win.T (D, N).
        self.W_T = np.ascontiguousarray(W.T, dtype=dtype)
        self.Win_T = np.ascontiguousarray(np.vstack([w.Win for w in weights]).T, dtype=dtype)
        self.bias = np.concatenate([w.bias for w in weights]).astype(dtype)
        self.leak = np.concatenate([np.full(w.units, w.lr) for w in weights]).astype(dtype)
        self.keep = (1.0 - self.leak).astype(dtype)
        self.dtype = dtype
        self._has_bias = bool(np.any(self.bias))

    def step(self, states: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """Advance every state row by one step, in place.

        Args:
            states: Shape ``(n, N)``; updated in place and returned.
            inputs: Shape ``(n, input_dim)``.

        Returns:
            ``states``.
        """
        pre = states @ self.W_T
        pre += inputs @ self.Win_T
        if self._has_bias:
            pre += self.bias
        np.tanh(pre, out=pre)
        pre *= self.leak
        states *= self.keep
        states += pre
        return states

    def run(self, inputs: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
        """Run one sequence through the bank (for tests and analysis, not the hot path).

        Args:
            inputs: Shape ``(T, input_dim)``.
            state: Initial state, shape ``(N,)`` (zeros by default).

        Returns:
            States, shape ``(T, N)``.
        """
        x = np.zeros((1, self.n_units), self.dtype) if state is None else state[None].copy()
        out = np.empty((len(inputs), self.n_units), self.dtype)
        for t, u in enumerate(np.asarray(inputs, self.dtype)):
            out[t] = self.step(x, u[None])[0]
        return out
