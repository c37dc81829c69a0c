"""The environments of a population: ``P`` agents x ``E`` environments each, stepped in lockstep.

Each agent sees exactly what the SB3 path gives one agent (see
[`ermrl.agents.train_agent`][ermrl.agents.train_agent]): ``gym.make -> ObservationMask``
environments that auto-reset like SB3's ``DummyVecEnv`` (env ``i`` of an agent first reset with
``env_seed + i``), then the agent's own reservoir (the rule of
[`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv], its weights from the same initializers and
seeds: an echo state network's or a frozen RTU layer's), then the agent's own running normalization
(SB3 ``VecNormalize``'s rule). The reservoirs of all agents advance in one batched matrix product
(NVARs: one batched gather of their delay lines); everything else is per agent data in arrays with a
leading agent axis, so an agent can be dropped by slicing
([`PopulationEnvs.keep`][ermrl.population.PopulationEnvs.keep]).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Hashable, Sequence
from typing import Any

import numpy as np
from gymnasium import spaces

from ermrl.config import EncoderConfig, NormalizeConfig, TaskConfig

__all__ = ["BatchedReservoir", "PopulationEnvs", "RunningStats", "encoder_structure"]


def encoder_structure(encoder: EncoderConfig | None) -> Hashable:
    """What the agents of one population must share: the encoder's family, its encoding
    options and the layout of what the policy sees of each reservoir
    ([`layout`][ermrl.encoders.Encoder.layout]: an ESN's units, an NVAR's delay and order). The
    hyperparameters that only change the values (spectral radius, leak rate, input scaling, an
    NVAR's strides, ...) may differ. ``None``: the raw observation."""
    from ermrl.encoders import encoder_for

    if encoder is None:
        return None
    options = tuple(
        (f.name, getattr(encoder, f.name))
        for f in dataclasses.fields(encoder)
        if f.name != "reservoirs"
    )
    layout = tuple(encoder_for(encoder).layout(p) for p in encoder.reservoirs)
    return encoder.family, options, layout


class BatchedReservoir:
    """The reservoirs of ``P`` agents (each its own weights), ``E`` state rows per agent.

    Agent ``p`` gets the bank [`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv] would build for
    ``encoders[p]`` and ``seeds[p]`` (its encoder's [`bank`][ermrl.encoders.Encoder.bank], in
    the population's layout: [`population_banks`][ermrl.encoders.Encoder.population_banks]); all
    agents must share the encoder's structure
    ([`encoder_structure`][ermrl.population.encoder_structure]); the hyperparameters may differ. The
    banks' `stack` steps every agent at
    once: for echo state networks and frozen RTU layers one stacked ``matmul`` of ``[x | u]``
    (``P x E x (N + D)``) with each agent's ``M = [W.T; Win.T]``, which numpy computes slice by
    slice, as one agent's ``ReservoirBank`` would; for NVARs one batched gather of their delay
    lines. The encodings equal ``ReservoirVecEnv``'s. Agents of other structures are refused:
    train them as separate populations
    ([`train_population_parallel`][ermrl.population.train_population_parallel] groups them).
    """

    def __init__(
        self,
        encoders: Sequence[EncoderConfig],
        seeds: Sequence[int],
        obs_dim: int,
        action_space: spaces.Space,
        n_envs: int,
    ) -> None:
        from ermrl.encoders import encoder_for
        from ermrl.encoders._vec_env import ActionEncoder

        first = encoders[0]
        structure = encoder_structure(first)
        for enc in encoders[1:]:
            if encoder_structure(enc) != structure:
                raise ValueError(
                    "the agents of a population must share the encoder's structure (family, "
                    "units or NVAR delay and order, number of reservoirs and encoding options); "
                    "train such agents in separate populations"
                )
        self.config = first
        self.action_encoder = ActionEncoder(action_space, dtype=first.dtype)
        self.obs_dim = obs_dim
        self.act_dim = self.action_encoder.dim
        self.input_dim = (
            obs_dim + (self.act_dim if first.feed_action else 0) + (1 if first.feed_reward else 0)
        )
        banks = encoder_for(first).population_banks(encoders, seeds, self.input_dim)
        self.stack = type(banks[0]).stack(banks)
        self.dtype = banks[0].dtype
        self.linear = banks[0].linear
        self.units = banks[0].units
        self.n_units = banks[0].n_units
        P, N, d_obs, d_act = len(banks), self.n_units, obs_dim, self.act_dim
        self.xu = np.zeros((P, n_envs, N + self.input_dim), self.dtype)
        # The encoded action and scaled reward are also shown by the skip connection, so they are
        # kept even when they are not fed to the reservoir (then in arrays of their own).
        self.act_in = np.zeros((P, n_envs, d_act), self.dtype)
        self.rew_in = np.zeros((P, n_envs, 1), self.dtype)
        # What the policy sees of the states (the same function for every agent).
        self._emit, n_state = banks[0].emitter(first.exposed_units)
        self.out_dim = n_state + (d_obs + d_act + 1 if first.skip_connection else 0)

    # Views of the [x | u] buffer (recomputed after keep(), which replaces the arrays).
    @property
    def states(self) -> np.ndarray:
        return self.xu[..., : self.n_units]

    def _sync_in(self) -> None:
        """Copy the action and reward inputs into the buffer where the reservoir is fed them."""
        N, d_obs = self.n_units, self.obs_dim
        if self.config.feed_action:
            self.xu[..., N + d_obs : N + d_obs + self.act_dim] = self.act_in
        if self.config.feed_reward:
            self.xu[..., -1:] = self.rew_in

    def step_all(self) -> None:
        """Advance every row one step (the inputs already written)."""
        self.stack.step(self.xu)

    def step_rows(self, p: int, rows: np.ndarray) -> None:
        """Advance rows ``rows`` of agent ``p`` one step (as ``ReservoirBank.step_buffer`` on
        the same rows of one agent)."""
        xu = self.xu[p, rows]  # a copy (fancy indexing): step it, then write it back
        self.stack.step_agent(p, xu)
        self.xu[p, rows] = xu

    def set_obs(self, obs: np.ndarray) -> None:
        self.xu[..., self.n_units : self.n_units + self.obs_dim] = obs

    def set_action_reward(self, actions: np.ndarray, rewards: np.ndarray) -> None:
        P, E = rewards.shape
        flat = self.act_in.reshape(P * E, self.act_dim)
        self.action_encoder(
            actions.reshape(P * E, -1) if actions.ndim > 2 else actions.reshape(-1), flat
        )
        self.rew_in[..., 0] = rewards
        if self.config.reward_scale != 1.0:
            self.rew_in *= self.config.reward_scale
        self._sync_in()

    def policy_obs(self, p: Any = slice(None), rows: Any = slice(None)) -> np.ndarray:
        """The policy's float32 observation (``[P, E, out_dim]``, or rows of one agent)."""
        x = self._emit(self.xu[p, rows, : self.n_units])
        if not self.config.skip_connection:
            return x
        obs = self.xu[p, rows, self.n_units : self.n_units + self.obs_dim]
        parts = [x, obs, self.act_in[p, rows], self.rew_in[p, rows]]
        return np.concatenate(parts, axis=-1).astype(np.float32)

    def reset_rows(self, p: int, rows: np.ndarray, obs: np.ndarray) -> None:
        """First step of a new episode for rows of agent ``p``: no previous action or reward."""
        self.act_in[p, rows] = 0.0
        self.rew_in[p, rows] = 0.0
        self._sync_in_rows(p, rows)
        self.xu[p, rows, self.n_units : self.n_units + self.obs_dim] = obs
        if self.config.reset == "episode":
            self.xu[p, rows, : self.n_units] = 0.0
        self.step_rows(p, rows)

    def _sync_in_rows(self, p: int, rows: np.ndarray) -> None:
        N, d_obs = self.n_units, self.obs_dim
        if self.config.feed_action:
            self.xu[p, rows, N + d_obs : N + d_obs + self.act_dim] = self.act_in[p, rows]
        if self.config.feed_reward:
            self.xu[p, rows, -1:] = self.rew_in[p, rows]

    def keep(self, idx: np.ndarray) -> None:
        self.stack.keep(idx)
        for name in ("xu", "act_in", "rew_in"):
            setattr(self, name, getattr(self, name)[idx].copy())


class RunningStats:
    """SB3's ``RunningMeanStd`` for ``P`` agents at once: statistics of shape ``[P, *shape]``."""

    def __init__(self, n_agents: int, shape: tuple[int, ...] = ()) -> None:
        self.mean = np.zeros((n_agents, *shape), np.float64)
        self.var = np.ones((n_agents, *shape), np.float64)
        self.count = np.full(n_agents, 1e-4, np.float64)

    def update(self, batch: np.ndarray) -> None:
        """Update from ``batch`` of shape ``[P, n, *shape]`` (``n`` samples per agent)."""
        batch_mean = np.mean(batch, axis=1)
        batch_var = np.var(batch, axis=1)
        batch_count = batch.shape[1]
        extra = (1,) * (self.mean.ndim - 1)
        count = self.count.reshape(-1, *extra)
        delta = batch_mean - self.mean
        total = count + batch_count
        new_mean = self.mean + delta * batch_count / total
        m_2 = (
            self.var * count
            + batch_var * batch_count
            + np.square(delta) * count * batch_count / total
        )
        self.mean = new_mean
        self.var = m_2 / total
        self.count = self.count + batch_count

    def keep(self, idx: np.ndarray) -> None:
        self.mean, self.var, self.count = self.mean[idx], self.var[idx], self.count[idx]

    def agent(self, p: int) -> dict[str, Any]:
        mean, var = self.mean[p], self.var[p]
        return {
            "mean": mean.tolist() if mean.ndim else float(mean),
            "var": var.tolist() if var.ndim else float(var),
            "count": float(self.count[p]),
        }

    def state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(mean, var, count)``, for a checkpoint (`load_state` restores them)."""
        return self.mean.copy(), self.var.copy(), self.count.copy()

    def load_state(self, state: Sequence[np.ndarray]) -> None:
        self.mean, self.var, self.count = (np.array(a, np.float64) for a in state)

    @classmethod
    def frozen(cls, stats: Sequence[dict[str, Any]]) -> RunningStats:
        out = cls(len(stats))
        out.mean = np.stack([np.asarray(s["mean"], np.float64) for s in stats])
        out.var = np.stack([np.asarray(s["var"], np.float64) for s in stats])
        out.count = np.asarray([float(s["count"]) for s in stats])
        return out


class PopulationEnvs:
    """``P x E`` environments of one task, with each agent's reservoir and normalization.

    Args:
        task: The task and its observation mask.
        n_envs: Environments per agent.
        env_seeds: Agent ``p``'s env ``i`` is first reset with ``env_seeds[p] + i``.
        encoders: Each agent's encoder (``None``: the raw masked observation for every agent).
        reservoir_seeds: Each agent's reservoir weight seed.
        normalize: Running normalization (``None``: none).
        gamma: Discount of the reward normalization (PPO's gamma).
        frozen_stats: Evaluation: each agent's final training statistics, not updated, raw
            rewards (as [`frozen_normalize_env`][ermrl.agents.frozen_normalize_env]).
    """

    def __init__(
        self,
        task: TaskConfig,
        n_envs: int,
        env_seeds: Sequence[int],
        encoders: Sequence[EncoderConfig] | None = None,
        reservoir_seeds: Sequence[int] | None = None,
        normalize: NormalizeConfig | None = None,
        gamma: float = 0.99,
        frozen_stats: Sequence[dict[str, Any]] | None = None,
    ) -> None:
        from ermrl.envs import make_env

        P, E = len(env_seeds), n_envs
        self.n_agents, self.n_envs = P, E
        self.envs = [[make_env(task.env_id, task.observe) for _ in range(E)] for _ in range(P)]
        first = self.envs[0][0]
        obs_space = first.observation_space
        if not isinstance(obs_space, spaces.Box) or len(obs_space.shape) != 1:
            raise TypeError(
                f"the population backend needs flat Box observations, got {obs_space!r}"
            )
        self.action_space = first.action_space
        if not isinstance(self.action_space, (spaces.Box, spaces.Discrete)):
            raise TypeError(
                f"the population backend supports Box and Discrete actions, got {self.action_space!r}"
            )
        self.discrete = isinstance(self.action_space, spaces.Discrete)
        self.obs_dim = int(obs_space.shape[0])
        self.env_seeds = list(env_seeds)
        self.reservoir: BatchedReservoir | None = None
        if encoders is not None:
            assert reservoir_seeds is not None
            self.reservoir = BatchedReservoir(
                encoders, reservoir_seeds, self.obs_dim, self.action_space, E
            )
        self.policy_dim = self.obs_dim if self.reservoir is None else self.reservoir.out_dim
        self.normalize = normalize
        self.gamma = gamma
        self.training = frozen_stats is None
        self.obs_rms: RunningStats | None = None
        self.ret_rms: RunningStats | None = None
        if normalize is not None:
            if frozen_stats is None:
                self.obs_rms = RunningStats(P, (self.policy_dim,)) if normalize.norm_obs else None
                self.ret_rms = RunningStats(P)
            else:
                if normalize.norm_obs:
                    self.obs_rms = RunningStats.frozen([s["obs_rms"] for s in frozen_stats])
                self.ret_rms = RunningStats.frozen([s["ret_rms"] for s in frozen_stats])
        self.returns = np.zeros((P, E))
        self.episode_reward = np.zeros((P, E))
        self.episode_length = np.zeros((P, E), np.int64)
        # Time spent in the environments and in the reservoir (the rest is the caller's).
        self.env_seconds = 0.0
        self.reservoir_seconds = 0.0

    # -- normalization (SB3 VecNormalize) ------------------------------------------------------
    def _norm_obs(self, obs: np.ndarray, p: Any = slice(None)) -> np.ndarray:
        if self.obs_rms is None:
            return obs
        assert self.normalize is not None
        mean, var = self.obs_rms.mean[p], self.obs_rms.var[p]
        if obs.ndim == 3:
            mean, var = mean[:, None, :], var[:, None, :]
        out = np.clip(
            (obs - mean) / np.sqrt(var + self.normalize.epsilon),
            -self.normalize.clip_obs,
            self.normalize.clip_obs,
        )
        return out.astype(np.float32)

    def _norm_reward(self, rewards: np.ndarray, dones: np.ndarray) -> np.ndarray:
        if self.normalize is None or not self.training:
            return rewards
        assert self.ret_rms is not None
        self.returns = self.returns * self.gamma + rewards
        self.ret_rms.update(self.returns)
        out = rewards
        if self.normalize.norm_reward:
            out = np.clip(
                rewards / np.sqrt(self.ret_rms.var[:, None] + self.normalize.epsilon),
                -self.normalize.clip_reward,
                self.normalize.clip_reward,
            )
        self.returns[dones] = 0.0
        return out

    def normalize_stats(self, p: int) -> dict[str, Any]:
        """Agent ``p``'s statistics in [`normalize_stats`][ermrl.agents.normalize_stats]'s
        format."""
        from ermrl.agents._normalize import STATS_FORMAT

        n = self.normalize
        assert n is not None and self.ret_rms is not None
        return {
            "format": STATS_FORMAT,
            "norm_obs": bool(n.norm_obs),
            "norm_reward": bool(n.norm_reward),
            "clip_obs": float(n.clip_obs),
            "clip_reward": float(n.clip_reward),
            "gamma": float(self.gamma),
            "epsilon": float(n.epsilon),
            "obs_rms": self.obs_rms.agent(p) if self.obs_rms is not None else None,
            "ret_rms": self.ret_rms.agent(p),
        }

    # -- stepping ------------------------------------------------------------------------------
    def reset(self, seed_offset: int = 0) -> np.ndarray:
        """First reset of every env, agent ``p``'s env ``i`` seeded with ``env_seeds[p] + i +
        seed_offset`` (a resumed training restarts its envs with an offset, so as not to replay
        its first episodes); returns the policy observations ``[P, E, d]``."""
        t0 = time.perf_counter()
        obs = np.stack(
            [
                np.stack([env.reset(seed=seed + i + seed_offset)[0] for i, env in enumerate(row)])
                for row, seed in zip(self.envs, self.env_seeds)
            ]
        )
        t1 = time.perf_counter()
        self.env_seconds += t1 - t0
        self.returns[:] = 0.0
        self.episode_reward[:] = 0.0
        self.episode_length[:] = 0
        if self.reservoir is not None:
            r = self.reservoir
            r.xu[:] = 0.0
            r.act_in[:] = 0.0
            r.rew_in[:] = 0.0
            r.set_obs(obs)
            r.step_all()
            policy = r.policy_obs()
            self.reservoir_seconds += time.perf_counter() - t1
        else:
            policy = obs.astype(np.float32)
        if self.obs_rms is not None and self.training:
            self.obs_rms.update(policy)
        return self._norm_obs(policy)

    def step(
        self, actions: np.ndarray
    ) -> tuple[
        np.ndarray,
        np.ndarray,
        np.ndarray,
        np.ndarray,
        dict[tuple[int, int], np.ndarray],
        list[tuple[int, int, float, int]],
    ]:
        """Step every env with ``actions`` (already clipped to the bounds).

        Returns:
            ``(obs, rewards, raw_rewards, dones, terminal, episodes)``: the policy observations
            ``[P, E, d]`` (float32, the next episode's first for finished envs), the rewards
            the learner sees (normalized when asked) and the raw ones ``[P, E]``, ``dones``
            ``[P, E]``, the policy observation of the true last state of each *truncated*
            episode keyed by ``(agent, env)`` (PPO bootstraps from it), and
            ``(agent, env, return, length)`` for each episode that ended.
        """
        obs, raw, dones, last_obs, truncated = self._step_envs(actions)
        episodes = self._end_episodes(raw, last_obs)
        # What DummyVecEnv hands on (its reward buffer is float32): the reservoir, the
        # normalization and PPO see these.
        raw32 = raw.astype(np.float32)
        if self.reservoir is not None:
            policy, terminal = self._encode(obs, actions, raw32, last_obs, truncated)
        else:
            policy = obs.astype(np.float32)
            terminal = {key: np.asarray(o, np.float32) for key, o in truncated.items()}
        if self.obs_rms is not None and self.training:
            self.obs_rms.update(policy)
        policy = self._norm_obs(policy)
        for (p, i), o in terminal.items():
            terminal[(p, i)] = self._norm_obs(o, p)
        rewards = self._norm_reward(raw32, dones)
        return policy, rewards, raw, dones, terminal, episodes

    def _step_envs(
        self, actions: np.ndarray
    ) -> tuple[
        np.ndarray,
        np.ndarray,
        np.ndarray,
        dict[tuple[int, int], np.ndarray],
        dict[tuple[int, int], np.ndarray],
    ]:
        """Step each env once, resetting those whose episode ended (as ``DummyVecEnv``).

        Returns:
            ``(obs, raw, dones, last_obs, truncated)``: the observations ``[P, E, obs_dim]``
            (the next episode's first for finished envs), the rewards and ``dones``
            ``[P, E]``, and the true last observation of each finished and each truncated
            episode, keyed by ``(agent, env)``.
        """
        P, E = self.n_agents, self.n_envs
        t0 = time.perf_counter()
        obs = np.empty((P, E, self.obs_dim), np.float64)
        raw = np.empty((P, E))
        dones = np.zeros((P, E), bool)
        truncated: dict[tuple[int, int], np.ndarray] = {}
        last_obs: dict[tuple[int, int], np.ndarray] = {}
        discrete = self.discrete
        for p, row in enumerate(self.envs):
            act_p = actions[p]
            for i, env in enumerate(row):
                a = int(act_p[i]) if discrete else act_p[i]
                o, reward, term, trunc, _ = env.step(a)
                raw[p, i] = reward
                if term or trunc:
                    dones[p, i] = True
                    last_obs[(p, i)] = o
                    if trunc and not term:
                        truncated[(p, i)] = o
                    o, _ = env.reset()
                obs[p, i] = o
        self.env_seconds += time.perf_counter() - t0
        return obs, raw, dones, last_obs, truncated

    def _end_episodes(
        self, raw: np.ndarray, last_obs: dict[tuple[int, int], np.ndarray]
    ) -> list[tuple[int, int, float, int]]:
        """Add this step's raw rewards ``[P, E]`` to the episodes' sums (as ``Monitor``: the
        rewards as the envs returned them), and close the episodes that ended (the keys of
        ``last_obs``): ``(agent, env, return, length)`` each."""
        self.episode_reward += raw
        self.episode_length += 1
        episodes: list[tuple[int, int, float, int]] = []
        for p, i in last_obs:
            episodes.append(
                (p, i, float(self.episode_reward[p, i]), int(self.episode_length[p, i]))
            )
            self.episode_reward[p, i] = 0.0
            self.episode_length[p, i] = 0
        return episodes

    def _encode(
        self,
        obs: np.ndarray,
        actions: np.ndarray,
        raw32: np.ndarray,
        last_obs: dict[tuple[int, int], np.ndarray],
        truncated: dict[tuple[int, int], np.ndarray],
    ) -> tuple[np.ndarray, dict[tuple[int, int], np.ndarray]]:
        """Step the reservoirs with the observations, actions and float32 rewards of this
        step; the rows of finished episodes see their true last observation first, then
        restart from the next episode's first.

        Returns:
            ``(policy, terminal)``: the policy observations ``[P, E, d]`` and the encoded last
            state of each truncated episode, keyed by ``(agent, env)``.
        """
        t0 = time.perf_counter()
        res = self.reservoir
        assert res is not None
        terminal: dict[tuple[int, int], np.ndarray] = {}
        res.set_action_reward(actions, raw32)
        if not last_obs:
            res.set_obs(obs)
            res.step_all()
        else:
            # Terminal step: the finished rows see the true last observation first.
            feed = obs.copy()
            for (p, i), o in last_obs.items():
                feed[p, i] = o
            res.set_obs(feed)
            res.step_all()
            by_agent: dict[int, list[int]] = {}
            for p, i in last_obs:
                by_agent.setdefault(p, []).append(i)
            for p, rows in by_agent.items():
                enc = res.policy_obs(p, np.asarray(rows))
                for j, i in enumerate(rows):
                    if (p, i) in truncated:
                        terminal[(p, i)] = enc[j]
                res.reset_rows(p, np.asarray(rows), obs[p, rows])
        policy = res.policy_obs()
        self.reservoir_seconds += time.perf_counter() - t0
        return policy, terminal

    def keep(self, idx: np.ndarray) -> None:
        """Keep only the agents ``idx`` (the others' envs are closed)."""
        kept = set(int(i) for i in idx)
        for p, row in enumerate(self.envs):
            if p not in kept:
                for env in row:
                    env.close()
        self.envs = [self.envs[int(i)] for i in idx]
        self.env_seeds = [self.env_seeds[int(i)] for i in idx]
        self.n_agents = len(self.envs)
        if self.reservoir is not None:
            self.reservoir.keep(idx)
        for rms in (self.obs_rms, self.ret_rms):
            if rms is not None:
                rms.keep(idx)
        self.returns = self.returns[idx]
        self.episode_reward = self.episode_reward[idx]
        self.episode_length = self.episode_length[idx]

    def close(self) -> None:
        for row in self.envs:
            for env in row:
                env.close()
