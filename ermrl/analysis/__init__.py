"""Reading results back: run folders, learning curves, summaries and figures."""

from ermrl.analysis._plots import AGENT_LABELS, plot_learning_curves
from ermrl.analysis._results import (
    curves_on_grid,
    load_curves,
    load_run_results,
    run_dir,
    summarize,
    write_atomic,
    write_run,
)

__all__ = [
    "AGENT_LABELS",
    "curves_on_grid",
    "load_curves",
    "load_run_results",
    "plot_learning_curves",
    "run_dir",
    "summarize",
    "write_atomic",
    "write_run",
]
