"""Writing a test phase's run folders (``agents/<agent>/seed_<seed>/``); :mod:`ermrl.analysis`
reads them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ermrl._io import write_atomic

__all__ = ["write_run"]


def write_run(
    folder: str | Path, agent: str, result: Any, extra: dict[str, Any] | None = None
) -> None:
    """Save one run: ``episodes.csv`` (every training episode) and ``result.json`` (written last).

    Args:
        folder: The run folder.
        agent: Agent name (``ppo``, ``res-ppo``, ...).
        result: A :class:`~ermrl.agents.RunResult`.
        extra: More fields for ``result.json`` (reservoir parameters, ...).

    ``result.json`` also holds ``phase_steps`` when the learner splits its env steps into
    phases (``imitation-sac``).
    """
    folder = Path(folder)
    episodes = pd.DataFrame(
        {"env_step": result.episode_steps, "episode_return": result.episode_returns}
    )
    write_atomic(folder / "episodes.csv", episodes.to_csv(index=False))
    record = {
        "agent": agent,
        "seed": result.seed,
        "env_steps": result.env_steps,
        "wall_seconds": result.wall_seconds,
        "steps_per_second": result.steps_per_second,
        "final_return": None if not np.isfinite(result.last_return) else result.last_return,
        "eval_return": result.eval_return,
        "eval_returns": result.eval_returns,
        "n_episodes": len(result.episode_returns),
        **(extra or {}),
    }
    if getattr(result, "phase_steps", None):  # a learner's own split of its env steps
        record["phase_steps"] = result.phase_steps
    write_atomic(folder / "result.json", json.dumps(record, indent=2))
