"""Imitation from an expert: behaviour cloning and DAgger, as reusable pieces.

The ``bc`` and ``dagger`` learners (`ermrl.learners._bc`, `ermrl.learners._dagger`)
are built from these functions, and so can other learners (pretraining SAC's actor): each takes
a torch module that maps the learner's observation ``(n, obs_dim)`` to its action mean in the
*scaled* action space ``[-1, 1]^act_dim`` (SB3's convention for SAC's actor,
`scale_actions`), and an `Expert`, which acts on the raw *full*
observation.

The learner sees the env's observation as the ``VecEnv`` returns it (masked by
``--observe``, maybe reservoir-encoded, maybe normalized); the expert sees the raw full
observation of the same state, read by `FullObservations` from the innermost
``DummyVecEnv`` (``info["full_observation"]`` from [`ObservationMask`][ermrl.envs.ObservationMask]
when the observation is masked, else the env's own observation).

DAgger (Ross, Gordon and Bagnell, 2011). Iteration ``i`` rolls out the mixture policy: at
each step and in each env, with probability ``beta_i`` the expert's action is executed,
otherwise the learner's; every visited state is labelled with the expert's action on that
state, whoever acted. The policy is then refit on all labels gathered so far. The schedules
(`beta`): ``linear``, ``beta_i = max(0, 1 - i / K)`` (1 at ``i = 0``, 0 from ``i = K``
on), and ``inverse``, ``beta_i = 1 / (1 + i)``. Panjete/mujocoagents (whose DAgger this
replaces) labelled a state with the *learner's own* action with probability ``1 - beta``; that
trains the learner on its own outputs and is not DAgger.

Training episodes are the learner's alone. A mixture rollout's episode in which the expert
executed even one action scores the expert in part, so its Monitor record
(``info["episode"]``) is moved to ``info["mixture_episode"]`` (`MIXTURE_EPISODE_KEY`,
`hide_mixture_episodes`) before anything reads it: ermrl's training returns (the
``--fitness last`` measure, the pruning reports) count only *learner-only* episodes, in which
every executed action was the learner's. `dagger_rollout` does this given
``episode_mixed``; `LearnerOnlyEpisodes` does it for an SB3 algorithm's env.

Examples:
    ```python
    policy = ImitationPolicy(obs_dim=2, act_dim=1, hidden_sizes=(64, 64))
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)
    full = FullObservations(venv)
    obs = venv.reset()
    rollout = dagger_rollout(venv, policy, expert, beta=0.5, n_steps=1000,
                             rng=np.random.default_rng(0), obs=obs, full_obs=full.after_reset())
    targets = scale_actions(venv.action_space, rollout.expert_actions)
    losses = bc_fit(policy, optimizer, rollout.observations, targets, epochs=5, batch_size=256)
    ```
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnvWrapper
from torch import nn

from ermrl.envs._masks import FULL_OBSERVATION_KEY

__all__ = [
    "BETA_SCHEDULES",
    "MIXTURE_EPISODE_KEY",
    "BetaSchedule",
    "DaggerRollout",
    "FullObservations",
    "ImitationPolicy",
    "LearnerOnlyEpisodes",
    "bc_fit",
    "beta",
    "dagger_rollout",
    "hide_mixture_episodes",
    "scale_actions",
    "unscale_actions",
]

BetaSchedule = Literal["linear", "inverse"]
BETA_SCHEDULES: tuple[str, ...] = ("linear", "inverse")
# Where the Monitor record of an episode in which the expert acted is moved (out of "episode").
MIXTURE_EPISODE_KEY = "mixture_episode"

# Called after every env step of a rollout with (infos, dones, rewards, actions); False stops it.
StepHook = Callable[[list[dict[str, Any]], np.ndarray, np.ndarray, np.ndarray], bool]


def beta(schedule: str, i: int, k: int) -> float:
    """The probability that the expert acts in DAgger iteration ``i`` (0-based).

    Args:
        schedule: ``"linear"``: ``max(0, 1 - i / k)``, 1 at ``i = 0`` down to 0 at ``i >= k``;
            ``"inverse"``: ``1 / (1 + i)`` (``k`` unused).
        i: The iteration, ``>= 0``.
        k: The linear schedule's number of iterations to reach 0, ``>= 1``.

    Returns:
        ``beta_i`` in ``[0, 1]``.

    Raises:
        ValueError: an unknown schedule, ``i < 0`` or ``k < 1``.
    """
    if i < 0:
        raise ValueError(f"the iteration must be >= 0, got {i}")
    if schedule == "linear":
        if k < 1:
            raise ValueError(f"the linear schedule needs K >= 1 iterations, got {k}")
        return max(0.0, 1.0 - i / k)
    if schedule == "inverse":
        return 1.0 / (1.0 + i)
    raise ValueError(f"unknown beta schedule {schedule!r}; choose from {', '.join(BETA_SCHEDULES)}")


def scale_actions(space: spaces.Box, actions: np.ndarray) -> np.ndarray:
    """Env actions ``(n, *shape)`` -> the scaled space ``[-1, 1]``, flat ``(n, act_dim)``."""
    low = np.asarray(space.low, np.float64).ravel()
    high = np.asarray(space.high, np.float64).ravel()
    flat = np.asarray(actions, np.float64).reshape(-1, low.size)
    return (2.0 * (flat - low) / (high - low) - 1.0).astype(np.float32)


def unscale_actions(space: spaces.Box, scaled: np.ndarray) -> np.ndarray:
    """Scaled actions ``(n, act_dim)`` in ``[-1, 1]`` (clipped) -> env actions ``(n, *shape)``."""
    low = np.asarray(space.low, np.float64).ravel()
    high = np.asarray(space.high, np.float64).ravel()
    clipped = np.clip(np.asarray(scaled, np.float64).reshape(-1, low.size), -1.0, 1.0)
    out = low + (clipped + 1.0) * 0.5 * (high - low)
    return out.reshape((-1, *space.shape)).astype(space.dtype)


class ImitationPolicy(nn.Module):
    """A deterministic MLP policy: ``mean = tanh(MLP(obs))`` in the scaled action space.

    Hidden layers use tanh. ``state_dict`` holds tensors only (saved as ``policy.pt``).

    Args:
        obs_dim: Width of the learner's observation.
        act_dim: Number of action entries.
        hidden_sizes: Widths of the hidden layers (may be empty: a linear readout).
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden_sizes: Sequence[int]) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = obs_dim
        for size in hidden_sizes:
            layers += [nn.Linear(width, int(size)), nn.Tanh()]
            width = int(size)
        layers += [nn.Linear(width, act_dim), nn.Tanh()]
        self.net = nn.Sequential(*layers)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """``(n, obs_dim)`` -> scaled action means ``(n, act_dim)`` in ``(-1, 1)``."""
        out: torch.Tensor = self.net(obs)
        return out

    def set_training_mode(self, mode: bool) -> None:
        """SB3's name for ``train(mode)``."""
        self.train(mode)


def _act(module: nn.Module, obs: np.ndarray) -> np.ndarray:
    """The module's scaled action means for ``(n, obs_dim)`` observations, as numpy."""
    param = next(module.parameters())
    with torch.no_grad():
        tensor = torch.as_tensor(np.asarray(obs), dtype=param.dtype, device=param.device)
        return module(tensor).cpu().numpy()


def bc_fit(
    policy_mean: nn.Module,
    optimizer: torch.optim.Optimizer,
    obs: np.ndarray,
    expert_actions: np.ndarray,
    epochs: int,
    batch_size: int,
    *,
    generator: torch.Generator | None = None,
) -> list[float]:
    """Regress the policy mean onto the expert's (scaled) actions: mean squared error, minibatches.

    Args:
        policy_mean: Maps observations ``(n, obs_dim)`` to action means ``(n, act_dim)``.
        optimizer: Steps ``policy_mean``'s parameters.
        obs: The learner's observations, ``(n, obs_dim)``.
        expert_actions: Targets in the scaled space, ``(n, act_dim)`` (`scale_actions`).
        epochs: Passes over the data, ``>= 1``.
        batch_size: Minibatch size (the last minibatch of an epoch may be smaller).
        generator: Shuffles the minibatches (``None``: torch's global generator).

    Returns:
        The mean loss of each epoch.
    """
    param = next(policy_mean.parameters())
    x = torch.as_tensor(np.asarray(obs), dtype=param.dtype, device=param.device)
    y = torch.as_tensor(np.asarray(expert_actions), dtype=param.dtype, device=param.device)
    if x.shape[0] != y.shape[0] or x.shape[0] == 0:
        raise ValueError(
            f"bc_fit needs as many observations as actions (> 0): {x.shape}, {y.shape}"
        )
    y = y.reshape(x.shape[0], -1)
    policy_mean.train(True)
    losses = []
    for _ in range(epochs):
        order = torch.randperm(x.shape[0], generator=generator).to(param.device)
        total = 0.0
        for start in range(0, x.shape[0], batch_size):
            index = order[start : start + batch_size]
            loss = torch.mean((policy_mean(x[index]) - y[index]) ** 2)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            total += float(loss.detach()) * index.shape[0]
        losses.append(total / x.shape[0])
    policy_mean.train(False)
    if not all(np.isfinite(losses)):
        raise ValueError("imitation: the regression loss became nan or infinite")
    return losses


class FullObservations:
    """The raw full observation of the state each env of a ``VecEnv`` is in.

    Read from the innermost ``DummyVecEnv`` (``venv.unwrapped``): the ``full_observation`` that
    [`ObservationMask`][ermrl.envs.ObservationMask] puts into the step's (or, after an episode ended
    and the env reset, the reset's) info; without a mask, that ``DummyVecEnv``'s own observation,
    which is then the full one (the reservoir and ``VecNormalize`` wrap it from outside).

    Args:
        venv: The learner's ``VecEnv`` (any SB3 wrappers around a ``DummyVecEnv``).
    """

    def __init__(self, venv: Any) -> None:
        from stable_baselines3.common.vec_env import DummyVecEnv

        base = venv.unwrapped
        if not isinstance(base, DummyVecEnv):
            raise TypeError(f"imitation needs a DummyVecEnv inside, got {type(base).__name__}")
        self.base = base

    def _own(self, i: int) -> np.ndarray:
        # SB3 keys a non-dict observation space's buffer by None
        return np.array(self.base.buf_obs[None][i])  # type: ignore[index]

    def after_reset(self) -> np.ndarray:
        """Full observations ``(n_envs, obs_dim)`` after ``venv.reset()``."""
        return np.stack(
            [
                np.array(info[FULL_OBSERVATION_KEY])
                if FULL_OBSERVATION_KEY in info
                else self._own(i)
                for i, info in enumerate(self.base.reset_infos)
            ]
        )

    def after_step(self) -> np.ndarray:
        """Full observations ``(n_envs, obs_dim)`` after ``venv.step()`` (auto-resets included)."""
        rows = []
        for i in range(self.base.num_envs):
            info = self.base.reset_infos[i] if self.base.buf_dones[i] else self.base.buf_infos[i]
            rows.append(
                np.array(info[FULL_OBSERVATION_KEY])
                if FULL_OBSERVATION_KEY in info
                else self._own(i)
            )
        return np.stack(rows)


def hide_mixture_episodes(
    infos: Sequence[dict[str, Any]], dones: np.ndarray, episode_mixed: np.ndarray
) -> int:
    """Move the Monitor record of every finished episode the expert acted in out of the way.

    For each env ``e`` whose episode just ended (``dones[e]``) and in which a non-learner action
    was executed (``episode_mixed[e]``), ``infos[e]["episode"]`` becomes
    ``infos[e][MIXTURE_EPISODE_KEY]``, so readers of Monitor records (ermrl's training returns,
    SB3's episode statistics) see only learner-only episodes. ``episode_mixed`` is then cleared
    for every env whose episode ended (the next one starts learner-only).

    Args:
        infos: The step's infos, one dict per env (changed in place).
        dones: Which envs' episodes ended at this step, ``(E,)``.
        episode_mixed: Whether the expert acted in each env's current episode, ``(E,)`` bool
            (changed in place).

    Returns:
        The number of episode records hidden.
    """
    hidden = 0
    ended = np.asarray(dones, dtype=bool)
    for e in np.flatnonzero(ended & episode_mixed).tolist():
        if "episode" in infos[e]:
            infos[e][MIXTURE_EPISODE_KEY] = infos[e].pop("episode")
            hidden += 1
    episode_mixed[ended] = False
    return hidden


class LearnerOnlyEpisodes(VecEnvWrapper):
    """A ``VecEnv`` whose Monitor records are those of learner-only episodes.

    The agent calls `expert_acts` before each step with who executes the expert's action;
    after the step, `hide_mixture_episodes` hides the record of every episode that
    ended with at least one expert action in it. A reset starts every env learner-only.

    Args:
        venv: The learner's ``VecEnv``.
    """

    def __init__(self, venv: Any) -> None:
        super().__init__(venv)
        self.episode_mixed = np.zeros(self.num_envs, dtype=bool)
        self._pending = np.zeros(self.num_envs, dtype=bool)

    def expert_acts(self, by_expert: np.ndarray) -> None:
        """Record that the next step executes the expert's action in the envs of ``by_expert``
        (``(E,)`` bool)."""
        self._pending = np.asarray(by_expert, dtype=bool).reshape(self.num_envs).copy()

    def reset(self) -> Any:
        self.episode_mixed[:] = False
        self._pending[:] = False
        return self.venv.reset()

    def step_async(self, actions: np.ndarray) -> None:
        self.episode_mixed |= self._pending
        self._pending = np.zeros(self.num_envs, dtype=bool)
        self.venv.step_async(actions)

    def step_wait(self) -> Any:
        obs, rewards, dones, infos = self.venv.step_wait()
        hide_mixture_episodes(infos, dones, self.episode_mixed)
        return obs, rewards, dones, infos


@dataclass
class DaggerRollout:
    """What one DAgger rollout visited (``T`` steps of ``E`` envs, ``n = T * E`` rows).

    Attributes:
        observations: The learner's observations of the visited states, ``(n, obs_dim)``.
        full_observations: The raw full observations of the same states, ``(n, full_dim)``.
        expert_actions: The expert's deterministic action on each state (the label),
            ``(n, *action_shape)`` in env units.
        actions: The executed actions, ``(n, *action_shape)``.
        expert_executed: Whether the expert's action was the one executed, ``(n,)``.
        obs: The learner's observations after the last step, ``(E, obs_dim)`` (the next
            rollout starts there).
        full_obs: The full observations after the last step, ``(E, full_dim)``.
        stopped: A step hook asked to stop.
    """

    observations: np.ndarray
    full_observations: np.ndarray
    expert_actions: np.ndarray
    actions: np.ndarray
    expert_executed: np.ndarray
    obs: np.ndarray
    full_obs: np.ndarray
    stopped: bool = False

    @property
    def n_expert_executed(self) -> int:
        return int(np.count_nonzero(self.expert_executed))

    @property
    def n_learner_executed(self) -> int:
        return int(self.expert_executed.size - self.n_expert_executed)


def _mixture_action(
    space: spaces.Box,
    policy_mean: nn.Module | None,
    obs: np.ndarray,
    expert_action: np.ndarray,
    by_expert: np.ndarray,
) -> np.ndarray:
    """The actions the envs execute: the expert's where ``by_expert``, else the learner's.

    Args:
        space: The env's action space (Box).
        policy_mean: The learner (``None``: only the expert may act).
        obs: The learner's observations ``(E, obs_dim)``.
        expert_action: The expert's actions ``(E, *action_shape)``.
        by_expert: Whether the expert acts in each env, ``(E,)`` bool.

    Returns:
        Env actions ``(E, *action_shape)`` (a new array).

    Raises:
        ValueError: the learner should act somewhere but ``policy_mean`` is ``None``.
    """
    if by_expert.all() or policy_mean is None:
        if policy_mean is None and not by_expert.all():
            raise ValueError("dagger_rollout: beta < 1 needs a learner policy")
        return expert_action.copy()
    action = unscale_actions(space, _act(policy_mean, obs))
    action[by_expert] = expert_action[by_expert]
    return action


def dagger_rollout(
    venv: Any,
    policy_mean: nn.Module | None,
    expert: Any,
    beta: float,
    n_steps: int,
    rng: np.random.Generator,
    obs: np.ndarray,
    full_obs: np.ndarray,
    *,
    full: FullObservations | None = None,
    on_step: StepHook | None = None,
    episode_mixed: np.ndarray | None = None,
) -> DaggerRollout:
    """Roll out the mixture policy for ``n_steps`` steps of every env, labelling with the expert.

    At each step, env ``e`` executes the expert's action when ``rng.random(E)[e] < beta`` (one
    draw per env and step, nothing else is drawn from ``rng``), else the learner's
    (deterministic) action; the state is labelled with the expert's action either way.
    ``beta = 1`` is the expert's own rollout (behaviour cloning's data; ``policy_mean`` may then
    be ``None``).

    Args:
        venv: The learner's ``VecEnv`` (Box actions).
        policy_mean: The learner: observations -> scaled action means (`ImitationPolicy`).
        expert: Has ``predict(full_obs (E, full_dim)) -> actions (E, *action_shape)``.
        beta: Probability that the expert acts, in ``[0, 1]``.
        n_steps: Steps per env.
        rng: The source of the mixture's draws.
        obs: The learner's current observations ``(E, obs_dim)``.
        full_obs: The current full observations ``(E, full_dim)``.
        full: Reads the full observations after each step (default: built from ``venv``).
        on_step: Called after every step as ``on_step(infos, dones, rewards, actions)``;
            returning ``False`` ends the rollout early.
        episode_mixed: Whether the expert has acted in each env's current episode, ``(E,)``
            bool, carried across rollouts and updated in place; when given, the Monitor record
            of an episode the expert acted in is hidden (`hide_mixture_episodes`) before
            ``on_step`` sees the infos.

    Returns:
        The visited states, their labels and who acted (`DaggerRollout`).
    """
    full = full if full is not None else FullObservations(venv)
    space = venv.action_space
    n_envs = int(venv.num_envs)
    observations, fulls, labels, executed, who = [], [], [], [], []
    stopped = False
    for _ in range(n_steps):
        expert_action = np.asarray(expert.predict(full_obs, deterministic=True)).reshape(
            (n_envs, *space.shape)
        )
        by_expert = rng.random(n_envs) < beta
        action = _mixture_action(space, policy_mean, obs, expert_action, by_expert)
        observations.append(np.array(obs))
        fulls.append(np.array(full_obs))
        labels.append(expert_action)
        executed.append(action)
        who.append(by_expert)
        if episode_mixed is not None:
            episode_mixed |= by_expert
        obs, rewards, dones, infos = venv.step(action)
        full_obs = full.after_step()
        if episode_mixed is not None:
            hide_mixture_episodes(infos, dones, episode_mixed)
        if on_step is not None and not on_step(infos, dones, rewards, action):
            stopped = True
            break
    return DaggerRollout(
        observations=np.concatenate(observations),
        full_observations=np.concatenate(fulls),
        expert_actions=np.concatenate(labels),
        actions=np.concatenate(executed),
        expert_executed=np.concatenate(who),
        obs=np.asarray(obs),
        full_obs=full_obs,
        stopped=stopped,
    )
