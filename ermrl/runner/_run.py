"""Running an experiment file: its plan, what is done, and the unfinished stages in order.

``ermrl run FILE`` and [`ermrl.Experiment.run`][ermrl.runner.Experiment.run] share this code. Each
stage runs the library function its command runs (`ermrl.runner._commands`,
`ermrl.runner._generalization`) with the configuration the plan resolved from the file's options, in
this process, and prints the equivalent command line first, so that one stage can be run by hand.
The study and the run folders are the state: a stage the storage or the folders say is done is
skipped, and an interrupted one resumes.
"""

from __future__ import annotations

import contextlib
import shlex
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TextIO

from ermrl._text import plural
from ermrl.runner._commands import (
    EvolveRequest,
    ReportRequest,
    TestRequest,
    exit_code,
    quiet_libraries,
    run_evolve,
    run_report,
    run_test,
)
from ermrl.runner._experiment import (
    DEFAULT_SNAPSHOT_EVERY,
    ExperimentError,
    ExperimentFile,
    Step,
    experiment_plan,
    format_duration,
    resolved_document,
)
from ermrl.runner._generalization import (
    TestGeneralizationRequest,
    run_evolve_generalization,
    run_test_generalization,
)
from ermrl.runner._publish import (
    PeriodicSnapshots,
    import_snapshots,
    publish_finished_runs,
    publish_results,
    published_runs_status,
    restore_finished_runs,
    snapshot_status,
    write_snapshots,
)
from ermrl.runner._requests import with_run_options

__all__ = [
    "DEFAULT_SNAPSHOT_EVERY",
    "PROGRESS_STAGES",
    "STAGE_CHOICES",
    "TENSORBOARD_COMMANDS",
    "WANDB_COMMANDS",
    "StageFailed",
    "StageInterrupted",
    "Status",
    "choose_stages",
    "plan_experiment",
    "check_test_piece",
    "plan_lines",
    "remove_if_untouched",
    "results_lines",
    "run_experiment",
    "run_plan",
    "stage_argv",
    "step_status",
    "write_snapshot_files_verbose",
]

#: The stages of an experiment, in the order they run.
STAGE_CHOICES = ("evolve", "reevaluate", "test", "report")
#: The stages whose commands take ``--progress`` (each evolve and test command does).
PROGRESS_STAGES = ("evolve", "test")
#: The commands ``ermrl run --wandb`` passes ``--wandb`` to.
WANDB_COMMANDS = ("evolve", "test")
#: The commands that take ``--tensorboard``.
TENSORBOARD_COMMANDS = ("evolve", "evolve-generalization", "test", "test-generalization")
# The file each run writes beside its results: the experiment with every option filled in.
_RESOLVED_FILE = "experiment.resolved.yaml"

#: A step's status: ``(done, fraction of it left, what the storage or folders say)``.
Status = tuple[bool, float, str]


class StageFailed(ExperimentError):
    """A stage's command stopped with a non-zero exit code.

    The command printed its own one-line error on stderr first. Running the experiment again
    resumes: finished trials and runs are kept.

    Attributes:
        stage: ``evolve``, ``reevaluate``, ``test`` or ``report``.
        label: The task (or task set) of the stage.
        code: The command's exit code.
    """

    def __init__(self, stage: str, label: str, code: int) -> None:
        super().__init__(f"stage {stage} of {label} stopped (exit code {code})")
        self.stage, self.label, self.code = stage, label, code


class StageInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM during a stage; the stage's finished test runs were published first.

    A ``KeyboardInterrupt``, so that it stops a caller as Ctrl-C does.

    Attributes:
        stage: The stage that was running.
        label: Its task (or task set).
        signum: The signal (``SIGINT`` for Ctrl-C, ``SIGTERM``).
    """

    def __init__(self, stage: str, label: str, signum: int) -> None:
        super().__init__(f"stage {stage} of {label} interrupted")
        self.stage, self.label, self.signum = stage, label, signum


def stage_argv(
    step: Step,
    progress: str | None,
    tensorboard: str | None,
    quiet: bool = False,
    wandb: str | None = None,
) -> list[str]:
    """A step's arguments with ``ermrl run``'s own ``--progress`` and ``--tensorboard`` added
    (the last of a repeated option wins over the file's).

    ``--tensorboard DIR`` goes to the evolve commands (``DIR/<label>/evolve``) and to ``ermrl
    test`` (``DIR/<label>/test``); ``test-generalization`` takes none.

    Args:
        step: The step.
        progress: ``bar``, ``lines`` or ``none`` for the evolve and test commands (``None``:
            the file's, else the commands' default).
        tensorboard: The folder of the TensorBoard logs (``None``: none).
        quiet: Also pass ``--quiet`` (every stage's command takes it).
        wandb: A Weights & Biases project for the evolve and test commands (``None``: none).

    Returns:
        The command's arguments, without the command's name.
    """
    argv = list(step.argv)
    if progress is not None and step.stage in PROGRESS_STAGES:
        argv += ["--progress", progress]
    if tensorboard is not None and step.command in TENSORBOARD_COMMANDS:
        argv += ["--tensorboard", str(Path(tensorboard) / step.label / step.stage)]
    if wandb is not None and step.command in WANDB_COMMANDS:
        argv += ["--wandb", wandb]
    if quiet:
        argv.append("--quiet")
    return argv


def step_status(exp: ExperimentFile, step: Step) -> Status:
    """A step's status; for an evolution the storage lacks, what its snapshot holds; for a
    test phase, the published finished runs its folder lacks.

    Args:
        exp: The experiment.
        step: One of its steps.

    Returns:
        ``(done, fraction left, text)``.
    """
    done, left, text = step.status()
    if step.stage == "evolve" and text == "not started":
        from_snapshot = snapshot_status(exp, step)
        if from_snapshot is not None:
            left, text = from_snapshot
    elif step.stage == "test" and not done:
        # Not done until they are put back (the run does it, then skips them).
        from_publish = published_runs_status(exp, step)
        if from_publish is not None:
            left, text = from_publish
    return done, left, text


def plan_experiment(
    exp: ExperimentFile,
    *,
    tasks: Sequence[str] | None = None,
    tensorboard: bool = False,
    wandb: bool = False,
    build_agents: bool = True,
    test_agents: Sequence[str] = (),
    test_seeds: Sequence[int] = (),
) -> tuple[ExperimentFile, list[Step], list[Status]]:
    """Every step of an experiment, checked, with its status.

    Args:
        exp: The experiment ([`load_experiment`][ermrl.runner.load_experiment]).
        tasks: Only these tasks (for a generalization experiment: these test tasks).
        tensorboard: The evolve and test stages will log for TensorBoard (on either
            backend).
        build_agents: Also build each evolution agent once (``False``: a dry run, which
            checks the options, tables and storage only).
        test_agents: Each test stage trains only these of its agents (empty: all): a piece
            of a phase too long for one sitting. The report waits for the whole phase.
        test_seeds: Each test stage trains only these of its seeds (empty: all).

    Returns:
        ``(experiment, steps, statuses)``, the experiment with ``tensorboard`` and
        ``wandb`` set.

    Raises:
        ExperimentError: A key or value the commands refuse, or a study that contradicts the
            file (one line).
        ermrl.storage.StorageError: The storage cannot be read.
    """
    import dataclasses

    exp = dataclasses.replace(
        exp,
        tensorboard=bool(tensorboard),
        wandb=bool(wandb),
        test_agents=tuple(test_agents),
        test_seeds=tuple(test_seeds),
    )
    steps = experiment_plan(exp, tasks=tasks, build_agents=build_agents)
    return exp, steps, [step_status(exp, step) for step in steps]


def check_test_piece(
    stages: Sequence[str] | None, test_agents: Sequence[str], test_seeds: Sequence[int]
) -> None:
    """Refuse a piece of the test phase (``--agents``, ``--seeds``) with other stages than
    ``test``: the report of a piece would read part of the phase as the whole.

    Raises:
        ExperimentError: one line saying so.
    """
    if (test_agents or test_seeds) and list(stages or ()) != ["test"]:
        raise ExperimentError(
            "--agents and --seeds run a piece of the test phase: give --stage test alone "
            "(the report waits for the whole phase)"
        )


def choose_stages(
    steps: Sequence[Step], statuses: Sequence[Status], stages: Sequence[str] | None = None
) -> list[tuple[Step, Status]]:
    """The steps of these stages (``None`` or empty: all), each with its status, in order.

    Raises:
        ExperimentError: A stage that is not one of `STAGE_CHOICES`.
    """
    unknown = [s for s in stages or () if s not in STAGE_CHOICES]
    if unknown:
        raise ExperimentError(
            f"unknown stage {unknown[0]!r}; choose from {', '.join(STAGE_CHOICES)}"
        )
    keep = set(stages or STAGE_CHOICES)
    return [(s, st) for s, st in zip(steps, statuses) if s.stage in keep]


def plan_lines(exp: ExperimentFile, chosen: Sequence[tuple[Step, Status]]) -> list[str]:
    """The plan as ``ermrl run`` prints it: each command, its env steps, estimated wall time
    and status, then the totals.

    Args:
        exp: The experiment.
        chosen: The steps to show, each with its status (`choose_stages`).
    """
    head = f"experiment {exp.name!r}" + (f" (variant {exp.variant})" if exp.variant else "")
    lines = [
        f"{head} from {exp.path}",
        f"  storage {exp.storage}; results {exp.out}"
        + (f"; published to {exp.publish}" if exp.publish else ""),
    ]
    total_steps = 0
    total_seconds = 0.0
    left_seconds = 0.0
    for index, (step, (done, left, text)) in enumerate(chosen, start=1):
        mark = "done" if done else "todo"
        size = f"{step.env_steps / 1e6:.4g}M env steps" if step.env_steps else "no training"
        lines.append(
            f"  {index:>2}. [{mark}] {step.stage:<10} {step.label:<16} {size}, "
            f"~{format_duration(step.seconds)} ({text})"
        )
        if step.stage == "reevaluate":
            lines.append("      (run by the evolve command once the budget is spent)")
        else:
            lines.append(f"      {step.command_line}")
        if step.note:
            lines.append(f"      ({step.note})")
        total_steps += step.env_steps
        total_seconds += step.seconds
        left_seconds += 0.0 if done else step.seconds * left
    lines.append(
        f"  total {total_steps / 1e6:.4g}M env steps, ~{format_duration(total_seconds)} on 2 cores; "
        f"left ~{format_duration(left_seconds)} (estimates from ermrl/data/throughput.yml)"
    )
    return lines


def write_snapshot_files_verbose(
    exp: ExperimentFile, steps: Sequence[Step], stream: TextIO | None = None
) -> None:
    """Write what ``ermrl run --snapshot`` writes, one line per file on ``stream``: each
    evolution study as ``study.json`` and each test step's finished runs.

    Raises:
        OSError: A file cannot be written.
    """
    out = stream or sys.stdout
    for step, path, n in write_snapshots(exp, steps):
        print(
            f"wrote {path}: study {step.study_name!r}, {plural(n, 'trial')}", file=out, flush=True
        )
    for step in steps:
        n = publish_finished_runs(exp, step)
        if n:
            print(
                f"published {plural(n, 'finished test run')} of {step.label} to "
                f"{exp.publish}/{step.label}/test",
                file=out,
                flush=True,
            )


def run_experiment(
    exp: ExperimentFile,
    *,
    stages: Sequence[str] | None = None,
    tasks: Sequence[str] | None = None,
    progress: str | None = None,
    tensorboard: str | None = None,
    snapshot_every: float = DEFAULT_SNAPSHOT_EVERY,
    quiet: bool = False,
    quiet_stages: bool = False,
    stream: TextIO | None = None,
    wandb: str | None = None,
    test_agents: Sequence[str] = (),
    test_seeds: Sequence[int] = (),
) -> list[Step]:
    """Plan an experiment and run its unfinished steps, as ``ermrl run FILE`` does.

    Args:
        exp: The experiment ([`load_experiment`][ermrl.runner.load_experiment]).
        stages: Only these stages (default: all, in order).
        tasks: Only these tasks (for a generalization experiment: these test tasks).
        progress: ``bar``, ``lines`` or ``none`` inside the evolve and test stages
            (``None``: the file's, else the commands' default).
        tensorboard: Also log training curves for TensorBoard under this folder.
        snapshot_every: With ``publish:`` in the file, write the snapshot every this many
            seconds while it runs (0: never).
        quiet: No plan and no lines of this runner (the commands still print theirs).
        quiet_stages: Also pass ``--quiet`` to each stage's command.
        stream: Where the plan and this runner's lines go (default ``sys.stdout``).
        test_agents: Only these agents of each test stage (``ermrl run --agents``).
        test_seeds: Only these seeds of each test stage (``ermrl run --seeds``).

    Returns:
        Every step of the plan (of these tasks), the chosen ones now done.

    Raises:
        ExperimentError: The file cannot run (one line), or its results folder cannot be
            written.
        StageFailed: A stage's command stopped with an error (rerun to resume).
        StageInterrupted: Ctrl-C or SIGTERM during a stage.
    """
    out = stream or sys.stdout
    check_test_piece(stages, test_agents, test_seeds)
    exp, steps, statuses = plan_experiment(
        exp,
        tasks=tasks,
        tensorboard=bool(tensorboard),
        wandb=bool(wandb),
        test_agents=test_agents,
        test_seeds=test_seeds,
    )
    chosen = choose_stages(steps, statuses, stages)
    if not quiet:
        for line in plan_lines(exp, chosen):
            print(line, file=out, flush=True)
    run_plan(
        exp,
        steps,
        chosen,
        progress=progress,
        tensorboard=tensorboard,
        snapshot_every=snapshot_every,
        quiet=quiet,
        quiet_stages=quiet_stages,
        stream=out,
        wandb=wandb,
    )
    return steps


def run_plan(
    exp: ExperimentFile,
    steps: Sequence[Step],
    chosen: Sequence[tuple[Step, object]],
    *,
    progress: str | None = None,
    tensorboard: str | None = None,
    snapshot_every: float = DEFAULT_SNAPSHOT_EVERY,
    quiet: bool = False,
    quiet_stages: bool = False,
    stream: TextIO | None = None,
    wandb: str | None = None,
) -> None:
    """Write the resolved configuration, bring back published state, and run the chosen steps.

    What this creates (the resolved file and its folders) is removed again when it fails
    before any stage wrote a thing.

    Args:
        exp: The experiment, planned by `plan_experiment`.
        steps: All its steps (the resolved file lists them all).
        chosen: The steps to run (`choose_stages`).
        progress: ``--progress`` of the evolve and test commands (``None``: theirs).
        tensorboard: ``--tensorboard`` folder (``None``: no logs).
        snapshot_every: Seconds between snapshots of a file with ``publish:`` (0: never).
        quiet: No lines of this runner.
        quiet_stages: Also pass ``--quiet`` to each stage's command.
        stream: Where this runner's lines go (default ``sys.stdout``).
        wandb: Weights & Biases project of the evolve and test commands (``None``: none).

    Raises:
        ExperimentError: The results folder cannot be written, or a published snapshot or
            run cannot be brought back.
        StageFailed: A stage's command stopped with an error.
        StageInterrupted: Ctrl-C or SIGTERM during a stage.
    """
    if not snapshot_every >= 0:
        raise ExperimentError(
            f"snapshot_every must be 0 (never) or a number of seconds, not {snapshot_every}"
        )
    resolved_file = exp.out / _RESOLVED_FILE
    # What this run creates, removed again when it fails before any stage wrote a thing.
    created = [p for p in (resolved_file, exp.out, *exp.out.parents) if not p.exists()]
    try:
        _write_and_run(
            exp,
            steps,
            [step for step, _ in chosen],
            progress=progress,
            tensorboard=tensorboard,
            snapshot_every=snapshot_every,
            quiet=quiet,
            quiet_stages=quiet_stages,
            stream=stream or sys.stdout,
            wandb=wandb,
        )
    except BaseException:
        remove_if_untouched(created)
        raise


def remove_if_untouched(created: Sequence[Path]) -> None:
    """Remove what a failed run created (the resolved file, then its folders) if no stage
    wrote anything beside it: a folder is removed only when empty.

    Args:
        created: The resolved file first, then the folders created for it (innermost first).
    """
    if not created or created[0].name != _RESOLVED_FILE:
        return  # the file was there before this run: an earlier run's, kept
    resolved, *folders = created
    if not resolved.parent.is_dir():
        return
    if any(p != resolved for p in resolved.parent.iterdir()):
        return  # a stage wrote something: the resolved file says how it was run
    resolved.unlink(missing_ok=True)
    for folder in folders:
        with contextlib.suppress(OSError):
            folder.rmdir()


def _write_and_run(
    exp: ExperimentFile,
    steps: Sequence[Step],
    chosen: Sequence[Step],
    *,
    progress: str | None,
    tensorboard: str | None,
    snapshot_every: float,
    quiet: bool,
    quiet_stages: bool,
    stream: TextIO,
    wandb: str | None = None,
) -> None:
    """Write the resolved configuration, bring back published state, and run the steps."""
    import yaml

    from ermrl._io import write_atomic

    try:
        resolved = resolved_document(exp, steps)
        write_atomic(
            exp.out / _RESOLVED_FILE,
            "# ermrl run: the experiment as run, every command's options filled in\n"
            + yaml.safe_dump(resolved, sort_keys=False, width=100),
        )
    except OSError as err:
        raise ExperimentError(f"cannot write {exp.out}: {err.strerror or err}") from None
    try:
        _bring_back(exp, steps, stream)
    except OSError as err:
        raise ExperimentError(
            f"cannot restore the published test runs: {err.strerror or err}"
        ) from None
    with PeriodicSnapshots(exp, steps, snapshot_every):
        _run_steps(exp, chosen, progress, tensorboard, quiet, quiet_stages, stream, wandb)
    if not quiet:
        print(
            f"done: experiment {exp.name!r}; resolved configuration in {exp.out}/{_RESOLVED_FILE}",
            file=stream,
            flush=True,
        )


def _bring_back(exp: ExperimentFile, steps: Sequence[Step], stream: TextIO) -> None:
    """Import the published study snapshots the storage lacks and restore the published
    finished test runs the run folders lack, one line each."""
    for step, path, n in import_snapshots(exp, steps):
        print(
            f"imported {path}: study {step.study_name!r}, {plural(n, 'trial')}",
            file=stream,
            flush=True,
        )
    for step in steps:
        restored, retrained = restore_finished_runs(exp, step)
        if restored or retrained:
            again = ", ".join(f"{a} seed {s}" for a, s in retrained)
            if again:
                again = (
                    f"; trained again for the model the report replays, their published "
                    f"results kept: {again}"
                )
            print(
                f"restored {plural(restored, 'finished test run')} of {step.label} from "
                f"{exp.publish}/{step.label}/test{again}",
                file=stream,
                flush=True,
            )


def _run_steps(
    exp: ExperimentFile,
    chosen: Sequence[Step],
    progress: str | None,
    tensorboard: str | None,
    quiet: bool,
    quiet_stages: bool,
    stream: TextIO,
    wandb: str | None = None,
) -> None:
    """Run the unfinished steps in order, each through the library function of its command
    (`_run_step`).

    Raises:
        StageFailed: The first step whose command stopped with an error.
        StageInterrupted: Ctrl-C or SIGTERM during a step.
    """
    skipped: list[Step] = []
    for step in chosen:
        done, _, text = step.status()
        if done:
            skipped.append(step)
            if not quiet:
                print(
                    f"[{step.stage} {step.label}] skipped, already done: {text}",
                    file=stream,
                    flush=True,
                )
            publish_results(exp, step, stream)  # again: an earlier run's may have failed
            continue
        argv = stage_argv(step, progress, tensorboard, quiet=quiet_stages, wandb=wandb)
        line = shlex.join(["ermrl", step.command, *argv])
        if not quiet:
            print(f"[{step.stage} {step.label}] {line}", file=stream, flush=True)
        try:
            code = _run_step(step, line, progress, tensorboard, quiet_stages, wandb)
        except SystemExit as err:
            code = err.code if isinstance(err.code, int) else 1
        except KeyboardInterrupt as err:
            publish_results(exp, step, stream, finished=False)
            signum = getattr(err, "signum", None) or signal.SIGINT
            raise StageInterrupted(step.stage, step.label, int(signum)) from err
        if code != 0:
            publish_results(exp, step, stream, finished=False)
            raise StageFailed(step.stage, step.label, code)
        publish_results(exp, step, stream)
    if not quiet:
        for line in results_lines(skipped):
            print(line, file=stream, flush=True)


def _run_step(
    step: Step,
    line: str,
    progress: str | None,
    tensorboard: str | None,
    quiet_stages: bool,
    wandb: str | None,
) -> int:
    """Run one step, printing what its command prints; return the command's exit code.

    Each step runs its planned configuration through the library
    (`ermrl.runner._commands`) with ``ermrl run``'s own options added as
    [`stage_argv`][ermrl.runner.stage_argv] adds them to the printed command line (``line``, which
    the study or the test folder keeps).
    """
    prog = f"ermrl {step.command}"
    request = with_run_options(
        step.request,
        quiet=quiet_stages,
        progress=progress if step.stage in PROGRESS_STAGES else None,  # type: ignore[arg-type]
        tensorboard=(
            str(Path(tensorboard) / step.label / step.stage)
            if tensorboard is not None and step.command in TENSORBOARD_COMMANDS
            else None
        ),
        wandb=wandb if step.command in WANDB_COMMANDS else None,
        command=line,
    )
    return run_request(request, prog)


def run_request(request: Any, prog: str) -> int:
    """Run a planned stage's request; its one-line error on stderr, its exit code back."""
    runs: dict[type, Callable[[Any, str], int]] = {
        EvolveRequest: run_evolve,
        TestRequest: run_test,
        TestGeneralizationRequest: run_test_generalization,
        ReportRequest: run_report,
    }
    if isinstance(request, EvolveRequest) and request.config.generalization is not None:
        runs[EvolveRequest] = run_evolve_generalization
    quiet_libraries()
    return exit_code(prog, lambda: runs[type(request)](request, prog))


def results_lines(steps: Sequence[Step]) -> list[str]:
    """What a rerun that skipped finished steps shows again: each skipped test phase's summary
    table (its ``summary.csv``) and each skipped report's path. Nothing for other steps."""
    import pandas as pd

    lines: list[str] = []
    for step in steps:
        if step.folder is None:
            continue
        if step.stage == "test" and (step.folder / "summary.csv").is_file():
            try:
                table = pd.read_csv(step.folder / "summary.csv")
            except (OSError, ValueError, pd.errors.ParserError):
                continue  # a damaged table: the test stage's own rerun says so
            lines.append(f"results of {step.label}: {step.folder / 'summary.csv'}")
            lines += ["  " + row for row in table.to_string(index=False).splitlines()]
        elif step.stage == "report":
            for name in ("report.html", "report.md"):
                if (step.folder / name).is_file():
                    lines.append(f"report of {step.label}: {step.folder / name}")
                    break
    return lines
