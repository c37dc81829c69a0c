"""Evolve, test and report from Python: the library functions the ``ermrl`` commands run.

Each function does what its command does, without the command line: it takes the library's
configuration objects (or keyword options named as the command's options), raises the
library's exceptions instead of exiting, prints nothing unless asked, and returns a small
frozen result.
"""

from __future__ import annotations

import contextlib
import dataclasses
import shlex
import sys
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from ermrl._schema import to_argv, validate
from ermrl.config import ConfigError
from ermrl.storage import DEFAULT_STORAGE

if TYPE_CHECKING:
    import optuna
    import pandas as pd

    from ermrl._progress import ProgressMode
    from ermrl.analysis import ReportResult
    from ermrl.config import EvolveConfig
    from ermrl.search import EvolutionSummary
    from ermrl.test_phase import TestOptions

__all__ = [
    "EvolveResult",
    "NothingToReport",
    "TestResult",
    "evolve",
    "evolve_config",
    "report",
    "test",
]

# Options of ``ermrl evolve`` that are not part of the configuration: arguments of
# `evolve` itself, or of the command line only.
_NOT_CONFIG = {
    "env_id", "storage", "study_name", "quiet", "help", "progress", "tensorboard", "wandb",
    "heartbeat_interval", "grace_period", "max_retry", "wait_for_running",
}  # fmt: skip


def shown(value: Any) -> str:
    """A value and its type, for a one-line refusal (``int 42``)."""
    return f"{type(value).__name__} {value!r}"


def check_call(where: str, storage: Any, study_name: Any, *, name_optional: bool = False) -> None:
    """Refuse, in one line, a storage or a study name that is not one, before anything is
    opened (the library's functions are called with Python values no parser has seen).

    Raises:
        ConfigError: ``storage`` is not a supported storage URL, or ``study_name`` not a name.
    """
    from ermrl.storage import StorageError, storage_kind

    if not isinstance(storage, str):
        raise ConfigError(
            f"{where}: storage is a storage URL (sqlite:///file.db, postgresql://..., "
            f"journal:///file.log), got {shown(storage)}"
        )
    try:
        storage_kind(storage)
    except StorageError as err:
        raise ConfigError(f"{where}: storage: {err}") from None
    if study_name is None and name_optional:
        return
    if not isinstance(study_name, str) or not study_name.strip():
        raise ConfigError(f"{where}: study_name is a study's name, got {shown(study_name)}")


class NothingToReport(ConfigError):
    """A study with no completed trial: a report would have nothing to show."""


@dataclass(frozen=True)
class EvolveResult:
    """What an evolution holds after [`evolve`][ermrl.runner.evolve] returned.

    Attributes:
        study_name: The study.
        storage: Its storage URL.
        n_trials: Finished trials in the study (COMPLETE or PRUNED), every worker's.
        best_trial: The number of the trial with the best fitness (``None``: none completed).
        best_params: Its parameters (``sr``, ``lr``, ``input_scaling`` with one reservoir;
            ``sr_0``, ``lr_0``, ... with several).
        best_fitness: Its fitness, the mean return over the evolution's seeds.
        selected_trial: The trial the test phase selects: the re-evaluated best when a
            current ranking exists, else the best fitness (``None``: none completed).
        selection: How it was selected, in words.
        worker: What this call ran (trials started, completed, failed, pruned).
    """

    study_name: str
    storage: str
    n_trials: int
    best_trial: int | None
    best_params: dict[str, float]
    best_fitness: float | None
    selected_trial: int | None
    selection: str | None
    worker: EvolutionSummary

    @property
    def study(self) -> optuna.Study:
        """The ``optuna.Study``, loaded from the storage."""
        from ermrl.storage import load_study

        return load_study(self.study_name, self.storage)


@dataclass(frozen=True, eq=False)
class TestResult:
    """What [`test`][ermrl.runner.test] trained and wrote.

    Attributes:
        study_name: The evolution study.
        out: The test phase's folder.
        trial: The trial whose reservoir the evolved agents use (``None``: no such agent).
        params: Its parameters.
        selection: How it was selected, in words.
        agents: The agents trained.
        seeds: The test seeds.
        returns: One row per finished run (``agent``, ``seed``, ``final_return``,
            ``n_episodes``, ...), read back from the folder.
        summary: One row per agent: mean, std and IQM of the final returns
            (``summary.csv``).
        comparisons: The evolved agent against each other agent on the final returns, one
            row per other agent (``candidate``, ``baseline``, ``mean_diff``, bootstrap and
            Welch intervals, ``p_value``, ...: the report's comparison table,
            [`compare_agents`][ermrl.analysis.compare_agents]); empty without the evolved agent.
        files: ``{name: path}`` of the files written at the folder's top (``summary.csv``,
            ``curves.csv``, ``learning_curves.png``, ``config.yaml``, ``command.txt``).
        notes: Why the agents train with their backend, when none was asked for.
    """

    __test__ = False  # not a pytest test class

    study_name: str
    out: Path
    trial: int | None
    params: dict[str, float]
    selection: str | None
    agents: tuple[str, ...]
    seeds: tuple[int, ...]
    returns: pd.DataFrame = field(repr=False)
    summary: pd.DataFrame = field(repr=False)
    comparisons: pd.DataFrame = field(repr=False)
    files: dict[str, Path] = field(default_factory=dict)
    notes: tuple[str, ...] = ()


def evolve_config(
    env_id: str,
    *,
    storage: str | None = None,
    study_name: str | None = None,
    tensorboard: bool = False,
    **options: Any,
) -> EvolveConfig:
    """The configuration ``ermrl evolve --env-id ENV_ID`` with these options would run.

    The options are the command's, spelled as in an experiment file's ``evolve`` stage
    (``n_trials=20`` for ``--n-trials 20``, ``ppo={"n_steps": 128}``, ``fixed_input_scaling=True``);
    they are checked by the command's own schema (types, ranges, unknown keywords: one
    line, before anything is written) and configuration code.

    Args:
        env_id: The gymnasium env id.
        storage: Where the study is (or will be): an existing study keeps the backend it was
            created with when ``backend`` is left out, as the command resumes it.
        study_name: The study's name (default: derived from env, mask and budget).
        tensorboard: The runs will log for TensorBoard (the backend is then sb3 where
            ``backend`` is left out).
        **options: ``ermrl evolve`` options (see ``ermrl evolve --help``).

    Returns:
        The configuration.

    Raises:
        ExperimentError: An unknown option (with the nearest valid one) or a value the
            command refuses, in one line.

    Examples:
        >>> config = evolve_config("CartPole-v1", n_trials=4, training_steps=2000)
    """
    config, _ = _evolve_config_and_argv(env_id, storage, study_name, tensorboard, options)
    return config


def _evolve_config_and_argv(
    env_id: str,
    storage: str | None,
    study_name: str | None,
    tensorboard: bool,
    options: Mapping[str, Any],
) -> tuple[EvolveConfig, list[str]]:
    from ermrl.envs import UnknownEnvError, UnsupportedObserveError
    from ermrl.runner._evolve_options import evolve_options
    from ermrl.runner._experiment import ExperimentError
    from ermrl.runner._resolve import config_from_args, keep_study_backend

    where = f"evolve {env_id}"
    reserved = sorted(set(options) & _NOT_CONFIG)
    if reserved:
        raise ExperimentError(f"{where}: {reserved[0]} is not an option of the configuration")
    cls = evolve_options()
    try:
        values = validate(cls, options, where)
    except ConfigError as err:
        raise ExperimentError(str(err)) from None
    args = cls(env_id=env_id, **values)
    if tensorboard:
        args = dataclasses.replace(args, tensorboard="<tensorboard>")
    argv = ["--env-id", env_id, *to_argv(cls, options, values)]
    try:
        config = config_from_args(args)
        if storage is not None:
            name = study_name or config.default_study_name
            config = keep_study_backend(args, config, storage, name, config_from_args, [])[1]
    except (ConfigError, UnknownEnvError, UnsupportedObserveError) as err:
        raise ExperimentError(f"{where}: {err}") from None
    return config, argv


def evolve(
    config: EvolveConfig | str,
    storage: str = DEFAULT_STORAGE,
    study_name: str | None = None,
    *,
    quiet: bool = True,
    progress: ProgressMode = "none",
    stream: TextIO | None = None,
    tensorboard: str | Path | None = None,
    wait_for_running: bool = True,
    heartbeat_interval: int = 60,
    grace_period: int = 300,
    max_retry: int = 3,
    **options: Any,
) -> EvolveResult:
    """Evolve for one task, as ``ermrl evolve`` does: create or resume the study, run trials
    until its budget is spent, then re-evaluate the best candidates if the configuration asks.

    Several processes may call it on one study: they share the trials. Calling it again on a
    finished study does nothing and returns what the study holds.

    Args:
        config: The configuration ([`EvolveConfig`][ermrl.config.EvolveConfig]), or an env id whose
            configuration ``options`` give ([`evolve_config`][ermrl.runner.evolve_config]).
        storage: The Optuna storage URL (``sqlite:///file.db``, ``journal:///file.log``, ...).
        study_name: The study's name (default: derived from env, mask and budget).
        quiet: No progress lines.
        progress: ``"bar"``, ``"lines"`` or ``"none"`` inside each trial.
        stream: Where progress lines go (default ``sys.stdout``).
        tensorboard: Also log each trial's training curves under this folder (sb3 backend).
        wait_for_running: At the end, wait for other workers' running trials.
        heartbeat_interval: Seconds between a running trial's heartbeats (0: off).
        grace_period: Seconds without heartbeat before a running trial is failed and retried.
        max_retry: Retries of a trial whose worker died.
        **options: With an env id: ``ermrl evolve`` options (``n_trials``, ``n_seeds``,
            ``training_steps``, ``observe``, ``ppo``, ...).

    Returns:
        The study's best trial, the trial the test phase selects, and this call's counts.

    Raises:
        ExperimentError: A bad option (with an env id).
        ConfigError: A study of that name exists with another configuration, or a
            configuration evolved on several tasks (use an experiment file, or
            ``ermrl evolve-generalization``).
        ermrl.storage.StorageError: The storage cannot be opened.
        KeyboardInterrupt: Ctrl-C (the running trial is closed and queued again).

    Examples:
        >>> import ermrl
        >>> result = ermrl.evolve(
        ...     "CartPole-v1", "sqlite:///ermrl.db", n_trials=4, n_seeds=1, training_steps=2000
        ... )
        >>> result.best_trial, result.best_params
    """
    from ermrl.config import EvolveConfig
    from ermrl.search import create_or_resume_study, evolve_and_reevaluate

    check_call("ermrl.evolve", storage, study_name, name_optional=True)
    if not isinstance(config, (str, EvolveConfig)):
        raise ConfigError(
            f"ermrl.evolve: config is an env id (such as 'Pendulum-v1') or an EvolveConfig, "
            f"got {shown(config)}"
        )
    config, command = _resolved_config(config, storage, study_name, tensorboard, options)
    name = study_name or config.default_study_name
    study_kwargs: dict[str, Any] = {
        "heartbeat_interval": heartbeat_interval or None,
        "grace_period": grace_period,
        "max_retry": max_retry,
    }
    with _optuna_warnings_only(quiet):
        study = create_or_resume_study(config, storage, name, command=command, **study_kwargs)
        worker = evolve_and_reevaluate(
            config, study, storage, quiet=quiet, stream=stream, study_kwargs=study_kwargs,
            wait_for_running=wait_for_running, progress=progress, tensorboard=tensorboard,
        )  # fmt: skip
    return _evolve_result(study, storage, worker)


def _resolved_config(
    config: EvolveConfig | str,
    storage: str,
    study_name: str | None,
    tensorboard: str | Path | None,
    options: dict[str, Any],
) -> tuple[EvolveConfig, str | None]:
    """The configuration [`evolve`][ermrl.runner.evolve] runs, checked, and the command line that
    runs it.

    Args:
        config: A configuration, or an env id whose configuration ``options`` give.
        storage: The Optuna storage URL.
        study_name: The study's name (``None``: the configuration's default).
        tensorboard: The TensorBoard folder (``None``: no logs).
        options: ``ermrl evolve`` options (with an env id only).

    Returns:
        The configuration, and the equivalent ``ermrl evolve`` command (with an env id; the
        study keeps it), else ``None``.

    Raises:
        ExperimentError: A bad option (with an env id).
        TypeError: Options with a configuration object.
        ConfigError: A configuration evolved on several tasks.
    """
    command = None
    if isinstance(config, str):
        config, argv = _evolve_config_and_argv(
            config, storage, study_name, tensorboard is not None, options
        )
        name = study_name or config.default_study_name
        command = shlex.join(["ermrl", "evolve", *argv, "--storage", storage, "--study-name", name])
    elif options:
        raise TypeError(f"evolve() got options {sorted(options)} with a configuration object")
    elif tensorboard is not None:
        from types import SimpleNamespace

        from ermrl.runner._resolve import check_tensorboard

        check_tensorboard(SimpleNamespace(tensorboard=str(tensorboard)))
    if config.generalization is not None:
        raise ConfigError(
            "a configuration evolved on several tasks runs from an experiment file "
            "(evolve.suite) or ermrl evolve-generalization"
        )
    return config, command


@contextlib.contextmanager
def _optuna_warnings_only(quiet: bool) -> Iterator[None]:
    """Optuna logs warnings only while it runs (``quiet``), as the commands set it; its own
    verbosity is restored after."""
    import optuna

    before = optuna.logging.get_verbosity()
    if quiet:
        optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        yield
    finally:
        optuna.logging.set_verbosity(before)


def _evolve_result(study: optuna.Study, storage: str, worker: EvolutionSummary) -> EvolveResult:
    from optuna.trial import TrialState

    from ermrl.search._progress import best_trial

    value, number, params = best_trial(study)
    finished = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.PRUNED))
    selected, how = (None, None) if number is None else _selected(study)
    return EvolveResult(
        study_name=study.study_name,
        storage=storage,
        n_trials=len(finished),
        best_trial=number,
        best_params=dict(params or {}),
        best_fitness=value,
        selected_trial=selected,
        selection=how,
        worker=worker,
    )


def _selected(study: optuna.Study) -> tuple[int | None, str | None]:
    from ermrl.search import select_trial

    try:
        trial, how = select_trial(study)
    except ConfigError as err:  # every re-evaluated candidate failed
        return None, str(err)
    return trial.number, how


def test(
    study_name: str,
    storage: str = DEFAULT_STORAGE,
    options: TestOptions | None = None,
    *,
    quiet: bool = True,
    stream: TextIO | None = None,
    **keywords: Any,
) -> TestResult:
    """The test phase, as ``ermrl test`` runs it: train the selected trial's reservoir and
    the baselines on new seeds, and write the comparison.

    Finished runs in the folder are kept (a second call resumes); runs made there with other
    settings are refused.

    Args:
        study_name: The evolution study (a single-task one).
        storage: Its storage URL.
        options: The test phase's options ([`TestOptions`][ermrl.test_phase.TestOptions]).
        quiet: No progress lines.
        stream: Where progress lines go (default ``sys.stdout``).
        **keywords: Fields of [`TestOptions`][ermrl.test_phase.TestOptions] (``training_steps``,
            ``seeds``, ``agents``, ``out``, ``trial``, ...), on top of ``options``.

    Returns:
        The selected trial, the per-run returns, the summary and the files written.

    Raises:
        ConfigError: Bad options, seeds the selection used, or a folder holding runs made
            with other settings.
        ermrl.storage.StudyNotFound: No such study.
        KeyboardInterrupt: Ctrl-C (finished runs are kept).

    Examples:
        >>> result = ermrl.test(
        ...     "CartPole-v1__all__2000steps", "sqlite:///ermrl.db", training_steps=2000,
        ...     seeds=[10, 11], out="runs/cartpole-test",
        ... )
        >>> result.summary[["agent", "final_return_mean"]]
    """
    from ermrl._schema import validate
    from ermrl.analysis import compare_agents, load_run_results
    from ermrl.learners import AGENT_KINDS
    from ermrl.test_phase import TestOptions, prepare_test, run_comparison, run_in_folder

    check_call("ermrl.test", storage, study_name)
    if options is not None and not isinstance(options, TestOptions):
        raise ConfigError(
            f"ermrl.test: options is a TestOptions (or give its fields as keywords), "
            f"got {shown(options)}"
        )
    checked = validate(TestOptions, keywords, "ermrl.test")
    options = dataclasses.replace(options or TestOptions(), **checked)
    phase = prepare_test(study_name, storage, options)
    plan = phase.plan
    if plan.warning:
        warnings.warn(plan.warning, UserWarning, stacklevel=2)
    summary = run_in_folder(
        plan.out,
        lambda: run_comparison(
            phase.task,
            phase.encoder,  # type: ignore[arg-type]  # None: a learner with genes, no encoder
            phase.ppo,
            plan.agents,
            plan.settings,
            metadata=phase.metadata,
            quiet=quiet,
            stream=stream or sys.stdout,
        ),
    )
    names = ("summary.csv", "curves.csv", "learning_curves.png", "config.yaml", "command.txt")
    chosen = plan.chosen
    returns = load_run_results(plan.out)
    # The evolved agent against every other one (no rows without it), as the report compares.
    evolved = [a for a in plan.agent_names if AGENT_KINDS[a].reservoirs == "evolved"][:1]
    others = [a for a in plan.agent_names if evolved and a != evolved[0]]
    return TestResult(
        study_name=study_name,
        out=plan.out,
        trial=None if chosen is None else chosen.number,
        params={} if chosen is None else dict(chosen.params),
        selection=None if chosen is None else chosen.how,
        agents=plan.agent_names,
        seeds=plan.seeds,
        returns=returns,
        summary=summary,
        comparisons=compare_agents(returns, "".join(evolved), others),
        files={n: plan.out / n for n in names if (plan.out / n).is_file()},
        notes=phase.notes,
    )


test.__test__ = False  # type: ignore[attr-defined]  # not a pytest test


def report(
    study_name: str,
    storage: str = DEFAULT_STORAGE,
    *,
    runs: str | Path | None = None,
    out: str | Path | None = None,
    band: str = "ci95",
    dynamics: bool = True,
    interactive: bool = True,
    html: bool = True,
    quiet: bool = True,
    stream: TextIO | None = None,
) -> ReportResult:
    """The report of a study and its test phase, as ``ermrl report`` writes it: figures,
    tables, ``report.md`` and ``report.html``.

    Args:
        study_name: The study.
        storage: Its storage URL.
        runs: The test phase's folder (default ``runs/<study_name>`` when it exists).
        out: The report folder (default ``reports/<study_name>``).
        band: Learning-curve band across seeds: ``ci95``, ``std``, ``sem`` or ``none``.
        dynamics: Record one res-ppo episode for the reservoir-dynamics section.
        interactive: Also write interactive plotly HTML figures of the search.
        html: Also write ``report.html``.
        quiet: No progress lines.
        stream: Where progress lines go (default ``sys.stdout``).

    Returns:
        The paths written ([`ReportResult`][ermrl.analysis.ReportResult]): ``markdown``, ``html``,
        ``figures`` and ``tables`` by name, and the sections left out with why.

    Raises:
        NothingToReport: The study has no completed trial yet.
        ermrl.storage.StudyNotFound: No such study.
        ermrl.analysis.RunFolderError: A file of the test phase's folder is damaged.
        OSError: The report cannot be written (nothing is written then).

    Examples:
        >>> ermrl.report("S", "sqlite:///ermrl.db", runs="runs/S").markdown
        PosixPath('reports/S/report.md')
    """
    from optuna.trial import TrialState

    from ermrl._schema import validate
    from ermrl.analysis import write_report
    from ermrl.runner._requests import ReportRequest
    from ermrl.storage import load_study

    check_call("ermrl.report", storage, study_name)
    values = dict(runs=runs, out=out, band=band, dynamics=dynamics, interactive=interactive)
    validate(ReportRequest, {**values, "html": html}, "ermrl.report")
    if runs is not None and not Path(runs).is_dir():
        raise ConfigError(f"runs {runs}: no such folder (the out of the test phase)")
    if out is not None and Path(out).exists() and not Path(out).is_dir():
        raise ConfigError(f"out {out}: a file, not a folder; choose another report folder")
    study = load_study(study_name, storage)
    if not study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        states = [t.state.name for t in study.get_trials(deepcopy=False)]
        found = ", ".join(f"{states.count(s)} {s}" for s in sorted(set(states))) or "none"
        raise NothingToReport(
            f"study {study_name!r} has no completed trial yet (trials: {found}); "
            "nothing to report: run ermrl evolve (or wait for its first trial)"
        )
    return write_report(
        study_name,
        storage,
        runs=runs,
        out=out,
        band=band,
        dynamics=dynamics,
        interactive=interactive,
        html_page=html,
        quiet=quiet,
        stream=stream,
    )
