"""The ``bc`` and ``dagger`` agents: an MLP imitator trained from an expert, with SB3's interface.

`ImitationAgent` is not an SB3 algorithm; it offers what ermrl uses of one (``learn``
with SB3 callbacks, ``predict``, ``num_timesteps``, ``save`` as a plain ``.npz``, ``policy``
with ``state_dict``/``load_state_dict``/``set_training_mode``), so ``train_agent``,
``save_trained``/``load_policy``, evaluation and replays take it unchanged. The pieces
(`dagger_rollout`, `bc_fit`,
`beta`) live in `ermrl.learners._imitation`.

How env steps are counted (``num_timesteps``, the run's ``env_steps``): every env step the
learner's environment takes while the learner trains, whoever acted. DAgger's rollouts are all
learner steps (the expert-executed ones included; `ImitationAgent.iterations` splits
them). BC first runs the expert alone for ``n_expert_transitions`` steps to collect its data:
those are counted apart, in `ImitationAgent.expert_env_steps`, not as learner steps; the
budget's steps are then the learner's own rollouts (no learning), whose episodes are the run's
training episodes. The expert's own training steps are in its ``expert.json``
(`ExpertInfo`).

Which episodes are the run's training episodes (``--fitness last``, the pruning reports): only
*learner-only* ones, in which every executed action was the imitator's. A DAgger episode in
which the expert executed any action is hidden from the callback (its Monitor record moves to
``info["mixture_episode"]``, `hide_mixture_episodes`), since its
return scores the expert in part. With the linear schedule, learner-only episodes begin once
``beta`` reaches 0 (after ``beta_iterations * steps_per_iteration`` env steps); a budget that
ends before has none, and ``--fitness last`` fails that run (``--fitness eval`` evaluates the
imitator alone, deterministically). BC's episodes are all the imitator's.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from ermrl.config import ConfigError
from ermrl.learners._callbacks import as_callback
from ermrl.learners._imitation import (
    FullObservations,
    ImitationPolicy,
    StepHook,
    _act,
    bc_fit,
    beta,
    dagger_rollout,
    scale_actions,
    unscale_actions,
)

__all__ = ["ImitationAgent", "load_expert_for"]


def load_expert_for(env: Any, path: Any, learner: str) -> Any:
    """Load the expert of ``path`` and check that it acts on ``env``'s task.

    Raises:
        ConfigError: no expert there, or an expert of another task, with a one-line reason.
    """
    from ermrl.learners._expert import is_expert_folder, load_expert

    if not is_expert_folder(path):
        raise ConfigError(
            f"learner {learner!r}: expert={path!r} is not an expert folder (no expert.json; "
            "train one with: ermrl expert train --env-id ... --out DIR)"
        )
    try:
        expert = load_expert(path)
    except (OSError, ValueError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"learner {learner!r}: cannot load expert {path!r}: {first}") from None
    spec = getattr(env.unwrapped.envs[0], "spec", None)
    env_id = getattr(spec, "id", None)
    if env_id is not None and env_id != expert.env_id.split(":")[-1]:
        raise ConfigError(
            f"learner {learner!r}: the expert {path!r} acts on {expert.env_id}, not on {env_id}"
        )
    return expert


class ImitationAgent:
    """An MLP imitator (`ImitationPolicy`) and its training.

    Args:
        env: The learner's ``VecEnv`` (Box actions, flat Box observations).
        settings: The learner's checked settings (``mode`` ``"bc"`` or ``"dagger"``,
            ``expert``, ``hidden_sizes``, ``epochs``, ``batch_size``, ``learning_rate``, and
            ``n_expert_transitions`` for BC or ``steps_per_iteration``, ``beta_schedule``,
            ``beta_iterations`` for DAgger).
        seed: Seeds the network's weights, the minibatch order and the mixture's draws.
        expert: The loaded expert (default: loaded from ``settings["expert"]``).

    Attributes:
        num_timesteps: Learner env steps taken (see the module's docstring).
        expert_env_steps: Env steps the expert took alone to collect BC's data.
        iterations: One record per fit: ``beta``, ``steps`` (learner env steps of the
            iteration), ``expert_executed``, ``learner_executed``, ``dataset`` (labels fitted)
            and ``loss`` (last epoch's mean loss).
        episode_mixed: Whether the expert has executed an action in each env's current
            episode, ``(n_envs,)``; such an episode is not reported as a training episode.
    """

    def __init__(
        self, env: Any, settings: Mapping[str, Any], seed: int | None = None, expert: Any = None
    ) -> None:
        from gymnasium import spaces
        from stable_baselines3.common.logger import Logger

        mode = settings["mode"]
        if not isinstance(env.action_space, spaces.Box):
            raise ConfigError(f"learner {mode!r} needs a Box action space, got {env.action_space}")
        space = env.observation_space
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise ConfigError(f"learner {mode!r} needs a flat Box observation space, got {space}")
        self.env = env
        self.settings = dict(settings)
        self.mode = mode
        self.seed = seed
        self.n_envs = int(env.num_envs)
        self.observation_space = space
        self.action_space = env.action_space
        self.logger = Logger(folder=None, output_formats=[])
        self.num_timesteps = 0
        self.expert_env_steps = 0
        self.iterations: list[dict[str, Any]] = []
        self.expert = (
            expert if expert is not None else load_expert_for(env, settings["expert"], mode)
        )
        init_seq, shuffle_seq, mixture_seq = np.random.SeedSequence(seed).spawn(3)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(init_seq.generate_state(1)[0]))
            self.policy = ImitationPolicy(
                int(space.shape[0]),
                int(np.prod(env.action_space.shape)),
                [int(h) for h in settings["hidden_sizes"]],
            )
        self.policy.set_training_mode(False)
        self.optimizer = torch.optim.Adam(
            self.policy.parameters(), lr=float(settings["learning_rate"])
        )
        self.generator = torch.Generator().manual_seed(int(shuffle_seq.generate_state(1)[0]))
        self.rng = np.random.default_rng(mixture_seq)
        self._observations: list[np.ndarray] = []
        self._targets: list[np.ndarray] = []
        # whether the expert has executed an action in each env's current episode
        self.episode_mixed = np.zeros(self.n_envs, dtype=bool)

    # -- SB3-like interface -------------------------------------------------------------------

    def get_env(self) -> Any:
        return self.env

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, None]:
        """The imitator's actions (its mean: the policy is deterministic, ``deterministic`` is
        ignored).

        Args:
            observation: ``(E, obs_dim)`` or ``(obs_dim,)``.

        Returns:
            Env actions ``(E, *action_shape)`` (``action_shape`` for one observation), ``None``.
        """
        obs = np.asarray(observation, dtype=np.float32)
        single = obs.ndim == 1
        actions = unscale_actions(
            self.action_space, _act(self.policy, obs.reshape(-1, self.observation_space.shape[0]))
        )
        return (actions[0] if single else actions), None

    def save(self, path: Any) -> None:
        """Write the agent as a plain ``.npz``: the policy's arrays and a JSON record (settings,
        step counts, the iterations' records); ``np.load(..., allow_pickle=False)`` reads it."""
        arrays = {k: v.detach().cpu().numpy() for k, v in self.policy.state_dict().items()}
        config = {
            "learner": self.mode,
            "settings": self.settings,
            "seed": self.seed,
            "num_timesteps": self.num_timesteps,
            "expert_env_steps": self.expert_env_steps,
            "expert_info": self.expert.info.to_dict(),
            "iterations": self.iterations,
        }
        np.savez(path, config=np.array(json.dumps(config)), **arrays)

    def set_random_seed(self, seed: int | None = None) -> None:
        """Reseed the mixture's draws."""
        self.rng = np.random.default_rng(seed)

    # -- learning -----------------------------------------------------------------------------

    def _fit(self, record: dict[str, Any]) -> None:
        obs = np.concatenate(self._observations)
        targets = np.concatenate(self._targets)
        losses = bc_fit(
            self.policy,
            self.optimizer,
            obs,
            targets,
            int(self.settings["epochs"]),
            int(self.settings["batch_size"]),
            generator=self.generator,
        )
        record.update(dataset=int(obs.shape[0]), loss=losses[-1], losses=losses)
        self.iterations.append(record)

    def _add(self, observations: np.ndarray, expert_actions: np.ndarray) -> None:
        self._observations.append(np.asarray(observations, dtype=np.float32))
        self._targets.append(scale_actions(self.action_space, expert_actions))

    def _check_full(self, full_obs: np.ndarray) -> None:
        shape = tuple(self.expert.info.observation_shape)
        if tuple(full_obs.shape[1:]) != shape:
            raise ConfigError(
                f"learner {self.mode!r}: the expert takes observations of shape {shape}, the "
                f"env's full observation has shape {tuple(full_obs.shape[1:])}"
            )

    def _reset(self, full: FullObservations) -> tuple[np.ndarray, np.ndarray]:
        """Reset every env: no episode has been mixed yet.

        Args:
            full: Reads the full observations after the reset.

        Returns:
            The learner's observations ``(E, obs_dim)`` and the full ones ``(E, full_dim)``.
        """
        obs = np.asarray(self.env.reset())
        full_obs = full.after_reset()
        self.episode_mixed[:] = False
        return obs, full_obs

    def _clone_expert(self, obs: np.ndarray, full_obs: np.ndarray, full: FullObservations) -> None:
        """BC's data: the expert alone for ``n_expert_transitions`` steps (rounded up to whole
        steps of every env, counted in `expert_env_steps`), then a fit on its labels.

        Args:
            obs: The learner's observations ``(E, obs_dim)`` after a reset.
            full_obs: The full observations ``(E, full_dim)``.
            full: Reads the full observations after each step.
        """
        per_env = math.ceil(int(self.settings["n_expert_transitions"]) / self.n_envs)
        data = dagger_rollout(
            self.env, None, self.expert, 1.0, per_env, self.rng, obs, full_obs, full=full
        )
        self.expert_env_steps += per_env * self.n_envs
        self._add(data.observations, data.expert_actions)
        self._fit(
            {
                "beta": 1.0,
                "steps": 0,
                "expert_executed": data.n_expert_executed,
                "learner_executed": 0,
            }
        )

    def _dagger_iteration(
        self,
        obs: np.ndarray,
        full_obs: np.ndarray,
        full: FullObservations,
        total: int,
        on_step: StepHook,
    ) -> tuple[np.ndarray, np.ndarray, bool]:
        """One DAgger iteration: a rollout of the mixture with ``beta_i``, then a fit on every
        label so far (none when the callback stopped the rollout; its record is kept).

        Args:
            obs: The learner's current observations ``(E, obs_dim)``.
            full_obs: The current full observations ``(E, full_dim)``.
            full: Reads the full observations after each step.
            total: The learner env steps to reach; the iteration takes ``steps_per_iteration``
                of them at most.
            on_step: Called after every step; returning ``False`` stops the rollout.

        Returns:
            The observations and the full observations after the rollout, and whether it was
            stopped.
        """
        s, n_envs = self.settings, self.n_envs
        remaining = math.ceil((total - self.num_timesteps) / n_envs)
        i = len(self.iterations)
        b = beta(str(s["beta_schedule"]), i, int(s["beta_iterations"]))
        per_env = min(math.ceil(int(s["steps_per_iteration"]) / n_envs), remaining)
        start = self.num_timesteps
        rollout = dagger_rollout(
            self.env,
            self.policy,
            self.expert,
            b,
            per_env,
            self.rng,
            obs,
            full_obs,
            full=full,
            on_step=on_step,
            episode_mixed=self.episode_mixed,
        )
        self._add(rollout.observations, rollout.expert_actions)
        record = {
            "beta": b,
            "steps": self.num_timesteps - start,
            "expert_executed": rollout.n_expert_executed,
            "learner_executed": rollout.n_learner_executed,
        }
        if rollout.stopped:
            self.iterations.append(record)
        else:
            self._fit(record)
        return rollout.obs, rollout.full_obs, rollout.stopped

    def learn(
        self,
        total_timesteps: int,
        callback: Any = None,
        progress_bar: bool = False,
        reset_num_timesteps: bool = True,
        **_: Any,
    ) -> ImitationAgent:
        """Train for ``total_timesteps`` learner env steps (over all envs, rounded up to whole
        steps of every env, as SB3 does).

        DAgger: iterations of ``steps_per_iteration`` steps (the last one shorter), each a
        `dagger_rollout` with ``beta_i`` then a fit on every
        label gathered so far. BC (first call only): the expert's ``n_expert_transitions`` steps
        (`expert_env_steps`), a fit, a fresh reset; then the imitator acts for the budget.

        Args:
            total_timesteps: Learner env steps.
            callback: An SB3 ``BaseCallback`` (or a list, or ``None``); ``on_step`` runs after
                every learner step with ``locals`` holding ``infos``, ``dones``, ``rewards``,
                ``actions``; returning ``False`` stops training.
            progress_bar: Ignored.
            reset_num_timesteps: Count from zero.

        Returns:
            ``self``.
        """
        callback = as_callback(callback)
        if reset_num_timesteps:
            self.num_timesteps = 0
        total = int(total_timesteps) + (0 if reset_num_timesteps else self.num_timesteps)
        n_envs = self.n_envs
        full = FullObservations(self.env)

        def on_step(infos: Any, dones: Any, rewards: Any, actions: Any) -> bool:
            self.num_timesteps += n_envs
            if callback is None:
                return True
            callback.update_locals(
                {"infos": infos, "dones": dones, "rewards": rewards, "actions": actions}
            )
            return bool(callback.on_step())

        obs, full_obs = self._reset(full)
        self._check_full(full_obs)
        if self.mode == "bc" and not self.iterations:
            self._clone_expert(obs, full_obs, full)
            obs, full_obs = self._reset(full)  # the learner's episodes start afresh
        if callback is not None:
            callback.init_callback(self)
            callback.on_training_start(locals(), globals())
        while self.num_timesteps < total:
            if self.mode == "bc":
                action, _state = self.predict(obs)
                obs, rewards, dones, infos = self.env.step(action)
                if not on_step(infos, dones, rewards, action):
                    break
                continue
            obs, full_obs, stopped = self._dagger_iteration(obs, full_obs, full, total, on_step)
            if stopped:
                break
        if callback is not None:
            callback.on_training_end()
        return self
