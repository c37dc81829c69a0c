"""Figures (PNG, headless)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pandas as pd

__all__ = ["AGENT_LABELS", "plot_learning_curves"]

AGENT_LABELS = {
    "ppo": "PPO (raw observation)",
    "res-ppo": "RES-PPO (evolved reservoir)",
    "random-res-ppo": "RES-PPO (unevolved reservoir)",
}
AGENT_COLORS = {"ppo": "tab:blue", "res-ppo": "tab:orange", "random-res-ppo": "tab:green"}


def plot_learning_curves(
    grid: pd.DataFrame,
    path: str | Path,
    *,
    title: str = "",
    agents: Sequence[str] | None = None,
) -> Path:
    """Plot mean ± std learning curves per agent.

    Args:
        grid: Output of :func:`~ermrl.analysis.curves_on_grid`.
        path: PNG file to write.
        title: Figure title (for example the env and observation mask).
        agents: Order of the agents in the legend.

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=150)
    order = list(agents) if agents else list(dict.fromkeys(grid["agent"]))
    for agent in order:
        data = grid[grid["agent"] == agent]
        if data.empty:
            continue
        n = int(data["n_seeds"].max())
        color = AGENT_COLORS.get(agent)
        label = f"{AGENT_LABELS.get(agent, agent)}, n={n} seeds"
        ax.plot(data["env_step"], data["mean"], label=label, color=color, lw=1.8)
        ax.fill_between(
            data["env_step"],
            data["mean"] - data["std"],
            data["mean"] + data["std"],
            color=color,
            alpha=0.2,
            lw=0,
        )
    ax.set_xlabel("Environment steps")
    ax.set_ylabel("Episode return (mean ± std over seeds)")
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.ticklabel_format(axis="x", style="sci", scilimits=(0, 4))
    if ax.get_legend_handles_labels()[0]:
        ax.legend(frameon=False, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
