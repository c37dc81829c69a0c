"""Creating or resuming a study: its sampler, its stored configuration and the check that a
resumed study has the same fitness landscape."""

from __future__ import annotations

import sys
import warnings
import weakref
from collections.abc import Sequence
from typing import Any

import optuna
from optuna.distributions import BaseDistribution, FloatDistribution, IntDistribution
from optuna.trial import FrozenTrial

from ermrl._code import code_identity, code_versions, describe_code, same_code
from ermrl.config import ConfigError, EvolveConfig, SearchConfig, SearchSpace, to_dict
from ermrl.search._pruning import make_pruner
from ermrl.storage import (
    DEFAULT_GRACE_PERIOD,
    DEFAULT_HEARTBEAT_INTERVAL,
    DEFAULT_MAX_RETRY,
    check_study_name,
    open_storage,
    storage_lock,
)

__all__ = [
    "CodeVersionWarning",
    "REFERENCE_ATTR",
    "STUDY_COMMAND_ATTR",
    "STUDY_CONFIG_ATTR",
    "STUDY_KIND_ATTR",
    "check_stored_env_ids",
    "cma_start",
    "config_diffs",
    "create_or_resume_study",
    "enqueue_reference",
    "make_study_sampler",
    "refuse_other_config",
    "resume_conflicts",
    "sample_params",
    "search_distributions",
    "study_config",
    "warn_other_code",
]

STUDY_CONFIG_ATTR = "ermrl_config"
STUDY_COMMAND_ATTR = "ermrl_command"
STUDY_KIND_ATTR = "ermrl_kind"
#: The code that created the study ([`code_identity`][ermrl._code.code_identity]); each trial records the
#: code that trained it under the same name.
CODE_ATTR = "ermrl_code"
# Parts of the configuration that define the fitness landscape: a resumed study must match them.
_MUST_MATCH = ("problem", "space")


def _is_integer(r: Any) -> bool:
    """Whether a range is an integer gene (``integer`` set, as on an ``IntRange``)."""
    return bool(getattr(r, "integer", False))


def search_distributions(space: SearchSpace) -> dict[str, BaseDistribution]:
    """The fixed search space as Optuna distributions (what
    [`sample_params`][ermrl.search.sample_params] asks): an ``IntDistribution`` for an integer gene
    (CMA-ES then rounds inside the search, with margin), a ``FloatDistribution`` otherwise."""
    return {
        name: IntDistribution(int(r.low), int(r.high))
        if _is_integer(r)
        else FloatDistribution(r.low, r.high, log=r.log)
        for name, r in space.ranges().items()
    }


def cma_start(search: SearchConfig, space: SearchSpace) -> dict[str, float]:
    """The first CMA-ES mean: the reference reservoir (clipped into the box) or the box centre."""
    if search.start == "center":
        return space.center_params()
    ranges = space.ranges()
    return {
        name: min(max(value, ranges[name].low), ranges[name].high)
        for name, value in space.reference_params().items()
    }


def make_study_sampler(
    search: SearchConfig, space: SearchSpace | None = None
) -> optuna.samplers.BaseSampler:
    """The study's sampler; with ``space``, CMA-ES knows the space before any trial completes."""
    from ermrl.search._samplers import make_sampler

    fixed = search.sampler == "cmaes" and space is not None
    return make_sampler(
        search.sampler,  # type: ignore[arg-type]
        seed=search.sampler_seed,
        restart=search.restart,  # type: ignore[arg-type]
        popsize=search.popsize,
        consider_pruned_trials=search.pruner != "none",
        search_space=search_distributions(space) if fixed else None,  # type: ignore[arg-type]
        x0=cma_start(search, space) if fixed else None,  # type: ignore[arg-type]
    )


REFERENCE_ATTR = "reference"


def enqueue_reference(study: optuna.Study, space: SearchSpace) -> bool:
    """Queue the unevolved reference reservoir as a trial (user attribute ``reference``).

    Returns:
        ``False`` when the reference lies outside the search space (nothing is queued).
    """
    params = space.reference_params()
    if not space.contains(params):
        return False
    study.enqueue_trial(params, user_attrs={REFERENCE_ATTR: True}, skip_if_exists=True)
    return True


def sample_params(trial: optuna.Trial, space: SearchSpace) -> dict[str, float]:
    """Ask a trial for every evolved hyperparameter of the space (fixed order and ranges; an
    integer gene with ``suggest_int``)."""
    return {
        name: trial.suggest_int(name, int(r.low), int(r.high))
        if _is_integer(r)
        else trial.suggest_float(name, r.low, r.high, log=r.log)
        for name, r in space.ranges().items()
    }


def study_config(study: optuna.Study) -> EvolveConfig:
    """The configuration an ermrl study was created with.

    Its env ids must be registered ones
    ([`check_stored_env_ids`][ermrl.search.check_stored_env_ids]): the stored configuration is data
    that an edited database or an imported snapshot may carry, and a ``module:Env`` id in it would
    make gymnasium import that module.

    Raises:
        ConfigError: the study was not created by ``ermrl evolve``, or its configuration names
            an env id that is not registered.
    """
    data = study.user_attrs.get(STUDY_CONFIG_ATTR)
    if data is None:
        raise ConfigError(f"study {study.study_name!r} has no ermrl configuration")
    check_stored_env_ids(data, f"study {study.study_name!r} (its stored configuration)")
    return EvolveConfig.from_dict(data)


def check_stored_env_ids(data: Any, source: str) -> None:
    """Check every ``env_id`` in a stored configuration against gymnasium's registry.

    Nothing is imported: a ``module:Env`` id is refused unless that module is imported already
    (see [`ermrl.envs.check_registered_env_id`][ermrl.envs.check_registered_env_id]). The whole
    document is walked, so an env id in any part of it (a task, a generalization task set) is
    checked.

    Args:
        data: The decoded configuration (JSON-like).
        source: What it was read from, named in the error.

    Raises:
        ConfigError: one line naming ``source`` and the id.
    """
    from ermrl.envs import UnknownEnvError, check_registered_env_id

    pending, seen = [data], 0
    while pending:
        node = pending.pop()
        seen += 1
        if seen > 100_000:
            raise ConfigError(f"{source}: the configuration is too large to be ermrl's")
        if isinstance(node, dict):
            for key, value in node.items():
                if key == "env_id":
                    try:
                        check_registered_env_id(value, source)
                    except UnknownEnvError as err:
                        raise ConfigError(str(err)) from None
                else:
                    pending.append(value)
        elif isinstance(node, list):
            pending.extend(node)


def config_diffs(new: Any, stored: Any, path: str) -> list[str]:
    """Differences between two JSON-like values, recursing into dicts and equal-length lists.

    Args:
        new: The value now (e.g. ``to_dict(config)[key]``).
        stored: The value stored in the study.
        path: The dotted name of the value (``problem``, ``generalization``, ...).

    Returns:
        One ``"<path>: <stored> in the study, <new> now"`` line per differing leaf.
    """
    if isinstance(new, dict) and isinstance(stored, dict):
        out = []
        for key in sorted(set(new) | set(stored)):
            out += config_diffs(new.get(key), stored.get(key), f"{path}.{key}")
        return out
    if isinstance(new, list) and isinstance(stored, list) and len(new) == len(stored):
        return [
            d
            for i, (x, y) in enumerate(zip(new, stored))
            for d in config_diffs(x, y, f"{path}[{i}]")
        ]
    return [] if new == stored else [f"{path}: {stored!r} in the study, {new!r} now"]


# Provenance only (file paths of the score and PPO tables): their values are compared per task.
_PROVENANCE = ("scores", "hyperparams")


def resume_conflicts(config: EvolveConfig, stored: dict[str, Any]) -> list[str]:
    """What keeps ``config`` from resuming a study stored with configuration ``stored``.

    The problem and the search space must match; for a multi-task study, also the task set,
    PPO settings per task, reference returns, target column and ``--ppo``/``--n-envs``
    options (not the paths of the score and PPO tables).

    Args:
        config: The configuration now.
        stored: The study's ``ermrl_config`` attribute.

    Returns:
        One line per difference (`config_diffs`); empty when the study can resume.
    """
    new = to_dict(config)
    diffs = [d for key in _MUST_MATCH for d in config_diffs(new[key], stored.get(key), key)]
    if config.generalization is not None and stored.get("generalization") is not None:
        now = {k: v for k, v in new["generalization"].items() if k not in _PROVENANCE}
        old = {k: v for k, v in stored["generalization"].items() if k not in _PROVENANCE}
        diffs += config_diffs(now, old, "generalization")
    return diffs


def refuse_other_config(study_name: str, diffs: list[str]) -> None:
    """Refuse to resume a study whose stored configuration differs (nothing if ``diffs`` is empty).

    Args:
        study_name: The study's name.
        diffs: From `config_diffs`; the first four are named in the message.

    Raises:
        ConfigError: ``diffs`` is not empty.
    """
    if diffs:
        raise ConfigError(
            f"study {study_name!r} already exists with another configuration ("
            + "; ".join(diffs[:4])
            + (" ..." if len(diffs) > 4 else "")
            + "); pick another --study-name"
        )


METRIC_NAME = "fitness"
"""The objective's name (``study.metric_names``): ``study.trials_dataframe()`` calls its column
``value_fitness``. What it measures is `metric_description`, in `STUDY_METRIC_ATTR`."""
STUDY_METRIC_ATTR = "ermrl_metric"


def metric_description(config: EvolveConfig) -> str:
    """What a study's objective value is, in words.

    Stored as the study's ``ermrl_metric`` user attribute, which optuna-dashboard shows among
    the study's user attributes (the objective itself is named `METRIC_NAME`, short, as
    it names a column of ``study.trials_dataframe()``).

    Returns:
        e.g. ``"fitness: mean return of the last 10 training episodes, mean over seeds"``.
    """
    budget = config.problem.budget
    measure = (
        f"mean return of the last {budget.n_last_episodes} training episodes"
        if budget.fitness == "last"
        else f"mean return of {budget.n_eval_episodes} deterministic episodes after training"
    )
    what = f"{METRIC_NAME}: {measure}, mean over seeds"
    if config.generalization is not None:
        what += "; normalized per task ((R - random) / (target - random)), mean over tasks"
    return what


def name_metric(study: optuna.Study, config: EvolveConfig) -> None:
    """Name the study's objective `METRIC_NAME` and store `metric_description` as
    the ``ermrl_metric`` user attribute; optuna-dashboard shows both."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        study.set_metric_names([METRIC_NAME])
    study.set_user_attr(STUDY_METRIC_ATTR, metric_description(config))


def create_or_resume_study(
    config: EvolveConfig | None,
    storage_url: str,
    study_name: str,
    *,
    command: str | None = None,
    kind: str = "evolve",
    heartbeat_interval: int | None = DEFAULT_HEARTBEAT_INTERVAL,
    grace_period: int | None = DEFAULT_GRACE_PERIOD,
    max_retry: int | None = DEFAULT_MAX_RETRY,
) -> optuna.Study:
    """Create the study, or load it when it exists with the same problem and search space.

    Safe with many workers starting at once: the schema and the study are created under the
    storage's inter-process lock, and the first worker stores the configuration.

    Args:
        config: The run's configuration (``None``: create or load a bare study; the first
            worker that brings a configuration stores it).
        storage_url: Where the study lives (see
            [`ermrl.storage.open_storage`][ermrl.storage.open_storage]).
        study_name: The study's name.
        command: Launch command stored with the configuration (default: ``sys.argv``).
        kind: ``"evolve"`` or ``"generalization"``, stored as the ``ermrl_kind`` attribute.
        heartbeat_interval: Seconds between heartbeats of running trials (``None``: off).
        grace_period: Seconds without heartbeat before a running trial is failed and retried.
        max_retry: Retries of a trial whose worker died or was preempted (0: none; ``None``:
            no limit).

    Returns:
        The study.

    Raises:
        ConfigError: a study of that name exists with another configuration.
        StudyNameError: ermrl does not create a study of that name (a path separator,
            ``..``, a control character, blank or too long).
        StorageError: the storage cannot be opened.
    """
    check_study_name(study_name)
    storage = open_storage(
        storage_url,
        heartbeat_interval=heartbeat_interval,
        grace_period=grace_period,
        max_retry=max_retry,
    )
    search = config.search if config is not None else SearchConfig()
    sampler = make_study_sampler(search, config.space if config is not None else None)
    pruner = make_pruner(search.pruner)
    with storage_lock(storage_url, study_name):
        study = optuna.create_study(
            study_name=study_name,
            storage=storage,
            sampler=sampler,
            pruner=pruner,
            direction="maximize",
            load_if_exists=True,
        )
        if config is None:
            return study
        new = to_dict(config)
        stored = study.user_attrs.get(STUDY_CONFIG_ATTR)
        if stored is None:
            name_metric(study, config)
            study.set_user_attr(STUDY_CONFIG_ATTR, new)
            study.set_user_attr(STUDY_KIND_ATTR, kind)
            study.set_user_attr(STUDY_COMMAND_ATTR, command or " ".join(sys.argv))
            from ermrl import __version__

            study.set_user_attr("ermrl_version", __version__)
            study.set_user_attr(CODE_ATTR, code_identity())
            if config.search.reference_trial and not enqueue_reference(study, config.space):
                warnings.warn(
                    "the reference reservoir (sr = lr = input_scaling = 1) lies outside the "
                    "search space: it does not take part in this study",
                    stacklevel=2,
                )
            return study
    refuse_other_config(study_name, resume_conflicts(config, stored))
    warn_other_code(study)
    return study


class CodeVersionWarning(UserWarning):
    """Workers of different code share a study (see `warn_other_code`)."""


# The code versions each study object was warned about already (once per process each).
_WARNED: weakref.WeakKeyDictionary[optuna.Study, set[str]] = weakref.WeakKeyDictionary()


def warn_other_code(study: optuna.Study, trials: Sequence[FrozenTrial] | None = None) -> None:
    """Say in one line, once per other code version, when this worker's code is not the code
    that created the study or that ran some of ``trials``.

    Every worker warns, the older as well as the newer: a worker checks the study's creator
    when it joins and the trials at every claim. The study goes on: upgrading a cluster
    mid-study must not stop its workers, and each trial records its own code (user attribute
    ``ermrl_code``), which ``ermrl study show`` and ``ermrl report`` count.

    Args:
        study: The study.
        trials: Trials whose code to compare (``ermrl_code``, set when they are claimed);
            ``None``: the study's own (``ermrl_code`` of the study, none for an older ermrl).
    """
    others: list[tuple[Any, str]] = []
    if trials is None:
        stored = study.user_attrs.get(CODE_ATTR)
        if same_code(stored) is not True:  # other code, or none recorded (an older ermrl)
            others.append((stored, "was created by"))
    else:
        records = code_versions(t.user_attrs.get(CODE_ATTR) for t in trials)
        others += [(r, "holds trials of") for r, _ in records if same_code(r) is False]
    warned = _WARNED.setdefault(study, set())
    for record, what in others:
        other = describe_code(record)
        if other in warned:
            continue
        warned.add(other)
        # warn_explicit without a source line: one line on stderr, not two.
        warnings.warn_explicit(
            f"study {study.study_name!r} {what} {other}; this worker runs "
            f"{describe_code(code_identity())}: its trials mix code versions (each trial records "
            "its own, user attribute ermrl_code)",
            CodeVersionWarning,
            "ermrl",
            0,
        )
