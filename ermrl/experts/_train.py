"""Training an expert with ermrl's own inner loop, and writing its folder of plain files.

`train_expert` resolves the learner's settings (its YAML table, then overrides), trains
with [`ermrl.agents.train_agent`][ermrl.agents.train_agent] on the full observation, evaluates the
deterministic policy, and writes the folder described in `ermrl.experts._expert`. The folder is
built under a temporary name beside ``out`` and renamed at the end, so an interrupted run (Ctrl-C, a
crash, a full disk) never leaves a half-written expert under its final name.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ermrl._io import write_atomic
from ermrl._progress import Progress
from ermrl.config import BudgetConfig, ConfigError, PPOConfig, TaskConfig
from ermrl.experts._expert import (
    EXPERT_FILE,
    NORMALIZE_FILE,
    ExpertInfo,
    _versions,
    expert_algos,
    is_expert_folder,
)

if TYPE_CHECKING:
    from ermrl.agents import RunResult

__all__ = ["ExpertExists", "TrainingProgress", "check_expert_out", "train_expert"]

DEFAULT_N_REPORTS = 9  # progress every 10% of the steps
_VERSIONED = ("ermrl", "stable_baselines3", "torch", "gymnasium", "numpy", "mujoco")


class ExpertExists(FileExistsError):
    """``out`` already holds an expert (pass ``overwrite=True`` to replace it)."""


@dataclass(frozen=True)
class TrainingProgress:
    """One progress report of `train_expert`.

    Attributes:
        steps: Environment steps done.
        total_steps: Steps asked for.
        recent_return: Mean return of the last (at most 10) training episodes.
        elapsed: Seconds since training started.
        previous_steps: Steps done at the previous report (0 for the first).
        previous_elapsed: Seconds at the previous report (0.0 for the first).
    """

    steps: int
    total_steps: int
    recent_return: float
    elapsed: float
    previous_steps: int = 0
    previous_elapsed: float = 0.0

    @property
    def steps_per_second(self) -> float:
        """Speed since the previous report (SAC slows down once ``learning_starts`` is past)."""
        seconds = self.elapsed - self.previous_elapsed
        return (self.steps - self.previous_steps) / seconds if seconds > 0 else math.nan

    @property
    def eta_seconds(self) -> float:
        """Seconds left at the current speed."""
        rate = self.steps_per_second
        return (self.total_steps - self.steps) / rate if rate > 0 else math.nan


def check_expert_out(out: str | Path, overwrite: bool = False) -> Path:
    """Refuse an output folder that would lose data; return it as a ``Path``.

    Args:
        out: The expert folder to write.
        overwrite: Replace an expert already there.

    Raises:
        ExpertExists: ``out`` holds an expert and ``overwrite`` is false.
        FileExistsError: ``out`` is a file, or a non-empty folder that holds no expert.
    """
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise FileExistsError(f"--out {str(path)!r} is a file, not a folder")
    if is_expert_folder(path):
        if not overwrite:
            raise ExpertExists(
                f"{str(path)!r} already holds an expert; pass --overwrite to replace it"
            )
    elif path.is_dir() and any(path.iterdir()):
        raise FileExistsError(
            f"{str(path)!r} is a non-empty folder that holds no expert; choose another --out"
        )
    return path


def _check_task(env_id: str, algo: str) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The observation and action shapes of ``env_id``, refusing what the learner cannot act on.

    Raises:
        ConfigError: the observation is not a flat box, or an off-policy learner (SAC) is given
            a discrete action space.
    """
    import gymnasium as gym
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

    from ermrl.envs import make_env
    from ermrl.learners import get_learner

    env = make_env(env_id, "all")
    try:
        obs_space, act_space = env.observation_space, env.action_space
    finally:
        env.close()
    if not isinstance(obs_space, gym.spaces.Box) or len(obs_space.shape) != 1:
        raise ConfigError(f"{env_id}: an expert needs a flat Box observation, got {obs_space}")
    off_policy = issubclass(get_learner(algo).algorithm(), OffPolicyAlgorithm)
    if off_policy and not isinstance(act_space, gym.spaces.Box):
        raise ConfigError(
            f"{algo} needs a continuous (Box) action space; {env_id} has {act_space} "
            "(use --algo ppo)"
        )
    return tuple(obs_space.shape), tuple(act_space.shape or ())


def _resolve_settings(
    env_id: str,
    algo: str,
    steps: int,
    seed: int,
    overrides: Mapping[str, Any] | None,
    n_eval_episodes: int,
    n_reports: int,
) -> tuple[PPOConfig, BudgetConfig]:
    """Check `train_expert`'s request and resolve the learner's settings and the budget.

    Args:
        env_id: The task.
        algo: The learner (a name of `expert_algos`).
        steps: Training environment steps.
        seed: The run's seed.
        overrides: Learner settings over the learner's table.
        n_eval_episodes: Deterministic evaluation episodes after training.
        n_reports: Progress reports over the training.

    Returns:
        The learner's settings and the training budget.

    Raises:
        ConfigError: unknown learner, bad settings, or a step count or seed out of range.
        UnknownEnvError: ``env_id`` is not registered.
    """
    from ermrl.agents import resolve_ppo_config
    from ermrl.envs import check_env_id

    algos = expert_algos()
    if algo not in algos:
        raise ConfigError(f"unknown expert algorithm {algo!r}; choose from {', '.join(algos)}")
    if steps < 1:
        raise ConfigError(f"steps must be >= 1, got {steps}")
    if seed < 0:
        raise ConfigError(f"seed must be >= 0, got {seed}")
    check_env_id(env_id)
    ppo = resolve_ppo_config(env_id, dict(overrides or {}), learner=algo)
    from ermrl.learners import get_learner

    get_learner(algo).check(ppo)
    budget = BudgetConfig(
        training_steps=steps,
        fitness="eval",
        n_eval_episodes=n_eval_episodes,
        n_reports=n_reports,
    )
    return ppo, budget


def _progress_hook(
    steps: int,
    progress: Callable[[TrainingProgress], None] | None,
    display: Progress | None,
) -> Callable[[int, float], None]:
    """The ``report`` hook of [`ermrl.agents.train_agent`][ermrl.agents.train_agent], timed from
    now.

    Args:
        steps: The steps asked for.
        progress: Given a `TrainingProgress` at each report.
        display: Its note becomes the recent return.

    Returns:
        ``report(step, recent_return)``.
    """
    start = time.perf_counter()
    previous = (0, 0.0)

    def report(step: int, recent: float) -> None:
        nonlocal previous
        elapsed = time.perf_counter() - start
        if display is not None:
            display.note = f"recent return {recent:.1f}"
        if progress is not None:
            progress(TrainingProgress(step, steps, recent, elapsed, *previous))
        previous = (step, elapsed)

    return report


def _train_into(
    partial: Path,
    env_id: str,
    ppo: PPOConfig,
    budget: BudgetConfig,
    seed: int,
    report: Callable[[int, float], None],
    display: Progress | None,
) -> RunResult:
    """Train and evaluate the expert on the full observation, its policy written in ``partial``.

    Args:
        partial: The folder being built.
        env_id: The task.
        ppo: The learner's settings.
        budget: The training steps, evaluation episodes and reports.
        seed: The run's seed.
        report: Called at each progress report.
        display: Told the env steps as training goes.

    Returns:
        The run's result (env steps, wall time, training and evaluation returns).
    """
    from ermrl.agents import train_agent

    result = train_agent(
        TaskConfig(env_id, "all"),
        None,
        ppo,
        budget,
        seed,
        evaluate=True,
        model_path=partial / "model.zip",
        report=report,
        progress=display,
    )
    # train_agent also writes SB3's model.zip (pickles): an expert folder holds none.
    (partial / "model.zip").unlink(missing_ok=True)
    return result


def _finish_folder(partial: Path, info: ExpertInfo) -> None:
    """Write ``expert.json``, check that ``partial`` holds the expert's files and nothing else,
    and give them the usual permissions.

    Raises:
        RuntimeError: the folder holds other files than the expert's.
    """
    from ermrl.agents import POLICY_FILE

    write_atomic(partial / EXPERT_FILE, json.dumps(info.to_dict(), indent=1) + "\n")
    expected = {EXPERT_FILE, POLICY_FILE} | ({NORMALIZE_FILE} if info.normalized else set())
    written = {p.name for p in partial.iterdir()}
    if written != expected:  # a change in train_agent's files must not slip in unnoticed
        raise RuntimeError(f"unexpected expert files {sorted(written)}, not {sorted(expected)}")
    # mkdtemp and mkstemp make them private (0o700, 0o600): give the usual permissions.
    os.chmod(partial, 0o777 & ~_umask())
    for file in partial.iterdir():
        os.chmod(file, 0o666 & ~_umask())


def train_expert(
    env_id: str,
    algo: str = "sac",
    steps: int = 100_000,
    out: str | Path = "expert",
    seed: int = 0,
    overrides: Mapping[str, Any] | None = None,
    n_eval_episodes: int = 10,
    *,
    overwrite: bool = False,
    progress: Callable[[TrainingProgress], None] | None = None,
    n_reports: int = DEFAULT_N_REPORTS,
    command: str | None = None,
    display: Progress | None = None,
) -> ExpertInfo:
    """Train an expert on a task's full observation and write its folder.

    Args:
        env_id: A registered gymnasium id with a flat Box observation (``Hopper-v5``, ...).
        algo: The learner (a name of `expert_algos`: ``sac``, ``ppo``).
        steps: Training environment steps.
        out: The expert folder (``expert.json``, ``policy.pt``, ``vecnormalize.json``).
        seed: Seeds the environments and the agent
            ([`ermrl.agents.derive_seeds`][ermrl.agents.derive_seeds]).
        overrides: Learner settings over the learner's table (``--ppo KEY=VALUE``).
        n_eval_episodes: Deterministic evaluation episodes after training.
        overwrite: Replace an expert already in ``out``.
        progress: Called ``n_reports`` times during training (once an episode has ended).
        n_reports: Progress reports, evenly spaced over ``steps``.
        command: The command line, recorded in ``expert.json``.
        display: Told the env steps as training goes (a bar or a line every tenth, as every
            training run shows, `ermrl._progress.Progress`); its note is the recent
            return once an episode has ended.

    Returns:
        What ``expert.json`` records, evaluation returns included.

    Raises:
        ConfigError: unknown learner, bad settings, or a task the learner cannot act on.
        UnknownEnvError: ``env_id`` is not registered.
        FileExistsError: ``out`` holds an expert (and not ``overwrite``) or other files.
        TrainingDiverged: training produced NaN values.
    """
    ppo, budget = _resolve_settings(
        env_id, algo, steps, seed, overrides, n_eval_episodes, n_reports
    )
    obs_shape, act_shape = _check_task(env_id, algo)
    final = check_expert_out(out, overwrite)
    final.parent.mkdir(parents=True, exist_ok=True)
    report = _progress_hook(steps, progress, display)
    partial = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}.partial-"))
    try:
        result = _train_into(partial, env_id, ppo, budget, seed, report, display)
        info = ExpertInfo(
            env_id=env_id,
            algo=algo,
            ppo=ppo,
            steps=steps,
            env_steps=result.env_steps,
            seed=seed,
            wall_seconds=result.wall_seconds,
            eval_returns=tuple(result.eval_returns),
            train_returns=tuple(result.episode_returns[-budget.n_last_episodes :]),
            observation_shape=obs_shape,
            action_shape=act_shape,
            versions=_versions(_VERSIONED),
            command=command,
        )
        _finish_folder(partial, info)
        _install(partial, final)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return info


def _install(partial: Path, final: Path) -> None:
    """Rename the finished folder to its final name, replacing an expert there (checked)."""
    if not final.exists():
        os.replace(partial, final)
        return
    if final.is_dir() and not any(final.iterdir()):
        final.rmdir()
        os.replace(partial, final)
        return
    old = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}.old-"))
    old.rmdir()
    os.replace(final, old)
    try:
        os.replace(partial, final)
    except BaseException:
        os.replace(old, final)
        raise
    shutil.rmtree(old, ignore_errors=True)


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
