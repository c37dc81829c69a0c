"""TensorBoard logs of a population's runs, under the names SB3's PPO logs for one run.

SB3 writes, after each rollout and update (``log_interval=1`` for on-policy algorithms),
``rollout/ep_rew_mean`` and ``rollout/ep_len_mean`` over its last ``stats_window_size`` (100)
episodes, ``time/fps``, and the update's ``train/*`` terms (means over its minibatches). A
population run writes the same scalars at the same env steps into its own folder, laid out as
SB3 lays out ``tensorboard_log`` (``<folder>/PPO_1/events.out.tfevents.*``), so that one
TensorBoard shows runs of both backends side by side.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["PopulationLogs"]

# SB3's default ``stats_window_size``: the episodes rollout/ep_*_mean average over.
STATS_WINDOW = 100
# SB3 names a run's folder <tb_log_name>_<n>; PPO's tb_log_name is "PPO".
RUN_FOLDER = "PPO_1"


class PopulationLogs:
    """One TensorBoard writer per run of a population (``None`` folders: that run logs nothing).

    Args:
        folders: Per job, in the population's job order, its ``tensorboard_log`` folder.

    Raises:
        ImportError: the ``tensorboard`` package is missing (as SB3 raises for one run).
    """

    def __init__(self, folders: Sequence[str | Path | None]) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.writers: list[Any] = [
            None if folder is None else SummaryWriter(str(Path(folder) / RUN_FOLDER))
            for folder in folders
        ]

    def wants_losses(self) -> bool:
        """Whether any run logs (then the update computes its loss terms)."""
        return any(w is not None for w in self.writers)

    def write(
        self,
        step: int,
        alive: Sequence[int],
        episodes: Sequence[Sequence[tuple[float, int]]],
        lengths: Sequence[Sequence[int]],
        fps: float,
        train: dict[str, np.ndarray],
    ) -> None:
        """Write one rollout's and update's scalars at env step ``step``.

        Args:
            step: Env steps per agent so far (SB3's ``num_timesteps``).
            alive: Position in the population's arrays -> job index.
            episodes: Per job, its finished episodes ``(return, env step at its end)``.
            lengths: Per job, its finished episodes' lengths.
            fps: Env steps per second per agent since the training started.
            train: The update's terms, each an array over positions (``train/<name>``).
        """
        for position, job in enumerate(alive):
            writer = self.writers[job]
            if writer is None:
                continue
            recent = episodes[job][-STATS_WINDOW:]
            if recent:
                writer.add_scalar(
                    "rollout/ep_rew_mean", float(np.mean([r for r, _ in recent])), step
                )
            if lengths[job]:  # (a run resumed from a checkpoint counts lengths from there)
                writer.add_scalar(
                    "rollout/ep_len_mean", float(np.mean(lengths[job][-STATS_WINDOW:])), step
                )
            writer.add_scalar("time/fps", float(fps), step)
            for name, values in train.items():
                writer.add_scalar(f"train/{name}", float(np.asarray(values)[position]), step)

    def close(self) -> None:
        """Flush and close every writer."""
        for writer in self.writers:
            if writer is not None:
                writer.close()
