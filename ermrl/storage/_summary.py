"""What a study holds, as plain data: its trials per state, its budget, its best trial, its
workers, the code versions of its trials and its running trials (what ``ermrl study list`` and ``ermrl study show`` print)."""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Sequence
from typing import Any

from ermrl._code import code_versions
from ermrl.storage._heartbeat import last_seen

__all__ = [
    "STATES",
    "best_trial_or_none",
    "stored_budget",
    "study_summary",
    "trial_counts",
    "worker_budgets",
    "worker_label",
]

#: The trial states a summary counts, in the order it lists them.
STATES = ("COMPLETE", "PRUNED", "RUNNING", "WAITING", "FAIL")


def trial_counts(trials: Sequence[Any]) -> dict[str, int]:
    """The number of trials in each of `STATES` (0 for a state none is in)."""
    counter = Counter(t.state.name for t in trials)
    return {state: counter.get(state, 0) for state in STATES}


def stored_budget(study: Any) -> int | None:
    """The study's trial budget (``n_trials``) from its stored configuration (``None``: none)."""
    config = study.user_attrs.get("ermrl_config") or {}
    value = (config.get("search") or {}).get("n_trials")
    return int(value) if value is not None else None


def worker_budgets(trials: Sequence[Any]) -> dict[int, int]:
    """How many trials were claimed under each worker's ``--n-trials`` (largest first)."""
    counter = Counter(
        int(t.user_attrs["worker_n_trials"]) for t in trials if "worker_n_trials" in t.user_attrs
    )
    return dict(sorted(counter.items(), reverse=True))


def best_trial_or_none(study: Any) -> Any:
    """The study's best trial (``None``: no trial completed)."""
    try:
        return study.best_trial
    except ValueError:
        return None


def worker_label(trial: Any) -> str:
    """The worker that ran a trial: ``host:pid``, with its SLURM job (``job 12_3``) if any."""
    attrs = trial.user_attrs
    host = attrs.get("worker_hostname", "?")
    pid = attrs.get("worker_pid", "?")
    job = attrs.get("worker_slurm_array_job_id") or attrs.get("worker_slurm_job_id")
    task = attrs.get("worker_slurm_array_task_id")
    slurm = f" job {job}" + (f"_{task}" if task is not None else "") if job else ""
    return f"{host}:{pid}{slurm}"


def study_summary(study: Any) -> dict[str, Any]:
    """The study in plain data (the JSON of ``ermrl study show --json``): its kind, task,
    budget and each worker's, trials per state, retries, best trial, workers and running
    trials with the seconds since their heartbeat, and the code versions its trials ran
    (``code``: each `ermrl._code.code_identity` record with its number of ``trials``)."""
    trials = study.get_trials(deepcopy=False)
    best = best_trial_or_none(study)
    now = time.time()
    config = study.user_attrs.get("ermrl_config") or {}
    task = (config.get("problem") or {}).get("task") or {}
    budget_steps = ((config.get("problem") or {}).get("budget") or {}).get("training_steps")
    workers = Counter(worker_label(t) for t in trials if "worker_pid" in t.user_attrs)
    return {
        "study": study.study_name,
        "kind": study.user_attrs.get("ermrl_kind"),
        "env_id": task.get("env_id"),
        "observe": task.get("observe"),
        "training_steps": budget_steps,
        "budget": stored_budget(study),
        "worker_budgets": worker_budgets(trials),
        "counts": trial_counts(trials),
        "retried": sum(1 for t in trials if "retry_of" in t.user_attrs),
        "best": None
        if best is None
        else {
            "number": best.number,
            "value": best.value,
            "params": best.params,
            "worker": worker_label(best),
        },
        "workers": dict(workers.most_common()),
        "code": [
            {**record, "trials": n}
            for record, n in code_versions(t.user_attrs.get("ermrl_code") for t in trials)
        ],
        "running": [
            {
                "number": t.number,
                "worker": worker_label(t),
                "seconds_since_heartbeat": round(now - last_seen(t), 1),
            }
            for t in trials
            if t.state.name == "RUNNING"
        ],
    }
