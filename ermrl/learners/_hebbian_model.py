"""The ``hebbian`` learner's agent: a leaky-integrator network and its Hebbian readout (numpy).

See `ermrl.learners._hebbian` for the rule and the settings. Shapes: ``E`` envs, ``N``
units, ``D`` observation entries, ``A`` action entries. One step of a batch of envs is one
matrix product for the recurrence (``[h, o] @ [J, J_in]^T``) and one for the readout
(``h @ J_out^T``).
"""

from __future__ import annotations

import io
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ermrl.config import ConfigError
from ermrl.learners._callbacks import as_callback

__all__ = ["HebbianAgent", "HebbianPolicy", "leak_factors", "load_npz", "recurrent_weights"]

# Arrays of the policy (what ``policy.pt`` holds); the learning state is saved by ``save`` only.
POLICY_ARRAYS = ("J", "J_in", "b", "alpha", "J_out", "critic_w", "critic_b")


def leak_factors(units: int, tau_min: float, tau_max: float, dt: float) -> np.ndarray:
    """Per-unit leak factors ``alpha = exp(-dt / tau)``, ``tau`` log-uniform over
    ``[tau_min, tau_max]`` (``np.geomspace``: unit ``i`` has the ``i``-th of ``units``
    log-evenly spaced time constants).

    Returns:
        ``alpha``, shape ``(units,)``, float64.
    """
    tau = np.geomspace(tau_min, tau_max, units)
    return np.exp(-dt / tau)


def recurrent_weights(units: int, spectral_radius: float, seed: Any) -> np.ndarray:
    """``J``: Gaussian (reservoirpy's ``mat_gen.normal``), zero diagonal, spectral radius rho.

    Returns:
        Shape ``(units, units)``, float64.
    """
    from reservoirpy import mat_gen

    J = np.array(mat_gen.normal(units, units, connectivity=1.0, seed=seed), dtype=np.float64)
    np.fill_diagonal(J, 0.0)
    radius = float(np.max(np.abs(np.linalg.eigvals(J)))) if units > 1 else 0.0
    return J * (spectral_radius / radius) if radius > 0 else J


@dataclass(frozen=True)
class _Rule:
    """The learning rule's constants for one `HebbianAgent.learn` (read from its settings).

    With a critic, the rule is actor-critic with eligibility traces (Sutton and Barto 2018,
    13.6): the actor's trace decays by ``gamma * lambda`` and each step's TD error modulates it,
    so ``G = sum_k psi_k h_k^T sum_{t>=k} (gamma lambda)^(t-k) delta_t`` (GAE(lambda) per step
    ``k``).

    Attributes:
        sigma: The exploration noise (Box actions).
        actor_decay: The eligibility's decay per step: ``gamma * trace_decay`` with a critic,
            else ``trace_decay``.
        baseline: ``"none"``, ``"mean"``, ``"critic"`` or ``"td"``.
        baseline_decay: The running mean's decay (``baseline="mean"``).
        gamma: The discount of the TD error (with a critic).
        critic_lr: The critic's learning rate.
        critic_lambda: The critic's trace decay (TD(lambda)).
        update_every: Batch steps between updates of ``J_out`` (0: when an episode ends).
    """

    sigma: float
    actor_decay: float
    baseline: str
    baseline_decay: float
    gamma: float
    critic_lr: float
    critic_lambda: float
    update_every: int

    @property
    def use_critic(self) -> bool:
        """Whether a critic's TD error modulates the traces (``critic`` and ``td``)."""
        return self.baseline in ("critic", "td")

    @classmethod
    def from_settings(cls, s: Mapping[str, Any]) -> _Rule:
        """The constants of the learner's settings (`HebbianAgent`'s ``settings``)."""
        baseline, gamma, trace_decay = (
            str(s["baseline"]),
            float(s["gamma"]),
            float(s["trace_decay"]),
        )
        return cls(
            sigma=float(s["sigma"]),
            actor_decay=gamma * trace_decay if baseline in ("critic", "td") else trace_decay,
            baseline=baseline,
            baseline_decay=float(s["baseline_decay"]),
            gamma=gamma,
            critic_lr=float(s["critic_lr"]),
            critic_lambda=float(s["critic_lambda"]),
            update_every=int(s["update_every"]),
        )

    def update_due(self, since_update: int, dones: np.ndarray) -> bool:
        """Whether ``J_out`` learns now: every ``update_every`` batch steps, or (0) when any of
        the ``(E,)`` ``dones`` ends an episode."""
        every = self.update_every
        return bool((every > 0 and since_update >= every) or (every == 0 and dones.any()))


class HebbianPolicy:
    """The network's weights and its forward step (numpy), with a torch-like state dict.

    Attributes:
        J: Recurrent weights ``(N, N)``.
        J_in: Input weights ``(N, D)``.
        b: Bias ``(N,)``.
        alpha: Leak factors ``(N,)``.
        J_out: Readout ``(A, N)`` (the plastic weights).
        critic_w: Linear critic's weights ``(N,)``; ``critic_b``: its bias ``(1,)``.
    """

    J: np.ndarray
    J_in: np.ndarray
    b: np.ndarray
    alpha: np.ndarray
    J_out: np.ndarray
    critic_w: np.ndarray
    critic_b: np.ndarray

    def __init__(self, arrays: Mapping[str, np.ndarray], dtype: np.dtype) -> None:
        self.dtype = dtype
        self.training = True
        self._set(arrays)

    def _set(self, arrays: Mapping[str, np.ndarray]) -> None:
        for name in POLICY_ARRAYS:
            setattr(self, name, np.array(arrays[name], dtype=self.dtype))
        self.W = np.concatenate([self.J, self.J_in], axis=1).T.copy()  # (N + D, N)

    def recur(self, h: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """``alpha h + (1 - alpha) tanh(J h + J_in o + b)`` for a batch ``h (E, N)``, ``obs (E, D)``."""
        pre = np.concatenate([h, obs], axis=1) @ self.W
        pre += self.b
        return self.alpha * h + (1.0 - self.alpha) * np.tanh(pre)

    def mean(self, h: np.ndarray) -> np.ndarray:
        """``mu = tanh(J_out h)``, shape ``(E, A)``."""
        return np.tanh(h @ self.J_out.T)

    def probabilities(self, h: np.ndarray) -> np.ndarray:
        """``p = softmax(J_out h)`` (discrete actions), shape ``(E, A)``."""
        logits = h @ self.J_out.T
        logits -= logits.max(axis=1, keepdims=True)
        p = np.exp(logits)
        p /= p.sum(axis=1, keepdims=True)
        return p

    def value(self, h: np.ndarray) -> np.ndarray:
        """The critic ``V(h) = critic_w . h + critic_b``, shape ``(E,)``."""
        return h @ self.critic_w + self.critic_b[0]

    def state_dict(self) -> dict[str, Any]:
        """The weights as CPU torch tensors (what ``policy.pt`` stores)."""
        import torch

        return {name: torch.from_numpy(np.array(getattr(self, name))) for name in POLICY_ARRAYS}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Take weights from `state_dict`'s output.

        Raises:
            RuntimeError: missing or unexpected names, or a shape that differs.
        """
        if set(state) != set(POLICY_ARRAYS):
            raise RuntimeError(
                f"Error(s) in loading state_dict for HebbianPolicy: expected {sorted(POLICY_ARRAYS)}, "
                f"got {sorted(state)}"
            )
        arrays = {name: np.asarray(state[name].detach().cpu().numpy()) for name in POLICY_ARRAYS}
        for name in POLICY_ARRAYS:
            if arrays[name].shape != getattr(self, name).shape:
                raise RuntimeError(
                    f"Error(s) in loading state_dict for HebbianPolicy: size mismatch for {name}: "
                    f"{arrays[name].shape} in the file, {getattr(self, name).shape} here"
                )
        self._set(arrays)

    def set_training_mode(self, mode: bool) -> None:
        """Recorded only: the forward step is the same in both modes."""
        self.training = bool(mode)


class HebbianAgent:
    """A leaky-integrator network with a reward-modulated Hebbian readout, on a VecEnv.

    Not an SB3 algorithm: it offers what ermrl uses of one (``learn`` with SB3 callbacks,
    ``predict``, ``num_timesteps``, ``save``, ``policy``, ``get_env``).

    Args:
        env: A VecEnv with a 1-D Box observation space and a Box or Discrete action space.
            Box: policy means ``mu`` lie in ``[-1, 1]``; the action ``mu + sigma xi`` is clipped
            to ``[-1, 1]`` and mapped linearly onto the action bounds (the identity when they
            are ``[-1, 1]``). Discrete (``A`` actions): a softmax policy
            ``p = softmax(J_out h)``, ``a ~ p``, whose eligibility is
            ``e = lambda e + (onehot(a) - p) h^T`` (the score of the softmax; ``sigma`` is not
            used); the deterministic action is ``argmax p``.
        settings: [`settings`][ermrl.learners.Learner.settings].
        seed: Seeds the weights (reservoirpy's initializers) and the exploration noise.

    Raises:
        ConfigError: the action space is neither a Box nor a Discrete one, or the observation
            space is not a 1-D Box.
    """

    def __init__(self, env: Any, settings: Mapping[str, Any], seed: int | None = None) -> None:
        from gymnasium import spaces
        from stable_baselines3.common.logger import Logger

        if not isinstance(env.action_space, (spaces.Box, spaces.Discrete)):
            raise ConfigError(
                f"learner 'hebbian' needs a Box or Discrete action space, got {env.action_space}"
            )
        if (
            not isinstance(env.observation_space, spaces.Box)
            or len(env.observation_space.shape) != 1
        ):
            raise ConfigError(
                f"learner 'hebbian' needs a flat Box observation space, got {env.observation_space}"
            )
        self.env = env
        self.settings = dict(settings)
        self.seed = seed
        self.n_envs = int(env.num_envs)
        self.num_timesteps = 0
        self.logger = Logger(folder=None, output_formats=[])
        self.observation_space = env.observation_space
        self.action_space = env.action_space
        self.dtype = np.dtype(self.settings["dtype"])
        self.obs_dim = int(env.observation_space.shape[0])
        space = env.action_space
        self.discrete = isinstance(space, spaces.Discrete)
        if isinstance(space, spaces.Discrete):
            self.act_dim = int(space.n)
            self._start = int(space.start)
        else:
            self.act_dim = int(np.prod(space.shape))
            low = np.asarray(space.low, dtype=np.float64).ravel()
            high = np.asarray(space.high, dtype=np.float64).ravel()
            self._unit_box = bool(np.all(low == -1.0) and np.all(high == 1.0))
            self._low, self._high = low, high
            self._shape: tuple[int, ...] = tuple(space.shape)

        weights_seq, noise_seq = np.random.SeedSequence(seed).spawn(2)
        j_seq, in_seq, b_seq, out_seq = (np.random.default_rng(s) for s in weights_seq.spawn(4))
        from reservoirpy import mat_gen

        s = self.settings
        n = int(s["units"])
        arrays = {
            "J": recurrent_weights(n, float(s["spectral_radius"]), j_seq),
            "J_in": np.array(
                mat_gen.normal(n, self.obs_dim, scale=float(s["input_scaling"]), seed=in_seq)
            ),
            "b": np.array(mat_gen.normal(n, 1, scale=float(s["bias_scaling"]), seed=b_seq)).ravel(),
            "alpha": leak_factors(n, float(s["tau_min"]), float(s["tau_max"]), float(s["dt"])),
            "J_out": np.array(
                mat_gen.normal(self.act_dim, n, scale=float(s["readout_scaling"]), seed=out_seq)
            ),
            "critic_w": np.zeros(n),
            "critic_b": np.zeros(1),
        }
        self.policy = HebbianPolicy(arrays, self.dtype)
        self.rng = np.random.default_rng(noise_seq)
        # Learning state: Adam's moments and step, the accumulator G, the running-mean baseline.
        self.adam_m = np.zeros_like(self.policy.J_out)
        self.adam_v = np.zeros_like(self.policy.J_out)
        self.adam_t = 0
        self.G = np.zeros_like(self.policy.J_out)
        self.baseline_sum = 0.0  # exponentially weighted sum, bias-corrected by baseline_weight
        self.baseline_weight = 0.0

    # -- SB3-like interface -------------------------------------------------------------------

    def get_env(self) -> Any:
        return self.env

    def _env_action(self, action: np.ndarray) -> np.ndarray:
        """Box: clip to ``[-1, 1]`` and map onto the action bounds; shape
        ``(E, *action_shape)``. Discrete: the indices ``(E,)`` shifted by the space's start."""
        if self.discrete:
            return np.asarray(action, dtype=np.int64) + self._start
        clipped = np.clip(action, -1.0, 1.0)
        if not self._unit_box:
            clipped = self._low + (clipped + 1.0) * 0.5 * (self._high - self._low)
        out = clipped.reshape((-1, *self._shape))
        return out.astype(self.action_space.dtype, copy=False)

    def predict(
        self,
        observation: np.ndarray,
        state: np.ndarray | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Actions for a batch of observations, carrying the hidden state.

        Args:
            observation: ``(E, D)`` (or ``(D,)`` for one env).
            state: ``h`` from the previous call, ``(E, N)``; ``None``: zeros.
            episode_start: ``(E,)`` booleans; a true entry resets that env's ``h`` to zero.
            deterministic: The mean action ``mu`` (else ``mu + sigma xi``).

        Returns:
            The env actions ``(E, *action_shape)`` (``(*action_shape,)`` for a single
            observation) and the new state ``h``.
        """
        obs = np.asarray(observation, dtype=self.dtype)
        single = obs.ndim == 1
        obs = obs.reshape(-1, self.obs_dim)
        n = self.policy.J.shape[0]
        if state is None:
            h = np.zeros((obs.shape[0], n), dtype=self.dtype)
        else:
            h = np.array(state, dtype=self.dtype).reshape(obs.shape[0], n)
        if episode_start is not None:
            h[np.asarray(episode_start, dtype=bool).reshape(-1)] = 0.0
        h = self.policy.recur(h, obs)
        if self.discrete:
            p = self.policy.probabilities(h)
            action = p.argmax(axis=1) if deterministic else self._sample(p)
        else:
            mu = self.policy.mean(h)
            noise = self.settings["sigma"] * self.rng.standard_normal(mu.shape)
            action = mu if deterministic else mu + noise
        env_action = self._env_action(action)
        return (env_action[0] if single else env_action), h

    def _sample(self, p: np.ndarray) -> np.ndarray:
        """One index per row of the probabilities ``p (E, A)`` (inverse CDF)."""
        u = self.rng.random((p.shape[0], 1))
        return np.minimum((np.cumsum(p, axis=1) < u).sum(axis=1), p.shape[1] - 1)

    def save(self, path: Any) -> None:
        """Write the agent as a plain ``.npz``: its arrays, learning state and a JSON config.

        Args:
            path: A file name or a binary file handle. ``np.load(..., allow_pickle=False)``
                reads it back.
        """
        arrays = {name: getattr(self.policy, name) for name in POLICY_ARRAYS}
        arrays.update(adam_m=self.adam_m, adam_v=self.adam_v, G=self.G)
        config = {
            "learner": "hebbian",
            "settings": self.settings,
            "seed": self.seed,
            "num_timesteps": self.num_timesteps,
            "adam_t": self.adam_t,
            "baseline_sum": self.baseline_sum,
            "baseline_weight": self.baseline_weight,
        }
        np.savez(path, config=np.array(json.dumps(config)), **arrays)

    def set_random_seed(self, seed: int | None = None) -> None:
        """Reseed the exploration noise."""
        self.rng = np.random.default_rng(seed)

    # -- learning -----------------------------------------------------------------------------

    def _apply_update(self) -> None:
        """``J_out += Adam(G / E - l2 J_out)`` (gradient ascent), then ``G = 0``."""
        s = self.settings
        beta1, beta2 = (float(b) for b in s["adam_betas"])
        grad = self.G / self.n_envs - float(s["l2"]) * self.policy.J_out
        self.adam_t += 1
        self.adam_m *= beta1
        self.adam_m += (1.0 - beta1) * grad
        self.adam_v *= beta2
        self.adam_v += (1.0 - beta2) * grad * grad
        m_hat = self.adam_m / (1.0 - beta1**self.adam_t)
        v_hat = self.adam_v / (1.0 - beta2**self.adam_t)
        self.policy.J_out += (
            float(s["learning_rate"]) * m_hat / (np.sqrt(v_hat) + float(s["adam_eps"]))
        )
        self.G[...] = 0.0
        if not np.all(np.isfinite(self.policy.J_out)):
            raise ValueError("hebbian: the readout J_out became non-finite (nan or inf)")

    def _reward(self, rewards: np.ndarray, infos: list[dict[str, Any]]) -> np.ndarray:
        if self.settings["reward"] == "task":
            return np.asarray(rewards, dtype=np.float64)
        try:
            return np.array([float(info["x_velocity"]) for info in infos])
        except KeyError:
            raise ConfigError(
                "hebbian reward x_velocity needs an env whose info has 'x_velocity' "
                "(MuJoCo locomotion tasks such as Ant-v5)"
            ) from None

    def _explore(self, h: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Draw this step's actions and their eligibility factor ``psi`` (one draw of ``rng``).

        Args:
            h: The hidden state ``(E, N)``.
            sigma: The exploration noise (Box actions).

        Returns:
            ``mu`` (Box: the means ``tanh(J_out h)``; Discrete: the probabilities), each
            ``(E, A)``; the actions (Box: ``mu + sigma xi``, ``(E, A)``; Discrete: indices
            ``(E,)``); ``psi`` ``(E, A)``, the factor of the eligibility ``e = lambda e + psi
            h^T``: ``(a - mu)(1 - mu^2) / sigma^2`` (Box) or ``onehot(a) - p`` (Discrete).
        """
        n_envs = self.n_envs
        if self.discrete:
            # softmax policy: e = lambda e + (onehot(a) - p) h^T, per env
            mu = self.policy.probabilities(h)
            actions = self._sample(mu)
            psi = -mu
            psi[np.arange(n_envs), actions] += 1.0
        else:
            mu = self.policy.mean(h)
            actions = mu + sigma * self.rng.standard_normal(mu.shape)
            # e = lambda e + ((a - mu)(1 - mu^2) / sigma^2) h^T, per env
            psi = (actions - mu) * (1.0 - mu * mu) / (sigma * sigma)
        return mu, actions, psi

    def _td_error(
        self,
        rule: _Rule,
        h: np.ndarray,
        h_next: np.ndarray,
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
        critic_trace: np.ndarray,
        critic_bias_trace: np.ndarray,
    ) -> np.ndarray:
        """The TD errors ``delta = r + gamma V(h') - V(h)``; the critic then takes a TD(lambda) step.

        ``V(h') = 0`` after a termination; after a truncation, ``h'`` is the state reached on the
        env's terminal observation. The critic ``V(h) = w.h + c`` learns with accumulating
        traces, updated in place and reset where an episode ended.

        Args:
            rule: The learning rule's constants.
            h: The state the actions were taken in, ``(E, N)``.
            h_next: The next state ``(E, N)`` (reset where ``dones``).
            reward: The rewards ``(E,)``.
            dones: ``(E,)`` booleans.
            infos: The envs' infos (``terminal_observation``, ``TimeLimit.truncated``).
            critic_trace: The trace of ``w``, ``(E, N)``.
            critic_bias_trace: The trace of ``c``, ``(E,)``.

        Returns:
            ``delta``, shape ``(E,)``: the modulator with a critic (``critic`` and ``td``
            alike; ``r_t - V(h_t)`` was biased for ``t > k``).
        """
        policy, dtype, gamma = self.policy, self.dtype, rule.gamma
        value = policy.value(h)
        value_next = policy.value(h_next)
        for i in np.flatnonzero(dones):
            terminal = infos[i].get("terminal_observation")
            truncated = bool(infos[i].get("TimeLimit.truncated", False))
            if truncated and terminal is not None:
                last = policy.recur(h[i : i + 1], np.asarray(terminal, dtype=dtype)[None])
                value_next[i] = policy.value(last)[0]
            else:
                value_next[i] = 0.0
        delta = reward + gamma * value_next - value
        # TD(lambda) with accumulating traces on V(h) = w.h + c
        critic_trace *= gamma * rule.critic_lambda
        critic_trace += h
        critic_bias_trace *= gamma * rule.critic_lambda
        critic_bias_trace += 1.0
        policy.critic_w += rule.critic_lr * (delta @ critic_trace) / self.n_envs
        policy.critic_b += rule.critic_lr * float(delta @ critic_bias_trace) / self.n_envs
        critic_trace[dones] = 0.0
        critic_bias_trace[dones] = 0.0
        return delta

    def _minus_running_mean(self, reward: np.ndarray, decay: float) -> np.ndarray:
        """``r - b`` with ``b`` the running mean of the rewards so far, then ``b`` takes ``r``.

        Args:
            reward: The rewards ``(E,)``, folded into the mean env by env.
            decay: The exponential mean's decay.

        Returns:
            The modulator ``(E,)``.
        """
        current = self.baseline_sum / self.baseline_weight if self.baseline_weight else 0.0
        modulator = reward - current
        for r in reward:
            self.baseline_sum = decay * self.baseline_sum + (1.0 - decay) * float(r)
            self.baseline_weight = decay * self.baseline_weight + (1.0 - decay)
        return modulator

    def learn(
        self,
        total_timesteps: int,
        callback: Any = None,
        progress_bar: bool = False,
        reset_num_timesteps: bool = True,
        **_: Any,
    ) -> HebbianAgent:
        """Learn online for ``total_timesteps`` env steps (counted over all envs, as SB3 does).

        Args:
            total_timesteps: Env steps to take.
            callback: An SB3 ``BaseCallback`` (or a list of them, or ``None``); its ``on_step``
                runs after every batch step with ``locals`` holding ``dones``, ``infos``,
                ``rewards``, ``actions``; returning ``False`` stops training.
            progress_bar: Ignored (no progress bar).
            reset_num_timesteps: Start counting from zero.

        Returns:
            ``self``.

        Raises:
            ValueError: the network's state or weights became non-finite (the message says
                "nan").
        """
        callback = as_callback(callback)
        if reset_num_timesteps:
            self.num_timesteps = 0
        total_timesteps = int(total_timesteps) + (0 if reset_num_timesteps else self.num_timesteps)
        rule = _Rule.from_settings(self.settings)
        policy, n_envs, dtype = self.policy, self.n_envs, self.dtype
        n = policy.J.shape[0]
        eligibility = np.zeros((n_envs, self.act_dim, n), dtype=dtype)
        critic_trace = np.zeros((n_envs, n), dtype=dtype)
        critic_bias_trace = np.zeros(n_envs)
        since_update = 0

        obs = np.asarray(self.env.reset(), dtype=dtype)
        h = policy.recur(np.zeros((n_envs, n), dtype=dtype), obs)
        if callback is not None:
            callback.init_callback(self)
            callback.on_training_start(locals(), globals())
        while self.num_timesteps < total_timesteps:
            mu, actions, psi = self._explore(h, rule.sigma)
            eligibility *= rule.actor_decay
            eligibility += psi[:, :, None] * h[:, None, :]
            new_obs, rewards, dones, infos = self.env.step(self._env_action(actions))
            new_obs = np.asarray(new_obs, dtype=dtype)
            reward = self._reward(rewards, infos)
            dones = np.asarray(dones, dtype=bool)
            h_start = h.copy()
            h_start[dones] = 0.0
            h_next = policy.recur(h_start, new_obs)
            if not np.all(np.isfinite(h_next)):
                raise ValueError("hebbian: the network state became non-finite (nan or inf)")
            if rule.use_critic:
                modulator = self._td_error(
                    rule, h, h_next, reward, dones, infos, critic_trace, critic_bias_trace
                )
            elif rule.baseline == "mean":
                modulator = self._minus_running_mean(reward, rule.baseline_decay)
            else:
                modulator = reward
            # G += (r - b) e (with a critic, delta e), summed over envs (the update divides by E)
            self.G += np.tensordot(modulator.astype(dtype), eligibility, axes=1)
            eligibility[dones] = 0.0
            self.num_timesteps += n_envs
            since_update += 1
            if rule.update_due(since_update, dones):
                self._apply_update()
                since_update = 0
            obs, h = new_obs, h_next
            if callback is not None:
                callback.update_locals(locals())
                if not callback.on_step():
                    break
        if callback is not None:
            callback.on_training_end()
        return self


def load_npz(data: bytes | Any) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read a saved agent (``save``'s ``.npz``) without pickles.

    Args:
        data: The file's bytes, a path or a binary handle.

    Returns:
        The JSON config and the arrays.
    """
    source = io.BytesIO(data) if isinstance(data, bytes) else data
    with np.load(source, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    config = json.loads(str(arrays.pop("config")))
    return config, arrays
