"""``train_agent(eval_at=...)``: evaluations at fixed env steps during training."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ermrl.agents import RunResult, resolve_ppo_config, train_agent
from ermrl.config import BudgetConfig, TaskConfig

PENDULUM = TaskConfig("Pendulum-v1", "all")
TINY_PPO = {"n_steps": 64, "batch_size": 64, "n_epochs": 1}


@pytest.mark.parametrize("normalize", [False, True])
def test_ppo_checkpoints_and_the_last_one_is_the_final_evaluation(normalize: bool) -> None:
    ppo = resolve_ppo_config(
        "Pendulum-v1", {**TINY_PPO, "normalize": normalize}, n_envs=2
    )  # 2 envs: steps advance by 2, a checkpoint may run a step after its own
    budget = BudgetConfig(training_steps=512, n_eval_episodes=2)
    result = train_agent(
        PENDULUM, None, ppo, budget, seed=3, evaluate=True, eval_at=(511, 255, 512)
    )
    assert [step for step, _ in result.checkpoint_returns] == [255, 511, 512]
    assert all(np.isfinite(r) for _, r in result.checkpoint_returns)
    # The checkpoint at the full budget runs after the last update, on the same evaluation
    # seeds as the final evaluation: the same model, the same episodes.
    assert result.eval_return is not None
    assert result.checkpoint_returns[-1][1] == result.eval_return
    # The checkpoint one step before the budget runs before the last rollout's update.
    assert result.checkpoint_returns[1][1] != result.eval_return


def test_checkpoints_do_not_change_training() -> None:
    ppo = resolve_ppo_config("Pendulum-v1", TINY_PPO, n_envs=1)
    budget = BudgetConfig(training_steps=448, n_eval_episodes=1)
    plain = train_agent(PENDULUM, None, ppo, budget, seed=5, evaluate=True)
    checked = train_agent(PENDULUM, None, ppo, budget, seed=5, evaluate=True, eval_at=(200, 448))
    assert plain.checkpoint_returns == [] and len(checked.checkpoint_returns) == 2
    assert checked.episode_returns == plain.episode_returns
    assert checked.eval_return == plain.eval_return


def test_eval_at_outside_the_budget_is_refused() -> None:
    ppo = resolve_ppo_config("Pendulum-v1", TINY_PPO, n_envs=1)
    with pytest.raises(ValueError, match="eval_at"):
        train_agent(PENDULUM, None, ppo, BudgetConfig(training_steps=128), seed=0, eval_at=(129,))


def test_a_result_without_the_new_fields_keeps_their_defaults() -> None:
    old = RunResult(seed=1, env_steps=10, last_return=1.0)  # as older callers build it
    assert old.checkpoint_returns == [] and old.phase_steps is None


def test_dagger_checkpoints(tiny_expert: Path) -> None:  # noqa: F811
    ppo = resolve_ppo_config(
        "Pendulum-v1",
        {"expert": str(tiny_expert), "steps_per_iteration": 300, "epochs": 1},
        learner="dagger",
    )
    # beta > 0 throughout: no training episode is the imitator's alone, so fitness is eval
    budget = BudgetConfig(training_steps=600, fitness="eval", n_eval_episodes=1)
    result = train_agent(PENDULUM, None, ppo, budget, seed=2, evaluate=True, eval_at=(300, 600))
    assert [step for step, _ in result.checkpoint_returns] == [300, 600]
    assert result.checkpoint_returns[-1][1] == result.eval_return
