"""``ermrl test`` / ``test.py``: train the best evolved reservoir against baselines."""

from __future__ import annotations

import argparse
import os
import sys
import textwrap
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from ermrl.cli._common import (
    EXIT_INTERRUPTED,
    ArgumentParser,
    HelpFormatter,
    add_storage_args,
    fail,
    nonneg_int,
    positive_int,
    quiet_libraries,
)
from ermrl.config import AGENT_KINDS, AGENTS, ConfigError, default_agents

T = TypeVar("T")

__all__ = ["add_test_args", "build_test_parser", "run_or_exit", "test_main", "select_seeds"]

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
    --out with other settings (--ppo, --trial, --training-steps, --eval, ...) is refused: use
    another --out, or --overwrite to retrain.

    example:
      test.py --study-name S --storage sqlite:///ermrl.db --training-steps 1000000 --seeds 10 11 12
    """
)


def add_test_args(
    parser: argparse.ArgumentParser, *, out_help: str, trial_help: str, ppo_help: str
) -> None:
    """Add the test-phase options shared by ``ermrl test`` and ``ermrl test-generalization``.

    Adds, in this order: ``--training-steps``, ``--seeds``, ``--agents``, ``--out``, ``--trial``,
    ``--n-procs``, ``--eval/--no-eval``, ``--n-eval-episodes``, ``--ppo``,
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
        choices=AGENTS,
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


def build_test_parser(prog: str = "ermrl test") -> ArgumentParser:
    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    add_storage_args(parser, study_required=True)
    add_test_args(
        parser,
        out_help="output folder (default: runs/<study name>)",
        trial_help="test this trial's reservoir instead of the best one",
        ppo_help="PPO overrides on top of the study's, e.g. --ppo learning_rate=1e-4",
    )
    parser.add_argument(
        "--tensorboard",
        default=None,
        metavar="DIR",
        help="also log training curves for TensorBoard under DIR/<agent>/seed_<s> "
        "(needs: pip install tensorboard)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


def select_seeds(seeds: Sequence[int], task_id: str | None) -> tuple[int, ...]:
    """The seeds this process runs: all, or the ``task_id``-th under a SLURM array.

    Raises:
        ConfigError: the task id is not an index of ``seeds``.
    """
    if task_id is None or task_id == "":
        return tuple(seeds)
    try:
        index = int(task_id)
    except ValueError as err:
        raise ConfigError(f"SLURM_ARRAY_TASK_ID={task_id!r} is not an integer") from err
    if not 0 <= index < len(seeds):
        raise ConfigError(
            f"SLURM_ARRAY_TASK_ID={index} has no seed: {len(seeds)} seeds given "
            f"({' '.join(map(str, seeds))}); submit --array=0-{len(seeds) - 1}"
        )
    return (seeds[index],)


def run_or_exit(prog: str, out: Path, run: Callable[[], T]) -> T | None:
    """Run a test phase; its expected failures become one line on stderr.

    Shared by ``ermrl test`` and ``ermrl test-generalization``.

    Args:
        prog: program name that starts the error line.
        out: the output folder (named in the messages).
        run: the test phase.

    Returns:
        What ``run`` returned, or ``None`` after Ctrl-C (finished runs are kept; the caller
        exits with ``EXIT_INTERRUPTED``).

    Raises:
        SystemExit: exit code 2 when ``--out`` holds runs made with other settings, when a run
            ends no episode or diverges, or when a full disk, a quota or a read-only folder
            stops a write.
    """
    from ermrl.agents import NoEpisodeFinished, TrainingDiverged
    from ermrl.experiments._test_phase import WRITE_ERRNOS, write_error_message

    try:
        return run()
    except ConfigError as err:  # --out holds runs made with other settings
        fail(prog, str(err))
    except (NoEpisodeFinished, TrainingDiverged) as err:  # a run could not be measured
        fail(prog, f"{err}; finished runs are kept in {out}")
    except OSError as err:  # a full disk, a quota, a read-only folder
        if err.errno not in WRITE_ERRNOS:
            raise
        fail(prog, write_error_message(err, out))
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; finished runs are kept in {out}", file=sys.stderr)
        return None


def test_main(argv: Sequence[str] | None = None, prog: str = "ermrl test") -> int:
    """Entry point of ``ermrl test`` and ``test.py``."""
    from ermrl.agents import check_ppo_config, parse_overrides, with_overrides
    from ermrl.envs import UnknownEnvError, UnsupportedObserveError
    from ermrl.experiments import (
        TestSettings,
        default_test_seeds,
        describe_selection,
        learner_settings_for,
        run_comparison,
        selection_metadata,
        study_agents,
    )
    from ermrl.experiments._test_phase import check_out_folder
    from ermrl.search import study_config
    from ermrl.storage import StorageError, StudyNotFound, load_study

    parser = build_test_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    if args.tensorboard:
        import importlib.util

        if importlib.util.find_spec("tensorboard") is None:
            fail(
                prog,
                "--tensorboard needs the tensorboard package, which is not installed "
                "(pip install tensorboard)",
            )
    try:
        study = load_study(args.study_name, args.storage)
        config = study_config(study)
        if getattr(config, "generalization", None) is not None:
            raise ConfigError(
                f"study {args.study_name!r} evolved on several tasks; test it on an unseen task "
                "with test_generalization.py --env-id ENV"
            )
        problem = config.problem
        seeds = tuple(args.seeds) if args.seeds else default_test_seeds(problem.seeds)
        reused = sorted(set(seeds) & set(problem.seeds))
        if reused:
            warnings.warn(
                f"test seeds {reused} were also used by evolution; results on them are not "
                "independent of the selection",
                stacklevel=1,
            )
        seeds = select_seeds(seeds, os.environ.get("SLURM_ARRAY_TASK_ID"))
        args.agents = args.agents or list(default_agents(problem.task.observe))
        overrides = parse_overrides(args.ppo)
        ppo = with_overrides(problem.ppo, overrides)
        agents, chosen = study_agents(
            study,
            config,
            args.agents,
            args.trial,
            learner_settings_for(ppo, problem.task.env_id, overrides),
        )
        if overrides:  # refused now rather than by the first run
            check_ppo_config(problem.task, problem.encoder, ppo, where="--ppo")
        for agent in agents:
            if agent.ppo is not None and overrides:
                check_ppo_config(agent.task(problem.task), None, agent.ppo, where=agent.name)
        out = Path(args.out) if args.out else Path("runs") / args.study_name
        check_out_folder(out)
        settings = TestSettings(
            training_steps=args.training_steps,
            seeds=seeds,
            out=out,
            n_procs=args.n_procs,
            evaluate=args.eval,
            n_eval_episodes=args.n_eval_episodes,
            n_last_episodes=problem.budget.n_last_episodes,
            save_models=args.save_models,
            overwrite=args.overwrite,
            tensorboard=Path(args.tensorboard) if args.tensorboard else None,
        )
    except (
        ConfigError,
        StorageError,
        StudyNotFound,
        UnknownEnvError,
        UnsupportedObserveError,
    ) as err:
        fail(prog, str(err))
    if not args.quiet:
        best = describe_selection(chosen)
        print(
            f"test phase of {args.study_name!r}: {problem.task.label}, agents {' '.join(args.agents)}, "
            f"seeds {' '.join(map(str, seeds))}, {args.training_steps} steps each; reservoir: {best}; out: {out}",
            flush=True,
        )
    metadata = {
        "study_name": args.study_name,
        "storage": args.storage,
        **selection_metadata(chosen),
    }
    summary = run_or_exit(
        prog,
        out,
        lambda: run_comparison(
            problem.task,
            problem.encoder,
            ppo,
            agents,
            settings,
            metadata=metadata,
            quiet=args.quiet,
        ),
    )
    if summary is None:
        return EXIT_INTERRUPTED
    if not args.quiet:
        print(
            summary.drop(columns=["seeds"]).to_string(
                index=False, float_format=lambda v: f"{v:.4g}"
            )
        )
        print(f"wrote {out}/summary.csv, curves.csv, learning_curves.png", flush=True)
    return 0
