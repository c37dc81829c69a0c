"""``ermrl run EXPERIMENT.yaml``: a whole experiment (evolve, re-evaluate, test, report) in one file.

The file composes ermrl's own commands (see :mod:`ermrl.cli._experiment`); this module only
prints the plan, writes the resolved configuration and runs the unfinished steps in order.
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path

from ermrl._interrupt import interruption
from ermrl._progress import PROGRESS_MODES
from ermrl._text import plural
from ermrl.cli._common import ArgumentParser, HelpFormatter, fail
from ermrl.cli._experiment import (
    PUBLISH_MAX_BYTES,
    Experiment,
    PeriodicSnapshots,
    Step,
    publish_step,
    snapshot_status,
)

__all__ = ["build_run_parser", "run_main"]

STAGE_CHOICES = ("evolve", "reevaluate", "test", "report")
# How often a run with `publish:` writes its snapshot by itself (seconds).
DEFAULT_SNAPSHOT_EVERY = 600.0
# The stages whose commands take --progress (each evolve and test command does).
PROGRESS_STAGES = ("evolve", "test")
# The commands that take --tensorboard.
TENSORBOARD_COMMANDS = ("evolve", "evolve-generalization", "test", "test-generalization")

DESCRIPTION = textwrap.dedent(
    """\
    Run a whole experiment described by one YAML file: evolution (one study per task, or one
    over a task set), re-evaluation of the best candidates on fresh seeds, the test phase
    against baselines, and the report. Each stage runs the ermrl command of the same name with
    the options the file gives it.

    The plan (each command, its env steps and an estimated wall time) is printed first. Running
    the file again skips the finished stages and resumes an interrupted one: the study and the
    run folders are the state. Workers started with --stage evolve (SLURM array tasks, say)
    share the studies; the later stages then run once, from one more `ermrl run FILE`.

    examples:
      ermrl run experiments/paper/h2_locomotion.yaml --dry-run
      ermrl run experiments/paper/h2_locomotion.yaml --task Swimmer-v5
      ermrl run experiments/paper/h1_partial_observability.yaml --variant quick
      ermrl run experiments/paper/h3_generalization.yaml --stage evolve   # one worker
    """
)


def build_run_parser(prog: str = "ermrl run") -> ArgumentParser:
    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    parser.add_argument("file", metavar="EXPERIMENT.yaml", help="the experiment file")
    parser.add_argument(
        "--variant",
        default=None,
        help="apply this entry of the file's `variants` (e.g. quick); its results go to "
        "<out>/<variant>",
    )
    parser.add_argument(
        "--task",
        nargs="+",
        default=None,
        metavar="ENV_ID",
        help="only these tasks (for a generalization experiment: these test tasks); a task "
        "the file does not list runs with the file's settings",
    )
    parser.add_argument(
        "--stage",
        nargs="+",
        choices=STAGE_CHOICES,
        default=None,
        help="only these stages (default: all, in order)",
    )
    parser.add_argument(
        "--dry-run",
        action="store_true",
        help="print the plan (commands, env steps, estimated wall time, what is done) and stop",
    )
    parser.add_argument(
        "--snapshot",
        action="store_true",
        help="write each evolution study as one plain JSON file, <publish or out>/<task>/"
        "study.json, and the finished test runs' plain files to <publish>/<task>/test/, and "
        "stop (commit them: a later `ermrl run` on another machine imports the study, puts "
        "the runs back, and resumes where it stopped)",
    )
    parser.add_argument(
        "--snapshot-every",
        type=float,
        default=DEFAULT_SNAPSHOT_EVERY,
        metavar="SECONDS",
        help="while it runs, write the snapshot of --snapshot every SECONDS (0: never), so a "
        "machine or sitting that ends loses at most that much finished work; only for a file "
        "with `publish:` (the snapshot is also written when an evolution ends)",
    )
    parser.add_argument(
        "--progress",
        choices=PROGRESS_MODES,
        default=None,
        help="progress inside the evolve and test stages, passed to their commands (bar: a live "
        "bar per run; lines: a line per run every tenth of its steps or 30 s; none: a line per "
        "finished trial or run only); default: a `progress` the file gives the stage, else bar "
        "when stdout is a terminal and lines otherwise",
    )
    parser.add_argument(
        "--tensorboard",
        default=None,
        metavar="DIR",
        help="also log training curves for TensorBoard: each evolution's trials under "
        "DIR/<task>/evolve (its --tensorboard) and each test phase under DIR/<task>/test; "
        "those stages then train with the sb3 backend (needs: pip install "
        "tensorboard)",
    )
    parser.add_argument("--quiet", action="store_true", help="no plan and no progress lines")
    return parser


def stage_argv(step: Step, progress: str | None, tensorboard: str | None) -> list[str]:
    """A step's arguments with ``ermrl run``'s own ``--progress`` and ``--tensorboard`` added
    (the last of a repeated option wins over the file's).

    ``--tensorboard DIR`` goes to the evolve commands (``DIR/<label>/evolve``) and to ``ermrl
    test`` (``DIR/<label>/test``); ``test-generalization`` takes none.
    """
    argv = list(step.argv)
    if progress is not None and step.stage in PROGRESS_STAGES:
        argv += ["--progress", progress]
    if tensorboard is not None and step.command in TENSORBOARD_COMMANDS:
        argv += ["--tensorboard", str(Path(tensorboard) / step.label / step.stage)]
    return argv


def _plan_lines(
    exp: Experiment, steps: Sequence[Step], statuses: Sequence[tuple[bool, float, str]]
) -> list[str]:
    from ermrl.cli._experiment import format_duration

    head = f"experiment {exp.name!r}" + (f" (variant {exp.variant})" if exp.variant else "")
    lines = [
        f"{head} from {exp.path}",
        f"  storage {exp.storage}; results {exp.out}"
        + (f"; published to {exp.publish}" if exp.publish else ""),
    ]
    total_steps = 0
    total_seconds = 0.0
    left_seconds = 0.0
    for index, (step, (done, left, text)) in enumerate(zip(steps, statuses), start=1):
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
        total_steps += step.env_steps
        total_seconds += step.seconds
        left_seconds += 0.0 if done else step.seconds * left
    lines.append(
        f"  total {total_steps / 1e6:.4g}M env steps, ~{format_duration(total_seconds)} on 2 cores; "
        f"left ~{format_duration(left_seconds)} (estimates from ermrl/data/throughput.yml)"
    )
    return lines


def _status(exp: Experiment, step: Step) -> tuple[bool, float, str]:
    """A step's status; for an evolution the storage lacks, what its snapshot holds."""
    done, left, text = step.status()
    if step.stage == "evolve" and text == "not started":
        from_snapshot = snapshot_status(exp, step)
        if from_snapshot is not None:
            left, text = from_snapshot
    return done, left, text


def _run_steps(exp: Experiment, chosen: Sequence[Step], args: argparse.Namespace, prog: str) -> int:
    """Run the unfinished steps in order; the exit code of the first that stops, else 0."""
    from ermrl.cli import COMMANDS, _load
    from ermrl.cli._experiment import publish_finished_runs, write_snapshots

    for step in chosen:
        done, _, text = step.status()
        if done:
            if not args.quiet:
                print(f"[{step.stage} {step.label}] done ({text}): skipped", flush=True)
            continue
        argv = stage_argv(step, args.progress, args.tensorboard)
        if not args.quiet:
            line = shlex.join(["ermrl", step.command, *argv])
            print(f"[{step.stage} {step.label}] {line}", flush=True)
        run = _load(COMMANDS[step.command][0])
        try:
            code = int(run(argv, prog=f"ermrl {step.command}") or 0)
        except SystemExit as err:
            code = err.code if isinstance(err.code, int) else 1
        except KeyboardInterrupt as err:
            publish_finished_runs(exp, step)
            what, code = interruption(err)
            print(f"{prog}: {what}; rerun the same command to resume", file=sys.stderr)
            return code
        if code != 0:
            publish_finished_runs(exp, step)
            print(
                f"{prog}: stage {step.stage} of {step.label} stopped (exit code {code}); "
                "rerun the same command to resume",
                file=sys.stderr,
            )
            return code
        if exp.publish is not None and step.stage in ("test", "report"):
            _, left_out = publish_step(exp, step)
            for path in left_out:
                print(
                    f"not published: {path} ({path.stat().st_size / 2**20:.1f} MiB, over "
                    f"{PUBLISH_MAX_BYTES / 2**20:.0f} MiB); it stays in {exp.out}",
                    flush=True,
                )
        if exp.publish is not None and step.stage == "evolve":
            write_snapshots(exp, [step])
    return 0


def run_main(argv: Sequence[str] | None = None, prog: str = "ermrl run") -> int:
    """Entry point of ``ermrl run``."""
    from ermrl.cli._common import quiet_libraries
    from ermrl.cli._experiment import (
        ExperimentError,
        experiment_plan,
        load_experiment,
        publish_finished_runs,
        write_snapshots,
    )
    from ermrl.storage import StorageError

    parser = build_run_parser(prog)
    args = parser.parse_args(argv)
    if not args.snapshot_every >= 0:
        fail(
            prog,
            f"--snapshot-every must be 0 (never) or a number of seconds, not {args.snapshot_every}",
        )
    quiet_libraries()
    try:
        exp = load_experiment(args.file, args.variant)
        exp = dataclasses.replace(exp, tensorboard=bool(args.tensorboard))
        steps = experiment_plan(exp, tasks=args.task, build_agents=not args.dry_run)
        statuses = [_status(exp, step) for step in steps]
    except (ExperimentError, StorageError) as err:
        fail(prog, str(err))
    if args.snapshot:
        try:
            for step, path, n in write_snapshots(exp, steps):
                print(f"wrote {path}: study {step.study_name!r}, {plural(n, 'trial')}", flush=True)
            for step in steps:
                n = publish_finished_runs(exp, step)
                if n:
                    print(
                        f"published {plural(n, 'finished test run')} of {step.label} to "
                        f"{exp.publish}/{step.label}/test",
                        flush=True,
                    )
        except OSError as err:
            fail(prog, f"cannot write the snapshot: {err.strerror or err}")
        return 0
    if args.stage:
        keep = set(args.stage)
        chosen = [(s, st) for s, st in zip(steps, statuses) if s.stage in keep]
    else:
        chosen = list(zip(steps, statuses))
    if not args.quiet or args.dry_run:
        for line in _plan_lines(exp, [s for s, _ in chosen], [st for _, st in chosen]):
            print(line, flush=True)
    if args.dry_run:
        return 0
    resolved_file = exp.out / "experiment.resolved.yaml"
    # What this run creates, removed again when it fails before any stage wrote a thing.
    created = [p for p in (resolved_file, exp.out, *exp.out.parents) if not p.exists()]
    try:
        code = _write_and_run(exp, steps, chosen, args, prog)
    except BaseException:
        _remove_if_untouched(created)
        raise
    if code != 0:
        _remove_if_untouched(created)
    return code


def _remove_if_untouched(created: Sequence[Path]) -> None:
    """Remove what a failed run created (the resolved file, then its folders) if no stage
    wrote anything beside it: a folder is removed only when empty."""
    import contextlib

    if not created or created[0].name != "experiment.resolved.yaml":
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
    exp: Experiment,
    steps: Sequence[Step],
    chosen: Sequence[tuple[Step, object]],
    args: argparse.Namespace,
    prog: str,
) -> int:
    """Write the resolved configuration, bring back published state, and run the steps."""
    import yaml

    from ermrl._io import write_atomic
    from ermrl.cli._experiment import (
        ExperimentError,
        import_snapshots,
        resolved_document,
        restore_finished_runs,
    )

    try:
        resolved = resolved_document(exp, steps)
        write_atomic(
            exp.out / "experiment.resolved.yaml",
            "# ermrl run: the experiment as run, every command's options filled in\n"
            + yaml.safe_dump(resolved, sort_keys=False, width=100),
        )
    except OSError as err:
        fail(prog, f"cannot write {exp.out}: {err.strerror or err}")
    try:
        for step, path, n in import_snapshots(exp, steps):
            print(f"imported {path}: study {step.study_name!r}, {plural(n, 'trial')}", flush=True)
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
                    flush=True,
                )
    except ExperimentError as err:
        fail(prog, str(err))
    except OSError as err:
        fail(prog, f"cannot restore the published test runs: {err.strerror or err}")
    with PeriodicSnapshots(exp, steps, args.snapshot_every):
        code = _run_steps(exp, [step for step, _ in chosen], args, prog)
    if code != 0:
        return code
    if not args.quiet:
        print(
            f"done: experiment {exp.name!r}; resolved configuration in {exp.out}/experiment.resolved.yaml",
            flush=True,
        )
    return 0
