"""The reproduction page: each hypothesis of an experiment file, its published results, verdicts.

It reads only plain files: the experiment files (``experiments/paper/*.yaml``) and what
``ermrl run`` published for them (per-seed ``result.json`` and ``episodes.csv`` files, the
report's figures, the study snapshot). Every number on the page can be recomputed from those
files.

The verdicts follow the rule each experiment file states in its ``verdict:`` block
([`VerdictRule`][ermrl.analysis.VerdictRule]; the rule is printed on the page): per task and
sub-question, *supported*, *contradicted* or *inconclusive* after Holm's correction over every
test of that question on the page, under each metric (the mean of the last 10 training
episodes, of the last 100 as the paper plots, and of deterministic evaluation episodes), with
the effect, both intervals, raw and adjusted p, the effects an inconclusive test still excludes,
and the seeds that would detect the observed effect. See `ermrl.analysis._verdicts`.

A task is rendered only when the trial its test phase tested can be traced to a recorded
selection in the study snapshot (the re-evaluation record, the evolution's best trial, or a
trial named by hand): an untraceable one is refused, naming what is missing. A task whose test
phase is published in part (some of the runs its file plans, ``test.agents`` x ``test.seeds``)
gets no verdict until every planned run is in: judging on the seeds that happen to have
finished would let the stopping point choose the result.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from ermrl._io import load_yaml
from ermrl.analysis._mechanism import (
    ABLATED,
    MECHANISM_FILE,
    describe_mechanism,
    mechanism_question,
    mechanism_table,
    mechanism_verdict,
    read_mechanism,
    spectral_outcome,
    without_gait,
)
from ermrl.analysis._stats import FEW_SEEDS
from ermrl.analysis._verdicts import (
    METRICS,
    NOT_RUN,
    NOT_TESTED,
    Question,
    Reference,
    TaskRuns,
    VerdictError,
    VerdictRule,
    aggregate_question,
    equivalence_text,
    excluded_effects,
    first_result_date,
    judge,
    load_test_runs,
    not_run,
    shared_runs,
    task_outcome,
)

__all__ = [
    "Hypothesis",
    "TaskFiles",
    "add_reference_runs",
    "TaskResult",
    "load_test_runs",
    "question_answer",
    "read_summary",
    "results_summary",
    "task_result",
    "trace_selection",
    "untraceable_tasks",
    "write_reproduction_page",
    "write_summary",
]

EVOLVED = "res-ppo"
UNEVOLVED = "random-res-ppo"


@dataclass
class TaskResult:
    """What the published files say about one task of one experiment.

    Attributes:
        label: The task (test task for a generalization experiment).
        folder: Its published folder.
        runs: One row per finished test run (``result.json``, with ``last100_return`` read
            from ``episodes.csv`` for runs that predate it).
        evolution: ``finished``, ``n_trials``, ``env_steps``, ``wall_seconds`` of the study.
        selection: The selected reservoir(s) and how they were chosen.
        traced: Whether the tested trial is traced to a recorded selection.
        trace: What the trace found, in words (what is missing when it failed).
        references: Baselines read from another experiment's published runs: ``{name: where
            from}`` (see [`add_reference_runs`][ermrl.analysis.add_reference_runs]).
        planned: The test runs the experiment file plans, ``{agent: seeds}`` (empty: no plan
            known, the published runs are taken as the whole phase).
    """

    label: str
    folder: Path
    runs: pd.DataFrame
    evolution: dict[str, Any] = field(default_factory=dict)
    selection: dict[str, Any] = field(default_factory=dict)
    traced: bool = True
    trace: str = ""
    references: dict[str, str] = field(default_factory=dict)
    planned: dict[str, tuple[int, ...]] = field(default_factory=dict)

    @property
    def tested(self) -> bool:
        return not self.runs.empty and EVOLVED in set(self.runs["agent"])

    @property
    def missing(self) -> dict[str, tuple[int, ...]]:
        """The planned runs not published yet, ``{agent: seeds}`` (agents with none left out)."""
        done = set()
        if not self.runs.empty:
            done = {(str(a), int(sd)) for a, sd in zip(self.runs["agent"], self.runs["seed"])}
        left = {
            a: tuple(sd for sd in seeds if (a, sd) not in done) for a, seeds in self.planned.items()
        }
        return {agent: seeds for agent, seeds in left.items() if seeds}

    @property
    def judged(self) -> bool:
        """Whether the page gives the task verdicts: tested, traced, and every planned run in."""
        return self.tested and self.traced and not self.missing

    @property
    def reference_selected(self) -> bool:
        return bool(self.selection.get("reference"))


#: What a borrowed baseline's runs must share with the task's own runs (``result.json`` keys).
_SAME_SETTING = ("env_id", "observe", "env_steps")


def _setting(values: pd.Series) -> list[Any]:
    """The distinct values of one setting of a group of runs, sorted (integers as integers)."""
    out = {int(v) if isinstance(v, float) and v.is_integer() else v for v in values.dropna()}
    try:
        return sorted(out)
    except TypeError:
        return sorted(out, key=str)


def add_reference_runs(result: TaskResult, ref: Reference, where: str = "verdict") -> None:
    """Add a baseline another experiment published ([`Reference`][ermrl.analysis.Reference]) to a
    task's runs, as agent ``ref.name``: its runs of ``ref.agent`` in the folder it names for
    the task (none named: nothing is added).

    Raises:
        VerdictError: the task has runs of its own under that name, the folder has no
            finished run of the agent, or its runs trained on another env, observation or
            budget than the task's own runs (one line).
    """
    folder = ref.tests.get(result.label)
    if folder is None:
        return
    here = f"{where}: references.{ref.name} ({result.label})"
    runs = load_test_runs(folder) if Path(folder).is_dir() else pd.DataFrame()
    runs = runs[runs["agent"] == ref.agent] if not runs.empty else runs
    runs = _run_dates(runs, Path(folder)) if not runs.empty else runs
    if runs.empty:
        raise VerdictError(f"{here}: no finished run of {ref.agent} in {folder}")
    own = result.runs
    if not own.empty and ref.name in set(own["agent"]):
        raise VerdictError(f"{here}: the task has runs of its own named {ref.name}")
    for key in _SAME_SETTING:
        if own.empty or key not in own or key not in runs:
            continue
        mine, theirs = _setting(own[key]), _setting(runs[key])
        if mine and theirs and mine != theirs:
            raise VerdictError(
                f"{here}: {folder}'s runs have {key} {theirs}, this task's {mine}: not the same "
                "setting"
            )
    runs = runs.assign(agent=ref.name)
    result.runs = pd.concat([own, runs], ignore_index=True) if not own.empty else runs
    result.references[ref.name] = f"`{ref.agent}` of `{folder}`"


def _snapshot_evolution(doc: dict[str, Any] | None, n_trials: int) -> dict[str, Any]:
    if doc is None:
        return {"finished": 0, "n_trials": n_trials, "env_steps": 0, "wall_seconds": 0.0}
    trials = doc.get("trials", [])
    done = [t for t in trials if t.get("state") in ("COMPLETE", "PRUNED")]
    steps = sum(int(t.get("user_attrs", {}).get("env_steps") or 0) for t in trials)
    wall = sum(float(t.get("user_attrs", {}).get("wall_seconds") or 0.0) for t in trials)
    for related in doc.get("related", {}).values():  # the re-evaluation runs
        for t in related.get("trials", []):
            steps += int(t.get("user_attrs", {}).get("env_steps") or 0)
            wall += float(t.get("user_attrs", {}).get("wall_seconds") or 0.0)
    return {"finished": len(done), "n_trials": n_trials, "env_steps": steps, "wall_seconds": wall}


def trace_selection(selection: dict[str, Any], snapshot: dict[str, Any] | None) -> tuple[bool, str]:
    """Whether the tested trial follows from a selection the study snapshot records.

    Args:
        selection: ``trial`` and ``selection`` (how it was chosen) of the test's ``config.yaml``.
        snapshot: The study snapshot (``study.json``), ``None`` when there is none.

    Returns:
        ``(traced, what was found or what is missing)``. A re-evaluated selection needs the
        study's complete re-evaluation record naming that trial best; a best-fitness selection
        needs that trial to be the study's best COMPLETE trial; a trial named by hand
        (``--trial``) is recorded as such in ``config.yaml`` and traced to it.
    """
    trial = selection.get("trial")
    how = str(selection.get("selection") or "")
    if trial is None:
        return True, "no evolved trial tested"
    if how.endswith("(--trial)"):
        return True, f"trial #{trial} named by hand (--trial), as config.yaml records"
    if snapshot is None:
        return (
            False,
            f"tested trial #{trial} ({how or 'no selection recorded'}), but no study snapshot (study.json) is published",
        )
    if how.startswith("re-evaluated"):
        record = (snapshot.get("user_attrs") or {}).get("ermrl_reevaluation")
        if not isinstance(record, dict):
            return False, (
                f"tested trial #{trial} as '{how}', but the published study.json holds no "
                "re-evaluation record (user attribute ermrl_reevaluation) and no related "
                "re-evaluation study"
            )
        if not record.get("complete"):
            return (
                False,
                f"tested trial #{trial} as '{how}', but the published re-evaluation is not complete",
            )
        if record.get("best_trial") != trial:
            return False, (
                f"tested trial #{trial} as '{how}', but the published re-evaluation record "
                f"ranks trial #{record.get('best_trial')} best"
            )
        rows = record.get("candidates") or []
        best: dict[str, Any] = next((r for r in rows if r.get("trial") == trial), {})
        fitness = best.get("fitness")
        value = f", re-evaluated fitness {fitness:.4g}" if isinstance(fitness, (int, float)) else ""
        return True, (
            f"trial #{trial} is the best of the {len(rows)} candidates of the published "
            f"re-evaluation record (seeds {', '.join(map(str, record.get('seeds') or []))}{value})"
        )
    if how.startswith("best evolution fitness"):
        done = [
            t for t in snapshot.get("trials", [])
            if t.get("state") == "COMPLETE" and isinstance(t.get("value"), (int, float))
        ]  # fmt: skip
        if not done:
            return (
                False,
                f"tested trial #{trial} as the best evolution fitness, but the snapshot has no COMPLETE trial with a value",
            )
        best = max(done, key=lambda t: float(t["value"]))
        if best.get("number") != trial:
            return False, (
                f"tested trial #{trial} as the best evolution fitness, but the snapshot's best "
                f"is trial #{best.get('number')}"
            )
        return (
            True,
            f"trial #{trial} is the study's best COMPLETE trial (fitness {float(best['value']):.4g})",
        )
    return (
        False,
        f"tested trial #{trial}, but config.yaml does not say how it was selected ({how!r})",
    )


def _selection(test: Path) -> dict[str, Any]:
    """The tested trial and how it was chosen, from a test phase's ``config.yaml``."""
    config = test / "config.yaml"
    if not config.exists():
        return {}
    doc = load_yaml(config.read_text()) or {}
    agents = doc.get("agents") or {}
    return {
        "trial": doc.get("trial"),
        "selection": doc.get("selection"),
        "reservoirs": agents.get(EVOLVED),
        # The evolved agent's reservoirs are the unevolved one's: the reference won.
        "reference": bool(agents.get(EVOLVED)) and agents.get(EVOLVED) == agents.get(UNEVOLVED),
    }


def _read_snapshot(snapshot: Path) -> dict[str, Any] | None:
    return json.loads(snapshot.read_text()) if snapshot.is_file() else None


def task_result(
    folder: Path,
    label: str,
    n_trials: int,
    snapshot: Path,
    planned: dict[str, tuple[int, ...]] | None = None,
) -> TaskResult:
    """Read one task's published files (see [`TaskResult`][ermrl.analysis.TaskResult]); ``planned``
    is the test phase its file plans, ``{agent: seeds}``."""
    test = folder / "test"
    runs = _run_dates(load_test_runs(test), test) if test.exists() else pd.DataFrame()
    snapshot_doc = _read_snapshot(snapshot)
    selection = _selection(test)
    traced, trace = (True, "") if not selection else trace_selection(selection, snapshot_doc)
    return TaskResult(
        label,
        folder,
        runs,
        _snapshot_evolution(snapshot_doc, n_trials),
        selection,
        traced,
        trace,
        planned=dict(planned or {}),
    )


@dataclass(frozen=True)
class TaskFiles:
    """Where one task's published files are.

    Attributes:
        label: The task tested.
        evolved_on: The task (or task set) its reservoirs were evolved on.
        folder: Its published folder (``test/`` and ``report/`` inside).
        snapshot: The evolution study's snapshot (``study.json``).
        n_trials: The evolution's budget.
        planned: The test runs the file plans, ``{agent: seeds}`` (empty: not known).
    """

    label: str
    evolved_on: str
    folder: Path
    snapshot: Path
    n_trials: int
    planned: dict[str, tuple[int, ...]] = field(default_factory=dict)


@dataclass(frozen=True)
class Hypothesis:
    """One experiment file on the page: its claim, its tasks' files and its verdict rule."""

    name: str
    file: str
    claim: str | None
    description: str | None
    tasks: tuple[TaskFiles, ...]
    rule: VerdictRule | None = None


def untraceable_tasks(hypotheses: Sequence[Hypothesis]) -> list[str]:
    """``"<hypothesis> <task>: what is missing"`` for each tested task the page refuses."""
    from ermrl.analysis._results import RUNS_DIR

    out = []
    for hyp in hypotheses:
        for task in hyp.tasks:
            test = task.folder / "test"
            selection = _selection(test)
            if not selection or not any((test / RUNS_DIR / EVOLVED).glob("seed_*/result.json")):
                continue
            traced, trace = trace_selection(selection, _read_snapshot(task.snapshot))
            if not traced:
                out.append(f"{hyp.name} {task.label}: {trace}")
    return out


def _normalizer() -> Any:
    """``(env_id, values) -> normalized values`` from the packaged reference table
    (``ermrl/data/scores.csv``, the one ``ermrl scores`` writes), ``None`` for an env without
    a random and a target return. Read with pandas here: ``ermrl.search`` imports the
    learners (torch, SB3) just to parse this table."""
    table = pd.read_csv(Path(__file__).resolve().parents[1] / "data" / "scores.csv")
    refs = {
        str(r.env_id): (float(r.random_mean), float(r.target))
        for r in table.itertuples(index=False)
        if math.isfinite(float(r.random_mean)) and math.isfinite(float(r.target))
    }

    def normalize(env_id: str, values: Any) -> Any:
        if env_id not in refs:
            return None
        random, target = refs[env_id]
        return (pd.Series(values, dtype=float) - random) / (target - random)

    return normalize


def _num(value: Any) -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if math.isnan(v):
        return "–"
    if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5):
        return f"{v:.2e}"
    return f"{v:.4g}"


def _ci(low: Any, high: Any) -> str:
    return f"[{_num(low)}, {_num(high)}]"


def _signed(value: float) -> str:
    return f"{value:+.4g}"


def write_reproduction_page(
    hypotheses: Sequence[Hypothesis],
    out: str | Path,
    *,
    html_page: bool = True,
) -> tuple[Path, Path | None]:
    """Write the reproduction page.

    Args:
        hypotheses: One entry per experiment file (see [`Hypothesis`][ermrl.analysis.Hypothesis]).
        out: The Markdown file to write (``docs/reproduction.md``); the HTML form goes beside it
            with the ``.html`` suffix. Figures are linked relative to its folder.
        html_page: Also write the HTML form.

    Returns:
        ``(markdown, html or None)``; every judged test is also written as CSV beside the page
        (``.csv`` suffix; the columns of [`judge`][ermrl.analysis.judge]).

    Raises:
        VerdictError: experiment files that pool a question into one family disagree on its
            alpha or correction.
    """
    from ermrl._io import write_atomic
    from ermrl.analysis._report import _Doc

    out = Path(out)
    results = {
        hyp.name: [
            task_result(t.folder, t.label, t.n_trials, t.snapshot, t.planned) for t in hyp.tasks
        ]
        for hyp in hypotheses
    }
    for hyp in hypotheses:
        for ref in hyp.rule.references if hyp.rule is not None else ():
            for result in results[hyp.name]:
                add_reference_runs(result, ref, hyp.file)
    rules = {h.name: h.rule for h in hypotheses if h.rule is not None}
    judged = [
        TaskRuns(hyp.name, r.label, r.runs, r.reference_selected, r.label)
        for hyp in hypotheses
        for r in results[hyp.name]
        if r.judged
    ]
    tests = judge(judged, rules)
    normalize = _normalizer()
    borrowed = {
        (hyp.name, r.label, name) for hyp in hypotheses for r in results[hyp.name]
        for name in r.references
    }  # fmt: skip
    after = [
        t for t in (_after_rule(t, rules[t.hypothesis], borrowed) for t in judged) if t is not None
    ]
    sensitivity = judge(after, rules) if after else pd.DataFrame()
    common = judge(judged, rules, common_seeds=True) if judged else pd.DataFrame()

    doc = _Doc()
    doc.h(1, "Reproducing *Evolving Reservoirs for Meta Reinforcement Learning*")
    doc.p(
        "Léger, Hamon, Nisioti, Hinaut and Moulin-Frier, EvoApplications 2024 "
        "([arXiv:2312.06695](https://arxiv.org/abs/2312.06695)). Each hypothesis below is one "
        "experiment file that `ermrl run FILE` runs and resumes; its header states its scale "
        "and how it differs from the paper. Every number is computed from the per-seed files "
        "published under `benchmarks/results/paper/` (a `result.json` and an `episodes.csv` "
        "per run) by `ermrl reproduction`."
        + (
            " A file without a claim from the paper goes beyond it: it tests what the "
            "reproduction found and publishes under its own `publish:` folder."
            if any(hyp.claim is None for hyp in hypotheses)
            else ""
        )
    )
    doc.p(
        "**How verdicts are decided.** Each experiment file states its rule in a `verdict:` "
        "block, printed in its section. A hypothesis is split into sub-questions, each answered "
        "per task by comparisons `candidate − baseline` of per-seed returns. A comparison is "
        "**supported** when Welch's t interval and the percentile bootstrap interval of the "
        "difference of means both lie above 0 after Holm's correction, **contradicted** when "
        "both lie below 0, and **inconclusive** otherwise. The correction's family is every "
        "test of one sub-question under one metric on this page (all tasks of all files), and a "
        "test of Holm rank i of m is judged at confidence 1 − α/(m − i + 1) (the stopping "
        "step's level after the first test Holm keeps), so its intervals exclude 0 exactly when "
        "Holm rejects it. A sub-question is supported on a task when all its comparisons are, "
        "contradicted when any is. Over a hypothesis's tasks the page counts those outcomes; it "
        "does not turn them into one word. The aggregates (rliable's interquartile mean of "
        "normalized scores and probability of improvement, stratified bootstrap 95% intervals, "
        "not adjusted) describe the tasks together. Every verdict is given under three "
        "metrics: the mean return of the last 10 training episodes (`last10`), of the last 100 "
        "(`last100`, SB3's `rollout/ep_rew_mean`, the metric the paper plots) and of 10 "
        f"deterministic evaluation episodes after training (`eval`; {_eval_coverage(judged)}). "
        f"A group of fewer than {FEW_SEEDS} seeds is flagged."
    )
    glance: list[dict[str, Any]] = []
    sections = []
    for hyp in hypotheses:
        section = _Doc()
        _hypothesis_section(section, hyp, results[hyp.name], tests, normalize, out.parent, glance)
        sections.append(section)
    refused = [
        f"{hyp.name} {r.label}: {r.trace}"
        for hyp in hypotheses
        for r in results[hyp.name]
        if r.tested and not r.traced
    ]
    doc.h(2, "Verdicts at a glance")
    doc.p(
        "Per sub-question: a one-line answer over the tasks (one outcome when every tested "
        "task has it, else *mixed* with the counts), the outcome on each task under each "
        "hypothesis's primary metric, then the counts under the other metrics. *Not tested* "
        "is no outcome: the selection is the reference, or the runs are another test's. The "
        "sections below give every effect, interval, p-value and equivalence test."
    )
    if glance:
        doc.table(pd.DataFrame(glance))
    shared = _shared_text(judged, borrowed)
    if shared:
        doc.p(
            "**Shared runs** (found from the data: the same seed with the same final and "
            "last-100 returns to the last digit). Where a comparison's two sides are the same "
            "runs, or an earlier test on the page compares the same runs, it is not tested "
            "again and counts once in its family: " + "; ".join(shared) + "."
        )
    _sensitivity_block(doc, tests, sensitivity, after)
    _common_seeds_block(doc, tests, common)
    if refused:
        doc.p(
            "**Not rendered** (the tested trial cannot be traced to a recorded selection): "
            + "; ".join(refused)
            + "."
        )
    for section in sections:
        doc.blocks += section.blocks
    write_atomic(out, doc.markdown())
    # Every test, one row each, for other tools (and for recomputing the page's labels).
    write_atomic(out.with_suffix(".csv"), tests.to_csv(index=False))
    html_path = None
    if html_page:
        html_path = out.with_suffix(".html")
        write_atomic(html_path, doc.html("ermrl: reproduction of ER-MRL"))
    return out, html_path


#: The aggregate's probability of improvement, in words: unadjusted, so descriptive only.
_DESCRIPTIVE = {
    "supported": "interval above 1/2",
    "contradicted": "interval below 1/2",
    "inconclusive": "interval across 1/2",
}
#: The markers between which `write_summary` writes the results table into a file.
SUMMARY_START = "<!-- reproduction:start -->"
SUMMARY_END = "<!-- reproduction:end -->"


def _run_dates(runs: pd.DataFrame, test_folder: Path) -> pd.DataFrame:
    """``runs`` with a ``dated`` column: the day each run finished (``result.json``'s
    ``finished``), or for a run written before that was recorded, the day of the commit that
    added its ``result.json`` (one ``git log`` of the folder; unknown outside a repository)."""
    import subprocess

    if runs.empty:
        return runs
    finished = runs["finished"] if "finished" in runs else pd.Series(None, index=runs.index)
    dated = pd.Series(
        [str(v)[:10] if isinstance(v, str) and v else None for v in finished],
        index=runs.index,
        dtype=object,
    )
    if dated.isna().any():
        added: dict[tuple[str, int], str] = {}
        try:
            done = subprocess.run(
                ["git", "log", "--diff-filter=A", "--name-only", "--format=@%cs", "--", "agents"],
                cwd=test_folder, capture_output=True, text=True, timeout=60, check=False,
            )  # fmt: skip
            day = None
            for line in done.stdout.splitlines() if done.returncode == 0 else []:
                if line.startswith("@"):
                    day = line[1:]
                elif line.endswith("/result.json") and day:
                    parts = line.split("/")
                    agent, seed = parts[-3], parts[-2].removeprefix("seed_")
                    if seed.isdigit():
                        added[(agent, int(seed))] = min(day, added.get((agent, int(seed)), day))
        except (OSError, subprocess.SubprocessError):
            pass
        fill = [
            added.get((str(a), int(sd))) for a, sd in zip(runs["agent"], runs["seed"], strict=True)
        ]
        dated = dated.where(dated.notna(), pd.Series(fill, index=runs.index))
    return runs.assign(dated=dated)


def _after_rule(
    task: TaskRuns, rule: VerdictRule, borrowed: set[tuple[str, str, str]]
) -> TaskRuns | None:
    """The task's runs on the seeds all of whose runs were made on or after the rule's adoption
    date (`_run_dates`: ``finished``, or the commit that published the run); ``None`` when the
    rule has no date."""
    runs = task.runs
    if rule.adopted is None or runs.empty or "dated" not in runs:
        return None
    late = runs["dated"].notna() & (runs["dated"].astype(str) >= rule.adopted)
    # A baseline borrowed from another file (references) was run for that file's rule.
    own = ~runs["agent"].map(lambda a: (task.hypothesis, task.task, str(a)) in borrowed)
    early = set(runs.loc[own & ~late, "seed"])
    kept = runs[~runs["seed"].isin(early)]
    return TaskRuns(task.hypothesis, task.task, kept, task.reference_selected, task.env_id)


def _sensitivity_block(
    doc: Any, tests: pd.DataFrame, sensitivity: pd.DataFrame, after: Sequence[TaskRuns]
) -> None:
    """The verdicts again on the seeds run after each rule, and the outcomes that change."""
    if sensitivity.empty or tests.empty:
        return
    seeds = []
    for task in after:
        kept = sorted({int(sd) for sd in task.runs["seed"]}) if not task.runs.empty else []
        seeds.append(f"{task.hypothesis} {task.task}: {_span(kept) if kept else 'none'}")
    key = ["hypothesis", "task", "question", "comparison", "metric"]
    both = tests.merge(sensitivity, on=key, suffixes=("", "_after"))
    checked = both["outcome_after"].isin(["supported", "contradicted", "inconclusive"])
    unchecked = both[~checked & (both["outcome"] != both["outcome_after"])]
    both = both[checked]
    moved = both[both["outcome"] != both["outcome_after"]]
    doc.h(3, "Sensitivity: the seeds run after each rule")
    doc.p(
        "Every rule above was written after some of its test results existed. The same "
        "verdicts, by the same rule and Holm families, on only the seeds all of whose runs on "
        "a task were made on or after the rule's adoption date (each run's `result.json` "
        "`finished`, or for runs that predate that field the commit that published them; "
        "baselines borrowed from another file not counted): "
        + "; ".join(seeds)
        + ". "
        + (
            f"{len(unchecked)} comparison(s) cannot be checked this way (a side has no run "
            "after the rule, or the comparison is not tested). "
            if len(unchecked)
            else ""
        )
        + (
            f"**{len(moved)} of the {len(both)} others change outcome** (a flag, not a "
            "verdict: fewer seeds give less power):"
            if len(moved)
            else f"No outcome of the {len(both)} others changes."
        )
    )
    if len(moved):
        doc.table(_moved_table(moved, "after the rule"))


def _moved_table(moved: pd.DataFrame, label: str) -> pd.DataFrame:
    """Rows of a merged (``_after``-suffixed) pair of test tables whose outcome moved."""
    return pd.DataFrame(
        {
            "hypothesis": moved["hypothesis"],
            "task": moved["task"],
            "comparison": moved["comparison"],
            "metric": moved["metric"],
            "all seeds": [
                f"{o} ({int(a)} / {int(b)})"
                for o, a, b in zip(
                    moved["outcome"], moved["n_candidate"], moved["n_baseline"], strict=True
                )
            ],
            label: [
                f"{o} ({int(a)} / {int(b)})"
                for o, a, b in zip(
                    moved["outcome_after"],
                    moved["n_candidate_after"],
                    moved["n_baseline_after"],
                    strict=True,
                )
            ],
            "effect": [_signed(v) if math.isfinite(v) else "–" for v in moved["mean_diff_after"]],
            "Holm p": [_num(v) for v in moved["p_adjusted_after"]],
        }
    )


def _common_seeds_block(doc: Any, tests: pd.DataFrame, common: pd.DataFrame) -> None:
    """The comparisons whose two groups have different seeds, judged on the seeds both have."""
    if common.empty or tests.empty:
        return
    key = ["hypothesis", "task", "question", "comparison", "metric"]
    both = tests.merge(common, on=key, suffixes=("", "_after"))
    differ = (both["n_candidate"] != both["n_candidate_after"]) | (
        both["n_baseline"] != both["n_baseline_after"]
    )
    both = both[differ & both["outcome"].isin(["supported", "contradicted", "inconclusive"])]
    if both.empty:
        return
    checked = both["outcome_after"].isin(["supported", "contradicted", "inconclusive"])
    moved = both[checked & (both["outcome"] != both["outcome_after"])]
    doc.h(3, "Sensitivity: the seeds both groups have")
    doc.p(
        f"{len(both)} comparison(s) set groups of different seeds against each other (an agent "
        "trained on fewer seeds, or evaluation episodes recorded on some seeds only). The same "
        "verdicts on the seeds both groups of each comparison have, by the same rule and "
        "families: "
        + (
            f"**{len(moved)} change outcome** (a flag, not a verdict):"
            if len(moved)
            else "no outcome changes."
        )
    )
    if len(moved):
        doc.table(_moved_table(moved, "common seeds"))


def _eval_coverage(tasks: Sequence[TaskRuns]) -> str:
    """Which seeds of the judged groups of runs have evaluation episodes, computed: ``recorded
    on every seed of N groups, on seeds 15–29 of M (...), on none of K (...)``."""
    spans: dict[str, list[str]] = {}
    for task in tasks:
        runs = task.runs
        if runs.empty or "eval_return" not in runs:
            continue
        for agent, group in runs.groupby("agent", sort=False):
            seeds = sorted(int(sd) for sd in group["seed"])
            has = sorted(
                int(sd)
                for sd, v in zip(group["seed"], pd.to_numeric(group["eval_return"]), strict=True)
                if math.isfinite(float(v))
            )
            key = "every seed" if has == seeds else (f"seeds {_span(has)}" if has else "no seed")
            spans.setdefault(key, []).append(f"{task.hypothesis} {task.task} {agent}")
    if not spans:
        return "not recorded"
    parts = []
    order = sorted(spans, key=lambda k: -len(spans[k]))
    for key in order:
        groups = spans[key]
        listed = "" if key == order[0] else f": {', '.join(groups)}"
        parts.append(f"on {key} of {len(groups)} group(s) of runs (agent, task){listed}")
    return "recorded " + "; ".join(parts)


def question_answer(outcomes: Sequence[str]) -> str:
    """A sub-question's one-line answer over a hypothesis's tasks, from each task's outcome
    under the rule: one word when every tested task agrees, else ``mixed`` with the counts.

    Examples:
        >>> question_answer(["supported", "supported"])
        'supported on all 2 tasks'
        >>> question_answer(["supported", "inconclusive", "inconclusive"])
        'mixed: supported on 1 of 3 tasks, inconclusive on 2'
        >>> question_answer(["inconclusive", "not tested"])
        'inconclusive on the 1 task tested (1 not tested)'
    """
    tested = [o for o in outcomes if o in ("supported", "contradicted", "inconclusive")]
    others = [o for o in outcomes if o not in tested]
    rest = f" ({_counts(others)})" if others else ""
    if not tested:
        if len(set(others)) == 1:
            n = len(others)
            return f"{others[0]} on " + (f"all {n} tasks" if n > 1 else "its one task")
        return _counts(others) or "no task"
    n = len(tested)
    if len(set(tested)) == 1:
        if others:
            where = f"the {n} task{'s' if n > 1 else ''} tested"
        else:
            where = f"all {n} tasks" if n > 1 else "its one task"
        return f"{tested[0]} on {where}{rest}"
    kinds = [o for o in ("supported", "contradicted", "inconclusive") if o in tested]
    first, *more = kinds
    text = f"mixed: {first} on {tested.count(first)} of {n} tasks" + "".join(
        f", {o} on {tested.count(o)}" for o in more
    )
    return text + rest


def results_summary(tests: pd.DataFrame, hypotheses: Sequence[Hypothesis]) -> str:
    """The results table that README.md and docs/getting-started.md show, from the page's tests
    (its CSV) and the experiment files' rules: per hypothesis and sub-question, the answer and
    each task's outcome under the primary metric, with the other metrics' where they differ and
    equivalence where it is shown.

    Args:
        tests: The page's tests ([`judge`][ermrl.analysis.judge]'s rows, or
            ``docs/reproduction.csv`` read back).
        hypotheses: The page's experiment files, in its order.

    Returns:
        Markdown: one table and the line that says where it comes from.
    """
    if tests.empty:
        return "No test has been judged yet.\n"
    tests = tests.copy()
    column = tests["equivalence"] if "equivalence" in tests else pd.Series("", index=tests.index)
    tests["equivalence"] = column.astype(object).where(column.notna(), "")
    lines = []
    primaries = set()
    for hyp in hypotheses:
        rule = hyp.rule
        if rule is None:
            continue
        primaries.add(rule.primary)
        for question in rule.questions:
            rows = tests[(tests["hypothesis"] == hyp.name) & (tests["question"] == question.name)]
            if rows.empty:
                continue
            cells, primary = [], []
            for task, group in rows.groupby("task", sort=False):
                first = group[group["metric"] == rule.primary]
                outcome = task_outcome(first)
                primary.append(outcome)
                text = f"{task}: {outcome}"
                marks = [str(e) for e in first["equivalence"] if e]
                if outcome == "inconclusive" and marks and all(m == "equivalent" for m in marks):
                    margin = float(first["margin"].iloc[0])
                    text += f" (equivalent within ±{margin:g})"
                differ = []
                for metric in rule.metrics[1:]:
                    other = task_outcome(group[group["metric"] == metric])
                    if other != outcome:
                        differ.append(f"{metric}: {other}")
                if differ:
                    text += " [" + "; ".join(differ) + "]"
                cells.append(text)
            lines.append(
                f"| {hyp.name} | {question.text} | {question_answer(primary)} | "
                + "; ".join(cells)
                + " |"
            )
    metric = "/".join(sorted(primaries)) or "last10"
    head = [
        f"| experiment | sub-question | answer ({metric}) | per task ({metric}; [other metrics "
        "where they differ]) |",
        "|---|---|---|---|",
    ]
    source = (
        "Written by `ermrl reproduction` from its tests (`docs/reproduction.csv`): "
        "supported, contradicted or inconclusive by each file's `verdict:` rule, Holm-corrected "
        "over the page; *not tested* where the selection is the reference or the runs are "
        "another test's; equivalence only where two one-sided tests show it within the "
        "task's margin (set after the data)."
    )
    return "\n".join([*head, *lines]) + "\n\n" + source + "\n"


def write_summary(path: str | Path, summary: str) -> bool:
    """Write `results_summary` between `SUMMARY_START` and `SUMMARY_END` in a file.

    Returns:
        Whether the file changed.

    Raises:
        VerdictError: the file lacks the markers, in that order (one line).
    """
    from ermrl._io import write_atomic

    path = Path(path)
    text = path.read_text()
    start, end = text.find(SUMMARY_START), text.find(SUMMARY_END)
    if start < 0 or end < start:
        raise VerdictError(f"{path}: no {SUMMARY_START} ... {SUMMARY_END} markers to write into")
    new = text[: start + len(SUMMARY_START)] + "\n" + summary + text[end:]
    if new == text:
        return False
    write_atomic(path, new)
    return True


def read_summary(path: str | Path) -> str | None:
    """What a file holds between `SUMMARY_START` and `SUMMARY_END` (``None`` without them)."""
    text = Path(path).read_text()
    start, end = text.find(SUMMARY_START), text.find(SUMMARY_END)
    if start < 0 or end < start:
        return None
    return text[start + len(SUMMARY_START) + 1 : end]


def _shared_text(tasks: Sequence[TaskRuns], borrowed: set[tuple[str, str, str]]) -> list[str]:
    """Each pair of groups of runs of two experiment files that are the same runs, in words
    (a baseline a file declares it borrows, `references`, left out: the page names it)."""
    out = []
    for (k, agent), others in shared_runs(tasks).items():
        for (j, other), seeds in others.items():
            one, two = tasks[k], tasks[j]
            if j <= k or one.hypothesis == two.hypothesis:
                continue
            if {(one.hypothesis, one.task, agent), (two.hypothesis, two.task, other)} & borrowed:
                continue
            n = int((one.runs["agent"] == agent).sum())
            out.append(
                f"{one.hypothesis} {one.task} `{agent}` and {two.hypothesis} {two.task} "
                f"`{other}` on seeds {_span(seeds)} ({len(seeds)} of {n})"
            )
    return out


def _span(seeds: Sequence[int]) -> str:
    if len(seeds) > 2 and seeds[-1] - seeds[0] == len(seeds) - 1:
        return f"{seeds[0]}–{seeds[-1]}"
    return ", ".join(map(str, seeds))


def _counts(outcomes: Sequence[str]) -> str:
    parts = [
        f"{outcomes.count(o)} {o}"
        for o in ("supported", "contradicted", "inconclusive", NOT_TESTED, NOT_RUN)
        if outcomes.count(o)
    ]
    return ", ".join(parts) if parts else "–"


def _question_outcomes(
    tests: pd.DataFrame, hyp: str, question: Question, metric: str
) -> dict[str, str]:
    rows = tests[
        (tests["hypothesis"] == hyp)
        & (tests["question"] == question.name)
        & (tests["metric"] == metric)
    ]
    return {str(task): task_outcome(group) for task, group in rows.groupby("task", sort=False)}


def _hypothesis_section(
    doc: Any,
    hyp: Hypothesis,
    results: list[TaskResult],
    tests: pd.DataFrame,
    normalize: Any,
    docs_dir: Path,
    glance: list[dict[str, Any]],
) -> None:
    doc.h(2, f"{hyp.name}: `{hyp.file}`")
    if hyp.claim:
        doc.p(f"**The paper's claim** (quoted as a claim, not as a finding): {hyp.claim}")
    if hyp.description:
        doc.p(hyp.description.strip())
    rule = hyp.rule
    judged = [r for r in results if r.judged]
    if rule is None:
        doc.p("**No verdict rule**: the file has no `verdict:` block, so no verdict is given.")
    else:
        doc.p(f"**Rule** (`verdict:` block of `{hyp.file}`): {rule.describe()}.")
        first, source = (None, "unknown")
        for r in judged:
            date, where = first_result_date(r.folder / "test")
            if date is not None and (first is None or date < first):
                first, source = date, where
        if rule.adopted and first and rule.adopted > first:
            doc.p(
                f"**Flag: the rule was written after results existed.** Rule adopted "
                f"{rule.adopted}; first test result {first} (dated by {source}). Read its "
                "verdicts as a re-analysis, not as a test fixed in advance."
            )
        else:
            doc.p(
                f"Rule adopted {rule.adopted or 'on an unrecorded date'}; first test result "
                f"{first or 'not yet'}" + (f" (dated by {source})" if first else "") + "."
            )
        if rule.margins and rule.margins_adopted and first and rule.margins_adopted > first:
            doc.p(
                f"**Flag: the equivalence margins were set after the data.** Margins adopted "
                f"{rule.margins_adopted}, a rule of their own added to the file after its test "
                f"results existed (first {first}): read every *equivalent* and *not shown either "
                "way* on this file as a re-analysis, not as a test fixed in advance."
            )
        _questions_block(doc, hyp, rule, judged, tests, normalize, glance)
    for result, files in zip(results, hyp.tasks, strict=True):
        _task_section(doc, hyp, result, tests, docs_dir, files.evolved_on)


def _questions_block(
    doc: Any,
    hyp: Hypothesis,
    rule: VerdictRule,
    judged: list[TaskResult],
    tests: pd.DataFrame,
    normalize: Any,
    glance: list[dict[str, Any]],
) -> None:
    runs = [TaskRuns(hyp.name, r.label, r.runs, r.reference_selected, r.label) for r in judged]
    mine = tests[(tests["hypothesis"] == hyp.name) & (tests["outcome"] == NOT_TESTED)]
    untested = {
        (str(r["task"]), str(r["comparison"])): "shared runs, not tested"
        for r in mine.to_dict("records")
        if "same runs" in str(r["note"])
    }
    items = []
    aggregate_rows = []
    for question in rule.questions:
        primary = _question_outcomes(tests, hyp.name, question, rule.primary)
        per_task = "; ".join(f"{t}: **{o}**" for t, o in primary.items()) or "no task tested yet"
        others = "; ".join(
            f"{m}: {_counts(list(_question_outcomes(tests, hyp.name, question, m).values()))}"
            for m in rule.metrics[1:]
        )
        adopted = f"; added {question.adopted}" if question.adopted else ""
        items.append(
            f"**{question.text}** (`{question.name}`: "
            + ", ".join(f"`{c.label}`" for c in question.comparisons)
            + f"{adopted}) — {rule.primary}: {per_task}; {_counts(list(primary.values()))} of "
            f"{len(primary)} task(s). Other metrics: {others}."
        )
        glance.append(
            {
                "hypothesis": hyp.name,
                "sub-question": question.text,
                f"answer ({rule.primary})": question_answer(list(primary.values())),
                f"per task ({rule.primary})": per_task.replace("**", ""),
                **{
                    m: _counts(list(_question_outcomes(tests, hyp.name, question, m).values()))
                    for m in rule.metrics[1:]
                },
            }
        )
        if primary and all(o == NOT_RUN for o in primary.values()):
            continue  # no aggregate of a question none of whose comparisons ran
        for metric in rule.metrics:
            for row in aggregate_question(
                runs,
                question,
                metric,
                normalize,
                n_resamples=rule.n_resamples,
                untested=untested,
            ):
                aggregate_rows.append(
                    {
                        "sub-question": question.name,
                        "comparison": row["comparison"],
                        "metric": metric,
                        "tasks": row["n_tasks"],
                        "P(candidate > baseline)": _num(row["poi"]),
                        "95% CI": _ci(row["poi_low"], row["poi_high"]),
                        "descriptive (not adjusted)": _DESCRIPTIVE[row["poi_outcome"]]
                        if row["n_tasks"]
                        else "–",
                        "IQM candidate [95% CI]": (
                            f"{_num(row['iqm_candidate'])} {_ci(row['iqm_candidate_low'], row['iqm_candidate_high'])}"
                            if math.isfinite(row["iqm_candidate"])
                            else "–"
                        ),
                        "IQM baseline [95% CI]": (
                            f"{_num(row['iqm_baseline'])} {_ci(row['iqm_baseline_low'], row['iqm_baseline_high'])}"
                            if math.isfinite(row["iqm_baseline"])
                            else "–"
                        ),
                        "note": row["note"],
                    }
                )
    doc.h(3, f"{hyp.name}: sub-questions")
    doc.bullets(items)
    _mechanism_summary(doc, hyp, rule, judged, tests)
    if aggregate_rows:
        doc.p(
            "Aggregates over the tasks (rliable's definitions; scores normalized as "
            "(R − R_random) / (R_target − R_random) with ermrl's reference table, "
            "`ermrl/data/scores.csv`). They are descriptive: not adjusted for multiple "
            "comparisons and not part of the rule, so they say where the probability of "
            "improvement's 95% interval lies (above 1/2, below it, or across it), not "
            "supported or contradicted:"
        )
        doc.table(pd.DataFrame(aggregate_rows))


def _task_mechanism(hyp: Hypothesis, result: TaskResult, tests: pd.DataFrame) -> Any:
    """``(verdict, spectral outcome)`` of a task whose rule asks the mechanism question, read
    from its judged comparison and its published ``report/dynamics/mechanism.csv``; ``None``
    without that question."""
    question = mechanism_question(hyp.rule)
    if question is None or hyp.rule is None or without_gait(result.label):
        return None
    rows = tests[
        (tests["hypothesis"] == hyp.name)
        & (tests["task"] == result.label)
        & (tests["question"] == question.name)
        & (tests["metric"] == hyp.rule.primary)
        & (tests["baseline"] == ABLATED)
    ].to_dict("records")
    spectral = spectral_outcome(read_mechanism(result.folder / "report" / "dynamics"))
    return mechanism_verdict(rows[0] if rows else None, spectral), spectral


def _mechanism_summary(
    doc: Any, hyp: Hypothesis, rule: VerdictRule, judged: list[TaskResult], tests: pd.DataFrame
) -> None:
    question = mechanism_question(rule)
    if question is None:
        return
    labels = []
    for result in judged:
        found = _task_mechanism(hyp, result, tests)
        if found is not None:
            labels.append(f"{result.label}: {found[0].headline}")
    if judged and not labels and all(without_gait(r.label) for r in judged):
        return  # no locomotion task here: the question is answered as any other
    doc.p(
        f"**Mechanism: oscillations at the gait, or leaky integration?** ({rule.primary}, per "
        f"task, from `{question.name}` and the spectra) "
        + ("; ".join(labels) or "no task tested yet")
        + f". How it is decided: {describe_mechanism()}."
    )


def _mechanism_section(
    doc: Any, hyp: Hypothesis, result: TaskResult, docs_dir: Path, tests: pd.DataFrame
) -> None:
    found = _task_mechanism(hyp, result, tests)
    if found is None:
        return
    verdict, spectral = found
    assert hyp.rule is not None
    doc.h(4, f"{result.label}: mechanism")
    doc.p(f"**Mechanism ({hyp.rule.primary}):** {verdict.headline}; {verdict.text}.")
    folder = result.folder / "report" / "dynamics"
    if spectral.summary.empty:
        doc.p(
            f"Spectra: not recorded yet (the published report has no "
            f"`dynamics/{MECHANISM_FILE}`; `ermrl report` writes it from an episode of the "
            "test phase's saved `res-ppo` models)."
        )
        return
    where = _rel(folder / MECHANISM_FILE, docs_dir)
    band = ", ".join(f"{v:.3g}" for v in spectral.band)
    gait = (
        f"gait {spectral.gait_frequency:.3g} {spectral.unit}, band [{band}]"
        if math.isfinite(spectral.gait_frequency)
        else spectral.reason.partition(":")[0] or "no gait"  # or "gait below resolution"
    )
    counts = (
        f"the criterion holds on {spectral.n_holding} of {spectral.n_seeds} weight seeds"
        if spectral.holds is not None
        else f"the criterion cannot be judged: {spectral.reason}"
    )
    doc.p(f"Spectra ({gait}; {counts}; per seed: [{where}]({where})):")
    doc.table(mechanism_table(spectral))
    figure = folder / "mechanism_spectra.png"
    if figure.exists():
        doc.img(_rel(figure, docs_dir), f"{result.label}: one input stream, three reservoirs")


def _reservoir_text(selection: dict[str, Any]) -> str:
    reservoirs = selection.get("reservoirs") or []
    parts = []
    for i, r in enumerate(reservoirs):
        genes = ", ".join(
            f"{k} {r[k]:.4g}"
            for k in ("sr", "lr", "lr_max", "input_scaling")  # lr_max: a band of leak rates
            if isinstance(r.get(k), float)
        )
        parts.append(f"reservoir {i}: {genes} ({r.get('units')} units)")
    trial = selection.get("trial")
    how = selection.get("selection") or ""
    head = f"trial #{trial}" if trial is not None else "the selected trial"
    return f"{head}{f' ({how})' if how else ''}: " + "; ".join(parts) if parts else head


def _agents_table(runs: pd.DataFrame) -> pd.DataFrame:
    from ermrl.analysis._stats import final_returns_table

    rows = []
    for metric, (column, _) in METRICS.items():
        table = final_returns_table(runs, metric=column)
        for row in table.itertuples(index=False):
            rows.append(
                {
                    "agent": row.agent,
                    "metric": metric,
                    "seeds": row.n_seeds,
                    "mean": row.mean,
                    "std": row.std,
                    "95% CI": _ci(row.ci95_low, row.ci95_high),
                    f"< {FEW_SEEDS} seeds": "yes" if row.n_seeds < FEW_SEEDS else "no",
                }
            )
    frame = pd.DataFrame(rows)
    if frame.empty:
        return frame
    env_steps = runs.groupby("agent")["env_steps"].sum()
    wall = runs.groupby("agent")["wall_seconds"].sum()
    frame["env steps"] = [
        int(env_steps.get(a, 0)) if m == "last10" else ""
        for a, m in zip(frame["agent"], frame["metric"], strict=True)
    ]
    frame["wall (h)"] = [
        float(wall.get(a, 0.0)) / 3600 if m == "last10" else ""
        for a, m in zip(frame["agent"], frame["metric"], strict=True)
    ]
    return frame.sort_values(
        ["metric", "agent"],
        key=lambda s: s.map({m: i for i, m in enumerate(METRICS)}) if s.name == "metric" else s,
        kind="stable",
    )


def _tests_table(rows: pd.DataFrame) -> pd.DataFrame:
    out = []
    for row in rows.to_dict("records"):
        if not_run(row):  # the task's verdict line says "not run yet"
            continue
        tested = not row["note"]
        out.append(
            {
                "sub-question": row["question"],
                "comparison": row["comparison"],
                "metric": row["metric"],
                "seeds": f"{row['n_candidate']} / {row['n_baseline']}",
                "effect": _signed(row["mean_diff"]) if tested else "–",
                "Welch 95% CI": _ci(row["welch_low"], row["welch_high"]) if tested else "–",
                "bootstrap 95% CI": _ci(row["boot_low"], row["boot_high"]) if tested else "–",
                "p": _num(row["p_value"]) if tested else "–",
                "Holm p (m)": f"{_num(row['p_adjusted'])} ({row['family_size']})"
                if tested
                else "–",
                "adjusted level": f"{100 * (1 - row['level']):.4g}%" if tested else "–",
                "Welch CI, adjusted": _ci(row["adj_welch_low"], row["adj_welch_high"])
                if tested
                else "–",
                "bootstrap CI, adjusted": _ci(row["adj_boot_low"], row["adj_boot_high"])
                if tested
                else "–",
                "outcome": f"**{row['outcome']}**",
                "what it rules out": excluded_effects(row)
                if tested and row["outcome"] == "inconclusive"
                else row["note"],
                "equivalence (two one-sided tests)": (equivalence_text(row) or "–")
                if tested
                else "–",
                "seeds for 80% power": (
                    "–"
                    if not tested
                    else (
                        str(int(row["seeds_needed"]))
                        if row["seeds_needed"] is not None and not pd.isna(row["seeds_needed"])
                        else "> 10000 or no effect"
                    )
                ),
            }
        )
    return pd.DataFrame(out)


def _rel(path: Path, start: Path) -> str:
    import os

    return os.path.relpath(path, start)


def _task_section(
    doc: Any,
    hyp: Hypothesis,
    result: TaskResult,
    tests: pd.DataFrame,
    docs_dir: Path,
    evolve_label: str,
) -> None:
    evo = result.evolution
    doc.h(
        3, result.label + (f" (evolved on {evolve_label})" if evolve_label != result.label else "")
    )
    evolution_text = (
        f"Evolution: {evo['finished']}/{evo['n_trials']} trials finished"
        + (
            f", {evo['env_steps'] / 1e6:.4g}M env steps, {evo['wall_seconds'] / 3600:.2f} h of "
            "training wall time (trials' shares of their generations, re-evaluation included)"
            if evo["env_steps"]
            else ""
        )
        + "."
    )
    if not result.tested:
        started = "Not tested yet" if evo["finished"] else "Not run yet"
        doc.p(f"**{started}.** {evolution_text} The test phase has not run.")
        return
    if not result.traced:
        doc.p(
            f"**Not rendered: the tested trial cannot be traced to a recorded selection.** "
            f"{result.trace}. Publish the study's re-evaluation record (rerun `ermrl run "
            f"{hyp.file} --task {result.label} --stage reevaluate`) or test the recorded "
            "selection."
        )
        return
    missing = result.missing
    if missing:
        planned = sum(len(seeds) for seeds in result.planned.values())
        left = sum(len(seeds) for seeds in missing.values())
        per_agent = ", ".join(
            f"`{agent}` {len(seeds) - len(missing.get(agent, ()))}/{len(seeds)}"
            for agent, seeds in result.planned.items()
        )
        doc.p(
            f"**Test in progress: {planned - left} of the {planned} planned runs published** "
            f"({per_agent}). No verdict until every planned run is in: judging the seeds that "
            f"happen to have finished would let the stopping point choose the result. "
            f"{evolution_text} Selected reservoir: {_reservoir_text(result.selection)}."
        )
        doc.table(_agents_table(result.runs))
        return
    rows = tests[(tests["hypothesis"] == hyp.name) & (tests["task"] == result.label)]
    if hyp.rule is not None and not rows.empty:
        primary = rows[rows["metric"] == hyp.rule.primary]
        words = []
        for question in hyp.rule.questions:
            q = primary[primary["question"] == question.name]
            if not q.empty:
                words.append(f"{question.name}: **{task_outcome(q)}**")
        doc.p(f"**Verdicts ({hyp.rule.primary}).** " + "; ".join(words) + ".")
    doc.p(
        evolution_text
        + f" Selected reservoir: {_reservoir_text(result.selection)}. Selection record: "
        f"{result.trace}."
    )
    doc.table(_agents_table(result.runs))
    for name, source in result.references.items():
        doc.p(f"`{name}`: the published runs of {source}, read as they are (not re-run).")
    if not rows.empty:
        doc.table(_tests_table(rows))
    curves = result.folder / "report" / "test" / "learning_curves.png"
    if curves.exists():
        doc.img(_rel(curves, docs_dir), f"{result.label}: learning curves (mean and 95% CI)")
    spectra = result.folder / "report" / "dynamics" / "spectrum_comparison.png"
    if spectra.exists():
        doc.img(
            _rel(spectra, docs_dir),
            f"{result.label}: power spectra of the evolved and unevolved reservoirs' states",
        )
    per_seed = result.folder / "test" / "summary.csv"
    if per_seed.exists():
        link = _rel(result.folder / "test", docs_dir)
        doc.p(f"Per-seed files: [{link}]({link}).")
    own = result.runs[~result.runs["agent"].isin(result.references)]
    if math.isfinite(float(own["env_steps"].sum())):
        doc.p(
            f"Test phase: {int(own['env_steps'].sum()) / 1e6:.4g}M env steps, "
            f"{float(own['wall_seconds'].sum()) / 3600:.2f} h of run wall time"
            + (" (the borrowed runs not counted)." if result.references else ".")
        )
    _mechanism_section(doc, hyp, result, docs_dir, tests)
