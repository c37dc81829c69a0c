"""Verdicts that say no more than the data: a written rule, Holm's correction, three outcomes.

A *question* of an experiment (does the evolved reservoir beat PPO? does evolution beat the
unevolved reservoir?) is answered on each task by one or more *comparisons* ``candidate −
baseline`` of per-seed returns. Each comparison gets one of three outcomes:

- **supported**: both 95% intervals of the difference of means, Welch's t interval and the
  percentile bootstrap, lie above 0 *after the family's multiple-comparison adjustment*;
- **contradicted**: both lie below 0 after it;
- **inconclusive**: otherwise. The page then says which effects the data still excludes
  (the adjusted intervals' bounds), so that "no evidence" reads as "small" or as "unknown".

The *family* of a comparison is every test of the same question under the same metric on the
page (all tasks of all experiment files that name that question): Holm's step-down procedure
(Holm 1979) controls the family-wise error rate over it. The adjusted interval of the test of
Holm rank ``i`` (1-based, by raw Welch p) of ``m`` is taken at confidence ``1 − α/(m − i + 1)``,
and every test ranked after the first one Holm does not reject at the level of that step, so a
test's intervals exclude 0 exactly when Holm rejects it (Welch's interval and Welch's p agree;
the bootstrap must agree too).

A question's outcome on a task combines its comparisons: *supported* when all are,
*contradicted* when any is, *inconclusive* otherwise; *not run yet* when an agent of every one
of its comparisons has no finished run on the task (such a comparison is not tested and does not
count in its family). Over a hypothesis's tasks, the page counts
the outcomes and gives two aggregates with stratified bootstrap intervals (Agarwal et al. 2021,
rliable's definitions): the interquartile mean of normalized scores of each agent, and the
probability of improvement ``P(candidate > baseline)``.

The rule itself is data: the ``verdict:`` block of an experiment file
([`VerdictRule`][ermrl.analysis.VerdictRule]).
"""

from __future__ import annotations

import datetime as dt
import math
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ermrl.analysis._stats import (
    aggregate_iqm,
    bootstrap_mean_diff_ci,
    welch_t_test,
)

__all__ = [
    "METRICS",
    "NOT_RUN",
    "OUTCOMES",
    "Comparison",
    "Question",
    "EQUIVALENT",
    "NOT_SHOWN",
    "Reference",
    "TaskRuns",
    "VerdictRule",
    "VerdictError",
    "aggregate_question",
    "combine_outcomes",
    "equivalence_outcome",
    "equivalence_text",
    "not_run",
    "task_outcome",
    "holm",
    "verdict_changes",
    "judge",
    "load_test_runs",
    "probability_of_improvement",
    "seeds_for_power",
    "shared_runs",
]

#: The metrics a verdict can rest on: name -> (result.json column, what it is).
METRICS: dict[str, tuple[str, str]] = {
    "last10": ("final_return", "mean return of the last 10 training episodes"),
    "last100": (
        "last100_return",
        "mean return of the last 100 training episodes (SB3's rollout/ep_rew_mean, the metric "
        "the paper plots)",
    ),
    "eval": ("eval_return", "mean return of 10 deterministic evaluation episodes after training"),
}
OUTCOMES = ("supported", "contradicted", "inconclusive")
#: A question's status on a task none of whose comparisons could run (not an outcome).
NOT_RUN = "not run yet"
#: A comparison the page does not test (the selection is the reference, its two sides are the
#: same runs, or another test on the page already made it on the same runs): not an outcome,
#: and outside its family.
NOT_TESTED = "not tested"
CORRECTIONS = ("holm", "none")
#: Seeds searched by `seeds_for_power` before it gives up.
MAX_POWER_SEEDS = 10_000


class VerdictError(ValueError):
    """A ``verdict:`` block that cannot be used: one line naming the key."""


@dataclass(frozen=True)
class Comparison:
    """``candidate − baseline``, on the per-seed values of one metric."""

    candidate: str
    baseline: str

    @property
    def label(self) -> str:
        return f"{self.candidate} − {self.baseline}"

    @classmethod
    def parse(cls, text: Any, where: str) -> Comparison:
        """``"res-ppo - ppo"`` (an ASCII or a typographic minus)."""
        parts = str(text).replace("−", " - ").split(" - ") if isinstance(text, str) else []
        parts = [p.strip() for p in parts]
        if len(parts) != 2 or not all(parts):
            raise VerdictError(f"{where}: {text!r} is not 'CANDIDATE - BASELINE'")
        return cls(parts[0], parts[1])


@dataclass(frozen=True)
class Question:
    """One sub-question of a hypothesis.

    Attributes:
        name: Its family: every test of a question of this name on a page is adjusted
            together.
        text: The question in words.
        comparisons: What answers it on a task (all must be supported for a supported answer).
        adopted: When this question was added to its rule (ISO date), when later than the rule
            itself; ``None``: with the rule.
    """

    name: str
    text: str
    comparisons: tuple[Comparison, ...]
    adopted: str | None = None


@dataclass(frozen=True)
class Reference:
    """A baseline another experiment already ran: its published runs of one agent, per task.

    The runs are read from the other file's published test folders (not re-run) and enter the
    page under ``name``, so that a question can compare against them (``res-ppo - NAME``).

    Attributes:
        name: The baseline's name in this rule's comparisons.
        agent: The agent whose runs are read.
        tests: ``{task label: published test folder}``, relative to the working directory (the
            repository root, as ``publish:`` paths are).
    """

    name: str
    agent: str
    tests: Mapping[str, str]


@dataclass(frozen=True)
class VerdictRule:
    """How an experiment's verdicts are decided, as its file's ``verdict:`` block states it.

    Attributes:
        questions: The sub-questions, in order.
        alpha: Family-wise error rate (two-sided).
        correction: ``holm`` or ``none``.
        primary: The metric the headline verdicts use (a key of `METRICS`).
        adopted: When the rule was written (ISO date), compared on the page with the date of the
            first test result it judges.
        n_resamples: Bootstrap resamples.
        power: The power the seeds-needed line targets.
        references: Baselines read from other experiments' published runs
            ([`Reference`][ermrl.analysis.Reference]).
        margins: The equivalence margin of each task, ``((task, margin), ...)`` in the task's
            return units (the ``equivalence:`` block): a comparison is *equivalent within
            ±margin* only when two one-sided tests at its adjusted level reject both
            ``diff <= -margin`` and ``diff >= margin`` (see `equivalence_outcome`).
        margins_adopted: When the margins were written (ISO date), a rule of their own.
    """

    questions: tuple[Question, ...]
    alpha: float = 0.05
    correction: str = "holm"
    primary: str = "last10"
    adopted: str | None = None
    n_resamples: int = 10_000
    power: float = 0.8
    references: tuple[Reference, ...] = ()
    margins: tuple[tuple[str, float], ...] = ()
    margins_adopted: str | None = None

    def margin(self, task: str) -> float | None:
        """The equivalence margin of a task (``None``: the rule states none)."""
        return dict(self.margins).get(task)

    @classmethod
    def from_doc(cls, doc: Any, where: str = "verdict") -> VerdictRule:
        """Read a ``verdict:`` block (see ``experiments/paper/*.yaml``).

        Raises:
            VerdictError: an unknown key, a value out of range, an empty question list.
        """
        if not isinstance(doc, Mapping):
            raise VerdictError(f"{where}: a mapping is needed (alpha, correction, questions)")
        known = {
            "adopted",
            "alpha",
            "correction",
            "equivalence",
            "primary",
            "questions",
            "power",
            "references",
            "resamples",
        }
        for key in doc:
            if key not in known:
                raise VerdictError(
                    f"{where}: unknown key {key!r} (known: {', '.join(sorted(known))})"
                )
        alpha = doc.get("alpha", 0.05)
        if not isinstance(alpha, (int, float)) or isinstance(alpha, bool) or not 0 < alpha < 1:
            raise VerdictError(f"{where}.alpha: a number in (0, 1) is needed, got {alpha!r}")
        correction = doc.get("correction", "holm")
        if correction not in CORRECTIONS:
            raise VerdictError(
                f"{where}.correction: one of {', '.join(CORRECTIONS)}, got {correction!r}"
            )
        primary = doc.get("primary", "last10")
        if primary not in METRICS:
            raise VerdictError(f"{where}.primary: one of {', '.join(METRICS)}, got {primary!r}")
        power = doc.get("power", 0.8)
        if not isinstance(power, (int, float)) or isinstance(power, bool) or not 0 < power < 1:
            raise VerdictError(f"{where}.power: a number in (0, 1) is needed, got {power!r}")
        resamples = doc.get("resamples", 10_000)
        if not isinstance(resamples, int) or isinstance(resamples, bool) or resamples < 100:
            raise VerdictError(f"{where}.resamples: an integer >= 100 is needed, got {resamples!r}")
        adopted = _date(doc.get("adopted"), f"{where}.adopted")
        questions_doc = doc.get("questions")
        if not isinstance(questions_doc, Mapping) or not questions_doc:
            raise VerdictError(f"{where}.questions: name at least one question")
        questions = []
        for name, q in questions_doc.items():
            here = f"{where}.questions.{name}"
            if not isinstance(q, Mapping):
                raise VerdictError(f"{here}: a mapping with text and compare is needed")
            for key in q:
                if key not in ("adopted", "text", "compare"):
                    raise VerdictError(
                        f"{here}: unknown key {key!r} (known: adopted, compare, text)"
                    )
            compare = q.get("compare")
            if isinstance(compare, str):
                compare = [compare]
            if not isinstance(compare, list) or not compare:
                raise VerdictError(f"{here}.compare: list 'CANDIDATE - BASELINE' comparisons")
            comparisons = tuple(Comparison.parse(c, f"{here}.compare") for c in compare)
            questions.append(
                Question(
                    str(name),
                    str(q.get("text") or name),
                    comparisons,
                    _date(q.get("adopted"), f"{here}.adopted"),
                )
            )
        return cls(
            tuple(questions),
            float(alpha),
            str(correction),
            str(primary),
            adopted,
            int(resamples),
            float(power),
            _references(doc.get("references"), f"{where}.references"),
            *_margins(doc.get("equivalence"), f"{where}.equivalence"),
        )

    @property
    def metrics(self) -> tuple[str, ...]:
        """Every metric, the primary first."""
        return (self.primary, *(m for m in METRICS if m != self.primary))

    def describe(self) -> str:
        """The rule in words, as the page prints it."""
        correction = (
            f"Holm's step-down correction over each family (all tests of one question under one "
            f"metric on this page), family-wise α = {self.alpha:g}"
            if self.correction == "holm"
            else f"no multiple-comparison correction, α = {self.alpha:g} per test"
        )
        return (
            f"primary metric: {self.primary} ({METRICS[self.primary][1]}); {correction}; a "
            "comparison is supported when Welch's t interval and the percentile bootstrap "
            f"interval ({self.n_resamples} resamples) of the difference of means both lie above 0 "
            "at the adjusted level, contradicted when both lie below 0, inconclusive otherwise; "
            "a question is supported on a task when all its comparisons are, contradicted when "
            f"any is; seeds needed: per agent, for {self.power:.0%} power of Welch's test at the "
            "adjusted level, if the observed difference and spread were the truth"
            + self._describe_margins()
        )

    def _describe_margins(self) -> str:
        if not self.margins:
            return ""
        margins = ", ".join(f"{task} ±{value:g}" for task, value in self.margins)
        return (
            f"; equivalence (a rule of its own, adopted {self.margins_adopted}): a comparison is "
            f"*equivalent within ±δ* (δ per task: {margins}, in the task's return) when two "
            "one-sided Welch tests at its adjusted level α' reject both a difference of −δ or "
            "less and one of +δ or more, and the percentile bootstrap agrees (both 1 − 2α' "
            "intervals lie inside ±δ); otherwise equivalence is *not shown either way*, and the "
            "page gives the largest difference the intervals still allow"
        )


def _margins(doc: Any, where: str) -> tuple[tuple[tuple[str, float], ...], str | None]:
    """An ``equivalence:`` block: ``{adopted: DATE, margins: {TASK: MARGIN}}``."""
    if doc is None:
        return (), None
    if not isinstance(doc, Mapping) or set(doc) != {"adopted", "margins"}:
        raise VerdictError(f"{where}: a mapping with exactly adopted and margins is needed")
    adopted = _date(doc["adopted"], f"{where}.adopted")
    margins = doc["margins"]
    if not isinstance(margins, Mapping) or not margins:
        raise VerdictError(f"{where}.margins: a mapping TASK: margin (in the task's units)")
    out = []
    for task, value in margins.items():
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not ok or not math.isfinite(value) or value <= 0:
            raise VerdictError(
                f"{where}.margins.{task}: a positive number is needed, got {value!r}"
            )
        out.append((str(task), float(value)))
    return tuple(out), adopted


def _references(doc: Any, where: str) -> tuple[Reference, ...]:
    """A ``references:`` block: ``{NAME: {agent: AGENT, tests: {TASK: FOLDER}}}``."""
    if doc is None:
        return ()
    if not isinstance(doc, Mapping) or not doc:
        raise VerdictError(f"{where}: a mapping NAME: {{agent: AGENT, tests: {{TASK: FOLDER}}}}")
    out = []
    for name, ref in doc.items():
        here = f"{where}.{name}"
        if not isinstance(ref, Mapping) or set(ref) != {"agent", "tests"}:
            raise VerdictError(f"{here}: a mapping with exactly agent and tests is needed")
        agent, tests = ref["agent"], ref["tests"]
        if not isinstance(agent, str) or not agent:
            raise VerdictError(f"{here}.agent: an agent name is needed, got {agent!r}")
        if (
            not isinstance(tests, Mapping)
            or not tests
            or not all(isinstance(k, str) and isinstance(v, str) for k, v in tests.items())
        ):
            raise VerdictError(f"{here}.tests: a mapping TASK: published test folder is needed")
        out.append(Reference(str(name), agent, dict(tests)))
    return tuple(out)


def _date(value: Any, where: str) -> str | None:
    """An ``adopted:`` value as an ISO date (``None`` stays ``None``)."""
    if value is None:
        return None
    try:
        return dt.date.fromisoformat(str(value)).isoformat()
    except ValueError:
        raise VerdictError(f"{where}: a date (YYYY-MM-DD), got {value!r}") from None


@dataclass
class TaskRuns:
    """One task's per-seed results, as a verdict reads them.

    Attributes:
        hypothesis: The experiment's name.
        task: The task's label.
        runs: One row per run: ``agent``, ``seed`` and the metric columns of `METRICS`.
        reference_selected: The selection tested the unevolved reference itself (``res-ppo``
            and ``random-res-ppo`` are then the same runs: their difference is not tested).
        env_id: The env (for normalized scores; default: the label).
    """

    hypothesis: str
    task: str
    runs: pd.DataFrame
    reference_selected: bool = False
    env_id: str | None = None


def _values(runs: pd.DataFrame, agent: str, column: str) -> pd.Series:
    if runs.empty or column not in runs:
        return pd.Series(dtype=float)
    rows = runs[runs["agent"] == agent]
    values = pd.to_numeric(rows[column], errors="coerce")
    values.index = rows["seed"].to_numpy() if "seed" in rows else values.index
    return values[np.isfinite(values.to_numpy(dtype=float))]


def _pair(
    runs: pd.DataFrame, candidate: str, baseline: str, column: str, common: bool
) -> tuple[pd.Series, pd.Series]:
    """Both agents' values (on the seeds both have, with ``common``)."""
    a, b = _values(runs, candidate, column), _values(runs, baseline, column)
    if common:
        both = [sd for sd in a.index if sd in set(b.index)]
        a, b = a.loc[both], b.loc[both]
    return a, b


def _ran(runs: pd.DataFrame, agent: str) -> bool:
    return not runs.empty and "agent" in runs and bool((runs["agent"] == agent).any())


def holm(p_values: Sequence[float], alpha: float) -> tuple[list[float], list[float]]:
    """Holm's step-down procedure: adjusted p-values, and the level each test is judged at.

    Args:
        p_values: Raw two-sided p-values of one family.
        alpha: The family-wise error rate.

    Returns:
        ``(adjusted, levels)`` in the input order: ``adjusted[i] = max_{j <= rank(i)} min(1,
        (m - j + 1) p_(j))``; ``levels[i] = α / (m - rank(i) + 1)`` up to the first rank Holm does
        not reject, and that step's level from there on (so a test is rejected exactly when its
        p is at most its level, and its interval at ``1 - level`` excludes 0).

    Examples:
        >>> holm([0.01, 0.04, 0.03], 0.05)[0]
        [0.03, 0.06, 0.06]
    """
    p = np.asarray(p_values, dtype=float)
    m = len(p)
    order = np.argsort(p, kind="stable")
    adjusted = np.empty(m)
    levels = np.empty(m)
    running = 0.0
    stop_level = None
    for rank, i in enumerate(order):
        step = alpha / (m - rank)
        running = max(running, min(1.0, (m - rank) * p[i]))
        adjusted[i] = running
        if stop_level is None and not p[i] <= step:
            stop_level = step
        levels[i] = step if stop_level is None else stop_level
    # 12 significant digits: 2 x 0.03 reads 0.06, and a tiny p stays itself (15 decimals printed
    # H2 Ant's 7 x 9.9e-23 as 0).
    return [float(f"{a:.12g}") for a in adjusted], [float(v) for v in levels]


def seeds_for_power(
    diff: float,
    std_a: float,
    std_b: float,
    alpha: float,
    power: float = 0.8,
    max_seeds: int = MAX_POWER_SEEDS,
) -> int | None:
    """Seeds per agent at which a two-sided t test of two equal groups reaches ``power``.

    The effect is the observed one, ``|diff| / sqrt((std_a² + std_b²) / 2)`` (Cohen's d with
    the two spreads pooled), and the power is the noncentral t's (scipy).

    Returns:
        The smallest such number of seeds (at least 2); ``None`` when the difference is 0 or not
        finite, or more than ``max_seeds`` would be needed.
    """
    from scipy import stats

    if not all(math.isfinite(v) for v in (diff, std_a, std_b)) or diff == 0:
        return None
    spread = math.sqrt((std_a**2 + std_b**2) / 2)
    if spread == 0:
        return 2
    d = abs(diff) / spread

    def achieved(n: int) -> float:
        dof = 2 * n - 2
        crit = stats.t.ppf(1 - alpha / 2, dof)
        shift = d * math.sqrt(n / 2)
        value = float(stats.nct.sf(crit, dof, shift) + stats.nct.cdf(-crit, dof, shift))
        if not math.isfinite(value):  # scipy's noncentral t far in its tail
            value = float(stats.norm.sf(crit - shift))
        return value

    high = 2
    while achieved(high) < power:  # doubling, then bisection: power grows with the seeds
        if high >= max_seeds:
            return None
        high = min(2 * high, max_seeds)
    low = max(2, high // 2)
    while low < high:
        mid = (low + high) // 2
        if achieved(mid) >= power:
            high = mid
        else:
            low = mid + 1
    return low


def probability_of_improvement(
    pairs: Mapping[str, tuple[Sequence[float], Sequence[float]]],
    *,
    confidence: float = 0.95,
    n_resamples: int = 10_000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """``P(X > Y)`` averaged over tasks, with a stratified percentile bootstrap interval.

    rliable's ``probability_of_improvement``: per task, the Mann-Whitney statistic of the runs
    of ``X`` against those of ``Y`` divided by ``n_x n_y`` (a tie counts one half), averaged over
    tasks; each bootstrap resample redraws each agent's runs within each task.

    Args:
        pairs: ``{task: (x values, y values)}``; a task missing either side is left out.

    Returns:
        ``(estimate, low, high)``; NaNs with no task.
    """
    rng = np.random.default_rng(seed)
    per_task, resampled = [], []
    for x_raw, y_raw in pairs.values():
        x = np.asarray([v for v in x_raw if math.isfinite(v)], dtype=float)
        y = np.asarray([v for v in y_raw if math.isfinite(v)], dtype=float)
        if not len(x) or not len(y):
            continue
        per_task.append(_poi(x[None, :], y[None, :])[0])
        xs = x[rng.integers(0, len(x), size=(n_resamples, len(x)))]
        ys = y[rng.integers(0, len(y), size=(n_resamples, len(y)))]
        resampled.append(_poi(xs, ys))
    if not per_task:
        return math.nan, math.nan, math.nan
    estimates = np.mean(resampled, axis=0)
    tail = (1 - confidence) / 2
    low, high = np.quantile(estimates, [tail, 1 - tail])
    return float(np.mean(per_task)), float(low), float(high)


def _poi(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per row: the share of (x, y) pairs with x > y, ties counted one half; shape (rows,)."""
    greater = (x[:, :, None] > y[:, None, :]).mean(axis=(1, 2))
    ties = (x[:, :, None] == y[:, None, :]).mean(axis=(1, 2))
    return np.asarray(greater + 0.5 * ties)


def _outcome(lows: Sequence[float], highs: Sequence[float]) -> str:
    if all(math.isfinite(v) and v > 0 for v in lows):
        return "supported"
    if all(math.isfinite(v) and v < 0 for v in highs):
        return "contradicted"
    return "inconclusive"


def combine_outcomes(outcomes: Sequence[str]) -> str:
    """A question's outcome on a task from its comparisons' (see the module's docstring)."""
    if not outcomes:
        return "inconclusive"
    if all(o == "supported" for o in outcomes):
        return "supported"
    if any(o == "contradicted" for o in outcomes):
        return "contradicted"
    return "inconclusive"


def not_run(row: Mapping[str, Any]) -> bool:
    """Whether a judged comparison (a row of [`judge`][ermrl.analysis.judge]) was not tested because
    one of its agents has no finished run on the task."""
    return str(row.get("note") or "").startswith(NOT_RUN)


def task_outcome(rows: pd.DataFrame) -> str:
    """A question's outcome on a task from its judged comparisons (rows of
    [`judge`][ermrl.analysis.judge]): `combine_outcomes`, or `NOT_RUN` when none of them could
    run."""
    records = rows.to_dict("records")
    if records and all(not_run(r) for r in records):
        return NOT_RUN
    if records and all(str(r["outcome"]) == NOT_TESTED for r in records):
        return NOT_TESTED
    return combine_outcomes([str(r["outcome"]) for r in records if r["outcome"] != NOT_TESTED])


TEST_COLUMNS = [
    "hypothesis", "task", "question", "comparison", "candidate", "baseline", "metric",
    "n_candidate", "n_baseline", "mean_diff", "welch_low", "welch_high", "boot_low",
    "boot_high", "p_value", "family_size", "p_adjusted", "level", "adj_welch_low",
    "adj_welch_high", "adj_boot_low", "adj_boot_high", "outcome", "seeds_needed", "note",
    "margin", "tost_p", "equiv_low", "equiv_high", "equivalence",
]  # fmt: skip
#: A comparison's ``equivalence`` when its rule states a margin for the task: both ``1 - 2α'``
#: intervals (α' its adjusted level) lie inside ``±margin``.
EQUIVALENT = "equivalent"
#: Neither equivalence within the margin nor a difference is shown.
NOT_SHOWN = "not shown either way"


def judge(
    tasks: Sequence[TaskRuns],
    rules: Mapping[str, VerdictRule],
    seed: int = 0,
    *,
    common_seeds: bool = False,
) -> pd.DataFrame:
    """Every comparison of every question on every task, under every metric, judged.

    Args:
        tasks: The tasks of the page, each naming its hypothesis.
        rules: Each hypothesis's rule (a hypothesis without one is left out). Questions of one
            name form one family across hypotheses; their rules must then agree on alpha and
            correction.
        seed: Seed of the bootstraps.
        common_seeds: Compare each pair of agents on the seeds both have a value on only (a
            sensitivity check of comparisons whose groups have different seeds).

    Returns:
        One row per test (`TEST_COLUMNS`). ``note`` explains a comparison that was not
        tested (an agent without runs under that metric, or the reference selected), whose
        outcome is then ``inconclusive`` and which does not count in its family; an agent
        without any finished run on the task makes it `NOT_RUN` (outcome and note).

    Raises:
        VerdictError: two rules that pool a family disagree on its alpha or correction.
    """
    rows: list[dict[str, Any]] = []
    shared = shared_runs(tasks)
    made: list[tuple[int, Comparison]] = []  # the tests made so far, in the page's order
    for k, task in enumerate(tasks):
        rule = rules.get(task.hypothesis)
        if rule is None:
            continue
        comparisons = [comp for question in rule.questions for comp in question.comparisons]
        untested = {
            comp: why for comp in comparisons if (why := _same_runs(tasks, k, comp, shared, made))
        }
        reference = {"res-ppo", "random-res-ppo"}
        made += [
            (k, comp)
            for comp in comparisons
            if comp not in untested
            and not (task.reference_selected and {comp.candidate, comp.baseline} == reference)
        ]
        for metric in rule.metrics:
            column = METRICS[metric][0]
            for question in rule.questions:
                for comp in question.comparisons:
                    row = _raw_test(task, rule, question, comp, metric, column, seed, common_seeds)
                    if comp in untested and not row["note"]:
                        row["note"] = untested[comp]
                    if str(row["note"]).startswith(NOT_TESTED):
                        row["outcome"] = NOT_TESTED
                    rows.append(row)
    table = pd.DataFrame(rows, columns=TEST_COLUMNS)
    if table.empty:
        return table
    families: dict[tuple[str, str], list[int]] = {}
    tested = table[table["note"] == ""]
    for key, group in tested.groupby(["question", "metric"], sort=False):
        families[(str(key[0]), str(key[1]))] = [int(i) for i in group.index]
    for (family, _metric), index in families.items():
        family_rules = {
            (rules[h].alpha, rules[h].correction) for h in table.loc[index, "hypothesis"]
        }
        if len(family_rules) > 1:
            raise VerdictError(
                f"question {family!r} is one family across experiment files, but their "
                f"verdict rules differ in alpha or correction: {sorted(family_rules)}"
            )
        alpha, correction = family_rules.pop()
        p = table.loc[index, "p_value"].to_numpy(dtype=float)
        if correction == "holm":
            adjusted, levels = holm(p, alpha)
        else:
            adjusted, levels = list(p), [alpha] * len(p)
        for i, adj, level in zip(index, adjusted, levels, strict=True):
            _adjust(table, i, tasks, rules, adj, level, len(index), seed, common_seeds)
    return table


def shared_runs(
    tasks: Sequence[TaskRuns],
) -> dict[tuple[int, str], dict[tuple[int, str], list[int]]]:
    """Which groups of runs on a page are the same runs, found from the data.

    A group is one agent's runs on one task (``(index in tasks, agent)``). Two groups share a
    run when they have a seed with the same final and last-100 returns to the last digit (runs
    trained apart do not agree in every digit of both; runs of one setting, seed and code do):
    the reference's runs read by two files, a baseline borrowed from another file, a file that
    re-ran another's setting.

    Returns:
        ``{group: {other group: shared seeds}}``, both ways, for groups of different tasks or
        agents that share at least one seed.
    """
    prints: dict[tuple[int, str], dict[int, tuple[float, float]]] = {}
    for k, task in enumerate(tasks):
        runs = task.runs
        if runs.empty or not {"agent", "seed", "final_return"} <= set(runs.columns):
            continue
        last100 = runs["last100_return"] if "last100_return" in runs else math.nan
        frame = runs.assign(_last100=last100)
        for agent, group in frame.groupby("agent", sort=False):
            values = {
                int(sd): (float(f), float(h))
                for sd, f, h in zip(group["seed"], group["final_return"], group["_last100"])
                if math.isfinite(float(f))
            }
            prints[(k, str(agent))] = values
    out: dict[tuple[int, str], dict[tuple[int, str], list[int]]] = {}
    keys = list(prints)
    for i, one in enumerate(keys):
        for two in keys[i + 1 :]:
            env_one, env_two = (
                (tasks[one[0]].env_id or tasks[one[0]].task),
                (tasks[two[0]].env_id or tasks[two[0]].task),
            )
            if env_one != env_two:
                continue
            a, b = prints[one], prints[two]
            seeds = sorted(sd for sd in a if sd in b and _same(a[sd], b[sd]))
            if seeds:
                out.setdefault(one, {})[two] = seeds
                out.setdefault(two, {})[one] = seeds
    return out


def _same(one: tuple[float, float], two: tuple[float, float]) -> bool:
    return all(x == y or (math.isnan(x) and math.isnan(y)) for x, y in zip(one, two, strict=True))


def _seed_span(seeds: Sequence[int]) -> str:
    """``15–29`` for a run of consecutive seeds, else the list."""
    if len(seeds) > 2 and seeds[-1] - seeds[0] == len(seeds) - 1:
        return f"{seeds[0]}–{seeds[-1]}"
    return ", ".join(map(str, seeds))


def _same_runs(
    tasks: Sequence[TaskRuns],
    k: int,
    comp: Comparison,
    shared: Mapping[tuple[int, str], Mapping[tuple[int, str], list[int]]],
    made: Sequence[tuple[int, Comparison]],
) -> str:
    """Why a comparison is not tested because of shared runs (``""``: it is tested).

    Its two sides are the same runs (the same reservoir compared with itself), or an earlier test
    on the page compares the same runs on both sides: that test stands for both, counted once
    in its family.
    """
    task = tasks[k]
    cand, base = (k, comp.candidate), (k, comp.baseline)
    n = int((task.runs["agent"] == comp.candidate).sum()) if not task.runs.empty else 0
    selected = (
        "the selection is the unevolved reference (its evolved reservoir is the reference's), "
        if task.reference_selected and comp.candidate == "res-ppo"
        else ""
    )
    itself = shared.get(cand, {}).get(base)
    if itself:
        return (
            f"{NOT_TESTED}: {selected}`{comp.candidate}` and `{comp.baseline}` are the same runs "
            f"on seeds {_seed_span(itself)} ({len(itself)} of {n}): the same reservoir compared "
            "with itself"
        )
    for j, other in made:
        one = shared.get(cand, {}).get((j, other.candidate))
        two = shared.get(base, {}).get((j, other.baseline))
        if one and two and j != k:
            where = tasks[j]
            return (
                f"{NOT_TESTED}: {selected}the same runs as {where.hypothesis} {where.task}'s "
                f"`{other.label}` (`{comp.candidate}` on seeds {_seed_span(one)}, "
                f"`{comp.baseline}` on seeds {_seed_span(two)}): tested once, there"
            )
    return ""


def _raw_test(
    task: TaskRuns,
    rule: VerdictRule,
    question: Question,
    comp: Comparison,
    metric: str,
    column: str,
    seed: int,
    common: bool = False,
) -> dict[str, Any]:
    a, b = _pair(task.runs, comp.candidate, comp.baseline, column, common)
    row: dict[str, Any] = {c: math.nan for c in TEST_COLUMNS}
    row.update(
        hypothesis=task.hypothesis, task=task.task, question=question.name,
        comparison=comp.label, candidate=comp.candidate, baseline=comp.baseline, metric=metric,
        n_candidate=len(a), n_baseline=len(b), outcome="inconclusive", seeds_needed=None,
        note="", family_size=0, equivalence="",
    )  # fmt: skip
    same_runs = {comp.candidate, comp.baseline} == {"res-ppo", "random-res-ppo"}
    if task.reference_selected and same_runs:
        row["note"] = (
            "not tested: the selection chose the unevolved reference itself, so both agents are "
            "the same runs (evolution added nothing measurable)"
        )
        return row
    absent = [agent for agent in (comp.candidate, comp.baseline) if not _ran(task.runs, agent)]
    if absent:
        row["note"] = f"{NOT_RUN}: {absent[0]} has no finished run on this task"
        row["outcome"] = NOT_RUN
        return row
    if len(a) < 2 or len(b) < 2:
        missing = comp.candidate if len(a) < 2 else comp.baseline
        row["note"] = f"not tested: {missing} has fewer than 2 runs with this metric"
        return row
    welch = welch_t_test(a.to_numpy(), b.to_numpy())
    low, high = bootstrap_mean_diff_ci(a, b, n_resamples=rule.n_resamples, seed=seed)
    row.update(
        mean_diff=float(a.mean() - b.mean()), welch_low=welch.ci_low, welch_high=welch.ci_high,
        boot_low=low, boot_high=high, p_value=welch.p_value,
    )  # fmt: skip
    return row


def _adjust(
    table: pd.DataFrame,
    i: int,
    tasks: Sequence[TaskRuns],
    rules: Mapping[str, VerdictRule],
    adjusted: float,
    level: float,
    family_size: int,
    seed: int,
    common: bool = False,
) -> None:
    row = table.loc[i]
    rule = rules[row["hypothesis"]]
    task = next(t for t in tasks if t.hypothesis == row["hypothesis"] and t.task == row["task"])
    column = METRICS[row["metric"]][0]
    one, two = _pair(task.runs, row["candidate"], row["baseline"], column, common)
    a, b = one.to_numpy(), two.to_numpy()
    confidence = 1 - level
    welch = welch_t_test(a, b, confidence=confidence)
    low, high = bootstrap_mean_diff_ci(
        a, b, confidence=confidence, n_resamples=rule.n_resamples, seed=seed
    )
    outcome = _outcome([welch.ci_low, low], [welch.ci_high, high])
    seeds = seeds_for_power(
        float(row["mean_diff"]), float(np.std(a, ddof=1)), float(np.std(b, ddof=1)), level,
        rule.power,
    )  # fmt: skip
    table.loc[i, ["p_adjusted", "level", "family_size"]] = [adjusted, level, family_size]
    table.loc[i, ["adj_welch_low", "adj_welch_high", "adj_boot_low", "adj_boot_high"]] = [
        welch.ci_low, welch.ci_high, low, high,
    ]  # fmt: skip
    table.loc[i, "outcome"] = outcome
    table.at[i, "seeds_needed"] = seeds
    margin = rule.margin(str(row["task"]))
    if margin is not None:
        found = equivalence_outcome(a, b, margin, level, outcome, rule.n_resamples, seed)
        table.loc[i, ["margin", "tost_p", "equiv_low", "equiv_high"]] = [
            margin, found["tost_p"], found["equiv_low"], found["equiv_high"],
        ]  # fmt: skip
        table.loc[i, "equivalence"] = found["equivalence"]


def equivalence_outcome(
    a: np.ndarray,
    b: np.ndarray,
    margin: float,
    level: float,
    outcome: str,
    n_resamples: int = 10_000,
    seed: int = 0,
) -> dict[str, Any]:
    """The equivalence test of ``mean(a) - mean(b)`` within ``±margin`` at level ``level``.

    Two one-sided Welch tests ([`welch_tost`][ermrl.analysis.welch_tost]) at ``level`` (the
    comparison's Holm-adjusted level), with the percentile bootstrap's ``1 - 2 level`` interval
    required inside ``±margin`` too, as the three outcomes require both intervals.

    Args:
        a: The candidate's values.
        b: The baseline's values.
        margin: The task's margin (> 0).
        level: The comparison's adjusted level.
        outcome: The comparison's outcome (supported, contradicted or inconclusive).

    Returns:
        ``tost_p``, ``equiv_low`` and ``equiv_high`` (the outer ends of the two ``1 - 2 level``
        intervals) and ``equivalence``: `EQUIVALENT`, `NOT_SHOWN` (an inconclusive comparison
        not shown equivalent) or ``""`` (a difference shown, not equivalent).

    Examples:
        >>> import numpy as np
        >>> a, b = np.array([10.0, 11, 9, 10, 10.5, 9.5]), np.array([10.2, 9.8, 10, 10.4, 9.6, 10])
        >>> equivalence_outcome(a, b, 2.0, 0.05, "inconclusive", 2000)["equivalence"]
        'equivalent'
        >>> equivalence_outcome(a, b, 0.1, 0.05, "inconclusive", 2000)["equivalence"]
        'not shown either way'
    """
    from ermrl.analysis._stats import welch_tost

    tost = welch_tost(a, b, margin, level)
    low, high = bootstrap_mean_diff_ci(
        a, b, confidence=1 - 2 * level, n_resamples=n_resamples, seed=seed
    )
    lows, highs = [tost.ci_low, low], [tost.ci_high, high]
    finite = all(math.isfinite(v) for v in (*lows, *highs))
    inside = finite and tost.p_value <= level and -margin < min(lows) and max(highs) < margin
    label = (
        EQUIVALENT if inside else ("" if outcome in ("supported", "contradicted") else NOT_SHOWN)
    )
    return {
        "tost_p": tost.p_value,
        "equiv_low": min(lows) if finite else math.nan,
        "equiv_high": max(highs) if finite else math.nan,
        "equivalence": label,
    }


def equivalence_text(row: Mapping[str, Any]) -> str:
    """A judged comparison's equivalence in words (``""`` without a margin or an answer)."""
    label = row.get("equivalence")
    if not isinstance(label, str) or not label:
        return ""
    margin = float(row["margin"])
    level = _percent(1 - 2 * float(row["level"]))
    if label == EQUIVALENT:
        return (
            f"equivalent within ±{margin:g} (TOST p {float(row['tost_p']):.3g}; {level} "
            f"intervals within [{float(row['equiv_low']):+.4g}, {float(row['equiv_high']):+.4g}])"
        )
    bound = max(abs(float(row["equiv_low"])), abs(float(row["equiv_high"])))
    return (
        f"equivalence within ±{margin:g} not shown either way (TOST p "
        f"{float(row['tost_p']):.3g}; the {level} intervals reach {bound:.4g})"
    )


def excluded_effects(row: Mapping[str, Any]) -> str:
    """What an inconclusive comparison still rules out, in words (its adjusted intervals' ends)."""
    highs = [row.get("adj_welch_high", math.nan), row.get("adj_boot_high", math.nan)]
    lows = [row.get("adj_welch_low", math.nan), row.get("adj_boot_low", math.nan)]
    if not all(math.isfinite(float(v)) for v in (*highs, *lows)):
        return ""
    level = 1 - float(row["level"])
    return (
        f"effects above {max(highs):+.4g} or below {min(lows):+.4g} are excluded at "
        f"{_percent(level)}"
    )


#: The columns that name one judged comparison on a page.
COMPARISON_KEY = ["hypothesis", "task", "question", "comparison", "metric"]
#: What `verdict_changes` keeps of each side, besides the key.
_CHANGE_FIELDS = ["outcome", "n_candidate", "n_baseline", "mean_diff", "p_adjusted"]


def _outcome_or_not_run(table: pd.DataFrame) -> pd.Series:
    notes = table["note"] if "note" in table else pd.Series("", index=table.index)
    not_tested = notes.fillna("").astype(str).str.startswith(NOT_RUN)
    return table["outcome"].astype(str).where(~not_tested, NOT_RUN)


def verdict_changes(before: pd.DataFrame, after: pd.DataFrame) -> pd.DataFrame:
    """Each judged comparison of two pages side by side, and whether its verdict moved.

    Args:
        before: The earlier page's tests (rows of [`judge`][ermrl.analysis.judge], or its
            ``reproduction.csv``).
        after: The later page's.

    Returns:
        One row per comparison of either page (`COMPARISON_KEY`), in the later page's
        order with comparisons only the earlier page has at the end. Columns ``outcome``,
        ``n_candidate``, ``n_baseline``, ``mean_diff`` and ``p_adjusted`` with suffixes
        ``_before`` and ``_after`` (a comparison that was not tested reads `NOT_RUN`),
        the later page's ``seeds_needed`` (the power line) and ``change``: ``moved`` (another
        outcome), ``same``, ``new`` (only the later page has it) or ``gone`` (only the earlier).

    Raises:
        VerdictError: a table lacks a column of the key or the outcome.
    """
    sides = []
    for name, table in (("before", before), ("after", after)):
        missing = [c for c in (*COMPARISON_KEY, "outcome") if c not in table.columns]
        if missing:
            raise VerdictError(f"the {name} table has no column {', '.join(missing)}")
        side = table.copy()
        side["outcome"] = _outcome_or_not_run(side)
        for column in _CHANGE_FIELDS:
            if column not in side:
                side[column] = math.nan
        side["order"] = range(len(side))
        kept = [*COMPARISON_KEY, *_CHANGE_FIELDS, "order"]
        if name == "after":
            side["seeds_needed"] = side.get("seeds_needed", math.nan)
            kept.append("seeds_needed")
        sides.append(side[kept].drop_duplicates(COMPARISON_KEY))
    merged = sides[0].merge(
        sides[1], on=COMPARISON_KEY, how="outer", suffixes=("_before", "_after"), indicator=True
    )
    change = np.where(
        merged["_merge"] == "right_only",
        "new",
        np.where(
            merged["_merge"] == "left_only",
            "gone",
            np.where(merged["outcome_before"] == merged["outcome_after"], "same", "moved"),
        ),
    )
    merged["change"] = change
    merged["_rank"] = merged["order_after"].fillna(len(merged) + merged["order_before"])
    merged = merged.sort_values("_rank", kind="stable").reset_index(drop=True)
    columns = [
        *COMPARISON_KEY,
        *(f"{c}_{s}" for c in _CHANGE_FIELDS for s in ("before", "after")),
        "seeds_needed",
        "change",
    ]
    return merged[columns]


def _percent(level: float) -> str:
    text = f"{100 * level:.2f}".rstrip("0").rstrip(".")
    return f"{text}%"


def aggregate_question(
    tasks: Sequence[TaskRuns],
    question: Question,
    metric: str,
    normalizer: Any = None,
    *,
    n_resamples: int = 10_000,
    seed: int = 0,
    untested: Mapping[tuple[str, str], str] | None = None,
) -> list[dict[str, Any]]:
    """A question's aggregates over tasks: the probability of improvement of each comparison
    and the IQM of each agent's normalized scores, with stratified bootstrap 95% intervals.

    Args:
        tasks: The hypothesis's tasks.
        question: The question.
        metric: A key of `METRICS`.
        normalizer: ``(env_id, values) -> normalized values`` or ``None`` when a task has no
            reference scores (the IQMs are then left out, naming it).
        untested: ``{(task, comparison label): why}`` of comparisons the page does not test
            (shared runs, [`judge`][ermrl.analysis.judge]'s `NOT_TESTED`): left out, naming why.

    Returns:
        One row per comparison: ``comparison, n_tasks, poi, poi_low, poi_high, poi_outcome``
        (supported when the interval lies above 1/2, contradicted below), and
        ``iqm_candidate, iqm_candidate_low, iqm_candidate_high`` and the same for the baseline
        (NaN without normalized scores), and ``note``.
    """
    column = METRICS[metric][0]
    rows = []
    for comp in question.comparisons:
        pairs: dict[str, tuple[Any, Any]] = {}
        skipped = []
        for task in tasks:
            same = {comp.candidate, comp.baseline} == {"res-ppo", "random-res-ppo"}
            if task.reference_selected and same:
                skipped.append(f"{task.task} (reference selected)")
                continue
            if untested and (task.task, comp.label) in untested:
                skipped.append(f"{task.task} ({untested[(task.task, comp.label)]})")
                continue
            a = _values(task.runs, comp.candidate, column)
            b = _values(task.runs, comp.baseline, column)
            if len(a) and len(b):
                pairs[task.task] = (a.to_numpy(), b.to_numpy())
            else:
                skipped.append(f"{task.task} (no runs)")
        poi, low, high = probability_of_improvement(pairs, n_resamples=n_resamples, seed=seed)
        row: dict[str, Any] = {
            "comparison": comp.label,
            "n_tasks": len(pairs),
            "poi": poi,
            "poi_low": low,
            "poi_high": high,
            "poi_outcome": _outcome([low - 0.5], [high - 0.5]) if pairs else "inconclusive",
            "note": ("left out: " + ", ".join(skipped)) if skipped else "",
        }
        for side in ("candidate", "baseline"):
            row[f"iqm_{side}"] = row[f"iqm_{side}_low"] = row[f"iqm_{side}_high"] = math.nan
        envs = {task.task: task.env_id or task.task for task in tasks if task.task in pairs}
        unscored = [
            env for env in envs.values() if normalizer is None or normalizer(env, [0.0]) is None
        ]
        if unscored and pairs:
            row["note"] = (row["note"] + "; " if row["note"] else "") + (
                f"no reference scores for {', '.join(unscored)}: no IQM"
            )
        elif pairs:
            for k, side in enumerate(("candidate", "baseline")):
                scores = {t: normalizer(envs[t], pair[k]) for t, pair in pairs.items()}
                result = aggregate_iqm(scores, n_resamples=n_resamples, seed=seed)
                row[f"iqm_{side}"] = result.iqm
                row[f"iqm_{side}_low"] = result.ci_low
                row[f"iqm_{side}_high"] = result.ci_high
        rows.append(row)
    return rows


def load_test_runs(test_folder: str | Path) -> pd.DataFrame:
    """A test phase's finished runs with every verdict metric (`METRICS`).

    ``last100_return`` is read from each run's ``result.json``, or computed from its
    ``episodes.csv`` for runs written before it was recorded (the same definition: the mean of
    the last 100 training episodes).
    """
    from ermrl.analysis._results import EPISODES_FILE, load_run_results, read_episodes, run_dir

    runs = load_run_results(test_folder)
    if runs.empty:
        return runs
    for column in ("last100_return", "eval_return"):
        if column not in runs:
            runs[column] = math.nan
    missing = runs["last100_return"].isna()
    for i in runs.index[missing]:
        agent, seed = runs.at[i, "agent"], int(runs.at[i, "seed"])
        episodes = read_episodes(run_dir(test_folder, agent, seed) / EPISODES_FILE)
        values = pd.to_numeric(episodes["episode_return"], errors="coerce").dropna()
        runs.at[i, "last100_return"] = float(values.tail(100).mean()) if len(values) else math.nan
    runs["last100_return"] = runs["last100_return"].astype(float)
    runs["eval_return"] = pd.to_numeric(runs["eval_return"], errors="coerce")
    return runs


def returns_at_step(
    test_folder: str | Path, step: int, n: int = 10, agent: str | None = None
) -> pd.DataFrame:
    """What a test phase's finished runs (of `agent`, or all) had learned by env step `step`:
    each run's mean return over its last `n` training episodes that ended by then, from its
    ``episodes.csv``.

    With `step` at the evolution's budget, this compares the runs where evolution judged its
    candidates (a longer test budget can rank them otherwise).

    Returns:
        One row per run: ``agent``, ``seed`` and ``return_at_step`` (NaN for a run with no
        episode ended by `step`).
    """
    from ermrl.analysis._results import EPISODES_FILE, load_run_results, read_episodes, run_dir

    if step <= 0 or n <= 0:
        raise ValueError(f"step and n must be positive, got step={step}, n={n}")
    runs = load_run_results(test_folder)
    if not runs.empty and agent is not None:
        runs = runs[runs["agent"] == agent]
    if runs.empty:
        return pd.DataFrame(columns=["agent", "seed", "return_at_step"])
    values = []
    for name, seed in zip(runs["agent"], runs["seed"], strict=True):
        episodes = read_episodes(run_dir(test_folder, name, int(seed)) / EPISODES_FILE)
        ended = pd.to_numeric(episodes["env_step"]) <= step
        kept = pd.to_numeric(episodes["episode_return"])[ended].dropna()
        values.append(float(kept.tail(n).mean()) if len(kept) else math.nan)
    return runs[["agent", "seed"]].assign(return_at_step=values).reset_index(drop=True)


def first_result_date(test_folder: Path) -> tuple[str | None, str]:
    """When a test phase's first result existed: ``(ISO date or None, where it comes from)``.

    A run's ``result.json`` says when it finished (``finished``); runs written before ermrl
    recorded that are dated by the git commit that first added a result of the folder.
    """
    import json

    dates = []
    for path in sorted(Path(test_folder).glob("agents/*/seed_*/result.json")):
        try:
            finished = json.loads(path.read_text()).get("finished")
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(finished, str):
            dates.append(finished[:10])
    try:
        done = subprocess.run(
            ["git", "log", "--diff-filter=A", "--format=%cs", "--", "agents"],
            cwd=test_folder,
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
        committed = done.stdout.split() if done.returncode == 0 else []
    except (OSError, subprocess.SubprocessError):
        committed = []
    if committed:
        dates.append(min(committed))
    if not dates:
        return None, "unknown"
    first = min(dates)
    source = "the commit that published it" if first in committed else "its result.json"
    return first, source
