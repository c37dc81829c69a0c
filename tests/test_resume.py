"""A killed sb3 training run resumes from its checkpoint (ermrl.agents._checkpoint).

Real SB3 training on real environments; the kill is a KeyboardInterrupt raised right after a
save, so the state at the kill is known exactly.
"""

from __future__ import annotations

import copy
import io
from pathlib import Path
from typing import Any

import pytest
import torch
from stable_baselines3.common.callbacks import BaseCallback

from ermrl._progress import Progress
from ermrl.agents import RunCheckpoint, resolve_ppo_config, train_agent, with_overrides
from ermrl.config import BudgetConfig, EncoderConfig, ReservoirParams, TaskConfig

TASK = TaskConfig("Pendulum-v1", "positions")
ENCODER = EncoderConfig(reservoirs=(ReservoirParams(units=12),))
BUDGET = BudgetConfig(training_steps=2048, fitness="last", n_last_episodes=1)


def settings(learner: str = "ppo") -> Any:
    overrides = {"n_steps": 64, "batch_size": 64, "n_epochs": 2, "normalize": True}
    return with_overrides(resolve_ppo_config("Pendulum-v1", learner=learner), overrides)


class KilledAfterSave(RunCheckpoint):
    """Saves as a checkpoint does, then records the model's state and kills the run (once
    ``kill_at`` steps are saved)."""

    kill_at = 1024
    at_kill: dict[str, Any] = {}

    def save(self, model: Any, normalized: Any, records: dict[str, Any]) -> None:
        super().save(model, normalized, records)
        if model.num_timesteps >= self.kill_at:
            KilledAfterSave.at_kill = {
                "steps": int(model.num_timesteps),
                "policy": {k: v.clone() for k, v in model.policy.state_dict().items()},
                "optimizer": copy.deepcopy(model.policy.optimizer.state_dict()),
                "obs_count": float(normalized.obs_rms.count),
                "episodes": list(records["episode_returns"]),
            }
            raise KeyboardInterrupt


class AtStart(BaseCallback):
    """Records what the resumed learner holds when its training starts."""

    seen: dict[str, Any] = {}

    def _on_training_start(self) -> None:
        AtStart.seen = {
            "steps": int(self.model.num_timesteps),
            "total": int(self.model._total_timesteps),
            "policy": {k: v.clone() for k, v in self.model.policy.state_dict().items()},
            "optimizer": copy.deepcopy(self.model.policy.optimizer.state_dict()),
            "obs_count": float(self.model.get_vec_normalize_env().obs_rms.count),
        }

    def _on_step(self) -> bool:
        return True


@pytest.mark.parametrize("learner", ["ppo", "lstm-ppo"])
def test_a_killed_run_resumes_from_its_checkpoint(learner: str, tmp_path: Path) -> None:
    """The resumed learner starts from the saved weights, Adam state, normalization and steps;
    it trains only the rest of the budget, its schedules end at the budget, its episodes go on
    from the saved ones, it says so, and the checkpoint is removed at the end."""
    ppo = settings(learner)
    key = f"{learner} Pendulum seed 3"
    killed = KilledAfterSave(tmp_path / "checkpoints", every=256, key=key)
    with pytest.raises(KeyboardInterrupt):
        train_agent(TASK, ENCODER, ppo, BUDGET, 3, checkpoint=killed)
    at_kill = KilledAfterSave.at_kill
    assert at_kill["steps"] == 1024 and at_kill["episodes"]
    assert [p.name for p in (tmp_path / "checkpoints").glob("model-*.zip")] == ["model-1024.zip"]
    stream = io.StringIO()
    progress = Progress("again", BUDGET.training_steps, mode="lines", stream=stream)
    checkpoint = RunCheckpoint(tmp_path / "checkpoints", every=256, key=key)
    result = train_agent(
        TASK, ENCODER, ppo, BUDGET, 3, checkpoint=checkpoint, callbacks=[AtStart()],
        progress=progress,
    )  # fmt: skip
    seen = AtStart.seen
    assert seen["steps"] == 1024 and seen["total"] == BUDGET.training_steps
    for name, value in at_kill["policy"].items():
        assert torch.equal(seen["policy"][name], value), name
    assert seen["optimizer"]["state"].keys() == at_kill["optimizer"]["state"].keys()
    for k, state in at_kill["optimizer"]["state"].items():
        assert torch.equal(seen["optimizer"]["state"][k]["exp_avg_sq"], state["exp_avg_sq"])
    # The normalization goes on from the saved statistics: SB3's first reset of the resumed
    # envs adds their n_envs observations to them (a fresh one would count 1e-4 + n_envs).
    assert seen["obs_count"] == at_kill["obs_count"] + ppo.n_envs
    assert f"[again] resumed from {tmp_path / 'checkpoints'} at 1,024 steps" in stream.getvalue()
    assert result.env_steps == BUDGET.training_steps
    assert result.episode_returns[: len(at_kill["episodes"])] == at_kill["episodes"]
    assert len(result.episode_returns) > len(at_kill["episodes"])
    assert all(t > 1024 for t in result.episode_steps[len(at_kill["episodes"]) :])
    assert not (tmp_path / "checkpoints").exists()


def test_a_checkpoint_of_other_settings_is_not_resumed(tmp_path: Path) -> None:
    """Another key (the run's settings): the run starts from step 0 and says nothing of it."""
    killed = KilledAfterSave(tmp_path / "c", every=256, key="a")
    with pytest.raises(KeyboardInterrupt):
        train_agent(TASK, ENCODER, settings(), BUDGET, 3, checkpoint=killed)
    assert RunCheckpoint(tmp_path / "c", every=256, key="a").load() is not None
    other = RunCheckpoint(tmp_path / "c", every=256, key="b")
    assert other.load() is None
    stream = io.StringIO()
    progress = Progress("other", BUDGET.training_steps, mode="lines", stream=stream)
    train_agent(TASK, ENCODER, settings(), BUDGET, 3, checkpoint=other, callbacks=[AtStart()],
                progress=progress)  # fmt: skip
    assert AtStart.seen["steps"] == 0 and "resumed" not in stream.getvalue()


def test_an_off_policy_learner_is_not_checkpointed(tmp_path: Path) -> None:
    """SAC (its replay buffer is not saved) trains without writing a checkpoint."""
    sac = with_overrides(
        resolve_ppo_config("Pendulum-v1", learner="sac"),
        {"learning_starts": 100, "buffer_size": 1000, "batch_size": 32},
    )
    budget = BudgetConfig(training_steps=600, fitness="last", n_last_episodes=1)
    checkpoint = RunCheckpoint(tmp_path / "c", every=100, key="sac")
    result = train_agent(TASK, None, sac, budget, 3, checkpoint=checkpoint)
    assert result.env_steps == 600 and not (tmp_path / "c").exists()
