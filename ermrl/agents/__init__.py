"""The inner loop: Stable-Baselines3 PPO on raw or reservoir-encoded observations."""

from ermrl.agents._checkpoint import RunCheckpoint
from ermrl.agents._hyperparams import (
    ACTIVATIONS,
    activation_fn,
    check_ppo_config,
    linear_schedule,
    load_hyperparams_table,
    parse_normalize,
    parse_overrides,
    ppo_kwargs,
    resolve_ppo_config,
    with_overrides,
)
from ermrl.agents._model import MODEL_FORMAT, Model, train_model
from ermrl.agents._normalize import (
    frozen_normalize_env,
    load_normalize_stats,
    normalize_env,
    normalize_stats,
    save_normalize_stats,
    stats_path,
)
from ermrl.agents._pool import pool_size, stop_workers, training_pool
from ermrl.agents._train import (
    NoEpisodeFinished,
    RunResult,
    SeedSet,
    TrainingDiverged,
    derive_seeds,
    make_vec_env,
    steps_trained,
    train_agent,
)
from ermrl.agents._wandb import WANDB_MISSING, WandbRun, study_wandb_callback, wandb_installed
from ermrl.learners._policy_io import POLICY_FILE, load_policy, policy_path, save_policy

__all__ = [
    "ACTIVATIONS",
    "MODEL_FORMAT",
    "Model",
    "POLICY_FILE",
    "NoEpisodeFinished",
    "RunCheckpoint",
    "RunResult",
    "SeedSet",
    "TrainingDiverged",
    "WANDB_MISSING",
    "WandbRun",
    "activation_fn",
    "check_ppo_config",
    "derive_seeds",
    "frozen_normalize_env",
    "linear_schedule",
    "load_hyperparams_table",
    "load_normalize_stats",
    "load_policy",
    "make_vec_env",
    "normalize_env",
    "normalize_stats",
    "parse_normalize",
    "parse_overrides",
    "policy_path",
    "pool_size",
    "ppo_kwargs",
    "resolve_ppo_config",
    "save_normalize_stats",
    "save_policy",
    "stats_path",
    "study_wandb_callback",
    "steps_trained",
    "train_agent",
    "stop_workers",
    "train_model",
    "training_pool",
    "wandb_installed",
    "with_overrides",
]
