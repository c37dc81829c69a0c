"""The reproduction page: each hypothesis of an experiment file, its published results, a verdict.

It reads only plain files: the experiment files (``experiments/paper/*.yaml``) and what
``ermrl run`` published for them (per-seed ``result.json`` files, the report's figures, the
study snapshot). Every number on the page can be recomputed from those files.

Verdicts, per task, on the paper's claim that the evolved reservoir (``res-ppo``) helps PPO:

- *reproduced*: the 95% CIs of ``res-ppo − ppo`` both lie above 0, the percentile bootstrap
  and Welch's t interval (the bootstrap alone is too narrow on a handful of seeds);
- *partly*: ``res-ppo`` is ahead of ``ppo`` but a CI spans 0;
- *not reproduced*: ``res-ppo`` is not ahead of ``ppo``.

The rule was fixed before the paper-scale test phases ran, and it is not tuned per task.

What evolution itself adds (``res-ppo − random-res-ppo``) is reported beside it in words of its
own, and so is where ``res-ppo`` stands against every other agent the test phase trained
(learned memory such as ``lstm-ppo`` and ``framestack-ppo``, or ``ppo-full``, the ceiling): ahead
or behind when both CIs agree, inside the noise otherwise. A hypothesis is *reproduced* when all its tasks are, *not reproduced* when none is, and
*partly* otherwise; tasks not yet run are named as such and left out of the verdict.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from ermrl.analysis._stats import FEW_SEEDS

__all__ = [
    "Hypothesis",
    "TaskFiles",
    "TaskResult",
    "task_result",
    "verdict",
    "write_reproduction_page",
]

EVOLVED = "res-ppo"
BASELINES = ("ppo", "random-res-ppo")


@dataclass
class TaskResult:
    """What the published files say about one task of one experiment.

    Attributes:
        label: The task (test task for a generalization experiment).
        folder: Its published folder.
        runs: One row per finished test run (``result.json``).
        comparison: :func:`~ermrl.analysis.compare_agents` of ``res-ppo`` against the baselines
            (``ppo``, ``random-res-ppo``), then every other agent tested.
        evolution: ``finished``, ``n_trials``, ``env_steps``, ``wall_seconds`` of the study.
        selection: The selected reservoir(s) and how they were chosen.
    """

    label: str
    folder: Path
    runs: pd.DataFrame
    comparison: pd.DataFrame
    evolution: dict[str, Any] = field(default_factory=dict)
    selection: dict[str, Any] = field(default_factory=dict)

    @property
    def tested(self) -> bool:
        return not self.runs.empty and EVOLVED in set(self.runs["agent"])


def _row(comparison: pd.DataFrame, baseline: str) -> dict[str, Any] | None:
    if comparison.empty:
        return None
    rows = comparison[comparison["baseline"] == baseline]
    return None if rows.empty else rows.iloc[0].to_dict()


def verdict(comparison: pd.DataFrame, reference_selected: bool = False) -> tuple[str, str]:
    """The verdict on ``res-ppo > ppo`` and what evolution adds, each as ``(word, reason)``.

    ``reference_selected``: the selection chose the unevolved reference itself, so ``res-ppo``
    and ``random-res-ppo`` are the same runs and their difference is 0 by construction (its
    unpaired CIs, which resample the two copies independently, say nothing then).

    Returns:
        ``(verdict, reason)`` where verdict is ``reproduced``, ``partly`` or ``not reproduced``.
    """
    vs_ppo = _row(comparison, "ppo")
    if vs_ppo is None:
        return "not run", "no finished res-ppo and ppo runs"
    diff = vs_ppo["mean_diff"]
    lows = [vs_ppo["boot_ci_low"], vs_ppo.get("welch_ci_low", math.nan)]
    ci = f"res-ppo − ppo = {diff:+.4g}, {_intervals(vs_ppo)}"
    if all(math.isfinite(low) and low > 0 for low in lows):
        word, why = "reproduced", f"{ci}: both lie above 0"
    elif diff > 0:
        word, why = "partly", f"{ci}: ahead, but not both CIs lie above 0"
    else:
        word, why = "not reproduced", f"{ci}: res-ppo is not ahead of PPO"
    if vs_ppo.get("few_seeds"):
        why += f" (fewer than {FEW_SEEDS} seeds per agent: the CIs are unreliable)"
    vs_random = _row(comparison, "random-res-ppo")
    if vs_random is not None and reference_selected:
        why += (
            "; res-ppo − random-res-ppo = 0 by construction: the selection chose the unevolved "
            "reference itself (the same runs), so evolution added nothing measurable here"
        )
    elif vs_random is not None:
        r_lows = [vs_random["boot_ci_low"], vs_random.get("welch_ci_low", math.nan)]
        r_highs = [vs_random["boot_ci_high"], vs_random.get("welch_ci_high", math.nan)]
        if all(math.isfinite(v) and v > 0 for v in r_lows):
            add = "evolution beats the unevolved reservoir (both CIs above 0)"
        elif all(math.isfinite(v) and v < 0 for v in r_highs):
            add = "the unevolved reservoir beats the evolved one (both CIs below 0)"
        else:
            add = "evolved against unevolved is inside the noise (a CI spans 0)"
        why += (
            f"; res-ppo − random-res-ppo = {vs_random['mean_diff']:+.4g}, "
            f"{_intervals(vs_random)}: {add}"
        )
    others = [] if comparison.empty else [
        b for b in comparison["baseline"] if b not in BASELINES
    ]  # fmt: skip
    for baseline in others:
        row = _row(comparison, baseline)
        assert row is not None
        why += (
            f"; res-ppo − {baseline} = {row['mean_diff']:+.4g}, {_intervals(row)}: {_standing(row)}"
        )
    return word, why


def _standing(row: dict[str, Any]) -> str:
    """Where the candidate stands against one baseline: both CIs above 0, below 0, or neither."""
    lows = [row["boot_ci_low"], row.get("welch_ci_low", math.nan)]
    highs = [row["boot_ci_high"], row.get("welch_ci_high", math.nan)]
    if all(math.isfinite(v) and v > 0 for v in lows):
        return "ahead (both CIs above 0)"
    if all(math.isfinite(v) and v < 0 for v in highs):
        return "behind (both CIs below 0)"
    return "inside the noise (a CI spans 0)"


def _intervals(row: dict[str, Any]) -> str:
    """The bootstrap and Welch 95% intervals of a comparison row, in words."""
    text = f"95% bootstrap CI [{row['boot_ci_low']:+.4g}, {row['boot_ci_high']:+.4g}]"
    if math.isfinite(row.get("welch_ci_low", math.nan)):
        text += (
            f", Welch CI [{row['welch_ci_low']:+.4g}, {row['welch_ci_high']:+.4g}]"
            f" (p = {row['p_value']:.2g})"
        )
    return text


def _snapshot_evolution(path: Path, n_trials: int) -> dict[str, Any]:
    if not path.exists():
        return {"finished": 0, "n_trials": n_trials, "env_steps": 0, "wall_seconds": 0.0}
    doc = json.loads(path.read_text())
    trials = doc.get("trials", [])
    done = [t for t in trials if t.get("state") in ("COMPLETE", "PRUNED")]
    steps = sum(int(t.get("user_attrs", {}).get("env_steps") or 0) for t in trials)
    wall = sum(float(t.get("user_attrs", {}).get("wall_seconds") or 0.0) for t in trials)
    for related in doc.get("related", {}).values():  # the re-evaluation runs
        for t in related.get("trials", []):
            steps += int(t.get("user_attrs", {}).get("env_steps") or 0)
            wall += float(t.get("user_attrs", {}).get("wall_seconds") or 0.0)
    return {"finished": len(done), "n_trials": n_trials, "env_steps": steps, "wall_seconds": wall}


def task_result(folder: Path, label: str, n_trials: int, snapshot: Path) -> TaskResult:
    """Read one task's published files (see :class:`TaskResult`)."""
    from ermrl.analysis._results import load_run_results
    from ermrl.analysis._stats import compare_agents

    test = folder / "test"
    runs = load_run_results(test) if test.exists() else pd.DataFrame()
    comparison = pd.DataFrame()
    if not runs.empty:
        # The paper's baselines first, then every other agent the test phase trained (learned
        # memory, the full observation), in the agent table's order.
        from ermrl.learners import AGENT_KINDS

        tested = set(runs["agent"])
        others = [a for a in AGENT_KINDS if a in tested and a != EVOLVED and a not in BASELINES]
        others += sorted(tested - set(AGENT_KINDS) - {EVOLVED} - set(BASELINES))
        comparison = compare_agents(runs, EVOLVED, [*BASELINES, *others])
    selection: dict[str, Any] = {}
    config = test / "config.yaml"
    if config.exists():
        doc = yaml.safe_load(config.read_text()) or {}
        agents = doc.get("agents") or {}
        selection = {
            "trial": doc.get("trial"),
            "selection": doc.get("selection"),
            "reservoirs": agents.get(EVOLVED),
            # The evolved agent's reservoirs are the unevolved one's: the reference won.
            "reference": bool(agents.get(EVOLVED))
            and agents.get(EVOLVED) == agents.get("random-res-ppo"),
        }
    return TaskResult(
        label, folder, runs, comparison, _snapshot_evolution(snapshot, n_trials), selection
    )


def _agents_table(runs: pd.DataFrame) -> pd.DataFrame:
    from ermrl.analysis._stats import final_returns_table

    table = final_returns_table(runs)
    if table.empty:
        return table
    out = table[["agent", "n_seeds", "mean", "std", "ci95_low", "ci95_high"]].copy()
    env_steps = runs.groupby("agent")["env_steps"].sum()
    wall = runs.groupby("agent")["wall_seconds"].sum()
    out["env steps"] = [int(env_steps.get(a, 0)) for a in out["agent"]]
    out["wall (h)"] = [float(wall.get(a, 0.0)) / 3600 for a in out["agent"]]
    return out.rename(
        columns={"n_seeds": "seeds", "ci95_low": "95% CI low", "ci95_high": "95% CI high"}
    )


def _comparison_table(comparison: pd.DataFrame) -> pd.DataFrame:
    cols = {
        "baseline": "res-ppo against",
        "mean_diff": "mean difference",
        "boot_ci_low": "bootstrap CI low",
        "boot_ci_high": "bootstrap CI high",
        "welch_ci_low": "Welch CI low",
        "welch_ci_high": "Welch CI high",
        "paired_ci_low": "paired CI low",
        "paired_ci_high": "paired CI high",
        "n_paired": "paired seeds",
        "p_value": "Welch p",
    }
    cols["few_seeds"] = f"< {FEW_SEEDS} seeds"
    present = [c for c in cols if c in comparison]
    return comparison[present].rename(columns=cols)


def _reference_selected(result: TaskResult) -> bool:
    return bool(result.selection.get("reference"))


def _reservoir_text(selection: dict[str, Any]) -> str:
    reservoirs = selection.get("reservoirs") or []
    parts = []
    for i, r in enumerate(reservoirs):
        genes = ", ".join(
            f"{k} {r[k]:.4g}" for k in ("sr", "lr", "input_scaling") if isinstance(r.get(k), float)
        )
        parts.append(f"reservoir {i}: {genes} ({r.get('units')} units)")
    trial = selection.get("trial")
    how = selection.get("selection") or ""
    head = f"trial #{trial}" if trial is not None else "the selected trial"
    return f"{head}{f' ({how})' if how else ''}: " + "; ".join(parts) if parts else head


@dataclass(frozen=True)
class TaskFiles:
    """Where one task's published files are.

    Attributes:
        label: The task tested.
        evolved_on: The task (or task set) its reservoirs were evolved on.
        folder: Its published folder (``test/`` and ``report/`` inside).
        snapshot: The evolution study's snapshot (``study.json``).
        n_trials: The evolution's budget.
    """

    label: str
    evolved_on: str
    folder: Path
    snapshot: Path
    n_trials: int


@dataclass(frozen=True)
class Hypothesis:
    """One experiment file on the page: its claim and its tasks' files."""

    name: str
    file: str
    claim: str | None
    description: str | None
    tasks: tuple[TaskFiles, ...]


def write_reproduction_page(
    hypotheses: Sequence[Hypothesis],
    out: str | Path,
    *,
    html_page: bool = True,
) -> tuple[Path, Path | None]:
    """Write the reproduction page.

    Args:
        hypotheses: One entry per experiment file (see :class:`Hypothesis`).
        out: The Markdown file to write (``docs/reproduction.md``); the HTML form goes beside it
            with the ``.html`` suffix. Figures are linked relative to its folder.
        html_page: Also write the HTML form.

    Returns:
        ``(markdown, html or None)``.
    """
    from ermrl._io import write_atomic
    from ermrl.analysis._report import _Doc

    out = Path(out)
    doc = _Doc()
    doc.h(1, "Reproducing *Evolving Reservoirs for Meta Reinforcement Learning*")
    doc.p(
        "Léger, Hamon, Nisioti, Hinaut and Moulin-Frier, EvoApplications 2024 "
        "([arXiv:2312.06695](https://arxiv.org/abs/2312.06695)). Each hypothesis below is one "
        "experiment file that `ermrl run FILE` runs and resumes; its header states its scale "
        "and how it differs from the paper. Every number is computed from the per-seed files "
        "published under `benchmarks/results/paper/` (a `result.json` per run) by "
        "`ermrl reproduction`."
    )
    doc.p(
        "**Verdicts.** Per task, on the paper's claim that the evolved reservoir helps PPO: "
        "*reproduced* when the 95% CIs of `res-ppo − ppo` (final return: mean of the last 10 "
        "training episodes) both lie above 0, the percentile bootstrap and Welch's t interval "
        "(the bootstrap alone is too narrow on a handful of seeds); *partly* when `res-ppo` is "
        "ahead but a CI spans 0; *not reproduced* otherwise. The rule was fixed before the "
        "paper-scale test phases ran. What evolution itself adds, `res-ppo − "
        "random-res-ppo`, is reported beside it, and so is `res-ppo` against every other "
        "agent a test phase trained (learned memory, the full observation): ahead or behind "
        "when both CIs agree, inside the noise otherwise. The paired CI resamples per-seed "
        "differences "
        "(the agents of one seed share its env and initialization streams). A result that "
        "contradicts the paper is reported as such."
    )
    summary_rows = []
    sections = []
    for hyp in hypotheses:
        section = _Doc()
        section.h(2, f"{hyp.name}: `{hyp.file}`")
        if hyp.claim:
            section.p(f"**The paper's claim** (quoted as a claim, not as a finding): {hyp.claim}")
        if hyp.description:
            section.p(hyp.description.strip())
        results = []
        for task in hyp.tasks:
            result = task_result(task.folder, task.label, task.n_trials, task.snapshot)
            results.append(result)
            _task_section(section, result, out.parent, task.evolved_on)
        tested = [r for r in results if r.tested]
        words = [verdict(r.comparison, _reference_selected(r))[0] for r in tested]
        if not tested:
            overall = "not run yet"
        elif all(w == "reproduced" for w in words):
            overall = "reproduced"
        elif not any(w in ("reproduced", "partly") for w in words):
            overall = "not reproduced"
        else:
            overall = "partly"
        pending = [r.label for r in results if not r.tested]
        if pending and tested:
            overall += f" (on {len(tested)} of {len(results)} tasks; pending: {', '.join(pending)})"
        progress = "; ".join(
            f"{r.label}: {r.evolution['finished']}/{r.evolution['n_trials']} trials"
            for r in results
        )
        summary_rows.append(
            {"hypothesis": hyp.name, "verdict": overall, "evolution progress": progress}
        )
        sections.append(section)
    doc.h(2, "Verdicts at a glance")
    doc.table(pd.DataFrame(summary_rows))
    for section in sections:
        doc.blocks += section.blocks
    write_atomic(out, doc.markdown())
    html_path = None
    if html_page:
        html_path = out.with_suffix(".html")
        write_atomic(html_path, doc.html("ermrl: reproduction of ER-MRL"))
    return out, html_path


def _rel(path: Path, start: Path) -> str:
    import os

    return os.path.relpath(path, start)


def _task_section(doc: Any, result: TaskResult, docs_dir: Path, evolve_label: str) -> None:
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
        doc.p(f"**Verdict: not run yet.** {evolution_text} The test phase has not run.")
        return
    word, why = verdict(result.comparison, _reference_selected(result))
    doc.p(f"**Verdict: {word}.** {why}.")
    doc.p(evolution_text + f" Selected reservoir: {_reservoir_text(result.selection)}.")
    doc.table(_agents_table(result.runs))
    if not result.comparison.empty:
        doc.table(_comparison_table(result.comparison))
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
        doc.p(
            f"Per-seed files: [{_rel(result.folder / 'test', docs_dir)}]({_rel(result.folder / 'test', docs_dir)})."
        )
    if math.isfinite(float(result.runs["env_steps"].sum())):
        doc.p(
            f"Test phase: {int(result.runs['env_steps'].sum()) / 1e6:.4g}M env steps, "
            f"{float(result.runs['wall_seconds'].sum()) / 3600:.2f} h of run wall time."
        )
