"""What a test phase trains, decided before anything trains: options, agents, seeds, backend.

``ermrl test``, ``ermrl test-generalization`` and [`ermrl.test`][ermrl.runner.test] share this code.
The options are a [`TestOptions`][ermrl.test_phase.TestOptions] (the command-line options of the
test commands, as plain data); [`prepare_test`][ermrl.test_phase.prepare_test] turns them and a
study into a [`TestPhase`][ermrl.test_phase.TestPhase], every check done, which
[`run_comparison`][ermrl.test_phase.run_comparison] then trains.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

from ermrl._progress import ProgressMode
from ermrl._schema import option, validate
from ermrl.config import ConfigError
from ermrl.learners import AGENT_KINDS, default_agents

if TYPE_CHECKING:
    import optuna

    from ermrl.config import EncoderConfig, EvolveConfig, PPOConfig, TaskConfig
    from ermrl.test_phase._test_phase import AgentSpec, Selection, TestSettings

T = TypeVar("T")

__all__ = [
    "TestOptions",
    "TestPhase",
    "TestPlan",
    "agent_learners",
    "check_test_seeds",
    "check_for_learner",
    "choose_agents",
    "parse_for_learner",
    "plan_test_phase",
    "prepare_test",
    "run_in_folder",
    "select_seeds",
    "with_backend",
]


def _agents_help() -> str:
    return (
        "agents to train (default: "
        + ", ".join(n for n, k in AGENT_KINDS.items() if k.default)
        + "; ppo-full only when the mask hides something, since on the full observation it "
        "would repeat ppo): "
        + "; ".join(f"{name}: {kind.description}" for name, kind in AGENT_KINDS.items())
    )


_BACKEND_HELP = (
    "what trains the agents of the study's learner: population (all seeds of an agent "
    "trained in lockstep, PPO only) or sb3 (the reference implementation: one "
    "Stable-Baselines3 process per run). Default: the study's backend when it was evolved "
    "with sb3, else population where it applies (not with --wandb, nor into an --out "
    "whose finished runs were made with sb3), else sb3, with one line saying why. Agents "
    "with another learner always train with sb3"
)
_CHECKPOINT_HELP = (
    "runs save their training state every STEPS steps per run, and a rerun after a "
    "kill or crash resumes them from there (weights, optimizer, normalization, episodes so "
    "far; the environments restart from fresh episodes): population runs in "
    "OUT/checkpoints, runs of on-policy sb3 learners (ppo, lstm-ppo, framestack-ppo, "
    "rtu-ppo) in their run folder; other learners restart. Default: a tenth of "
    "--training-steps; 0: no checkpoints"
)
STALE_GRADIENT_HELP = (
    "rtu-ppo only: keep each stored RTU carry as it was collected (the default, the "
    "paper's stale gradient), or re-scan the rollout with the new parameters after each "
    "epoch (--no-stale-gradient, about half as fast)"
)
FOR_LEARNER_HELP = (
    "settings of one learner only, on top of its table and --ppo: the first word names the "
    "learner, the rest are KEY=VALUE as in --ppo (values read as YAML). Repeatable; a later "
    "flag wins per key. Use it for what other learners refuse, e.g. the dagger learner's "
    "expert: --for-learner dagger expert=experts/hopper steps_per_iteration=500"
)
TENSORBOARD_HELP = (
    "also log training curves for TensorBoard under DIR/<agent>/seed_<s>: the scalars "
    "SB3's PPO logs (returns, losses, fps), on either backend (needs: pip install "
    "tensorboard)"
)


@dataclass(frozen=True)
class TestOptions:
    """The options of a test phase: one definition for ``ermrl test`` (its options are
    generated from these fields), an experiment file's ``test:`` stage and
    [`ermrl.test`][ermrl.runner.test]'s keywords, checked by the same code
    (`ermrl._schema.validate`).

    Attributes:
        training_steps: Env steps per run (paper: 1,000,000).
        seeds: Test seeds (``None``: 5 seeds after the largest seed evolution trained on).
        agents: Agents to train (``None``: the study's default agents; see
            `ermrl.learners.AGENT_KINDS`).
        out: Output folder (``None``: ``runs/<study name>``).
        trial: Test this trial's reservoir instead of the selected one (``None``: the
            re-evaluated best, else the best evolution fitness).
        n_procs: Cores for the runs, trained in parallel single-threaded processes.
        evaluate: Also run deterministic evaluation episodes after training (``--eval``).
        n_eval_episodes: Their number.
        ppo: Learner overrides on top of the study's, every agent (``--ppo``): a mapping
            (``{"learning_rate": 1e-4}``) or ``KEY=VALUE`` words.
        stale_gradient: The rtu-ppo learner's ``stale_gradient`` (``None``: its table's).
        for_learner: Settings of one learner only, ``{learner: {key: value}}``
            (``--for-learner``), e.g. the dagger learner's expert.
        backend: ``"population"`` or ``"sb3"`` for the agents of the study's learner
            (``None``: population where it applies, else sb3).
        save_models: Save each trained model as ``model.zip``.
        overwrite: Retrain the asked-for runs that already have results.
        checkpoint_every: Save each run's training state every this many steps (``None``: a
            tenth of ``training_steps``; 0: never).
        tensorboard: Also log training curves for TensorBoard under this folder.
        wandb: Also log each run to this Weights & Biases project.
        progress: ``"bar"``, ``"lines"`` or ``"none"`` inside each run.
    """

    __test__ = False  # not a pytest test class

    training_steps: int = option(1_000_000, "env steps per run (paper: 1000000)", low=1)
    seeds: Sequence[int] | None = option(
        None, "test seeds (default: 5 seeds after the largest seed evolution trained on)", low=0
    )
    agents: Sequence[str] | None = option(None, _agents_help, choices=lambda: tuple(AGENT_KINDS))
    out: str | Path | None = option(None, "output folder (default: runs/<study name>)")
    trial: int | None = option(None, "test this trial's reservoir instead of the best one", low=0)
    n_procs: int = option(
        1, "cores for the runs, trained in parallel single-threaded processes", low=1
    )
    evaluate: bool = option(
        False, "also run deterministic evaluation episodes after training", flag="--eval",
        key="eval",
    )  # fmt: skip
    n_eval_episodes: int = option(10, "evaluation episodes with --eval", low=1)
    ppo: Mapping[str, Any] | Sequence[str] = option(
        (), "PPO overrides on top of the study's, e.g. --ppo learning_rate=1e-4",
        metavar="KEY=VALUE", words=True,
    )  # fmt: skip
    stale_gradient: bool | None = option(None, STALE_GRADIENT_HELP)
    for_learner: Mapping[str, Mapping[str, Any]] = option(
        {}, FOR_LEARNER_HELP, metavar=("LEARNER", "KEY=VALUE"), check=lambda v: check_for_learner(v)
    )
    backend: Literal["population", "sb3"] | None = option(None, _BACKEND_HELP)
    save_models: bool = option(True, "save each trained model as model.zip")
    overwrite: bool = option(
        False, "retrain the asked-for runs that already have results (a rerun into an --out "
        "whose runs were made with other settings is refused without it)", negatable=False,
    )  # fmt: skip
    checkpoint_every: int | None = option(None, _CHECKPOINT_HELP, metavar="STEPS", low=0)
    tensorboard: str | Path | None = option(None, TENSORBOARD_HELP, metavar="DIR")
    wandb: str | None = option(
        None, "also log each run to the Weights & Biases project PROJECT (wandb's SB3 "
        "callback; the runs of one test folder form a group; WANDB_MODE=offline logs "
        "locally; needs: pip install 'ermrl[wandb]')", metavar="PROJECT",
    )  # fmt: skip
    progress: ProgressMode = option("none", cli=False)

    @classmethod
    def from_options(cls, where: str = "", *, text: bool = False, **values: Any) -> TestOptions:
        """The options, every value checked first (`ermrl._schema.validate`).

        Args:
            where: Names the options in errors (``"ermrl.test"``).
            text: Strings are read as the command line reads its words.
            **values: Fields.

        Raises:
            ConfigError: An unknown field (with the nearest valid one) or a bad value, in one
                line.
        """
        return cls(**validate(cls, values, where, text=text))

    def __post_init__(self) -> None:
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for name, value in validate(type(self), values, "TestOptions").items():
            object.__setattr__(self, name, value)  # lists as tuples

    def ppo_overrides(self, learner: str | None = None) -> dict[str, Any]:
        """``ppo`` as a checked mapping (values read as ``--ppo`` reads them).

        Args:
            learner: The learner the settings are for: an unknown key is then matched against
                its keys only (``None``: any learner's).

        Raises:
            ConfigError: A malformed item or an unknown key.
        """
        from ermrl.agents import parse_overrides

        if isinstance(self.ppo, Mapping):
            words = [f"{k}={json.dumps(v, default=str)}" for k, v in self.ppo.items()]
            return parse_overrides(words, learner)
        return parse_overrides(list(self.ppo), learner)

    def learner_settings(self) -> dict[str, dict[str, Any]]:
        """Settings of one learner only, keyed by learner: ``stale_gradient`` (rtu-ppo's)
        first, then ``for_learner``, a later one winning per key."""
        out: dict[str, dict[str, Any]] = {}
        if self.stale_gradient is not None:
            out["rtu-ppo"] = {"stale_gradient": self.stale_gradient}
        for name, settings in self.for_learner.items():
            out[name] = {**out.get(name, {}), **settings}
        return out


def parse_for_learner(values: Sequence[str]) -> tuple[str, dict[str, Any]]:
    """One ``--for-learner LEARNER KEY=VALUE [KEY=VALUE ...]``: the learner and its settings.

    Values are read as ``--ppo`` values are
    ([`ermrl.agents.parse_overrides`][ermrl.agents.parse_overrides]: YAML, ``1e-4`` a number,
    ``[64, 64]`` a list).

    Args:
        values: The flag's words, the learner's name first.

    Returns:
        The learner's name and its settings.

    Raises:
        ConfigError: an unregistered learner, no ``KEY=VALUE``, a malformed one or an unknown
            key (one line, starting ``--for-learner LEARNER:``).

    Examples:
        >>> parse_for_learner(["dagger", "expert=experts/hopper", "epochs=3"])
        ('dagger', {'expert': 'experts/hopper', 'epochs': 3})
    """
    from ermrl.agents import parse_overrides
    from ermrl.learners import learner_names

    name, *items = values
    where = f"--for-learner {name}"
    if name not in learner_names():
        raise ConfigError(
            f"{where}: unknown learner {name!r}; choose from {', '.join(learner_names())}"
        )
    if not items:
        raise ConfigError(f"{where}: give at least one KEY=VALUE after the learner's name")
    settings: dict[str, Any] = {}
    for item in items:
        key, sep, _ = item.replace(":", "=", 1).partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"{where}: {item!r} is not KEY=VALUE (or KEY:VALUE)")
        try:
            settings.update(parse_overrides([item], name))
        except ConfigError as err:
            raise ConfigError(f"{where}: {str(err).removeprefix('--ppo: ')}") from None
    return name, settings


def check_for_learner(value: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """``for_learner`` as [`parse_for_learner`][ermrl.test_phase.parse_for_learner] reads each
    ``--for-learner`` flag: a registered learner, and settings it accepts.

    Raises:
        ConfigError: An unregistered learner, a learner without settings, or a setting it
            does not know (one line).
    """
    from ermrl._schema import _pairs

    out: dict[str, dict[str, Any]] = {}
    for name, settings in value.items():
        if not isinstance(settings, Mapping):
            raise ConfigError(f"{name}: a mapping {{KEY: VALUE}} of its settings is expected")
        learner, parsed = parse_for_learner([str(name), *_pairs(settings.items())])
        out[learner] = {**out.get(learner, {}), **parsed}
    return out


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


def agent_learners(names: Sequence[str], study_learner: str) -> tuple[str, ...]:
    """The learners that train the agents ``names`` (``AGENT_KINDS``), each once.

    Args:
        names: Agent names.
        study_learner: The study's learner, which trains the agents of no learner of their own.
    """
    kinds = [AGENT_KINDS[n] for n in names if n in AGENT_KINDS]
    return tuple(dict.fromkeys(kind.learner or study_learner for kind in kinds))


def choose_agents(options: TestOptions, config: EvolveConfig, observe: str) -> list[str]:
    """The agents of ``options`` (default: the study's default agents), checked against
    ``options.for_learner``.

    Raises:
        ConfigError: a ``for_learner`` entry names a learner that none of the agents trains
            with.
    """
    agents = list(options.agents or default_agents(observe, config.space.family))
    used = agent_learners(agents, config.problem.ppo.learner)
    for name in options.for_learner:
        if name not in used:
            raise ConfigError(
                f"--for-learner {name}: no agent of this run uses learner {name} (agents "
                f"{' '.join(agents)} use {', '.join(used)})"
            )
    return agents


@dataclass
class TestPlan:
    """What a test phase trains: its agents, the selected trial, seeds and settings."""

    __test__ = False  # not a pytest test class

    agents: list[AgentSpec]
    chosen: Selection | None
    seeds: tuple[int, ...]
    settings: TestSettings
    out: Path
    warning: str | None = None
    """A line for stderr before anything runs: the stored ranking is stale."""
    agent_names: tuple[str, ...] = ()
    """The agents asked for, in the order given (``options.agents`` or the defaults)."""


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
            ([`used_reevaluation_seeds`][ermrl.search.used_reevaluation_seeds]).
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
    options: TestOptions,
    study: optuna.Study,
    config: EvolveConfig,
    task: TaskConfig,
    ppo: PPOConfig,
    default_out: Path,
    *,
    observe: str,
) -> TestPlan:
    """The part of ``ermrl test`` and ``ermrl test-generalization`` that is the same: seeds,
    agents (each with its learner's settings), checks of the settings and of the folder.

    Args:
        options: The test phase's options.
        study: The evolution study.
        config: Its configuration.
        task: The task the agents train on.
        ppo: The settings of the study's learner on that task (``options.ppo`` applied).
        default_out: The folder when ``options.out`` is not given.
        observe: The mask that decides the default agents.

    Raises:
        ConfigError: bad settings, test seeds evolution or the re-evaluation used, a bad
            folder, or an agent that cannot be built.
    """
    from ermrl.search import used_reevaluation_seeds
    from ermrl.test_phase._test_phase import (
        check_out_folder,
        default_test_seeds,
        learner_settings_for,
        study_agents,
    )

    problem = config.problem
    seeds = tuple(options.seeds) if options.seeds else default_test_seeds(problem.seeds)
    check_test_seeds(seeds, problem.seeds, used_reevaluation_seeds(study), study.study_name)
    seeds = select_seeds(seeds, os.environ.get("SLURM_ARRAY_TASK_ID"))
    names = choose_agents(options, config, observe)
    overrides = options.ppo_overrides()
    own = options.learner_settings()
    agents, chosen = study_agents(
        study,
        config,
        names,
        options.trial,
        learner_settings_for(ppo, task.env_id, overrides, own),
        ppo,
    )
    _check_agent_settings(agents, task)
    out = Path(options.out) if options.out else default_out
    check_out_folder(out)
    settings = _test_settings(options, seeds, out, problem.budget.n_last_episodes)
    warning = _stale_ranking_warning(study, chosen, options.trial)
    return TestPlan(agents, chosen, seeds, settings, out, warning, tuple(names))


def _check_agent_settings(agents: Sequence[AgentSpec], task: TaskConfig) -> None:
    """Check the settings of each agent of another learner than the study's.

    Such an agent has settings no study checked (its table, ``--ppo``, ``--for-learner``;
    dagger's expert): refused now rather than by its first run.

    Raises:
        ConfigError: an agent's settings are bad, naming the agent.
    """
    from ermrl.agents import check_ppo_config

    for agent in agents:
        if agent.ppo is not None:
            check_ppo_config(agent.task(task), None, agent.ppo, where=agent.name)


def _test_settings(
    options: TestOptions, seeds: tuple[int, ...], out: Path, n_last_episodes: int
) -> TestSettings:
    """How the comparison runs: ``options`` on ``seeds`` into ``out``, each run's final return
    the mean of its last ``n_last_episodes`` training episodes (the study's measure)."""
    from ermrl.test_phase._test_phase import TestSettings

    return TestSettings(
        training_steps=options.training_steps,
        seeds=seeds,
        out=out,
        n_procs=options.n_procs,
        evaluate=options.evaluate,
        n_eval_episodes=options.n_eval_episodes,
        n_last_episodes=n_last_episodes,
        save_models=options.save_models,
        overwrite=options.overwrite,
        tensorboard=Path(options.tensorboard) if options.tensorboard else None,
        wandb=options.wandb,
        progress=options.progress,
        checkpoint_every=options.checkpoint_every,
    )


def _stale_ranking_warning(
    study: optuna.Study, chosen: Selection | None, trial: int | None
) -> str | None:
    """A line for stderr when the stored ranking is stale and the trial was selected without it.

    Only when the ranking would have picked the trial: not with a trial given (``trial``), nor
    when no agent uses the evolved trial (``chosen`` is ``None``).
    """
    from ermrl.search import stale_ranking

    stale = None if chosen is None or trial is not None else stale_ranking(study)
    if chosen is None or stale is None:
        return None
    return (
        f"the re-evaluated ranking is stale and not used ({stale}); testing trial "
        f"{chosen.number}, the best evolution fitness (run the evolve command again to "
        "re-rank, or pass --trial N)"
    )


def with_backend(
    ppo: PPOConfig,
    options: TestOptions,
    *,
    task: TaskConfig | None = None,
    out: Path | None = None,
    notes: list[str] | None = None,
) -> PPOConfig:
    """The study's learner settings with the backend that trains its agents.

    ``options.backend`` when given (checked for it). Left out: the study's own backend when it
    was evolved with sb3 (an existing study keeps the backend it was created with, so a study
    of an older ermrl tests to the same returns); otherwise population where it applies,
    unless ``out`` holds finished runs of this learner made with sb3 (a test folder never
    mixes backends; not with ``overwrite``), else sb3.

    Args:
        ppo: The settings of the study's learner on the test task.
        options: The test phase's options (``backend``, ``tensorboard``, ``wandb``,
            ``overwrite``).
        task: The test task (its env's spaces are checked; ``None``: not checked).
        out: The test folder.
        notes: Receives the one-line reason a left-out backend is not population.

    Raises:
        ConfigError: The population backend asked for where it does not apply.
    """
    from ermrl.population import choose_backend

    if options.backend is None:
        from ermrl.test_phase._test_phase import finished_backend

        if ppo.backend == "sb3" and ppo.learner == "ppo":
            return ppo  # the study's own backend: kept silently, as an evolution resumes it
        backend, why = choose_backend(
            None,
            ppo,
            () if task is None else (task,),
            wandb=bool(options.wandb),  # (a population's runs log for TensorBoard themselves)
        )
        if (
            backend == "population"
            and out is not None
            and not options.overwrite
            and finished_backend(out, ppo.learner) == "sb3"
        ):
            backend = "sb3"
            why = (
                f"the finished runs in {out} were made with it (a test folder never mixes backends)"
            )
        if why is not None and notes is not None:
            notes.append(why)
        return dataclasses.replace(ppo, backend=backend)
    ppo = dataclasses.replace(ppo, backend=options.backend)
    if ppo.backend == "population":
        from ermrl.population import check_population_config

        check_population_config(ppo)
        if options.wandb:
            raise ConfigError("--wandb logs come from the sb3 backend; use --backend sb3")
    return ppo


@dataclass(frozen=True)
class TestPhase:
    """A test phase of one study, every check done: what
    [`prepare_test`][ermrl.test_phase.prepare_test] returns.

    Attributes:
        study_name: The evolution study.
        storage: Its storage URL.
        task: The task the agents train on.
        encoder: The study's encoding options (``None``: a learner with genes, no encoder).
        ppo: The settings of the study's learner, with the backend that trains its agents.
        plan: Agents, selected trial, seeds, settings and folder.
        notes: One line per reason the backend is not population, when none was asked for.
    """

    __test__ = False  # not a pytest test class

    study_name: str
    storage: str
    task: TaskConfig
    encoder: EncoderConfig | None
    ppo: PPOConfig
    plan: TestPlan
    notes: tuple[str, ...] = ()

    @property
    def metadata(self) -> dict[str, Any]:
        """What ``config.yaml`` records besides the settings: the study and the selection."""
        from ermrl.test_phase._test_phase import selection_metadata

        return {
            "study_name": self.study_name,
            "storage": self.storage,
            **selection_metadata(self.plan.chosen),
        }


def prepare_test(study_name: str, storage: str, options: TestOptions) -> TestPhase:
    """Everything ``ermrl test`` decides and checks before the first run trains.

    Args:
        study_name: The evolution study (a single-task one).
        storage: Its storage URL.
        options: The test phase's options.

    Returns:
        The test phase, ready for [`run_comparison`][ermrl.test_phase.run_comparison].

    Raises:
        ConfigError: Bad options, a study evolved on several tasks (its test is
            ``ermrl test-generalization``), seeds the selection used, or a folder holding
            runs made with other settings.
        ermrl.storage.StudyNotFound: No such study.
        ermrl.storage.StorageError: The storage cannot be opened.
    """
    from ermrl.agents import check_ppo_config, with_overrides
    from ermrl.search import study_config
    from ermrl.storage import folder_for, load_study

    study = load_study(study_name, storage)
    config = study_config(study)
    if getattr(config, "generalization", None) is not None:
        raise ConfigError(
            f"study {study_name!r} evolved on several tasks; test it on an unseen task "
            "with ermrl test-generalization --env-id ENV"
        )
    problem = config.problem
    options = dataclasses.replace(
        options, agents=choose_agents(options, config, problem.task.observe)
    )
    overrides = options.ppo_overrides()
    own = options.learner_settings().get(problem.ppo.learner, {})
    default_out = folder_for("runs", study_name)
    notes: list[str] = []
    ppo = with_backend(
        with_overrides(problem.ppo, {**overrides, **own}),
        options,
        task=problem.task,
        out=Path(options.out) if options.out else default_out,
        notes=notes,
    )
    if overrides or own:  # refused now rather than by the first run
        where = "--ppo" if overrides else f"--for-learner {problem.ppo.learner}"
        check_ppo_config(problem.task, problem.encoder, ppo, where=where)
    plan = plan_test_phase(
        options, study, config, problem.task, ppo, default_out, observe=problem.task.observe
    )
    return TestPhase(study_name, storage, problem.task, problem.encoder, ppo, plan, tuple(notes))


# Files a test phase writes before its first run finishes: a folder holding only these (and
# empty folders) is a skeleton, removed when the call that created it fails.
_SKELETON_FILES = ("config.yaml", "command.txt")


def run_in_folder(out: Path, run: Callable[[], T]) -> T:
    """Run a test phase writing to ``out``; when ``run`` fails (an error, a crash, Ctrl-C)
    before ``out`` holds anything but its skeleton (no finished run, no checkpoint), remove
    ``out`` again, and the parents this call created for it.

    Args:
        out: The test phase's folder.
        run: The test phase.

    Returns:
        What ``run`` returned.
    """
    with _removed_when_failed(out):
        return run()


@contextlib.contextmanager
def _removed_when_failed(out: Path) -> Iterator[None]:
    created = [p for p in (Path(out), *Path(out).parents) if not p.exists()]
    try:
        yield
    except BaseException:
        _remove_skeleton(created)
        raise


def _remove_skeleton(created: Sequence[Path]) -> None:
    """Remove the folders of ``created`` (``out`` first, then the parents this created) when
    ``out`` holds no file other than `_SKELETON_FILES`."""
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
