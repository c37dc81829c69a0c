"""``ermrl test`` / ``test.py``: train the best evolved reservoir against baselines."""

from __future__ import annotations

import argparse
import os
import sys
import textwrap
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from ermrl._interrupt import interruption
from ermrl.cli._common import (
    EXIT_INTERRUPTED,
    ArgumentParser,
    HelpFormatter,
    add_for_learner_arg,
    add_progress_arg,
    add_stale_gradient_arg,
    add_storage_args,
    fail,
    for_learner_names,
    learner_overrides,
    nonneg_int,
    positive_int,
    progress_mode,
    quiet_libraries,
)
from ermrl.config import ConfigError
from ermrl.learners import AGENT_KINDS, default_agents

T = TypeVar("T")

__all__ = [
    "TestPlan",
    "add_tensorboard_arg",
    "add_test_args",
    "agent_learners",
    "build_test_parser",
    "choose_agents",
    "plan_test_phase",
    "require_tensorboard",
    "run_or_exit",
    "run_test_phase",
    "select_seeds",
    "setup_errors",
    "test_main",
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
        "with sb3, else population where it applies (not with --tensorboard, nor into an --out "
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


# Files a test phase writes before its first run finishes: a folder holding only these (and
# empty folders) is a skeleton, removed when the command that created it fails.
_SKELETON_FILES = ("config.yaml", "command.txt")


def run_or_exit(prog: str, out: Path, run: Callable[[], T]) -> T | None:
    """:func:`_run_or_exit`, removing ``out`` again when this command created it and fails
    (an error, a crash, a signal) before it holds anything but its skeleton: no finished run,
    no checkpoint."""
    created = [p for p in (Path(out), *Path(out).parents) if not p.exists()]
    try:
        result = _run_or_exit(prog, out, run)
    except BaseException:
        _remove_skeleton(created)
        raise
    if result is None:  # interrupted
        _remove_skeleton(created)
    return result


def _remove_skeleton(created: Sequence[Path]) -> None:
    """Remove the folders of ``created`` (``out`` first, then the parents this created) when
    ``out`` holds no file other than :data:`_SKELETON_FILES`."""
    import contextlib
    import shutil

    if not created or not created[0].is_dir():
        return
    out = created[0]
    files = [p for p in out.rglob("*") if not p.is_dir()]
    if any(p.parent != out or p.name not in _SKELETON_FILES for p in files):
        return
    shutil.rmtree(out, ignore_errors=True)
    for folder in created[1:]:
        with contextlib.suppress(OSError):
            folder.rmdir()


def _run_or_exit(prog: str, out: Path, run: Callable[[], T]) -> T | None:
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
        SystemExit: exit code 2 when ``--out`` holds runs made with other settings or a damaged
            finished run, when a run
            ends no episode or diverges, or when a full disk, a quota or a read-only folder
            stops a write.
    """
    from ermrl.agents import NoEpisodeFinished, TrainingDiverged
    from ermrl.analysis import RunFolderError
    from ermrl.experiments._test_phase import WRITE_ERRNOS, write_error_message

    try:
        return run()
    except ConfigError as err:  # --out holds runs made with other settings
        fail(prog, str(err))
    except RunFolderError as err:  # a finished run in --out that would be kept is damaged
        fail(
            prog,
            f"{err}; move that run folder away, or rerun with --overwrite to retrain the "
            "runs asked for",
        )
    except (NoEpisodeFinished, TrainingDiverged) as err:  # a run could not be measured
        fail(prog, f"{err}; finished runs are kept in {out}")
    except OSError as err:  # a full disk, a quota, a read-only folder
        if err.errno not in WRITE_ERRNOS:
            raise
        fail(prog, write_error_message(err, out))
    except KeyboardInterrupt as err:
        what, code = interruption(err)
        print(f"{prog}: {what}; finished runs are kept in {out}", file=sys.stderr)
        if code != EXIT_INTERRUPTED:
            raise SystemExit(code) from None
        return None


def agent_learners(names: Sequence[str], study_learner: str) -> tuple[str, ...]:
    """The learners that train the agents ``names`` (``AGENT_KINDS``), each once.

    Args:
        names: Agent names.
        study_learner: The study's learner, which trains the agents of no learner of their own.
    """
    kinds = [AGENT_KINDS[n] for n in names if n in AGENT_KINDS]
    return tuple(dict.fromkeys(kind.learner or study_learner for kind in kinds))


def choose_agents(args: argparse.Namespace, config: Any, observe: str) -> list[str]:
    """``--agents`` (default: the study's default agents), checked against ``--for-learner``.

    Sets ``args.agents`` and returns it.

    Raises:
        ConfigError: a ``--for-learner`` names a learner that none of the agents trains with.
    """
    args.agents = args.agents or list(default_agents(observe, config.space.family))
    used = agent_learners(args.agents, config.problem.ppo.learner)
    for name in for_learner_names(args):
        if name not in used:
            raise ConfigError(
                f"--for-learner {name}: no agent of this run uses learner {name} (agents "
                f"{' '.join(args.agents)} use {', '.join(used)})"
            )
    return list(args.agents)


@dataclass
class TestPlan:
    """What a test phase trains: its agents, the selected trial, seeds and settings."""

    agents: list[Any]
    chosen: Any
    seeds: tuple[int, ...]
    settings: Any
    out: Path
    warning: str | None = None
    """A line for stderr before anything runs: the stored ranking is stale."""


def check_test_seeds(
    seeds: Sequence[int],
    evolution_seeds: Sequence[int],
    reevaluation_seeds: Sequence[int],
    study_name: str,
) -> None:
    """Refuse test seeds that evolution or the re-evaluation trained on: the selection saw
    them, so results on them are not independent of it.

    Args:
        seeds: The test seeds.
        evolution_seeds: The study's seeds.
        reevaluation_seeds: The seeds its re-evaluation used
            (:func:`~ermrl.search.used_reevaluation_seeds`).
        study_name: Named in the message.

    Raises:
        ConfigError: with the seeds that overlap, in one line.
    """
    used = [
        (what, sorted(set(seeds) & set(other)))
        for what, other in (
            ("evolution", evolution_seeds),
            (f"the re-evaluation ({study_name}.reeval)", reevaluation_seeds),
        )
    ]
    overlaps = [f"{found} by {what}" for what, found in used if found]
    if overlaps:
        raise ConfigError(
            f"test seeds already used to select the trial: {'; '.join(overlaps)}; results on them "
            "are not independent of the selection (omit --seeds for 5 unused ones)"
        )


def plan_test_phase(
    args: argparse.Namespace,
    study: Any,
    config: Any,
    task: Any,
    ppo: Any,
    default_out: Path,
    *,
    observe: str,
) -> TestPlan:
    """The part of ``ermrl test`` and ``ermrl test-generalization`` that is the same: seeds,
    agents (each with its learner's settings), checks of the settings and of ``--out``.

    Args:
        args: The parsed command line (``add_test_args``).
        study: The evolution study.
        config: Its configuration.
        task: The task the agents train on.
        ppo: The settings of the study's learner on that task (``--ppo`` applied).
        default_out: ``--out`` when not given.
        observe: The mask that decides the default agents.

    Raises:
        ConfigError: bad settings, test seeds evolution or the re-evaluation used, a bad
            ``--out``, or an agent that cannot be built.
    """
    from ermrl.agents import check_ppo_config, parse_overrides
    from ermrl.experiments import (
        TestSettings,
        default_test_seeds,
        learner_settings_for,
        study_agents,
    )
    from ermrl.experiments._test_phase import check_out_folder
    from ermrl.search import stale_ranking, used_reevaluation_seeds

    problem = config.problem
    seeds = tuple(args.seeds) if args.seeds else default_test_seeds(problem.seeds)
    check_test_seeds(seeds, problem.seeds, used_reevaluation_seeds(study), study.study_name)
    seeds = select_seeds(seeds, os.environ.get("SLURM_ARRAY_TASK_ID"))
    choose_agents(args, config, observe)
    overrides = parse_overrides(args.ppo)
    own = learner_overrides(args)
    agents, chosen = study_agents(
        study,
        config,
        args.agents,
        args.trial,
        learner_settings_for(ppo, task.env_id, overrides, own),
        ppo,
    )
    # An agent of another learner than the study's has settings no study checked (its table,
    # --ppo, --for-learner; dagger's expert): refused now rather than by its first run.
    for agent in agents:
        if agent.ppo is not None:
            check_ppo_config(agent.task(task), None, agent.ppo, where=agent.name)
    out = Path(args.out) if args.out else default_out
    check_out_folder(out)
    tensorboard = getattr(args, "tensorboard", None)
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
        tensorboard=Path(tensorboard) if tensorboard else None,
        wandb=getattr(args, "wandb", None),
        progress=progress_mode(args),
        checkpoint_every=args.checkpoint_every,
    )
    warning = None
    # Only when the ranking would have picked the trial: not with --trial, nor when no agent
    # uses the evolved trial (chosen is None).
    stale = None if chosen is None or args.trial is not None else stale_ranking(study)
    if chosen is not None and stale is not None:
        warning = (
            f"the re-evaluated ranking is stale and not used ({stale}); testing trial "
            f"{chosen.number}, the best evolution fitness (run the evolve command again to "
            "re-rank, or pass --trial N)"
        )
    return TestPlan(agents, chosen, seeds, settings, out, warning)


# What a test command reports as one line before anything runs.
def with_backend(
    ppo: Any,
    args: argparse.Namespace,
    *,
    task: Any = None,
    out: Path | None = None,
    notes: list[str] | None = None,
) -> Any:
    """The study's learner settings with the backend that trains its agents.

    ``--backend`` when given (checked for it). Left out: the study's own backend when it was
    evolved with sb3 (an existing study keeps the backend it was created with, so a study of
    an older ermrl tests to the same returns); otherwise population where it applies, unless
    ``out`` holds finished runs of this learner made with sb3 (a test folder never mixes
    backends; not with ``--overwrite``), else sb3.

    Args:
        ppo: The settings of the study's learner on the test task.
        args: The parsed command line (``--backend``, ``--tensorboard``, ``--overwrite``).
        task: The test task (its env's spaces are checked; ``None``: not checked).
        out: The test folder.
        notes: Receives the one-line reason a left-out ``--backend`` is not population.
    """
    import dataclasses

    from ermrl.population import choose_backend

    if getattr(args, "backend", None) is None:
        from ermrl.experiments._test_phase import finished_backend

        if ppo.backend == "sb3" and ppo.learner == "ppo":
            return ppo  # the study's own backend: kept silently, as an evolution resumes it
        backend, why = choose_backend(
            None,
            ppo,
            () if task is None else (task,),
            tensorboard=bool(getattr(args, "tensorboard", None)),
            wandb=bool(getattr(args, "wandb", None)),
        )
        if (
            backend == "population"
            and out is not None
            and not getattr(args, "overwrite", False)
            and finished_backend(out, ppo.learner) == "sb3"
        ):
            backend = "sb3"
            why = (
                f"the finished runs in {out} were made with it (a test folder never mixes backends)"
            )
        if why is not None and notes is not None:
            notes.append(why)
        return dataclasses.replace(ppo, backend=backend)
    ppo = dataclasses.replace(ppo, backend=args.backend)
    if ppo.backend == "population":
        from ermrl.population import check_population_config

        check_population_config(ppo)
        for flag in ("tensorboard", "wandb"):
            if getattr(args, flag, None):
                raise ConfigError(f"--{flag} logs come from the sb3 backend; use --backend sb3")
    return ppo


def print_notes(prog: str, ppo: Any, notes: Sequence[str]) -> None:
    """One line on stderr (also with ``--quiet``) per reason the study's agents train with
    their backend when ``--backend`` was left out."""
    for note in notes:
        print(
            f"{prog}: training with the {ppo.backend} backend: {note}", file=sys.stderr, flush=True
        )


def setup_errors() -> tuple[type[BaseException], ...]:
    from ermrl.envs import UnknownEnvError, UnsupportedObserveError
    from ermrl.storage import StorageError, StudyNotFound

    return (ConfigError, StorageError, StudyNotFound, UnknownEnvError, UnsupportedObserveError)


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
    """Train the plan's agents (one-line errors, Ctrl-C keeps finished runs) and print the
    summary; ``then`` post-processes the summary table. Returns it, or ``None`` after Ctrl-C."""
    from ermrl.experiments import run_comparison

    def run() -> Any:
        summary = run_comparison(
            task, encoder, ppo, plan.agents, plan.settings, metadata=metadata, quiet=args.quiet
        )
        return summary if then is None else then(summary)

    summary = run_or_exit(prog, plan.out, run)
    if summary is not None and not args.quiet:
        # Without --eval the evaluation columns are empty: left out of the printed table (they
        # stay in summary.csv, whose columns do not depend on the options).
        shown = summary.drop(columns=["seeds"])
        empty = [c for c in shown.columns if c.startswith("eval_") and shown[c].isna().all()]
        print(shown.drop(columns=empty).to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    return summary


def add_tensorboard_arg(parser: argparse.ArgumentParser) -> None:
    """``--tensorboard DIR`` of the test-phase commands (their runs train with sb3 then)."""
    parser.add_argument(
        "--tensorboard",
        default=None,
        metavar="DIR",
        help="also log training curves for TensorBoard under DIR/<agent>/seed_<s>; the runs "
        "then train with the sb3 backend (needs: pip install tensorboard)",
    )


def require_tensorboard(args: argparse.Namespace, prog: str) -> None:
    """Exit 2 in one line when ``--tensorboard`` is given without the tensorboard package."""
    if not getattr(args, "tensorboard", None):
        return
    import importlib.util

    if importlib.util.find_spec("tensorboard") is None:
        fail(
            prog,
            "--tensorboard needs the tensorboard package, which is not installed "
            "(pip install tensorboard)",
        )


def test_main(argv: Sequence[str] | None = None, prog: str = "ermrl test") -> int:
    """Entry point of ``ermrl test`` and ``test.py``."""
    from ermrl.agents import check_ppo_config, parse_overrides, with_overrides
    from ermrl.experiments import describe_selection, selection_metadata
    from ermrl.search import study_config
    from ermrl.storage import load_study

    parser = build_test_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    require_tensorboard(args, prog)
    if args.wandb:
        from ermrl.agents import WANDB_MISSING, wandb_installed

        if not wandb_installed():
            fail(prog, WANDB_MISSING)
    notes: list[str] = []
    try:
        study = load_study(args.study_name, args.storage)
        config = study_config(study)
        if getattr(config, "generalization", None) is not None:
            raise ConfigError(
                f"study {args.study_name!r} evolved on several tasks; test it on an unseen task "
                "with ermrl test-generalization --env-id ENV"
            )
        problem = config.problem
        choose_agents(args, config, problem.task.observe)
        overrides = parse_overrides(args.ppo)
        own = learner_overrides(args).get(problem.ppo.learner, {})
        default_out = Path("runs") / args.study_name
        ppo = with_backend(
            with_overrides(problem.ppo, {**overrides, **own}),
            args,
            task=problem.task,
            out=Path(args.out) if args.out else default_out,
            notes=notes,
        )
        if overrides or own:  # refused now rather than by the first run
            where = "--ppo" if overrides else f"--for-learner {problem.ppo.learner}"
            check_ppo_config(problem.task, problem.encoder, ppo, where=where)
        plan = plan_test_phase(
            args,
            study,
            config,
            problem.task,
            ppo,
            default_out,
            observe=problem.task.observe,
        )
    except setup_errors() as err:
        fail(prog, str(err))
    print_notes(prog, ppo, notes)
    if plan.warning:  # also with --quiet: the selection is not the one a ranking would give
        print(f"{prog}: warning: {plan.warning}", file=sys.stderr, flush=True)
    if not args.quiet:
        best = describe_selection(plan.chosen)
        print(
            f"test phase of {args.study_name!r}: {problem.task.label}, agents {' '.join(args.agents)}, "
            f"seeds {' '.join(map(str, plan.seeds))}, {args.training_steps} steps each; "
            f"selected: {best}; out: {plan.out}",
            flush=True,
        )
    metadata = {
        "study_name": args.study_name,
        "storage": args.storage,
        **selection_metadata(plan.chosen),
    }
    summary = run_test_phase(prog, args, plan, problem.task, problem.encoder, ppo, metadata)
    if summary is None:
        return EXIT_INTERRUPTED
    if not args.quiet:
        print(f"wrote {plan.out}/summary.csv, curves.csv, learning_curves.png", flush=True)
    return 0
