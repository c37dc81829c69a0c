"""Frozen configuration dataclasses shared by every part of ermrl.

A run's whole configuration is one [`EvolveConfig`][ermrl.config.EvolveConfig]. It is saved as a
study user attribute (``ermrl_config``) and as ``config.yaml`` next to results, so the test phase
and the analysis need only the study name and the storage URL.

Only what is generic lives here: tasks, learner settings, budgets, the search and the problem.
The test-phase agents are declared by the learners and encoders that own them and listed by
`ermrl.learners.AGENT_KINDS`. Each encoder's settings, search space, flags and agents live in its
module of [`ermrl.encoders`][ermrl.encoders] (this module sits above it and reads its registry); the
names every layer needs ([`ConfigError`][ermrl.config.ConfigError], [`Range`][ermrl.config.Range],
the limits, ...) come from `ermrl._config_base`. Both are re-exported, so
``from ermrl.config import ReservoirParams`` keeps working.

Derived values are properties, never fields filled in after parsing.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

from ermrl._config_base import (
    BACKENDS,
    FITNESS_MODES,
    MAX_EPISODES,
    MAX_N_ENVS,
    MAX_SEEDS,
    MAX_TRAINING_STEPS,
    MAX_TRIALS,
    MAX_UNITS,
    PRUNERS,
    RESET_MODES,
    STARTS,
    AgentKind,
    ConfigError,
    FitnessMode,
    ObserveMode,
    PrunerName,
    Range,
    ResetMode,
    SearchSpace,
    StartName,
    TaskConfig,
    _box_center,
    _box_contains,
    _check_steps,
)
from ermrl.encoders import (
    BIAS_INITS,
    ENCODERS,
    EncoderConfig,
    EncoderParams,
    EncoderSpace,
    PerReservoirSpace,
    ReservoirParams,
    ReservoirSpace,
    RTUParams,
    RTUSpace,
    encoder_families,
    encoder_of_family,
    reference_encoder,
)
from ermrl.encoders._reservoir import BiasInit

_PerReservoirSpace = PerReservoirSpace  # its name before encoders owned it

__all__ = [
    "BACKENDS",
    "BIAS_INITS",
    "FAMILIES",
    "FITNESS_MODES",
    "MAX_EPISODES",
    "MAX_N_ENVS",
    "MAX_SEEDS",
    "MAX_TRAINING_STEPS",
    "MAX_TRIALS",
    "MAX_UNITS",
    "PRUNERS",
    "RESET_MODES",
    "STARTS",
    "AgentKind",
    "BiasInit",
    "BudgetConfig",
    "ConfigError",
    "EncoderConfig",
    "EncoderParams",
    "EncoderSpace",
    "EvolveConfig",
    "FitnessMode",
    "GeneralizationConfig",
    "GeneralizationTask",
    "LearnerSpace",
    "NormalizeConfig",
    "ObserveMode",
    "PPOConfig",
    "Problem",
    "PrunerName",
    "Range",
    "ReservoirParams",
    "ReservoirSpace",
    "ResetMode",
    "RTUParams",
    "RTUSpace",
    "SearchConfig",
    "SearchSpace",
    "SearchSpaceConfig",
    "StartName",
    "TaskConfig",
    "from_dict",
    "to_dict",
]

# The encoders' families when this module was imported ([`encoder_families`][ermrl.encoders.encoder_families]
# reads the registry as it is now).
FAMILIES: tuple[str, ...] = encoder_families()


def _reference_family() -> str:
    return reference_encoder().family


@dataclass(frozen=True)
class NormalizeConfig:
    """Running normalization of observations and rewards (SB3's ``VecNormalize``).

    rl-baselines3-zoo's ``normalize`` key: ``true`` means these defaults, a mapping sets some of
    them. The wrapper is the outermost one, so with a reservoir it normalizes the reservoir
    states the policy sees; episode returns are still recorded raw. Reward normalization uses
    PPO's own ``gamma`` for its running discounted return, as the zoo does. Evaluation and
    replays use the statistics reached at the end of training, frozen, with raw rewards.

    Attributes:
        norm_obs: Normalize the policy's input by a running mean and variance.
        norm_reward: Divide rewards by the running standard deviation of the discounted return.
        clip_obs: Clip normalized observations to ``[-clip_obs, clip_obs]``.
        clip_reward: Clip normalized rewards to ``[-clip_reward, clip_reward]``.
        epsilon: Added to variances before the square root.
    """

    norm_obs: bool = True
    norm_reward: bool = True
    clip_obs: float = 10.0
    clip_reward: float = 10.0
    epsilon: float = 1e-8

    def __post_init__(self) -> None:
        for name in ("norm_obs", "norm_reward"):
            value = getattr(self, name)
            if not isinstance(value, bool):
                raise ConfigError(f"normalize: {name} must be true or false, got {value!r}")
        if not (self.norm_obs or self.norm_reward):
            raise ConfigError(
                "normalize: norm_obs and norm_reward are both false; use normalize: false instead"
            )
        for name in ("clip_obs", "clip_reward", "epsilon"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"normalize: {name} must be a number, got {value!r}")
            if not (value > 0 and math.isfinite(value)):
                raise ConfigError(f"normalize: {name} must be positive, got {value}")


@dataclass(frozen=True)
class PPOConfig:
    """An inner learner's settings (PPO's, or those of another learner of
    [`ermrl.learners`][ermrl.learners]).

    Attributes:
        n_envs: Environments stepped in lockstep by one agent (a ``DummyVecEnv``). PPO collects
            ``n_steps * n_envs`` transitions per update; more envs means fewer, larger updates
            for the same budget.
        hyperparams: Keyword arguments for ``PPO(...)`` on top of SB3's defaults, resolved from the
            packaged YAML table and command-line overrides (see [`ermrl.agents`][ermrl.agents]).
        torch_threads: ``torch.set_num_threads`` for each training process (1 is fastest for the
            small MLPs used here and avoids oversubscription when seeds run in parallel).
        device: Torch device; ermrl runs everything on the CPU by default.
        normalize: Wrap the environment in ``VecNormalize`` (rl-baselines3-zoo's ``normalize``
            key); ``None``: no normalization. Left out of [`to_dict`][ermrl.config.to_dict] while
            ``None``, so configs stored before it existed are unchanged.
        learner: The inner learner that takes these settings (a name of
            `ermrl.learners.LEARNERS`; ``hyperparams`` are its algorithm's arguments).
            Left out of [`to_dict`][ermrl.config.to_dict] while ``"ppo"``, so configs stored before
            learners were plug-ins read as PPO, unchanged.
        backend: What trains the agents: ``"sb3"`` (one Stable-Baselines3 process per agent, the
            default) or ``"population"`` ([`ermrl.population`][ermrl.population]: a whole
            generation's agents in lockstep, PPO only). Part of a study's stored configuration, so a
            study never mixes backends; left out of [`to_dict`][ermrl.config.to_dict] while
            ``"sb3"``.
    """

    n_envs: int = 1
    hyperparams: Mapping[str, Any] = field(default_factory=dict)
    torch_threads: int = 1
    device: str = "cpu"
    normalize: NormalizeConfig | None = field(default=None, metadata={"omit_if_default": True})
    learner: str = field(default="ppo", metadata={"omit_if_default": True})
    backend: str = field(default="sb3", metadata={"omit_if_default": True})

    def __post_init__(self) -> None:
        if not isinstance(self.learner, str) or not self.learner:
            raise ConfigError(f"learner must be a learner's name, got {self.learner!r}")
        if self.backend not in BACKENDS:
            raise ConfigError(f"unknown backend {self.backend!r}; choose one of {BACKENDS}")
        if self.backend == "population" and self.learner != "ppo":
            raise ConfigError(
                f"the population backend trains the ppo learner only, not {self.learner!r}; "
                "use --backend sb3"
            )
        if not 1 <= self.n_envs <= MAX_N_ENVS:
            raise ConfigError(f"n_envs must be in [1, {MAX_N_ENVS}], got {self.n_envs}")
        if self.torch_threads < 1:
            raise ConfigError(f"torch_threads must be >= 1, got {self.torch_threads}")


@dataclass(frozen=True)
class BudgetConfig:
    """How long one agent trains and how its return is measured.

    Attributes:
        training_steps: Environment steps per agent (summed over ``n_envs``).
        fitness: ``"last"``: mean return of the last ``n_last_episodes`` training episodes (the
            paper's measure); ``"eval"``: mean return of ``n_eval_episodes`` deterministic
            episodes on a separate environment after training.
        n_last_episodes: Training episodes averaged by the ``"last"`` measure.
        n_eval_episodes: Deterministic episodes run by the ``"eval"`` measure.
        n_reports: Intermediate returns reported to the pruner during training.
    """

    training_steps: int
    fitness: FitnessMode = "last"
    n_last_episodes: int = 10
    n_eval_episodes: int = 5
    n_reports: int = 4

    def __post_init__(self) -> None:
        _check_steps("training steps", self.training_steps)
        if self.fitness not in FITNESS_MODES:
            raise ConfigError(f"fitness must be one of {FITNESS_MODES}, got {self.fitness!r}")
        for name in ("n_last_episodes", "n_eval_episodes"):
            value = getattr(self, name)
            if not 1 <= value <= MAX_EPISODES:
                raise ConfigError(f"{name} must be in [1, {MAX_EPISODES}], got {value}")
        if self.n_reports < 0:
            raise ConfigError(f"n_reports must be >= 0, got {self.n_reports}")


@dataclass(frozen=True)
class LearnerSpace:
    """The evolved genes of an inner learner (``evolve --learner hebbian``): data, not code.

    Evolution then shapes the learner itself, plasticity included, and the agent sees the raw
    (masked) observation: the study has no encoder. Each gene is a named
    [`Range`][ermrl.config.Range]; the learner turns a point into settings
    ([`ermrl.learners.Learner.decode_genes`][ermrl.learners.Learner.decode_genes]), so search code
    never handles a learner's own settings. The space has a fixed dimension, so that CMA-ES works; a
    categorical choice (the Hebbian learner's baseline) is fixed per study through the learner's
    settings (``--ppo baseline=critic``).

    Attributes:
        learner: The learner whose genes these are (a name of `ermrl.learners.LEARNERS`).
        genes: Gene name -> search range, in order.
        reference: The unevolved genes: the study's own learner settings (the learner's table
            for the task and ``--ppo``) as gene values, what ``random-<learner>`` trains with.
            Its trial (``--reference-trial``) is clipped into the box.
    """

    learner: str
    genes: Mapping[str, Range]
    reference: Mapping[str, float]

    n_reservoirs: ClassVar[int] = 0

    def __post_init__(self) -> None:
        if not self.genes:
            raise ConfigError(f"learner {self.learner!r} has no genes to evolve")
        if set(self.reference) != set(self.genes):
            raise ConfigError(
                f"the reference genes {sorted(self.reference)} must be the genes "
                f"{sorted(self.genes)}"
            )
        for name, value in self.reference.items():
            if not math.isfinite(value):
                raise ConfigError(f"reference gene {name} must be finite, got {value}")

    @property
    def family(self) -> str:
        """What the study evolves: the learner's name (the test phase's agents follow it)."""
        return self.learner

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(self.genes)

    def ranges(self) -> dict[str, Range]:
        return dict(self.genes)

    def reference_params(self) -> dict[str, float]:
        """The reference genes clipped into the box (a gene whose default lies outside a
        log-scale range, as an l2 of 0, takes the nearest bound)."""
        return {
            name: min(max(float(self.reference[name]), r.low), r.high)
            for name, r in self.genes.items()
        }

    def center_params(self) -> dict[str, float]:
        return _box_center(self.genes)

    def contains(self, params: Mapping[str, float]) -> bool:
        return _box_contains(self.genes, params)

    def values(self, params: Mapping[str, float]) -> dict[str, float]:
        """A trial's gene values, in gene order.

        Raises:
            ConfigError: a gene is missing.
        """
        try:
            return {name: float(params[name]) for name in self.genes}
        except KeyError as err:
            raise ConfigError(f"gene {err.args[0]!r} missing from {dict(params)}") from err


SearchSpaceConfig = EncoderSpace | LearnerSpace


@dataclass(frozen=True)
class SearchConfig:
    """The outer loop: how candidates are proposed.

    Attributes:
        sampler: ``cmaes`` (default), ``tpe`` or ``random``.
        sampler_seed: Seed of the sampler (``None``: nondeterministic).
        restart: CMA-ES restart strategy: ``none``, ``ipop`` or ``bipop``.
        popsize: CMA-ES population size (``None``: CMA-ES's default, 4 + 3 ln(dim)).
        pruner: ``none``, ``median`` or ``halving``; prunes on intermediate training returns.
        n_trials: Total trials of the study, all workers together.
        start: Where CMA-ES starts: ``center`` (the centre of the log-scaled box, as the
            ER-MRL paper's code did; the default, which was not worse than ``reference`` in
            the science benchmark's runs once the reference competes as a trial) or ``reference``
            (the unevolved reference reservoir, reservoirpy's defaults sr = lr = input_scaling
            = 1, clipped into the box; better for a handful of trials).
        reference_trial: Queue the unevolved reference reservoir as the study's first trial, so
            that it competes with the evolved candidates (and is told to CMA-ES like them).
        reevaluate_top: After the budget, re-train the ``reevaluate_top`` best trials (and the
            reference trial) on fresh seeds; the test phase then uses that ranking. 0: off.
        reevaluate_seeds: Seeds per re-evaluated candidate.
        reevaluate_steps: Training steps of a re-evaluation run (``None``: the evolution
            budget; the test budget removes the budget mismatch at a higher cost).
    """

    sampler: str = "cmaes"
    sampler_seed: int | None = None
    restart: str = "none"
    popsize: int | None = None
    pruner: PrunerName = "none"
    n_trials: int = 100
    start: StartName = "center"
    reference_trial: bool = True
    reevaluate_top: int = 0
    reevaluate_seeds: int = 3
    reevaluate_steps: int | None = None

    def __post_init__(self) -> None:
        if self.sampler not in ("cmaes", "tpe", "random"):
            raise ConfigError(f"unknown sampler {self.sampler!r}; choose cmaes, tpe or random")
        if self.restart not in ("none", "ipop", "bipop"):
            raise ConfigError(f"unknown restart strategy {self.restart!r}")
        if self.restart != "none" and self.sampler != "cmaes":
            raise ConfigError("--restart applies to the cmaes sampler only")
        if self.popsize is not None and self.popsize < 2:
            raise ConfigError(f"popsize must be >= 2, got {self.popsize}")
        if self.pruner not in PRUNERS:
            raise ConfigError(f"unknown pruner {self.pruner!r}; choose one of {PRUNERS}")
        if not 1 <= self.n_trials <= MAX_TRIALS:
            raise ConfigError(f"n_trials must be in [1, {MAX_TRIALS}], got {self.n_trials}")
        if self.start not in STARTS:
            raise ConfigError(f"unknown CMA-ES start {self.start!r}; choose one of {STARTS}")
        if self.reevaluate_top < 0:
            raise ConfigError(f"reevaluate_top must be >= 0, got {self.reevaluate_top}")
        if not 1 <= self.reevaluate_seeds <= MAX_SEEDS:
            raise ConfigError(
                f"reevaluate_seeds must be in [1, {MAX_SEEDS}], got {self.reevaluate_seeds}"
            )
        if self.reevaluate_steps is not None:
            _check_steps("reevaluate_steps", self.reevaluate_steps)


@dataclass(frozen=True)
class Problem:
    """How the fitness of a reservoir is computed (independent of how candidates are proposed).

    Attributes:
        task: The environment.
        encoder: Encoding options; its ``reservoirs`` are replaced by each candidate's.
            ``None``: no encoder (a study of a learner's genes,
            [`LearnerSpace`][ermrl.config.LearnerSpace]).
        ppo: Agent settings.
        budget: Training budget and fitness measure.
        seeds: Training seeds; fitness is the mean over them.
    """

    task: TaskConfig
    encoder: EncoderConfig | None
    ppo: PPOConfig
    budget: BudgetConfig
    seeds: tuple[int, ...] = (0, 1, 2)

    def __post_init__(self) -> None:
        if not self.seeds:
            raise ConfigError("at least one seed is needed")
        if len(self.seeds) > MAX_SEEDS:
            raise ConfigError(f"at most {MAX_SEEDS} seeds are allowed, got {len(self.seeds)}")
        if len(set(self.seeds)) != len(self.seeds):
            raise ConfigError(f"seeds must be distinct, got {self.seeds}")


@dataclass(frozen=True)
class GeneralizationTask:
    """One task of a multi-task (generalization) problem, with its normalization references.

    Attributes:
        task: The environment and observation mask.
        ppo: PPO settings resolved for this env (SB3 defaults for MuJoCo).
        random_return: R_random, the mean episodic return of a uniformly random policy.
        target_return: R_target, the documented reference return that normalizes to 1.
    """

    task: TaskConfig
    ppo: PPOConfig
    random_return: float
    target_return: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.random_return) and math.isfinite(self.target_return)):
            raise ConfigError(f"{self.task.env_id}: reference returns must be finite")
        if self.target_return == self.random_return:
            raise ConfigError(
                f"{self.task.env_id}: the target return equals the random return "
                f"({self.target_return:g}), so the normalized return is undefined"
            )

    def normalize(self, value: float) -> float:
        """``(value - random_return) / (target_return - random_return)``: 0 random, 1 target."""
        return (value - self.random_return) / (self.target_return - self.random_return)


@dataclass(frozen=True)
class GeneralizationConfig:
    """The task set of ``evolve-generalization``.

    A candidate's fitness is the mean over tasks of the normalized return
    ``(R - R_random) / (R_target - R_random)``, where each task's ``R`` is the mean over the
    problem's seeds. Every task uses the same reservoirs: the same hyperparameters and, for a
    given seed, the same recurrent weights ``W`` and bias; only the input matrix ``Win`` is drawn
    per task (its shape depends on the task's observation and action sizes).

    Attributes:
        tasks: The tasks, in order.
        suite: Name of the suite they come from (``None`` for an explicit list of ids).
        scores: The reference table the returns were read from (``packaged`` or a path).
        target_column: The table column used as R_target (``target`` or ``provisional_target``).
        ppo_overrides: ``--ppo`` overrides applied on top of each env's table entry (also applied
            to the env of a generalization test).
        n_envs: Explicit ``--n-envs`` (``None``: each env's table value).
        hyperparams: The PPO table used (``None``: the packaged one).
    """

    tasks: tuple[GeneralizationTask, ...]
    suite: str | None = None
    scores: str = "packaged"
    target_column: str = "target"
    ppo_overrides: Mapping[str, Any] = field(default_factory=dict)
    n_envs: int | None = None
    hyperparams: str | None = None

    def __post_init__(self) -> None:
        if not self.tasks:
            raise ConfigError("a generalization problem needs at least one task")
        ids = self.env_ids
        if len(set(ids)) != len(ids):
            raise ConfigError(f"each task may appear once, got {', '.join(ids)}")

    @property
    def env_ids(self) -> tuple[str, ...]:
        return tuple(t.task.env_id for t in self.tasks)


@dataclass(frozen=True)
class EvolveConfig:
    """Everything an evolution run needs; stored in the study so that it can be resumed or tested.

    Attributes:
        problem: How fitness is computed.
        space: What is searched: an encoder's space, or a learner's genes
            ([`LearnerSpace`][ermrl.config.LearnerSpace], with no encoder).
        search: How it is searched.
        n_procs: Processes that train a trial's seeds in parallel.
        generalization: The task set of a multi-task run (``evolve-generalization``); then
            ``problem`` holds the shared encoder, budget and seeds, and its ``task``/``ppo``
            are the first task's. ``None`` (single task) is left out of
            [`to_dict`][ermrl.config.to_dict].
    """

    problem: Problem
    space: SearchSpaceConfig
    search: SearchConfig
    n_procs: int = 1
    generalization: GeneralizationConfig | None = field(
        default=None, metadata={"omit_if_default": True}
    )

    def __post_init__(self) -> None:
        if self.n_procs < 1:
            raise ConfigError(f"n_procs must be >= 1, got {self.n_procs}")
        if self.search.pruner != "none" and self.n_procs > 1:
            raise ConfigError(
                "pruning reads intermediate returns while a trial's seeds train one after "
                "another: use --n-procs 1 with --pruner (or run more workers instead)"
            )
        if self.search.pruner != "none" and self.problem.ppo.backend == "population":
            raise ConfigError(
                "the population backend trains a whole generation at once and reports no "
                "intermediate returns: use --pruner none with --backend population"
            )
        encoder = self.problem.encoder
        if isinstance(self.space, LearnerSpace):
            if encoder is not None:
                raise ConfigError(
                    f"a study of the {self.space.learner} learner's genes has no encoder "
                    "(the learner's own network is the evolved one)"
                )
            if self.space.learner != self.problem.ppo.learner:
                raise ConfigError(
                    f"the genes of learner {self.space.learner!r} cannot evolve learner "
                    f"{self.problem.ppo.learner!r}"
                )
            if self.generalization is not None:
                raise ConfigError(
                    "evolve-generalization evolves encoders only; evolve a learner's genes "
                    "with evolve"
                )
        elif encoder is None:
            raise ConfigError("an encoder's search space needs the problem's encoder")
        elif self.space.n_reservoirs != encoder.n_reservoirs:
            raise ConfigError("the encoder and the search space disagree on n_reservoirs")
        elif self.space.family != encoder.family:
            raise ConfigError("the encoder and the search space are of different families")
        if self.generalization is not None and self.problem.task not in (
            t.task for t in self.generalization.tasks
        ):
            raise ConfigError("the problem's task must be one of the generalization tasks")

    @property
    def default_study_name(self) -> str:
        task = self.problem.task
        # A namespaced env id (``MyNamespace/Task-v0``) keeps its namespace with "-" for "/":
        # a study name names folders of results, so it holds no path separator.
        env = task.env_id.replace("/", "-")
        parts = [env, task.observe, f"{self.problem.budget.training_steps}steps"]
        if self.space.family != _reference_family():
            parts.append(self.space.family)
        tag = getattr(self.space, "study_tag", "")  # a variant of its family (multi-timescale)
        if tag:
            parts.append(str(tag))
        if self.space.n_reservoirs > 1:
            parts.append(f"{self.space.n_reservoirs}res")
        return "__".join(parts)

    def to_dict(self) -> dict[str, Any]:
        return to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> EvolveConfig:
        return from_dict(cls, data)


# --------------------------------------------------------------------------------------------
# (De)serialization of the nested dataclasses to plain JSON/YAML-friendly dicts.

_T = TypeVar("_T")


def to_dict(obj: Any) -> Any:
    """Convert nested frozen dataclasses (and tuples, mappings) to JSON-friendly values."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {
            f.name: to_dict(getattr(obj, f.name))
            for f in dataclasses.fields(obj)
            # Optional additions keep older configs' dicts unchanged while unset.
            if not (f.metadata.get("omit_if_default") and getattr(obj, f.name) == f.default)
        }
    if isinstance(obj, Mapping):
        return {str(k): to_dict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    return obj


def _encoder(family: Any) -> Any:
    """The registered encoder of a stored ``family`` (none stored: the reference encoder).

    Raises:
        ConfigError: no registered encoder has that family (a name read from a stored
            configuration is checked against the registry, never imported).
    """
    encoder = encoder_of_family(None if family is None else str(family))
    if encoder is None:
        raise ConfigError(
            f"a stored configuration names encoder family {family!r}, which no registered "
            f"encoder has ({', '.join(e.family for e in ENCODERS.values())})"
        )
    return encoder


def _field_class(cls: type, key: str) -> type | None:
    """The dataclass a field of ``cls`` holds, read from its annotation (``Range``,
    ``Range | None``, an encoder's own range class, ...); ``None`` if it holds none."""
    hint = typing.get_type_hints(cls).get(key)
    options = typing.get_args(hint) or (hint,)
    found = [o for o in options if isinstance(o, type) and dataclasses.is_dataclass(o)]
    return found[0] if len(found) == 1 else None


def from_dict(cls: type[_T], data: Mapping[str, Any]) -> _T:
    """Inverse of [`to_dict`][ermrl.config.to_dict] for the dataclasses of this module and of the
    encoders.

    An encoder's search space and reservoir settings are read as the classes of the registered
    encoder whose ``family`` they store (`ermrl.encoders.ENCODERS`; none stored: the
    reference encoder's, as echo state networks were stored); their range fields follow their
    annotations.
    """
    hints = {
        (EvolveConfig, "problem"): Problem,
        (EvolveConfig, "search"): SearchConfig,
        (Problem, "task"): TaskConfig,
        (Problem, "encoder"): EncoderConfig,
        (Problem, "ppo"): PPOConfig,
        (Problem, "budget"): BudgetConfig,
        (EvolveConfig, "generalization"): GeneralizationConfig,
        (GeneralizationTask, "task"): TaskConfig,
        (GeneralizationTask, "ppo"): PPOConfig,
        (PPOConfig, "normalize"): NormalizeConfig,
    }
    kwargs: dict[str, Any] = {}
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    if cls is SearchConfig:
        # Studies stored before these options existed started at the box centre, without the
        # reference trial: read them as what they were.
        data = {"start": "center", "reference_trial": False, **data}
    encoder_owned = any(cls is e.space_cls for e in ENCODERS.values())
    for key, value in data.items():
        if key not in names:
            continue  # tolerate fields added by newer versions
        sub = hints.get((cls, key))
        if cls is EvolveConfig and key == "space" and isinstance(value, Mapping):
            sub = LearnerSpace if "learner" in value else _encoder(value.get("family")).space_cls
        elif encoder_owned:
            sub = _field_class(cls, key)
        if cls is LearnerSpace and key == "genes":
            value = {str(k): from_dict(Range, v) for k, v in value.items()}
        elif cls is LearnerSpace and key == "reference":
            value = {str(k): float(v) for k, v in value.items()}
        elif sub is not None and value is not None:
            value = from_dict(sub, value)
        elif cls is EncoderConfig and key == "reservoirs":
            value = tuple(from_dict(_encoder(v.get("family")).params_cls, v) for v in value)
        elif cls is Problem and key == "seeds":
            value = tuple(int(v) for v in value)
        elif cls is PPOConfig and key == "hyperparams":
            value = dict(value)
        elif cls is GeneralizationConfig and key == "tasks":
            value = tuple(from_dict(GeneralizationTask, v) for v in value)
        elif cls is GeneralizationConfig and key == "ppo_overrides":
            value = dict(value)
        kwargs[key] = value
    return cls(**kwargs)
