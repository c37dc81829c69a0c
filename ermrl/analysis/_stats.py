"""Statistics of final returns: per-agent tables, tests of one agent against another, and the
IQM aggregate of scores over a set of tasks."""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ermrl.analysis._results import t_quantile
from ermrl.learners import AGENT_KINDS, EVOLVED_AGENT

__all__ = [
    "FEW_SEEDS",
    "IQMResult",
    "TOSTResult",
    "WelchResult",
    "aggregate_iqm",
    "bootstrap_mean_diff_ci",
    "compare_agents",
    "few_seeds_flag",
    "final_returns_table",
    "iqm",
    "paired_bootstrap_mean_diff_ci",
    "welch_t_test",
    "welch_tost",
]

METRICS = ("final_return", "eval_return")

#: Below this many seeds per agent, a confidence interval is flagged: the percentile bootstrap
#: is too narrow on 2-4 values (it cannot reach beyond the sample's range), so a report shows
#: Welch's t interval beside it and marks the comparison ``few_seeds``.
FEW_SEEDS = 5


def few_seeds_flag(*n_seeds: int) -> str:
    """The visible flag of an interval computed from fewer than `FEW_SEEDS` seeds.

    Args:
        n_seeds: The number of seeds (runs) of each group behind the interval.

    Returns:
        ``"few seeds (n=2 < 5)"`` (``n`` the smallest group), or ``""`` when every group has
        at least `FEW_SEEDS` seeds or none is given.

    Examples:
        >>> few_seeds_flag(2, 5)
        'few seeds (n=2 < 5)'
        >>> few_seeds_flag(5, 8)
        ''
    """
    if not n_seeds:
        return ""
    n = min(int(k) for k in n_seeds)
    return f"few seeds (n={n} < {FEW_SEEDS})" if n < FEW_SEEDS else ""


@dataclass(frozen=True)
class WelchResult:
    """Welch's unequal-variance t-test of ``mean(a) - mean(b)``.

    Attributes:
        statistic: The t statistic (NaN when undefined: fewer than 2 values in a group, or
            both groups without variance).
        dof: Welch-Satterthwaite degrees of freedom.
        p_value: Two-sided p-value.
        ci_low: Lower end of Welch's t confidence interval of ``mean(a) - mean(b)``.
        ci_high: Upper end of that interval.
    """

    statistic: float
    dof: float
    p_value: float
    ci_low: float = math.nan
    ci_high: float = math.nan


def welch_t_test(
    a: Sequence[float] | np.ndarray,
    b: Sequence[float] | np.ndarray,
    *,
    confidence: float = 0.95,
) -> WelchResult:
    """Welch's t-test (two-sided) of the difference of means of two independent samples.

    Computed by `scipy.stats.ttest_ind` with ``equal_var=False``, interval included.

    Args:
        a: Values of the first group, shape ``(n_a,)`` (NaNs are dropped).
        b: Values of the second group, shape ``(n_b,)``.
        confidence: Coverage of the t interval.

    Returns:
        The statistic, degrees of freedom, p-value and interval (all NaN when undefined).

    Examples:
        >>> round(welch_t_test([1.0, 2.0, 3.0], [4.0, 5.0, 6.0]).statistic, 3)
        -3.674
    """
    from scipy import stats

    x = _clean(a)
    y = _clean(b)
    nan = WelchResult(math.nan, math.nan, math.nan)
    if len(x) < 2 or len(y) < 2:
        return nan
    vx, vy = x.var(ddof=1) / len(x), y.var(ddof=1) / len(y)
    if vx + vy == 0:
        return nan
    with warnings.catch_warnings():
        # One constant group (every seed at a task's ceiling, as ppo-full on CartPole) is exact:
        # its variance is 0 and the other's carries the test. scipy still warns of "precision
        # loss" in that group's moments.
        warnings.filterwarnings("ignore", message="Precision loss", category=RuntimeWarning)
        result = stats.ttest_ind(x, y, equal_var=False)
    dof = (vx + vy) ** 2 / (vx**2 / (len(x) - 1) + vy**2 / (len(y) - 1))
    ci = result.confidence_interval(confidence)
    return WelchResult(
        float(result.statistic), float(dof), float(result.pvalue), float(ci.low), float(ci.high)
    )


@dataclass(frozen=True)
class TOSTResult:
    """Two one-sided Welch tests of ``|mean(a) - mean(b)| < margin`` (an equivalence test).

    Attributes:
        p_value: The larger of the two one-sided p-values (of ``H0: diff <= -margin`` and of
            ``H0: diff >= margin``); equivalence is shown at level α when it is at most α.
        ci_low: Lower end of Welch's ``1 - 2α`` interval of the difference (the interval the
            test at level α checks against ``±margin``).
        ci_high: Upper end of that interval.
    """

    p_value: float
    ci_low: float
    ci_high: float


def welch_tost(
    a: Sequence[float] | np.ndarray,
    b: Sequence[float] | np.ndarray,
    margin: float,
    alpha: float = 0.05,
) -> TOSTResult:
    """Schuirmann's two one-sided tests, each a Welch t test (scipy), of equivalence within
    ``±margin``.

    At level α, equivalence is shown exactly when Welch's ``1 - 2α`` interval of ``mean(a) -
    mean(b)`` lies inside ``(-margin, margin)``.

    Args:
        a: Values of the first group (NaNs are dropped).
        b: Values of the second group.
        margin: The equivalence margin, in the values' units (> 0).
        alpha: The level of each one-sided test.

    Returns:
        The TOST p-value and the ``1 - 2α`` interval (NaN when Welch's test is undefined).

    Examples:
        >>> same = welch_tost([1.0, 2.0, 3.0, 2.0], [2.0, 1.0, 3.0, 2.0], margin=2.0)
        >>> same.p_value < 0.05
        True
        >>> welch_tost([1.0, 2.0, 3.0, 2.0], [2.0, 1.0, 3.0, 2.0], margin=0.1).p_value > 0.05
        True
    """
    from scipy import stats

    if not margin > 0:
        raise ValueError(f"an equivalence margin must be positive, got {margin!r}")
    x = _clean(a)
    y = _clean(b)
    interval = welch_t_test(x, y, confidence=1 - 2 * alpha)
    if not math.isfinite(interval.p_value):
        return TOSTResult(math.nan, math.nan, math.nan)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Precision loss", category=RuntimeWarning)
        above = stats.ttest_ind(x + margin, y, equal_var=False, alternative="greater")
        below = stats.ttest_ind(x - margin, y, equal_var=False, alternative="less")
    p = max(float(above.pvalue), float(below.pvalue))
    return TOSTResult(p, interval.ci_low, interval.ci_high)


def bootstrap_mean_diff_ci(
    a: Sequence[float] | np.ndarray,
    b: Sequence[float] | np.ndarray,
    *,
    confidence: float = 0.95,
    n_resamples: int = 10_000,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap confidence interval of ``mean(a) - mean(b)``.

    Each group is resampled with replacement independently (the seeds of two agents are
    independent runs).

    Args:
        a: Values of the first group, shape ``(n_a,)`` (NaNs are dropped).
        b: Values of the second group, shape ``(n_b,)``.
        confidence: Coverage of the interval.
        n_resamples: Bootstrap resamples.
        seed: Seed of the resampling generator (the interval is reproducible).

    Returns:
        ``(low, high)``; ``(nan, nan)`` when a group is empty.
    """
    x = _clean(a)
    y = _clean(b)
    if len(x) == 0 or len(y) == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    mx = x[rng.integers(0, len(x), size=(n_resamples, len(x)))].mean(axis=1)
    my = y[rng.integers(0, len(y), size=(n_resamples, len(y)))].mean(axis=1)
    alpha = (1 - confidence) / 2
    low, high = np.quantile(mx - my, [alpha, 1 - alpha])
    return float(low), float(high)


def paired_bootstrap_mean_diff_ci(
    a: Sequence[float] | np.ndarray,
    b: Sequence[float] | np.ndarray,
    *,
    confidence: float = 0.95,
    n_resamples: int = 10_000,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap confidence interval of ``mean(a - b)`` over paired values.

    Two agents trained on the same seeds share their env and initialization streams, so the
    per-seed differences remove the seed's own luck from the comparison: the seeds (pairs) are
    resampled, not each group on its own.

    Args:
        a: Values of the first agent, shape ``(n,)``, in seed order.
        b: Values of the second agent on the same seeds, shape ``(n,)``.
        confidence: Coverage of the interval.
        n_resamples: Bootstrap resamples.
        seed: Seed of the resampling generator.

    Returns:
        ``(low, high)``; ``(nan, nan)`` with fewer than 2 pairs or a NaN in either.

    Raises:
        ValueError: ``a`` and ``b`` differ in length.
    """
    x = np.asarray(a, dtype=np.float64)
    y = np.asarray(b, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"paired values need equal lengths, got {x.shape} and {y.shape}")
    d = x - y
    if len(d) < 2 or not np.all(np.isfinite(d)):
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, len(d), size=(n_resamples, len(d)))].mean(axis=1)
    alpha = (1 - confidence) / 2
    low, high = np.quantile(means, [alpha, 1 - alpha])
    return float(low), float(high)


def final_returns_table(
    results: pd.DataFrame, agents: Sequence[str] | None = None, metric: str = "final_return"
) -> pd.DataFrame:
    """Per-agent statistics of the runs' final returns.

    Args:
        results: Output of [`load_run_results`][ermrl.analysis.load_run_results] (one row per run).
        agents: Order of the rows (default: order of appearance).
        metric: ``final_return`` (mean of the last training episodes) or ``eval_return``.

    Returns:
        Columns ``agent, n_seeds, mean, std, sem, ci95_low, ci95_high, median, min, max``
        (sample std; Student-t 95% interval of the mean).
    """
    columns = [
        "agent",
        "n_seeds",
        "mean",
        "std",
        "sem",
        "ci95_low",
        "ci95_high",
        "median",
        "min",
        "max",
    ]
    if results.empty or metric not in results:
        return pd.DataFrame(columns=columns)
    rows = []
    for agent in _agent_order(results, agents):
        values = _clean(results.loc[results["agent"] == agent, metric])
        if len(values) == 0:
            continue
        n = len(values)
        std = float(values.std(ddof=1)) if n > 1 else math.nan
        sem = std / math.sqrt(n) if n > 1 else math.nan
        half = sem * float(t_quantile(n - 1)) if n > 1 else math.nan
        mean = float(values.mean())
        rows.append(
            {
                "agent": agent,
                "n_seeds": n,
                "mean": mean,
                "std": std,
                "sem": sem,
                "ci95_low": mean - half,
                "ci95_high": mean + half,
                "median": float(np.median(values)),
                "min": float(values.min()),
                "max": float(values.max()),
            }
        )
    return pd.DataFrame(rows, columns=columns)


def compare_agents(
    results: pd.DataFrame,
    candidate: str = EVOLVED_AGENT,
    baselines: Sequence[str] | None = None,
    *,
    metric: str = "final_return",
    confidence: float = 0.95,
    n_resamples: int = 10_000,
    seed: int = 0,
) -> pd.DataFrame:
    """Test ``candidate`` against each baseline on the runs' final returns.

    Args:
        results: Output of [`load_run_results`][ermrl.analysis.load_run_results].
        candidate: The agent tested (default the evolved reservoir, ``res-ppo``).
        baselines: Agents it is compared with (missing ones are skipped; default: every other
            agent of `AGENT_KINDS`).
        metric: ``final_return`` or ``eval_return``.
        confidence: Coverage of the bootstrap interval.
        n_resamples: Bootstrap resamples.
        seed: Seed of the bootstrap.

    Returns:
        One row per baseline: ``candidate, baseline, n_candidate, n_baseline, mean_diff,
        boot_ci_low, boot_ci_high, welch_t, welch_dof, p_value, welch_ci_low, welch_ci_high,
        n_paired, paired_ci_low, paired_ci_high, few_seeds``, where ``mean_diff`` is
        ``mean(candidate) - mean(baseline)``, the Welch interval is Student's t with
        Welch-Satterthwaite degrees of freedom at the same coverage, the paired interval
        ([`paired_bootstrap_mean_diff_ci`][ermrl.analysis.paired_bootstrap_mean_diff_ci]) is over
        the seeds both agents ran (NaN when ``results`` has no ``seed`` column or fewer than 2
        shared seeds), and ``few_seeds`` flags a group of fewer than `FEW_SEEDS` runs.
    """
    if baselines is None:
        baselines = [a for a in AGENT_KINDS if a != candidate]
    columns = [
        "candidate",
        "baseline",
        "n_candidate",
        "n_baseline",
        "mean_diff",
        "boot_ci_low",
        "boot_ci_high",
        "welch_t",
        "welch_dof",
        "p_value",
        "welch_ci_low",
        "welch_ci_high",
        "n_paired",
        "paired_ci_low",
        "paired_ci_high",
        "few_seeds",
    ]
    if results.empty or metric not in results:
        return pd.DataFrame(columns=columns)
    by_seed = None
    if "seed" in results:
        by_seed = results.groupby(["agent", "seed"])[metric].mean().unstack("agent")
    a = _clean(results.loc[results["agent"] == candidate, metric])
    rows = []
    for baseline in baselines:
        b = _clean(results.loc[results["agent"] == baseline, metric])
        if len(a) == 0 or len(b) == 0:
            continue
        low, high = bootstrap_mean_diff_ci(
            a, b, confidence=confidence, n_resamples=n_resamples, seed=seed
        )
        test = welch_t_test(a, b, confidence=confidence)
        n_paired, paired = 0, (math.nan, math.nan)
        if by_seed is not None and baseline in by_seed and candidate in by_seed:
            pairs = by_seed[[candidate, baseline]].dropna()
            n_paired = len(pairs)
            paired = paired_bootstrap_mean_diff_ci(
                pairs[candidate].to_numpy(),
                pairs[baseline].to_numpy(),
                confidence=confidence,
                n_resamples=n_resamples,
                seed=seed,
            )
        rows.append(
            {
                "candidate": candidate,
                "baseline": baseline,
                "n_candidate": len(a),
                "n_baseline": len(b),
                "mean_diff": float(a.mean() - b.mean()),
                "boot_ci_low": low,
                "boot_ci_high": high,
                "welch_t": test.statistic,
                "welch_dof": test.dof,
                "p_value": test.p_value,
                "welch_ci_low": test.ci_low,
                "welch_ci_high": test.ci_high,
                "n_paired": n_paired,
                "paired_ci_low": paired[0],
                "paired_ci_high": paired[1],
                "few_seeds": min(len(a), len(b)) < FEW_SEEDS,
            }
        )
    return pd.DataFrame(rows, columns=columns)


# ---------------------------------------------------------------------------------------------
# Aggregates over a set of tasks (Agarwal et al., 2021, "Deep RL at the edge of the statistical
# precipice"; the method of the `rliable` package).
#
# rliable itself is not a dependency: its release (1.2.0) needs `arch`, whose newest release
# (7.2.0) fails to import beside the newest `statsmodels` (0.15.0) that pip resolves with it
# (``deprecate_kwarg()`` changed its signature), and it would add arch, statsmodels, seaborn and
# absl-py for two functions. IQM and the stratified percentile bootstrap below follow
# `rliable.metrics.aggregate_iqm` and `rliable.library.get_interval_estimates` (whose default
# interval is the percentile one), with numpy and scipy.


@dataclass(frozen=True)
class IQMResult:
    """The interquartile mean of scores over a set of tasks, with its stratified bootstrap CI.

    Attributes:
        iqm: Interquartile mean of all (task, run) scores pooled.
        ci_low: Lower end of the percentile interval of the stratified bootstrap.
        ci_high: Upper end of that interval.
        n_tasks: Tasks with at least one finite score.
        n_runs: Runs (seeds) of the task that has the fewest.
        few_seeds: ``n_runs < FEW_SEEDS``: the interval is rough.
    """

    iqm: float
    ci_low: float
    ci_high: float
    n_tasks: int
    n_runs: int
    few_seeds: bool


def iqm(values: Sequence[float] | np.ndarray) -> float:
    """Interquartile mean: the mean of the middle 50% of the values (NaNs dropped).

    The same as ``rliable.metrics.aggregate_iqm``: `scipy.stats.trim_mean` cutting 25% at
    each end of the flattened values.

    Args:
        values: Scores of any shape (typically ``(n_runs, n_tasks)``); they are pooled.

    Returns:
        The IQM (NaN with no finite value).

    Examples:
        >>> iqm([1.0, 2.0, 3.0, 4.0, 100.0, -100.0, 2.5, 3.5])
        2.75
    """
    from scipy import stats

    x = _clean(np.ravel(np.asarray(values, dtype=np.float64)))
    return float(stats.trim_mean(x, 0.25)) if len(x) else math.nan


def aggregate_iqm(
    task_scores: Mapping[str, Sequence[float] | np.ndarray]
    | Sequence[Sequence[float] | np.ndarray]
    | np.ndarray,
    *,
    confidence: float = 0.95,
    n_resamples: int = 10_000,
    seed: int = 0,
) -> IQMResult:
    """IQM of scores over tasks, with a stratified percentile bootstrap confidence interval.

    Each bootstrap resample draws, for every task on its own, as many runs as the task has, with
    replacement ("stratified": a resample never trades one task's runs for another's), pools
    them and takes the IQM. Scores of different tasks must be on one scale (normalized scores,
    e.g. ``(R - R_random) / (R_target - R_random)``).

    Args:
        task_scores: Per-task scores: ``{task: values of shape (n_runs,)}``, a sequence of such
            arrays (tasks may have different numbers of runs), or one array of shape
            ``(n_runs, n_tasks)`` as rliable takes it. NaNs are dropped; a task left with no
            value is left out.
        confidence: Coverage of the interval.
        n_resamples: Bootstrap resamples.
        seed: Seed of the resampling generator (the interval is reproducible).

    Returns:
        The point estimate, the interval, the numbers of tasks and runs, and the few-seeds flag;
        all NaN with no score at all.

    Examples:
        >>> result = aggregate_iqm({"a": [0.1, 0.2, 0.3], "b": [0.8, 0.9, 1.0]})
        >>> round(result.iqm, 3), result.n_tasks, result.few_seeds
        (0.55, 2, True)
    """
    from scipy import stats

    if isinstance(task_scores, Mapping):
        columns = [_clean(v) for v in task_scores.values()]
    elif isinstance(task_scores, np.ndarray) and task_scores.ndim == 2:
        columns = [_clean(task_scores[:, k]) for k in range(task_scores.shape[1])]
    else:
        columns = [_clean(v) for v in task_scores]
    columns = [c for c in columns if len(c)]
    if not columns:
        return IQMResult(math.nan, math.nan, math.nan, 0, 0, True)
    n_runs = min(len(c) for c in columns)
    rng = np.random.default_rng(seed)
    resampled = np.concatenate(
        [c[rng.integers(0, len(c), size=(n_resamples, len(c)))] for c in columns], axis=1
    )  # (n_resamples, total runs): each task's runs drawn from that task only
    estimates = stats.trim_mean(resampled, 0.25, axis=1)
    alpha = (1 - confidence) / 2
    low, high = np.quantile(estimates, [alpha, 1 - alpha])
    return IQMResult(
        iqm=iqm(np.concatenate(columns)),
        ci_low=float(low),
        ci_high=float(high),
        n_tasks=len(columns),
        n_runs=n_runs,
        few_seeds=n_runs < FEW_SEEDS,
    )


def _clean(values: Sequence[float] | np.ndarray | pd.Series) -> np.ndarray:
    arr = np.asarray(pd.to_numeric(pd.Series(values), errors="coerce"), dtype=float)
    return arr[np.isfinite(arr)]


def _agent_order(results: pd.DataFrame, agents: Sequence[str] | None) -> list[str]:
    present = list(dict.fromkeys(results["agent"]))
    if agents is None:
        return present
    return [a for a in agents if a in present] + [a for a in present if a not in agents]
