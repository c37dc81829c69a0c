"""``ermrl test`` / ``test.py``: train the best evolved reservoir against baselines."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import textwrap
import warnings
from collections.abc import Sequence
from pathlib import Path

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
from ermrl.config import ConfigError

__all__ = ["add_test_args", "build_test_parser", "test_main", "select_seeds"]

DESCRIPTION = textwrap.dedent(
    """\
    Test phase: train PPO, PPO on the best evolved reservoir (res-ppo) and PPO on an unevolved
    reservoir (random-res-ppo) on every seed, and write curves.csv, summary.csv,
    learning_curves.png, the models, config.yaml and command.txt to --out.

    The env, observation mask, encoding and PPO settings come from the study. When
    SLURM_ARRAY_TASK_ID is set, it selects one seed of the list (task i -> i-th seed). Finished
    runs are kept: re-running resumes, and array tasks sharing --out merge their results.

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
        choices=("ppo", "res-ppo", "random-res-ppo"),
        default=["ppo", "res-ppo", "random-res-ppo"],
        help="agents to train",
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
        "--overwrite", action="store_true", help="retrain runs that already have results"
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


def test_main(argv: Sequence[str] | None = None, prog: str = "ermrl test") -> int:
    """Entry point of ``ermrl test`` and ``test.py``."""
    from ermrl.agents import parse_overrides
    from ermrl.experiments import (
        AgentSpec,
        TestSettings,
        default_test_seeds,
        run_comparison,
        study_reservoirs,
    )
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
        agents = []
        params: dict[str, float] = {}
        trial_number = None
        if "res-ppo" in args.agents:
            params, reservoirs, trial_number = study_reservoirs(study, config, args.trial)
        for name in args.agents:
            if name == "ppo":
                agents.append(AgentSpec("ppo", None))
            elif name == "res-ppo":
                agents.append(AgentSpec("res-ppo", reservoirs))
            else:
                agents.append(AgentSpec("random-res-ppo", config.space.default_reservoirs()))
        overrides = parse_overrides(args.ppo)
        ppo = dataclasses.replace(problem.ppo, hyperparams={**problem.ppo.hyperparams, **overrides})
        out = Path(args.out) if args.out else Path("runs") / args.study_name
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
    except (ConfigError, StorageError, StudyNotFound) as err:
        fail(prog, str(err))
    if not args.quiet:
        best = (
            f"trial {trial_number} ({', '.join(f'{k}={v:.3g}' for k, v in params.items())})"
            if trial_number is not None
            else "-"
        )
        print(
            f"test phase of {args.study_name!r}: {problem.task.label}, agents {' '.join(args.agents)}, "
            f"seeds {' '.join(map(str, seeds))}, {args.training_steps} steps each; reservoir: {best}; out: {out}",
            flush=True,
        )
    metadata = {
        "study_name": args.study_name,
        "storage": args.storage,
        "trial": trial_number,
        "params": params,
    }
    try:
        summary = run_comparison(
            problem.task,
            problem.encoder,
            ppo,
            agents,
            settings,
            metadata=metadata,
            quiet=args.quiet,
        )
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; finished runs are kept in {out}", file=sys.stderr)
        return EXIT_INTERRUPTED
    if not args.quiet:
        print(
            summary.drop(columns=["seeds"]).to_string(
                index=False, float_format=lambda v: f"{v:.4g}"
            )
        )
        print(f"wrote {out}/summary.csv, curves.csv, learning_curves.png", flush=True)
    return 0
