"""A Stable-Baselines3 ``VecEnv`` wrapper that shows the policy reservoir states.

Each environment of the wrapped ``VecEnv`` owns one state row. At every step the reservoir input
is ``u = [observation, previous action, previous reward * reward_scale]``:

- a ``Discrete`` action is one-hot, a ``MultiDiscrete`` action is a concatenation of one-hots, a
  bounded ``Box`` action is scaled to [-1, 1];
- at the start of an episode the previous action and reward are zero.

When an episode ends, the row first takes one step on the terminal observation; that encoded
terminal state replaces ``infos[i]["terminal_observation"]`` (PPO bootstraps truncated episodes
from it). Then, with ``reset="episode"``, the row is zeroed and takes one step on the first
observation of the next episode.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from numpy.typing import DTypeLike
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

from ermrl.encoders._reservoir import ReservoirWeights, StepBank, reservoir_seeds
from ermrl.encoders._settings import EncoderConfig

__all__ = ["ActionEncoder", "ReservoirVecEnv"]


class ActionEncoder:
    """Turns a batch of actions into reservoir inputs.

    A ``Discrete`` action becomes one-hot, ``MultiDiscrete`` a concatenation of one-hots,
    ``MultiBinary`` stays 0/1, and a ``Box`` action is scaled to [-1, 1] (unbounded dimensions
    pass through unscaled).

    Args:
        space: The action space of one environment.
        dtype: Float type of the output (that of the reservoir buffer), so that the hot path
            does no type conversion.
    """

    def __init__(self, space: spaces.Space, dtype: DTypeLike = np.float64) -> None:
        self.space = space
        dtype = np.dtype(dtype)
        self.low, self.high = 0.0, 1.0
        if isinstance(space, spaces.Discrete):
            self.dim = int(space.n)
            self._eye = np.eye(self.dim)
            self._start = int(space.start)
            self._encode = self._discrete
        elif isinstance(space, spaces.MultiDiscrete):
            self._nvec = np.asarray(space.nvec).ravel()
            self._offsets = np.concatenate([[0], np.cumsum(self._nvec)[:-1]])
            self.dim = int(self._nvec.sum())
            self._encode = self._multi_discrete
        elif isinstance(space, spaces.MultiBinary):
            self.dim = int(np.prod(space.shape))
            self._encode = self._multi_binary
        elif isinstance(space, spaces.Box):
            self.dim = int(np.prod(space.shape))
            low = np.asarray(space.low, np.float64).ravel()
            high = np.asarray(space.high, np.float64).ravel()
            bounded = np.isfinite(low) & np.isfinite(high)
            self._center = np.where(bounded, (high + low) / 2, 0.0).astype(dtype)
            self._inv_half = (1.0 / np.where(bounded, (high - low) / 2, 1.0)).astype(dtype)
            self._upper = np.where(bounded, 1.0, np.inf).astype(dtype)
            self._lower = -self._upper
            self.low, self.high = -1.0, 1.0
            unit_box = bool(bounded.all() and np.all(low == -1.0) and np.all(high == 1.0))
            self._encode = self._unit_box if unit_box else self._box
        else:
            raise TypeError(f"unsupported action space {space!r}")

    def __call__(self, actions: np.ndarray, out: np.ndarray) -> None:
        """Write encoded ``actions`` (a batch) into ``out`` of shape ``(n, dim)``."""
        self._encode(actions, out)

    def _discrete(self, actions: np.ndarray, out: np.ndarray) -> None:
        out[:] = self._eye[np.asarray(actions, dtype=np.int64).ravel() - self._start]

    def _multi_discrete(self, actions: np.ndarray, out: np.ndarray) -> None:
        out[:] = 0.0
        idx = np.asarray(actions, dtype=np.int64).reshape(len(out), -1) + self._offsets
        np.put_along_axis(out, idx, 1.0, axis=1)

    def _multi_binary(self, actions: np.ndarray, out: np.ndarray) -> None:
        out[:] = np.asarray(actions).reshape(len(out), -1)

    def _unit_box(self, actions: np.ndarray, out: np.ndarray) -> None:
        # Bounds already [-1, 1] (all MuJoCo locomotion tasks): scaling is the identity.
        # (The ndarray method: np.reshape costs ~1.5 us more per call, on every env step.)
        np.minimum(np.asarray(actions).reshape(out.shape), 1.0, out=out, casting="unsafe")
        np.maximum(out, -1.0, out=out)

    def _box(self, actions: np.ndarray, out: np.ndarray) -> None:
        # PPO already clips actions to the bounds; clipping again guards other callers.
        # (np.minimum/np.maximum: np.clip costs several times more at this size.)
        np.subtract(np.asarray(actions).reshape(out.shape), self._center, out=out, casting="unsafe")
        out *= self._inv_half
        np.minimum(out, self._upper, out=out, casting="unsafe")
        np.maximum(out, self._lower, out=out, casting="unsafe")


class ReservoirVecEnv(VecEnvWrapper):
    """Encode a ``VecEnv``'s observations with one or several reservoirs.

    Args:
        venv: The wrapped vectorized environment (flat ``Box`` observations).
        config: Reservoir hyperparameters and encoding options.
        seed: Seed of the reservoir weights (each reservoir gets its own derived seed).

    The policy observes, as float32, the exposed reservoir units (an NVAR's: its exposed
    features, `NVARBank`), followed, with a skip connection, by
    ``[observation, encoded previous action, scaled previous reward]``.
    """

    def __init__(self, venv: VecEnv, config: EncoderConfig, seed: int) -> None:
        obs_space = venv.observation_space
        if not isinstance(obs_space, spaces.Box) or len(obs_space.shape) != 1:
            raise TypeError(f"the reservoir encoder needs flat Box observations, got {obs_space!r}")
        self.config = config
        self.reservoir_seed = seed
        self.obs_dim = int(obs_space.shape[0])
        self.action_encoder = ActionEncoder(venv.action_space, dtype=config.dtype)
        self.act_dim = self.action_encoder.dim if config.feed_action else 0
        self.rew_dim = 1 if config.feed_reward else 0
        self.input_dim = self.obs_dim + self.act_dim + self.rew_dim

        from ermrl.encoders import encoder_for

        # The encoder builds its bank: an ESN's or RTU layer's random weights (one derived seed
        # per reservoir), an NVAR's delay line.
        self.weight_seeds = reservoir_seeds(seed, config.n_reservoirs)
        self.bank: StepBank = encoder_for(config).bank(config, self.input_dim, seed)
        self.weights: list[ReservoirWeights] = list(getattr(self.bank, "weights", ()))

        n = venv.num_envs
        N, d_obs, d_act = self.bank.n_units, self.obs_dim, self.action_encoder.dim
        # One [x | u] buffer, u = [obs | action | reward]: a step is one matrix product (see
        # ReservoirBank). Observation, action and reward are written straight into views of it.
        self._xu = self.bank.buffer(n)
        self.states = self._xu[:, :N]
        self._inputs = self._xu[:, N:]
        self._obs_in = self._xu[:, N : N + d_obs]
        # The encoded action and scaled reward are also shown by the skip connection, so they are
        # kept even when they are not fed to the reservoir (then in arrays of their own).
        if config.feed_action:
            self._act_in = self._xu[:, N + d_obs : N + d_obs + d_act]
        else:
            self._act_in = np.zeros((n, d_act), self.bank.dtype)
        self._rew_in = self._xu[:, -1:] if config.feed_reward else np.zeros((n, 1), self.bank.dtype)
        self._reward_scale = float(config.reward_scale)
        self._actions: np.ndarray | None = None
        # The default policy observation is the state rows as they are (no skip connection, all
        # units): step_wait then copies them directly instead of assembling parts.
        self._state_only = config.exposed_units is None and not config.skip_connection

        # What the policy sees of the states (the first exposed_units of each reservoir).
        self._emit, n_state = self.bank.emitter(config.exposed_units)
        bound = self.bank.out_bound
        low: list[np.ndarray] = [np.full(n_state, -bound)]
        high: list[np.ndarray] = [np.full(n_state, bound)]
        if config.skip_connection:
            a = self.action_encoder
            low += [obs_space.low.astype(np.float64), np.full(a.dim, a.low), np.array([-np.inf])]
            high += [obs_space.high.astype(np.float64), np.full(a.dim, a.high), np.array([np.inf])]
        observation_space = spaces.Box(
            low=np.concatenate(low).astype(np.float32),
            high=np.concatenate(high).astype(np.float32),
            dtype=np.float32,
        )
        super().__init__(venv, observation_space=observation_space)

    # -- encoding --------------------------------------------------------------------------
    def _policy_obs(self, rows: Any = slice(None), obs: np.ndarray | None = None) -> np.ndarray:
        """The policy's float32 observation for ``rows`` (always a fresh array: SB3 keeps it)."""
        x = self.states[rows]
        if not self.config.skip_connection:
            return self._emit(x)
        parts = [
            self._emit(x),
            self._obs_in[rows] if obs is None else obs,
            self._act_in[rows],
            self._rew_in[rows],
        ]
        return np.concatenate(parts, axis=1).astype(np.float32)

    def _set_reward(self, rewards: np.ndarray) -> None:
        self._rew_in[:, 0] = rewards
        if self._reward_scale != 1.0:
            self._rew_in *= self._reward_scale

    # -- VecEnv API --------------------------------------------------------------------------
    def reset(self) -> VecEnvObs:
        obs = self.venv.reset()
        self._xu[:] = 0.0
        self._act_in[:] = 0.0
        self._rew_in[:] = 0.0
        self._obs_in[:] = obs
        self.bank.step_buffer(self._xu)
        return self._policy_obs()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions
        self.venv.step_async(actions)

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        assert self._actions is not None, "step_async must be called before step_wait"
        self.action_encoder(self._actions, self._act_in)
        self._set_reward(rewards)

        # Every step pays for this path: each numpy call here costs ~0.3-2 us (np.count_nonzero
        # is a C function; ndarray.any goes through Python and costs ~4x more).
        if not np.count_nonzero(dones):
            self._obs_in[:] = obs
            self.bank.step_buffer(self._xu)
            if self._state_only:
                return self._emit(self.states), rewards, dones, infos
            return self._policy_obs(), rewards, dones, infos

        # Terminal step: feed the true last observation of each finished episode.
        done_rows = np.flatnonzero(dones)
        self._obs_in[:] = obs
        for i in done_rows:
            terminal = infos[i].get("terminal_observation")
            if terminal is not None:
                self._obs_in[i] = terminal
        self.bank.step_buffer(self._xu)
        terminal_enc = self._policy_obs(done_rows)
        for j, i in enumerate(done_rows):
            if "terminal_observation" in infos[i]:
                infos[i]["terminal_observation"] = terminal_enc[j]

        # First step of the next episode for the finished rows: no previous action or reward.
        self._act_in[done_rows] = 0.0
        self._rew_in[done_rows] = 0.0
        self._obs_in[done_rows] = np.asarray(obs)[done_rows]
        rows = self._xu[done_rows]  # a copy (fancy indexing): step it, then write it back
        if self.config.reset == "episode":
            rows[:, : self.bank.n_units] = 0.0
        self.bank.step_buffer(rows)
        self._xu[done_rows] = rows
        return self._policy_obs(), rewards, dones, infos

    # -- helpers for analysis ------------------------------------------------------------------
    def get_states(self) -> np.ndarray:
        """A copy of the full reservoir states, shape ``(n_envs, sum(units))`` (an NVAR's: its
        delay line)."""
        return self.states.copy()

    def get_inputs(self) -> np.ndarray:
        """A copy of the last reservoir inputs, shape ``(n_envs, input_dim)``."""
        return self._inputs.copy()

    def input_layout(self) -> Sequence[tuple[str, int]]:
        """Names and sizes of the blocks of ``u``: observation, action, reward."""
        layout = [("observation", self.obs_dim)]
        if self.act_dim:
            layout.append(("action", self.act_dim))
        if self.rew_dim:
            layout.append(("reward", 1))
        return layout
