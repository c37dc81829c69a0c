"""Population PPO: ``P`` agents trained in lockstep, with SB3 PPO's semantics per agent.

Every agent is what [`ermrl.agents.train_agent`][ermrl.agents.train_agent] trains with
``learner: ppo``: the same environments, seeds, reservoir, normalization, network and PPO update
(GAE with truncation bootstrapping, clipped objective, value loss, entropy bonus, advantage
normalization, Adam with eps 1e-5, gradient clipping, minibatches, epochs, linear schedules, gSDE).
What is shared is only the arithmetic: environments are stepped one after another, the reservoirs
and the policies of all agents run as stacked products, and all weights live in one flat ``[P, N]``
buffer (one row per agent) that one ``Adam`` steps in a few ops (Adam is elementwise, so that equals
one Adam per agent; the gradient clipping is per agent: one norm per row).

Each agent draws from its own random streams (weight initialization, action noise, gSDE
matrices, minibatch permutations), derived from its seed: its result does not depend on the size
of the population nor on its place in it. An agent whose training produces NaN is dropped (its
weights, optimizer state, envs and reservoir rows sliced away); the others go on.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import math
import sys
import time
import warnings
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import threadpoolctl
import torch
from gymnasium import spaces

from ermrl._code import code_identity, describe_code, same_code
from ermrl._interrupt import raise_swallowed_signal
from ermrl._io import write_atomic
from ermrl._progress import Progress
from ermrl.agents._train import NoEpisodeFinished, RunResult, TrainingDiverged, derive_seeds
from ermrl.config import BudgetConfig, ConfigError, EncoderConfig, PPOConfig, TaskConfig, to_dict
from ermrl.population._envs import PopulationEnvs
from ermrl.population._policy import PolicySpec, StackedAdam, StackedPolicy, policy_spec
from ermrl.population._tensorboard import PopulationLogs

__all__ = [
    "Checkpoint",
    "PopulationJob",
    "PopulationPPO",
    "check_population_config",
    "compute_gae",
    "train_population",
]

# SB3 PPO's defaults for the keys the population backend reads.
_DEFAULTS: dict[str, Any] = {
    "learning_rate": 3e-4,
    "n_steps": 2048,
    "batch_size": 64,
    "n_epochs": 10,
    "gamma": 0.99,
    "gae_lambda": 0.95,
    "clip_range": 0.2,
    "clip_range_vf": None,
    "normalize_advantage": True,
    "ent_coef": 0.0,
    "vf_coef": 0.5,
    "max_grad_norm": 0.5,
    "use_sde": False,
    "sde_sample_freq": -1,
    "target_kl": None,
    "policy_kwargs": None,
}


@dataclass(frozen=True)
class PopulationJob:
    """One agent of a population: its encoder (``None``: raw observation) and its seed."""

    encoder: EncoderConfig | None
    seed: int


def _settings(ppo: PPOConfig) -> dict[str, Any]:
    from ermrl.agents._hyperparams import ppo_kwargs

    kwargs = ppo_kwargs(ppo)
    unknown = sorted(set(kwargs) - set(_DEFAULTS))
    if unknown:
        raise ConfigError(
            f"the population backend does not implement PPO settings {unknown}; use --backend sb3"
        )
    if kwargs.get("target_kl") is not None:
        raise ConfigError(
            "the population backend does not implement target_kl (its early stop would differ "
            "per agent); use --backend sb3"
        )
    return {**_DEFAULTS, **kwargs}


def steps_trained(ppo: PPOConfig, steps: int) -> int:
    """The env steps each agent makes for a budget of ``steps``: whole rollouts of
    ``n_steps * n_envs``, as SB3's ``learn`` rounds up (a progress line's total); the same
    count as [`ermrl.agents.steps_trained`][ermrl.agents.steps_trained] for the sb3 backend."""
    from ermrl.agents._train import steps_trained as whole_rollouts

    return whole_rollouts(ppo, steps)


def check_population_config(ppo: PPOConfig) -> None:
    """Refuse settings the population backend cannot train as SB3 would, in one line.

    Raises:
        ConfigError: another learner than PPO, or an unimplemented PPO setting.
    """
    if ppo.learner != "ppo":
        raise ConfigError(
            f"the population backend trains the ppo learner only, not {ppo.learner!r}; "
            "use --backend sb3"
        )
    settings = _settings(ppo)
    try:
        policy_spec(settings["policy_kwargs"] or {}, 1, 1, False, bool(settings["use_sde"]))
    except ValueError as err:
        raise ConfigError(str(err)) from None


def compute_gae(
    rewards: np.ndarray,
    values: np.ndarray,
    episode_starts: np.ndarray,
    last_values: np.ndarray,
    dones: np.ndarray,
    gamma: float,
    gae_lambda: float,
) -> tuple[np.ndarray, np.ndarray]:
    """SB3's ``RolloutBuffer.compute_returns_and_advantage`` for every agent at once.

    ``delta_t = r_t + gamma * V_{t+1} * (1 - start_{t+1}) - V_t`` and
    ``A_t = delta_t + gamma * gae_lambda * (1 - start_{t+1}) * A_{t+1}``, where after the last
    step ``V`` is ``last_values`` and ``start`` is ``dones``. A truncated episode's bootstrap,
    ``gamma * V(last observation)``, is already in its last reward (as SB3 adds it in
    ``collect_rollouts``).

    Args:
        rewards: ``[P, n_steps, E]`` rewards (float32).
        values: ``[P, n_steps, E]`` values of the observations.
        episode_starts: ``[P, n_steps, E]``, 1 where the observation is an episode's first.
        last_values: ``[P, E]`` values of the observations after the last step.
        dones: ``[P, E]``, whether the last step ended an episode.
        gamma: Discount.
        gae_lambda: GAE's lambda.

    Returns:
        ``(advantages, returns)``, each ``[P, n_steps, E]`` float32; ``returns = advantages +
        values``.
    """
    n_steps = rewards.shape[1]
    adv = np.zeros(rewards.shape, np.float32)
    last_gae = np.zeros(last_values.shape, np.float32)
    for t in reversed(range(n_steps)):
        if t == n_steps - 1:
            non_terminal = 1.0 - dones.astype(np.float32)
            next_values = last_values
        else:
            non_terminal = 1.0 - episode_starts[:, t + 1]
            next_values = values[:, t + 1]
        delta = rewards[:, t] + gamma * next_values * non_terminal - values[:, t]
        last_gae = delta + gamma * gae_lambda * non_terminal * last_gae
        adv[:, t] = last_gae
    return adv, adv + values


CHECKPOINT_VERSION = 1


@dataclass(frozen=True)
class Checkpoint:
    """Where a population saves its training state, and how often
    ([`PopulationPPO.learn`][ermrl.population.PopulationPPO.learn]).

    The file is an ``.npz`` (no pickle): the weights, Adam's moments and the normalization
    statistics as arrays, the rest (steps, episodes so far, random streams, dropped agents) as
    JSON in its ``meta`` entry. It is written atomically at the end of an update, so a killed
    training leaves the last complete one. A training resumed from it goes on with the saved
    weights, optimizer, normalization and random streams, while its environments restart from
    fresh episodes (seeded anew): the episodes in progress at the save are not counted, so a
    resumed run is not bit for bit the uninterrupted one.

    Attributes:
        path: The file.
        every: Env steps per agent between saves (at least one rollout).
    """

    path: Path
    every: int

    def load(self, key: str) -> tuple[dict[str, Any], dict[str, np.ndarray]] | None:
        """``(meta, arrays)`` saved by the training ``key`` names, or ``None`` (no file, a file
        of another training, or an unreadable one: the training then starts over). ``meta``'s
        ``code`` names the code that saved it (`ermrl._code.code_identity`):
        [`PopulationPPO.learn`][ermrl.population.PopulationPPO.learn] resumes only a checkpoint of
        its own code."""
        try:
            with np.load(io.BytesIO(self.path.read_bytes()), allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                arrays = {name: data[name] for name in data.files if name != "meta"}
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return None  # torn or foreign (JSONDecodeError is a ValueError)
        if meta.get("version") != CHECKPOINT_VERSION or meta.get("key") != key:
            return None
        return meta, arrays

    def save(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        buffer = io.BytesIO()
        payload: dict[str, Any] = {"meta": np.asarray(json.dumps(meta)), **arrays}
        np.savez(buffer, **payload)
        write_atomic(self.path, buffer.getvalue())

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


@dataclass
class _Rollout:
    """One rollout of every agent: arrays ``[P, n_steps, E, ...]`` (SB3's ``RolloutBuffer``)."""

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    starts: np.ndarray
    values: np.ndarray
    log_probs: np.ndarray

    @classmethod
    def empty(
        cls, P: int, n_steps: int, E: int, obs_dim: int, spec: PolicySpec, discrete: bool
    ) -> _Rollout:
        """Zeros for ``P`` agents (actions: integers ``[P, n_steps, E]`` when ``discrete``,
        else ``[P, n_steps, E, spec.action_dim]``)."""
        return cls(
            obs=np.zeros((P, n_steps, E, obs_dim), np.float32),
            actions=np.zeros(
                (P, n_steps, E) if discrete else (P, n_steps, E, spec.action_dim),
                np.int64 if discrete else np.float32,
            ),
            rewards=np.zeros((P, n_steps, E), np.float32),
            starts=np.zeros((P, n_steps, E), np.float32),
            values=np.zeros((P, n_steps, E), np.float32),
            log_probs=np.zeros((P, n_steps, E), np.float32),
        )

    def keep(self, keep: np.ndarray) -> None:
        """Keep only the agents at positions ``keep``."""
        for f in dataclasses.fields(self):
            setattr(self, f.name, getattr(self, f.name)[keep])

    def store(self, step: int, *arrays: np.ndarray) -> None:
        """Store one step: ``obs, actions, rewards, starts, values, log_probs`` (``[P, E, ...]``)."""
        for f, a in zip(dataclasses.fields(self), arrays, strict=True):
            getattr(self, f.name)[:, step] = a


def _schedule(value: Any) -> Any:
    return value if callable(value) else (lambda _progress, v=float(value): v)


class PopulationPPO:
    """Train a population of PPO agents on one task in lockstep.

    Args:
        task: The task (all agents).
        ppo: PPO settings (all agents; ``learner`` must be ``ppo``).
        jobs: One [`PopulationJob`][ermrl.population.PopulationJob] per agent. Encoders must all be
            ``None`` or all share their structure (their reservoir hyperparameters may differ).
    """

    def __init__(self, task: TaskConfig, ppo: PPOConfig, jobs: Sequence[PopulationJob]) -> None:
        check_population_config(ppo)
        if not jobs:
            raise ValueError("a population needs at least one agent")
        with_encoder = {job.encoder is not None for job in jobs}
        if len(with_encoder) != 1:
            raise ValueError("the agents of a population must all have an encoder, or none")
        self.task, self.ppo, self.jobs = task, ppo, list(jobs)
        self.s = _settings(ppo)
        self.seeds = [derive_seeds(job.seed) for job in jobs]
        encoders = [job.encoder for job in jobs] if jobs[0].encoder is not None else None
        self.envs = PopulationEnvs(
            task,
            ppo.n_envs,
            [s.env for s in self.seeds],
            encoders,  # type: ignore[arg-type]
            [s.reservoir for s in self.seeds],
            ppo.normalize,
            float(self.s["gamma"]),
        )
        space = self.envs.action_space
        self.discrete = self.envs.discrete
        if isinstance(space, spaces.Discrete):
            action_dim = int(space.n)
        else:
            assert isinstance(space, spaces.Box)
            action_dim = int(np.prod(space.shape))
            self.low = np.asarray(space.low, np.float32)
            self.high = np.asarray(space.high, np.float32)
        self.spec = policy_spec(
            self.s["policy_kwargs"] or {},
            self.envs.policy_dim,
            action_dim,
            self.discrete,
            bool(self.s["use_sde"]),
        )
        # Each agent's streams: weight initialization (torch) and everything sampled (numpy).
        streams = [np.random.SeedSequence(s.agent).spawn(2) for s in self.seeds]
        init_seeds = [int(a.generate_state(1, dtype=np.uint64)[0] >> 1) for a, _ in streams]
        self.rngs = [np.random.default_rng(b) for _, b in streams]
        self.policy = StackedPolicy(self.spec, init_seeds)
        self.lr = _schedule(self.s["learning_rate"])
        self.clip_range = _schedule(self.s["clip_range"])
        self.clip_range_vf = (
            None if self.s["clip_range_vf"] is None else _schedule(self.s["clip_range_vf"])
        )
        self.optimizer = StackedAdam(self.policy.flat, self.lr(1.0), eps=1e-5)
        self.alive = list(range(len(jobs)))  # position in the arrays -> job index
        self.failed: dict[int, BaseException] = {}
        self.episodes: list[list[tuple[float, int]]] = [[] for _ in jobs]
        self.episode_lengths: list[list[int]] = [[] for _ in jobs]  # read by TensorBoard logs
        self.num_timesteps = 0
        self.timings = {"env": 0.0, "reservoir": 0.0, "policy": 0.0, "update": 0.0, "total": 0.0}
        self.resumed_at = 0  # env steps per agent restored from a checkpoint
        self.wall_before = 0.0  # wall seconds of the training before its checkpoint
        self._sde: np.ndarray | None = None

    @property
    def n_agents(self) -> int:
        return len(self.alive)

    # -- dropping agents -----------------------------------------------------------------------
    def _drop(self, positions: Sequence[int], reason: str) -> np.ndarray:
        """Drop the agents at ``positions``; returns the kept positions."""
        bad = set(positions)
        for pos in bad:
            job = self.alive[pos]
            self.failed[job] = TrainingDiverged(f"seed {self.jobs[job].seed}: {reason}")
        keep = np.asarray([i for i in range(self.n_agents) if i not in bad], np.int64)
        self.alive = [self.alive[i] for i in keep]
        self.rngs = [self.rngs[i] for i in keep]
        self.envs.keep(keep)
        if self._sde is not None:
            self._sde = self._sde[keep]
        index = torch.from_numpy(keep)
        self.policy.keep(index)
        self.optimizer = self.optimizer.keep(index, self.policy.flat)
        return keep

    # -- checkpoints ---------------------------------------------------------------------------
    def checkpoint_key(self, total_timesteps: int) -> str:
        """A digest of what this training is: task, settings, budget, and each agent's seed and
        encoder (a checkpoint is resumed only by the same training)."""
        doc = {
            "task": to_dict(self.task),
            "ppo": to_dict(self.ppo),
            "total_timesteps": int(total_timesteps),
            "jobs": [[job.seed, to_dict(job.encoder)] for job in self.jobs],
        }
        text = json.dumps(doc, sort_keys=True, default=repr)
        return hashlib.sha256(text.encode()).hexdigest()

    def _state(self, key: str, elapsed: float) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The checkpoint of this moment, ``elapsed`` seconds into the current
        [`learn`][ermrl.population.PopulationPPO.learn]."""
        timings = {
            **self.timings,
            "env": self.envs.env_seconds,
            "reservoir": self.envs.reservoir_seconds,
            "total": self.timings["total"] + elapsed,
        }
        meta = {
            "version": CHECKPOINT_VERSION,
            "key": key,
            "code": code_identity(),
            "num_timesteps": self.num_timesteps,
            "alive": self.alive,
            "failed": {str(j): str(err) for j, err in self.failed.items()},
            "episodes": self.episodes,
            "rngs": [rng.bit_generator.state for rng in self.rngs],
            "adam_steps": self.optimizer.steps,
            "timings": timings,
            "wall_seconds": self.wall_before + elapsed,
        }
        arrays = {
            "flat": self.policy.flat.numpy(),
            "exp_avg": self.optimizer.exp_avg.numpy(),
            "exp_avg_sq": self.optimizer.exp_avg_sq.numpy(),
        }
        for name in ("obs_rms", "ret_rms"):
            rms = getattr(self.envs, name)
            if rms is not None:
                for part, value in zip(("mean", "var", "count"), rms.state()):
                    arrays[f"{name}.{part}"] = value
        return meta, arrays

    def _restore(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        alive = set(meta["alive"])
        dropped = [pos for pos, job in enumerate(self.alive) if job not in alive]
        if dropped:
            self._drop(dropped, "dropped before the checkpoint")
        self.failed = {int(j): TrainingDiverged(text) for j, text in meta["failed"].items()}
        with torch.no_grad():
            self.policy.flat.copy_(torch.from_numpy(arrays["flat"]))
            self.optimizer.exp_avg.copy_(torch.from_numpy(arrays["exp_avg"]))
            self.optimizer.exp_avg_sq.copy_(torch.from_numpy(arrays["exp_avg_sq"]))
        self.optimizer.steps = int(meta["adam_steps"])
        for rng, state in zip(self.rngs, meta["rngs"]):
            rng.bit_generator.state = state
        self.episodes = [[(float(r), int(t)) for r, t in runs] for runs in meta["episodes"]]
        self.num_timesteps = self.resumed_at = int(meta["num_timesteps"])
        for name in ("obs_rms", "ret_rms"):
            rms = getattr(self.envs, name)
            if rms is not None:
                rms.load_state([arrays[f"{name}.{part}"] for part in ("mean", "var", "count")])
        self.timings = {k: float(v) for k, v in meta["timings"].items()}
        self.envs.env_seconds = self.timings["env"]
        self.envs.reservoir_seconds = self.timings["reservoir"]
        self.wall_before = float(meta["wall_seconds"])

    # -- rollouts ------------------------------------------------------------------------------
    def _reset_noise(self) -> None:
        std = np.exp(self.policy.np["log_std"])  # [P, L, A]
        E = self.envs.n_envs
        self._sde = np.stack(
            [
                rng.standard_normal((E, *std.shape[1:]), dtype=np.float32) * std[p]
                for p, rng in enumerate(self.rngs)
            ]
        )

    def _act(
        self, obs: np.ndarray, deterministic: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(actions, values, log_probs)`` for observations ``[P, E, d]``."""
        latent, head, values = self.policy.forward_np(obs)
        P, E = obs.shape[:2]
        if self.discrete:
            logits = head - head.max(-1, keepdims=True)
            logp = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
            if deterministic:
                actions = head.argmax(-1)
            else:
                u = np.stack([rng.random(E) for rng in self.rngs])
                cdf = np.cumsum(np.exp(logp), -1)
                actions = np.minimum((cdf < u[..., None]).sum(-1), head.shape[-1] - 1)
            log_probs = np.take_along_axis(logp, actions[..., None], -1)[..., 0]
            return actions, values, log_probs
        if deterministic:
            return head, values, np.zeros((P, E), np.float32)
        if self.spec.use_sde:
            assert self._sde is not None
            noise = np.matmul(latent[:, :, None, :], self._sde)[:, :, 0, :]
            std2 = np.exp(2.0 * self.policy.np["log_std"])
            var = np.matmul(np.square(latent), std2) + np.float32(1e-6)
            actions = head + noise
            log_probs = (-0.5 * np.square(noise) / var - 0.5 * np.log(var)).sum(-1)
        else:
            eps = np.stack(
                [rng.standard_normal((E, head.shape[-1]), dtype=np.float32) for rng in self.rngs]
            )
            log_std = self.policy.np["log_std"][:, None, :]
            actions = head + np.exp(log_std) * eps
            log_probs = (-0.5 * np.square(eps) - log_std).sum(-1)
        log_probs = log_probs - np.float32(0.5 * math.log(2 * math.pi) * head.shape[-1])
        return actions, values, log_probs

    def _clip(self, actions: np.ndarray) -> np.ndarray:
        return actions if self.discrete else np.clip(actions, self.low, self.high)

    # -- training ------------------------------------------------------------------------------
    def learn(
        self,
        total_timesteps: int,
        progress: Progress | None = None,
        checkpoint: Checkpoint | None = None,
        logs: PopulationLogs | None = None,
    ) -> None:
        """Train every agent for ``total_timesteps`` env steps (whole rollouts, as SB3);
        ``progress`` is told each agent's env steps as they go, and closed at the end.

        With ``logs``, each run's rollout and update scalars are written after each update, as
        SB3 logs them for one run ([`PopulationLogs`][ermrl.population.PopulationLogs]).

        With ``checkpoint``, the training first resumes from the checkpoint's file if that holds
        this training's state ([`checkpoint_key`][ermrl.population.PopulationPPO.checkpoint_key];
        see [`Checkpoint`][ermrl.population.Checkpoint] for what resuming keeps), then saves its
        state there every ``checkpoint.every`` env steps per agent. The file is left in place at the
        end (the caller removes it once the results are safe).
        """
        start = time.perf_counter()
        key = self.checkpoint_key(total_timesteps)
        if checkpoint is not None:
            self._resume(checkpoint, key, progress)
        obs = self.envs.reset(seed_offset=self.num_timesteps)
        starts = np.ones((self.n_agents, self.envs.n_envs), np.float32)
        last_saved = self.num_timesteps
        while self.num_timesteps < total_timesteps and self.n_agents:
            raise_swallowed_signal()  # a Ctrl-C or SIGTERM that a weakref callback dropped
            obs, starts, dones, rollout = self._collect_rollout(obs, starts, progress)
            if not self.n_agents:
                break
            remaining = 1.0 - float(self.num_timesteps) / float(total_timesteps)
            kept = self._update_rollout(rollout, obs, dones, remaining, logs, start)
            if kept is not None:  # agents whose weights became NaN were dropped
                obs, starts = obs[kept], starts[kept]
            if (
                checkpoint is not None
                and self.n_agents
                and self.num_timesteps < total_timesteps
                and self.num_timesteps - last_saved >= checkpoint.every
            ):
                checkpoint.save(*self._state(key, time.perf_counter() - start))
                last_saved = self.num_timesteps
        self.timings["env"] = self.envs.env_seconds
        self.timings["reservoir"] = self.envs.reservoir_seconds
        self.timings["total"] += time.perf_counter() - start
        if progress is not None:
            progress.close()

    def _resume(self, checkpoint: Checkpoint, key: str, progress: Progress | None) -> None:
        """Restore this training's state from ``checkpoint``'s file, if it holds it and was
        saved by this code (a line says so, or why it was not resumed)."""
        saved = checkpoint.load(key)
        if saved is None:
            return
        if not same_code(saved[0].get("code")):
            # The same training by other code: its state may not mean what this code reads.
            line = (
                f"not resumed: {checkpoint.path} was saved by other code "
                f"({describe_code(saved[0].get('code'))}; this is "
                f"{describe_code(code_identity())}): training from the start"
            )
            if progress is not None:
                progress.message(line)
            else:
                print(line, file=sys.stderr, flush=True)
            return
        self._restore(*saved)
        if progress is not None:
            progress.message(f"resumed from {checkpoint.path} at {self.num_timesteps:,} steps each")

    def _collect_rollout(
        self, obs: np.ndarray, starts: np.ndarray, progress: Progress | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, _Rollout]:
        """One rollout of ``n_steps`` steps of every agent's envs (SB3's ``collect_rollouts``),
        from observations ``obs`` ``[P, E, d]`` and episode starts ``starts`` ``[P, E]``. An
        agent whose actions or values are not finite is dropped on the way.

        Returns:
            ``(obs, starts, dones, rollout)`` after the last step, for the agents still alive.
        """
        s, E = self.s, self.envs.n_envs
        n_steps, use_sde, freq = int(s["n_steps"]), self.spec.use_sde, int(s["sde_sample_freq"])
        P = self.n_agents
        rollout = _Rollout.empty(P, n_steps, E, self.envs.policy_dim, self.spec, self.discrete)
        if use_sde:
            self._reset_noise()
        dones = np.zeros((P, E), bool)
        for step in range(n_steps):
            if use_sde and freq > 0 and step % freq == 0:
                self._reset_noise()
            t0 = time.perf_counter()
            actions, values, log_probs = self._act(obs)
            self.timings["policy"] += time.perf_counter() - t0
            P = self.n_agents
            bad = ~np.isfinite(actions.reshape(P, -1)).all(1) | ~np.isfinite(values).all(1)
            if bad.any():
                keep = self._drop(np.flatnonzero(bad).tolist(), "training diverged (NaN)")
                obs, starts, dones = obs[keep], starts[keep], dones[keep]
                actions, values, log_probs = actions[keep], values[keep], log_probs[keep]
                rollout.keep(keep)
                if not self.n_agents:
                    break
            new_obs, rewards, dones = self._step_envs(actions, progress)
            rollout.store(step, obs, actions, rewards, starts, values, log_probs)
            obs, starts = new_obs, dones.astype(np.float32)
        return obs, starts, dones, rollout

    def _step_envs(
        self, actions: np.ndarray, progress: Progress | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Step every env once with ``actions``; record the episodes that ended and bootstrap
        truncated ones from their last state's value. Returns ``(obs, rewards, dones)``."""
        new_obs, rewards, _, dones, terminal, finished = self.envs.step(self._clip(actions))
        self.num_timesteps += self.envs.n_envs
        if progress is not None:
            progress.update(self.num_timesteps)
        for p, _, ret, length in finished:
            self.episodes[self.alive[p]].append((ret, self.num_timesteps))
            self.episode_lengths[self.alive[p]].append(length)
        rewards = rewards.astype(np.float32)
        if terminal:
            keys = list(terminal)
            agents = np.asarray([p for p, _ in keys])
            t0 = time.perf_counter()
            boot = self.policy.values_np(np.stack([terminal[k] for k in keys]), agents)
            self.timings["policy"] += time.perf_counter() - t0
            for (p, i), v in zip(keys, boot):
                rewards[p, i] += float(self.s["gamma"]) * v
        return new_obs, rewards, dones

    def _update_rollout(
        self,
        rollout: _Rollout,
        obs: np.ndarray,
        dones: np.ndarray,
        remaining: float,
        logs: PopulationLogs | None,
        start: float,
    ) -> np.ndarray | None:
        """GAE on ``rollout`` (bootstrapped from the values of ``obs`` where not ``dones``),
        then the PPO update at ``remaining`` progress, and its scalars to ``logs``.

        Returns:
            The kept positions when agents were dropped (``None``: none dropped).
        """
        gamma, lam = float(self.s["gamma"]), float(self.s["gae_lambda"])
        t0 = time.perf_counter()
        _, _, last_values = self.policy.forward_np(obs)
        adv, returns = compute_gae(
            rollout.rewards, rollout.values, rollout.starts, last_values, dones, gamma, lam
        )
        self.timings["policy"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        logging = logs is not None and logs.wants_losses()
        self.policy.loss_terms = [] if logging else None
        alive_before = list(self.alive)
        kept = self._train(
            remaining, rollout.obs, rollout.actions, rollout.values, rollout.log_probs, adv,
            returns,
        )  # fmt: skip
        self.timings["update"] += time.perf_counter() - t0
        if logging:
            assert logs is not None
            elapsed = max(time.perf_counter() - start, 1e-9)
            scalars = self._train_scalars(remaining, rollout.values, returns)
            if kept is not None:  # the dropped agents log nothing more
                alive_before = [alive_before[int(k)] for k in kept]
                scalars = {k: np.asarray(v)[kept] for k, v in scalars.items()}
            logs.write(
                self.num_timesteps,
                alive_before,
                self.episodes,
                self.episode_lengths,
                (self.num_timesteps - self.resumed_at) / elapsed,
                scalars,
            )
            self.policy.loss_terms = None
        return kept

    def _train_scalars(
        self, progress: float, values: np.ndarray, returns: np.ndarray
    ) -> dict[str, Any]:
        """The last update's ``train/*`` scalars per position, as SB3's ``PPO.train`` logs
        them: the loss terms' means over every minibatch (``approx_kl`` over the last epoch's,
        ``loss`` the last minibatch's), the explained variance of the rollout's values
        ``[P, ...]``, the learning rate, the clip range and the policy's mean std."""
        terms = self.policy.loss_terms or []
        if not terms:
            return {}
        per_epoch = max(len(terms) // int(self.s["n_epochs"]), 1)
        out: dict[str, Any] = {
            name: np.mean([t[name] for t in terms], axis=0)
            for name in ("policy_gradient_loss", "entropy_loss", "value_loss", "clip_fraction")
        }
        out["approx_kl"] = np.mean([t["approx_kl"] for t in terms[-per_epoch:]], axis=0)
        last = terms[-1]
        out["loss"] = (
            last["policy_gradient_loss"]
            + float(self.s["ent_coef"]) * last["entropy_loss"]
            + float(self.s["vf_coef"]) * last["value_loss"]
        )
        P = len(out["loss"])
        flat_v, flat_r = values.reshape(P, -1), returns.reshape(P, -1)
        var_r = flat_r.var(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            # SB3's explained_variance: nan where the returns do not vary.
            out["explained_variance"] = np.where(
                var_r == 0, np.nan, 1 - (flat_r - flat_v).var(1) / var_r
            )
        out["learning_rate"] = np.full(P, float(self.lr(progress)))
        out["clip_range"] = np.full(P, float(self.clip_range(progress)))
        if "log_std" in self.policy.params:
            log_std = self.policy.params["log_std"].detach().numpy().reshape(P, -1)
            out["std"] = np.exp(log_std).mean(1)
        return out

    def _train(
        self,
        progress: float,
        obs: np.ndarray,
        actions: np.ndarray,
        values: np.ndarray,
        log_probs: np.ndarray,
        advantages: np.ndarray,
        returns: np.ndarray,
    ) -> np.ndarray | None:
        """SB3 ``PPO.train`` on every agent's rollout (arrays ``[P, n_steps, E, ...]``); returns
        the kept positions when agents were dropped."""
        P = self.n_agents

        def flat(a: np.ndarray) -> np.ndarray:
            # SB3's swap_and_flatten: env-major order, index = env * n_steps + step.
            a = np.swapaxes(a, 1, 2)
            return np.ascontiguousarray(a.reshape(P, -1, *a.shape[3:]))

        data = [flat(a) for a in (obs, actions, values, log_probs, advantages, returns)]
        return self.update(progress, *data, permutations=None)

    def update(
        self,
        progress: float,
        obs: npt.ArrayLike,
        actions: npt.ArrayLike,
        old_values: npt.ArrayLike,
        old_log_probs: npt.ArrayLike,
        advantages: npt.ArrayLike,
        returns: npt.ArrayLike,
        *,
        permutations: Sequence[np.ndarray] | None = None,
    ) -> np.ndarray | None:
        """The PPO update on flattened rollouts ``[P, T, ...]`` (numpy arrays or CPU tensors);
        an agent whose weights became NaN is dropped, and the kept positions are returned
        (``None``: none dropped).

        Args:
            progress: SB3's ``progress_remaining`` (1 at the start, 0 at the end).
            permutations: The minibatch orders, one ``[P, T]`` array per epoch (default: each
                agent's own stream draws them, as SB3 draws ``np.random.permutation``).
        """
        s = self.s
        obs_np = np.asarray(obs, np.float32)
        P, T = obs_np.shape[:2]
        lr = float(self.lr(progress))
        self.optimizer.lr = lr
        clip = float(self.clip_range(progress))
        clip_vf = None if self.clip_range_vf is None else float(self.clip_range_vf(progress))
        batch_size, n_epochs = int(s["batch_size"]), int(s["n_epochs"])
        ent_coef, vf_coef = float(s["ent_coef"]), float(s["vf_coef"])
        max_norm = float(s["max_grad_norm"])
        rows = np.arange(P)[:, None]
        # One [P, T, D] table of everything a minibatch reads, shuffled once per epoch (one
        # gather instead of six per minibatch); minibatches are then slices of it.
        act = np.asarray(actions).astype(np.float32).reshape(P, T, -1)
        d_obs, d_act = obs_np.shape[2], act.shape[2]
        columns = (old_values, old_log_probs, advantages, returns)
        table = np.concatenate(
            [obs_np, act, *(np.asarray(t, np.float32)[..., None] for t in columns)], axis=2
        )
        for epoch in range(n_epochs):
            if permutations is None:
                perm = np.stack([rng.permutation(T) for rng in self.rngs])
            else:
                perm = np.asarray(permutations[epoch])
            shuffled = table[rows, perm]
            for begin in range(0, T, batch_size):
                batch = shuffled[:, begin : begin + batch_size]
                b_act = batch[..., d_obs : d_obs + d_act]
                if self.discrete:
                    b_act = b_act[..., 0].astype(np.int64)
                b_oldv, b_oldlp, b_adv, b_ret = np.moveaxis(batch[..., d_obs + d_act :], -1, 0)
                flat = self.policy.ppo_gradient(
                    batch[..., :d_obs],
                    b_act,
                    b_oldv,
                    b_oldlp,
                    b_adv,
                    b_ret,
                    clip_range=clip,
                    clip_range_vf=clip_vf,
                    ent_coef=ent_coef,
                    vf_coef=vf_coef,
                    normalize_advantage=bool(s["normalize_advantage"]),
                )
                grad = torch.from_numpy(flat)
                # Per-agent clip_grad_norm_ (SB3 clips each agent's whole gradient): one norm per
                # row, reduced along a contiguous row, so in the same order for any P.
                total = torch.linalg.vector_norm(grad, dim=1, keepdim=True)
                grad.mul_(torch.clamp(max_norm / (total + 1e-6), max=1.0))
                self.optimizer.step(grad)
        finite = torch.isfinite(self.policy.flat).all(1)
        if not bool(finite.all()):
            return self._drop(
                torch.nonzero(~finite).flatten().tolist(), "training diverged (NaN weights)"
            )
        return None

    # -- evaluation and export -----------------------------------------------------------------
    def evaluate(self, n_episodes: int) -> dict[int, list[float]]:
        """Deterministic episodes on each surviving agent's separate evaluation env (seeded with
        its ``eval_env`` seed, its training's final normalization frozen): job -> returns."""
        jobs = [self.jobs[j] for j in self.alive]
        frozen = None
        if self.ppo.normalize is not None:
            frozen = [self.envs.normalize_stats(p) for p in range(self.n_agents)]
        env = PopulationEnvs(
            self.task,
            1,
            [self.seeds[j].eval_env for j in self.alive],
            [job.encoder for job in jobs] if jobs[0].encoder is not None else None,  # type: ignore[misc]
            [self.seeds[j].reservoir for j in self.alive],
            self.ppo.normalize,
            float(self.s["gamma"]),
            frozen_stats=frozen,
        )
        out: dict[int, list[float]] = {j: [] for j in self.alive}
        try:
            obs = env.reset()
            while any(len(v) < n_episodes for v in out.values()):
                actions, _, _ = self._act(obs, deterministic=True)
                obs, _, _, _, _, finished = env.step(self._clip(actions))
                for p, _, ret, _ in finished:
                    job = self.alive[p]
                    if len(out[job]) < n_episodes:
                        out[job].append(ret)
        finally:
            env.close()
        return out

    def export(self, position: int, model_path: str | Path) -> None:
        """Save an agent as the SB3 path saves one: ``model.zip``, ``policy.pt`` and, with
        normalization, its statistics (so replays, videos and reports read it unchanged)."""
        from ermrl.agents._normalize import frozen_normalize_env
        from ermrl.agents._train import make_vec_env, save_trained
        from ermrl.learners import get_learner

        job = self.jobs[self.alive[position]]
        seeds = self.seeds[self.alive[position]]
        learner = get_learner(self.ppo.learner)
        venv = make_vec_env(self.task, 1, seeds.env, job.encoder, seeds.reservoir)
        stats = None
        if self.ppo.normalize is not None:
            stats = self.envs.normalize_stats(position)
            venv = frozen_normalize_env(venv, stats)
        try:
            with warnings.catch_warnings():
                # The model only carries the trained weights, on one env: SB3's warning that
                # n_steps x 1 env is not a multiple of batch_size concerns a training it never does.
                warnings.filterwarnings(
                    "ignore", message="You have specified a mini-batch size", category=UserWarning
                )
                model = learner.build(venv, self.ppo, seed=seeds.agent)
            model.policy.load_state_dict(self.policy.sb3_state(position))
            model.num_timesteps = self.num_timesteps
            save_trained(model, model_path, stats)
        finally:
            venv.close()

    def close(self) -> None:
        self.envs.close()


def train_population(
    task: TaskConfig,
    ppo: PPOConfig,
    budget: BudgetConfig,
    jobs: Sequence[PopulationJob],
    *,
    evaluate: bool | None = None,
    model_paths: Sequence[str | Path | None] | None = None,
    progress: Progress | None = None,
    checkpoints: str | Path | None = None,
    checkpoint_every: int | None = None,
    tensorboard_logs: Sequence[str | Path | None] | None = None,
) -> list[RunResult | BaseException]:
    """Train ``jobs`` as one population in this process; one result per job, in order.

    A job whose training diverged or finished no episode (with the ``last`` measure) gets the
    exception [`train_agent`][ermrl.agents.train_agent] would have raised, instead of a result; the
    other jobs are unaffected. Each result's ``wall_seconds`` is its share of the population's wall
    time (the wall time over the number of agents) and ``timings`` the population's breakdown
    (``env``, ``reservoir``, ``policy``, ``update``, ``total`` seconds, for all agents together).

    Args:
        task: The task of every job.
        ppo: PPO settings of every job.
        budget: Training steps and fitness measure.
        jobs: The agents.
        evaluate: Run deterministic evaluation episodes (default: with the ``eval`` measure).
        model_paths: Per job, where to save the trained agent (``None``: not saved).
        progress: Told the env steps each agent has made (see `ermrl._progress.Progress`).
        checkpoints: A folder where the training saves its state
            ([`Checkpoint`][ermrl.population.Checkpoint], a file named by
            [`PopulationPPO.checkpoint_key`][ermrl.population.PopulationPPO.checkpoint_key]) and
            from which a rerun of the same training resumes; the file is removed once the results
            are returned. ``None``: no checkpoints.
        checkpoint_every: Env steps per agent between saves (default: a tenth of the budget).
        tensorboard_logs: Per job, a folder for its TensorBoard logs (SB3's
            ``tensorboard_log``: the scalars SB3's PPO logs, in ``<folder>/PPO_1``), or
            ``None``; needs the ``tensorboard`` package.
    """
    torch.set_num_threads(ppo.torch_threads)
    threadpoolctl.threadpool_limits(ppo.torch_threads)
    start = time.perf_counter()
    population = PopulationPPO(task, ppo, jobs)
    checkpoint = None
    if checkpoints is not None:
        key = population.checkpoint_key(budget.training_steps)
        every = checkpoint_every or max(budget.training_steps // 10, 1)
        checkpoint = Checkpoint(Path(checkpoints) / f"population-{key[:16]}.npz", every)
    logs = None
    if tensorboard_logs is not None and any(t is not None for t in tensorboard_logs):
        logs = PopulationLogs(tensorboard_logs)
    try:
        population.learn(budget.training_steps, progress, checkpoint, logs)
        eval_returns: dict[int, list[float]] = {}
        if (evaluate if evaluate is not None else budget.fitness == "eval") and population.n_agents:
            eval_returns = population.evaluate(budget.n_eval_episodes)
        if model_paths is not None:
            for pos, index in enumerate(population.alive):
                path = model_paths[index]
                if path is not None:
                    population.export(pos, path)
    finally:
        population.close()
        if logs is not None:
            logs.close()
    wall = time.perf_counter() - start + population.wall_before
    results = [
        _job_result(population, j, task, budget, wall / len(jobs), eval_returns.get(j))
        for j in range(len(jobs))
    ]
    if checkpoint is not None:
        checkpoint.remove()
    return results


def _job_result(
    population: PopulationPPO,
    j: int,
    task: TaskConfig,
    budget: BudgetConfig,
    wall_seconds: float,
    eval_returns: Sequence[float] | None,
) -> RunResult | BaseException:
    """Job ``j``'s result in a trained ``population`` (with its ``wall_seconds`` share and its
    evaluation returns, ``None``: not evaluated), or the exception
    [`train_agent`][ermrl.agents.train_agent] would have raised for it."""
    job = population.jobs[j]
    if j in population.failed:
        return population.failed[j]
    episodes = population.episodes[j]
    result = RunResult(
        seed=job.seed,
        episode_returns=[r for r, _ in episodes],
        episode_steps=[s for _, s in episodes],
        env_steps=population.num_timesteps,
        wall_seconds=wall_seconds,
        timings=dict(population.timings),
    )
    if not all(math.isfinite(r) for r in result.episode_returns):
        return TrainingDiverged(f"seed {job.seed}: non-finite episode return")
    if result.episode_returns:
        result.last_return = float(np.mean(result.episode_returns[-budget.n_last_episodes :]))
    elif budget.fitness == "last":
        return NoEpisodeFinished(
            f"seed {job.seed}: no episode of {task.env_id} ended within "
            f"{budget.training_steps} training steps; raise --training-steps or use "
            "--fitness eval"
        )
    if eval_returns is not None:
        result.eval_returns = [float(r) for r in eval_returns]
        result.eval_return = float(np.mean(result.eval_returns))
    return result
