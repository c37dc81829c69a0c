"""What the evolve, test and report commands run once their options are parsed.

Each ``run_*`` function takes the library's configuration objects, prints the lines its
command prints (progress, summary, one-line errors on stderr) and returns the command's exit
code. ``ermrl evolve``, ``ermrl test`` and ``ermrl report`` parse their argv and call them;
``ermrl run`` calls them with the configuration its plan resolved. A one-line error is a
`CommandFailed`, which the caller prints as ``prog: error: message``.
"""

from __future__ import annotations

import shlex
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from ermrl._interrupt import interruption
from ermrl._text import plural
from ermrl.config import ConfigError
from ermrl.runner._requests import EvolveRequest, ReportRequest, TestRequest

if TYPE_CHECKING:
    import optuna

    from ermrl._progress import ProgressMode
    from ermrl.config import EvolveConfig
    from ermrl.search import EvolutionSummary, Interrupted
    from ermrl.test_phase import TestPlan

__all__ = [
    "EXIT_INTERRUPTED",
    "EXIT_TERMINATED",
    "EXIT_USAGE",
    "CommandFailed",
    "EvolveRequest",
    "ReportRequest",
    "TestRequest",
    "check_wandb",
    "print_backend_notes",
    "print_notes",
    "quiet_libraries",
    "require_tensorboard",
    "run_and_report",
    "create_study",
    "progress_or_default",
    "run_evolve",
    "run_or_fail",
    "run_report",
    "run_test",
    "run_test_phase",
    "setup_errors",
    "study_write_failure",
]

T = TypeVar("T")

EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143


class CommandFailed(Exception):
    """A command stops with a one-line error (``message``; ``None``: already printed) and an
    exit code (2: bad input)."""

    def __init__(self, message: str | None, code: int = EXIT_USAGE) -> None:
        super().__init__(message)
        self.message, self.code = message, code


def quiet_libraries() -> None:
    """Keep the terminal for ermrl's own progress lines: Optuna logs warnings only."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)


def exit_code(prog: str, run: Callable[[], int]) -> int:
    """``run()``'s exit code; a `CommandFailed` is its line on stderr and its code."""
    try:
        return run()
    except CommandFailed as err:
        if err.message is not None:
            print(f"{prog}: error: {err.message}", file=sys.stderr)
        return err.code


# ---------------------------------------------------------------------------------------------
# evolve


def progress_or_default(value: ProgressMode | None) -> ProgressMode:
    from ermrl._progress import default_mode

    return default_mode() if value is None else value


def dashboard_line(storage: str) -> str | None:
    """The line that tells how to watch a study live in optuna-dashboard (``None``: it cannot)."""
    import importlib.util

    from ermrl.storage import dashboard_command

    command = dashboard_command(storage)
    if command is None:
        return None
    missing = importlib.util.find_spec("optuna_dashboard") is None
    return f"live view: {command}" + ("  (pip install 'ermrl[viz]')" if missing else "")


def create_study(request: EvolveRequest, prog: str) -> optuna.Study:
    """Check the worker's options, print the backend notes and create or resume the study
    (on one task or a set of tasks, as the configuration says).

    Raises:
        CommandFailed: The study cannot be created or written (one line, exit code 2).
    """
    from ermrl.search import create_or_resume_generalization_study, create_or_resume_study
    from ermrl.storage import LockTimeout, StorageError

    config, storage = request.config, request.storage
    check_wandb(request.wandb)
    print_backend_notes(prog, config, request.notes)
    create = (
        create_or_resume_study
        if config.generalization is None
        else create_or_resume_generalization_study
    )
    try:
        return create(
            config, storage, request.study_name, command=request.command, **study_options(request)
        )
    except (ConfigError, StorageError, LockTimeout) as err:
        raise CommandFailed(str(err)) from None
    except OSError as err:  # a full disk or read-only folder under a journal file
        message = study_write_failure(err, storage)
        if message is None:
            raise
        raise CommandFailed(message) from None


def study_options(request: EvolveRequest) -> dict[str, Any]:
    """The study's heartbeat and retry options of the worker (also its re-evaluation's)."""
    return {
        "heartbeat_interval": request.heartbeat_interval or None,
        "grace_period": request.grace_period,
        "max_retry": request.max_retry,
    }


def run_evolve(request: EvolveRequest, prog: str = "ermrl evolve") -> int:
    """Create or resume the study and run this worker's trials, printing what ``ermrl evolve``
    prints; return its exit code. (A study on a set of tasks:
    `ermrl.runner._generalization.run_evolve_generalization`.)

    Raises:
        CommandFailed: The study cannot be created or written (one line, exit code 2).
    """
    config, storage, study_name = request.config, request.storage, request.study_name
    study = create_study(request, prog)
    if not request.quiet:
        print(
            f"study {study_name!r} in {storage}: {config.problem.task.label}, "
            f"{plural(len(config.problem.seeds), 'seed')} x {config.problem.budget.training_steps} steps per trial, "
            f"{config.search.sampler} sampler, {plural(config.search.n_trials, 'trial')}",
            flush=True,
        )
        if (live := dashboard_line(storage)) is not None:
            print(live, flush=True)
    return run_and_report(
        prog,
        config,
        study,
        quiet=request.quiet,
        fitness_name="fitness",
        next_command=f"ermrl test --study-name {shlex.quote(study_name)} "
        f"--storage {shlex.quote(storage)}",
        storage_url=storage,
        study_kwargs=study_options(request),
        wait_for_running=request.wait_for_running,
        progress=progress_or_default(request.progress),
        wandb=request.wandb,
        tensorboard=request.tensorboard,
    )


def print_backend_notes(prog: str, config: EvolveConfig, notes: Sequence[str]) -> None:
    """One line on stderr (also with ``--quiet``) per reason the run trains with its backend
    when ``--backend`` was left out."""
    for note in notes:
        print(
            f"{prog}: training with the {config.problem.ppo.backend} backend: {note}",
            file=sys.stderr,
            flush=True,
        )


def database_cause(err: BaseException) -> str:
    """What the database said under Optuna's ``StorageInternalError`` (whose own message
    blames "invalid data ... e.g. exceeding max length" whatever happened): the driver's
    error, e.g. SQLite's ``database or disk is full``, in one line."""
    seen: set[int] = set()
    cause: BaseException | None = err
    found = None
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        orig = getattr(cause, "orig", None)  # SQLAlchemy's DBAPIError: the driver's error
        if isinstance(orig, BaseException):
            found = orig
        cause = cause.__cause__ or cause.__context__
    text = str(found if found is not None else err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def interrupted_message(err: Interrupted) -> str:
    """What a signal did to this worker's trial, in words (after ``prog: ``)."""
    signame = err.args[0]
    if err.trial_number is None:
        return f"stopped by {signame} between trials; no trial of this worker was running"
    return f"stopped by {signame}; {_closed_trials(err)}"


def _closed_trials(err: BaseException) -> str:
    """The trials a signal closed (a generation's with the population backend), in words."""
    closed = getattr(err, "closed_trials", None) or [
        (getattr(err, "trial_number", None), getattr(err, "requeued", False))
    ]
    if len(closed) == 1:
        number, requeued = closed[0]
        again = " and queued again" if requeued else " (its retries are spent; not queued again)"
        return f"the running trial #{number} was closed as FAIL{again}"
    numbers = ", ".join(f"#{n}" for n, _ in sorted(closed))
    n_requeued = sum(1 for _, requeued in closed if requeued)
    again = (
        " and queued again"
        if n_requeued == len(closed)
        else f" ({n_requeued} queued again; the others' retries are spent)"
    )
    return f"the {len(closed)} running trials {numbers} were closed as FAIL{again}"


def study_write_failure(err: OSError, storage: str) -> str | None:
    """One line for a study that could not be created because its storage cannot be written.

    ``None``: not a full disk, a quota or a read-only folder (the caller re-raises).
    """
    from ermrl.test_phase._test_phase import WRITE_ERRNOS

    if err.errno not in WRITE_ERRNOS:
        return None
    return (
        f"cannot write to {storage}: {err.strerror or err}; the study was not created (or "
        "not changed): free space (or fix the folder) and rerun"
    )


def check_wandb(project: str | None) -> None:
    """``--wandb`` without its packages: one line, before anything is written.

    Raises:
        CommandFailed: wandb is not installed.
    """
    if project is not None:
        from ermrl.agents import WANDB_MISSING, wandb_installed

        if not wandb_installed():
            raise CommandFailed(WANDB_MISSING)


def wandb_callbacks(
    project: str | None, study_name: str, config: EvolveConfig
) -> tuple[list[Any], Callable[[], None]]:
    """The trial callbacks of ``--wandb PROJECT`` (none without it) and what ends them."""
    if project is None:
        return [], lambda: None
    import warnings

    from ermrl.agents import study_wandb_callback
    from ermrl.config import to_dict

    check_wandb(project)
    with warnings.catch_warnings():  # optuna marks the callback experimental
        warnings.simplefilter("ignore")
        callback, finish = study_wandb_callback(project, study_name, to_dict(config))
    return [callback], finish


def run_and_report(
    prog: str,
    config: EvolveConfig,
    study: optuna.Study,
    *,
    quiet: bool,
    fitness_name: str,
    next_command: str,
    storage_url: str | None = None,
    study_kwargs: dict[str, Any] | None = None,
    evaluator_factory: Any = None,
    wandb: str | None = None,
    **run_kwargs: Any,
) -> int:
    """Run this worker's trials of ``study`` and print how it ended; return the exit code.

    Shared by ``ermrl evolve`` and ``ermrl evolve-generalization``. On SIGTERM or Ctrl-C, one
    line on stderr says what became of the running trial.

    Args:
        prog: program name that starts the stderr lines.
        config: the study's configuration.
        study: the created or resumed study.
        quiet: no progress lines and no summary (the stderr lines are still printed).
        fitness_name: what the summary calls the best value, e.g. ``"normalized fitness"``.
        next_command: the test command the summary suggests next.
        storage_url: the study's storage, where its re-evaluation study lives (``None``: no
            re-evaluation).
        study_kwargs: heartbeat and retry options of the re-evaluation study.
        evaluator_factory: builds the fitness of the re-evaluation config (multi-task runs).
        wandb: ``--wandb PROJECT``: each recorded trial is logged there (``None``: not).
        **run_kwargs: passed on to
            [`ermrl.search.evolve_and_reevaluate`][ermrl.search.evolve_and_reevaluate]
            (``evaluate``, ``wait_for_running``, ``progress``, ``tensorboard``).

    Returns:
        0 when the worker finished, ``EXIT_TERMINATED`` (143) when stopped by a signal,
        ``EXIT_INTERRUPTED`` (130) on Ctrl-C.

    Raises:
        CommandFailed: The storage could not be written or read while the worker ran.
    """
    from optuna.exceptions import StorageInternalError

    from ermrl.search import Interrupted, evolve_and_reevaluate
    from ermrl.storage import StorageError
    from ermrl.test_phase._test_phase import WRITE_ERRNOS

    where = storage_url or "the storage"
    callbacks, finish_wandb = wandb_callbacks(wandb, study.study_name, config)
    try:
        summary = evolve_and_reevaluate(
            config,
            study,
            storage_url,
            quiet=quiet,
            evaluator_factory=evaluator_factory,
            study_kwargs=study_kwargs,
            callbacks=callbacks,
            **run_kwargs,
        )
    except Interrupted as err:
        print(f"{prog}: {interrupted_message(err)}", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt as err:
        print(f"{prog}: {_ctrl_c_message(err)}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except StorageError as err:  # e.g. another process damaged a journal while this one ran
        raise CommandFailed(str(err)) from None
    except StorageInternalError as err:  # a database's write failed: a full disk, say
        raise CommandFailed(_database_write_failure(err, where)) from None
    except OSError as err:  # a full disk, a quota or a read-only folder under a journal file
        if err.errno not in WRITE_ERRNOS:
            raise
        raise CommandFailed(_journal_write_failure(err, where)) from None
    finally:
        finish_wandb()
    if not quiet:
        _print_summary(summary, fitness_name, next_command)
    return 0


def _ctrl_c_message(err: KeyboardInterrupt) -> str:
    """What Ctrl-C did to this worker's trial, in words (after ``prog: ``)."""
    if getattr(err, "trial_number", None) is None:
        return "interrupted between trials; no trial of this worker was running"
    return f"interrupted; {_closed_trials(err)}"


def _database_write_failure(err: BaseException, where: str) -> str:
    """One line for a database write that failed while the worker ran (a full disk, say)."""
    return (
        f"cannot write to {where}: {database_cause(err)}; its finished trials are kept, "
        "a trial cut short is retried once its heartbeat is stale (or run ermrl study "
        "fail-stale): free space (or fix the database) and rerun"
    )


def _journal_write_failure(err: OSError, where: str) -> str:
    """One line for a journal file that could not be written while the worker ran (a full
    disk, a quota or a read-only folder)."""
    return (
        f"cannot write to {where}: {err.strerror or err}; its finished trials are kept, "
        "a trial cut short is retried once its heartbeat is stale (or run ermrl study "
        "fail-stale), and a record cut short is set aside when the next worker opens the "
        "journal: free space (or fix the folder) and rerun"
    )


def _print_summary(summary: EvolutionSummary, fitness_name: str, next_command: str) -> None:
    """What this worker did, the study's best and the command to run next."""
    from ermrl.search import format_params

    best = (
        "none yet"
        if summary.best_value is None
        else f"{summary.best_value:.4g} with {format_params(summary.best_params or {})}"
    )
    print(
        f"done: this worker ran {plural(summary.trials_run, 'trial')} ({summary.completed} complete, "
        f"{summary.pruned} pruned, {summary.failed} failed); best {fitness_name} {best}\n"
        f"next: {next_command}",
        flush=True,
    )


# ---------------------------------------------------------------------------------------------
# test


def run_or_fail(prog: str, out: Path, run: Callable[[], T]) -> T | None:
    """Run a test phase in ``out`` (removed again when this call created it and it fails
    before it holds anything but its skeleton:
    [`ermrl.test_phase.run_in_folder`][ermrl.test_phase.run_in_folder]); its expected failures
    become one line.

    Shared by ``ermrl test`` and ``ermrl test-generalization``.

    Args:
        prog: program name that starts the interruption line.
        out: the output folder (named in the messages).
        run: the test phase.

    Returns:
        What ``run`` returned, or ``None`` after Ctrl-C (finished runs are kept; the caller
        exits with ``EXIT_INTERRUPTED``).

    Raises:
        CommandFailed: exit code 2 when ``out`` holds runs made with other settings or a
            damaged finished run, when a run ends no episode or diverges, or when a full disk,
            a quota or a read-only folder stops a write; a signal's code after its line.
    """
    from ermrl.test_phase import run_in_folder

    return _run_or_fail(prog, out, lambda: run_in_folder(out, run))


def _run_or_fail(prog: str, out: Path, run: Callable[[], T]) -> T | None:
    from ermrl.agents import NoEpisodeFinished, TrainingDiverged
    from ermrl.analysis import RunFolderError
    from ermrl.test_phase._test_phase import WRITE_ERRNOS, write_error_message

    try:
        return run()
    except ConfigError as err:  # the folder holds runs made with other settings
        raise CommandFailed(str(err)) from None
    except RunFolderError as err:  # a finished run in the folder that would be kept is damaged
        raise CommandFailed(
            f"{err}; move that run folder away, or rerun with --overwrite to retrain the "
            "runs asked for"
        ) from None
    except (NoEpisodeFinished, TrainingDiverged) as err:  # a run could not be measured
        raise CommandFailed(f"{err}; finished runs are kept in {out}") from None
    except OSError as err:  # a full disk, a quota, a read-only folder
        if err.errno not in WRITE_ERRNOS:
            raise
        raise CommandFailed(write_error_message(err, out)) from None
    except KeyboardInterrupt as err:
        what, code = interruption(err)
        print(f"{prog}: {what}; finished runs are kept in {out}", file=sys.stderr)
        if code != EXIT_INTERRUPTED:
            raise CommandFailed(None, code) from None
        return None


def print_notes(prog: str, ppo: Any, notes: Sequence[str]) -> None:
    """One line on stderr (also with ``--quiet``) per reason the study's agents train with
    their backend when ``--backend`` was left out."""
    for note in notes:
        print(
            f"{prog}: training with the {ppo.backend} backend: {note}", file=sys.stderr, flush=True
        )


def setup_errors() -> tuple[type[BaseException], ...]:
    """The errors that make a test phase's preparation stop in one line."""
    from ermrl.envs import UnknownEnvError, UnsupportedObserveError
    from ermrl.storage import StorageError, StudyNotFound

    return (ConfigError, StorageError, StudyNotFound, UnknownEnvError, UnsupportedObserveError)


def require_tensorboard(tensorboard: str | Path | None) -> None:
    """``--tensorboard`` without the tensorboard package.

    Raises:
        CommandFailed: the package is not installed.
    """
    if not tensorboard:
        return
    import importlib.util

    if importlib.util.find_spec("tensorboard") is None:
        raise CommandFailed(
            "--tensorboard needs the tensorboard package, which is not installed "
            "(pip install tensorboard)"
        )


def run_test_phase(
    prog: str,
    plan: TestPlan,
    task: Any,
    encoder: Any,
    ppo: Any,
    metadata: dict[str, Any],
    *,
    quiet: bool,
    command: str | None = None,
    then: Callable[[Any], Any] | None = None,
) -> Any:
    """Train the plan's agents (one-line errors, Ctrl-C keeps finished runs) and print the
    summary; ``then`` post-processes the summary table. Returns it, or ``None`` after Ctrl-C.

    Raises:
        CommandFailed: see `run_or_fail`.
    """
    from ermrl.test_phase import run_comparison

    def run() -> Any:
        summary = run_comparison(
            task, encoder, ppo, plan.agents, plan.settings, metadata=metadata, quiet=quiet,
            command=command,
        )  # fmt: skip
        return summary if then is None else then(summary)

    summary = run_or_fail(prog, plan.out, run)
    if summary is not None and not quiet:
        # Without --eval the evaluation columns are empty: left out of the printed table (they
        # stay in summary.csv, whose columns do not depend on the options).
        shown = summary.drop(columns=["seeds"])
        empty = [c for c in shown.columns if c.startswith("eval_") and shown[c].isna().all()]
        print(shown.drop(columns=empty).to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    return summary


def run_test(request: TestRequest, prog: str = "ermrl test") -> int:
    """The test phase, printing what ``ermrl test`` prints; return its exit code.

    Raises:
        CommandFailed: Bad options, study or folder, or a run that cannot be measured.
    """
    from ermrl.test_phase import describe_selection, prepare_test

    options = request.options
    require_tensorboard(options.tensorboard)
    check_wandb(options.wandb)
    try:
        phase = prepare_test(request.study_name, request.storage, options)
    except setup_errors() as err:
        raise CommandFailed(str(err)) from None
    plan = phase.plan
    print_notes(prog, phase.ppo, phase.notes)
    if plan.warning:  # also with --quiet: the selection is not the one a ranking would give
        print(f"{prog}: warning: {plan.warning}", file=sys.stderr, flush=True)
    if not request.quiet:
        best = describe_selection(plan.chosen)
        print(
            f"test phase of {request.study_name!r}: {phase.task.label}, agents "
            f"{' '.join(plan.agent_names)}, seeds {' '.join(map(str, plan.seeds))}, "
            f"{options.training_steps} steps each; selected: {best}; out: {plan.out}",
            flush=True,
        )
    summary = run_test_phase(
        prog, plan, phase.task, phase.encoder, phase.ppo, phase.metadata,
        quiet=request.quiet, command=request.command,
    )  # fmt: skip
    if summary is None:
        return EXIT_INTERRUPTED
    if not request.quiet:
        print(f"wrote {plan.out}/summary.csv, curves.csv, learning_curves.png", flush=True)
    return 0


# ---------------------------------------------------------------------------------------------
# report


def run_report(request: ReportRequest, prog: str = "ermrl report") -> int:
    """Write the report, printing what ``ermrl report`` prints; return its exit code.

    Raises:
        CommandFailed: No such study or runs folder, nothing to report, or the report cannot
            be written (nothing is written then).
    """
    from ermrl.analysis import RunFolderError
    from ermrl.envs import UnknownEnvError
    from ermrl.runner._stages import report
    from ermrl.storage import StorageError, StudyNotFound

    r = request
    if r.runs is not None and not Path(r.runs).is_dir():  # the flag's name; report() says runs
        raise CommandFailed(f"--runs {r.runs}: no such folder (the --out of ermrl test)")
    try:
        result = report(
            r.study_name, r.storage, runs=r.runs, out=r.out, band=r.band, dynamics=r.dynamics,
            interactive=r.interactive, html=r.html, quiet=r.quiet,
        )  # fmt: skip
    except (
        ConfigError,  # nothing to report yet, a study name that names no folder
        StorageError,
        StudyNotFound,
        FileNotFoundError,
        UnknownEnvError,
        RunFolderError,
    ) as err:
        raise CommandFailed(str(err)) from None
    except OSError as err:  # a read-only folder, a full disk: the report was staged, not written
        raise CommandFailed(
            f"cannot write the report {r.out or Path('reports') / r.study_name}: "
            f"{err.strerror or err}; nothing was written (free space, or choose a writable --out)"
        ) from None
    except KeyboardInterrupt as err:
        what, code = interruption(err)
        print(f"{prog}: {what}; no report written", file=sys.stderr)
        return code
    for warning in result.warnings:  # also with --quiet: the results may not compare
        print(f"{prog}: warning: {warning}", file=sys.stderr, flush=True)
    if not r.quiet:
        for note in result.notes:
            print(f"left out: {note}")
        print(
            f"wrote {result.markdown}"
            + (f" and {result.html}" if result.html else "")
            + f" ({len(result.figures)} figures, {len(result.tables)} tables)",
            flush=True,
        )
    return 0
