"""Stacked actor-critic MLPs: SB3's PPO ``MlpPolicy`` for ``P`` agents at once.

Each layer holds the weights of every agent in one tensor ``[P, in, out]`` (biases ``[P, 1, out]``),
so a forward pass is one stacked product per layer; these tensors are views into one flat ``[P, N]``
buffer (one row per agent), which the gradient clipping and Adam treat as a whole. Rollouts and
updates run the weights through numpy (views of the torch tensors), which is several times faster
than torch for these small products on a CPU: the update's gradient is written out by hand
([`StackedPolicy.ppo_gradient`][ermrl.population.StackedPolicy.ppo_gradient], backpropagation
through the tanh MLPs) rather than taken by autograd, whose per-op overhead cost more than the
products (``benchmarks/bench_update.py``). The network is SB3's: separate policy and value MLPs
(``net_arch``, default 64-64, tanh), an action head (diagonal Gaussian with a state-independent
``log_std``, gSDE, or categorical) and a value head, orthogonal initialization with SB3's gains;
[`StackedPolicy.sb3_state`][ermrl.population.StackedPolicy.sb3_state] and
[`StackedPolicy.load_sb3_state`][ermrl.population.StackedPolicy.load_sb3_state] convert one agent to
and from SB3's ``state_dict``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

__all__ = ["ROW_ALIGN", "PolicySpec", "StackedAdam", "StackedPolicy", "policy_spec"]

LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)
SDE_EPSILON = 1e-6  # SB3's StateDependentNoiseDistribution epsilon
# A row of the flat parameter buffer is padded to a multiple of this many elements (wider than any
# CPU kernel's unrolled SIMD step), so elementwise kernels treat each agent's elements alike for
# any number of rows: none falls in a scalar tail that would round differently.
ROW_ALIGN = 64


class PolicySpec:
    """The network's shape and action head, read from SB3's ``policy_kwargs`` and ``use_sde``."""

    def __init__(
        self,
        obs_dim: int,
        action_dim: int,
        discrete: bool,
        pi: Sequence[int],
        vf: Sequence[int],
        use_sde: bool,
        log_std_init: float,
        ortho_init: bool,
    ) -> None:
        self.obs_dim, self.action_dim, self.discrete = obs_dim, action_dim, discrete
        self.pi, self.vf = tuple(pi), tuple(vf)
        self.use_sde, self.log_std_init, self.ortho_init = use_sde, log_std_init, ortho_init

    @property
    def latent_pi(self) -> int:
        return self.pi[-1] if self.pi else self.obs_dim

    @property
    def latent_vf(self) -> int:
        return self.vf[-1] if self.vf else self.obs_dim


_POLICY_KWARGS = {"net_arch", "log_std_init", "ortho_init", "activation_fn"}


def policy_spec(
    policy_kwargs: Mapping[str, Any], obs_dim: int, action_dim: int, discrete: bool, use_sde: bool
) -> PolicySpec:
    """The network SB3's ``MlpPolicy`` would build with these ``policy_kwargs``.

    Raises:
        ValueError: a ``policy_kwargs`` key the population backend does not implement, or an
            ``activation_fn`` other than tanh (SB3's default, the only one implemented).
    """
    unknown = set(policy_kwargs) - _POLICY_KWARGS
    if unknown:
        raise ValueError(
            f"the population backend does not implement policy_kwargs {sorted(unknown)} "
            f"(it supports {sorted(_POLICY_KWARGS)}); use --backend sb3"
        )
    activation = policy_kwargs.get("activation_fn", torch.nn.Tanh)
    if activation not in (torch.nn.Tanh, "tanh"):
        name = getattr(activation, "__name__", activation)
        raise ValueError(
            f"the population backend implements activation_fn tanh only, not {name}; "
            "use --backend sb3"
        )
    arch = policy_kwargs.get("net_arch", {"pi": [64, 64], "vf": [64, 64]})
    if isinstance(arch, Mapping):
        pi, vf = list(arch.get("pi", [])), list(arch.get("vf", []))
    else:
        pi = vf = list(arch)
    return PolicySpec(
        obs_dim,
        action_dim,
        discrete,
        pi,
        vf,
        use_sde and not discrete,
        float(policy_kwargs.get("log_std_init", 0.0)),
        bool(policy_kwargs.get("ortho_init", True)),
    )


def _init_linear(
    w: torch.Tensor, b: torch.Tensor, gain: float, ortho: bool, gen: torch.Generator
) -> None:
    """Initialize one agent's ``[in, out]`` weight as SB3 does its ``[out, in]`` Linear."""
    fan_in = w.shape[0]
    bound = 1.0 / math.sqrt(fan_in) if fan_in > 0 else 0.0
    weight = torch.empty(w.shape[1], w.shape[0])
    if ortho:
        torch.nn.init.orthogonal_(weight, gain=gain, generator=gen)
        b.zero_()
    else:  # torch's Linear default
        weight.uniform_(-bound, bound, generator=gen)
        b.uniform_(-bound, bound, generator=gen)
    w.copy_(weight.T)


class StackedAdam:
    """Adam over a population's flat parameter buffer: ``torch.optim.Adam``'s arithmetic, op for op.

    The whole population's weights are one ``[P, N]`` tensor (see
    [`StackedPolicy`][ermrl.population.StackedPolicy]), so a step is seven elementwise ops on it,
    whatever the number of layers. Adam is elementwise, so one Adam over the buffer is one Adam per
    agent. Written out rather than ``torch.optim.Adam`` because building that imports
    ``torch._dynamo`` (1.4 s per process) and its fused CPU kernel rounds a tensor's SIMD body and
    scalar tail differently. Here every row's length ``N`` is a multiple of `ROW_ALIGN` elements, so
    no agent's element ever falls in a kernel's scalar tail and an agent's update does not depend on
    the population size. Slicing agents away is `keep`.

    Args:
        params: The flat parameters ``[P, N]`` (agent axis first), updated in place.
        lr: Learning rate (set `lr` to change it).
        betas: Adam's ``(beta1, beta2)``.
        eps: SB3's PPO uses 1e-5.
    """

    def __init__(
        self,
        params: torch.Tensor,
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-5,
    ) -> None:
        self.params = params
        self.lr, self.betas, self.eps = lr, betas, eps
        self.steps = 0
        self.exp_avg = torch.zeros_like(params)
        self.exp_avg_sq = torch.zeros_like(params)

    @torch.no_grad()
    def step(self, grad: torch.Tensor) -> None:
        """One Adam step with the gradient ``grad`` (``[P, N]``, as `params`)."""
        beta1, beta2 = self.betas
        self.steps += 1
        self.exp_avg.lerp_(grad, 1 - beta1)
        self.exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        step = float(self.steps)
        step_size = self.lr / (1 - beta1**step)
        denom = (self.exp_avg_sq.sqrt() / (1 - beta2**step) ** 0.5).add_(self.eps)
        self.params.addcdiv_(self.exp_avg, denom, value=-step_size)

    def keep(self, index: torch.Tensor, params: torch.Tensor) -> StackedAdam:
        """The optimizer of the agents ``index`` (their new, sliced flat ``params``)."""
        out = StackedAdam(params, self.lr, self.betas, self.eps)
        out.steps = self.steps
        out.exp_avg = self.exp_avg[index].clone()
        out.exp_avg_sq = self.exp_avg_sq[index].clone()
        return out


@dataclass
class _Distribution:
    """The action distribution of an update's minibatch and what its gradient reads: the
    log-probabilities ``[P, B]`` of the actions, the categorical's log-probabilities of every
    action (``logp_all``), or the Gaussian's standardized actions ``z``, ``scale`` and
    ``log_scale`` (and with gSDE, the ``variance``, the squared stds ``std2`` and the squared
    latent ``latent2``)."""

    log_prob: np.ndarray
    logp_all: np.ndarray | None = None
    z: np.ndarray | None = None
    scale: np.ndarray | None = None
    log_scale: np.ndarray | None = None
    variance: np.ndarray | None = None
    std2: np.ndarray | None = None
    latent2: np.ndarray | None = None


class StackedPolicy:
    """The policies of ``P`` agents as stacked torch parameters in one flat buffer.

    All weights live in one contiguous tensor `flat` of shape ``[P, N]``, agent-major: row
    ``p`` holds agent ``p``'s weights and biases one after another (then zeros up to a multiple of
    `ROW_ALIGN`). Each entry of `params` (``pi0.w`` ``[P, in, out]``, ``pi0.b``
    ``[P, 1, out]``, ..., ``log_std``) is a view into it, so the products read the weights in place
    while per-agent gradient norms and Adam are a few ops on the whole buffer
    ([`ppo_gradient`][ermrl.population.StackedPolicy.ppo_gradient] writes the gradient in the same
    layout; `StackedAdam`).

    Args:
        spec: The network.
        init_seeds: One seed per agent for its weight initialization.
    """

    def __init__(self, spec: PolicySpec, init_seeds: Sequence[int]) -> None:
        self.spec = spec
        P = len(init_seeds)
        shapes: list[tuple[str, int, int, float]] = []
        for prefix, arch in (("pi", spec.pi), ("vf", spec.vf)):
            d = spec.obs_dim
            for i, h in enumerate(arch):
                shapes.append((f"{prefix}{i}", d, h, math.sqrt(2)))
                d = h
        shapes.append(("action", spec.latent_pi, spec.action_dim, 0.01))
        shapes.append(("value", spec.latent_vf, 1, 1.0))
        # Each parameter's shape per agent, in the order of its block in a row of the buffer.
        self.layout: dict[str, tuple[int, ...]] = {}
        for name, d_in, d_out, _ in shapes:
            self.layout[f"{name}.w"] = (d_in, d_out)
            self.layout[f"{name}.b"] = (1, d_out)
        if not spec.discrete:
            self.layout["log_std"] = (
                (spec.latent_pi, spec.action_dim) if spec.use_sde else (spec.action_dim,)
            )
        used = sum(math.prod(shape) for shape in self.layout.values())
        self.row_size = -(-used // ROW_ALIGN) * ROW_ALIGN
        self._bind(torch.zeros(P, self.row_size))
        with torch.no_grad():
            if not spec.discrete:
                self.params["log_std"].fill_(spec.log_std_init)
            for p, seed in enumerate(init_seeds):
                gen = torch.Generator().manual_seed(int(seed))
                for name, _, _, gain in shapes:
                    w, b = self.params[f"{name}.w"][p], self.params[f"{name}.b"][p, 0]
                    _init_linear(w, b, gain, spec.ortho_init, gen)

        # With a list here, ppo_gradient appends each minibatch's loss terms per agent (SB3's
        # train/* scalars, for TensorBoard); None: not computed.
        self.loss_terms: list[dict[str, np.ndarray]] | None = None

    def _bind(self, flat: torch.Tensor) -> None:
        """Make ``flat`` (``[P, row_size]``) the buffer, `params` views of it, and
        `np` numpy views of those."""
        self.flat = flat
        P, offset = flat.shape[0], 0
        self.params: dict[str, torch.nn.Parameter] = {}
        for name, shape in self.layout.items():
            size = math.prod(shape)
            view = flat[:, offset : offset + size].view(P, *shape)
            self.params[name] = torch.nn.Parameter(view)  # shares the buffer's storage
            offset += size
        # ppo_gradient's output buffer and its per-parameter views (rebuilt with the buffer).
        self._grad = np.zeros((P, self.row_size), np.float32)
        self._grads = self.grad_views(self._grad)
        self.refresh()

    @property
    def n_agents(self) -> int:
        return int(self.flat.shape[0])

    def parameters(self) -> list[torch.nn.Parameter]:
        return list(self.params.values())

    def refresh(self) -> None:
        """Numpy views of the weights (they follow every in-place update of the buffer)."""
        self.np = {k: v.detach().numpy() for k, v in self.params.items()}

    def keep(self, index: torch.Tensor) -> None:
        """Keep only the agents ``index`` (a new buffer: rebuilt views, numpy views included)."""
        self._bind(self.flat[index].clone())

    def grad_views(self, grad: np.ndarray) -> dict[str, np.ndarray]:
        """Views of a ``[P, row_size]`` gradient buffer shaped as `params`."""
        P, offset, views = grad.shape[0], 0, {}
        for name, shape in self.layout.items():
            size = math.prod(shape)
            views[name] = grad[:, offset : offset + size].reshape(P, *shape)
            offset += size
        return views

    # -- numpy forward (rollouts) --------------------------------------------------------------
    def _mlp_np(self, x: np.ndarray, prefix: str, n: int, p: Any = slice(None)) -> np.ndarray:
        for i in range(n):
            x = np.matmul(x, self.np[f"{prefix}{i}.w"][p])
            x += self.np[f"{prefix}{i}.b"][p]
            np.tanh(x, out=x)
        return x

    def forward_np(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(latent_pi, head, values)`` for observations ``[P, n, obs_dim]`` (float32);
        ``head`` is the Gaussian mean or the categorical logits."""
        s = self.spec
        latent = self._mlp_np(obs, "pi", len(s.pi))
        head = np.matmul(latent, self.np["action.w"]) + self.np["action.b"]
        latent_vf = self._mlp_np(obs, "vf", len(s.vf))
        values = (np.matmul(latent_vf, self.np["value.w"]) + self.np["value.b"])[..., 0]
        return latent, head, values

    def values_np(self, obs: np.ndarray, agents: np.ndarray) -> np.ndarray:
        """Values of single observations ``[k, obs_dim]``, row ``j`` under agent ``agents[j]``."""
        x = obs[:, None, :].astype(np.float32)
        x = self._mlp_np(x, "vf", len(self.spec.vf), agents)
        out = np.matmul(x, self.np["value.w"][agents]) + self.np["value.b"][agents]
        return out[:, 0, 0]

    # -- the PPO loss's gradient (updates) -----------------------------------------------------
    def _backward(
        self,
        inputs: list[np.ndarray],
        d_out: np.ndarray,
        prefix: str,
        head: str,
        grads: Mapping[str, np.ndarray],
    ) -> None:
        """Backpropagate ``d_out`` (``[P, B, out]``, the loss's gradient at the head's output)
        through the head and the tanh MLP ``prefix`` whose layer inputs were ``inputs`` (the
        observations, then each hidden layer's output); writes into ``grads``."""
        w = self.np
        np.matmul(inputs[-1].transpose(0, 2, 1), d_out, out=grads[f"{head}.w"])
        np.sum(d_out, axis=1, keepdims=True, out=grads[f"{head}.b"])
        if len(inputs) == 1:
            return
        d = np.matmul(d_out, w[f"{head}.w"].transpose(0, 2, 1))
        for i in range(len(inputs) - 2, -1, -1):
            h = inputs[i + 1]
            d *= 1 - h * h  # tanh'
            np.matmul(inputs[i].transpose(0, 2, 1), d, out=grads[f"{prefix}{i}.w"])
            np.sum(d, axis=1, keepdims=True, out=grads[f"{prefix}{i}.b"])
            if i:
                d = np.matmul(d, w[f"{prefix}{i}.w"].transpose(0, 2, 1))

    def ppo_gradient(
        self,
        obs: np.ndarray,
        actions: np.ndarray,
        old_values: np.ndarray,
        old_log_probs: np.ndarray,
        advantages: np.ndarray,
        returns: np.ndarray,
        *,
        clip_range: float,
        clip_range_vf: float | None,
        ent_coef: float,
        vf_coef: float,
        normalize_advantage: bool,
    ) -> np.ndarray:
        """The gradient of SB3 PPO's minibatch loss for every agent, laid out as `flat`.

        The loss is SB3's ``PPO.train``: clipped surrogate on the probability ratio (advantages
        normalized per minibatch), entropy bonus, value loss on optionally clipped values. Its
        gradient is written out (backpropagation through the tanh MLPs by stacked products),
        not taken by autograd: at these sizes torch's per-op and autograd overheads cost more
        than the products, and numpy's ``matmul`` runs one product per agent, so an agent's
        gradient does not depend on the population around it. Where ``torch.minimum`` ties
        (the ratio inside the clip range) the two halves of its gradient add up to the whole,
        as here.

        Args:
            obs: Observations ``[P, B, obs_dim]`` (float32).
            actions: ``[P, B, action_dim]`` (Gaussian) or ``[P, B]`` integers (categorical).
            old_values: ``[P, B]``, the rollout's values.
            old_log_probs: ``[P, B]``, the rollout's log-probabilities of ``actions``.
            advantages: ``[P, B]``, GAE advantages (normalized here per minibatch).
            returns: ``[P, B]``, the value targets.
            clip_range: PPO's clip range of the ratio.
            clip_range_vf: The values' clip range around ``old_values`` (``None``: unclipped).
            ent_coef: Weight of the entropy bonus.
            vf_coef: Weight of the value loss.
            normalize_advantage: Normalize the advantages per minibatch (as SB3).

        Returns:
            ``[P, row_size]`` float32: the gradient (zero in the padding); a buffer the next
            call overwrites.
        """
        B = obs.shape[1]
        pi, vf, head, values = self._forward_layers(obs)
        dist = self._distribution(head, pi[-1], actions)
        if normalize_advantage and B > 1:
            advantages = (advantages - advantages.mean(1, keepdims=True)) / (
                advantages.std(1, ddof=1, keepdims=True) + np.float32(1e-8)
            )
        ratio = np.exp(dist.log_prob - old_log_probs)
        unclipped = advantages * ratio
        clipped = advantages * np.clip(ratio, 1 - clip_range, 1 + clip_range)
        # d(-mean(min(unclipped, clipped)))/d ratio: the unclipped branch's, where it is the
        # minimum (or ties, the ratio then inside the range); 0 where the clipped one is smaller.
        d_ratio = np.where(unclipped <= clipped, advantages * np.float32(-1.0 / B), np.float32(0))
        d_logp = (d_ratio * ratio)[..., None]
        # Of the loss, per unit of entropy gradient.
        d_head, entropy = self._head_gradient(dist, actions, d_logp, np.float32(ent_coef / B))
        if self.loss_terms is not None:
            # SB3 PPO.train's logged terms, per agent over this minibatch.
            if entropy is None:  # the Gaussian's, per sample
                assert dist.log_scale is not None
                entropy = (dist.log_scale + np.float32(0.5 + LOG_SQRT_2PI)).sum(-1)
            log_ratio = dist.log_prob - old_log_probs
            self.loss_terms.append(
                {
                    "policy_gradient_loss": -np.minimum(unclipped, clipped).mean(1),
                    "entropy_loss": -entropy.mean(1),
                    "clip_fraction": (np.abs(ratio - 1) > clip_range).mean(1),
                    "approx_kl": ((ratio - 1) - log_ratio).mean(1),
                }
            )
        d_values = self._value_gradient(values, old_values, returns, clip_range_vf, vf_coef)
        grads = self._grads
        self._backward(pi, d_head.astype(np.float32, copy=False), "pi", "action", grads)
        self._backward(vf, d_values[..., None].astype(np.float32, copy=False), "vf", "value", grads)
        return self._grad

    def _forward_layers(
        self, obs: np.ndarray
    ) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray, np.ndarray]:
        """The forward pass of an update, keeping each layer's input for the backward pass:
        ``(pi, vf, head, values)``, ``pi`` and ``vf`` the observations ``[P, B, obs_dim]`` then
        each hidden layer's output, ``head`` ``[P, B, out]`` and ``values`` ``[P, B]``."""
        s, w = self.spec, self.np
        pi, vf = [obs], [obs]
        for inputs, prefix, n in ((pi, "pi", len(s.pi)), (vf, "vf", len(s.vf))):
            for i in range(n):
                x = np.matmul(inputs[-1], w[f"{prefix}{i}.w"])
                x += w[f"{prefix}{i}.b"]
                inputs.append(np.tanh(x, out=x))
        head = np.matmul(pi[-1], w["action.w"])
        head += w["action.b"]
        values = np.matmul(vf[-1], w["value.w"])[..., 0] + w["value.b"][..., 0]
        return pi, vf, head, values

    def _distribution(
        self, head: np.ndarray, latent: np.ndarray, actions: np.ndarray
    ) -> _Distribution:
        """The action distribution at ``head`` (``latent``: the policy MLP's output, for gSDE)
        and the log-probabilities of ``actions`` ``[P, B]``."""
        s, w = self.spec, self.np
        if s.discrete:
            logits = head - head.max(-1, keepdims=True)
            logp_all = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
            log_prob = np.take_along_axis(logp_all, actions[..., None].astype(np.int64), -1)[..., 0]
            return _Distribution(log_prob, logp_all=logp_all)
        variance = std2 = latent2 = None
        if s.use_sde:
            std2 = np.exp(2.0 * w["log_std"])  # [P, L, A]
            latent2 = np.square(latent)
            variance = np.matmul(latent2, std2) + np.float32(SDE_EPSILON)
            scale = np.sqrt(variance)
            log_scale = np.log(scale)
        else:
            log_scale = np.broadcast_to(w["log_std"][:, None, :], head.shape)
            scale = np.exp(log_scale)
        z = (actions - head) / scale
        log_prob = (-0.5 * np.square(z) - log_scale - np.float32(LOG_SQRT_2PI)).sum(-1)
        return _Distribution(
            log_prob, z=z, scale=scale, log_scale=log_scale, variance=variance, std2=std2,
            latent2=latent2,
        )  # fmt: skip

    def _head_gradient(
        self, dist: _Distribution, actions: np.ndarray, d_logp: np.ndarray, entropy_grad: Any
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The loss's gradient at the action head (``log_std``'s written into the gradient
        buffer), from ``d_logp`` ``[P, B, 1]`` (its gradient with respect to the
        log-probabilities) and ``entropy_grad`` (per unit of the entropy's gradient).

        Returns:
            ``(d_head, entropy)``: ``[P, B, out]``, and the categorical's entropy per sample
            ``[P, B]`` (``None`` for a Gaussian, whose entropy's gradient needs no samples).
        """
        grads = self._grads
        if self.spec.discrete:
            assert dist.logp_all is not None
            probs = np.exp(dist.logp_all)
            entropy = -(probs * dist.logp_all).sum(-1, keepdims=True)
            onehot = np.zeros_like(probs)
            np.put_along_axis(onehot, actions[..., None].astype(np.int64), 1.0, -1)
            d_head = d_logp * (onehot - probs) + entropy_grad * probs * (dist.logp_all + entropy)
            return d_head, entropy[..., 0]
        z, scale, log_scale = dist.z, dist.scale, dist.log_scale
        assert z is not None and scale is not None and log_scale is not None
        d_head = d_logp * z / scale
        # d log_prob / d log_scale = z^2 - 1; the entropy's is 1 per element.
        d_log_scale = d_logp * (np.square(z) - 1) - entropy_grad
        if self.spec.use_sde:
            assert dist.variance is not None and dist.latent2 is not None
            assert dist.std2 is not None
            d_variance = d_log_scale / (2 * dist.variance)
            d_std2 = np.matmul(dist.latent2.transpose(0, 2, 1), d_variance)
            np.multiply(d_std2, 2 * dist.std2, out=grads["log_std"])
        else:
            np.sum(d_log_scale, axis=1, out=grads["log_std"])
        return d_head, None

    def _value_gradient(
        self,
        values: np.ndarray,
        old_values: np.ndarray,
        returns: np.ndarray,
        clip_range_vf: float | None,
        vf_coef: float,
    ) -> np.ndarray:
        """The value loss's gradient at the values ``[P, B]`` (clipped around ``old_values``
        by ``clip_range_vf``, ``None``: unclipped); the loss itself goes to the logged terms."""
        B = values.shape[1]
        if clip_range_vf is not None:
            delta = values - old_values
            values = old_values + np.clip(delta, -clip_range_vf, clip_range_vf)
            inside = (delta >= -clip_range_vf) & (delta <= clip_range_vf)
            d_values = np.float32(-2.0 * vf_coef / B) * (returns - values) * inside
        else:
            d_values = np.float32(-2.0 * vf_coef / B) * (returns - values)
        if self.loss_terms is not None:
            self.loss_terms[-1]["value_loss"] = np.square(returns - values).mean(1)
        return d_values

    # -- SB3 state dicts -----------------------------------------------------------------------
    def _sb3_names(self) -> list[tuple[str, str]]:
        """``(our name, SB3's name)`` for each weight and bias."""
        out = []
        for prefix, net, arch in (
            ("pi", "policy_net", self.spec.pi),
            ("vf", "value_net", self.spec.vf),
        ):
            for i in range(len(arch)):
                out.append((f"{prefix}{i}", f"mlp_extractor.{net}.{2 * i}"))
        out += [("action", "action_net"), ("value", "value_net")]
        return out

    def sb3_state(self, p: int) -> dict[str, torch.Tensor]:
        """Agent ``p``'s weights under the names of SB3's ``ActorCriticPolicy.state_dict()``."""
        state: dict[str, torch.Tensor] = {}
        for ours, theirs in self._sb3_names():
            state[f"{theirs}.weight"] = self.params[f"{ours}.w"][p].detach().T.clone()
            state[f"{theirs}.bias"] = self.params[f"{ours}.b"][p, 0].detach().clone()
        if "log_std" in self.params:
            state["log_std"] = self.params["log_std"][p].detach().clone()
        return state

    def load_sb3_state(self, p: int, state: Mapping[str, torch.Tensor]) -> None:
        """Set agent ``p``'s weights from an SB3 ``state_dict`` of the same network."""
        with torch.no_grad():
            for ours, theirs in self._sb3_names():
                self.params[f"{ours}.w"][p].copy_(state[f"{theirs}.weight"].T)
                self.params[f"{ours}.b"][p, 0].copy_(state[f"{theirs}.bias"])
            if "log_std" in self.params:
                self.params["log_std"][p].copy_(state["log_std"])
