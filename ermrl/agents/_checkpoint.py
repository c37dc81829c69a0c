"""Checkpoints of one training run on the sb3 backend: a killed run resumes from its last save.

A run of an on-policy Stable-Baselines3 learner (PPO and the learners built on SB3's
``OnPolicyAlgorithm``: ``lstm-ppo``, ``framestack-ppo``, ``rtu-ppo``) saves, every ``every`` env
steps at the start of a rollout (after an update), its model with SB3's ``model.save`` (the
policy's weights and the optimizer's state), the running normalization statistics (JSON, as
:func:`~ermrl.agents.normalize_stats` writes them) and its episode records. A rerun of the same
run (the same ``key``) loads them with SB3's ``set_parameters`` and trains the remaining steps
with ``reset_num_timesteps=False``, so the learning-rate and clip schedules go on where they were.
The environments restart from fresh episodes (seeded anew), and the learner's other state (a
recurrent learner's hidden state, its random streams) starts afresh: a resumed run is not bit for
bit the uninterrupted one. Off-policy learners (SAC, whose replay buffer is not saved) and
learners that are no SB3 algorithm are not checkpointed: they restart from step 0.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ermrl._io import write_atomic

__all__ = ["RunCheckpoint", "can_checkpoint"]

CHECKPOINT_VERSION = 1
STATE_FILE = "state.json"


def can_checkpoint(model: Any) -> bool:
    """Whether ``model``'s training can be saved and resumed (an SB3 on-policy algorithm)."""
    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

    return isinstance(model, OnPolicyAlgorithm)


@dataclass(frozen=True)
class RunCheckpoint:
    """Where one run saves its training state, how often, and what run it is.

    Attributes:
        folder: The run's checkpoint folder (``state.json`` and ``model-<step>.zip``).
        every: Env steps between saves.
        key: The run's settings as text; a checkpoint saved under another key is not resumed.
    """

    folder: Path
    every: int
    key: str

    def load(self) -> dict[str, Any] | None:
        """The saved state (with ``model``, the path of its model file), or ``None``: no
        checkpoint, one of another run, or an unreadable one (the run then starts over)."""
        try:
            state = json.loads((self.folder / STATE_FILE).read_text())
        except (OSError, ValueError):
            return None
        if (
            not isinstance(state, dict)
            or state.get("version") != CHECKPOINT_VERSION
            or state.get("key") != self.key
            or not (self.folder / str(state.get("model"))).is_file()
        ):
            return None
        return {**state, "model": self.folder / state["model"]}

    def save(self, model: Any, normalized: Any, records: dict[str, Any]) -> None:
        """Save ``model`` (at its ``num_timesteps``), the statistics of ``normalized`` (when it
        is a ``VecNormalize``) and ``records`` (the run's episodes so far, JSON-ready). The
        state file is written last and atomically, so a kill leaves the previous save whole."""
        from stable_baselines3.common.vec_env import VecNormalize

        from ermrl.agents._normalize import normalize_stats

        step = int(model.num_timesteps)
        self.folder.mkdir(parents=True, exist_ok=True)
        name = f"model-{step}.zip"
        partial = self.folder / f".{name}.partial"
        with partial.open("wb") as handle:
            model.save(handle)
        os.replace(partial, self.folder / name)
        state = {
            "version": CHECKPOINT_VERSION,
            "key": self.key,
            "num_timesteps": step,
            "model": name,
            "normalize": normalize_stats(normalized)
            if isinstance(normalized, VecNormalize)
            else None,
            **records,
        }
        write_atomic(self.folder / STATE_FILE, json.dumps(state) + "\n")
        for old in self.folder.glob("model-*.zip"):
            if old.name != name:
                old.unlink(missing_ok=True)

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


def restore_normalization(normalized: Any, stats: dict[str, Any]) -> None:
    """Set a training ``VecNormalize``'s running statistics to saved ones (it keeps updating)."""
    from ermrl.agents._normalize import set_running_stats

    if stats.get("obs_rms") is not None:
        set_running_stats(normalized.obs_rms, stats["obs_rms"])
    set_running_stats(normalized.ret_rms, stats["ret_rms"])


def saver_callback(checkpoint: RunCheckpoint, normalized: Any, records: Any) -> Any:
    """An SB3 callback that saves ``checkpoint`` at the start of a rollout once ``every`` steps
    have passed since the last save (``records()`` gives the episode records to save)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class CheckpointSaver(BaseCallback):
        last = -1

        def _on_training_start(self) -> None:
            self.last = int(self.model.num_timesteps)

        def _on_rollout_start(self) -> None:
            if self.model.num_timesteps - self.last >= checkpoint.every:
                checkpoint.save(self.model, normalized, records())
                self.last = int(self.model.num_timesteps)

        def _on_step(self) -> bool:
            return True

    return CheckpointSaver()
