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
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

from ermrl.config import EncoderConfig
from ermrl.encoders._reservoir import ReservoirBank, reservoir_seeds, reservoir_weights

__all__ = ["ActionEncoder", "ReservoirVecEnv"]


class ActionEncoder:
    """Turns a batch of actions into reservoir inputs.

    Args:
        space: The action space of one environment.
    """

    def __init__(self, space: spaces.Space) -> None:
        self.space = space
        if isinstance(space, spaces.Discrete):
            self.dim = int(space.n)
            self._eye = np.eye(self.dim)
            self.low, self.high = 0.0, 1.0
        elif isinstance(space, spaces.MultiDiscrete):
            self._nvec = np.asarray(space.nvec).ravel()
            self._offsets = np.concatenate([[0], np.cumsum(self._nvec)[:-1]])
            self.dim = int(self._nvec.sum())
            self.low, self.high = 0.0, 1.0
        elif isinstance(space, spaces.MultiBinary):
            self.dim = int(np.prod(space.shape))
            self.low, self.high = 0.0, 1.0
        elif isinstance(space, spaces.Box):
            self.dim = int(np.prod(space.shape))
            low = np.asarray(space.low, np.float64).ravel()
            high = np.asarray(space.high, np.float64).ravel()
            bounded = np.isfinite(low) & np.isfinite(high)
            self._center = np.where(bounded, (high + low) / 2, 0.0)
            self._half = np.where(bounded, (high - low) / 2, 1.0)
            self._bounded = bounded
            self.low, self.high = -1.0, 1.0
        else:
            raise TypeError(f"unsupported action space {space!r}")

    def __call__(self, actions: np.ndarray, out: np.ndarray) -> None:
        """Write encoded ``actions`` (a batch) into ``out`` of shape ``(n, dim)``."""
        space = self.space
        if isinstance(space, spaces.Discrete):
            out[:] = self._eye[np.asarray(actions, dtype=np.int64).ravel() - int(space.start)]
        elif isinstance(space, spaces.MultiDiscrete):
            out[:] = 0.0
            idx = np.asarray(actions, dtype=np.int64).reshape(len(out), -1) + self._offsets
            np.put_along_axis(out, idx, 1.0, axis=1)
        elif isinstance(space, spaces.MultiBinary):
            out[:] = np.asarray(actions).reshape(len(out), -1)
        else:
            a = np.asarray(actions, dtype=np.float64).reshape(len(out), -1)
            np.subtract(a, self._center, out=out)
            out /= self._half
            np.clip(out, -1.0, 1.0, out=out, where=self._bounded[None, :])


class ReservoirVecEnv(VecEnvWrapper):
    """Encode a ``VecEnv``'s observations with one or several reservoirs.

    Args:
        venv: The wrapped vectorized environment (flat ``Box`` observations).
        config: Reservoir hyperparameters and encoding options.
        seed: Seed of the reservoir weights (each reservoir gets its own derived seed).

    The policy observes, as float32, the exposed reservoir units, followed, with a skip
    connection, by ``[observation, encoded previous action, scaled previous reward]``.
    """

    def __init__(self, venv: VecEnv, config: EncoderConfig, seed: int) -> None:
        obs_space = venv.observation_space
        if not isinstance(obs_space, spaces.Box) or len(obs_space.shape) != 1:
            raise TypeError(f"the reservoir encoder needs flat Box observations, got {obs_space!r}")
        self.config = config
        self.reservoir_seed = seed
        self.obs_dim = int(obs_space.shape[0])
        self.action_encoder = ActionEncoder(venv.action_space)
        self.act_dim = self.action_encoder.dim if config.feed_action else 0
        self.rew_dim = 1 if config.feed_reward else 0
        self.input_dim = self.obs_dim + self.act_dim + self.rew_dim

        self.weight_seeds = reservoir_seeds(seed, config.n_reservoirs)
        self.weights = [
            reservoir_weights(p, self.input_dim, s)
            for p, s in zip(config.reservoirs, self.weight_seeds)
        ]
        self.bank = ReservoirBank(self.weights)

        n = venv.num_envs
        self.states = np.zeros((n, self.bank.n_units))
        self._inputs = np.zeros((n, self.input_dim))
        # Skip-connection extras, always tracked so that terminal encodings are right.
        self._act_enc = np.zeros((n, self.action_encoder.dim))
        self._rew = np.zeros((n, 1))
        self._actions: np.ndarray | None = None

        if config.exposed_units is None:
            self._exposed = None
        else:
            starts = np.cumsum((0,) + self.bank.units[:-1])
            self._exposed = np.concatenate([np.arange(s, s + config.exposed_units) for s in starts])
        n_state = self.bank.n_units if self._exposed is None else len(self._exposed)
        low = [np.full(n_state, -1.0)]
        high = [np.full(n_state, 1.0)]
        if config.skip_connection:
            a = self.action_encoder
            low += [obs_space.low.astype(np.float64), np.full(a.dim, a.low), [-np.inf]]
            high += [obs_space.high.astype(np.float64), np.full(a.dim, a.high), [np.inf]]
        observation_space = spaces.Box(
            low=np.concatenate(low).astype(np.float32),
            high=np.concatenate(high).astype(np.float32),
            dtype=np.float32,
        )
        super().__init__(venv, observation_space=observation_space)

    # -- encoding --------------------------------------------------------------------------
    def _fill_inputs(self, rows: slice | np.ndarray, obs: np.ndarray) -> None:
        u = self._inputs
        u[rows, : self.obs_dim] = obs
        if self.act_dim:
            u[rows, self.obs_dim : self.obs_dim + self.act_dim] = self._act_enc[rows]
        if self.rew_dim:
            u[rows, -1:] = self._rew[rows] * self.config.reward_scale

    def _policy_obs(
        self, states: np.ndarray, obs: np.ndarray, rows: Any = slice(None)
    ) -> np.ndarray:
        x = states if self._exposed is None else states[:, self._exposed]
        if not self.config.skip_connection:
            return x.astype(np.float32)
        scaled_rew = self._rew[rows] * self.config.reward_scale
        return np.concatenate([x, obs, self._act_enc[rows], scaled_rew], axis=1).astype(np.float32)

    # -- VecEnv API --------------------------------------------------------------------------
    def reset(self) -> VecEnvObs:
        obs = np.asarray(self.venv.reset(), dtype=np.float64)
        self.states[:] = 0.0
        self._act_enc[:] = 0.0
        self._rew[:] = 0.0
        self._fill_inputs(slice(None), obs)
        self.bank.step(self.states, self._inputs)
        return self._policy_obs(self.states, obs)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions
        self.venv.step_async(actions)

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        obs = np.asarray(obs, dtype=np.float64)
        assert self._actions is not None, "step_async must be called before step_wait"
        self.action_encoder(self._actions, self._act_enc)
        self._rew[:, 0] = rewards

        done_rows = np.flatnonzero(dones)
        if len(done_rows) == 0:
            self._fill_inputs(slice(None), obs)
            self.bank.step(self.states, self._inputs)
            return self._policy_obs(self.states, obs), rewards, dones, infos

        # Terminal step: feed the true last observation of each finished episode.
        step_obs = obs.copy()
        for i in done_rows:
            terminal = infos[i].get("terminal_observation")
            if terminal is not None:
                step_obs[i] = terminal
        self._fill_inputs(slice(None), step_obs)
        self.bank.step(self.states, self._inputs)
        terminal_enc = self._policy_obs(self.states[done_rows], step_obs[done_rows], done_rows)
        for j, i in enumerate(done_rows):
            if "terminal_observation" in infos[i]:
                infos[i]["terminal_observation"] = terminal_enc[j]

        # First step of the next episode for the finished rows.
        if self.config.reset == "episode":
            self.states[done_rows] = 0.0
        self._act_enc[done_rows] = 0.0
        self._rew[done_rows] = 0.0
        sub_states = self.states[done_rows]
        self._fill_inputs(done_rows, obs[done_rows])
        self.bank.step(sub_states, self._inputs[done_rows])
        self.states[done_rows] = sub_states
        return self._policy_obs(self.states, obs), rewards, dones, infos

    # -- helpers for analysis ------------------------------------------------------------------
    def get_states(self) -> np.ndarray:
        """A copy of the full reservoir states, shape ``(n_envs, sum(units))``."""
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
