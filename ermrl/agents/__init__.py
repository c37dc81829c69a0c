"""The inner loop: Stable-Baselines3 PPO on raw or reservoir-encoded observations."""

from ermrl.agents._hyperparams import (
    linear_schedule,
    load_hyperparams_table,
    parse_overrides,
    ppo_kwargs,
    resolve_ppo_config,
)
from ermrl.agents._pool import pool_size, training_pool
from ermrl.agents._train import (
    NoEpisodeFinished,
    RunResult,
    SeedSet,
    TrainingDiverged,
    derive_seeds,
    make_vec_env,
    train_agent,
)

__all__ = [
    "NoEpisodeFinished",
    "RunResult",
    "SeedSet",
    "TrainingDiverged",
    "derive_seeds",
    "linear_schedule",
    "load_hyperparams_table",
    "make_vec_env",
    "parse_overrides",
    "pool_size",
    "ppo_kwargs",
    "resolve_ppo_config",
    "train_agent",
    "training_pool",
]
