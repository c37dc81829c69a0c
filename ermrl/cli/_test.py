"""``ermrl test`` / ``test.py``: train the best evolved reservoir against baselines."""

from __future__ import annotations

import argparse
import shlex
import sys
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from ermrl.cli._common import (
    ArgumentParser,
    HelpFormatter,
    add_for_learner_arg,
    add_progress_arg,
    add_stale_gradient_arg,
    add_storage_args,
    exit_on_failure,
    nonneg_int,
    positive_int,
    quiet_libraries,
)
from ermrl.learners import AGENT_KINDS
from ermrl.runner import _commands
from ermrl.runner._commands import print_notes, setup_errors
from ermrl.runner._resolve import test_options

if TYPE_CHECKING:
    from ermrl.test_phase import TestPlan

T = TypeVar("T")

__all__ = [
    "add_tensorboard_arg",
    "add_test_args",
    "build_test_parser",
    "print_notes",
    "require_tensorboard",
    "run_or_exit",
    "run_test_phase",
    "setup_errors",
    "test_main",
    "test_options",
]

DESCRIPTION = textwrap.dedent(
    """\
    Test phase: train PPO (ppo), PPO on the full, unmasked observation (ppo-full), PPO on the
    best evolved reservoir (res-ppo) and PPO on an unevolved reservoir (random-res-ppo) on every
    seed, and write curves.csv, summary.csv, learning_curves.png, the models, config.yaml and
    command.txt to --out.

    The env, observation mask, encoding and PPO settings come from the study. When
    SLURM_ARRAY_TASK_ID is set, it selects one seed of the list (task i -> i-th seed). Finished
    runs are kept: re-running with the same settings resumes, and array tasks sharing --out
    merge their results. Each run records its settings (settings.json); a rerun into the same
    --out with other settings (--ppo, --trial, --training-steps, ...) is refused: use
    another --out, or --overwrite to retrain. --eval is not a training setting: it adds
    deterministic evaluation episodes to the runs it trains, beside runs made without them.

    The settings of each agent are its learner's table (ermrl/data/<learner>.yml), then --ppo
    (every agent), then the flags of its learner only (--for-learner, --stale-gradient). A
    setting other learners refuse, such as the dagger learner's expert, goes in --for-learner.

    examples:
      ermrl test --study-name S --storage sqlite:///ermrl.db --training-steps 1000000 --seeds 10 11 12
      ermrl test --study-name S --agents ppo dagger res-dagger --for-learner dagger expert=experts/hopper
    """
)


def add_test_args(
    parser: argparse.ArgumentParser, *, out_help: str, trial_help: str, ppo_help: str
) -> None:
    """Add the test-phase options shared by ``ermrl test`` and ``ermrl test-generalization``.

    Adds, in this order: ``--training-steps``, ``--seeds``, ``--agents``, ``--out``, ``--trial``,
    ``--n-procs``, ``--eval/--no-eval``, ``--n-eval-episodes``, ``--ppo``,
    ``--stale-gradient/--no-stale-gradient``, ``--for-learner``, ``--backend``,
    ``--save-models/--no-save-models`` and ``--overwrite``.

    Args:
        parser: the command's parser.
        out_help: help of ``--out`` (each command has its own default folder).
        trial_help: help of ``--trial`` (one reservoir or several).
        ppo_help: help of ``--ppo`` (the PPO settings the overrides go on top of).
    """
    parser.add_argument(
        "--training-steps",
        type=positive_int,
        default=1_000_000,
        help="env steps per run (paper: 1000000)",
    )
    parser.add_argument(
        "--seeds",
        nargs="+",
        type=nonneg_int,
        default=None,
        help="test seeds (default: 5 seeds after the largest seed evolution trained on)",
    )
    parser.add_argument(
        "--agents",
        nargs="+",
        choices=tuple(AGENT_KINDS),
        default=None,
        help="agents to train (default: "
        + ", ".join(n for n, k in AGENT_KINDS.items() if k.default)
        + "; ppo-full only when the mask hides something, since on the full observation it "
        "would repeat ppo): "
        + "; ".join(f"{name}: {kind.description}" for name, kind in AGENT_KINDS.items()),
    )
    parser.add_argument("--out", default=None, help=out_help)
    parser.add_argument("--trial", type=nonneg_int, default=None, help=trial_help)
    parser.add_argument(
        "--n-procs",
        type=positive_int,
        default=1,
        help="cores for the runs, trained in parallel single-threaded processes",
    )
    parser.add_argument(
        "--eval",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="also run deterministic evaluation episodes after training",
    )
    parser.add_argument(
        "--n-eval-episodes", type=positive_int, default=10, help="evaluation episodes with --eval"
    )
    parser.add_argument("--ppo", nargs="+", default=[], metavar="KEY=VALUE", help=ppo_help)
    add_stale_gradient_arg(parser)
    add_for_learner_arg(parser)
    parser.add_argument(
        "--backend",
        choices=("population", "sb3"),
        default=None,
        help="what trains the agents of the study's learner: population (all seeds of an agent "
        "trained in lockstep, PPO only) or sb3 (the reference implementation: one "
        "Stable-Baselines3 process per run). Default: the study's backend when it was evolved "
        "with sb3, else population where it applies (not with --wandb, nor into an --out "
        "whose finished runs were made with sb3), else sb3, with one line saying why. Agents "
        "with another learner always train with sb3",
    )
    parser.add_argument(
        "--save-models",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="save each trained model as model.zip",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="retrain the asked-for runs that already have results (a rerun into an --out "
        "whose runs were made with other settings is refused without it)",
    )
    parser.add_argument(
        "--checkpoint-every",
        type=nonneg_int,
        default=None,
        metavar="STEPS",
        help="runs save their training state every STEPS steps per run, and a rerun after a "
        "kill or crash resumes them from there (weights, optimizer, normalization, episodes so "
        "far; the environments restart from fresh episodes): population runs in "
        "OUT/checkpoints, runs of on-policy sb3 learners (ppo, lstm-ppo, framestack-ppo, "
        "rtu-ppo) in their run folder; other learners restart. Default: a tenth of "
        "--training-steps; 0: no checkpoints",
    )


def build_test_parser(prog: str = "ermrl test") -> ArgumentParser:
    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    add_storage_args(parser, study_required=True)
    add_test_args(
        parser,
        out_help="output folder (default: runs/<study name>)",
        trial_help="test this trial's reservoir instead of the best one",
        ppo_help="PPO overrides on top of the study's, e.g. --ppo learning_rate=1e-4",
    )
    add_tensorboard_arg(parser)
    parser.add_argument(
        "--wandb",
        default=None,
        metavar="PROJECT",
        help="also log each run to the Weights & Biases project PROJECT (wandb's SB3 callback; "
        "the runs of one test folder form a group; WANDB_MODE=offline logs locally; "
        "needs: pip install 'ermrl[wandb]')",
    )
    add_progress_arg(parser, inside="", finished="run")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


def run_or_exit(prog: str, out: Path, run: Callable[[], T]) -> T | None:
    """:func:`ermrl.runner._commands.run_or_fail`, its one-line errors exiting with code 2
    (a signal's code after its line)."""
    return exit_on_failure(prog, lambda: _commands.run_or_fail(prog, out, run))


def run_test_phase(
    prog: str,
    args: argparse.Namespace,
    plan: TestPlan,
    task: Any,
    encoder: Any,
    ppo: Any,
    metadata: dict[str, Any],
    *,
    then: Callable[[Any], Any] | None = None,
) -> Any:
    """:func:`ermrl.runner._commands.run_test_phase` with the parsed options' ``--quiet`` and
    command line, its one-line errors exiting with code 2."""
    return exit_on_failure(
        prog,
        lambda: _commands.run_test_phase(
            *(prog, plan, task, encoder, ppo, metadata),
            quiet=args.quiet,
            command=getattr(args, "command_line", None),
            then=then,
        ),
    )


def add_tensorboard_arg(parser: argparse.ArgumentParser) -> None:
    """``--tensorboard DIR`` of the test-phase commands (on either backend)."""
    parser.add_argument(
        "--tensorboard",
        default=None,
        metavar="DIR",
        help="also log training curves for TensorBoard under DIR/<agent>/seed_<s>: the scalars "
        "SB3's PPO logs (returns, losses, fps), on either backend (needs: pip install "
        "tensorboard)",
    )


def require_tensorboard(args: argparse.Namespace, prog: str) -> None:
    """Exit 2 in one line when ``--tensorboard`` is given without the tensorboard package."""
    exit_on_failure(prog, lambda: _commands.require_tensorboard(getattr(args, "tensorboard", None)))


def test_main(argv: Sequence[str] | None = None, prog: str = "ermrl test") -> int:
    """Entry point of ``ermrl test`` and ``test.py``."""
    parser = build_test_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    # The command that made the test folder (command.txt): `ermrl test ...` also when `ermrl
    # run` runs this stage.
    command = shlex.join([*prog.split(), *(sys.argv[1:] if argv is None else argv)])
    require_tensorboard(args, prog)
    if args.wandb:
        exit_on_failure(prog, lambda: _commands.check_wandb(args.wandb))
    request = _commands.TestRequest(
        args.study_name, args.storage, test_options(args), args.quiet, command
    )
    return exit_on_failure(prog, lambda: _commands.run_test(request, prog))
