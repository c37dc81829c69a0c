"""Linear recurrent trace units (RTUs) trained by exact real-time recurrent learning (RTRL).

Elelimy et al., "Real-Time Recurrent Learning using Trace Units in Reinforcement Learning"
(NeurIPS 2024; official JAX code: esraaelelimy/rtus). This module holds the torch side of the
``rtu-ppo`` learner (`ermrl.learners._rtu_ppo`): the RTU layer and its RTRL step here,
then real-time PPO's policy, rollout buffer and algorithm (`RTUPPO`). It is only
imported when an ``rtu-ppo`` agent is built, so that importing the learner registry stays free
of torch, as for every other learner.

**The unit.** ``n`` complex units ``c = c¹ + i c²`` with parameters ``nu_log`` (n),
``theta_log`` (n), ``w1`` and ``w2`` (n × d_in, no bias)::

    r = exp(-exp(nu_log)),  theta = exp(theta_log)
    g = r cos(theta),  phi = r sin(theta),  gamma = sqrt(1 - r²)
    c¹_t = g c¹_{t-1} - phi c²_{t-1} + gamma (W₁ x_t)
    c²_t = g c²_{t-1} + phi c¹_{t-1} + gamma (W₂ x_t)
    h_t  = f([c¹_t; c²_t])                                 (width 2n)

``f`` is ReLU: the official ``RealTimeLinearRTUsLayer`` (``src/nets/rtus/rtus.py``) applies
``act_options[activation]`` with ``activation="relu"`` by default, and its PPO network
(``src/agents/RealTimeActorCritic.py``) builds the layer as ``rec_fn(config.d_rec)`` without
passing an activation (the config's ``activation: tanh`` only applies to the Dense layers).

**Initialisation** as the official ``rtus_utils.py``: ``r² ~ U(r_min², r_max²)`` with
``(r_min, r_max) = (0, 1)``, i.e. ``nu_log = log(-½ log u)``; ``theta ~ U(0, max_phase)`` with
``max_phase = 2π`` (the official code writes 6.28), ``theta_log = log theta``. ``W₁`` and ``W₂`` are
flax ``nn.Dense(use_bias=False)`` kernels there, i.e. flax's default ``lecun_normal``: a normal
of standard deviation ``sqrt(1/d_in) / 0.8796`` truncated at two standard deviations. The
official ``gamma`` adds 1e-8 to ``sqrt(1 - r²)``; here ``gamma`` is exact (see
`rtu_coefficients`). The official files named here were read in the indexed fork
SakodaShintaro/rtus of esraaelelimy/rtus.

**Exact RTRL.** The recurrence is diagonal (a complex scalar per unit), so the sensitivities
of ``c_t`` to the parameters are carried forward exactly at O(n) cost for ``nu_log`` and
``theta_log`` and O(n·d_in) for ``W₁``/``W₂``. With ``e = exp(nu_log)`` and ``u = W x``::

    dg/dnu_log = -e g,  dphi/dnu_log = -e phi,  dgamma/dnu_log = e r² / gamma
    dg/dtheta_log = -theta phi,  dphi/dtheta_log = theta g     (the chain-rule factor theta)

and every trace ``(T¹, T²)`` of ``(c¹, c²)`` obeys the same rotation plus its own forcing::

    T¹_t = g T¹_{t-1} - phi T²_{t-1} + F¹_t,   T²_t = g T²_{t-1} + phi T¹_{t-1} + F²_t
    nu_log:    F = (g' c¹ - phi' c², g' c² + phi' c¹)_{t-1} + gamma' (u¹_t, u²_t)
    theta_log: F = theta (-phi c¹ - g c², -phi c² + g c¹)_{t-1}
    W₁ row i:  F = (gamma_i x_t, 0)

The official code drops the factor ``theta`` in the ``theta_log`` forcing, so its gradient is
the true one divided by ``theta`` (``tests/test_rtu.py`` shows that such a gradient fails the
comparison with backpropagation through time). The ``W₂`` traces need no storage: in complex
form ``dc/dW₁ = A`` and ``dc/dW₂ = i A`` (both start at zero and obey the same recursion), so
``dc¹/dW₂ = -dc²/dW₁`` and ``dc²/dW₂ = dc¹/dW₁``. A carry therefore holds ``2 n d_in + 6 n``
numbers per row instead of ``4 n d_in + 6 n`` (half the paper's stored-trace memory).

The step is a `torch.autograd.Function` (`rtrl_step`): its backward gives the RTU
parameters the full RTRL gradient ``grad_c · trace`` and the input ``x`` its one-step gradient
``gamma (W₁ᵀ grad_c¹ + W₂ᵀ grad_c²)``; nothing flows into the carry (the paper stops the hidden
state's gradient), so layers below the RTU learn from the current step only.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Generator
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.distributions import (
    DiagGaussianDistribution,
    Distribution,
    make_proba_distribution,
)
from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import FlattenExtractor
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from stable_baselines3.common.utils import FloatSchedule, explained_variance, obs_as_tensor
from stable_baselines3.common.vec_env import VecEnv
from torch import Tensor, nn
from torch.nn import functional as F

__all__ = [
    "RTU",
    "RTUCarry",
    "RTUCoefficients",
    "RTUActorCriticPolicy",
    "RTURolloutBuffer",
    "RTURolloutSamples",
    "RTUPPO",
    "rtu_coefficients",
    "rtrl_step",
]

# flax's lecun_normal truncates a normal at two standard deviations; this is the standard
# deviation of the unit normal so truncated, by which its scale is divided.
_TRUNCATED_NORMAL_STD = 0.87962566103423978
_ACTIVATIONS = ("relu", "tanh", "linear")


class RTUCarry(NamedTuple):
    """What an RTU layer carries from one step to the next: its state and its RTRL traces.

    Every field has the batch (one row per sequence) first; the second axis is ``(c¹, c²)``.

    Attributes:
        h: ``(B, 2, n)``: the state ``(c¹, c²)``.
        nu: ``(B, 2, n)``: ``(dc¹/dnu_log, dc²/dnu_log)`` per unit.
        theta: ``(B, 2, n)``: ``(dc¹/dtheta_log, dc²/dtheta_log)`` per unit.
        w: ``(B, 2, n, d_in)``: ``(dc¹_i/dW₁[i], dc²_i/dW₁[i])`` per unit ``i``; the ``W₂``
            traces are ``(-w[:, 1], w[:, 0])``.
    """

    h: Tensor
    nu: Tensor
    theta: Tensor
    w: Tensor

    def reset(self, episode_starts: Tensor) -> RTUCarry:
        """The carry with the rows of starting episodes set to zero.

        Args:
            episode_starts: ``(B,)``, nonzero where a new sequence starts.
        """
        keep = 1.0 - episode_starts.to(self.h.dtype).reshape(-1)
        return RTUCarry(
            self.h * keep[:, None, None],
            self.nu * keep[:, None, None],
            self.theta * keep[:, None, None],
            self.w * keep[:, None, None, None],
        )

    def rows(self, index: Any) -> RTUCarry:
        """The carry of some rows (any torch index of the batch axis)."""
        return RTUCarry(self.h[index], self.nu[index], self.theta[index], self.w[index])

    def to(self, dtype: th.dtype | None = None, device: th.device | str | None = None) -> RTUCarry:
        """The carry converted to another dtype and/or device."""
        return RTUCarry(*(t.to(device=device, dtype=dtype) for t in self))


class RTUCoefficients(NamedTuple):
    """The rotation, input scale and their derivatives, each ``(n,)``.

    Attributes:
        g: ``r cos(theta)``.
        phi: ``r sin(theta)``.
        gamma: ``sqrt(1 - r²)``.
        dg_dnu: ``dg/dnu_log = -exp(nu_log) g``.
        dphi_dnu: ``dphi/dnu_log = -exp(nu_log) phi``.
        dgamma_dnu: ``dgamma/dnu_log = exp(nu_log) r² / gamma``.
        dg_dtheta: ``dg/dtheta_log = -theta phi``.
        dphi_dtheta: ``dphi/dtheta_log = theta g``.
    """

    g: Tensor
    phi: Tensor
    gamma: Tensor
    dg_dnu: Tensor
    dphi_dnu: Tensor
    dgamma_dnu: Tensor
    dg_dtheta: Tensor
    dphi_dtheta: Tensor


def _lecun_normal(weight: Tensor, generator: th.Generator | None = None) -> None:
    """flax's default Dense kernel init: variance 1/fan_in, a normal truncated at 2 std."""
    std = math.sqrt(1.0 / weight.shape[1]) / _TRUNCATED_NORMAL_STD
    with th.no_grad():
        nn.init.trunc_normal_(weight, std=std, a=-2 * std, b=2 * std, generator=generator)


def rtu_coefficients(nu_log: Tensor, theta_log: Tensor) -> RTUCoefficients:
    """The RTU's rotation ``(g, phi)``, input scale ``gamma`` and their parameter derivatives.

    ``1 - r²`` is computed as ``-expm1(-2 exp(nu_log))``, exact for ``r`` close to 1 (slow units),
    where ``1 - r²`` would round to 0 in float32.

    Args:
        nu_log: ``(n,)``.
        theta_log: ``(n,)``.
    """
    e = th.exp(nu_log)
    r = th.exp(-e)
    theta = th.exp(theta_log)
    g = r * th.cos(theta)
    phi = r * th.sin(theta)
    gamma = th.sqrt(-th.expm1(-2.0 * e))
    tiny = th.finfo(gamma.dtype).tiny
    return RTUCoefficients(
        g=g,
        phi=phi,
        gamma=gamma,
        dg_dnu=-e * g,
        dphi_dnu=-e * phi,
        # e r² / gamma -> 0 as e -> 0 (gamma ~ sqrt(2e)); the clamp only guards e == 0 exactly.
        dgamma_dnu=e * r * r / gamma.clamp_min(tiny),
        dg_dtheta=-theta * phi,
        dphi_dtheta=theta * g,
    )


def _rotate(g: Tensor, phi: Tensor, a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """``(g a - phi b, g b + phi a)``: multiplication by ``g + i phi`` in real form."""
    return g * a - phi * b, g * b + phi * a


def _state_step(
    co: RTUCoefficients, x: Tensor, h: Tensor, w1: Tensor, w2: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """One step of the recurrence: ``(c, u¹, u²)`` with ``c`` ``(B, 2, n)``, ``u = W x``."""
    u1 = x @ w1.T
    u2 = x @ w2.T
    c1, c2 = _rotate(co.g, co.phi, h[:, 0], h[:, 1])
    c = th.stack((c1 + co.gamma * u1, c2 + co.gamma * u2), dim=1)
    return c, u1, u2


class _RTRLStep(th.autograd.Function):
    """One RTU step whose backward is exact RTRL (see the module docstring).

    The ``W₁`` traces after the step, ``A_t = rot(A_{t-1}) + (gamma x, 0)``, are only built
    when the next carry is asked for (acting, re-scanning). The backward contracts the
    rotated output gradient with the traces before the step instead,
    ``grad_c · A_t = rotᵀ(grad_c) · A_{t-1} + gamma grad_c¹ x``, so a minibatch that only needs
    gradients never materialises a second ``(B, 2, n, d_in)`` tensor.
    """

    @staticmethod
    def forward(
        ctx: Any,
        new_w: bool,
        x: Tensor,
        nu_log: Tensor,
        theta_log: Tensor,
        w1: Tensor,
        w2: Tensor,
        h: Tensor,
        t_nu: Tensor,
        t_theta: Tensor,
        t_w: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        co = rtu_coefficients(nu_log, theta_log)
        c, u1, u2 = _state_step(co, x, h, w1, w2)
        c1p, c2p = h[:, 0], h[:, 1]
        # nu_log: the rotation of the old trace, plus the derivative of this step's map.
        n1, n2 = _rotate(co.g, co.phi, t_nu[:, 0], t_nu[:, 1])
        dg, dphi = co.dg_dnu, co.dphi_dnu
        n1 = n1 + dg * c1p - dphi * c2p + co.dgamma_dnu * u1
        n2 = n2 + dg * c2p + dphi * c1p + co.dgamma_dnu * u2
        # theta_log: gamma does not depend on theta.
        a1, a2 = _rotate(co.g, co.phi, t_theta[:, 0], t_theta[:, 1])
        dg, dphi = co.dg_dtheta, co.dphi_dtheta
        a1 = a1 + dg * c1p - dphi * c2p
        a2 = a2 + dg * c2p + dphi * c1p
        new_nu = th.stack((n1, n2), dim=1)
        new_theta = th.stack((a1, a2), dim=1)
        if new_w:
            # W₁ rows: unit i only sees row i, forced by gamma_i x (into c¹ only).
            g, phi = co.g[:, None], co.phi[:, None]
            w_1, w_2 = _rotate(g, phi, t_w[:, 0], t_w[:, 1])
            traces = th.stack((w_1 + co.gamma[:, None] * x[:, None, :], w_2), dim=1)
        else:
            traces = t_w.new_empty(0)
        ctx.save_for_backward(co.g, co.phi, co.gamma, x, w1, w2, new_nu, new_theta, t_w)
        ctx.mark_non_differentiable(new_nu, new_theta, traces)
        return c, new_nu, new_theta, traces

    @staticmethod
    def backward(ctx: Any, grad_c: Tensor, *unused: Tensor) -> tuple[Tensor | None, ...]:
        g, phi, gamma, x, w1, w2, t_nu, t_theta, t_w = ctx.saved_tensors
        d1, d2 = grad_c[:, 0], grad_c[:, 1]
        need = ctx.needs_input_grad
        grad_x = grad_nu = grad_theta = grad_w1 = grad_w2 = None
        if need[1]:
            grad_x = (gamma * d1) @ w1 + (gamma * d2) @ w2
        if need[2]:
            grad_nu = (d1 * t_nu[:, 0] + d2 * t_nu[:, 1]).sum(0)
        if need[3]:
            grad_theta = (d1 * t_theta[:, 0] + d2 * t_theta[:, 1]).sum(0)
        if need[4] or need[5]:
            # rotᵀ(grad_c), then the W₁ gradient sum_k e_k · A^k and, since
            # dc¹/dW₂ = -dc²/dW₁ and dc²/dW₂ = dc¹/dW₁, the W₂ gradient e_2 · A¹ - e_1 · A².
            e1, e2 = g * d1 + phi * d2, g * d2 - phi * d1
            weights = th.stack((th.stack((e1, e2), dim=1), th.stack((e2, -e1), dim=1)))
            grads = th.einsum("wbkn,bknd->wnd", weights, t_w)
            forcing = th.stack((gamma * d1, gamma * d2)).transpose(1, 2) @ x
            grad_w1, grad_w2 = grads[0] + forcing[0], grads[1] + forcing[1]
        return None, grad_x, grad_nu, grad_theta, grad_w1, grad_w2, None, None, None, None


def rtrl_step(
    x: Tensor,
    carry: RTUCarry,
    nu_log: Tensor,
    theta_log: Tensor,
    w1: Tensor,
    w2: Tensor,
    new_carry: bool = True,
) -> tuple[Tensor, RTUCarry | None]:
    """One RTU step from ``carry`` whose gradient is exact RTRL.

    Args:
        x: ``(B, d_in)`` input.
        carry: The state and traces before the step (never differentiated).
        nu_log: ``(n,)``.
        theta_log: ``(n,)``.
        w1: ``(n, d_in)``.
        w2: ``(n, d_in)``.
        new_carry: Build the carry after the step; without it (a minibatch that only needs
            gradients) the step skips the ``(B, 2, n, d_in)`` trace update.

    Returns:
        ``c`` ``(B, 2, n)`` (the new ``(c¹, c²)``, differentiable: the parameters get
        ``grad_c · trace``, ``x`` its one-step gradient) and the new carry (detached), or
        ``None`` without ``new_carry``.
    """
    c, t_nu, t_theta, t_w = _RTRLStep.apply(
        new_carry, x, nu_log, theta_log, w1, w2, carry.h.detach(), carry.nu, carry.theta, carry.w
    )
    if not new_carry:
        return c, None
    return c, RTUCarry(c.detach(), t_nu, t_theta, t_w)


class RTU(nn.Module):
    """A layer of linear RTUs (``n`` complex units) with exact RTRL.

    Args:
        input_dim: ``d_in``.
        units: ``n``; the output has ``2 n`` features.
        activation: ``f`` applied to ``[c¹; c²]``: ``"relu"`` (the official linear RTU),
            ``"tanh"`` or ``"linear"``.
        r_min: Smallest initial modulus ``r``.
        r_max: Largest initial modulus ``r``.
        max_phase: Initial phases are uniform on ``[0, max_phase]``.
    """

    def __init__(
        self,
        input_dim: int,
        units: int,
        activation: str = "relu",
        r_min: float = 0.0,
        r_max: float = 1.0,
        max_phase: float = 2 * math.pi,
    ) -> None:
        super().__init__()
        if activation not in _ACTIVATIONS:
            raise ValueError(f"activation must be one of {_ACTIVATIONS}, got {activation!r}")
        if not 0.0 <= r_min < r_max <= 1.0:
            raise ValueError(f"need 0 <= r_min < r_max <= 1, got {r_min}, {r_max}")
        self.input_dim = input_dim
        self.units = units
        self.activation = activation
        self.r_min, self.r_max, self.max_phase = r_min, r_max, max_phase
        self.nu_log = nn.Parameter(th.empty(units))
        self.theta_log = nn.Parameter(th.empty(units))
        self.w1 = nn.Parameter(th.empty(units, input_dim))
        self.w2 = nn.Parameter(th.empty(units, input_dim))
        self.reset_parameters()

    def reset_parameters(self, generator: th.Generator | None = None) -> None:
        """Draw the parameters as the official code does (see the module docstring)."""
        with th.no_grad():
            # u = r², clamped away from 0 and 1 where nu_log would be infinite.
            u = th.rand(self.units, generator=generator, dtype=th.float64)
            u = u * (self.r_max**2 - self.r_min**2) + self.r_min**2
            u = u.clamp(1e-12, 1.0 - 1e-12)
            self.nu_log.copy_(th.log(-0.5 * th.log(u)))
            phase = th.rand(self.units, generator=generator, dtype=th.float64) * self.max_phase
            self.theta_log.copy_(th.log(phase.clamp_min(1e-12)))
            for w in (self.w1, self.w2):
                _lecun_normal(w, generator)

    def initial_carry(
        self, batch: int, dtype: th.dtype | None = None, device: th.device | str | None = None
    ) -> RTUCarry:
        """Zeros: the carry at an episode's start, for ``batch`` rows."""
        dtype = dtype or self.w1.dtype
        device = device or self.w1.device
        n, d = self.units, self.input_dim
        return RTUCarry(
            th.zeros(batch, 2, n, dtype=dtype, device=device),
            th.zeros(batch, 2, n, dtype=dtype, device=device),
            th.zeros(batch, 2, n, dtype=dtype, device=device),
            th.zeros(batch, 2, n, d, dtype=dtype, device=device),
        )

    def output(self, c: Tensor) -> Tensor:
        """``f([c¹; c²])``: ``(B, 2, n)`` to ``(B, 2 n)``."""
        flat = c.reshape(c.shape[0], 2 * self.units)
        if self.activation == "relu":
            return F.relu(flat)
        if self.activation == "tanh":
            return th.tanh(flat)
        return flat

    def forward(self, x: Tensor, carry: RTUCarry) -> tuple[Tensor, RTUCarry]:
        """One step with exact RTRL gradients (`rtrl_step`).

        Args:
            x: ``(B, d_in)``.
            carry: State and traces before the step (reset them at episode starts first).

        Returns:
            The output ``f([c¹; c²])`` ``(B, 2 n)`` and the carry after the step.
        """
        c, after = rtrl_step(x, carry, self.nu_log, self.theta_log, self.w1, self.w2)
        assert after is not None
        return self.output(c), after

    def step_output(self, x: Tensor, carry: RTUCarry) -> Tensor:
        """`forward`'s output and gradients without building the next carry.

        Args:
            x: ``(B, d_in)``.
            carry: State and traces before the step.

        Returns:
            The output ``f([c¹; c²])`` ``(B, 2 n)``.
        """
        c, _ = rtrl_step(x, carry, self.nu_log, self.theta_log, self.w1, self.w2, new_carry=False)
        return self.output(c)

    def state_step(self, x: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
        """One step of the plain recurrence, no traces (acting; unrolled, it is BPTT).

        Args:
            x: ``(B, d_in)``.
            h: ``(B, 2, n)`` state before the step.

        Returns:
            The output ``(B, 2 n)`` and the state after the step ``(B, 2, n)``.
        """
        co = rtu_coefficients(self.nu_log, self.theta_log)
        c, _, _ = _state_step(co, x, h, self.w1, self.w2)
        return self.output(c), c


# --------------------------------------------------------------------------------------------
# Real-time PPO (see ermrl.learners._rtu_ppo for the learner and its settings)
# --------------------------------------------------------------------------------------------


class RTUActorCriticPolicy(BasePolicy):
    """Shared trunk ``obs -> Dense(d_hidden) -> tanh -> RTU(d_rec) -> ReLU``, two heads.

    The actor head is ``Dense(d_head) -> tanh -> action distribution`` (a diagonal Gaussian with
    a state-independent log std for ``Box``, categorical for ``Discrete``, ...) and the critic
    head ``Dense(d_head) -> tanh -> Dense(1)``. Initialisation as the official
    ``RealTimeActorCritic``: orthogonal with gain 2 (head hidden layers), 0.01 (action output)
    and 1 (value output), zero biases, log std 0; the trunk Dense is flax's default
    ``lecun_normal`` (its ``MLP`` in ``src/nets/MLP.py`` takes an orthogonal ``kernel_init``
    but never passes it to its Dense layers).

    Args:
        observation_space: Flat (``Box``, ``Discrete``, ...) observation space.
        action_space: ``Box``, ``Discrete``, ``MultiDiscrete`` or ``MultiBinary``.
        lr_schedule: Learning rate schedule (its value at progress 1 sets Adam's rate).
        d_rec: RTU units ``n``.
        d_hidden: Width of the Dense layer under the RTU.
        d_head: Width of each head's hidden layer.
        optimizer_class: The optimizer (Adam).
        optimizer_kwargs: Its arguments (default ``eps=1e-5``, as SB3's PPO and the paper).
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        lr_schedule: Schedule,
        d_rec: int = 192,
        d_hidden: int = 64,
        d_head: int = 64,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ) -> None:
        if optimizer_kwargs is None:
            optimizer_kwargs = {"eps": 1e-5}
        super().__init__(
            observation_space,
            action_space,
            features_extractor_class=FlattenExtractor,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
        )
        self.d_rec, self.d_hidden, self.d_head = d_rec, d_hidden, d_head
        self.features_extractor = FlattenExtractor(observation_space)
        self.encoder = nn.Linear(self.features_extractor.features_dim, d_hidden)
        self.rtu = RTU(d_hidden, d_rec)
        self.actor = nn.Sequential(nn.Linear(2 * d_rec, d_head), nn.Tanh())
        self.critic = nn.Sequential(nn.Linear(2 * d_rec, d_head), nn.Tanh(), nn.Linear(d_head, 1))
        self.action_dist = make_proba_distribution(action_space)
        if isinstance(self.action_dist, DiagGaussianDistribution):
            self.action_net, self.log_std = self.action_dist.proba_distribution_net(
                latent_dim=d_head, log_std_init=0.0
            )
        else:
            self.action_net = self.action_dist.proba_distribution_net(latent_dim=d_head)  # type: ignore[assignment]
        _lecun_normal(self.encoder.weight)
        nn.init.zeros_(self.encoder.bias)
        for module, gain in (
            (self.actor[0], 2.0),
            (self.critic[0], 2.0),
            (self.critic[2], 1.0),
            (self.action_net, 0.01),
        ):
            self.init_weights(module, gain)
        self.optimizer = self.optimizer_class(
            self.parameters(),
            lr=lr_schedule(1),  # type: ignore[call-arg]
            **self.optimizer_kwargs,
        )

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(d_rec=self.d_rec, d_hidden=self.d_hidden, d_head=self.d_head)
        return data

    def _input(self, obs: Tensor) -> Tensor:
        """The RTU's input ``tanh(Dense(obs))`` ``(B, d_hidden)``."""
        return th.tanh(self.encoder(self.extract_features(obs, self.features_extractor)))

    def _distribution(self, latent: Tensor) -> Distribution:
        mean = self.action_net(self.actor(latent))
        if isinstance(self.action_dist, DiagGaussianDistribution):
            return self.action_dist.proba_distribution(mean, self.log_std)
        return self.action_dist.proba_distribution(action_logits=mean)

    def trunk(self, obs: Tensor, carry: RTUCarry) -> tuple[Tensor, RTUCarry]:
        """The RTU's output ``(B, 2 d_rec)`` on one step from ``carry`` (RTRL gradients)."""
        return self.rtu(self._input(obs), carry)

    def forward(
        self, obs: Tensor, carry: RTUCarry, deterministic: bool = False
    ) -> tuple[Tensor, Tensor, Tensor, RTUCarry]:
        """Act on one step: ``(actions, values (B, 1), log_probs (B,), carry after)``."""
        latent, carry = self.trunk(obs, carry)
        distribution = self._distribution(latent)
        actions = distribution.get_actions(deterministic=deterministic)
        return actions, self.critic(latent), distribution.log_prob(actions), carry

    def evaluate_actions(
        self, obs: Tensor, carry: RTUCarry, actions: Tensor
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """Recompute one step from stored carries: ``(values (B, 1), log_prob, entropy)``."""
        latent = self.rtu.step_output(self._input(obs), carry)
        distribution = self._distribution(latent)
        return self.critic(latent), distribution.log_prob(actions), distribution.entropy()

    def predict_values(self, obs: Tensor, h: Tensor) -> Tensor:
        """Values ``(B, 1)`` of ``obs`` from the states ``h`` ``(B, 2, d_rec)`` (no traces)."""
        latent, _ = self.rtu.state_step(self._input(obs), h)
        return self.critic(latent)

    def _predict(self, observation: Any, deterministic: bool = False) -> Tensor:
        raise NotImplementedError("a recurrent policy: call predict() with its state")

    def predict(  # type: ignore[override]
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: np.ndarray | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Actions and the next state, as SB3's recurrent policies.

        Args:
            observation: One observation or a batch (a VecEnv's).
            state: ``(n_envs, 2, d_rec)`` states ``(c¹, c²)`` returned by the previous call;
                ``None`` starts from zeros.
            episode_start: ``(n_envs,)``, true where an episode starts (its state is zeroed).
            deterministic: The distribution's mode instead of a sample.

        Returns:
            The actions and the states after this step.
        """
        self.set_training_mode(False)
        obs, vectorized_env = self.obs_to_tensor(observation)
        assert isinstance(obs, Tensor)
        n_envs = obs.shape[0]
        with th.no_grad():
            if state is None:
                h = th.zeros(n_envs, 2, self.d_rec, device=self.device)
            else:
                h = th.as_tensor(np.asarray(state), dtype=th.float32, device=self.device)
            if episode_start is not None:
                starts = th.as_tensor(np.asarray(episode_start), device=self.device)
                h = h * (1.0 - starts.float().reshape(-1))[:, None, None]
            latent, h = self.rtu.state_step(self._input(obs), h)
            actions = self._distribution(latent).get_actions(deterministic=deterministic)
        shape: tuple[int, ...] = self.action_space.shape or ()
        out = actions.cpu().numpy().reshape((-1, *shape))
        if isinstance(self.action_space, spaces.Box):
            out = np.clip(out, self.action_space.low, self.action_space.high)
        if not vectorized_env:
            out = out.squeeze(axis=0)
        return out, h.cpu().numpy()


class RTURolloutSamples(NamedTuple):
    """One minibatch of single steps, each with the carry it was taken from."""

    observations: Tensor
    actions: Tensor
    old_values: Tensor
    old_log_prob: Tensor
    advantages: Tensor
    returns: Tensor
    carries: RTUCarry


class RTURolloutBuffer(RolloutBuffer):
    """SB3's rollout buffer, plus every transition's carry before its step (float32 tensors).

    The carries live in preallocated tensors of shape ``(n_steps, n_envs, ...)`` kept across
    rollouts (about ``n_steps · n_envs · (2 units · input_dim + 6 units) · 4`` bytes).

    Args:
        buffer_size: Steps per env per rollout.
        observation_space: The env's observation space.
        action_space: The env's action space.
        units: RTU units ``n``.
        input_dim: RTU input width ``d_in``.
        device: Where minibatches go.
        gae_lambda: GAE's lambda.
        gamma: Discount.
        n_envs: Number of envs.
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        units: int,
        input_dim: int,
        device: th.device | str = "auto",
        gae_lambda: float = 1.0,
        gamma: float = 0.99,
        n_envs: int = 1,
    ) -> None:
        shape = (buffer_size, n_envs, 2, units)
        # Uninitialised: every entry is written by add() before it is read.
        self.carries = RTUCarry(
            th.empty(shape),
            th.empty(shape),
            th.empty(shape),
            th.empty((*shape, input_dim)),
        )
        super().__init__(
            buffer_size,
            observation_space,
            action_space,
            device=device,
            gae_lambda=gae_lambda,
            gamma=gamma,
            n_envs=n_envs,
        )
        self.carries = self.carries.to(device=self.device)

    def add(  # type: ignore[override]
        self,
        obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        episode_start: np.ndarray,
        value: Tensor,
        log_prob: Tensor,
        carry: RTUCarry,
    ) -> None:
        """Store one step of every env, with the carries it started from."""
        self.set_carry(self.pos, carry)
        super().add(obs, action, reward, episode_start, value, log_prob)

    def set_carry(self, step: int, carry: RTUCarry) -> None:
        """Overwrite the stored carries of one step (all envs)."""
        for stored, new in zip(self.carries, carry):
            stored[step] = new.to(dtype=stored.dtype)

    def carry_at(self, step: int) -> RTUCarry:
        """The stored carries of one step (all envs), ``(n_envs, ...)``."""
        return RTUCarry(*(stored[step] for stored in self.carries))

    def get(  # type: ignore[override]
        self, batch_size: int | None = None
    ) -> Generator[RTURolloutSamples, None, None]:
        """Shuffled minibatches of single steps (the whole rollout once)."""
        assert self.full, "the rollout buffer is not full"
        total = self.buffer_size * self.n_envs
        indices = np.random.permutation(total)
        if batch_size is None:
            batch_size = total
        for start in range(0, total, batch_size):
            yield self._get_samples(indices[start : start + batch_size])

    def _get_samples(self, batch_inds: np.ndarray, env: Any = None) -> RTURolloutSamples:  # type: ignore[override]
        steps, envs = np.divmod(batch_inds, self.n_envs)
        at = (th.as_tensor(steps, device=self.device), th.as_tensor(envs, device=self.device))
        return RTURolloutSamples(
            observations=self.to_torch(self.observations[steps, envs]),
            actions=self.to_torch(self.actions[steps, envs].astype(np.float32)),
            old_values=self.to_torch(self.values[steps, envs]),
            old_log_prob=self.to_torch(self.log_probs[steps, envs]),
            advantages=self.to_torch(self.advantages[steps, envs]),
            returns=self.to_torch(self.returns[steps, envs]),
            carries=RTUCarry(*(stored[at] for stored in self.carries)),
        )


class RTUPPO(OnPolicyAlgorithm):
    """Real-time PPO (Elelimy et al., 2024) with an RTU policy trained by exact RTRL.

    SB3's PPO, except that the policy is recurrent and trained online-style: every stored
    transition keeps the carry (RTU state and RTRL traces) it was taken from, carries reset at
    episode starts and otherwise run on across rollouts, and each minibatch element is one step
    recomputed from its stored carry with the current parameters. ``stale_gradient=False``
    re-scans the rollout after every epoch but the last (whose fresh carries no minibatch
    would use) to recompute the stored carries with the new parameters; advantages and
    returns stay those of the rollout (the official ``stale_target: true``).

    Args: as `stable_baselines3.PPO` (``use_sde`` and ``rollout_buffer_class`` are not
        supported), plus ``stale_gradient``. ``policy_kwargs`` go to
        `RTUActorCriticPolicy` (``d_rec``, ``d_hidden``, ``d_head``).
    """

    policy_aliases = {"MlpPolicy": RTUActorCriticPolicy}
    policy: RTUActorCriticPolicy  # type: ignore[assignment]
    rollout_buffer: RTURolloutBuffer

    def __init__(
        self,
        policy: str | type[RTUActorCriticPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 1e-4,
        n_steps: int = 2048,
        batch_size: int = 64,
        n_epochs: int = 4,
        gamma: float = 0.99,
        gae_lambda: float = 0.95,
        clip_range: float | Schedule = 0.2,
        clip_range_vf: float | Schedule | None = None,
        normalize_advantage: bool = True,
        ent_coef: float = 0.0,
        vf_coef: float = 0.5,
        max_grad_norm: float = 0.5,
        use_sde: bool = False,
        sde_sample_freq: int = -1,
        rollout_buffer_class: type[RolloutBuffer] | None = None,
        rollout_buffer_kwargs: dict[str, Any] | None = None,
        target_kl: float | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
        stale_gradient: bool = True,
    ) -> None:
        if use_sde:
            raise ValueError("rtu-ppo does not support use_sde")
        if rollout_buffer_class is not None or rollout_buffer_kwargs:
            raise ValueError("rtu-ppo uses its own rollout buffer (rollout_buffer_class)")
        super().__init__(
            policy,  # type: ignore[arg-type]
            env,
            learning_rate=learning_rate,
            n_steps=n_steps,
            gamma=gamma,
            gae_lambda=gae_lambda,
            ent_coef=ent_coef,
            vf_coef=vf_coef,
            max_grad_norm=max_grad_norm,
            use_sde=False,
            sde_sample_freq=sde_sample_freq,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            _init_setup_model=False,
            supported_action_spaces=(
                spaces.Box,
                spaces.Discrete,
                spaces.MultiDiscrete,
                spaces.MultiBinary,
            ),
        )
        if normalize_advantage and batch_size <= 1:
            raise ValueError("batch_size must be > 1 with advantage normalization")
        if self.env is not None:
            rollout = self.env.num_envs * self.n_steps
            if rollout <= 1:
                raise ValueError(f"n_steps * n_envs must be > 1, got {rollout}")
            if rollout % batch_size:
                warnings.warn(
                    f"the rollout ({rollout} steps) is not a multiple of batch_size "
                    f"({batch_size}): the last minibatch has {rollout % batch_size} steps",
                    stacklevel=2,
                )
        self.batch_size = batch_size
        self.n_epochs = n_epochs
        self.clip_range = clip_range
        self.clip_range_vf = clip_range_vf
        self.normalize_advantage = normalize_advantage
        self.target_kl = target_kl
        self.stale_gradient = bool(stale_gradient)
        if _init_setup_model:
            self._setup_model()

    def _setup_model(self) -> None:
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        self.policy = self.policy_class(  # type: ignore[assignment]
            self.observation_space, self.action_space, self.lr_schedule, **self.policy_kwargs
        )
        self.policy = self.policy.to(self.device)
        rtu = self.policy.rtu
        self.rollout_buffer = RTURolloutBuffer(
            self.n_steps,
            self.observation_space,
            self.action_space,
            units=rtu.units,
            input_dim=rtu.input_dim,
            device=self.device,
            gamma=self.gamma,
            gae_lambda=self.gae_lambda,
            n_envs=self.n_envs,
        )
        self._last_carry = rtu.initial_carry(self.n_envs)
        self.clip_range = FloatSchedule(self.clip_range)
        if self.clip_range_vf is not None:
            if isinstance(self.clip_range_vf, (float, int)) and self.clip_range_vf <= 0:
                raise ValueError("clip_range_vf must be positive (or None: no clipping)")
            self.clip_range_vf = FloatSchedule(self.clip_range_vf)

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_last_carry"]

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        rollout_buffer: RolloutBuffer,
        n_rollout_steps: int,
    ) -> bool:
        """Fill the buffer with ``n_rollout_steps`` steps per env and their carries (as SB3)."""
        assert self._last_obs is not None, "No previous observation was provided"
        assert isinstance(rollout_buffer, RTURolloutBuffer)
        self.policy.set_training_mode(False)
        n_steps = 0
        rollout_buffer.reset()
        callback.on_rollout_start()
        dones = self._last_episode_starts
        while n_steps < n_rollout_steps:
            with th.no_grad():
                obs_tensor = obs_as_tensor(self._last_obs, self.device)  # type: ignore[arg-type]
                carry = self._last_carry
                if np.any(self._last_episode_starts):
                    starts = th.as_tensor(self._last_episode_starts, device=self.device)
                    carry = carry.reset(starts)
                actions, values, log_probs, self._last_carry = self.policy(obs_tensor, carry)
            if not (th.isfinite(values).all() and th.isfinite(self._last_carry.h).all()):
                raise ValueError("rtu-ppo: the policy output nan or inf (training diverged)")
            actions = actions.cpu().numpy()
            clipped_actions = actions
            if isinstance(self.action_space, spaces.Box):
                clipped_actions = np.clip(actions, self.action_space.low, self.action_space.high)
            new_obs, rewards, dones, infos = env.step(clipped_actions)
            self.num_timesteps += env.num_envs
            callback.update_locals(locals())
            if not callback.on_step():
                return False
            self._update_info_buffer(infos, dones)
            n_steps += 1
            if isinstance(self.action_space, spaces.Discrete):
                actions = actions.reshape(-1, 1)
            # Truncated episodes bootstrap from the value of their last observation, seen from
            # the episode's own state (the carry after this step, before its reset).
            for idx, done in enumerate(dones):
                if (
                    done
                    and infos[idx].get("terminal_observation") is not None
                    and infos[idx].get("TimeLimit.truncated", False)
                ):
                    terminal_obs = self.policy.obs_to_tensor(infos[idx]["terminal_observation"])[0]
                    with th.no_grad():
                        terminal_value = self.policy.predict_values(
                            terminal_obs,  # type: ignore[arg-type]
                            self._last_carry.h[idx : idx + 1],
                        )[0]
                    rewards[idx] += self.gamma * terminal_value.item()
            rollout_buffer.add(
                self._last_obs,  # type: ignore[arg-type]
                actions,
                rewards,
                self._last_episode_starts,  # type: ignore[arg-type]
                values,
                log_probs,
                carry,
            )
            self._last_obs = new_obs  # type: ignore[assignment]
            self._last_episode_starts = dones
        with th.no_grad():
            starts = th.as_tensor(dones, device=self.device).float().reshape(-1)
            h = self._last_carry.h * (1.0 - starts)[:, None, None]
            values = self.policy.predict_values(obs_as_tensor(new_obs, self.device), h)  # type: ignore[arg-type]
        rollout_buffer.compute_returns_and_advantage(last_values=values, dones=np.asarray(dones))
        callback.update_locals(locals())
        callback.on_rollout_end()
        return True

    def refresh_carries(self) -> None:
        """Recompute every stored carry with the current parameters (``stale_gradient=False``).

        The scan starts from the rollout's first stored carry and zeroes the carry of every env
        whose episode starts at a step.
        """
        buffer = self.rollout_buffer
        with th.no_grad():
            carry = buffer.carry_at(0)
            for step in range(buffer.buffer_size):
                if step > 0:
                    starts = th.as_tensor(buffer.episode_starts[step], device=self.device)
                    carry = carry.reset(starts)
                    buffer.set_carry(step, carry)
                obs = obs_as_tensor(buffer.observations[step], self.device)
                _, carry = self.policy.trunk(obs, carry)  # type: ignore[arg-type]

    def train(self) -> None:
        """PPO's update (as SB3's ``PPO.train``) on single steps from their stored carries."""
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.policy.optimizer)
        clip_range = self.clip_range(self._current_progress_remaining)  # type: ignore[operator]
        clip_range_vf = None
        if self.clip_range_vf is not None:
            clip_range_vf = self.clip_range_vf(self._current_progress_remaining)  # type: ignore[operator]
        entropy_losses: list[float] = []
        pg_losses: list[float] = []
        value_losses: list[float] = []
        clip_fractions: list[float] = []
        approx_kl_divs: list[float] = []
        loss = th.zeros(())
        continue_training = True
        for epoch in range(self.n_epochs):
            approx_kl_divs = []
            for data in self.rollout_buffer.get(self.batch_size):
                actions = data.actions
                if isinstance(self.action_space, spaces.Discrete):
                    actions = data.actions.long().flatten()
                values, log_prob, entropy = self.policy.evaluate_actions(
                    data.observations, data.carries, actions
                )
                values = values.flatten()
                advantages = data.advantages
                if self.normalize_advantage and len(advantages) > 1:
                    advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
                ratio = th.exp(log_prob - data.old_log_prob)
                policy_loss_1 = advantages * ratio
                policy_loss_2 = advantages * th.clamp(ratio, 1 - clip_range, 1 + clip_range)
                policy_loss = -th.min(policy_loss_1, policy_loss_2).mean()
                pg_losses.append(policy_loss.item())
                clip_fractions.append(th.mean((th.abs(ratio - 1) > clip_range).float()).item())
                if clip_range_vf is None:
                    values_pred = values
                else:
                    values_pred = data.old_values + th.clamp(
                        values - data.old_values, -clip_range_vf, clip_range_vf
                    )
                value_loss = F.mse_loss(data.returns, values_pred)
                value_losses.append(value_loss.item())
                if entropy is None:
                    entropy_loss = -th.mean(-log_prob)
                else:
                    entropy_loss = -th.mean(entropy)
                entropy_losses.append(entropy_loss.item())
                loss = policy_loss + self.ent_coef * entropy_loss + self.vf_coef * value_loss
                with th.no_grad():
                    log_ratio = log_prob - data.old_log_prob
                    approx_kl_div = th.mean((th.exp(log_ratio) - 1) - log_ratio).item()
                    approx_kl_divs.append(approx_kl_div)
                if self.target_kl is not None and approx_kl_div > 1.5 * self.target_kl:
                    continue_training = False
                    break
                self.policy.optimizer.zero_grad()
                loss.backward()
                th.nn.utils.clip_grad_norm_(self.policy.parameters(), self.max_grad_norm)
                self.policy.optimizer.step()
            self._n_updates += 1
            if not continue_training:
                break
            if not self.stale_gradient and epoch < self.n_epochs - 1:
                self.refresh_carries()
        buffer = self.rollout_buffer
        explained_var = explained_variance(buffer.values.flatten(), buffer.returns.flatten())
        self.logger.record("train/entropy_loss", np.mean(entropy_losses))
        self.logger.record("train/policy_gradient_loss", np.mean(pg_losses))
        self.logger.record("train/value_loss", np.mean(value_losses))
        self.logger.record("train/approx_kl", np.mean(approx_kl_divs))
        self.logger.record("train/clip_fraction", np.mean(clip_fractions))
        self.logger.record("train/loss", loss.item())
        self.logger.record("train/explained_variance", explained_var)
        if hasattr(self.policy, "log_std"):
            self.logger.record("train/std", th.exp(self.policy.log_std).mean().item())
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/clip_range", clip_range)
        if clip_range_vf is not None:
            self.logger.record("train/clip_range_vf", clip_range_vf)
