"""``ermrl run EXPERIMENT.yaml``: a whole experiment (evolve, re-evaluate, test, report) in one file.

The file composes ermrl's own commands (see [`ermrl.runner`][ermrl.runner]); this module only parses
the command line, prints the plan and turns the runner's errors into one line and an exit code.
"""

from __future__ import annotations

import sys
import textwrap
from collections.abc import Sequence

from ermrl._interrupt import interruption
from ermrl._progress import PROGRESS_MODES
from ermrl.cli._common import fail
from ermrl.runner._options import ArgumentParser, HelpFormatter
from ermrl.runner._run import DEFAULT_SNAPSHOT_EVERY, STAGE_CHOICES

__all__ = ["build_run_parser", "run_main"]

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
    A test phase too long for one sitting runs in pieces: --stage test with --agents and/or
    --seeds trains only those runs, and publishes them as they finish (with `publish:`).

    examples:
      ermrl run experiments/paper/h2_locomotion.yaml --dry-run
      ermrl run experiments/paper/h2_locomotion.yaml --task Swimmer-v5
      ermrl run experiments/paper/h1_partial_observability.yaml --variant quick
      ermrl run experiments/paper/h3_generalization.yaml --stage evolve   # one worker
      ermrl run experiments/paper/h2_locomotion.yaml --task Ant-v5 --stage test \\
          --agents res-ppo leaky-res-ppo   # a piece of the test phase
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
        "--agents",
        nargs="+",
        default=None,
        metavar="AGENT",
        help="with --stage test: train only these of the test stage's agents, a piece of a "
        "phase too long for one sitting (the rest runs later, from the same command with "
        "other agents or none)",
    )
    parser.add_argument(
        "--seeds",
        nargs="+",
        type=int,
        default=None,
        metavar="SEED",
        help="with --stage test: train only these of the test stage's seeds",
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
        "DIR/<task>/evolve (its --tensorboard) and each test phase under DIR/<task>/test, on "
        "either backend (needs: pip install tensorboard)",
    )
    parser.add_argument(
        "--wandb",
        default=None,
        metavar="PROJECT",
        help="also log to the Weights & Biases project PROJECT: each evolution's trials and each "
        "single-task test phase's runs (the --wandb of evolve and test; a test phase then "
        "trains with the sb3 backend; WANDB_MODE=offline logs locally; needs: pip install "
        "'ermrl[wandb]')",
    )
    parser.add_argument("--quiet", action="store_true", help="no plan and no progress lines")
    return parser


def run_main(argv: Sequence[str] | None = None, prog: str = "ermrl run") -> int:
    """Entry point of ``ermrl run``."""
    from ermrl.cli._common import quiet_libraries
    from ermrl.runner._experiment import ExperimentError, load_experiment
    from ermrl.runner._run import (
        StageFailed,
        StageInterrupted,
        check_test_piece,
        choose_stages,
        plan_experiment,
        plan_lines,
        run_plan,
        write_snapshot_files_verbose,
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
        check_test_piece(args.stage, args.agents or (), args.seeds or ())
        exp, steps, statuses = plan_experiment(
            load_experiment(args.file, args.variant),
            tasks=args.task,
            tensorboard=bool(args.tensorboard),
            wandb=bool(args.wandb),
            build_agents=not args.dry_run,
            test_agents=args.agents or (),
            test_seeds=args.seeds or (),
        )
    except (ExperimentError, StorageError) as err:
        fail(prog, str(err))
    if args.snapshot:
        try:
            write_snapshot_files_verbose(exp, steps, sys.stdout)
        except OSError as err:
            fail(prog, f"cannot write the snapshot: {err.strerror or err}")
        return 0
    chosen = choose_stages(steps, statuses, args.stage)
    if not args.quiet or args.dry_run:
        for line in plan_lines(exp, chosen):
            print(line, flush=True)
    if args.dry_run:
        return 0
    try:
        run_plan(
            exp,
            steps,
            chosen,
            progress=args.progress,
            tensorboard=args.tensorboard,
            wandb=args.wandb,
            snapshot_every=args.snapshot_every,
            quiet=args.quiet,
            stream=sys.stdout,
        )
    except StageFailed as err:
        print(f"{prog}: {err}; rerun the same command to resume", file=sys.stderr)
        return err.code
    except StageInterrupted as err:
        what, code = interruption(err)
        print(f"{prog}: {what}; rerun the same command to resume", file=sys.stderr)
        return code
    except ExperimentError as err:
        fail(prog, str(err))
    return 0
