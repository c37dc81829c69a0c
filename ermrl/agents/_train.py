"""Train one PPO agent on one seed: the inner loop ("development") of ER-MRL.

The environment pipeline is ``gym.make -> ObservationMask -> Monitor -> DummyVecEnv ->
ReservoirVecEnv -> VecNormalize`` (the reservoir only for reservoir agents, ``VecNormalize`` only
when the PPO settings say ``normalize``), so episode returns are always the task's raw returns.
"""

from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import threadpoolctl

from ermrl._interrupt import raise_swallowed_signal
from ermrl._progress import Progress
from ermrl.agents._checkpoint import (
    RunCheckpoint,
    can_checkpoint,
    saver_callback,
)
from ermrl.agents._wandb import WandbRun
from ermrl.config import BudgetConfig, EncoderConfig, PPOConfig, TaskConfig

__all__ = [
    "SeedSet",
    "derive_seeds",
    "make_vec_env",
    "RunResult",
    "TrainingDiverged",
    "NoEpisodeFinished",
    "train_agent",
    "steps_trained",
]

ReportFn = Callable[[int, float], None]


class TrainingDiverged(RuntimeError):
    """Training produced NaN or infinite values (the trial fails; the study goes on)."""


class NoEpisodeFinished(RuntimeError):
    """No training episode ended within the budget, so the ``last`` fitness is undefined."""


@dataclass(frozen=True)
class SeedSet:
    """Independent seeds derived from one integer seed.

    Attributes:
        reservoir: Seed of the reservoir weights.
        env: Seed of the training environments (env ``i`` gets ``env + i``).
        agent: Seed of PPO (policy initialization, action sampling, minibatch order).
        eval_env: Seed of the separate evaluation environment.
    """

    reservoir: int
    env: int
    agent: int
    eval_env: int


def steps_trained(ppo: PPOConfig, steps: int) -> int:
    """The env steps a run of ``ppo``'s learner makes for a budget of ``steps``.

    SB3's on-policy algorithms (PPO, RecurrentPPO and ermrl's PPO variants) collect whole
    rollouts of ``n_steps * n_envs`` steps and stop after the one that reaches the budget, so
    the budget rounds up to a whole number of rollouts; other learners train ``steps``.

    Examples:
        >>> from ermrl.config import PPOConfig
        >>> steps_trained(PPOConfig(n_envs=1, hyperparams={"n_steps": 2048}), 3000)
        4096
    """
    import inspect

    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

    from ermrl.learners import get_learner

    algorithm = get_learner(ppo.learner).algorithm()
    if not (isinstance(algorithm, type) and issubclass(algorithm, OnPolicyAlgorithm)):
        return int(steps)
    n_steps = ppo.hyperparams.get("n_steps")
    if n_steps is None:
        n_steps = inspect.signature(algorithm).parameters["n_steps"].default
    rollout = max(int(n_steps) * max(ppo.n_envs, 1), 1)
    return -(-int(steps) // rollout) * rollout


def derive_seeds(seed: int) -> SeedSet:
    """Split one seed into independent seeds for weights, envs and the agent."""
    if seed < 0:
        raise ValueError(f"seeds must be >= 0, got {seed}")
    children = np.random.SeedSequence(seed).spawn(4)
    values = [int(c.generate_state(1, dtype=np.uint32)[0] % (2**31 - 1)) for c in children]
    return SeedSet(*values)


def make_vec_env(
    task: TaskConfig,
    n_envs: int,
    env_seed: int,
    encoder: EncoderConfig | None = None,
    reservoir_seed: int = 0,
    render_mode: str | None = None,
) -> Any:
    """Build the (optionally reservoir-encoded) vectorized environment of a task.

    Args:
        task: Env id and observation mask.
        n_envs: Number of environments in the ``DummyVecEnv``.
        env_seed: Env ``i`` is seeded with ``env_seed + i`` at its first reset.
        encoder: Reservoir encoding, or ``None`` for the raw (masked) observation.
        reservoir_seed: Seed of the reservoir weights.
        render_mode: Passed to ``gymnasium.make``.

    Returns:
        A ``VecEnv`` (a [`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv] when ``encoder`` is
        given).
    """
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    from ermrl.encoders import encoder_for
    from ermrl.envs import make_env

    def factory() -> Any:
        return Monitor(make_env(task.env_id, task.observe, render_mode=render_mode))

    venv = DummyVecEnv([factory] * n_envs)
    venv.seed(env_seed)
    if encoder is not None:
        venv = encoder_for(encoder).wrap_env(venv, encoder, reservoir_seed)
    return venv


@dataclass
class RunResult:
    """What one training run produced.

    Attributes:
        seed: The run's seed.
        episode_returns: Return of every finished training episode, in order.
        episode_steps: Training env step at which each of those episodes ended.
        env_steps: Environment steps actually taken (PPO rounds up to whole rollouts).
        wall_seconds: Wall-clock time of training (and evaluation).
        last_return: Mean return of the last ``n_last_episodes`` training episodes.
        eval_return: Mean return of the deterministic evaluation episodes (if run).
        eval_returns: The evaluation episodes' returns.
        timings: Where the time went, in seconds (the population backend's ``env``,
            ``reservoir``, ``policy``, ``update`` and ``total``, for its whole population).
        checkpoint_returns: ``(env_step, mean evaluation return)`` of each evaluation during
            training (``train_agent(eval_at=...)``), in step order; empty when none was asked.
        phase_steps: The learner's own split of its env steps (the trained model's
            ``phase_steps`` attribute, e.g. an imitation learner's steps per phase), or ``None``
            when the model has none.
    """

    seed: int
    episode_returns: list[float] = field(default_factory=list)
    episode_steps: list[int] = field(default_factory=list)
    env_steps: int = 0
    wall_seconds: float = 0.0
    last_return: float = math.nan
    eval_return: float | None = None
    eval_returns: list[float] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    checkpoint_returns: list[tuple[int, float]] = field(default_factory=list)
    phase_steps: dict[str, int] | None = None

    @property
    def steps_per_second(self) -> float:
        return self.env_steps / self.wall_seconds if self.wall_seconds > 0 else math.nan

    def fitness(self, mode: str) -> float:
        """The run's return under a fitness measure (``last`` or ``eval``)."""
        if mode == "eval":
            return math.nan if self.eval_return is None else self.eval_return
        return self.last_return


def _episode_callback(result: RunResult, budget: BudgetConfig, report: ReportFn | None) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    checkpoints = [
        budget.training_steps * (k + 1) // (budget.n_reports + 1) for k in range(budget.n_reports)
    ]

    class EpisodeRecorder(BaseCallback):
        """Records episode returns from Monitor infos and reports intermediate returns.

        An imitation learner moves the record of an episode its expert acted in to
        ``info["mixture_episode"]``: such episodes are only counted (``mixture_episodes``).
        """

        mixture_episodes = 0

        def _on_step(self) -> bool:
            raise_swallowed_signal()  # a Ctrl-C or SIGTERM that a callback dropped
            # Called on every env step: look at the infos only when an episode ended (Monitor
            # writes info["episode"] exactly then; np.count_nonzero is a cheap C call).
            if np.count_nonzero(self.locals["dones"]):
                for info in self.locals["infos"]:
                    episode = info.get("episode")
                    if episode is not None:
                        result.episode_returns.append(float(episode["r"]))
                        result.episode_steps.append(int(self.num_timesteps))
                    elif "mixture_episode" in info:
                        self.mixture_episodes += 1
            while checkpoints and self.num_timesteps >= checkpoints[0]:
                step = checkpoints.pop(0)
                if report is not None and result.episode_returns:
                    recent = result.episode_returns[-budget.n_last_episodes :]
                    report(step, float(np.mean(recent)))
            return True

    return EpisodeRecorder()


def _progress_callback(progress: Progress) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class ProgressCallback(BaseCallback):
        def _on_step(self) -> bool:
            progress.update(self.num_timesteps)
            return True

        def _on_training_end(self) -> None:
            progress.update(self.num_timesteps)
            progress.close()

    return ProgressCallback()


def _evaluate(
    model: Any,
    task: TaskConfig,
    encoder: EncoderConfig | None,
    ppo: PPOConfig,
    seeds: SeedSet,
    normalized: Any,
    n_eval_episodes: int,
) -> list[float]:
    """Deterministic evaluation episodes of ``model`` on a fresh evaluation env.

    The env is built as training's (mask, encoder with the run's reservoir weights, the
    learner's wrappers) on one environment seeded with ``seeds.eval_env``, so every call with
    the same model gives the same returns. With ``ppo.normalize`` it normalizes observations
    with the training env's statistics *at the time of the call*, frozen; rewards stay raw.

    Args:
        model: The learner (an SB3 algorithm or anything with SB3's ``predict``).
        task: Env id and observation mask.
        encoder: The run's reservoir encoding, or ``None``.
        ppo: The learner's settings.
        seeds: The run's seeds ([`derive_seeds`][ermrl.agents.derive_seeds]).
        normalized: The training env after ``normalize_env`` (a ``VecNormalize`` when
            ``ppo.normalize`` is set).
        n_eval_episodes: Episodes to run.

    Returns:
        The episodes' returns, shape ``(n_eval_episodes,)``.
    """
    from stable_baselines3.common.evaluation import evaluate_policy

    from ermrl.agents._normalize import frozen_normalize_env, normalize_stats
    from ermrl.learners import get_learner

    learner = get_learner(ppo.learner)
    eval_env = make_vec_env(task, 1, seeds.eval_env, encoder, seeds.reservoir)
    if ppo.normalize is not None:
        eval_env = frozen_normalize_env(eval_env, normalize_stats(normalized))
    eval_env = learner.wrap_env(eval_env, ppo)
    try:
        returns, _ = evaluate_policy(
            model,
            eval_env,
            n_eval_episodes=n_eval_episodes,
            deterministic=True,
            return_episode_rewards=True,
        )
    finally:
        eval_env.close()
    # return_episode_rewards=True: a list per episode (SB3 types it as float | list).
    assert isinstance(returns, list)
    return [float(r) for r in returns]


def _checkpoint_callback(
    result: RunResult, eval_at: Sequence[int], training_steps: int, evaluate: Callable[[], float]
) -> Any:
    """An SB3 callback that calls ``evaluate()`` when the learner's ``num_timesteps`` first
    reaches each step of ``eval_at`` and appends ``(step, return)`` to
    ``result.checkpoint_returns``.

    Steps at or past ``training_steps`` are evaluated when training ends, after the learner's
    last update (an on-policy learner reaches its last step before the update of its last
    rollout), so a checkpoint at the full budget measures the final model.
    """
    from stable_baselines3.common.callbacks import BaseCallback

    pending = sorted(set(int(s) for s in eval_at))

    def run(step: int) -> None:
        result.checkpoint_returns.append((step, float(evaluate())))

    class CheckpointEvaluator(BaseCallback):
        """Evaluates the learner at fixed env steps (works with any ``on_step`` caller)."""

        def _on_step(self) -> bool:
            while pending and pending[0] < training_steps and self.num_timesteps >= pending[0]:
                run(pending.pop(0))
            return True

        def _on_training_end(self) -> None:
            while pending:
                run(pending.pop(0))

    return CheckpointEvaluator()


def save_trained(model: Any, model_path: str | Path, stats: dict[str, Any] | None) -> None:
    """Write a trained agent's files: ``model_path`` (``model.zip``), its ``policy.pt`` and, with
    normalization statistics, their JSON ([`stats_path`][ermrl.agents.stats_path]).

    ``model.zip`` is SB3's format (pickles, never read by ermrl); ``policy.pt`` holds the weights
    as plain tensors, the only file ermrl reads a policy from. The zip is written under a
    temporary name and renamed once complete: a full disk never leaves a truncated ``model.zip``
    under its final name, nor a ``model.zip`` without its ``policy.pt``.
    """
    import json

    from ermrl.agents._normalize import stats_path
    from ermrl.learners._policy_io import policy_path, save_policy

    partial = Path(f"{model_path}.partial")
    try:
        with partial.open("wb") as handle:
            model.save(handle)
        os.replace(partial, model_path)
    finally:
        partial.unlink(missing_ok=True)
    try:
        save_policy(model, policy_path(model_path))
        if stats is not None:
            stats_path(model_path).write_text(json.dumps(stats, indent=1) + "\n")
    except BaseException:
        # All or nothing: a model.zip without its policy.pt (a full disk) is taken away too.
        for path in (Path(model_path), policy_path(model_path), stats_path(model_path)):
            Path(path).unlink(missing_ok=True)
        raise


def train_agent(
    task: TaskConfig,
    encoder: EncoderConfig | None,
    ppo: PPOConfig,
    budget: BudgetConfig,
    seed: int,
    *,
    evaluate: bool | None = None,
    model_path: str | Path | None = None,
    report: ReportFn | None = None,
    tensorboard_log: str | None = None,
    eval_at: Sequence[int] = (),
    wandb: WandbRun | None = None,
    callbacks: Sequence[Any] = (),
    progress: Progress | None = None,
    checkpoint: RunCheckpoint | None = None,
) -> RunResult:
    """Train the learner of ``ppo.learner`` (PPO by default) on a task for one seed and measure
    its returns.

    Args:
        task: Env id and observation mask.
        encoder: Reservoir encoding; ``None`` trains plain PPO on the (masked) observation.
        ppo: The learner's settings (``ppo.learner`` names it, see
            [`ermrl.learners`][ermrl.learners]).
        budget: Training steps and fitness measure.
        seed: Seeds the reservoir weights, the environments and the agent (see
            [`derive_seeds`][ermrl.agents.derive_seeds]).
        evaluate: Run deterministic evaluation episodes after training (default: when
            ``budget.fitness == "eval"``).
        model_path: Save the trained model there (``.zip``, SB3's format), its policy's
            weights as plain tensors ([`policy_path`][ermrl.agents.policy_path], the file ermrl
            reads back) and, with ``ppo.normalize``, the normalization statistics as JSON
            ([`stats_path`][ermrl.agents.stats_path]).
        report: Called as ``report(env_step, mean_recent_return)`` ``budget.n_reports`` times
            during training (for pruning); it may raise to stop training.
        tensorboard_log: Directory for SB3's TensorBoard logs.
        eval_at: Env steps at which to run ``budget.n_eval_episodes`` deterministic
            evaluation episodes during training, each on a fresh evaluation env built as the
            final evaluation's (same seeds every time, distinct from training's; with
            normalization, training's statistics of that moment, frozen). A checkpoint runs
            when the learner's ``num_timesteps`` first reaches its step (up to ``n_envs - 1``
            steps later); checkpoints at the full budget run after the last update, so they
            measure the final model. Stored in ``RunResult.checkpoint_returns``. The evaluations
            do not change training (deterministic actions on their own env).
        wandb: Log the run to Weights & Biases through wandb's SB3 callback (SB3's
            TensorBoard scalars synced, the outcome in the W&B run's summary); see
            `ermrl.agents._wandb`. Needs the ``wandb`` package.
        callbacks: More SB3 callbacks, called after ermrl's own.
        progress: Told the learner's env steps as training goes (a line every tenth of the
            budget or 30 s, with the rate from the first step on), and closed at the end.
        checkpoint: Resume from this checkpoint when it holds this run's state, and save the
            run there as it trains (`ermrl.agents._checkpoint`: on-policy SB3 learners
            only; others ignore it); removed when the run ends.

    Returns:
        The run's returns and timings.

    Raises:
        TrainingDiverged: NaN or infinite values appeared in training.
        NoEpisodeFinished: the ``last`` measure is needed but no episode ended.
        ValueError: a step of ``eval_at`` outside ``[1, budget.training_steps]``.
    """
    bad = [s for s in eval_at if not 1 <= int(s) <= budget.training_steps]
    if bad:
        raise ValueError(f"eval_at steps must be in [1, {budget.training_steps}], got {bad}")
    run = functools.partial(
        _train, task, encoder, ppo, budget, seed, evaluate=evaluate, model_path=model_path,
        report=report, eval_at=eval_at, progress=progress, checkpoint=checkpoint,
    )  # fmt: skip
    if wandb is not None:
        return _train_with_wandb(run, wandb, tensorboard_log, callbacks)
    return run(tensorboard_log=tensorboard_log, callbacks=callbacks)


def _train_with_wandb(
    run: Callable[..., RunResult],
    wandb: WandbRun,
    tensorboard_log: str | None,
    callbacks: Sequence[Any],
) -> RunResult:
    """``run(tensorboard_log=..., callbacks=...)`` logged to Weights & Biases (see
    [`train_agent`][ermrl.agents.train_agent]): wandb's SB3 callback after ``callbacks``, and the
    outcome in the W&B run's summary."""
    from ermrl.agents._wandb import wandb_run

    with wandb_run(wandb, tensorboard_log) as (wandb_callback, log_dir, session):
        result = run(tensorboard_log=log_dir, callbacks=(*callbacks, wandb_callback))
        session.summary.update(
            {
                "ermrl/last_return": result.last_return,
                "ermrl/eval_return": result.eval_return,
                "ermrl/env_steps": result.env_steps,
                "ermrl/wall_seconds": result.wall_seconds,
            }
        )
    return result


def _train(
    task: TaskConfig,
    encoder: EncoderConfig | None,
    ppo: PPOConfig,
    budget: BudgetConfig,
    seed: int,
    *,
    evaluate: bool | None,
    model_path: str | Path | None,
    report: ReportFn | None,
    tensorboard_log: str | None,
    eval_at: Sequence[int],
    callbacks: Sequence[Any],
    progress: Progress | None,
    checkpoint: RunCheckpoint | None,
) -> RunResult:
    """[`train_agent`][ermrl.agents.train_agent] once its arguments are checked and W&B is set up:
    build the env and the learner, resume, learn, measure the returns, evaluate, save."""
    import torch

    from ermrl.agents._normalize import normalize_env, save_normalize_stats, stats_path
    from ermrl.learners import get_learner

    learner = get_learner(ppo.learner)
    torch.set_num_threads(ppo.torch_threads)
    # BLAS (numpy's matrix products in the encoder) gets the same thread budget: with several
    # training processes on a few cores, extra spinning BLAS threads only steal CPU time.
    threadpoolctl.threadpool_limits(ppo.torch_threads)
    seeds = derive_seeds(seed)
    result = RunResult(seed=seed)
    start = time.perf_counter()
    # VecNormalize (ppo.normalize) sees the reservoir states; the learner's own wrappers (a
    # frame stack) come last, as in rl-baselines3-zoo.
    normalized = normalize_env(
        make_vec_env(task, ppo.n_envs, seeds.env, encoder, seeds.reservoir), ppo
    )
    env = learner.wrap_env(normalized, ppo)
    try:
        model = learner.build(env, ppo, seed=seeds.agent, tensorboard_log=tensorboard_log)
        # PPO(seed=...) reseeds the env with the agent seed; give the envs their own seed.
        env.seed(seeds.env)
        if checkpoint is not None and not can_checkpoint(model):
            checkpoint = None
        resumed, wall_before = _resume(model, checkpoint, normalized, env, seeds, result, progress)
        eval_at = [t for t in eval_at if t > resumed]
        recorder = _episode_callback(result, budget, report)
        callback = _training_callback(
            recorder, callbacks, progress, checkpoint, normalized, result, wall_before, start
        )
        # The returns of deterministic episodes on a fresh evaluation env (see _evaluate).
        episodes = functools.partial(
            _evaluate, model, task, encoder, ppo, seeds, normalized, budget.n_eval_episodes
        )
        callback = _with_evaluations(callback, result, eval_at, budget.training_steps, episodes)
        _learn(model, callback, budget.training_steps, resumed, seed)
        _measure_training(result, model, recorder, budget, task.env_id, seed)
        if evaluate if evaluate is not None else budget.fitness == "eval":
            result.eval_returns = episodes()
            result.eval_return = float(np.mean(result.eval_returns))
            if not math.isfinite(result.eval_return):
                raise TrainingDiverged(f"seed {seed}: non-finite evaluation return")
        if model_path is not None:
            save_trained(model, model_path, None)
            if ppo.normalize is not None:
                save_normalize_stats(normalized, stats_path(model_path))
    finally:
        env.close()
    result.wall_seconds = wall_before + time.perf_counter() - start
    if checkpoint is not None:
        checkpoint.remove()
    return result


def _resume(
    model: Any,
    checkpoint: RunCheckpoint | None,
    normalized: Any,
    env: Any,
    seeds: SeedSet,
    result: RunResult,
    progress: Progress | None,
) -> tuple[int, float]:
    """Restore a run from ``checkpoint`` when it holds this run's state.

    ``restore()`` loads the weights and statistics, or sets a checkpoint that does not fit
    this model aside (one line) and leaves the model as built. A restored run gets back its
    step count, its records so far (into ``result``) and fresh episodes (``env`` reseeded).

    Returns:
        The env steps and wall seconds restored (``(0, 0.0)``: none).
    """
    saved = None if checkpoint is None else checkpoint.restore(model, normalized)
    if saved is None:
        return 0, 0.0
    assert checkpoint is not None
    model.num_timesteps = resumed = int(saved["num_timesteps"])
    result.episode_returns = [float(r) for r in saved["episode_returns"]]
    result.episode_steps = [int(t) for t in saved["episode_steps"]]
    result.checkpoint_returns = [(int(t), float(r)) for t, r in saved["checkpoint_returns"]]
    wall_before = float(saved["wall_seconds"])
    env.seed(seeds.env + resumed)  # fresh episodes, not the first ones again
    if progress is not None:
        progress.message(f"resumed from {checkpoint.folder} at {resumed:,} steps")
    return resumed, wall_before


def _training_callback(
    recorder: Any,
    callbacks: Sequence[Any],
    progress: Progress | None,
    checkpoint: RunCheckpoint | None,
    normalized: Any,
    result: RunResult,
    wall_before: float,
    start: float,
) -> Any:
    """The SB3 callback of a run: ``recorder``, then ``callbacks``, then the progress's and the
    checkpoint saver's (a list when there is more than ``recorder``).

    The saver stores ``result``'s records so far and the wall seconds of the run: ``wall_before``
    restored, plus the time since ``start`` (``time.perf_counter()``).
    """
    if progress is not None:
        callbacks = (*callbacks, _progress_callback(progress))
    if checkpoint is not None:

        def records() -> dict[str, Any]:
            return {
                "episode_returns": result.episode_returns,
                "episode_steps": result.episode_steps,
                "checkpoint_returns": result.checkpoint_returns,
                "wall_seconds": wall_before + time.perf_counter() - start,
            }

        callbacks = (*callbacks, saver_callback(checkpoint, normalized, records))
    return [recorder, *callbacks] if callbacks else recorder


def _with_evaluations(
    callback: Any,
    result: RunResult,
    eval_at: Sequence[int],
    training_steps: int,
    episodes: Callable[[], list[float]],
) -> Any:
    """``callback``, followed by the evaluations at the steps of ``eval_at`` (none: ``callback``
    alone), each the mean return of ``episodes()`` (see `_checkpoint_callback`)."""
    if not eval_at:
        return callback

    def evaluate_now() -> float:
        return float(np.mean(episodes()))

    return [
        *(callback if isinstance(callback, list) else [callback]),
        _checkpoint_callback(result, eval_at, training_steps, evaluate_now),
    ]


def _learn(model: Any, callback: Any, training_steps: int, resumed: int, seed: int) -> None:
    """Train ``model`` up to ``training_steps`` env steps, from ``resumed`` on.

    Raises:
        TrainingDiverged: the policy output NaN (torch.distributions raises ``ValueError``).
    """
    # A resumed run trains the steps left; with reset_num_timesteps=False SB3 counts on
    # from num_timesteps, so its schedules end at the budget as the uninterrupted run's.
    resume_kwargs = {"reset_num_timesteps": False} if resumed else {}
    try:
        model.learn(
            total_timesteps=training_steps - resumed,
            callback=callback,
            progress_bar=False,
            **resume_kwargs,
        )
    except ValueError as err:
        # torch.distributions raises ValueError when the policy outputs NaN.
        if "nan" in str(err).lower() or "invalid values" in str(err).lower():
            raise TrainingDiverged(f"seed {seed}: training diverged ({err})") from err
        raise


def _measure_training(
    result: RunResult, model: Any, recorder: Any, budget: BudgetConfig, env_id: str, seed: int
) -> None:
    """Fill in ``result``'s env steps, the learner's own split of them and the final return
    (the mean of the last ``budget.n_last_episodes`` training episodes).

    Raises:
        TrainingDiverged: an episode's return is not finite.
        NoEpisodeFinished: the ``last`` measure is needed but no episode (of the learner's
            own) ended.
    """
    result.env_steps = int(model.num_timesteps)
    phase_steps = getattr(model, "phase_steps", None)
    if isinstance(phase_steps, dict):
        result.phase_steps = {str(k): int(v) for k, v in phase_steps.items()}
    if not all(math.isfinite(r) for r in result.episode_returns):
        raise TrainingDiverged(f"seed {seed}: non-finite episode return")
    if result.episode_returns:
        result.last_return = float(np.mean(result.episode_returns[-budget.n_last_episodes :]))
    elif budget.fitness == "last" and recorder.mixture_episodes:
        raise NoEpisodeFinished(
            f"seed {seed}: none of the {recorder.mixture_episodes} episodes of "
            f"{env_id} that ended within {budget.training_steps} training steps was "
            "the learner's alone (the expert acted in each, and an imitation learner's "
            "training returns count only learner-only episodes); raise --training-steps "
            "past the expert's share (beta), or measure by evaluation (--fitness eval; "
            "--eval in a test phase)"
        )
    elif budget.fitness == "last":
        raise NoEpisodeFinished(
            f"seed {seed}: no episode of {env_id} ended within "
            f"{budget.training_steps} training steps; raise --training-steps or use "
            "--fitness eval"
        )
