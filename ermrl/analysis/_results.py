"""Loading test-phase run folders, learning curves on a common grid, and summaries."""

from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

__all__ = [
    "RUNS_DIR",
    "run_dir",
    "load_run_results",
    "load_curves",
    "curves_on_grid",
    "summarize",
    "load_run_config",
    "t_quantile",
]

RUNS_DIR = "agents"
CURVE_COLUMNS = ["agent", "seed", "env_step", "episode_return"]
GRID_COLUMNS = ["agent", "env_step", "mean", "std", "sem", "ci95", "n_seeds"]
CONFIG_FILE = "config.yaml"


def run_dir(out: str | Path, agent: str, seed: int) -> Path:
    """Folder of one (agent, seed) run inside a test-phase output folder."""
    return Path(out) / RUNS_DIR / agent / f"seed_{seed}"


def load_run_results(out: str | Path) -> pd.DataFrame:
    """One row per finished run (those with a ``result.json``) under ``out``."""
    rows = []
    for path in sorted(Path(out).glob(f"{RUNS_DIR}/*/seed_*/result.json")):
        rows.append(json.loads(path.read_text()))
    return pd.DataFrame(rows)


def load_curves(out: str | Path) -> pd.DataFrame:
    """All finished runs' training episodes: columns ``agent, seed, env_step, episode_return``."""
    frames = []
    for path in sorted(Path(out).glob(f"{RUNS_DIR}/*/seed_*/result.json")):
        record = json.loads(path.read_text())
        episodes = pd.read_csv(path.parent / "episodes.csv")
        episodes.insert(0, "seed", record["seed"])
        episodes.insert(0, "agent", record["agent"])
        frames.append(episodes)
    if not frames:
        return pd.DataFrame(columns=CURVE_COLUMNS)
    return pd.concat(frames, ignore_index=True)[CURVE_COLUMNS]


def curves_on_grid(
    curves: pd.DataFrame, n_points: int = 100, smooth_episodes: int = 10
) -> pd.DataFrame:
    """Learning curves of every agent on a common env-step grid, mean and std across seeds.

    Each run's episode returns are smoothed with a trailing mean over ``smooth_episodes``
    episodes, then read at each grid step as the value of the latest finished episode.

    Args:
        curves: Columns ``agent, seed, env_step, episode_return``.
        n_points: Grid size, from the first to the last episode end of all runs.
        smooth_episodes: Trailing window of the smoothing.

    Returns:
        Columns ``agent, env_step, mean, std, sem, ci95, n_seeds``: ``std`` is the sample
        standard deviation across seeds (``ddof=1``; 0 with one seed), ``sem`` the standard error
        of the mean and ``ci95`` the half-width of the Student-t 95% confidence interval of the
        mean (NaN with one seed). Grid points before a run's first episode do not count for
        that run.
    """
    if curves.empty:
        return pd.DataFrame(columns=GRID_COLUMNS)
    grid = np.unique(
        np.linspace(curves["env_step"].min(), curves["env_step"].max(), n_points).astype(np.int64)
    )
    rows = []
    for agent, group in curves.groupby("agent", sort=False):
        per_seed = []
        for _, run in group.groupby("seed"):
            run = run.sort_values("env_step")
            smooth = run["episode_return"].rolling(smooth_episodes, min_periods=1).mean().to_numpy()
            idx = np.searchsorted(run["env_step"].to_numpy(), grid, side="right") - 1
            values = np.where(idx >= 0, smooth[np.clip(idx, 0, None)], np.nan)
            per_seed.append(values)
        stack = np.vstack(per_seed)
        counts = np.sum(~np.isnan(stack), axis=0)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(np.where(counts > 0, stack, 0.0), axis=0)
            std = np.nanstd(np.where(counts > 0, stack, 0.0), axis=0, ddof=1)
        std = np.where(counts > 1, std, 0.0)
        sem = np.where(counts > 1, std / np.sqrt(np.maximum(counts, 1)), np.nan)
        ci95 = sem * t_quantile(counts - 1)
        for step, m, s, e, h, c in zip(grid, mean, std, sem, ci95, counts):
            if c > 0:
                rows.append(
                    {
                        "agent": agent,
                        "env_step": int(step),
                        "mean": m,
                        "std": s,
                        "sem": e,
                        "ci95": h,
                        "n_seeds": int(c),
                    }
                )
    return pd.DataFrame(rows, columns=GRID_COLUMNS)


def t_quantile(dof: np.ndarray | int, confidence: float = 0.95) -> np.ndarray:
    """Two-sided Student-t quantile for ``dof`` degrees of freedom (NaN where ``dof < 1``)."""
    from scipy import stats

    dof_arr = np.asarray(dof, dtype=float)
    with np.errstate(all="ignore"):
        q = stats.t.ppf(0.5 + confidence / 2, np.where(dof_arr >= 1, dof_arr, 1.0))
    return np.where(dof_arr >= 1, q, np.nan)


def summarize(results: pd.DataFrame, agents: Sequence[str] | None = None) -> pd.DataFrame:
    """Final returns per agent: ``agent, n_seeds, final_return_mean, final_return_std, ...``.

    The final return of a run is the mean return of its last training episodes (the fitness
    measure of evolution); with evaluation episodes, their mean is summarized too. Standard
    deviations are sample standard deviations across seeds (``ddof=1``; 0 with one seed).
    """
    columns = [
        "agent",
        "n_seeds",
        "final_return_mean",
        "final_return_std",
        "eval_return_mean",
        "eval_return_std",
        "seeds",
    ]
    if results.empty:
        return pd.DataFrame(columns=columns)
    rows = []
    order = list(agents) if agents else list(dict.fromkeys(results["agent"]))
    for agent in order:
        group = results[results["agent"] == agent]
        if group.empty:
            continue
        final = group["final_return"].astype(float)
        evals = (
            group["eval_return"].astype(float) if "eval_return" in group else pd.Series(dtype=float)
        )
        rows.append(
            {
                "agent": agent,
                "n_seeds": len(group),
                "final_return_mean": final.mean(),
                "final_return_std": final.std(ddof=1) if len(final) > 1 else 0.0,
                "eval_return_mean": evals.mean() if evals.notna().any() else np.nan,
                "eval_return_std": (
                    (evals.std(ddof=1) if evals.notna().sum() > 1 else 0.0)
                    if evals.notna().any()
                    else np.nan
                ),
                "seeds": " ".join(str(s) for s in sorted(group["seed"])),
            }
        )
    return pd.DataFrame(rows, columns=columns)


def load_run_config(out: str | Path) -> dict[str, Any]:
    """The ``config.yaml`` of a test-phase folder (task, encoder, agents, study, ...).

    The task's env id is checked against the registry (:func:`ermrl.envs.check_registered_env_id`):
    a ``module:Id`` there is refused, never imported, since the file may come from anyone.

    Raises:
        FileNotFoundError: ``out`` has no ``config.yaml`` (not a test-phase folder).
        ermrl.envs.UnknownEnvError: its task's env id is not a registered id.
    """
    import yaml

    from ermrl.envs import check_registered_env_id

    path = Path(out) / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found: {out} is not a test-phase folder (made by `ermrl test --out`)"
        )
    config = dict(yaml.safe_load(path.read_text()) or {})
    task = config.get("task")
    if isinstance(task, dict) and "env_id" in task:
        check_registered_env_id(task["env_id"], path)
    return config
