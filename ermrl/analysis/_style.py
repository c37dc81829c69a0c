"""Figure style shared by every ermrl plot: headless, paper-ready, no pyplot state.

Figures are plain `matplotlib.figure.Figure` objects (never created through ``pyplot``), so
plotting works without a display, never switches the global matplotlib backend, and leaks no
open figures. [`PaperFigure`][ermrl.analysis.PaperFigure] adds ``_repr_png_`` so that a figure
returned as the last value of a notebook cell is shown inline whatever backend the kernel uses.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import matplotlib as mpl
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from ermrl.learners import AGENT_KINDS

__all__ = [
    "AGENT_COLORS",
    "AGENT_LABELS",
    "AGENT_SHORT_LABELS",
    "PAPER_RC",
    "PaperFigure",
    "agent_color",
    "empty_axes",
    "new_figure",
    "paper_style",
    "save_figure",
    "task_title",
]

# Read from the agent table (ermrl.learners.AGENT_KINDS): an agent declared by a learner or an encoder is labelled here.
AGENT_LABELS = {name: kind.label or name for name, kind in AGENT_KINDS.items()}
AGENT_SHORT_LABELS = {name: kind.short_label or name for name, kind in AGENT_KINDS.items()}
AGENT_COLORS = {name: kind.color for name, kind in AGENT_KINDS.items() if kind.color}
_EXTRA_COLORS = ("tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan")

# Sizes are in points at the saved size (figures are saved at their nominal size in inches).
# dict[Any, Any]: matplotlib's stubs type rc keys as a Literal of every rcParam name.
PAPER_RC: dict[Any, Any] = {
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "xtick.labelsize": 9,
    "ytick.labelsize": 9,
    "legend.fontsize": 9,
    "legend.title_fontsize": 9,
    "figure.titlesize": 12,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "grid.linewidth": 0.6,
    "lines.linewidth": 1.6,
    "savefig.dpi": 200,
    "savefig.bbox": None,
    "savefig.pad_inches": 0.05,
    "image.cmap": "viridis",
}
_OBSERVE_WORDS = {
    "all": "full observation",
    "positions": "positions only",
    "velocities": "velocities only",
}


class PaperFigure(Figure):
    """A `Figure` that notebooks display inline as PNG."""

    def _repr_png_(self) -> bytes:
        buffer = io.BytesIO()
        with mpl.rc_context(PAPER_RC):
            self.savefig(buffer, format="png", dpi=110)
        return buffer.getvalue()


@contextmanager
def paper_style() -> Iterator[None]:
    """Apply ermrl's figure style (font sizes >= 9 pt, light grid) within a ``with`` block."""
    with mpl.rc_context(PAPER_RC):
        yield


def new_figure(
    nrows: int = 1,
    ncols: int = 1,
    *,
    figsize: tuple[float, float] = (7.0, 4.5),
    squeeze: bool = True,
    **subplot_kw: Any,
) -> tuple[PaperFigure, Any]:
    """A [`PaperFigure`][ermrl.analysis.PaperFigure] with its axes, created under
    [`paper_style`][ermrl.analysis.paper_style].

    Call it inside ``with paper_style():`` so that the style applies to everything drawn.

    Args:
        nrows: Rows of axes.
        ncols: Columns of axes.
        figsize: Size in inches (the saved size; fonts are sized for it).
        squeeze: As in `matplotlib.figure.Figure.subplots`.
        **subplot_kw: More arguments for `subplots`
            (``sharex``, ``gridspec_kw``, ...).

    Returns:
        The figure and its axes (one ``Axes`` or an array of them).
    """
    fig = PaperFigure(figsize=figsize, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=squeeze, **subplot_kw)
    return fig, axes


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` (PNG, PDF or SVG from the suffix) and return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with mpl.rc_context(PAPER_RC):
        fig.savefig(path)
    return path


def agent_color(agent: str, index: int = 0) -> str:
    """The agent's color (fixed for the test-phase agents, `AGENT_COLORS`)."""
    return AGENT_COLORS.get(agent, _EXTRA_COLORS[index % len(_EXTRA_COLORS)])


def task_title(env_id: str | None, observe: str | None = None) -> str:
    """A human title for a task, e.g. ``"HalfCheetah-v5, velocities only"``."""
    if not env_id:
        return ""
    if not observe:
        return env_id
    return f"{env_id}, {_OBSERVE_WORDS.get(observe, observe)}"


def empty_axes(ax: Axes, message: str) -> None:
    """Write ``message`` in the middle of ``ax`` (a panel without data says why)."""
    ax.text(0.5, 0.5, message, ha="center", va="center", transform=ax.transAxes, color="0.35")
    ax.set_xticks([])
    ax.set_yticks([])
