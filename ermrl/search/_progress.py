"""Progress lines of a worker."""

from __future__ import annotations

import optuna
from optuna.trial import TrialState

from ermrl._progress import duration
from ermrl.search._objective import FitnessResult

# The user attribute naming the evolution trial a re-evaluation run re-trains (kept here, the
# lower module, and re-exported by ermrl.search._reevaluate).
CANDIDATE_ATTR = "candidate"

__all__ = ["best_trial", "fmt_duration", "format_params", "trial_line"]


def format_params(params: dict[str, float]) -> str:
    return " ".join(f"{k}={v:.3g}" for k, v in params.items())


fmt_duration = duration  # "1h02m", "3m05s", "?": the one formatter of ermrl._progress


def best_trial(study: optuna.Study) -> tuple[float | None, int | None, dict[str, float] | None]:
    try:
        best = study.best_trial
    except ValueError:
        return None, None, None
    return best.value, best.number, best.params


def trial_line(
    study: optuna.Study,
    number: int,
    params: dict[str, float],
    state: TrialState,
    result: FitnessResult | None,
    note: str,
    elapsed: float,
    *,
    counted: int,
    n_trials: int,
    retry_of: int | None,
    eta: float,
    candidate: int | None = None,
) -> str:
    """The progress line of a finished trial: its outcome, the study's best and the ETA.

    A re-evaluation run (a trial of the sibling ``<study>.reeval`` study) is named by the
    evolution trial it re-trains (``[candidate #74 | 1/4]``), and so is the best so far; its own
    number in the sibling study would read as another evolution trial.

    Args:
        study: The study (for its best trial so far).
        number: The trial's number.
        params: Its parameters.
        state: How it ended.
        result: Its fitness (``None`` unless it completed).
        note: Why it was pruned or failed.
        elapsed: Its wall-clock seconds.
        counted: Trials the study counts towards the budget.
        n_trials: The budget.
        retry_of: The trial it retries, if any.
        eta: Seconds left, estimated.
        candidate: The evolution trial a re-evaluation run re-trains (``None``: an evolution
            trial).
    """
    try:
        top = study.best_trial  # read once: a storage round trip
    except ValueError:
        top = None
    name = f"trial {number}" if candidate is None else f"candidate #{candidate}"
    if top is None:
        best_value, best_number = None, None
    else:
        best_value = top.value
        best_number = top.number if candidate is None else top.user_attrs.get(CANDIDATE_ATTR)
    if state == TrialState.COMPLETE and result is not None:
        outcome = f"fitness {result.fitness:.4g}"
        speed = f"{result.steps_per_second:.0f} steps/s"
    else:
        outcome = f"{state.name} ({note})"
        speed = f"{elapsed:.0f}s"
    best = "-" if best_value is None else f"{best_value:.4g} (#{best_number})"
    retried = "" if retry_of is None else f" | retry of #{retry_of}"
    return (
        f"[{name} | {counted}/{n_trials}{retried}] {format_params(params)} | "
        f"{outcome} | best {best} | {speed} | ETA {fmt_duration(eta)}"
    )
