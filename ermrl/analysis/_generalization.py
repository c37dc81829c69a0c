"""Generalization studies: per-task normalized scores of reservoirs evolved on several tasks.

A generalization study (user attribute ``ermrl_kind == "evolve-generalization"``) records on each
trial the user attributes ``task_normalized = {env_id: score}`` and ``task_returns = {env_id:
mean return}``. Single-task studies have neither:
[`task_scores_frame`][ermrl.analysis.task_scores_frame] then returns an empty table and
[`task_scores_figure`][ermrl.analysis.task_scores_figure] says so in the figure.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from ermrl.analysis._style import PaperFigure, empty_axes, new_figure, paper_style

if TYPE_CHECKING:
    import optuna

__all__ = [
    "GENERALIZATION_KIND",
    "is_generalization_study",
    "task_scores_figure",
    "task_scores_frame",
    "task_seed_scores",
]

GENERALIZATION_KIND = "evolve-generalization"
TASK_COLUMNS = ["number", "state", "value", "env_id", "normalized", "return"]


def is_generalization_study(study: optuna.Study) -> bool:
    """Whether the study evolves reservoirs on several tasks (kind or per-task trial attributes)."""
    if study.user_attrs.get("ermrl_kind") == GENERALIZATION_KIND:
        return True
    return any(
        isinstance(t.user_attrs.get("task_normalized"), Mapping)
        for t in study.get_trials(deepcopy=False)
    )


def task_scores_frame(study: optuna.Study) -> pd.DataFrame:
    """Per-task scores of every trial that recorded them (long format).

    Returns:
        Columns ``number, state, value, env_id, normalized, return``: one row per (trial,
        task); ``normalized`` comes from ``task_normalized``, ``return`` from ``task_returns``
        (NaN when absent). Empty for a single-task study.
    """
    rows: list[dict[str, Any]] = []
    for trial in study.get_trials(deepcopy=False):
        normalized = trial.user_attrs.get("task_normalized")
        returns = trial.user_attrs.get("task_returns")
        normalized = normalized if isinstance(normalized, Mapping) else {}
        returns = returns if isinstance(returns, Mapping) else {}
        for env_id in dict.fromkeys([*normalized, *returns]):
            rows.append(
                {
                    "number": trial.number,
                    "state": trial.state.name,
                    "value": trial.value
                    if trial.values is not None and len(trial.values) == 1
                    else None,
                    "env_id": str(env_id),
                    "normalized": _number(normalized.get(env_id)),
                    "return": _number(returns.get(env_id)),
                }
            )
    frame = pd.DataFrame(rows, columns=TASK_COLUMNS)
    for key in ("value", "normalized", "return"):
        frame[key] = pd.to_numeric(frame[key], errors="coerce")
    return frame


def task_seed_scores(attrs: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Per-seed normalized scores of one generalization trial, per task.

    Each seed's raw return ``R`` (``task_seed_returns``) is normalized with the task's references
    as the fitness is, ``(R - R_random) / (R_target - R_random)`` (``task_random_returns``,
    ``task_target_returns``), so that the tasks share one scale and can be pooled by
    [`aggregate_iqm`][ermrl.analysis.aggregate_iqm].

    Args:
        attrs: The trial's user attributes (``trial.user_attrs``).

    Returns:
        ``{env_id: scores of shape (n_seeds,)}`` (NaN for a missing return); empty when the
        trial did not record per-seed returns or references (older studies, single-task ones).
    """
    seeds = attrs.get("task_seed_returns")
    randoms = attrs.get("task_random_returns")
    targets = attrs.get("task_target_returns")
    if not all(isinstance(m, Mapping) for m in (seeds, randoms, targets)):
        return {}
    assert isinstance(seeds, Mapping) and isinstance(randoms, Mapping)
    assert isinstance(targets, Mapping)
    out: dict[str, np.ndarray] = {}
    for env_id, values in seeds.items():
        low, high = _number(randoms.get(env_id)), _number(targets.get(env_id))
        if not isinstance(values, list) or not np.isfinite(low + high) or high == low:
            continue
        raw = np.array([_number(v) for v in values], dtype=np.float64)
        out[str(env_id)] = (raw - low) / (high - low)
    return out


def task_scores_figure(scores: pd.DataFrame, *, title: str = "") -> PaperFigure:
    """Per-task normalized scores: the best trial's per task, and each task's over the trials.

    Args:
        scores: Output of [`task_scores_frame`][ermrl.analysis.task_scores_frame].
        title: Figure title.

    Returns:
        The figure (a message panel for a single-task study).
    """
    with paper_style():
        data = scores[(scores["state"] == "COMPLETE") & scores["normalized"].notna()]
        if data.empty:
            fig, ax = new_figure(figsize=(6.0, 2.6))
            empty_axes(
                ax,
                "single-task study: no per-task normalized scores\n"
                "(they come from `ermrl evolve-generalization` studies)",
            )
            if title:
                ax.set_title(title)
            return fig
        fig, (left, right) = new_figure(1, 2, figsize=(10.0, 4.4))
        tasks = list(dict.fromkeys(data["env_id"]))
        per_trial = data.groupby("number")
        best_number = (
            data.dropna(subset=["value"]).sort_values("value").iloc[-1]["number"]
            if data["value"].notna().any()
            else per_trial["normalized"].mean().idxmax()
        )
        best = data[data["number"] == best_number].set_index("env_id")["normalized"]
        median = data.groupby("env_id")["normalized"].median()
        y = np.arange(len(tasks))
        left.barh(
            y + 0.2,
            [best.get(t, np.nan) for t in tasks],
            height=0.38,
            color="tab:orange",
            label=f"best trial (#{int(best_number)})",
        )
        left.barh(
            y - 0.2,
            [median.get(t, np.nan) for t in tasks],
            height=0.38,
            color="0.6",
            label="median over trials",
        )
        left.set_yticks(y, tasks)
        left.invert_yaxis()
        left.axvline(0, color="black", lw=0.8)
        left.set_xlabel("Normalized score")
        left.grid(axis="y", visible=False)
        left.legend(frameon=False, loc="best")
        left.set_title("Per task")
        for index, task in enumerate(tasks):
            sub = data[data["env_id"] == task].sort_values("number")
            right.plot(
                sub["number"],
                sub["normalized"],
                marker="o",
                ms=3,
                lw=1.0,
                alpha=0.85,
                label=task,
                color=f"C{index % 10}",
            )
        right.set_xlabel("Trial number")
        right.set_ylabel("Normalized score")
        right.set_title("Over the search")
        right.legend(frameon=False, loc="best", ncols=1 if len(tasks) <= 6 else 2)
        right.xaxis.get_major_locator().set_params(integer=True)
        if title:
            fig.suptitle(title)
    return fig


def _number(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")
