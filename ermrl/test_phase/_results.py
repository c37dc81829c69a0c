"""Writing a test phase's run folders (``agents/<agent>/seed_<seed>/``);
[`ermrl.analysis`][ermrl.analysis] reads them."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ermrl._io import write_atomic
from ermrl.analysis._results import KEPT_RECORD_DIR, REPLAY_MODEL_FILE

__all__ = [
    "KEPT_RECORD_DIR",
    "PAPER_LAST_EPISODES",
    "REPLAY_MODEL_FILE",
    "keep_published_record",
    "last_episodes_mean",
    "write_run",
]

_RECORDS = ("settings.json", "episodes.csv", "result.json")  # result.json last: marks it finished
#: Training episodes averaged into ``last100_return``: SB3's ``rollout/ep_rew_mean`` window,
#: the metric the ER-MRL paper plots (``stats_window_size`` 100).
PAPER_LAST_EPISODES = 100


def last_episodes_mean(returns: Any, n: int = PAPER_LAST_EPISODES) -> float | None:
    """The mean of the last ``n`` episode returns (all of them when fewer), ``None`` for none."""
    values = np.asarray(returns, dtype=float)[-n:]
    values = values[np.isfinite(values)]
    return float(values.mean()) if values.size else None


def write_run(
    folder: str | Path, agent: str, result: Any, extra: dict[str, Any] | None = None
) -> None:
    """Save one run: ``episodes.csv`` (every training episode) and ``result.json`` (written last).

    Args:
        folder: The run folder.
        agent: Agent name (``ppo``, ``res-ppo``, ...).
        result: A [`RunResult`][ermrl.agents.RunResult].
        extra: More fields for ``result.json`` (reservoir parameters, ...).

    ``result.json`` also holds ``last100_return``, the mean of the last
    `PAPER_LAST_EPISODES` training episodes (the paper's metric, beside ``final_return``
    over the run's own ``n_last_episodes``), ``n_eval_episodes``, the code that trained it
    (`ermrl._code.code_identity`), when it finished (``finished``, UTC), and ``phase_steps`` when
    the learner splits its env steps into phases (``imitation-sac``).
    """
    from ermrl._code import code_identity

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
        "n_eval_episodes": len(result.eval_returns),
        "last100_return": last_episodes_mean(result.episode_returns),
        "n_episodes": len(result.episode_returns),
        "code": code_identity(),
        "finished": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        **(extra or {}),
    }
    if getattr(result, "phase_steps", None):  # a learner's own split of its env steps
        record["phase_steps"] = result.phase_steps
    write_atomic(folder / "result.json", json.dumps(record, indent=2))


def keep_published_record(folder: str | Path) -> float | None:
    """Put a run's published records back over the ones its new training wrote.

    For a run folder with a `KEPT_RECORD_DIR` (see ``ermrl run``'s restore): its records
    (``settings.json``, ``episodes.csv``, ``result.json``) replace those just written, the
    model files stay (the report replays them), and `REPLAY_MODEL_FILE` says what that
    model's training returned. A run is a function of its settings and seed only up to
    floating-point order: trained in another population layout its return can differ, so the
    published one is kept rather than replaced after the fact.

    Returns:
        The published run's final return, or ``None`` when the folder keeps no record.
    """
    import shutil

    folder = Path(folder)
    kept = folder / KEPT_RECORD_DIR
    if not (kept / "result.json").is_file():
        return None
    new = json.loads((folder / "result.json").read_text())
    write_atomic(
        folder / REPLAY_MODEL_FILE,
        json.dumps(
            {
                "note": "the model in this folder was trained again (same settings and seed) "
                "for the report's replay; the records are the published run's",
                "final_return": new.get("final_return"),
                "wall_seconds": new.get("wall_seconds"),
            },
            indent=2,
        ),
    )
    for name in _RECORDS:
        if (kept / name).is_file():
            shutil.copyfile(kept / name, folder / name)
    shutil.rmtree(kept)
    published = json.loads((folder / "result.json").read_text()).get("final_return")
    return None if published is None else float(published)
