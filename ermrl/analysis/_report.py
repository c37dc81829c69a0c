"""``ermrl report``: every figure and table of a study and its test phase, gathered in one page.

The report is built from the study storage and the test-phase folder alone::

    reports/<study>/
      report.md, report.html          the page (same content; the HTML embeds its figures, so
                                      it opens offline and still does when moved on its own)
      trials.csv, best_params.csv     the search, one row per trial / parameter
      evolution/*.png                 history, importances, slices, contour, CMA-ES generations
      interactive/*.html              the same, interactive (Optuna's plotly figures)
      test/*.png, test/*.csv          learning curves, final returns, statistics
      generalization/*.png, *.csv     per-task normalized scores (generalization studies)
      dynamics/*.png, *.npz, *.json   an episode of res-ppo: states, spectra, dominant frequency
      dynamics/mechanism*.csv         its input stream through the evolved, unevolved and W = 0
                                      reservoirs: shares of power near the gait (the mechanism)
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import math
import mimetypes
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO
from xml.etree import ElementTree

import markdown
import numpy as np
import pandas as pd
from markdown.extensions import Extension
from markdown.treeprocessors import Treeprocessor

from ermrl._code import code_versions, describe_code, mixed_code
from ermrl._io import staged_folder
from ermrl._progress import duration
from ermrl.analysis._style import save_figure, task_title
from ermrl.config import LearnerSpace
from ermrl.learners import AGENT_KINDS, evolved_agent, unevolved_agent
from ermrl.storage import folder_for

__all__ = ["ReportResult", "notebook_parameters", "write_report"]

ENV_STUDY = "ERMRL_STUDY_NAME"
ENV_STORAGE = "ERMRL_STORAGE"
ENV_RUNS = "ERMRL_RUNS"


@dataclass(frozen=True)
class ReportResult:
    """What [`write_report`][ermrl.analysis.write_report] wrote.

    Attributes:
        out: The report folder.
        markdown: ``report.md``.
        html: ``report.html`` (``None`` with ``html=False``).
        figures: ``{name: path}`` of every PNG.
        tables: ``{name: path}`` of every CSV.
        notes: Sections left out, with the reason (no test-phase folder, single-task study...).
        warnings: What a reader must know about the results, one line each (trials of several
            code versions).
    """

    out: Path
    markdown: Path
    html: Path | None
    figures: dict[str, Path] = field(default_factory=dict)
    tables: dict[str, Path] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()


def notebook_parameters(
    study_name: str, storage: str, runs: str | None = None
) -> tuple[str, str, str | None]:
    """The study, storage and test-phase folder a notebook analyses.

    The notebook's first cell names them; the environment variables ``ERMRL_STUDY_NAME``,
    ``ERMRL_STORAGE`` and ``ERMRL_RUNS`` override them (this is how CI runs the notebooks on
    a tiny study). ``runs`` defaults to ``runs/<study name>``.

    Returns:
        ``(study_name, storage, runs)``.
    """
    study_name = os.environ.get(ENV_STUDY) or study_name
    storage = os.environ.get(ENV_STORAGE) or storage
    runs = os.environ.get(ENV_RUNS) or runs or str(folder_for("runs", study_name))
    print(f"study {study_name!r} in {storage}; test-phase folder: {runs}")
    return study_name, storage, runs


# ---------------------------------------------------------------------------------------------
# A tiny document model rendered both as Markdown and as HTML.


@dataclass
class _Doc:
    blocks: list[tuple[str, Any]] = field(default_factory=list)

    def h(self, level: int, text: str) -> None:
        self.blocks.append(("h", (level, text)))

    def p(self, text: str) -> None:
        self.blocks.append(("p", text))

    def img(self, path: str, alt: str) -> None:
        self.blocks.append(("img", (path, alt)))

    def table(self, frame: pd.DataFrame) -> None:
        self.blocks.append(("table", frame))

    def code(self, text: str, lang: str = "") -> None:
        self.blocks.append(("code", (lang, text)))

    def bullets(self, items: Sequence[str]) -> None:
        self.blocks.append(("ul", list(items)))

    def markdown(self) -> str:
        out: list[str] = []
        for kind, value in self.blocks:
            if kind == "h":
                out.append("#" * value[0] + " " + value[1])
            elif kind == "p":
                out.append(value)
            elif kind == "img":
                out.append(f"![{value[1]}]({value[0]})")
            elif kind == "table":
                out.append(_md_table(value))
            elif kind == "code":
                out.append(f"```{value[0]}\n{value[1].rstrip()}\n```")
            elif kind == "ul":
                out.append("\n".join(f"- {item}" for item in value))
        return "\n\n".join(out) + "\n"

    def html(self, title: str, embed: Path | None = None) -> str:
        """The page as HTML, rendered from the Markdown by Python-Markdown.

        Raw HTML in the text is escaped, not passed through: the text comes from study names,
        file names and parameters, never from someone writing HTML.

        Args:
            title: The page title.
            embed: The folder the figures' paths are relative to. When given, every figure is
                embedded as a ``data:`` URI and links to local files become plain text, so
                that the page is one self-contained file (it still opens when moved on its
                own). Without it, figures and links refer to the files.
        """
        converter = _markdown_converter(local_links=embed is None)
        body: list[str] = []
        pending = _Doc()  # consecutive text blocks, converted together

        def flush() -> None:
            if pending.blocks:
                body.append(converter.reset().convert(pending.markdown()))
                pending.blocks.clear()

        for kind, value in self.blocks:
            if kind != "img":
                pending.blocks.append((kind, value))
                continue
            flush()
            src, alt = (html.escape(v) for v in value)
            if embed is None:
                body.append(
                    f'<figure><a href="{src}"><img src="{src}" alt="{alt}"></a>'
                    f"<figcaption>{alt}</figcaption></figure>"
                )
            else:
                body.append(
                    f'<figure><img src="{_data_uri(embed / value[0])}" alt="{alt}">'
                    f"<figcaption>{alt} (<code>{src}</code>)</figcaption></figure>"
                )
        flush()
        style = (
            "body{font-family:system-ui,sans-serif;max-width:60rem;margin:2rem auto;padding:0 1rem;"
            "line-height:1.45;color:#222}img{max-width:100%;border:1px solid #ddd}"
            "figure{margin:1rem 0}figcaption{color:#555;font-size:.9rem}"
            "table{border-collapse:collapse;margin:.5rem 0;display:block;overflow-x:auto}"
            "td,th{border:1px solid #ccc;padding:.25rem .5rem;text-align:right}"
            "th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}"
            "pre{background:#f6f6f6;padding:.75rem;overflow-x:auto;font-size:.85rem}"
            "code{font-size:.9em}"
        )
        return (
            '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f"<title>{html.escape(title)}</title><style>{style}</style></head><body>\n"
            + "\n".join(body)
            + "\n</body></html>\n"
        )


def _fmt(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, float):
        if math.isnan(value):
            return "–"
        if value != 0 and (abs(value) >= 1e5 or abs(value) < 1e-3):
            return f"{value:.3e}"
        return f"{value:.4g}"
    return str(value)


def _md_table(frame: pd.DataFrame) -> str:
    header = "| " + " | ".join(str(c) for c in frame.columns) + " |"
    rule = "|" + "|".join("---" for _ in frame.columns) + "|"
    rows = [
        "| " + " | ".join(_fmt(v).replace("|", "\\|") for v in row) + " |"
        for row in frame.itertuples(index=False)
    ]
    return "\n".join([header, rule, *rows])


def _is_local(target: str) -> bool:
    """Whether a link target names a local file (no URL scheme, not an anchor of the page)."""
    return not re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:|^#", target)


class _LocalLinksAsText(Treeprocessor):
    """Writes a link to a local file as its text and path, for a self-contained page."""

    def run(self, root: ElementTree.Element) -> None:
        for link in root.iter("a"):
            target = link.get("href", "")
            if not _is_local(target):
                continue
            link.tag = "span"
            link.attrib.clear()
            path = ElementTree.SubElement(link, "code")
            path.text = target
            path.tail = ")"
            if len(link) > 1:  # the label has elements of its own: " (" follows the last
                label = link[-2]
                label.tail = (label.tail or "") + " ("
            else:
                link.text = (link.text or "") + " ("


class _ReportMarkdown(Extension):
    """The report's Markdown dialect: tables, fenced code, raw HTML escaped; local links as
    text when the page must stand alone."""

    def __init__(self, local_links: bool) -> None:
        super().__init__()
        self.local_links = local_links

    def extendMarkdown(self, md: markdown.Markdown) -> None:  # noqa: N802 (the library's name)
        # Python-Markdown's documented way to escape raw HTML instead of passing it through.
        md.preprocessors.deregister("html_block")
        md.inlinePatterns.deregister("html")
        if not self.local_links:
            md.treeprocessors.register(_LocalLinksAsText(md), "ermrl_local_links", 0)


def _markdown_converter(local_links: bool) -> markdown.Markdown:
    return markdown.Markdown(
        extensions=["tables", "fenced_code", "sane_lists", _ReportMarkdown(local_links)],
        output_format="html",
    )


def _data_uri(path: Path) -> str:
    """The file as a ``data:`` URI (base64), for a figure embedded in a self-contained page."""
    mime = mimetypes.guess_type(path.name)[0] or "application/octet-stream"
    return f"data:{mime};base64,{base64.b64encode(path.read_bytes()).decode('ascii')}"


# ---------------------------------------------------------------------------------------------


class _Progress:
    """One line per report step with its time and an ETA (silenced by ``quiet``).

    Not `ermrl._progress.Progress`, which counts env steps at a rate: a report's steps are
    a handful of unlike sections; the ETA is written as that module's lines write theirs.
    """

    def __init__(self, total: int, quiet: bool, stream: TextIO | None) -> None:
        self.total = total
        self.quiet = quiet
        self.stream = stream
        self.done = 0
        self.started = time.perf_counter()

    def step(self, name: str, func: Callable[[], Any]) -> Any:
        began = time.perf_counter()
        result = func()
        self.done += 1
        if not self.quiet:
            elapsed = time.perf_counter() - self.started
            eta = elapsed / self.done * (self.total - self.done)
            print(
                f"[report {self.done}/{self.total}] {name} | {time.perf_counter() - began:.1f}s"
                f" | ETA {duration(eta)}",
                file=self.stream or sys.stdout,
                flush=True,
            )
        return result


def write_report(
    study_name: str,
    storage: str,
    *,
    runs: str | Path | None = None,
    out: str | Path | None = None,
    band: str = "ci95",
    dynamics: bool = True,
    interactive: bool = True,
    html_page: bool = True,
    quiet: bool = True,
    stream: TextIO | None = None,
) -> ReportResult:
    """Write the figures, tables and ``report.md`` of a study and its test phase.

    Args:
        study_name: The study.
        storage: Its storage URL.
        runs: The test-phase folder (default ``runs/<study_name>`` when it exists).
        out: Report folder (default ``reports/<study_name>``).
        band: Learning-curve band: ``ci95``, ``std``, ``sem`` or ``none``.
        dynamics: Record an episode of ``res-ppo`` (and ``random-res-ppo``) for the reservoir
            dynamics section when the test phase saved models.
        interactive: Also write Optuna's interactive plotly figures as HTML.
        html_page: Also write ``report.html``.
        quiet: No progress lines.
        stream: Where progress lines go.

    Returns:
        What was written.

    Raises:
        ermrl.storage.StudyNotFound: no such study.
        ermrl.analysis.RunFolderError: a file of the test-phase folder is damaged (checked
            before anything is written).
        ermrl.envs.UnknownEnvError: the test phase's ``config.yaml`` names an env id that is
            not registered (checked before anything is written).
    """
    from ermrl import __version__
    from ermrl.analysis._replay import load_trained_agent
    from ermrl.analysis._results import check_run_folder
    from ermrl.analysis._study import open_study, study_config_or_none

    out = Path(out) if out is not None else folder_for("reports", study_name)
    runs_path = Path(runs) if runs is not None else folder_for("runs", study_name)
    runs_given = runs is not None
    study = open_study(study_name, storage)  # first: no empty report folder for a bad study
    if runs_path.is_dir():
        # Every file the report reads, checked up front: a damaged one (or an env id that is
        # not registered) stops the report before its folder is created.
        check_run_folder(runs_path)
        if dynamics:  # and the runs the dynamics section replays
            for agent, seed in _dynamics_runs(runs_path, study_config_or_none(study)):
                load_trained_agent(runs_path, agent, seed)
    # Written into a staged folder, moved into --out once complete: a full disk or a
    # read-only folder leaves no partial report (nor an earlier one half overwritten).
    with staged_folder(out) as stage:
        state = _State(out=stage, study=study, storage=storage)
        has_runs = (runs_path / "agents").is_dir()
        if not has_runs:
            why = "does not exist" if not runs_path.exists() else "has no agents/ folder"
            state.notes.append(
                f"test phase: {runs_path} {why}"
                + ("" if runs_given else " (pass --runs, or run `ermrl test` first)")
            )
        steps: list[tuple[str, Callable[[], Any]]] = [
            ("study and trials", lambda: _study_section(state)),
            ("evolution figures", lambda: _evolution_section(state)),
        ]
        if interactive:
            steps.append(("interactive HTML figures", lambda: _interactive_section(state)))
        steps.append(("generalization", lambda: _generalization_section(state)))
        if has_runs:
            steps.append(
                ("test-phase figures and statistics", lambda: _test_section(state, runs_path, band))
            )
            if dynamics:
                steps.append(("reservoir dynamics", lambda: _dynamics_section(state, runs_path)))
        progress = _Progress(len(steps) + 1, quiet, stream)
        for name, func in steps:
            progress.step(name, func)

        def finish() -> tuple[Path, Path | None]:
            doc = _Doc()
            doc.h(1, f"Report: study `{study_name}`")
            doc.p(
                f"Generated {_dt.datetime.now().isoformat(timespec='seconds')} by ermrl "
                f"{__version__} from `{storage}`"
                + (f" and `{runs_path}`" if has_runs else "")
                + "."
            )
            if state.notes:
                doc.p("Left out:")
                doc.bullets(state.notes)
            for section in [*state.sections, *([state.appendix] if state.appendix else [])]:
                for kind, value in section.blocks:
                    doc.blocks.append((kind, value))
            md_path = stage / "report.md"
            md_path.write_text(doc.markdown())
            html_path = None
            if html_page:
                html_path = stage / "report.html"
                html_path.write_text(doc.html(f"ermrl report: {study_name}", embed=stage))
            return md_path, html_path

        md_path, html_path = progress.step("report.md", finish)

    def moved(path: Path) -> Path:
        return out / path.relative_to(stage)

    return ReportResult(
        out=out,
        markdown=moved(md_path),
        html=None if html_path is None else moved(html_path),
        figures={name: moved(path) for name, path in state.figures.items()},
        tables={name: moved(path) for name, path in state.tables.items()},
        notes=tuple(state.notes),
        warnings=tuple(state.warnings),
    )


@dataclass
class _State:
    out: Path
    study: Any
    storage: str
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    figures: dict[str, Path] = field(default_factory=dict)
    tables: dict[str, Path] = field(default_factory=dict)
    sections: list[_Doc] = field(default_factory=list)
    config: Any = None
    frame: pd.DataFrame | None = None
    title: str = ""
    params: list[str] = field(default_factory=list)
    evolution_doc: _Doc | None = None
    appendix: _Doc | None = None

    def figure(self, name: str, fig: Any, rel: str) -> str:
        self.figures[name] = save_figure(fig, self.out / rel)
        return rel

    def csv(self, name: str, frame: pd.DataFrame, rel: str) -> str:
        path = self.out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        frame.to_csv(path, index=False)
        self.tables[name] = path
        return rel


def _evolved_row(config: Any) -> tuple[str, str]:
    """What the study evolved, as one row of the study table."""
    space = config.space
    if isinstance(space, LearnerSpace):
        return ("Evolved", f"the {space.learner} learner's {len(space.genes)} genes (no encoder)")
    from ermrl.encoders import encoder_of_family

    encoder = encoder_of_family(space.family)
    if encoder is None:
        return ("Reservoir", f"{space.n_reservoirs} x {space.family}")
    return ("Reservoir", encoder.describe(space))


def _study_section(state: _State) -> None:
    import yaml

    from ermrl.analysis._study import (
        best_params_table,
        param_names,
        study_config_or_none,
        study_overview,
        trials_frame,
        trials_table,
    )

    study = state.study
    overview = study_overview(study)
    config = study_config_or_none(study)
    state.config = config
    state.frame = trials_frame(study)
    state.params = param_names(study, config)
    state.title = task_title(overview.env_id, overview.observe) or overview.name
    # The file has ermrl study export's columns (Optuna's, then ermrl's); the report's own
    # figures and tables read the analysis frame.
    trials_rel = state.csv("trials", trials_table(study), "trials.csv")
    best = best_params_table(study, config)
    state.csv("best_params", best, "best_params.csv")

    doc = _Doc()
    doc.h(2, "Study")
    counts = ", ".join(f"{n} {s}" for s, n in overview.counts.items() if n) or "none"
    rows = [
        ("Study", f"`{overview.name}`"),
        ("Storage", f"`{state.storage}`"),
        ("Kind", overview.kind),
        ("Task", state.title if overview.env_id else "several tasks (see the configuration)"),
        ("Trials", f"{overview.n_trials} ({counts}); table: [{trials_rel}]({trials_rel})"),
    ]
    if config is not None:
        search = config.search
        budget = config.problem.budget
        rows += [
            (
                "Sampler",
                f"{search.sampler} (restart {search.restart}, popsize "
                f"{search.popsize or 'default'}), target {search.n_trials} trials",
            ),
            (
                "Fitness",
                f"{budget.fitness}: mean over {len(config.problem.seeds)} seed(s) of "
                + (
                    f"the last {budget.n_last_episodes} training episodes"
                    if budget.fitness == "last"
                    else f"{budget.n_eval_episodes} evaluation episodes"
                )
                + f", {budget.training_steps} training steps per seed",
            ),
            _evolved_row(config),
        ]
    if overview.best_number is not None:
        rows.append(("Best trial", f"#{overview.best_number}, fitness {overview.best_value:.4g}"))
    if overview.command:
        rows.append(("Command", f"`{overview.command}`"))
    if overview.version:
        rows.append(("ermrl version", overview.version))
    versions = code_versions(
        t.user_attrs.get("ermrl_code") for t in study.get_trials(deepcopy=False)
    )
    mixed = mixed_code(versions)
    if len(versions) == 1:
        rows.append(("Code", describe_code(versions[0][0])))
    doc.table(pd.DataFrame(rows, columns=["", "value"]))
    if mixed is not None:
        state.warnings.append(mixed)
        doc.p(f"**Warning:** {mixed}.")
    doc.h(3, "Trials by state")
    doc.table(pd.DataFrame([overview.counts]))
    doc.h(3, "Best parameters")
    if best.empty:
        doc.p("No COMPLETE trial yet.")
    else:
        doc.table(best)
    state.sections.append(doc)
    appendix = _Doc()
    appendix.h(2, "Appendix: the study's configuration")
    if overview.config:
        appendix.p("As stored in the study (user attribute `ermrl_config`).")
        appendix.code(yaml.safe_dump(overview.config, sort_keys=False), "yaml")
    else:
        appendix.p("The study has no `ermrl_config` attribute (not created by ermrl).")
    state.appendix = appendix


def _evolution_section(state: _State) -> None:
    from ermrl.analysis._study import (
        fitness_label,
        generations_figure,
        generations_frame,
        optimization_history_figure,
        param_contour_figure,
        param_importances,
        param_importances_figure,
        param_ranges,
        param_slices_figure,
    )

    study, frame, config = state.study, state.frame, state.config
    assert frame is not None
    ylabel = fitness_label(config)
    ranges = param_ranges(study, config)
    doc = _Doc()
    doc.h(2, "Evolution")
    rel = state.figure(
        "optimization_history",
        optimization_history_figure(frame, title=state.title, ylabel=ylabel),
        "evolution/optimization_history.png",
    )
    doc.img(rel, "Fitness of every trial and the best so far")
    importances = param_importances(study)
    rel = state.figure(
        "param_importances",
        param_importances_figure(importances, title=state.title),
        "evolution/param_importances.png",
    )
    doc.img(rel, "Parameter importances (PED-ANOVA)")
    rel = state.figure(
        "param_slices",
        param_slices_figure(frame, state.params, ranges=ranges, title=state.title, ylabel=ylabel),
        "evolution/param_slices.png",
    )
    doc.img(rel, "Fitness against each evolved hyperparameter")
    main = [k for k in importances if k in state.params][:2] or state.params[:2]
    if len(main) == 2:
        rel = state.figure(
            "param_contour",
            param_contour_figure(
                frame,
                main[1],
                main[0],
                ranges=ranges,
                title=state.title,
                zlabel=ylabel.replace("\n", " "),
            ),
            "evolution/param_contour.png",
        )
        doc.img(rel, f"Fitness over the two most important parameters ({main[0]}, {main[1]})")
    else:
        state.notes.append("contour: fewer than two evolved parameters")
    gens = generations_frame(study)
    rel = state.figure(
        "cma_generations",
        generations_figure(gens, title=state.title, ylabel=ylabel),
        "evolution/cma_generations.png",
    )
    doc.img(rel, "Fitness per CMA-ES generation")
    if importances:
        doc.p(
            "Importances: "
            + ", ".join(f"`{k}` {v:.2f}" for k, v in importances.items())
            + " (PED-ANOVA; unreliable with few trials)."
        )
    state.evolution_doc = doc
    state.sections.append(doc)


def _interactive_section(state: _State) -> None:
    from ermrl.analysis._study import write_interactive_evolution

    written = write_interactive_evolution(
        state.study, state.out / "interactive", state.params or None
    )
    links = [
        f"[{name.replace('_', ' ')}](interactive/{Path(v).name})"
        for name, v in written.items()
        if isinstance(v, Path)
    ]
    missing = [f"{name}: {v}" for name, v in written.items() if not isinstance(v, Path)]
    doc = state.evolution_doc or _Doc()
    if links:
        doc.p(
            "Interactive versions, in the report folder (open in a browser, offline): "
            + ", ".join(links)
            + "."
        )
    for item in missing:
        state.notes.append(f"interactive {item}")
    if state.evolution_doc is None:
        state.sections.append(doc)


def _generalization_section(state: _State) -> None:
    from ermrl.analysis._generalization import (
        is_generalization_study,
        task_scores_figure,
        task_scores_frame,
    )

    if not is_generalization_study(state.study):
        state.notes.append("generalization: single-task study (no per-task normalized scores)")
        return
    scores = task_scores_frame(state.study)
    doc = _Doc()
    doc.h(2, "Generalization")
    state.csv("task_scores", scores, "generalization/task_scores.csv")
    rel = state.figure(
        "task_scores",
        task_scores_figure(scores, title=f"Study {state.study.study_name}: per-task scores"),
        "generalization/task_scores.png",
    )
    doc.img(rel, "Per-task normalized scores")
    complete = scores[(scores["state"] == "COMPLETE") & scores["value"].notna()]
    if not complete.empty:
        best_number = complete.sort_values("value").iloc[-1]["number"]
        best = complete[complete["number"] == best_number][["env_id", "normalized", "return"]]
        doc.p(f"Best trial #{int(best_number)}, per task:")
        doc.table(best.rename(columns={"normalized": "normalized score", "return": "mean return"}))
        _iqm_paragraph(doc, state.study, int(best_number))
    state.sections.append(doc)


def _iqm_paragraph(doc: _Doc, study: Any, number: int) -> None:
    """The IQM over tasks of one trial's per-seed normalized scores, with its stratified CI."""
    from ermrl.analysis._generalization import task_seed_scores
    from ermrl.analysis._stats import aggregate_iqm, few_seeds_flag

    trial = next((t for t in study.get_trials(deepcopy=False) if t.number == number), None)
    scores = task_seed_scores(trial.user_attrs) if trial is not None else {}
    result = aggregate_iqm(scores)
    if result.n_tasks == 0:
        return
    flag = few_seeds_flag(result.n_runs)
    doc.p(
        f"Aggregate over the {result.n_tasks} tasks: interquartile mean (IQM) of the per-seed "
        f"normalized scores {result.iqm:.4g}, 95% stratified bootstrap CI "
        f"{_interval(result.ci_low, result.ci_high)} (each task's seeds resampled within the "
        f"task, 10 000 resamples; {result.n_runs} seed(s) per task)"
        + (f". **{flag.capitalize()}: the interval is rough.**" if flag else ".")
        + " The IQM is the mean of the middle half of all (task, seed) scores: less swayed by "
        "one outlying task or seed than the mean, less noisy than the median."
    )


def _test_section(state: _State, runs: Path, band: str) -> None:
    from ermrl.analysis._plots import final_returns_figure, learning_curves_figure
    from ermrl.analysis._results import (
        curves_on_grid,
        load_curves,
        load_run_config,
        load_run_results,
    )
    from ermrl.analysis._stats import (
        FEW_SEEDS,
        compare_agents,
        few_seeds_flag,
        final_returns_table,
    )

    results = load_run_results(runs)
    curves = load_curves(runs)
    try:
        run_config = load_run_config(runs)
    except FileNotFoundError:
        run_config = {}
    task = run_config.get("task") or {}
    title = task_title(task.get("env_id"), task.get("observe")) or state.title
    present = list(dict.fromkeys(results["agent"])) if not results.empty else []
    table = list(AGENT_KINDS)  # read now: an encoder registered after import has its place
    order = [a for a in table if a in present] + [a for a in present if a not in table]
    doc = _Doc()
    doc.h(2, f"Test phase (`{runs}`)")
    settings = run_config.get("settings") or {}
    facts = []
    if run_config.get("trial") is not None:
        params = run_config.get("params") or {}
        facts.append(
            f"`{_evolved_agent(state)}` uses trial #{run_config['trial']}: "
            + ", ".join(f"`{k}` = {v:.4g}" for k, v in params.items())
        )
    if settings:
        facts.append(
            f"{settings.get('training_steps')} training steps per run, seeds "
            f"{' '.join(str(s) for s in settings.get('seeds', []))}"
        )
    if facts:
        doc.bullets(facts)
    if results.empty:
        doc.p("No finished run yet.")
        state.sections.append(doc)
        return
    smooth = 10
    grid = curves_on_grid(curves, smooth_episodes=smooth)
    rel = state.figure(
        "learning_curves",
        learning_curves_figure(
            grid,
            title=title,
            agents=order,
            band=band,  # type: ignore[arg-type]
            smooth_episodes=smooth,
        ),
        "test/learning_curves.png",
    )
    doc.img(rel, "Learning curves (training episodes)")
    rel = state.figure(
        "final_returns",
        final_returns_figure(results, agents=order, title=title),
        "test/final_returns.png",
    )
    doc.img(rel, "Final return of every run")
    table = final_returns_table(results, order)
    state.csv("final_returns", table, "test/final_returns.csv")
    doc.h(3, "Final returns")
    doc.p(
        "Final return of a run: mean return of its last training episodes. "
        f"Mean, sample std and Student-t 95% CI of the mean across seeds (flagged below "
        f"{FEW_SEEDS} seeds)."
    )
    doc.table(_agent_table(table, ["agent", "n_seeds", "mean", "std", "ci95", "median"]))
    if (
        "eval_return" in results
        and pd.to_numeric(results["eval_return"], errors="coerce").notna().any()
    ):
        eval_table = final_returns_table(results, order, metric="eval_return")
        state.csv("eval_returns", eval_table, "test/eval_returns.csv")
        doc.h(3, "Evaluation returns (deterministic episodes)")
        doc.table(_agent_table(eval_table, ["agent", "n_seeds", "mean", "std", "ci95"]))
    evolved = _evolved_agent(state)
    comparison = compare_agents(results, evolved, [a for a in order if a != evolved])
    state.csv("comparison", comparison, "test/comparison.csv")
    doc.h(3, f"`{evolved}` against the baselines")
    if comparison.empty:
        doc.p(f"Needs finished runs of `{evolved}` and of a baseline.")
    else:
        flags = [
            few_seeds_flag(int(r.n_candidate), int(r.n_baseline))
            for r in comparison.itertuples(index=False)
        ]
        if any(flags):
            n_min = int(comparison[["n_candidate", "n_baseline"]].min().min())
            doc.p(
                f"**{few_seeds_flag(n_min).capitalize()}: every interval below is rough.** The "
                f"percentile bootstrap cannot reach beyond the range of {n_min} values and comes "
                "out too narrow; read Welch's t interval and its p-value first, and run more "
                "seeds before drawing a conclusion."
            )
        doc.table(
            pd.DataFrame(
                {
                    "baseline": comparison["baseline"],
                    f"seeds {evolved}": comparison["n_candidate"],
                    "seeds baseline": comparison["n_baseline"],
                    "mean difference": comparison["mean_diff"],
                    "95% bootstrap CI": _intervals(comparison, "boot_ci"),
                    "95% Welch t CI": _intervals(comparison, "welch_ci"),
                    "p (Welch, two-sided)": comparison["p_value"],
                    "95% paired CI": _intervals(comparison, "paired_ci"),
                    "flag": flags,
                }
            )
        )
        doc.p(
            f"Mean difference = mean(`{evolved}`) − mean(baseline) of the final returns. Three "
            "95% intervals of it: the percentile bootstrap (each agent's seeds resampled, 10 000 "
            "resamples), Student's t with Welch-Satterthwaite degrees of freedom (Welch's "
            "unequal-variance t-test, whose two-sided p-value is given), and the paired "
            "bootstrap of the per-seed differences over the seeds both agents ran (same env and "
            f"initialization streams). Below {FEW_SEEDS} seeds per agent a comparison is "
            "flagged: the bootstrap is then too narrow and can exclude 0 where Welch's interval "
            "does not. The t statistic and degrees of freedom are in `test/comparison.csv`."
        )
    state.sections.append(doc)


def _interval(low: float, high: float) -> str:
    """``[low, high]`` with a sign on each end; ``–`` when undefined."""
    if not (math.isfinite(low) and math.isfinite(high)):
        return "–"
    return f"[{low:+.4g}, {high:+.4g}]"


def _intervals(frame: pd.DataFrame, prefix: str) -> list[str]:
    """The ``{prefix}_low``/``{prefix}_high`` columns of ``frame`` as interval cells."""
    return [
        _interval(float(low), float(high))
        for low, high in zip(frame[f"{prefix}_low"], frame[f"{prefix}_high"], strict=True)
    ]


def _agent_table(table: pd.DataFrame, columns: Sequence[str]) -> pd.DataFrame:
    """A [`final_returns_table`][ermrl.analysis.final_returns_table] as shown: the CI as one cell,
    flagged."""
    from ermrl.analysis._stats import few_seeds_flag

    shown = pd.DataFrame(
        {
            "seeds" if c == "n_seeds" else "95% CI (Student t)" if c == "ci95" else c: (
                _intervals(table, "ci95") if c == "ci95" else table[c]
            )
            for c in columns
        }
    )
    shown["flag"] = [few_seeds_flag(int(n)) for n in table["n_seeds"]]
    return shown


def _evolved_agent(state: _State) -> str:
    """The report's study's evolved agent (``res-ppo``, or ``rtu-res-ppo`` for an RTU study)."""
    return evolved_agent(state.config.space.family if state.config else None)


def _dynamics_runs(runs: Path, config: Any) -> list[tuple[str, int]]:
    """``(agent, seed)`` the dynamics section replays: the evolved agent's smallest saved seed,
    and the unevolved agent on that seed when it was saved too (none without the former)."""
    from ermrl.analysis._replay import available_runs

    family = config.space.family if config else None
    evolved, unevolved = evolved_agent(family), unevolved_agent(family)
    models = available_runs(runs)
    seeds = sorted(s for a, s in models if a == evolved)
    if not seeds:
        return []
    return [(evolved, seeds[0])] + (
        [(unevolved, seeds[0])] if (unevolved, seeds[0]) in models else []
    )


def _dynamics_section(state: _State, runs: Path) -> None:
    from ermrl.analysis._dynamics import (
        record_dynamics,
        spectrum_comparison_figure,
        spectrum_summary,
        write_dynamics,
    )

    evolved = _evolved_agent(state)
    replayed = _dynamics_runs(runs, state.config)
    if not replayed:
        state.notes.append(
            f"reservoir dynamics: no saved {evolved} policy.pt in {runs} (test phase run with "
            f"--no-save-models, without {evolved}, or by an older ermrl that saved only "
            "model.zip, which is never unpickled: re-train)"
        )
        return
    seed = replayed[0][1]
    recordings = {agent: record_dynamics(runs, agent, s) for agent, s in replayed}
    doc = _Doc()
    doc.h(2, "Reservoir dynamics")
    rec = recordings[evolved]
    doc.p(
        f"One deterministic episode of `{evolved}`, seed {seed} ({rec.n_steps} steps, return "
        f"{rec.episode_return:.4g}); arrays in `dynamics/` (`.npz`: observations, actions, "
        "rewards, reservoir states)."
    )
    retrained = _retrained_note(runs, replayed)
    if retrained:
        doc.p(retrained)
    rows = []
    for agent, recording in recordings.items():
        paths = write_dynamics(recording, state.out / "dynamics")
        for key in ("dynamics", "spectrum"):
            state.figures[f"{agent}_{key}"] = paths[key]
        if agent == evolved:
            doc.img(
                f"dynamics/{paths['dynamics'].name}",
                "Observations, actions and the first 20 reservoir units",
            )
            doc.img(f"dynamics/{paths['spectrum'].name}", "Power spectra of one episode")
        summary = spectrum_summary(recording)
        unit = summary["frequency_unit"]
        for name, info in summary["signals"].items():
            f = info["dominant_frequency"]
            rows.append(
                {
                    "agent": agent,
                    "signal": name,
                    f"dominant frequency ({unit})": f if f is not None else math.nan,
                    f"period ({'s' if unit == 'Hz' else 'steps'})": info["dominant_period"]
                    if info["dominant_period"] is not None
                    else math.nan,
                }
            )
    if len(recordings) > 1:
        rel = state.figure(
            "spectrum_comparison",
            spectrum_comparison_figure(recordings),
            "dynamics/spectrum_comparison.png",
        )
        doc.img(rel, "Reservoir spectra, evolved against unevolved reservoir")
    table = pd.DataFrame(rows)
    state.csv("dominant_frequencies", table, "dynamics/dominant_frequencies.csv")
    doc.h(3, "Dominant frequencies")
    doc.table(table)
    doc.p(
        "Welch spectra of linearly detrended 256-step Hann segments, averaged over dimensions; "
        "the dominant frequency is the strongest spectral peak (a local maximum at least twice "
        "its surroundings), so a decaying start-of-episode transient is not taken for an "
        "oscillation."
    )
    if evolved == "res-ppo" and rec.states.shape[1] > 0:
        _mechanism_section(state, runs, rec, doc)
    state.sections.append(doc)


def _retrained_note(runs: Path, replayed: Sequence[tuple[str, int]]) -> str:
    """One sentence per replayed run whose model was trained again after its records were
    published (``replay-model.json``, written by ``ermrl run``'s restore): the replayed policy
    is then not the published run's, and the two returns say how far they are apart."""
    import json

    from ermrl.analysis._results import (
        REPLAY_MODEL_FILE,
        RESULT_FILE,
        read_run_result,
        run_dir,
    )

    parts = []
    for agent, seed in replayed:
        folder = run_dir(runs, agent, seed)
        try:
            again = json.loads((folder / REPLAY_MODEL_FILE).read_text())
            published = read_run_result(folder / RESULT_FILE)["final_return"]
        except (OSError, ValueError):  # RunFolderError is a ValueError
            continue
        new = again.get("final_return") if isinstance(again, dict) else None
        if not isinstance(new, int | float):
            continue
        parts.append(
            f"`{agent}` seed {seed}'s model was trained again for this replay (same settings "
            f"and seed; published runs carry no model): its training ended at a return of "
            f"{new:.4g}, the published run's at {published:.4g}, since a run repeats only up "
            f"to floating-point order (`{REPLAY_MODEL_FILE}` in its run folder)."
        )
    return " ".join(parts)


def _mechanism_section(state: _State, runs: Path, recording: Any, doc: _Doc) -> None:
    """Oscillations at the gait or leaky integration: the recorded episode's input stream drives
    the evolved, the unevolved and the W = 0 reservoirs (`ermrl.analysis._mechanism`), and
    ``res-ppo − leaky-res-ppo`` is judged when both ran."""
    from ermrl.analysis._mechanism import (
        ABLATED,
        MECHANISM_FILE,
        MECHANISM_SPECTRA_FILE,
        SpectralCriterion,
        mechanism_figure,
        mechanism_reservoirs,
        mechanism_table,
        mechanism_verdict,
        report_rule,
        reservoir_spectra,
        spectral_outcome,
        write_mechanism,
    )
    from ermrl.analysis._verdicts import TaskRuns, judge, load_test_runs

    criterion = SpectralCriterion()
    space = getattr(state.config, "space", None)
    defaults = getattr(space, "default_reservoirs", None)
    reference = tuple(defaults()) if callable(defaults) else ()
    encoder, reservoirs = mechanism_reservoirs(runs, recording.seed, reference)
    test_runs = load_test_runs(runs)
    seeds = sorted(
        {int(s) for s in test_runs.loc[test_runs["agent"] == "res-ppo", "seed"]} | {recording.seed}
    )
    measured = reservoir_spectra(recording, encoder, reservoirs, seeds, criterion=criterion)
    paths = write_mechanism(measured, state.out / "dynamics")
    state.tables["mechanism"] = paths["mechanism"]
    state.tables["mechanism_spectra"] = paths["spectra"]
    spectral = spectral_outcome(measured.table, criterion)
    rule = report_rule()
    tests = judge([TaskRuns("report", "task", test_runs)], {"report": rule})
    primary = tests[tests["metric"] == rule.primary].to_dict("records")
    verdict = mechanism_verdict(primary[0] if primary else None, spectral)
    doc.h(3, "Mechanism: oscillations at the gait, or leaky integration?")
    doc.p(
        f"**Mechanism ({rule.primary}):** {verdict.headline}; {verdict.text}. Here the family "
        f"of `res-ppo − {ABLATED}` is this one test; the reproduction page adjusts it over every "
        "task of the question (Holm)."
    )
    error = measured.replay_error
    replay = (
        "exactly"
        if error == 0
        else f"to within {error:.2g}"
        if math.isfinite(error)
        else "(not checked: the recorded seed's weights were not rebuilt)"
    )
    doc.p(
        f"The input stream of this episode (observation, previous action, previous reward) "
        f"drives three reservoirs, each with the weights of the {len(seeds)} `res-ppo` test "
        "seed(s): the evolved one, the unevolved reference and the evolved one with W = 0 "
        f"(`{ABLATED}`'s). Criterion: {criterion.describe()}. Replayed on the recorded seed's "
        f"weights, the evolved reservoir reproduces the states the policy saw {replay}. Per "
        f"seed: `dynamics/{MECHANISM_FILE}`; mean spectra: `dynamics/{MECHANISM_SPECTRA_FILE}`."
    )
    table = mechanism_table(spectral)
    if not table.empty:
        doc.table(table)
    rel = state.figure(
        "mechanism_spectra",
        mechanism_figure(measured.spectra, spectral),
        "dynamics/mechanism_spectra.png",
    )
    doc.img(rel, "Spectra of the joint angles and of three reservoirs driven by one input stream")
