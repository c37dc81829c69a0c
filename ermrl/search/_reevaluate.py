"""An honest winner: re-train the best candidates of a finished study on fresh seeds.

The best trial of an evolution is the maximum of noisy fitness values, so its fitness is biased
upwards (the winner's curse) and its rank among close candidates is partly luck. With
``--reevaluate-top K``, once a study's budget is spent, its ``K`` best trials and the unevolved
reference trial are trained again on seeds that neither evolution nor the test phase use
([`reevaluation_seeds`][ermrl.search.reevaluation_seeds]), optionally at another budget
(``--reevaluate-steps``, e.g. the test budget). The runs are trials of a sibling study named
``<study>.reeval`` in the same storage, so they get everything evolution trials get: any number of
workers share them, a dead worker's candidate is retried, SIGTERM and Ctrl-C lose nothing, and
re-running the command resumes.

The ranking is recorded in the evolution study's user attribute ``ermrl_reevaluation`` (plain
JSON), which the test phase reads ([`select_trial`][ermrl.search.select_trial]). A candidate whose
run fails on the fresh seeds (diverges, finishes no episode, or loses its worker more often than the
retries allow) is ranked last with its ``fail_reason``; only a run cut short by a signal (Ctrl-C,
SIGTERM) is queued again by the next call. The ranking records what it covered (``n_complete``,
``top_k``, ``top_trials``): once the study has grown and its best candidates are others
([`stale_ranking`][ermrl.search.stale_ranking]), the test phase no longer uses it, and the next
re-evaluation re-ranks, reusing the finished runs of the candidates still among the best.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np
import optuna
from optuna.trial import FrozenTrial, TrialState

from ermrl._progress import ProgressMode
from ermrl._text import plural
from ermrl.config import ConfigError, EvolveConfig, Problem
from ermrl.search._claim import cut_short
from ermrl.search._progress import CANDIDATE_ATTR
from ermrl.storage import study_lock

if TYPE_CHECKING:
    from ermrl.search._evolve import EvolutionSummary

__all__ = [
    "CANDIDATE_ATTR",
    "evolve_and_reevaluate",
    "REEVALUATION_ATTR",
    "reevaluation_config",
    "reevaluation_seeds",
    "reevaluation_study_name",
    "reevaluate_study",
    "select_trial",
    "stale_ranking",
    "top_candidates",
    "used_reevaluation_seeds",
]

REEVALUATION_ATTR = "ermrl_reevaluation"
# Re-evaluation seeds start this far above the largest evolution seed, clear of the test phase's
# default seeds (the five after the largest evolution seed).
SEED_OFFSET = 1000


def reevaluation_study_name(study_name: str) -> str:
    """Name of the sibling study that holds a study's re-evaluation runs."""
    return f"{study_name}.reeval"


def reevaluation_seeds(problem: Problem, n: int) -> tuple[int, ...]:
    """``n`` fresh seeds: ``max(evolution seeds) + 1000`` and up."""
    start = max(problem.seeds) + SEED_OFFSET
    return tuple(range(start, start + n))


def reevaluation_config(config: EvolveConfig, n_candidates: int) -> EvolveConfig:
    """The configuration of a study's re-evaluation: fresh seeds, its budget, queued trials only."""
    from ermrl.config import SearchConfig

    search = config.search
    budget = dataclasses.replace(
        config.problem.budget,
        training_steps=search.reevaluate_steps or config.problem.budget.training_steps,
        n_reports=0,
    )
    problem = dataclasses.replace(
        config.problem,
        seeds=reevaluation_seeds(config.problem, search.reevaluate_seeds),
        budget=budget,
    )
    # Every trial is a queued candidate; the sampler never proposes a point.
    quiet_search = SearchConfig(
        sampler="random", sampler_seed=0, n_trials=max(n_candidates, 1), reference_trial=False
    )
    return dataclasses.replace(config, problem=problem, search=quiet_search)


def _params_key(trial: FrozenTrial) -> tuple[tuple[str, float], ...]:
    return tuple(sorted(trial.params.items()))


def top_candidates(study: optuna.Study, k: int) -> list[FrozenTrial]:
    """The ``k`` best COMPLETE trials with distinct parameters, and the reference trial.

    Ties go to the earlier trial. The reference trial (user attribute ``reference``) is added
    when it is not among the ``k`` best, so the evolved winner always faces it.
    """
    complete = [
        t
        for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
        if t.value is not None and math.isfinite(t.value)
    ]
    complete.sort(key=lambda t: (-float(t.value), t.number))  # type: ignore[arg-type]
    out: list[FrozenTrial] = []
    seen: set[tuple[tuple[str, float], ...]] = set()
    for t in complete:
        if len(out) == k:
            break
        if _params_key(t) not in seen:
            seen.add(_params_key(t))
            out.append(t)
    for t in complete:
        if t.user_attrs.get("reference") and _params_key(t) not in seen:
            out.append(t)
            break
    return out


def _study_finished(study: optuna.Study, n_trials: int) -> tuple[bool, int]:
    """Whether the budget is spent and no trial runs or waits; and how many still run."""
    trials = study.get_trials(deepcopy=False)
    done = sum(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in trials)
    busy = sum(t.state in (TrialState.RUNNING, TrialState.WAITING) for t in trials)
    return done >= n_trials and busy == 0, busy


def _seed_values(trial: FrozenTrial) -> list[float]:
    """Per-seed values behind a trial's fitness (per-seed mean normalized return for multi-task)."""
    attrs = trial.user_attrs
    if "task_seed_returns" in attrs and "task_normalized" in attrs:
        return []  # multi-task: the fitness is a mean over tasks; per-task values are recorded
    key = "returns_eval" if attrs.get("fitness_mode") == "eval" else "returns_last"
    return [float(v) for v in attrs.get(key) or [] if v is not None]


def _candidate_runs(rstudy: optuna.Study) -> dict[int, list[FrozenTrial]]:
    """The re-evaluation runs of each candidate (evolution trial number), in trial order."""
    runs: dict[int, list[FrozenTrial]] = {}
    for t in rstudy.get_trials(deepcopy=False):
        number = t.user_attrs.get(CANDIDATE_ATTR)
        if number is not None:
            runs.setdefault(int(number), []).append(t)
    return runs


def _needs_run(runs: list[FrozenTrial]) -> bool:
    """Whether a candidate must be queued: it has no run yet, or its last one was interrupted
    by a signal or crashed and neither finished nor was queued again."""
    if not runs:
        return True
    if any(t.state in (TrialState.COMPLETE, TrialState.RUNNING, TrialState.WAITING) for t in runs):
        return False
    return cut_short(runs[-1])


def _n_complete(study: optuna.Study) -> int:
    return len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))


def record_reevaluation(
    study: optuna.Study,
    rstudy: optuna.Study,
    rconfig: EvolveConfig,
    candidates: list[int],
    top_k: int,
) -> dict[str, Any]:
    """Write the ranking of the re-evaluated candidates into ``study`` (``ermrl_reevaluation``).

    A candidate whose run failed for good (no COMPLETE run, none running or queued, and the last
    one not interrupted by a signal nor crashed) is ranked after every measured one, with ``failed: true``,
    ``fitness: null`` and its ``fail_reason``. The ranking is ``complete`` when every candidate
    is measured or failed; ``pending`` counts the others (running or queued in some worker).

    Args:
        study: The evolution study.
        rstudy: Its re-evaluation study.
        rconfig: The re-evaluation configuration (seeds, budget).
        candidates: Trial numbers of the current candidates
            ([`top_candidates`][ermrl.search.top_candidates]).
        top_k: The ``k`` they are the top of (``--reevaluate-top``).

    Returns:
        The recorded document.
    """
    evolved = {t.number: t for t in study.get_trials(deepcopy=False)}
    runs = _candidate_runs(rstudy)
    rows: list[dict[str, Any]] = []
    failed: list[dict[str, Any]] = []
    pending = 0
    for number in candidates:
        mine = runs.get(number, [])
        row = _candidate_row(number, evolved.get(number))
        done = next(
            (t for t in mine if t.state == TrialState.COMPLETE and t.value is not None), None
        )
        if done is not None:
            rows.append(_measured_row(row, done))
        elif _needs_run(mine) or any(
            t.state in (TrialState.RUNNING, TrialState.WAITING) for t in mine
        ):
            pending += 1
        else:
            failed.append(_failed_row(row, mine[-1]))
    rows.sort(key=lambda r: (-r["fitness"], r["trial"]))
    failed.sort(key=lambda r: r["trial"])
    doc = {
        "study": rstudy.study_name,
        "seeds": list(rconfig.problem.seeds),
        "training_steps": rconfig.problem.budget.training_steps,
        "fitness_mode": rconfig.problem.budget.fitness,
        "complete": pending == 0,
        "pending": pending,
        "best_trial": rows[0]["trial"] if rows else None,
        "candidates": rows + failed,
        # What the ranking covers, so that a study that grew since is seen (stale_ranking).
        "n_complete": _n_complete(study),
        "top_k": top_k,
        "top_trials": list(candidates),
    }
    study.set_user_attr(REEVALUATION_ATTR, doc)
    return doc


def _candidate_row(number: int, source: FrozenTrial | None) -> dict[str, Any]:
    """A candidate's row of the ranking before its runs are read: what evolution measured."""
    return {
        "trial": number,
        "reference": bool(source is not None and source.user_attrs.get("reference")),
        "params": dict(source.params) if source is not None else {},
        "fitness": None,
        "std": None,
        "seed_values": [],
        "evolution_fitness": None if source is None else source.value,
        "reevaluation_trial": None,
    }


def _measured_row(row: dict[str, Any], done: FrozenTrial) -> dict[str, Any]:
    """``row`` filled in from the candidate's COMPLETE re-evaluation run ``done``."""
    values = _seed_values(done)
    row.update(
        params=dict(done.params),
        fitness=float(done.value),  # type: ignore[arg-type]
        std=float(np.std(values, ddof=1)) if len(values) > 1 else None,
        seed_values=values,
        reevaluation_trial=done.number,
    )
    return row


def _failed_row(row: dict[str, Any], last: FrozenTrial) -> dict[str, Any]:
    """``row`` marked failed for good, with the reason of the candidate's ``last`` run."""
    reason = last.user_attrs.get("fail_reason") or last.state.name.lower()
    row.update(failed=True, fail_reason=str(reason), reevaluation_trial=last.number)
    return row


def evolve_and_reevaluate(
    config: EvolveConfig,
    study: optuna.Study,
    storage_url: str | None,
    *,
    quiet: bool = False,
    stream: TextIO | None = None,
    evaluator_factory: Callable[[EvolveConfig], Any] | None = None,
    study_kwargs: dict[str, Any] | None = None,
    wait_for_running: bool = True,
    progress: ProgressMode = "none",
    **run_kwargs: Any,
) -> EvolutionSummary:
    """Run this worker's trials of ``study``, then its re-evaluation once the budget is spent.

    What ``ermrl evolve`` (and ``ermrl evolve-generalization``) run:
    [`run_evolution`][ermrl.search.run_evolution], then
    [`reevaluate_study`][ermrl.search.reevaluate_study] when ``config.search.reevaluate_top`` is
    above 0.

    Args:
        config: The study's configuration.
        study: The created or resumed study
            ([`create_or_resume_study`][ermrl.search.create_or_resume_study]).
        storage_url: Its storage, where the re-evaluation study lives (``None``: no
            re-evaluation).
        quiet: No progress lines.
        stream: Where progress lines go (default ``sys.stdout``).
        evaluator_factory: Builds the fitness of the re-evaluation config (multi-task runs).
        study_kwargs: ``heartbeat_interval``, ``grace_period`` and ``max_retry`` of the
            re-evaluation study.
        wait_for_running: Wait for other workers' trials (and re-evaluation runs) at the end.
        progress: ``"bar"``, ``"lines"`` or ``"none"`` inside each trial or run.
        **run_kwargs: Passed on to [`run_evolution`][ermrl.search.run_evolution] (``evaluate``,
            ``callbacks``, ``tensorboard``, ...).

    Returns:
        What this worker did in the evolution.

    Raises:
        Interrupted: SIGTERM arrived (the running trial was closed).
        KeyboardInterrupt: Ctrl-C (the running trial was closed).
    """
    from ermrl.search._evolve import run_evolution

    summary = run_evolution(
        config,
        study,
        quiet=quiet,
        stream=stream,
        wait_for_running=wait_for_running,
        progress=progress,
        **run_kwargs,
    )
    if storage_url is not None and config.search.reevaluate_top > 0:
        reevaluate_study(
            config,
            study,
            storage_url,
            evaluator_factory=evaluator_factory,
            quiet=quiet,
            stream=stream,
            wait_for_running=wait_for_running,
            progress=progress,
            **(study_kwargs or {}),
        )
    return summary


def reevaluate_study(
    config: EvolveConfig,
    study: optuna.Study,
    storage_url: str,
    *,
    evaluator_factory: Callable[[EvolveConfig], Any] | None = None,
    quiet: bool = False,
    stream: TextIO | None = None,
    wait_for_running: bool = True,
    heartbeat_interval: int | None = None,
    grace_period: int | None = None,
    max_retry: int | None = None,
    progress: ProgressMode = "none",
) -> dict[str, Any] | None:
    """Re-train the study's best candidates on fresh seeds and record the ranking.

    Call it after [`run_evolution`][ermrl.search.run_evolution] returned; it does nothing until the
    study's budget is spent with no trial running. Several workers may call it at once: they
    share the candidates through the sibling study.

    Args:
        config: The evolution's configuration (``search.reevaluate_*`` set the re-evaluation).
        study: The evolution study.
        storage_url: Its storage (the sibling study lives there too).
        evaluator_factory: Builds the fitness of the re-evaluation config (the multi-task
            pipeline passes [`generalization_evaluator`][ermrl.search.generalization_evaluator]);
            ``None``: the single-task fitness.
        quiet: No progress lines.
        stream: Where progress lines go.
        wait_for_running: Wait for other workers' re-evaluation runs at the end.
        heartbeat_interval: Heartbeats of the re-evaluation trials (as for evolution).
        grace_period: Seconds without heartbeat before a run is failed and retried.
        max_retry: Retries of a run whose worker died.
        progress: Lines inside each run, as in [`run_evolution`][ermrl.search.run_evolution].

    Returns:
        The recorded ranking (see `record_reevaluation`), or ``None`` when re-evaluation
        is off, the study is not finished, or it has no COMPLETE trial.
    """
    from ermrl.search._evolve import run_evolution

    out = stream or sys.stdout

    def say(line: str) -> None:
        if not quiet:
            print(line, file=out, flush=True)

    k = config.search.reevaluate_top
    if k == 0:
        return None
    candidates = _candidates_to_reevaluate(study, config.search.n_trials, k, say)
    if not candidates:
        return None
    numbers = [t.number for t in candidates]
    rconfig, rstudy = _queue_candidates(
        config, study, storage_url, candidates,
        heartbeat_interval=heartbeat_interval, grace_period=grace_period, max_retry=max_retry,
    )  # fmt: skip
    seeds = rconfig.problem.seeds
    say(
        f"re-evaluating {len(candidates)} candidates (trials {', '.join(map(str, numbers))}) on "
        f"seeds {seeds[0]}..{seeds[-1]}, {rconfig.problem.budget.training_steps} steps each"
    )
    evaluate = evaluator_factory(rconfig) if evaluator_factory is not None else None
    run_evolution(
        rconfig, rstudy, quiet=quiet, stream=stream, evaluate=evaluate,
        wait_for_running=wait_for_running, queued_only=True, progress=progress,
    )  # fmt: skip
    with study_lock(study):
        doc = record_reevaluation(study, rstudy, rconfig, numbers, k)
    _say_ranking(doc, say)
    return doc


def _candidates_to_reevaluate(
    study: optuna.Study, n_trials: int, k: int, say: Callable[[str], None]
) -> list[FrozenTrial]:
    """The study's ``k`` best trials once it is finished; none (and why, said) before."""
    finished, busy = _study_finished(study, n_trials)
    if not finished:
        say(
            f"re-evaluation waits for the study to finish ({busy} trial(s) running or queued); "
            "run this command again when they are done"
        )
        return []
    candidates = top_candidates(study, k)
    if not candidates:
        say("re-evaluation skipped: the study has no COMPLETE trial")
    return candidates


def _queue_candidates(
    config: EvolveConfig,
    study: optuna.Study,
    storage_url: str,
    candidates: list[FrozenTrial],
    *,
    heartbeat_interval: int | None,
    grace_period: int | None,
    max_retry: int | None,
) -> tuple[EvolveConfig, optuna.Study]:
    """Open the re-evaluation study and queue the candidates that need a run.

    A candidate is queued once; again only when a signal cut its last run short. Finished runs
    of candidates still among the best are reused (a study that grew is re-ranked).

    Args:
        config: The evolution's configuration.
        study: The evolution study.
        storage_url: Its storage (the sibling study lives there too).
        candidates: The trials to re-evaluate ([`top_candidates`][ermrl.search.top_candidates]).
        heartbeat_interval: Heartbeats of the re-evaluation trials.
        grace_period: Seconds without heartbeat before a run is failed and retried.
        max_retry: Retries of a run whose worker died.

    Returns:
        The re-evaluation configuration (its ``n_trials``: every candidate it has run or will
        run) and the re-evaluation study.
    """
    from ermrl.search._study import create_or_resume_study

    numbers = [t.number for t in candidates]
    rconfig = reevaluation_config(config, len(candidates))
    name = reevaluation_study_name(study.study_name)
    rstudy = create_or_resume_study(
        rconfig,
        storage_url,
        name,
        kind="reevaluation",
        heartbeat_interval=heartbeat_interval,
        grace_period=grace_period,
        max_retry=max_retry,
    )
    with study_lock(rstudy):
        runs = _candidate_runs(rstudy)
        for t in candidates:
            if _needs_run(runs.get(t.number, [])):
                rstudy.enqueue_trial(dict(t.params), user_attrs={CANDIDATE_ATTR: t.number})
        n_total = len(set(runs) | set(numbers))
    rconfig = dataclasses.replace(
        rconfig, search=dataclasses.replace(rconfig.search, n_trials=n_total)
    )
    return rconfig, rstudy


def _say_ranking(doc: dict[str, Any], say: Callable[[str], None]) -> None:
    """Print a recorded ranking (`record_reevaluation`) and whether it is complete."""
    from ermrl.search._progress import format_params

    if doc["candidates"]:
        say("re-evaluated ranking (mean over fresh seeds; evolution fitness in brackets):")
        for row in doc["candidates"]:
            tag = " (reference)" if row["reference"] else ""
            evo = row["evolution_fitness"]
            if row.get("failed"):
                value = f"FAILED ({row['fail_reason']}), ranked last"
            else:
                std = "" if row["std"] is None else f" ± {row['std']:.3g}"
                value = f"{row['fitness']:.4g}{std}"
            say(
                f"  trial {row['trial']}{tag}: {value} "
                f"[{'-' if evo is None else f'{evo:.4g}'}] {format_params(row['params'])}"
            )
    if not doc["complete"]:
        say(
            f"re-evaluation incomplete: {doc['pending']} candidate(s) still running or queued in "
            "other workers; the last of them to finish records the ranking (or run this command "
            "again once they are done)"
        )


def stale_ranking(study: optuna.Study) -> str | None:
    """Why the stored ranking no longer covers the study's best candidates, or ``None``.

    The ranking is stale when the study's ``top_k`` best trials
    ([`top_candidates`][ermrl.search.top_candidates]) are no longer the ones it ranked: trials were
    added since (a larger ``--n-trials``, evolution resumed) and some beat a ranked candidate. A
    ranking recorded before ermrl kept ``top_k`` is compared with the top ``K`` and ``K - 1`` (the
    reference may be one of them).

    Args:
        study: An evolution study.

    Returns:
        ``None`` when there is no ranking or it is current; else a phrase saying what it covered
        and what the study's best candidates are now.
    """
    doc = study.user_attrs.get(REEVALUATION_ATTR)
    if not isinstance(doc, dict):
        return None
    recorded = doc.get("top_trials")
    top_k = doc.get("top_k")
    if recorded is None or top_k is None:  # recorded before ermrl kept its coverage
        recorded = [int(r["trial"]) for r in doc.get("candidates") or []]
        ks = [len(recorded), len(recorded) - 1]
    else:
        ks = [int(top_k)]
    now: list[int] = []
    for k in ks:
        if k < 1:
            continue
        now = [t.number for t in top_candidates(study, k)]
        if set(now) == set(recorded):
            return None
    covered = doc.get("n_complete")
    of = "" if covered is None else f" of {covered} complete trials"
    return (
        f"it ranked trials {', '.join(map(str, recorded))}{of}; the study now has "
        f"{_n_complete(study)} complete trials and its best candidates are trials "
        f"{', '.join(map(str, now))}"
    )


def used_reevaluation_seeds(study: optuna.Study) -> tuple[int, ...]:
    """The seeds a study's re-evaluation trained on: those of the stored ranking and of the
    sibling study ``<study>.reeval`` (empty when there is neither)."""
    from ermrl.search._study import STUDY_CONFIG_ATTR

    seeds: set[int] = set()
    doc = study.user_attrs.get(REEVALUATION_ATTR)
    if isinstance(doc, dict):
        seeds.update(int(s) for s in doc.get("seeds") or [])
    storage = study._storage
    try:
        study_id = storage.get_study_id_from_name(reevaluation_study_name(study.study_name))
    except KeyError:
        return tuple(sorted(seeds))
    stored = storage.get_study_user_attrs(study_id).get(STUDY_CONFIG_ATTR)
    if isinstance(stored, dict):
        seeds.update(int(s) for s in (stored.get("problem") or {}).get("seeds") or [])
    return tuple(sorted(seeds))


def _no_complete_trial(study: optuna.Study, trials: list[FrozenTrial]) -> str:
    """Why a study has nothing to test, and what to run: its trials by state, then the command
    that evolves it (the one it stored, else ``ermrl evolve``)."""
    counts = {state: sum(t.state == state for t in trials) for state in TrialState}
    words = {TrialState.FAIL: "failed"}
    seen = ", ".join(
        f"{n} {words.get(state, state.name.lower())}" for state, n in counts.items() if n
    )
    command = study.user_attrs.get("ermrl_command")
    evolving = isinstance(command, str) and "evolve" in command  # not a script's `-c`
    again = f"`{command}`" if evolving else "ermrl evolve"
    return (
        f"study {study.study_name!r} has no COMPLETE trial yet "
        f"({seen or 'no trial at all'}): run the evolution until a trial finishes ({again}; "
        "rerunning it resumes the study), then test; `ermrl study show` lists its trials"
    )


def select_trial(study: optuna.Study, trial_number: int | None = None) -> tuple[FrozenTrial, str]:
    """The trial the test phase should use, and how it was chosen.

    Without ``trial_number``: the best of a complete and current re-evaluated ranking; else the
    best evolution fitness, skipping the candidates that failed their re-evaluation. A stale
    ranking ([`stale_ranking`][ermrl.search.stale_ranking]) is not used, and the phrase says why.

    Args:
        study: An evolution study.
        trial_number: An explicit trial (wins over any ranking).

    Returns:
        The trial and a phrase saying how it was selected: ``"trial N (--trial)"``,
        ``"re-evaluated best of K candidates ..."`` or ``"best evolution fitness (...)"``.

    Raises:
        ConfigError: no such trial, no COMPLETE trial, or every re-evaluated candidate failed.
    """
    trials = {t.number: t for t in study.get_trials(deepcopy=False)}
    if trial_number is not None:
        if trial_number not in trials:
            raise ConfigError(f"study {study.study_name!r} has no trial {trial_number}")
        return trials[trial_number], f"trial {trial_number} (--trial)"
    doc = study.user_attrs.get(REEVALUATION_ATTR)
    stale = stale_ranking(study)
    rows = (doc.get("candidates") or []) if isinstance(doc, dict) else []
    failed = {int(r["trial"]) for r in rows if r.get("failed")}
    if isinstance(doc, dict) and doc.get("complete") and stale is None:
        if doc.get("best_trial") in trials:
            seeds = doc["seeds"]
            how = (
                f"re-evaluated best of {len(rows)} candidates "
                f"({plural(len(seeds), 'fresh seed')} x {doc['training_steps']} steps"
                + (f"; {len(failed)} failed, ranked last" if failed else "")
                + ")"
            )
            return trials[doc["best_trial"]], how
        if rows and len(failed) == len(rows):
            raise ConfigError(
                f"every re-evaluated candidate of study {study.study_name!r} failed on the fresh "
                f"seeds (trials {', '.join(map(str, sorted(failed)))}); pass --trial N to test "
                "one anyway"
            )
    complete = [
        t
        for t in trials.values()
        if t.state == TrialState.COMPLETE
        and t.value is not None
        and math.isfinite(t.value)
        and t.number not in failed
    ]
    if not complete:
        raise ConfigError(_no_complete_trial(study, list(trials.values())))
    best = min(complete, key=lambda t: (-float(t.value), t.number))  # type: ignore[arg-type]
    if not isinstance(doc, dict):
        why = "no re-evaluation; evolve with --reevaluate-top K for an unbiased pick"
    elif stale is not None:
        why = f"re-evaluated ranking stale: {stale}; run the evolve command again to re-rank"
    else:
        why = "re-evaluation incomplete"
    if failed:
        why += f"; trials {', '.join(map(str, sorted(failed)))} skipped: failed re-evaluation"
    return best, f"best evolution fitness ({why})"
