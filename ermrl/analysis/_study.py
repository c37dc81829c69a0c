"""Reading an evolution study back from its storage: trial tables and evolution figures.

Everything here needs only the study name and the storage URL (the study holds its own
configuration as the user attribute ``ermrl_config``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import pandas as pd

from ermrl.analysis._style import PaperFigure, empty_axes, new_figure, paper_style

if TYPE_CHECKING:
    import optuna
    from matplotlib.ticker import MaxNLocator

    from ermrl.config import EvolveConfig

__all__ = [
    "PARAM_LABELS",
    "StudyOverview",
    "best_params_table",
    "fitness_label",
    "generations_figure",
    "generations_frame",
    "open_study",
    "optimization_history_figure",
    "param_contour_figure",
    "param_importances",
    "param_importances_figure",
    "param_label",
    "param_names",
    "param_ranges",
    "param_slices_figure",
    "study_config_or_none",
    "study_overview",
    "trials_frame",
    "trials_table",
    "TRIALS_TABLE_EXTRA",
    "write_interactive_evolution",
]

PARAM_LABELS = {
    "sr": "Spectral radius",
    "lr": "Leak rate",
    "input_scaling": "Input scaling",
    "lr_max": "Highest leak rate",  # a multi-timescale reservoir's band (--multiscale)
    "lr_min_ratio": "Lowest / highest leak rate",
}
TRIAL_STATES = ("COMPLETE", "PRUNED", "FAIL", "RUNNING", "WAITING")


@dataclass(frozen=True)
class StudyOverview:
    """What a study is and how far it got.

    Attributes:
        name: Study name.
        kind: ``ermrl_kind`` user attribute (``evolve``, ``evolve-generalization``, ...).
        direction: ``MAXIMIZE`` or ``MINIMIZE``.
        counts: Number of trials per state (``COMPLETE``, ``PRUNED``, ``FAIL``, ...).
        best_number: Number of the best COMPLETE trial (``None`` if none).
        best_value: Its fitness.
        best_params: Its parameters.
        command: The command that created the study.
        version: The ermrl version that created it.
        config: The stored configuration as a plain dict (empty if absent).
        env_id: The task's env id (``None`` when the config has no single task).
        observe: The task's observation mask.
    """

    name: str
    kind: str
    direction: str
    counts: dict[str, int]
    best_number: int | None
    best_value: float | None
    best_params: dict[str, float]
    command: str
    version: str
    config: dict[str, Any] = field(default_factory=dict)
    env_id: str | None = None
    observe: str | None = None

    @property
    def n_trials(self) -> int:
        return sum(self.counts.values())


def open_study(study_name: str, storage: str) -> optuna.Study:
    """Load an existing study (its name, the storage URL) for reading.

    Raises:
        ermrl.storage.StudyNotFound: no study of that name (the error lists the names there).
        ermrl.storage.StorageError: the storage cannot be opened.
    """
    from ermrl.storage import load_study

    return load_study(study_name, storage)


def study_config_or_none(study: optuna.Study) -> EvolveConfig | None:
    """The study's [`EvolveConfig`][ermrl.config.EvolveConfig], or ``None`` when it has none
    readable."""
    from ermrl.search import study_config

    try:
        return study_config(study)
    except Exception:  # other kinds of studies store other configurations
        return None


def study_overview(study: optuna.Study) -> StudyOverview:
    """Name, kind, trial counts per state, best trial and stored configuration of a study."""
    counts = {state: 0 for state in TRIAL_STATES}
    for trial in study.get_trials(deepcopy=False):
        counts[trial.state.name] = counts.get(trial.state.name, 0) + 1
    try:
        best = study.best_trial
        best_number, best_value, best_params = best.number, best.value, dict(best.params)
    except ValueError:
        best_number, best_value, best_params = None, None, {}
    attrs = study.user_attrs
    config = attrs.get("ermrl_config")
    config = dict(config) if isinstance(config, Mapping) else {}
    task = (config.get("problem") or {}).get("task") if config else None
    return StudyOverview(
        name=study.study_name,
        kind=str(attrs.get("ermrl_kind", "unknown")),
        direction=study.direction.name,
        counts=counts,
        best_number=best_number,
        best_value=best_value,
        best_params=best_params,
        command=str(attrs.get("ermrl_command", "")),
        version=str(attrs.get("ermrl_version", "")),
        config=config,
        env_id=task.get("env_id") if isinstance(task, Mapping) else None,
        observe=task.get("observe") if isinstance(task, Mapping) else None,
    )


def trials_frame(study: optuna.Study) -> pd.DataFrame:
    """One row per trial, every state.

    Returns:
        Columns ``number, state, value, duration_s, <one column per parameter>, restart,
        generation, global_generation, popsize, fail_reason`` (CMA-ES columns are NaN for
        trials not sampled by CMA-ES).
    """
    from ermrl.search import cma_generation_info

    generations = {row["number"]: row for row in cma_generation_info(study)}
    rows = []
    names: dict[str, None] = {}
    for trial in study.get_trials(deepcopy=False):
        duration = (
            (trial.datetime_complete - trial.datetime_start).total_seconds()
            if trial.datetime_complete and trial.datetime_start
            else math.nan
        )
        row: dict[str, Any] = {
            "number": trial.number,
            "state": trial.state.name,
            "value": trial.value if trial.values is not None and len(trial.values) == 1 else None,
            "duration_s": duration,
        }
        for name, value in trial.params.items():
            names[name] = None
            row[name] = value
        gen = generations.get(trial.number, {})
        for key in ("restart", "generation", "global_generation", "popsize"):
            row[key] = gen.get(key)
        row["fail_reason"] = trial.user_attrs.get("fail_reason")
        rows.append(row)
    columns = ["number", "state", "value", "duration_s", *names]
    columns += ["restart", "generation", "global_generation", "popsize", "fail_reason"]
    frame = pd.DataFrame(rows, columns=columns)
    for key in ("value", "duration_s", *names, "restart", "generation", "global_generation"):
        frame[key] = pd.to_numeric(frame[key], errors="coerce")
    frame["popsize"] = pd.to_numeric(frame["popsize"], errors="coerce")
    return frame.sort_values("number").reset_index(drop=True)


# ermrl's columns after Optuna's, in the trials table (see trials_table).
TRIALS_TABLE_EXTRA = (
    "duration_s", "retry_of", "restart", "generation", "global_generation", "popsize",
)  # fmt: skip


def _plain_cell(value: Any) -> Any:
    """Lists and dicts (per-seed returns, versions) as JSON text, so CSV and Parquet agree."""
    import json

    if isinstance(value, (list, dict, tuple)):
        return json.dumps(value, default=str)
    return value


def trials_table(study: optuna.Study) -> pd.DataFrame:
    """Every trial as one row, for files: Optuna's own columns, then ermrl's.

    The one table behind ``ermrl study export --out X.csv|.parquet`` and the report's
    ``trials.csv``: the columns of `optuna.study.Study.trials_dataframe` (``number``,
    ``value``, ``datetime_start``, ``datetime_complete``, ``duration``, ``params_<name>``,
    ``user_attrs_<name>``, ``state``), then `TRIALS_TABLE_EXTRA`: ``duration_s`` (the
    duration in seconds), ``retry_of`` (the trial a retry replaces) and the CMA-ES generation
    columns of [`trials_frame`][ermrl.analysis.trials_frame], and last ``value`` when Optuna's
    column is ``values_<metric>`` (a study with a metric name, as ermrl's are; earlier exports had
    ``value``). Lists and dicts in user attributes are JSON text.

    Returns:
        One row per trial, by number (an empty frame with no columns for a study without
        trials).
    """
    frame = study.trials_dataframe(multi_index=False)
    if frame.empty:
        return frame
    frame = frame.sort_values("number").reset_index(drop=True)
    for column in frame.columns:
        if column.startswith("user_attrs_"):
            frame[column] = frame[column].map(_plain_cell)
    trials = {t.number: t for t in study.get_trials(deepcopy=False)}
    extra = trials_frame(study).set_index("number")
    frame["duration_s"] = frame["number"].map(extra["duration_s"])
    frame["retry_of"] = frame["number"].map(lambda n: trials[n].system_attrs.get("failed_trial"))
    for key in ("restart", "generation", "global_generation", "popsize"):
        frame[key] = frame["number"].map(extra[key])
    if "value" not in frame.columns and len(study.directions) == 1:
        # Optuna names it values_<metric> when the study has a metric name (ermrl's do).
        frame["value"] = frame["number"].map(lambda n: trials[n].value)
    return frame


def param_names(study: optuna.Study, config: EvolveConfig | None = None) -> list[str]:
    """The evolved parameters: from the configuration, else from the trials."""
    if config is not None:
        return list(config.space.param_names)
    names: dict[str, None] = {}
    for trial in study.get_trials(deepcopy=False):
        names.update(dict.fromkeys(trial.params))
    return list(names)


def param_ranges(
    study: optuna.Study, config: EvolveConfig | None = None
) -> dict[str, tuple[float, float, bool]]:
    """``{name: (low, high, log)}`` of every evolved parameter."""
    if config is not None:
        return {k: (r.low, r.high, r.log) for k, r in config.space.ranges().items()}
    ranges: dict[str, tuple[float, float, bool]] = {}
    for trial in study.get_trials(deepcopy=False):
        for name, dist in trial.distributions.items():
            low, high = getattr(dist, "low", None), getattr(dist, "high", None)
            if low is not None and high is not None:
                ranges[name] = (float(low), float(high), bool(getattr(dist, "log", False)))
    return ranges


def best_params_table(study: optuna.Study, config: EvolveConfig | None = None) -> pd.DataFrame:
    """The parameters of the trial a test phase selects, with their search ranges.

    The selected trial is [`select_trial`][ermrl.search.select_trial]'s: the re-evaluated best when
    the study records a complete, current re-evaluation, else the best evolution fitness (the noisy
    maximum a test phase would otherwise take), so that the report names the trial the test phase
    tests.

    Returns:
        Columns ``trial, selection, parameter, value, low, high, scale`` (empty without a
        COMPLETE trial).
    """
    from ermrl.config import ConfigError
    from ermrl.search import select_trial

    columns = ["trial", "selection", "parameter", "value", "low", "high", "scale"]
    try:
        best, how = select_trial(study)
    except (ConfigError, ValueError):
        return pd.DataFrame(columns=columns)
    ranges = param_ranges(study, config)
    rows = []
    for name, value in best.params.items():
        low, high, log = ranges.get(name, (math.nan, math.nan, False))
        rows.append(
            {
                "trial": best.number,
                "selection": how,
                "parameter": name,
                "value": value,
                "low": low,
                "high": high,
                "scale": "log" if log else "linear",
            }
        )
    return pd.DataFrame(rows, columns=columns)


def param_importances(study: optuna.Study) -> dict[str, float]:
    """Parameter importances (Optuna's default PED-ANOVA evaluator), highest first.

    Returns:
        ``{name: importance}`` summing to 1, or ``{}`` when they cannot be computed (fewer
        than two COMPLETE trials, or no variation of the fitness).
    """
    import optuna

    complete = study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
    if len(complete) < 2:
        return {}
    try:
        importances = optuna.importance.get_param_importances(study)
    except Exception:  # any evaluator failure means "not available"
        return {}
    values = {k: float(v) for k, v in importances.items()}
    if not values or not all(math.isfinite(v) for v in values.values()):
        return {}
    return values


def generations_frame(study: optuna.Study) -> pd.DataFrame:
    """CMA-ES generation of every COMPLETE trial.

    Returns:
        Columns ``number, value, restart, generation, global_generation, popsize, regime``
        (see [`ermrl.search.cma_generation_info`][ermrl.search.cma_generation_info]); rows without a
        generation are trials not sampled by CMA-ES.
    """
    from ermrl.search import cma_generation_info

    columns = ["number", "value", "restart", "generation", "global_generation", "popsize", "regime"]
    return pd.DataFrame(cma_generation_info(study), columns=columns)


def fitness_label(config: EvolveConfig | None, *, short: bool = False) -> str:
    """Axis label of the fitness, e.g. ``"Fitness: mean return of the last 10 episodes"``."""
    if config is None:
        return "Fitness (mean episode return)"
    budget = config.problem.budget
    if short:
        return "Fitness (mean episode return)"
    if budget.fitness == "eval":
        what = f"mean return of {budget.n_eval_episodes} evaluation episodes"
    else:
        what = f"mean return of the last {budget.n_last_episodes} training episodes"
    return f"Fitness\n({what})"


def param_label(name: str) -> str:
    """``"Spectral radius sr"``, ``"Leak rate lr_1 (reservoir 1)"``, ..."""
    base, _, index = name.rpartition("_")
    if base and index.isdigit() and base in PARAM_LABELS:
        return f"{PARAM_LABELS[base]} {name} (reservoir {index})"
    if name in PARAM_LABELS:
        return f"{PARAM_LABELS[name]} {name}" if name != "input_scaling" else PARAM_LABELS[name]
    return name


# ---------------------------------------------------------------------------------------------
# Figures.


def optimization_history_figure(
    frame: pd.DataFrame,
    *,
    title: str = "",
    ylabel: str = "Fitness (mean episode return)",
) -> PaperFigure:
    """Fitness of every COMPLETE trial against its number, with the best so far.

    Args:
        frame: Output of [`trials_frame`][ermrl.analysis.trials_frame].
        title: Figure title.
        ylabel: Y-axis label (see [`fitness_label`][ermrl.analysis.fitness_label]).

    Returns:
        The figure.
    """
    with paper_style():
        fig, ax = new_figure(figsize=(7.0, 4.2))
        complete = frame[(frame["state"] == "COMPLETE") & frame["value"].notna()]
        if complete.empty:
            empty_axes(ax, "no COMPLETE trial yet")
        else:
            x = complete["number"].to_numpy()
            y = complete["value"].to_numpy(dtype=float)
            ax.scatter(
                x,
                y,
                s=22,
                color="tab:blue",
                alpha=0.75,
                edgecolor="none",
                label=f"complete trials (n = {len(complete)})",
            )
            ax.plot(
                x,
                np.maximum.accumulate(y),
                color="tab:red",
                drawstyle="steps-post",
                label="best so far",
            )
            others = frame[frame["state"].isin(["PRUNED", "FAIL"])]
            for state, marker in (("PRUNED", "v"), ("FAIL", "x")):
                sub = others[others["state"] == state]
                if not sub.empty:
                    ax.scatter(
                        sub["number"],
                        np.full(len(sub), np.nanmin(y)),
                        marker=marker,
                        color="0.45",
                        s=24,
                        label=f"{state.lower()} trials (n = {len(sub)}), drawn at the minimum",
                    )
            ax.set_xlabel("Trial number")
            ax.legend(frameon=True, framealpha=0.85, loc="best")
            ax.xaxis.get_major_locator().set_params(integer=True)
        ax.set_ylabel(ylabel)
        if title:
            ax.set_title(title)
    return fig


def param_importances_figure(importances: Mapping[str, float], *, title: str = "") -> PaperFigure:
    """Horizontal bars of parameter importances (PED-ANOVA, normalized to sum to 1).

    Args:
        importances: Output of [`param_importances`][ermrl.analysis.param_importances].
        title: Figure title.

    Returns:
        The figure.
    """
    with paper_style():
        height = 1.4 + 0.45 * max(len(importances), 1)
        fig, ax = new_figure(figsize=(6.0, height))
        if not importances:
            empty_axes(ax, "importances need at least 2 COMPLETE trials with different fitness")
        else:
            items = sorted(importances.items(), key=lambda kv: kv[1])
            labels = [param_label(k) for k, _ in items]
            values = [v for _, v in items]
            bars = ax.barh(labels, values, color="tab:blue", alpha=0.8, height=0.6)
            for bar, value in zip(bars, values):
                ax.text(
                    bar.get_width() + 0.01,
                    bar.get_y() + bar.get_height() / 2,
                    f"{value:.2f}",
                    va="center",
                    fontsize=9,
                )
            ax.set_xlim(0, max(1.0, max(values) * 1.15))
            ax.set_xlabel("Importance for the fitness (PED-ANOVA, sums to 1)")
            ax.grid(axis="y", visible=False)
        if title:
            ax.set_title(title)
    return fig


def param_slices_figure(
    frame: pd.DataFrame,
    params: Sequence[str],
    *,
    ranges: Mapping[str, tuple[float, float, bool]] | None = None,
    title: str = "",
    ylabel: str = "Fitness (mean episode return)",
) -> PaperFigure:
    """Fitness against each evolved parameter (one panel per parameter), colored by trial.

    Args:
        frame: Output of [`trials_frame`][ermrl.analysis.trials_frame].
        params: Parameters to plot (for example ``("sr", "lr", "input_scaling")``).
        ranges: ``{name: (low, high, log)}`` search ranges (x limits and scale).
        title: Figure title.
        ylabel: Y-axis label of the first panel.

    Returns:
        The figure.
    """
    ranges = dict(ranges or {})
    params = [p for p in params if p in frame]
    ncols = min(max(len(params), 1), 3)
    nrows = max(1, math.ceil(len(params) / ncols))
    with paper_style():
        fig, axes = new_figure(
            nrows, ncols, figsize=(3.1 * ncols + 1.0, 3.3 * nrows), squeeze=False, sharey=True
        )
        complete = frame[(frame["state"] == "COMPLETE") & frame["value"].notna()]
        flat = list(axes.ravel())
        if not params or complete.empty:
            empty_axes(
                flat[0], "no COMPLETE trial yet" if params else "no trial with parameters yet"
            )
        scatter = None
        best = complete.loc[complete["value"].idxmax()] if not complete.empty else None
        for ax, name in zip(flat, params):
            scatter = ax.scatter(
                complete[name],
                complete["value"],
                c=complete["number"],
                cmap="viridis",
                s=22,
                alpha=0.85,
                edgecolor="none",
            )
            if best is not None:
                ax.scatter(
                    [best[name]],
                    [best["value"]],
                    marker="*",
                    s=160,
                    color="tab:red",
                    edgecolor="black",
                    linewidth=0.5,
                    zorder=3,
                    label="best trial",
                )
            low, high, log = ranges.get(name, (math.nan, math.nan, False))
            if log:
                ax.set_xscale("log")
            if math.isfinite(low) and math.isfinite(high):
                ax.set_xlim(low, high)
            ax.set_xlabel(param_label(name) + (" (log scale)" if log else ""))
        for ax in flat[max(len(params), 1) :]:
            ax.set_visible(False)
        for row in axes:
            row[0].set_ylabel(ylabel)
        if best is not None and params:
            flat[0].legend(frameon=True, framealpha=0.85, loc="best")
        if scatter is not None and not complete.empty:
            bar = fig.colorbar(scatter, ax=list(axes.ravel()), shrink=0.9, pad=0.02)
            bar.set_label("Trial number")
            # A colorbar's default locator is an AutoLocator, a MaxNLocator: it takes ``integer``
            # (matplotlib's stubs type the getter as the base Locator).
            locator = cast("MaxNLocator", bar.ax.yaxis.get_major_locator())
            locator.set_params(integer=True)
        if title:
            fig.suptitle(title)
    return fig


def param_contour_figure(
    frame: pd.DataFrame,
    x: str,
    y: str,
    *,
    ranges: Mapping[str, tuple[float, float, bool]] | None = None,
    title: str = "",
    zlabel: str = "Fitness (mean episode return)",
) -> PaperFigure:
    """Fitness over two parameters: trials as points on a linearly interpolated contour.

    The interpolation is done in the search space's coordinates (log10 for log-scale
    parameters) inside the convex hull of the trials; with fewer than 3 non-collinear trials
    only the points are drawn.

    Args:
        frame: Output of [`trials_frame`][ermrl.analysis.trials_frame].
        x: Parameter on the x axis.
        y: Parameter on the y axis.
        ranges: ``{name: (low, high, log)}`` search ranges.
        title: Figure title.
        zlabel: Colorbar label.

    Returns:
        The figure.
    """
    ranges = dict(ranges or {})
    with paper_style():
        fig, ax = new_figure(figsize=(6.2, 4.8))
        complete = frame[(frame["state"] == "COMPLETE") & frame["value"].notna()]
        if complete.empty or x not in complete or y not in complete:
            empty_axes(ax, "no COMPLETE trial yet")
            if title:
                ax.set_title(title)
            return fig
        xlog = ranges.get(x, (0, 0, False))[2]
        ylog = ranges.get(y, (0, 0, False))[2]

        def fwd(v: np.ndarray, log: bool) -> np.ndarray:
            return np.log10(v) if log else v

        px = fwd(complete[x].to_numpy(dtype=float), xlog)
        py = fwd(complete[y].to_numpy(dtype=float), ylog)
        z = complete["value"].to_numpy(dtype=float)
        vmin, vmax = float(np.min(z)), float(np.max(z))
        if vmin == vmax:
            vmin, vmax = vmin - 0.5, vmax + 0.5
        mappable = None
        if len(z) >= 3:
            try:
                from scipy.interpolate import griddata

                gx = np.linspace(px.min(), px.max(), 120)
                gy = np.linspace(py.min(), py.max(), 120)
                mx, my = np.meshgrid(gx, gy)
                mz = griddata((px, py), z, (mx, my), method="linear")
                if np.isfinite(mz).any():
                    inv_x = 10**mx if xlog else mx
                    inv_y = 10**my if ylog else my
                    mappable = ax.contourf(
                        inv_x, inv_y, mz, levels=14, cmap="viridis", vmin=vmin, vmax=vmax, alpha=0.9
                    )
            except Exception:  # collinear or duplicate points: points only
                mappable = None
        points = ax.scatter(
            complete[x],
            complete[y],
            c=z,
            cmap="viridis",
            vmin=vmin,
            vmax=vmax,
            s=26,
            edgecolor="black",
            linewidth=0.5,
            zorder=3,
        )
        ax.scatter([], [], s=26, color="white", edgecolor="black", linewidth=0.5, label="trials")
        best = complete.loc[complete["value"].idxmax()]
        ax.scatter(
            [best[x]],
            [best[y]],
            marker="*",
            s=220,
            color="tab:red",
            edgecolor="black",
            linewidth=0.6,
            zorder=4,
            label=f"best trial (#{int(best['number'])})",
        )
        for name, setter, lim, log in (
            (x, ax.set_xscale, ax.set_xlim, xlog),
            (y, ax.set_yscale, ax.set_ylim, ylog),
        ):
            if log:
                setter("log")
            low, high, _ = ranges.get(name, (math.nan, math.nan, False))
            if math.isfinite(low) and math.isfinite(high):
                lim(low, high)
        ax.set_xlabel(param_label(x) + (" (log scale)" if xlog else ""))
        ax.set_ylabel(param_label(y) + (" (log scale)" if ylog else ""))
        ax.grid(False)
        bar = fig.colorbar(mappable if mappable is not None else points, ax=ax, pad=0.02)
        bar.set_label(zlabel)
        ax.legend(frameon=True, framealpha=0.85, loc="best")
        if title:
            ax.set_title(title)
    return fig


def generations_figure(
    generations: pd.DataFrame,
    *,
    title: str = "",
    ylabel: str = "Fitness (mean episode return)",
) -> PaperFigure:
    """Fitness of the trials of each CMA-ES generation (box and points), and the best so far.

    Args:
        generations: Output of [`generations_frame`][ermrl.analysis.generations_frame].
        title: Figure title.
        ylabel: Y-axis label.

    Returns:
        The figure.
    """
    with paper_style():
        fig, ax = new_figure(figsize=(7.0, 4.2))
        data = generations.dropna(subset=["global_generation", "value"])
        if data.empty:
            empty_axes(ax, "no trial was sampled by CMA-ES (other sampler, or too few trials)")
            if title:
                ax.set_title(title)
            return fig
        data = data.assign(global_generation=data["global_generation"].astype(int))
        gens = sorted(data["global_generation"].unique())
        values = [data.loc[data["global_generation"] == g, "value"].to_numpy(float) for g in gens]
        ax.boxplot(
            values,
            positions=gens,
            widths=0.6,
            showfliers=False,
            patch_artist=True,
            boxprops={"facecolor": "tab:blue", "alpha": 0.25},
            medianprops={"color": "tab:blue", "lw": 1.2},
        )
        rng = np.random.default_rng(0)
        for g, v in zip(gens, values):
            ax.scatter(
                g + rng.uniform(-0.15, 0.15, size=len(v)),
                v,
                s=16,
                color="tab:blue",
                alpha=0.8,
                edgecolor="none",
            )
        best = np.maximum.accumulate([np.max(v) for v in values])
        ax.plot(gens, best, color="tab:red", marker="o", ms=3, label="best so far")
        ax.plot(
            gens,
            [np.mean(v) for v in values],
            color="0.3",
            ls="--",
            lw=1.2,
            label="generation mean",
        )
        starts = data.groupby("restart")["global_generation"].min()
        popsizes = data.groupby("restart")["popsize"].max()
        if len(starts) > 1:  # headroom for the restart labels
            low, high = ax.get_ylim()
            ax.set_ylim(low, high + 0.15 * (high - low))
        for restart, start in starts.items():
            if restart == 0 and len(starts) == 1:
                continue
            ax.axvline(start - 0.5, color="0.5", ls=":", lw=1)
            ax.text(
                start - 0.4,
                ax.get_ylim()[1],
                f"run {int(restart)}\npopsize {int(popsizes[restart])}",
                va="top",
                fontsize=9,
                color="0.3",
            )
        step = max(1, len(gens) // 12)
        ax.set_xticks(gens[::step], [str(g) for g in gens[::step]])
        pop = int(popsizes.iloc[0]) if len(popsizes) else 0
        ax.set_xlabel(
            "CMA-ES generation"
            + (f" (population size {pop})" if len(starts) == 1 and pop else " (across restarts)")
        )
        ax.set_ylabel(ylabel)
        ax.legend(frameon=False, loc="lower right")
        if title:
            ax.set_title(title)
    return fig


def write_interactive_evolution(
    study: optuna.Study, folder: str | Path, params: Sequence[str] | None = None
) -> dict[str, Path | str]:
    """Interactive HTML figures of the study (Optuna's plotly visualizations).

    The HTML files share one ``plotly.min.js`` written next to them, so they open offline.

    Args:
        study: The study.
        folder: Output folder.
        params: Parameters to show (default: all).

    Returns:
        ``{name: path}`` of the written files, or ``{name: reason}`` for a figure that could not
        be made (plotly missing, too few trials).
    """
    import optuna

    out: dict[str, Path | str] = {}
    try:
        import plotly  # noqa: F401
    except ImportError:
        return {"all": "plotly is not installed (pip install plotly)"}
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    vis = optuna.visualization
    target_name = "Fitness"
    # Optuna's plot functions are typed to take a list.
    param_list = None if params is None else list(params)
    makers = {
        "optimization_history": lambda: vis.plot_optimization_history(
            study, target_name=target_name
        ),
        "parallel_coordinate": lambda: vis.plot_parallel_coordinate(
            study, params=param_list, target_name=target_name
        ),
        "slice": lambda: vis.plot_slice(study, params=param_list, target_name=target_name),
        "contour": lambda: vis.plot_contour(study, params=param_list, target_name=target_name),
        "param_importances": lambda: vis.plot_param_importances(study, target_name=target_name),
    }
    import warnings

    for name, make in makers.items():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                figure = make()
            path = folder / f"{name}.html"
            figure.update_layout(title_text=f"{study.study_name}: {name.replace('_', ' ')}")
            figure.write_html(str(path), include_plotlyjs="directory", full_html=True)
            out[name] = path
        except Exception as err:  # one failed figure must not stop the report
            out[name] = f"not available ({type(err).__name__}: {err})"
    return out
