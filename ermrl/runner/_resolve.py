"""The parsed options of the evolve and test commands as the library's configuration objects.

``ermrl evolve``, ``ermrl evolve-generalization``, ``ermrl test`` and ``ermrl
test-generalization`` parse their argv and build their configuration here; so does the plan of
an experiment file ([`ermrl.runner.experiment_plan`][ermrl.runner.experiment_plan]), whose stages'
options are parsed as the commands parse them. Every function raises
[`ConfigError`][ermrl.config.ConfigError] (or an env error) on a value the configuration refuses, in
one line.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ermrl._schema import words_of
from ermrl.config import (
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    EncoderSpace,
    EvolveConfig,
    GeneralizationTask,
    LearnerSpace,
    PPOConfig,
    Problem,
    Range,
    SearchConfig,
    SearchSpaceConfig,
    TaskConfig,
)
from ermrl.encoders import ENCODERS, get_encoder, reference_encoder

if TYPE_CHECKING:
    from ermrl._progress import ProgressMode
    from ermrl.test_phase import TestOptions

# The options of a command: parsed from its argv (an ``argparse.Namespace``), or validated from
# a file or a call (an options dataclass, `ermrl.runner._evolve_options`); both are read by
# attribute.
Options = Any

__all__ = [
    "budget_from_args",
    "check_tensorboard",
    "config_from_args",
    "encoder_from_args",
    "for_learner_names",
    "generalization_config_from_args",
    "keep_study_backend",
    "learner_flags",
    "learner_overrides",
    "learner_space_from_args",
    "parse_gene_ranges",
    "search_from_args",
    "space_from_args",
    "stored_backend",
    "test_options",
    "validate_task",
]


def _progress_mode(args: Options) -> ProgressMode:
    """``args.progress``, or the default for where stdout goes."""
    from ermrl._progress import default_mode

    value = getattr(args, "progress", None)
    return default_mode() if value is None else value


def for_learner_names(args: Options) -> tuple[str, ...]:
    """The learners named by ``--for-learner`` flags, in order, each once."""
    given = _learner_items(getattr(args, "for_learner", None))
    return tuple(dict.fromkeys(name for name, _ in given))


def learner_overrides(args: Options) -> dict[str, dict[str, Any]]:
    """Settings given by learner-specific flags, keyed by the learner they apply to.

    ``--stale-gradient`` (rtu-ppo's ``stale_gradient``) first, then each ``--for-learner`` in
    the order given: a later flag wins per key.
    """
    out: dict[str, dict[str, Any]] = {}
    stale = getattr(args, "stale_gradient", None)
    if stale is not None:
        out["rtu-ppo"] = {"stale_gradient": stale}
    for name, settings in _learner_items(getattr(args, "for_learner", None)):
        out[name] = {**out.get(name, {}), **settings}
    return out


def _learner_items(given: Any) -> list[tuple[str, Mapping[str, Any]]]:
    """``--for-learner``'s ``(learner, settings)`` pairs, as parsed (a list) or validated (a
    mapping)."""
    return list(given.items()) if isinstance(given, Mapping) else list(given or [])


def parse_gene_ranges(items: Sequence[str], genes: Mapping[str, Range]) -> dict[str, Range]:
    """``--gene NAME=LOW:HIGH[:lin|:log]`` as ranges (the scale defaults to the gene's own).

    Raises:
        ConfigError: a malformed item, an unknown gene or a bad range.
    """
    out: dict[str, Range] = {}
    for item in items:
        name, sep, text = item.partition("=")
        parts = text.split(":")
        if (
            not sep
            or len(parts) not in (2, 3)
            or (len(parts) == 3 and parts[2] not in ("lin", "log"))
        ):
            raise ConfigError(f"--gene expects NAME=LOW:HIGH[:lin|:log], got {item!r}")
        if name not in genes:
            raise ConfigError(f"unknown gene {name!r}; the genes are {', '.join(genes)}")
        try:
            low, high = float(parts[0]), float(parts[1])
        except ValueError:
            raise ConfigError(f"--gene {name}: bounds must be numbers, got {text!r}") from None
        log = genes[name].log if len(parts) == 2 else parts[2] == "log"
        out[name] = Range(low, high, log=log)
    return out


def learner_space_from_args(args: Options, ppo: PPOConfig) -> LearnerSpace:
    """The gene space of a learner with genes; the encoder's flags are refused."""
    from ermrl.learners import get_learner
    from ermrl.runner._evolve_options import encoder_settings

    for name, (flag, default) in encoder_settings(args).items():
        value = getattr(args, name, default)
        if _listed(value) != _listed(default):
            raise ConfigError(
                f"{flag} sets an evolved encoder; --learner {ppo.learner} has none (evolution "
                "shapes its genes: see --gene)"
            )
    learner = get_learner(ppo.learner)
    genes = words_of(getattr(args, "gene", None))
    return learner.gene_space(ppo, parse_gene_ranges(genes, learner.genes))


def _listed(value: Any) -> Any:
    """A pair as a list (a parsed one is a list, a validated one a tuple)."""
    return list(value) if isinstance(value, tuple) else value


def space_from_args(args: Options) -> EncoderSpace:
    """The search space of the chosen encoder (``--encoder``) from its flags.

    Raises:
        ConfigError: a flag of another encoder only, or a bad value.
    """
    encoder = get_encoder(getattr(args, "encoder", reference_encoder().name))
    own = {s.name for s in encoder.setting_specs()}
    for other in ENCODERS.values():
        for spec in other.setting_specs():
            value = _listed(getattr(args, spec.name, None))
            if spec.name not in own and value not in (None, _listed(spec.default)):
                takers = [  # every encoder that declares the setting (--units: two of them)
                    e.name
                    for e in ENCODERS.values()
                    if spec.name in {s.name for s in e.setting_specs()}
                ]
                raise ConfigError(
                    f"{spec.flag} applies to --encoder {' or '.join(takers)}, not to "
                    f"--encoder {encoder.name}"
                )
    space: EncoderSpace = encoder.space_from_args(args)
    return space


def encoder_from_args(args: Options, space: EncoderSpace) -> EncoderConfig:
    return EncoderConfig(
        reservoirs=space.default_reservoirs(),
        skip_connection=args.skip_connection,
        reset=args.reset,
        exposed_units=args.exposed_units,
        reward_scale=args.reward_scale,
        feed_action=args.feed_action,
        feed_reward=args.feed_reward,
        dtype=args.dtype,
    )


def budget_from_args(args: Options) -> BudgetConfig:
    return BudgetConfig(
        training_steps=args.training_steps,
        fitness=args.fitness,
        n_last_episodes=args.n_last_episodes,
        n_eval_episodes=args.n_eval_episodes,
        n_reports=4 if args.pruner != "none" else 0,
    )


def search_from_args(args: Options) -> SearchConfig:
    return SearchConfig(
        sampler=args.sampler,
        sampler_seed=args.sampler_seed,
        restart=args.restart,
        popsize=args.popsize,
        pruner=args.pruner,
        n_trials=args.n_trials,
        start=args.cma_start,
        reference_trial=args.reference_trial,
        reevaluate_top=args.reevaluate_top,
        reevaluate_seeds=args.reevaluate_seeds,
        reevaluate_steps=args.reevaluate_steps,
    )


def validate_task(env_id: str, observe: str) -> None:
    """Cheap checks of an env id and mask (no env is built for an unknown id)."""
    from ermrl.envs import check_env_id, observation_indices

    check_env_id(env_id)
    observation_indices(env_id, observe)  # type: ignore[arg-type]


def learner_flags(args: Options, learner: str) -> dict[str, Any]:
    """The learner-specific flags' settings for ``learner``, the study's learner.

    Raises:
        ConfigError: a flag of another learner (``--for-learner dagger`` in a study of
            ``--learner ppo``; ``--stale-gradient`` without ``--learner rtu-ppo``).
    """
    for name in for_learner_names(args):
        if name != learner:
            raise ConfigError(
                f"--for-learner {name}: no agent of this run uses learner {name} (the study "
                f"trains --learner {learner})"
            )
    given = learner_overrides(args)
    for name in given:
        if name != learner:
            raise ConfigError(f"--stale-gradient applies to --learner {name} only")
    return dict(given.get(learner, {}))


def config_from_args(
    args: Options, *, build_agent: bool = True, notes: list[str] | None = None
) -> EvolveConfig:
    """Build and validate the run's configuration (raises ConfigError / env errors).

    Args:
        args: The parsed options.
        build_agent: Also build the agent once on the real env (and reservoir), so that what
            PPO or the encoder would only refuse in the first trial is refused now; ``False``
            (``ermrl run --dry-run``) checks the options and tables only.
        notes: Receives the one-line reason when ``--backend`` is left out and the population
            backend does not apply (the run then trains with sb3).
    """
    from ermrl.agents import check_ppo_config, parse_overrides, resolve_ppo_config
    from ermrl.learners import get_learner
    from ermrl.population import choose_backend

    validate_task(args.env_id, args.observe)
    learner = getattr(args, "learner", "ppo")
    ppo = resolve_ppo_config(
        args.env_id,
        {**parse_overrides(words_of(args.ppo), learner), **learner_flags(args, learner)},
        n_envs=args.n_envs,
        table_path=args.hyperparams,
        torch_threads=args.torch_threads,
        learner=learner,
    )
    evolves_encoder = not get_learner(learner).genes
    encoder_name = getattr(args, "encoder", None) if evolves_encoder else None
    backend, why = choose_backend(
        getattr(args, "backend", None),
        ppo,
        (TaskConfig(env_id=args.env_id, observe=args.observe),),
        pruner=getattr(args, "pruner", "none"),
        encoder=encoder_name,
    )
    if why is not None and notes is not None:
        notes.append(why)
    ppo = dataclasses.replace(ppo, backend=backend)
    space: SearchSpaceConfig
    if not evolves_encoder:
        space, encoder = learner_space_from_args(args, ppo), None
    else:
        if getattr(args, "gene", None):
            raise ConfigError(f"--gene evolves a learner's genes; learner {learner!r} has none")
        space = space_from_args(args)
        encoder = encoder_from_args(args, space)
        get_encoder(args.encoder).check(
            TaskConfig(env_id=args.env_id, observe=args.observe), encoder, space
        )
    problem = Problem(
        task=TaskConfig(env_id=args.env_id, observe=args.observe),
        encoder=encoder,
        ppo=ppo,
        budget=budget_from_args(args),
        seeds=tuple(range(args.seed, args.seed + args.n_seeds)),
    )
    config = EvolveConfig(
        problem=problem, space=space, search=search_from_args(args), n_procs=args.n_procs
    )
    # Whatever PPO or the encoder would refuse in the first trial is refused now, before the
    # study (and a FAIL trial) exists.
    if build_agent:
        check_ppo_config(problem.task, problem.encoder, ppo)
    if ppo.backend == "population":
        from ermrl.population import check_population_config

        check_population_config(ppo)
        if encoder_name is not None and not get_encoder(encoder_name).population:
            raise ConfigError(
                f"the population backend does not step --encoder {encoder_name}'s reservoirs; "
                "use --backend sb3"
            )
    check_tensorboard(args)
    return config


def check_tensorboard(args: Options) -> None:
    """``--tensorboard`` needs the tensorboard package (on either backend).

    Raises:
        ConfigError: ``--tensorboard`` without the tensorboard package.
    """
    if not getattr(args, "tensorboard", None):
        return
    import importlib.util

    if importlib.util.find_spec("tensorboard") is None:
        raise ConfigError(
            "--tensorboard needs the tensorboard package, which is not installed "
            "(pip install tensorboard)"
        )


def stored_backend(storage: str, study_name: str) -> str | None:
    """The backend an existing study was created with (``None``: no such study or storage, or
    a study without an ermrl configuration). Reads only: nothing is created."""
    from ermrl.search import STUDY_CONFIG_ATTR
    from ermrl.storage import StorageError, StudyNotFound, load_study

    try:
        stored = load_study(study_name, storage).user_attrs.get(STUDY_CONFIG_ATTR)
    except (StorageError, StudyNotFound):
        return None
    if not isinstance(stored, Mapping):
        return None
    ppo = (stored.get("problem") or {}).get("ppo") or {}
    return str(ppo.get("backend", "sb3")) if isinstance(ppo, Mapping) else None


def keep_study_backend(
    args: Options,
    config: EvolveConfig,
    storage: str,
    study_name: str,
    build: Callable[[Options], EvolveConfig],
    notes: list[str],
) -> tuple[Options, EvolveConfig]:
    """A resumed study keeps the backend it was created with when ``--backend`` is left out.

    Args:
        args: The parsed options.
        config: The configuration built from them.
        storage: The study's storage.
        study_name: The study's name.
        build: Builds the configuration from options (``config_from_args``, ...).
        notes: The one-line notes to print; replaced by the study's when it keeps its backend.

    Returns:
        ``(args, config)``, with ``--backend`` set to the study's and the configuration rebuilt
        when the study was created with another backend than the one chosen now.
    """
    if getattr(args, "backend", None) is not None:
        return args, config
    kept = stored_backend(storage, study_name)
    if kept is None or kept == config.problem.ppo.backend:
        return args, config
    args = _replaced(args, backend=kept)
    notes[:] = [f"study {study_name!r} was created with it (a study never mixes backends)"]
    return args, build(args)


def _replaced(args: Options, **changes: Any) -> Options:
    """The options (parsed, or a dataclass of them) with ``changes``."""
    if dataclasses.is_dataclass(args) and not isinstance(args, type):
        return dataclasses.replace(args, **changes)
    out = copy.copy(args)
    for name, value in changes.items():
        setattr(out, name, value)
    return out


def test_options(args: Options) -> TestOptions:
    """The parsed options of ``ermrl test`` or ``ermrl test-generalization`` as the library's
    [`TestOptions`][ermrl.test_phase.TestOptions]: its fields, each parsed under its own name
    (``--ppo`` words kept: they are read, and refused, where the command always read them)."""
    from ermrl._schema import fields_of
    from ermrl.test_phase import TestOptions

    values = {
        s.name: getattr(args, s.name) for s in fields_of(TestOptions) if hasattr(args, s.name)
    }
    for_learner: dict[str, dict[str, Any]] = {}
    for name, settings in values.get("for_learner") or []:
        for_learner[name] = {**for_learner.get(name, {}), **settings}
    values.update(for_learner=for_learner, ppo=tuple(values["ppo"]), progress=_progress_mode(args))
    return TestOptions(**values)


# -- a study on a set of tasks (ermrl evolve-generalization) ------------------------------------


def generalization_config_from_args(
    args: Options, *, build_agent: bool = True, notes: list[str] | None = None
) -> EvolveConfig:
    """Build and validate a multi-task configuration (raises ConfigError / env errors).

    Args:
        args: The parsed options of ``ermrl evolve-generalization``.
        build_agent: Also build each task's agent once (see
            `ermrl.runner._resolve.config_from_args`); ``False`` checks the options only.
        notes: Receives the one-line reason when ``--backend`` is left out and the population
            backend does not apply to some task (the study then trains with sb3).
    """
    from ermrl.agents import parse_overrides
    from ermrl.encoders import get_encoder
    from ermrl.search import generalization_config, generalization_tasks

    env_ids, suite = _suite_env_ids(args)
    _refuse_learner_genes(args.learner)
    overrides = {
        **parse_overrides(words_of(args.ppo), args.learner),
        **learner_flags(args, args.learner),
    }
    tasks = generalization_tasks(
        env_ids,
        observe=args.observe,
        ppo_overrides=overrides,
        n_envs=args.n_envs,
        hyperparams=args.hyperparams,
        torch_threads=args.torch_threads,
        scores=args.scores,
        target_column=args.target_column,
        learner=args.learner,
        backend=args.backend or "sb3",
    )
    if args.backend is None:  # population where it applies to every task; a study has one
        tasks = _one_backend(tasks, args, notes)
    space = space_from_args(args)
    encoder = encoder_from_args(args, space)
    for t in tasks:  # what depends on a task's sizes is refused before the study exists
        get_encoder(args.encoder).check(t.task, encoder, space)
    config = generalization_config(
        tasks,
        encoder=encoder,
        budget=budget_from_args(args),
        seeds=tuple(range(args.seed, args.seed + args.n_seeds)),
        space=space,
        search=search_from_args(args),
        n_procs=args.n_procs,
        suite=suite,
        scores=None if args.scores is None else str(Path(args.scores).resolve()),
        target_column=args.target_column,
        ppo_overrides=overrides,
        n_envs=args.n_envs,
        hyperparams=args.hyperparams,
    )
    _check_agents(config, tasks, build_agent)
    check_tensorboard(args)
    return config


def _suite_env_ids(args: Options) -> tuple[Sequence[str], str | None]:
    """The evolution tasks' env ids and the suite they come from (``None``: ``--env-ids``).

    Raises:
        ConfigError: ``--env-version`` without ``--suite``, or an unknown suite.
    """
    from ermrl.envs import get_suite

    if args.suite is not None:
        found = get_suite(args.suite, args.suites_file, env_version=args.env_version)
        return found.env_ids, found.name
    if args.env_version is not None:
        raise ConfigError("--env-version applies to --suite only; write the ids in full")
    return args.env_ids or (), None


def _refuse_learner_genes(learner: str) -> None:
    """A learner with genes of its own is evolved on one task (``ermrl evolve``).

    Raises:
        ConfigError: The learner has genes.
    """
    from ermrl.learners import get_learner

    if get_learner(learner).genes:
        raise ConfigError(
            f"evolve-generalization evolves encoders; the {learner} learner's genes are "
            "evolved on one task with evolve"
        )


def _one_backend(
    tasks: Sequence[GeneralizationTask], args: Options, notes: list[str] | None
) -> tuple[GeneralizationTask, ...]:
    """The tasks with one backend for all: population where it applies to every task, else sb3.

    Args:
        tasks: The evolution tasks.
        args: The parsed options (``--pruner``, ``--encoder``).
        notes: Receives the first task's reason the population backend does not apply.

    Returns:
        The tasks, each with the chosen backend.
    """
    from ermrl.population import choose_backend

    backend, why = "population", None
    for t in tasks:
        backend, why = choose_backend(
            None, t.ppo, (t.task,), pruner=args.pruner, encoder=args.encoder
        )
        if why is not None:
            if notes is not None:
                notes.append(f"{t.task.env_id}: {why}")
            break
    return tuple(
        dataclasses.replace(t, ppo=dataclasses.replace(t.ppo, backend=backend)) for t in tasks
    )


def _check_agents(
    config: EvolveConfig, tasks: Sequence[GeneralizationTask], build_agent: bool
) -> None:
    """What PPO (or the population backend) would refuse in the first trial is refused before
    the study exists; ``build_agent=False`` skips building each task's agent."""
    from ermrl.agents import check_ppo_config

    for task in tasks if build_agent else ():
        check_ppo_config(task.task, config.problem.encoder, task.ppo, where=task.task.env_id)
    if config.problem.ppo.backend == "population":
        from ermrl.population import check_population_config

        check_population_config(config.problem.ppo)
