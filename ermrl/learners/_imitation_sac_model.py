"""The ``imitation-sac`` agent: Stable-Baselines3 SAC seeded by imitation of an expert.

`ImitationSAC` is SB3's ``SAC`` with three phases, all inside ``learn`` and all counted
in ``num_timesteps`` (the learner's env-step budget):

1. **DAgger pretraining** (the first ``pretrain_steps`` env steps; they take the place of SAC's
   ``learning_starts`` random steps). Iteration ``i`` (``steps_per_iteration`` env steps) acts
   with the mixture policy: with probability ``beta_i`` (`beta`,
   ``beta_schedule`` over ``beta_iterations``) the expert's action, otherwise the actor's
   deterministic mean; every visited state is labelled with the expert's action on its raw full
   observation. After each iteration the actor's mean is regressed onto all labels so far
   (`bc_fit`, ``bc_epochs`` passes, Adam at
   ``bc_learning_rate``). The transitions go into SAC's replay buffer as usual. No SAC gradient
   step is taken.
2. **Critic warm-start** (no env step). The actor's log standard deviation head is reset to the
   constant ``initial_log_std`` (behaviour cloning fits only the mean, and SAC's freshly
   initialised head would act with a standard deviation near 1 before the tanh), then
   ``critic_warmup_steps`` gradient steps train the critics (and the entropy coefficient, which
   does not move the actor) on the buffer of phase 1, with the actor frozen.
3. **SAC**, SB3's update with one addition. The remaining env steps are cut into blocks of
   ``steps_per_iteration``; block ``j`` is a DAgger iteration with probability
   ``anchor_schedule`` applied to ``j`` over ``anchor_iterations`` (the same two schedules,
   so ``linear`` makes the first block always one and none after ``anchor_iterations``
   blocks). In a DAgger block the actor acts as SAC does (a DAgger iteration with ``beta = 0``),
   every visited state is labelled by the expert, and each actor update adds a behaviour
   cloning term on a minibatch of all expert-labelled states: ``bc_weight * mean|Q| * MSE``
   (the actor's mean against the label). Scaling by the batch's mean ``|Q|`` (detached) is
   TD3+BC's normalisation (Fujimoto and Gu, 2021): their ``alpha = 2.5`` is
   ``bc_weight = 0.4``.
   The table starts SAC's learned entropy temperature at 0.05 (``ent_coef: auto_0.05``), not
   SB3's 1.0, which would push the pretrained actor towards entropy and away from the expert.

The expert's own training is not part of the budget: its steps are in its ``expert.json``, and
`ImitationSAC.phase_steps` records, apart, what each phase used.

Training episodes (``--fitness last``, the pruning reports) are the learner's alone: the env is
wrapped in `LearnerOnlyEpisodes`, so an episode in which the
expert executed any action (in phase 1, with ``beta_i > 0``; an episode that reaches back into
it) is hidden from the callback (its Monitor record moves to ``info["mixture_episode"]``). The
run's training returns are those of the actor's own episodes: its deterministic mean in
phase 1 once ``beta`` is 0, SAC's sampled actions in phase 3 (DAgger blocks included, where the
actor acts and the expert only labels).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.utils import polyak_update
from torch import nn
from torch.nn import functional as F

from ermrl.config import ConfigError
from ermrl.learners._dagger_model import load_expert_for
from ermrl.learners._imitation import (
    FullObservations,
    LearnerOnlyEpisodes,
    bc_fit,
    beta,
    scale_actions,
    unscale_actions,
)

__all__ = ["ActorMean", "ImitationSAC"]


class ActorMean(nn.Module):
    """SAC's actor as a deterministic policy: observations -> ``tanh(mean)`` in ``[-1, 1]``."""

    def __init__(self, actor: nn.Module) -> None:
        super().__init__()
        self.actor = actor

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.actor(obs, deterministic=True)
        return out


class ImitationSAC(SAC):
    """SAC with DAgger pretraining, a critic warm-start and DAgger re-anchoring (module doc).

    Args:
        policy: SB3's policy name (``"MlpPolicy"``).
        env: The learner's ``VecEnv`` (Box actions; the expert sees the raw full observation).
        imitation: The checked imitation settings (``expert``, ``pretrain_steps``,
            ``steps_per_iteration``, ``beta_schedule``, ``beta_iterations``, ``bc_epochs``,
            ``bc_learning_rate``, ``critic_warmup_steps``, ``initial_log_std``,
            ``anchor_schedule``, ``anchor_iterations``, ``bc_weight``).
        expert: The loaded expert (default: loaded from ``imitation["expert"]``).
        **kwargs: SAC's own arguments (``learning_starts`` is ``pretrain_steps``).

    Attributes:
        phase_steps: What each phase used: ``pretrain_env_steps``, ``expert_executed_steps``
            (of those), ``pretrain_fits``, ``critic_warmup_gradient_steps``, ``sac_env_steps``,
            ``dagger_blocks``, ``dagger_block_env_steps``, ``expert_labels`` (states labelled
            in all) and ``expert_training_steps`` (the expert's own, from its
            ``expert.json``; not part of the budget).
    """

    def __init__(
        self,
        policy: Any,
        env: Any,
        imitation: Mapping[str, Any],
        expert: Any = None,
        **kwargs: Any,
    ) -> None:
        if "learning_starts" in kwargs:
            raise ConfigError(
                "learner 'imitation-sac' does not take learning_starts: pretrain_steps takes "
                "its place"
            )
        if not isinstance(env.action_space, spaces.Box):
            raise ConfigError(
                f"learner 'imitation-sac' needs a Box action space, got {env.action_space}"
            )
        self.imitation = dict(imitation)
        self.expert = (
            expert
            if expert is not None
            else load_expert_for(env, imitation["expert"], "imitation-sac")
        )
        # the expert acts in phase 1: its episodes are hidden from the training returns
        self._episodes = LearnerOnlyEpisodes(env)
        super().__init__(
            policy, self._episodes, learning_starts=int(imitation["pretrain_steps"]), **kwargs
        )
        mixture_seq, block_seq, shuffle_seq = np.random.SeedSequence(self.seed).spawn(3)
        self._mixture_rng = np.random.default_rng(mixture_seq)
        self._block_rng = np.random.default_rng(block_seq)
        self._generator = torch.Generator().manual_seed(int(shuffle_seq.generate_state(1)[0]))
        self._bc_optimizer = torch.optim.Adam(
            self.actor.parameters(), lr=float(imitation["bc_learning_rate"])
        )
        self._label_obs: list[np.ndarray] = []
        self._label_targets: list[np.ndarray] = []
        self._labels: tuple[np.ndarray, np.ndarray] | None = None
        self._full: FullObservations | None = None
        self._full_obs: np.ndarray | None = None
        self._fits = 0
        self._warmed_up = False
        self._block = -1
        self._in_dagger_block = False
        self.phase_steps: dict[str, int] = {
            "pretrain_env_steps": 0,
            "expert_executed_steps": 0,
            "pretrain_fits": 0,
            "critic_warmup_gradient_steps": 0,
            "sac_env_steps": 0,
            "dagger_blocks": 0,
            "dagger_block_env_steps": 0,
            "expert_labels": 0,
            "expert_training_steps": int(self.expert.info.env_steps),
        }

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "expert",
            "_episodes",
            "_full",
            "_full_obs",
            "_label_obs",
            "_label_targets",
            "_labels",
            "_bc_optimizer",
            "_generator",
        ]

    # -- where the run is -----------------------------------------------------------------------

    @property
    def pretrain_steps(self) -> int:
        return int(self.imitation["pretrain_steps"])

    @property
    def steps_per_iteration(self) -> int:
        return int(self.imitation["steps_per_iteration"])

    def _pretraining(self) -> bool:
        return self.num_timesteps < self.pretrain_steps

    def _enter_block(self) -> None:
        """Draw whether the current SAC block (phase 3) is a DAgger iteration."""
        block = (self.num_timesteps - self.pretrain_steps) // self.steps_per_iteration
        if block != self._block:
            self._block = block
            p = beta(
                str(self.imitation["anchor_schedule"]),
                block,
                int(self.imitation["anchor_iterations"]),
            )
            self._in_dagger_block = bool(self._block_rng.random() < p)
            if self._in_dagger_block:
                self.phase_steps["dagger_blocks"] += 1

    # -- acting -------------------------------------------------------------------------------

    def _setup_learn(self, total_timesteps: int, *args: Any, **kwargs: Any) -> Any:
        out = super()._setup_learn(total_timesteps, *args, **kwargs)
        self._full = FullObservations(self.env)
        # SB3 resets the env when it starts counting afresh (else the run goes on where it was)
        if self._full_obs is None or self.num_timesteps == 0:
            self._full_obs = self._full.after_reset()
        shape = tuple(self.expert.info.observation_shape)
        if tuple(self._full_obs.shape[1:]) != shape:
            raise ConfigError(
                f"learner 'imitation-sac': the expert takes observations of shape {shape}, the "
                f"env's full observation has shape {tuple(self._full_obs.shape[1:])}"
            )
        return out

    def _label(self, n_envs: int) -> np.ndarray:
        """The expert's actions on the current states (env units), stored as labels."""
        assert self._full_obs is not None and self._last_obs is not None
        space = self.action_space
        assert isinstance(space, spaces.Box)
        expert_action = np.asarray(self.expert.predict(self._full_obs, deterministic=True))
        expert_action = expert_action.reshape((n_envs, *space.shape))
        self._label_obs.append(np.array(self._last_obs, dtype=np.float32).reshape(n_envs, -1))
        self._label_targets.append(scale_actions(space, expert_action))
        self._labels = None
        self.phase_steps["expert_labels"] += n_envs
        return expert_action

    def _sample_action(
        self, learning_starts: int, action_noise: Any = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        if not self._pretraining():
            self._enter_block()
            if self._in_dagger_block:
                self._label(n_envs)
                self.phase_steps["dagger_block_env_steps"] += n_envs
            self.phase_steps["sac_env_steps"] += n_envs
            return super()._sample_action(learning_starts, action_noise, n_envs)
        space = self.action_space
        expert_action = self._label(n_envs)
        i = self.num_timesteps // self.steps_per_iteration
        b = beta(str(self.imitation["beta_schedule"]), i, int(self.imitation["beta_iterations"]))
        by_expert = self._mixture_rng.random(n_envs) < b
        if by_expert.all():
            action = expert_action.astype(space.dtype)
        else:
            assert self._last_obs is not None
            obs = torch.as_tensor(np.asarray(self._last_obs), dtype=torch.float32)
            with torch.no_grad():
                mean = ActorMean(self.actor)(obs.to(self.device)).cpu().numpy()
            action = unscale_actions(space, mean)  # type: ignore[arg-type]
            action[by_expert] = expert_action[by_expert]
        self._episodes.expert_acts(by_expert)
        self.phase_steps["pretrain_env_steps"] += n_envs
        self.phase_steps["expert_executed_steps"] += int(np.count_nonzero(by_expert))
        buffer_action = np.clip(self.policy.scale_action(action), -1.0, 1.0)
        return action, buffer_action

    def _store_transition(self, replay_buffer: Any, buffer_action: Any, *args: Any) -> None:
        super()._store_transition(replay_buffer, buffer_action, *args)
        assert self._full is not None
        self._full_obs = self._full.after_step()

    def _on_step(self) -> None:
        super()._on_step()
        if self._warmed_up:
            return
        done_pretraining = not self._pretraining()
        due = self.num_timesteps // self.steps_per_iteration > self._fits
        if self._label_obs and (done_pretraining or due):
            self._fit()
        if done_pretraining:
            self._warm_up()

    # -- learning -----------------------------------------------------------------------------

    def _label_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if self._labels is None:
            self._labels = (np.concatenate(self._label_obs), np.concatenate(self._label_targets))
        return self._labels

    def _fit(self) -> None:
        """Regress the actor's mean onto every label so far (one DAgger fit)."""
        obs, targets = self._label_arrays()
        bc_fit(
            ActorMean(self.actor),
            self._bc_optimizer,
            obs,
            targets,
            int(self.imitation["bc_epochs"]),
            int(self.batch_size),
            generator=self._generator,
        )
        self._fits = self.num_timesteps // self.steps_per_iteration
        self.phase_steps["pretrain_fits"] += 1

    def _warm_up(self) -> None:
        """Phase 2: reset the log-std head, then train the critics alone."""
        self._warmed_up = True
        log_std = self.actor.log_std
        if isinstance(log_std, nn.Linear):  # without gSDE (refused by the learner)
            with torch.no_grad():
                log_std.weight.zero_()
                log_std.bias.fill_(float(self.imitation["initial_log_std"]))
        n = int(self.imitation["critic_warmup_steps"])
        if n == 0 or self.replay_buffer is None or self.replay_buffer.size() == 0:
            return
        self.policy.set_training_mode(True)
        for _ in range(n):
            data = self.replay_buffer.sample(self.batch_size, env=self._vec_normalize_env)
            _actions, _log_prob, ent_coef = self._entropy_step(data.observations)
            self._critic_step(data, ent_coef)
            self._update_targets(self.phase_steps["critic_warmup_gradient_steps"])
            self.phase_steps["critic_warmup_gradient_steps"] += 1
        self.policy.set_training_mode(False)

    def _entropy_step(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The actor's sampled actions and log-probabilities on ``obs``, and the entropy
        coefficient (stepped first when it is learned), as in SB3's ``SAC.train``."""
        actions_pi, log_prob = self.actor.action_log_prob(obs)
        log_prob = log_prob.reshape(-1, 1)
        if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
            ent_coef = torch.exp(self.log_ent_coef.detach())
            assert isinstance(self.target_entropy, float)
            loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
            self.ent_coef_optimizer.zero_grad()
            loss.backward()
            self.ent_coef_optimizer.step()
        else:
            ent_coef = self.ent_coef_tensor
        return actions_pi, log_prob, ent_coef

    def _critic_step(self, data: Any, ent_coef: torch.Tensor) -> float:
        """One step of the critics toward the soft Bellman target (SB3's ``SAC.train``)."""
        discounts = getattr(data, "discounts", None)
        discounts = discounts if discounts is not None else self.gamma
        with torch.no_grad():
            next_actions, next_log_prob = self.actor.action_log_prob(data.next_observations)
            next_q = torch.cat(self.critic_target(data.next_observations, next_actions), dim=1)
            next_q, _ = torch.min(next_q, dim=1, keepdim=True)
            next_q = next_q - ent_coef * next_log_prob.reshape(-1, 1)
            target = data.rewards + (1 - data.dones) * discounts * next_q
        current = self.critic(data.observations, data.actions)
        loss = 0.5 * sum(F.mse_loss(q, target) for q in current)
        assert isinstance(loss, torch.Tensor)
        self.critic.optimizer.zero_grad()
        loss.backward()
        self.critic.optimizer.step()
        return float(loss.detach())

    def _update_targets(self, step: int) -> None:
        if step % self.target_update_interval == 0:
            polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
            polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)

    def _bc_term(self, batch_size: int) -> torch.Tensor:
        """Mean squared error of the actor's mean against the expert on a minibatch of labels."""
        obs, targets = self._label_arrays()
        index = torch.randint(0, obs.shape[0], (batch_size,), generator=self._generator)
        x = torch.as_tensor(obs[index.numpy()], device=self.device)
        y = torch.as_tensor(targets[index.numpy()], device=self.device)
        return torch.mean((ActorMean(self.actor)(x) - y) ** 2)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SB3's SAC update; in a DAgger block the actor loss gains the behaviour-cloning term."""
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers += [self.ent_coef_optimizer]
        self._update_learning_rate(optimizers)
        anchored = self._in_dagger_block and bool(self._label_obs)
        weight = float(self.imitation["bc_weight"])
        actor_losses, critic_losses, bc_losses, ent_coefs = [], [], [], []
        for step in range(gradient_steps):
            data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
            actions_pi, log_prob, ent_coef = self._entropy_step(data.observations)
            ent_coefs.append(float(ent_coef))
            critic_losses.append(self._critic_step(data, ent_coef))
            q_pi = torch.cat(self.critic(data.observations, actions_pi), dim=1)
            min_q, _ = torch.min(q_pi, dim=1, keepdim=True)
            actor_loss = (ent_coef * log_prob - min_q).mean()
            if anchored and weight > 0:
                bc = self._bc_term(batch_size)
                bc_losses.append(float(bc.detach()))
                actor_loss = actor_loss + weight * min_q.abs().mean().detach() * bc
            actor_losses.append(float(actor_loss.detach()))
            self.actor.optimizer.zero_grad()
            actor_loss.backward()
            self.actor.optimizer.step()
            self._update_targets(step)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/ent_coef", float(np.mean(ent_coefs)))
        self.logger.record("train/actor_loss", float(np.mean(actor_losses)))
        self.logger.record("train/critic_loss", float(np.mean(critic_losses)))
        if bc_losses:
            self.logger.record("train/bc_loss", float(np.mean(bc_losses)))
