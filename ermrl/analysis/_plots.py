"""Test-phase figures: learning curves and final returns per agent (PNG, headless).

Every ``*_figure`` function returns a [`PaperFigure`][ermrl.analysis.PaperFigure] (shown inline by
notebooks; write it with [`save_figure`][ermrl.analysis.save_figure]).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

from ermrl.analysis._style import (
    AGENT_COLORS,
    AGENT_LABELS,
    AGENT_SHORT_LABELS,
    PaperFigure,
    agent_color,
    empty_axes,
    new_figure,
    paper_style,
    save_figure,
)

__all__ = [
    "AGENT_COLORS",
    "AGENT_LABELS",
    "Band",
    "final_returns_figure",
    "learning_curves_figure",
    "plot_learning_curves",
]

Band = Literal["std", "ci95", "sem", "none"]
_BAND_WORDS = {
    "std": "mean ± std over seeds",
    "ci95": "mean and 95% CI over seeds",
    "sem": "mean ± s.e.m. over seeds",
    "none": "mean over seeds",
}


def learning_curves_figure(
    grid: pd.DataFrame,
    *,
    title: str = "",
    agents: Sequence[str] | None = None,
    band: Band = "std",
    smooth_episodes: int | None = None,
) -> PaperFigure:
    """Learning curves per agent, mean and a band across seeds, on a common env-step grid.

    Args:
        grid: Output of [`curves_on_grid`][ermrl.analysis.curves_on_grid] (columns
            ``agent, env_step, mean, std, sem, ci95, n_seeds``).
        title: Figure title (for example the env and observation mask).
        agents: Order of the agents in the legend (default: order of appearance).
        band: ``"std"`` (mean ± std), ``"ci95"`` (Student-t 95% CI of the mean), ``"sem"``
            or ``"none"``.
        smooth_episodes: Trailing smoothing window used for ``grid``, named in the legend.

    Returns:
        The figure.
    """
    with paper_style():
        fig, ax = new_figure(figsize=(7.0, 4.8))
        order = list(agents) if agents else list(dict.fromkeys(grid["agent"]))
        for index, agent in enumerate(order):
            data = grid[grid["agent"] == agent].sort_values("env_step")
            if data.empty:
                continue
            n = int(data["n_seeds"].max())
            color = agent_color(agent, index)
            label = f"{AGENT_LABELS.get(agent, agent)}, n = {n} seed{'s' if n != 1 else ''}"
            x = data["env_step"].to_numpy()
            mean = data["mean"].to_numpy(dtype=float)
            ax.plot(x, mean, label=label, color=color, drawstyle="steps-post")
            half = _band_half_width(data, band)
            if half is not None and np.isfinite(half).any():
                ax.fill_between(
                    x,
                    mean - half,
                    mean + half,
                    color=color,
                    alpha=0.2,
                    lw=0,
                    step="post",
                )
        ax.set_xlabel("Environment steps")
        ax.set_ylabel("Episode return")
        smooth = (
            f"; {smooth_episodes}-episode trailing mean"
            if smooth_episodes and smooth_episodes > 1
            else ""
        )
        words = _BAND_WORDS[band]
        legend_title = words[0].upper() + words[1:] + smooth
        if title:
            ax.set_title(title)
        ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 4), useMathText=True)
        handles, labels = ax.get_legend_handles_labels()
        if handles:
            fig.legend(
                handles,
                labels,
                loc="outside lower center",
                ncols=min(len(handles), 2),
                frameon=False,
                title=legend_title,
            )
        else:
            empty_axes(ax, "no finished runs")
    return fig


def plot_learning_curves(
    grid: pd.DataFrame,
    path: str | Path,
    *,
    title: str = "",
    agents: Sequence[str] | None = None,
    band: Band = "std",
) -> Path:
    """Plot mean ± std learning curves per agent and write them to ``path``.

    Args:
        grid: Output of [`curves_on_grid`][ermrl.analysis.curves_on_grid].
        path: PNG file to write.
        title: Figure title (for example the env and observation mask).
        agents: Order of the agents in the legend.
        band: What the shaded band shows (see
            [`learning_curves_figure`][ermrl.analysis.learning_curves_figure]).

    Returns:
        The written path.
    """
    fig = learning_curves_figure(grid, title=title, agents=agents, band=band)
    return save_figure(fig, path)


def final_returns_figure(
    results: pd.DataFrame,
    *,
    metric: str = "final_return",
    agents: Sequence[str] | None = None,
    title: str = "",
    ylabel: str | None = None,
) -> PaperFigure:
    """Box plot of the runs' final returns per agent, with every seed drawn as a point.

    Args:
        results: Output of [`load_run_results`][ermrl.analysis.load_run_results] (one row per run).
        metric: Column plotted: ``final_return`` or ``eval_return``.
        agents: Order of the boxes (default: order of appearance).
        title: Figure title.
        ylabel: Y-axis label (default names the metric).

    Returns:
        The figure.
    """
    with paper_style():
        fig, ax = new_figure(figsize=(5.2, 4.2))
        present = (
            list(dict.fromkeys(results["agent"]))
            if not results.empty and "agent" in results
            else []
        )
        order = [a for a in (agents or present) if a in present]
        data = []
        for agent in order:
            values = pd.to_numeric(
                results.loc[results["agent"] == agent, metric], errors="coerce"
            ).to_numpy(dtype=float)
            data.append(values[np.isfinite(values)])
        if not any(len(d) for d in data):
            empty_axes(ax, f"no {metric.replace('_', ' ')} recorded")
        else:
            positions = np.arange(1, len(order) + 1)
            boxes = ax.boxplot(
                data,
                positions=positions,
                widths=0.5,
                showfliers=False,
                patch_artist=True,
                medianprops={"color": "black", "lw": 1.2},
            )
            rng = np.random.default_rng(0)
            for index, (agent, values, box) in enumerate(zip(order, data, boxes["boxes"])):
                color = agent_color(agent, index)
                box.set_facecolor(color)
                box.set_alpha(0.35)
                jitter = rng.uniform(-0.12, 0.12, size=len(values))
                ax.scatter(
                    positions[index] + jitter,
                    values,
                    s=22,
                    color=color,
                    edgecolor="black",
                    linewidth=0.5,
                    zorder=3,
                )
                if len(values):
                    ax.scatter(
                        positions[index],
                        values.mean(),
                        marker="D",
                        s=30,
                        color="white",
                        edgecolor="black",
                        zorder=4,
                        label="mean" if index == 0 else None,
                    )
            ax.set_xticks(
                positions,
                [f"{AGENT_SHORT_LABELS.get(a, a)}\nn = {len(d)}" for a, d in zip(order, data)],
            )
            ax.grid(axis="x", visible=False)
            ax.legend(frameon=False, loc="best")
        words = "Final return (mean of the last training episodes)"
        if metric == "eval_return":
            words = "Evaluation return (deterministic episodes)"
        ax.set_ylabel(ylabel or words)
        ax.set_xlabel("Agent")
        if title:
            ax.set_title(title)
    return fig


def _band_half_width(data: pd.DataFrame, band: Band) -> np.ndarray | None:
    if band == "none" or band not in data:
        return None
    return data[band].to_numpy(dtype=float)
