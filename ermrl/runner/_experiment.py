"""A whole experiment in one YAML file: evolution, re-evaluation, test phase and report.

An experiment file composes ermrl's own commands; it never copies their logic. Each stage is a
mapping whose keys are the options of the command that runs it, spelled as the fields of their
schema (``n_trials`` for ``--n-trials``, ``fixed_input_scaling: true`` for a flag), so
everything a command accepts an experiment accepts, and a key no command knows is refused with
the nearest valid one. The stages:

- ``evolve``: ``ermrl evolve`` once per entry of ``tasks`` (one study per task, the same
  settings for all), or ``ermrl evolve-generalization`` when the stage names a ``suite`` or
  ``env_ids`` (one study over the task set);
- ``reevaluate``: ``top``, ``seeds`` and ``steps``, passed to the same command as
  ``--reevaluate-top/--reevaluate-seeds/--reevaluate-steps`` (the worker that finds the budget
  spent re-trains the best candidates; see ``ermrl evolve --help``);
- ``test``: ``ermrl test`` per task, or ``ermrl test-generalization`` once per entry of its
  ``env_ids`` for a generalization study;
- ``report``: ``ermrl report`` per test folder.

``variants`` holds named overrides (for example ``quick`` for CI), merged key by key over the
stages; a variant's results go to ``<out>/<variant>``, so they never mix with the full run's.

The study and the run folders are the state: a stage is done when the storage or the folders
say so, and running the file again resumes the first unfinished stage.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from ermrl._io import load_yaml
from ermrl._schema import keys_of, nearest, to_argv, validate
from ermrl.config import ConfigError
from ermrl.runner._requests import (
    EvolveRequest,
    ReportRequest,
    TestGeneralizationRequest,
    TestRequest,
)
from ermrl.storage import StudyNameError, folder_for

if TYPE_CHECKING:
    from ermrl.config import EvolveConfig

__all__ = [
    "ExperimentError",
    "ExperimentFile",
    "Step",
    "TOP_LEVEL_KEYS",
    "estimate_seconds",
    "experiment_plan",
    "format_duration",
    "load_experiment",
    "resolved_document",
    "throughput",
]

#: Keys of an experiment file, each with what it holds.
TOP_LEVEL_KEYS: dict[str, str] = {
    "name": "the experiment's name (required); results go to runs/<name> unless `out` is set",
    "description": "free text: the question, and how the scale differs from the paper's",
    "claim": "the claim this experiment tests, quoted from its source (the reproduction page)",
    "out": "results folder (default: runs/<name>)",
    "storage": "Optuna storage of the studies (default: sqlite:///<out>/ermrl.db)",
    "publish": "folder that receives the plain-file results (summary, per-seed CSV, trials)",
    "tasks": "env ids of a single-task experiment (one study each, the same settings)",
    "evolve": "ermrl evolve (or evolve-generalization) options",
    "reevaluate": "top, seeds, steps: re-train the best candidates on fresh seeds",
    "test": "ermrl test (or test-generalization) options",
    "report": "ermrl report options",
    "variants": "named overrides of the stages, e.g. quick (selected with --variant)",
    "verdict": "the rule of the reproduction page's verdicts: questions, alpha, correction, "
    "primary metric, the date it was adopted (see docs/experiments.md, Verdicts)",
}
STAGES = ("evolve", "reevaluate", "test", "report")
REEVALUATE_KEYS = {
    "top": "reevaluate_top",
    "seeds": "reevaluate_seeds",
    "steps": "reevaluate_steps",
}
# Options ermrl run sets itself (per task and folder); the file must not set them.
_RESERVED = {
    "evolve": {"env_id", "storage", "study_name", "quiet", "help"},
    "test": {"storage", "study_name", "out", "env_id", "quiet", "help"},
    "report": {"storage", "study_name", "runs", "out", "quiet", "help"},
}


class ExperimentError(ConfigError):
    """An experiment file that cannot run: one line, naming the file and the key."""


#: How often a run with ``publish:`` writes its snapshot by itself (seconds).
DEFAULT_SNAPSHOT_EVERY = 600.0

#: The most bytes of an experiment file read (a device or a huge file is refused, not read).
MAX_FILE_BYTES = 1 << 20


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key written twice in one mapping (PyYAML keeps the
    last silently). Keys brought in by a merge (``<<: *base``) may still be overridden."""


def _construct_unique_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode) -> Any:
    seen: set[Any] = set()
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            duplicate = key in seen
        except TypeError:  # an unhashable key: PyYAML refuses it below
            continue
        if duplicate:
            raise yaml.constructor.ConstructorError(
                None, None, f"key {key!r} appears twice in one mapping", key_node.start_mark
            )
        seen.add(key)
    return loader.construct_mapping(node)


_UniqueKeyLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
    _construct_unique_mapping,
)


def _read_text(path: Path) -> str:
    """The file's text, read as UTF-8 and at most `MAX_FILE_BYTES` (one-line errors)."""
    try:
        with path.open("rb") as file:
            data = file.read(MAX_FILE_BYTES + 1)
    except OSError as err:
        raise ExperimentError(f"{path}: cannot read ({err.strerror or err})") from None
    if len(data) > MAX_FILE_BYTES:
        raise ExperimentError(
            f"{path}: larger than {MAX_FILE_BYTES // (1 << 20)} MiB; an experiment file is a "
            "short YAML file"
        )
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ExperimentError(
            f"{path}: not UTF-8 text (byte {err.object[err.start]:#04x} at offset {err.start})"
        ) from None


def _path_value(value: Any, key: str, path: Path) -> Path | None:
    """A folder named by the file (``out``, ``publish``): a non-empty string, or ``None``."""
    if value is None:
        return None
    if not isinstance(value, str) or not value.strip():
        raise ExperimentError(f"{path}: {key}: a folder path (a string) is expected, got {value!r}")
    return Path(value)


# ---------------------------------------------------------------------------------------------
# Loading


def _merge(base: Any, over: Any) -> Any:
    """``over`` merged into ``base`` key by key (mappings), else ``over``."""
    if isinstance(base, Mapping) and isinstance(over, Mapping):
        out = dict(base)
        for key, value in over.items():
            out[key] = _merge(base.get(key), value) if key in base else copy.deepcopy(value)
        return out
    return copy.deepcopy(over)


@dataclass(frozen=True)
class TaskLine:
    """One task of a single-task experiment, with its own scale overrides (if any)."""

    env_id: str
    overrides: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)


@dataclass(frozen=True)
class ExperimentFile:
    """A parsed experiment file (variant applied): what the plan reads. Its Python face,
    [`Experiment`][ermrl.runner.Experiment], adds ``plan``, ``run`` and ``result``.

    Attributes:
        path: The file.
        name: The experiment's name.
        variant: The variant applied (``None``: the file as written).
        out: Results folder.
        storage: Optuna storage URL.
        publish: Folder for the plain-file results (``None``: not published).
        tasks: Single-task experiments: one line per task; empty for a generalization one.
        stages: ``{"evolve" | "reevaluate" | "test" | "report": options}``.
        document: The file's mapping with the variant merged in.
        tensorboard: ``ermrl run --tensorboard`` was given: the evolve and test commands get
            it, so the plan checks them as they will run (on either backend).
        wandb: ``ermrl run --wandb`` was given: the evolve and test commands get it, so the
            plan checks and estimates a test stage as it will run (sb3).
        test_agents: ``ermrl run --agents``: each test stage trains only these of its agents
            (empty: all), a piece of the phase that fits in one sitting.
        test_seeds: ``ermrl run --seeds``: each test stage trains only these of its seeds
            (empty: all).
    """

    path: Path
    name: str
    variant: str | None
    out: Path
    storage: str
    publish: Path | None
    tasks: tuple[TaskLine, ...]
    stages: Mapping[str, Mapping[str, Any]]
    document: Mapping[str, Any]
    tensorboard: bool = False
    wandb: bool = False
    test_agents: tuple[str, ...] = ()
    test_seeds: tuple[int, ...] = ()

    @property
    def generalization(self) -> bool:
        """Whether evolution runs on a task set (``suite`` or ``env_ids`` in ``evolve``)."""
        evolve = self.stages.get("evolve", {})
        return "suite" in evolve or "env_ids" in evolve


def _mapping(value: Any, where: str) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ExperimentError(f"{where}: expected a mapping of options, got {value!r}")
    bad = [k for k in value if not isinstance(k, str)]
    if bad:
        raise ExperimentError(f"{where}: option names must be words, got {bad[0]!r}")
    return dict(value)


def _read_document(path: Path) -> Mapping[str, Any]:
    """The file's mapping, its top-level keys checked (`TOP_LEVEL_KEYS`).

    Raises:
        ExperimentError: unreadable file, not YAML, not a mapping, or an unknown key (with the
            nearest valid one).
    """
    text = _read_text(path)
    try:
        doc = load_yaml(text, _UniqueKeyLoader)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise ExperimentError(f"{path}:{where} not valid YAML ({problem})") from None
    if not isinstance(doc, Mapping):
        raise ExperimentError(f"{path}: an experiment file is a mapping (name:, evolve:, ...)")
    for key in doc:
        if key not in TOP_LEVEL_KEYS:
            raise ExperimentError(f"{path}: unknown key {key!r}{nearest(str(key), TOP_LEVEL_KEYS)}")
    return doc


def _apply_variant(
    doc: Mapping[str, Any], variant: str | None, path: Path
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The document without its ``variants``, with ``variant``'s overrides merged in.

    Args:
        doc: The file's mapping.
        variant: A key of its ``variants`` (``None``: the file as written).
        path: The file (for messages).

    Returns:
        The merged document, and the variant's own overrides (empty without a variant).

    Raises:
        ExperimentError: ``variants`` is not a mapping, no such variant, or a key a variant
            cannot set.
    """
    variants = _mapping(doc.get("variants"), f"{path}: variants")
    base = {k: v for k, v in doc.items() if k != "variants"}
    if variant is None:
        return base, {}
    if variant not in variants:
        have = ", ".join(variants) or "none"
        raise ExperimentError(f"{path}: no variant {variant!r} (variants: {have})")
    over = _mapping(variants[variant], f"{path}: variants.{variant}")
    for key in over:
        if key not in TOP_LEVEL_KEYS or key in ("variants", "name"):
            valid = [k for k in TOP_LEVEL_KEYS if k not in ("variants", "name")]
            raise ExperimentError(
                f"{path}: variants.{variant}: unknown key {key!r}{nearest(str(key), valid)}"
            )
    return _merge(base, over), over


def _check_task_list(
    tasks: tuple[TaskLine, ...],
    stages: Mapping[str, Mapping[str, Any]],
    base: Mapping[str, Any],
    path: Path,
) -> None:
    """Check that the file names its tasks the way its kind of experiment needs.

    A single-task experiment lists ``tasks``; a generalization one (``evolve.suite`` or
    ``evolve.env_ids``) lists none, and names its test tasks in ``test.env_ids`` when it has
    a ``test`` stage.

    Raises:
        ExperimentError: tasks missing, or given where they do not belong.
    """
    generalization = "suite" in stages["evolve"] or "env_ids" in stages["evolve"]
    if generalization and tasks:
        raise ExperimentError(
            f"{path}: tasks: a generalization experiment (evolve.suite or evolve.env_ids) has no "
            "tasks list; name the test tasks in test.env_ids"
        )
    if not generalization and not tasks:
        raise ExperimentError(
            f"{path}: tasks: list the env ids to evolve on (or give evolve.suite for "
            "generalization)"
        )
    if generalization and not stages["test"].get("env_ids") and base.get("test") is not None:
        raise ExperimentError(f"{path}: test.env_ids: name the unseen tasks to test on")


def load_experiment(path: str | Path, variant: str | None = None) -> ExperimentFile:
    """Read an experiment file and apply a variant.

    Args:
        path: The YAML file.
        variant: A key of its ``variants`` (``None``: the file as written).

    Returns:
        The experiment (not yet checked against the commands: see
        [`experiment_plan`][ermrl.runner.experiment_plan]).

    Raises:
        ExperimentError: unreadable file, unknown key (with the nearest valid one), wrong type,
            unknown variant.
    """
    if not isinstance(path, (str, Path)):
        raise ExperimentError(
            f"an experiment is a YAML file's path, got {type(path).__name__} {path!r}"
        )
    if variant is not None and not isinstance(variant, str):
        raise ExperimentError(
            f"{path}: variant is a name, got {type(variant).__name__} {variant!r}"
        )
    path = Path(path)
    base, over = _apply_variant(_read_document(path), variant, path)
    name = base.get("name")
    if not isinstance(name, str):
        raise ExperimentError(f"{path}: name: a word is required (it names the results folder)")
    try:  # the name and the variant name folders: neither may lead out of its parent
        out = _path_value(base.get("out"), "out", path) or folder_for("runs", name, "out:")
        if variant is not None and "out" not in over:
            out = folder_for(out, variant, "out:")
    except StudyNameError as err:
        raise ExperimentError(f"{path}: name: {err}") from None
    storage = base.get("storage")
    if storage is not None and (not isinstance(storage, str) or not storage.strip()):
        raise ExperimentError(
            f"{path}: storage: a storage URL (a string) is expected, got {storage!r}"
        )
    storage = storage or f"sqlite:///{out / 'ermrl.db'}"
    # A variant (a CI-sized run, say) publishes only where it says so itself.
    publish = base.get("publish") if variant is None else over.get("publish")
    stages = {s: _mapping(base.get(s), f"{path}: {s}") for s in STAGES}
    for key in stages["reevaluate"]:
        if key not in REEVALUATE_KEYS:
            raise ExperimentError(
                f"{path}: reevaluate: unknown key {key!r}{nearest(key, REEVALUATE_KEYS)}"
            )
    tasks = _tasks(base.get("tasks"), path)
    _check_task_list(tasks, stages, base, path)
    return ExperimentFile(
        path=path,
        name=name,
        variant=variant,
        out=out,
        storage=storage,
        publish=_path_value(publish, "publish", path),
        tasks=tasks,
        stages=stages,
        document=base,
    )


def _tasks(value: Any, path: Path) -> tuple[TaskLine, ...]:
    if value is None:
        return ()
    if not isinstance(value, list):
        raise ExperimentError(f"{path}: tasks: a list of env ids, got {value!r}")
    out = []
    for item in value:
        if isinstance(item, str):
            out.append(TaskLine(item))
            continue
        entry = _mapping(item, f"{path}: tasks")
        env_id = entry.pop("env_id", None)
        if not isinstance(env_id, str):
            raise ExperimentError(f"{path}: tasks: each entry is an env id or has env_id: ...")
        for key in entry:
            if key not in ("evolve", "reevaluate", "test", "report"):
                raise ExperimentError(
                    f"{path}: tasks.{env_id}: unknown key {key!r}{nearest(key, STAGES)}"
                )
        out.append(
            TaskLine(
                env_id, {k: _mapping(v, f"{path}: tasks.{env_id}.{k}") for k, v in entry.items()}
            )
        )
    ids = [t.env_id for t in out]
    if len(set(ids)) != len(ids):
        raise ExperimentError(f"{path}: tasks: each task once, got {ids}")
    return tuple(out)


# ---------------------------------------------------------------------------------------------
# Throughput and wall-time estimates


@functools.lru_cache(maxsize=1)
def _throughput_table() -> dict[str, Any]:
    """``ermrl/data/throughput.yml``, read once per process."""
    from importlib import resources

    text = resources.files("ermrl.data").joinpath("throughput.yml").read_text()
    return dict(load_yaml(text))


def throughput(env_id: str, backend: str, n_procs: int, learner: str = "ppo") -> float:
    """Estimated env steps per second of a training layout (``ermrl/data/throughput.yml``).

    Args:
        env_id: The task.
        backend: ``"population"`` or ``"sb3"``.
        n_procs: Processes (the table holds 2-process rates; 1 process runs at half of it).
        learner: The learner (some are slower per step than PPO).
    """
    table = _throughput_table()
    rates = table.get(backend) or table["sb3"]
    rate = float(rates.get(env_id, rates["default"]))
    if learner != "ppo":
        rate = float(table["sb3"].get(env_id, table["sb3"]["default"]))
        rate *= float(table.get("learner_factor", {}).get(learner, 1.0))
    return rate * min(max(n_procs, 1), 2) / 2


def format_duration(seconds: float) -> str:
    """``1h05m``, ``12m30s``, ``40s``."""
    if not math.isfinite(seconds):
        return "?"
    seconds = max(0, int(round(seconds)))
    if seconds >= 3600:
        return f"{seconds // 3600}h{(seconds % 3600) // 60:02d}m"
    if seconds >= 60:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds}s"


def _rounded(ppo: Any, steps: int) -> tuple[int, str]:
    """A run's real env steps for a budget of ``steps`` (whole rollouts of an on-policy
    learner, [`ermrl.agents.steps_trained`][ermrl.agents.steps_trained]), and the plan's note when
    they differ."""
    from ermrl.agents import steps_trained

    real = steps_trained(ppo, steps)
    if real == steps:
        return real, ""
    return real, (
        f"each run's budget of {steps:,} steps rounds up to {real:,}: whole rollouts of "
        "n_steps x n_envs, as SB3 trains"
    )


def estimate_seconds(parts: Sequence[tuple[int, float]]) -> float:
    """Wall seconds of ``(env steps, steps/s)`` parts run one after the other."""
    return sum(steps / rate for steps, rate in parts if rate > 0)


# ---------------------------------------------------------------------------------------------
# The plan


@dataclass
class Step:
    """One command of the plan.

    Attributes:
        stage: ``evolve``, ``reevaluate``, ``test`` or ``report``.
        label: The task (or task set) it is about.
        command: The ``ermrl`` subcommand.
        argv: Its arguments.
        env_steps: Env steps it trains in all (0: none).
        seconds: Estimated wall seconds for all of it.
        status: Reads the storage and folders: ``(done, remaining fraction, text)``.
        study_name: The study it reads or writes.
        folder: The folder it writes (test and report steps).
        replayed: ``(agent, seed)`` runs of a test step whose saved models the report replays
            (its dynamics section); a snapshot carries no models, so these are retrained.
        note: A line the plan prints under it (a budget rounded up to whole rollouts).
        runs: ``(agent, seed)`` runs a test step trains.
        request: What it runs, resolved from its options: the configuration objects of the
            library function that runs it (`ermrl.runner._commands`,
            `ermrl.runner._generalization``.
    """

    stage: str
    label: str
    command: str
    argv: list[str]
    env_steps: int
    seconds: float
    status: Callable[[], tuple[bool, float, str]]
    study_name: str
    folder: Path | None = None
    replayed: tuple[tuple[str, int], ...] = ()
    note: str = ""
    request: Any = None
    runs: tuple[tuple[str, int], ...] = ()

    @property
    def command_line(self) -> str:
        import shlex

        return shlex.join(["ermrl", self.command, *self.argv])


def _stage(exp: ExperimentFile, stage: str, task: TaskLine | None) -> dict[str, Any]:
    options = dict(exp.stages.get(stage, {}))
    if task is not None and stage in task.overrides:
        options = _merge(options, task.overrides[stage])
    for key in _RESERVED.get(stage, ()):
        if key in options and not (stage == "test" and key == "env_ids"):
            raise ExperimentError(
                f"{exp.path}: {stage}: {key} is set by ermrl run (per task and folder)"
            )
    return options


def experiment_plan(
    exp: ExperimentFile, *, tasks: Sequence[str] | None = None, build_agents: bool = True
) -> list[Step]:
    """Every command of the experiment, checked by the commands' own parsers and configuration.

    Nothing is written: each stage's options are parsed as its command would parse them, the
    evolution configuration is built (what PPO or the encoder would refuse is refused now), and
    a study already in the storage must have the same problem and search space.

    Args:
        exp: The experiment.
        tasks: Only these tasks (env ids; for a generalization experiment, test tasks).
        build_agents: Also build each evolution agent once on its env (the commands' own
            check); ``False`` (the dry run) checks options, tables and the storage only.

    Returns:
        The steps, in the order ``ermrl run`` runs them.

    Raises:
        ExperimentError: a key or value the commands refuse, or a study that contradicts the
            file (one line).
    """
    if exp.generalization:
        return _generalization_plan(exp, tasks, build_agents)
    chosen = list(exp.tasks)
    if tasks:
        # A task the file does not name runs with the file's settings (one set per hypothesis).
        listed = {t.env_id: t for t in exp.tasks}
        chosen = [listed.get(t, TaskLine(t)) for t in dict.fromkeys(tasks)]
    steps: list[Step] = []
    for task in chosen:
        steps += _single_task_steps(exp, task, build_agents)
    return steps


def _evolve_parts(exp: ExperimentFile, task: TaskLine | None, where: str) -> tuple[list[str], Any]:
    """The ``evolve`` (and ``reevaluate``) stage of ``task`` (``None``: the task set), validated
    by the evolve options' schema: the command line that shows it and the options.

    Raises:
        ExperimentError: An unknown key (with the nearest valid one) or a bad value.
    """
    from ermrl.runner._evolve_options import evolve_options

    cls = evolve_options(multi_task=task is None)
    given = _stage(exp, "evolve", task)
    values = _validated(cls, given, where)
    again = {REEVALUATE_KEYS[k]: v for k, v in _stage(exp, "reevaluate", task).items()}
    values_again = _validated(cls, again, f"{exp.path}: reevaluate")
    if task is None:
        tasks = [k for k in ("env_ids", "suite") if values.get(k) is not None]
        if len(tasks) != 1:
            raise ExperimentError(
                f"{where}: the task set is env_ids or suite, "
                + ("not both" if tasks else "and the stage has neither")
            )
    own = {} if task is None else {"env_id": task.env_id}
    options = cls(**own, **values, **values_again, storage=exp.storage)
    if exp.tensorboard:  # as ermrl run --tensorboard will add it
        options = dataclasses.replace(options, tensorboard=_TENSORBOARD_IN_PLAN)
    argv = ([] if task is None else ["--env-id", task.env_id]) + to_argv(cls, given, values)
    argv += to_argv(cls, again, values_again) + ["--storage", exp.storage]
    return argv, options


# What stands for ``ermrl run --tensorboard DIR`` in the options the plan checks (the stage's
# own directory is added when it runs, by ``ermrl run``), so that the plan chooses, checks and
# estimates its backend as the command will.
_TENSORBOARD_IN_PLAN = "<ermrl run --tensorboard>"


def _config_error(exp: ExperimentFile, where: str, build: Callable[[], Any]) -> Any:
    from ermrl.envs import UnknownEnvError, UnsupportedObserveError

    try:
        return build()
    except (ConfigError, UnknownEnvError, UnsupportedObserveError) as err:
        raise ExperimentError(f"{where}: {err}") from None


def _single_task_steps(exp: ExperimentFile, task: TaskLine, build_agents: bool) -> list[Step]:
    from ermrl.runner._resolve import config_from_args

    where = f"{exp.path}: {task.env_id}: evolve"
    argv, args = _evolve_parts(exp, task, where)
    notes: list[str] = []
    config = _config_error(
        exp, where, lambda: config_from_args(args, build_agent=build_agents, notes=notes)
    )
    study_name = config.default_study_name
    argv += ["--study-name", study_name]
    config = _keep_study_backend(
        exp, where, args, config, study_name,
        lambda a: config_from_args(a, build_agent=build_agents), notes,
    )  # fmt: skip
    _check_study(exp, config, study_name, where)
    request = _evolve_request(exp, args, config, study_name, notes)
    problem = config.problem
    n_seeds = len(problem.seeds)
    per_run, note = _rounded(problem.ppo, problem.budget.training_steps)
    steps_per_trial = n_seeds * per_run
    backend = problem.ppo.backend
    learner = problem.ppo.learner
    rate = throughput(task.env_id, backend, config.n_procs, learner)
    n_trials = config.search.n_trials
    evolve = Step(
        "evolve", task.env_id, "evolve", argv, n_trials * steps_per_trial,
        n_trials * steps_per_trial / rate,
        _evolve_status(exp.storage, study_name, n_trials), study_name, note=note,
        request=request,
    )  # fmt: skip
    steps = [evolve]
    search = config.search
    if search.reevaluate_top > 0:
        re_steps, _ = _rounded(
            problem.ppo, search.reevaluate_steps or problem.budget.training_steps
        )
        total = (search.reevaluate_top + 1) * search.reevaluate_seeds * re_steps
        steps.append(
            Step(
                "reevaluate",
                task.env_id,
                "evolve",
                argv,
                total,
                total / rate,
                _reevaluate_status(exp.storage, study_name),
                study_name,
                request=request,
            )  # fmt: skip
        )
    if "test" in exp.document or exp.stages["test"]:
        steps.append(
            _test_step(exp, task, study_name, config, exp.out / task.env_id / "test", None)
        )
    if "report" in exp.document or exp.stages["report"]:
        steps.append(
            _report_step(
                exp,
                task,
                study_name,
                steps[-1].folder if steps[-1].stage == "test" else None,
                exp.out / task.env_id / "report",
            )
        )
    return steps


def _validated(cls: type, given: Mapping[str, Any], where: str) -> dict[str, Any]:
    """A stage's options checked by the schema of ``cls``, as text sources are (YAML reads
    ``1e6`` as a string)."""
    try:
        return validate(cls, given, where, text=True)
    except ConfigError as err:
        raise ExperimentError(str(err)) from None


def _test_step(
    exp: ExperimentFile,
    task: TaskLine | None,
    study_name: str,
    config: Any,
    folder: Path,
    env_id: str | None,
) -> Step:
    from ermrl.learners import AGENT_KINDS
    from ermrl.test_phase import TestOptions

    label = env_id or (task.env_id if task else "")
    where = f"{exp.path}: {label}: test"
    given = {k: v for k, v in _stage(exp, "test", task).items() if k != "env_ids"}
    task_keys = set(keys_of(TestGeneralizationRequest)) if env_id else set()
    test_keys = set(keys_of(TestOptions)) - {"out"}
    for key in given:  # a key of neither: the nearest of both
        if key not in test_keys | task_keys:
            raise ExperimentError(
                f"{where}: unknown key {key!r}{nearest(key, test_keys | task_keys)}"
            )
    values = _validated(TestOptions, {k: v for k, v in given.items() if k in test_keys}, where)
    own = _validated(
        TestGeneralizationRequest, {k: v for k, v in given.items() if k in task_keys}, where
    )
    # As the test command reads them: its default agents, seeds 0-4.
    all_seeds = list(values.get("seeds") or range(5))
    agents = list(values.get("agents") or [n for n, k in AGENT_KINDS.items() if k.default])
    if exp.test_agents or exp.test_seeds:
        agents, seeds = _test_piece(exp, where, agents, all_seeds)
        values.update(agents=agents, seeds=seeds)
        given = {**given, "agents": agents, "seeds": seeds}
    argv = (["--env-id", env_id] if env_id else []) + to_argv(
        (TestOptions, TestGeneralizationRequest), given, values={**values, **own}
    )
    argv += ["--storage", exp.storage, "--study-name", study_name, "--out", str(folder)]
    if values.get("progress") is None:  # as the test command resolves it: for where stdout goes
        from ermrl._progress import default_mode

        values["progress"] = default_mode()
    options = _config_error(exp, where, lambda: TestOptions(**values, out=str(folder)))
    if exp.tensorboard:  # (a test phase logs for TensorBoard on either backend)
        options = dataclasses.replace(options, tensorboard=_TENSORBOARD_IN_PLAN)
    if exp.wandb:  # ermrl run --wandb: W&B logs through SB3's callback
        if options.backend == "population":
            raise ExperimentError(
                f"{where}: --wandb logs come from the sb3 backend, and this stage sets "
                "backend: population; set backend: sb3 in the file, or leave --wandb out"
            )
        options = dataclasses.replace(options, wandb="<ermrl run --wandb>")
    seeds = list(options.seeds or range(5))
    per_run = options.training_steps
    test_env = env_id or (task.env_id if task else "")
    backend = options.backend
    if backend is None:  # as the test command chooses (the env's spaces aside)
        from ermrl.population import population_refusal

        refused = population_refusal(config.problem.ppo, wandb=bool(options.wandb))
        backend = "sb3" if refused else "population"
    # The study's learner's runs round up to whole rollouts of its settings (another learner's
    # agents train with their own tables: counted at the budget).
    rounded, note = _rounded(config.problem.ppo, per_run)
    parts = []
    for agent in agents:
        learner = AGENT_KINDS[agent].learner or config.problem.ppo.learner
        agent_backend = backend if learner == config.problem.ppo.learner else "sb3"
        rate = throughput(test_env, agent_backend, options.n_procs, learner)
        count = rounded if learner == config.problem.ppo.learner else per_run
        parts.append((len(seeds) * count, rate))
    total = sum(n for n, _ in parts)
    replayed: tuple[tuple[str, int], ...] = ()
    if _stage(exp, "report", task).get("dynamics") and not env_id and seeds:
        from ermrl.learners import evolved_agent, unevolved_agent

        family = config.space.family
        wanted = (evolved_agent(family), unevolved_agent(family))
        # The report replays the first seed of the whole phase (a piece trains it only if
        # the piece holds it).
        replayed = tuple((a, min(all_seeds)) for a in wanted if a in agents)
        replayed = tuple((a, s) for a, s in replayed if s in seeds)
    if env_id is None:
        request: Any = TestRequest(study_name, exp.storage, options)
    else:
        request = TestGeneralizationRequest(study_name, exp.storage, env_id, options, **own)
    return Step(
        "test", label, "test-generalization" if env_id else "test", argv, total,
        estimate_seconds(parts), _test_status(folder, agents, seeds), study_name, folder,
        replayed, note, request, tuple((a, s) for a in agents for s in seeds),
    )  # fmt: skip


def _test_piece(
    exp: ExperimentFile, where: str, agents: Sequence[str], seeds: Sequence[int]
) -> tuple[list[str], list[int]]:
    """The agents and seeds of a test stage that ``ermrl run --agents/--seeds`` keeps, in the
    file's order; one the stage does not list is refused."""
    for flag, wanted, listed in (
        ("--agents", exp.test_agents, agents),
        ("--seeds", exp.test_seeds, seeds),
    ):
        unknown = [str(w) for w in wanted if w not in listed]
        if unknown:
            raise ExperimentError(
                f"{where}: {flag} {' '.join(unknown)}: not in the stage's "
                f"{flag.removeprefix('--')} ({' '.join(map(str, listed))})"
            )
    return (
        [a for a in agents if not exp.test_agents or a in exp.test_agents],
        [s for s in seeds if not exp.test_seeds or s in exp.test_seeds],
    )


def _report_step(
    exp: ExperimentFile,
    task: TaskLine | None,
    study_name: str,
    runs: Path | None,
    folder: Path,
    label: str | None = None,
) -> Step:
    name = label or (task.env_id if task else "")
    where = f"{exp.path}: {name}: report"
    given = _stage(exp, "report", task)
    values = _validated(ReportRequest, given, where)
    argv = to_argv((ReportRequest,), given, values=values)
    argv += ["--storage", exp.storage, "--study-name", study_name, "--out", str(folder)]
    if runs is not None:
        argv += ["--runs", str(runs)]
        values["runs"] = str(runs)
    request = ReportRequest(study_name, exp.storage, **{**values, "out": str(folder)})
    return Step(
        "report", name, "report", argv, 0, 30.0, _report_status(folder, runs), study_name, folder,
        request=request,
    )  # fmt: skip


def _evolve_request(
    exp: ExperimentFile, args: Any, config: Any, study_name: str, notes: list[str]
) -> EvolveRequest:
    """What an evolve step runs: its configuration and the worker's options the file gives
    (``ermrl run``'s own are added when it runs)."""
    request = EvolveRequest.from_options(config, exp.storage, study_name, args, notes=notes)
    if args.tensorboard == _TENSORBOARD_IN_PLAN:
        request = dataclasses.replace(request, tensorboard=None)
    return request


def _generalization_plan(
    exp: ExperimentFile, only: Sequence[str] | None, build_agents: bool
) -> list[Step]:
    """The steps of a generalization file: evolve (and re-evaluate) on the task set, then test
    (and report) on each test task (``only``: these test tasks)."""
    steps, config, study_name = _generalization_evolve_steps(exp, build_agents)
    env_ids = exp.stages["test"].get("env_ids") or []
    if isinstance(env_ids, str):
        env_ids = [env_ids]
    if not isinstance(env_ids, list):
        raise ExperimentError(f"{exp.path}: test.env_ids: a list of env ids")
    if only:
        # Test tasks the file does not name run with the file's test settings.
        env_ids = list(dict.fromkeys(only))
    for env_id in env_ids:
        folder = exp.out / "test" / env_id
        steps.append(_test_step(exp, None, study_name, config, folder, env_id))
        if "report" in exp.document or exp.stages["report"]:
            steps.append(
                _report_step(
                    exp,
                    None,
                    study_name,
                    folder,
                    exp.out / "report" / env_id,
                    label=env_id,
                )
            )
    return steps


def _generalization_evolve_steps(
    exp: ExperimentFile, build_agents: bool
) -> tuple[list[Step], EvolveConfig, str]:
    """A generalization file's evolve (and re-evaluate) steps, its configuration and study."""
    from ermrl.runner._resolve import generalization_config_from_args
    from ermrl.search import generalization_study_name

    where = f"{exp.path}: evolve"
    argv, args = _evolve_parts(exp, None, where)
    notes: list[str] = []
    config = _config_error(
        exp,
        where,
        lambda: generalization_config_from_args(args, build_agent=build_agents, notes=notes),
    )
    study_name = generalization_study_name(config)
    argv += ["--study-name", study_name]
    config = _keep_study_backend(
        exp, where, args, config, study_name,
        lambda a: generalization_config_from_args(a, build_agent=build_agents), notes,
    )  # fmt: skip
    _check_study(exp, config, study_name, where)
    request = _evolve_request(exp, args, config, study_name, notes)
    gen = config.generalization
    label = gen.suite or "+".join(gen.env_ids)
    problem = config.problem
    n_trials = config.search.n_trials
    per_run, note = _rounded(problem.ppo, problem.budget.training_steps)
    per_task = len(problem.seeds) * per_run
    parts = [
        (
            n_trials * per_task,
            throughput(t.task.env_id, problem.ppo.backend, config.n_procs, problem.ppo.learner),
        )
        for t in gen.tasks
    ]
    total = n_trials * per_task * len(gen.tasks)
    steps = [
        Step(
            "evolve",
            label,
            "evolve-generalization",
            argv,
            total,
            estimate_seconds(parts),
            _evolve_status(exp.storage, study_name, n_trials),
            study_name,
            note=note,
            request=request,
        )  # fmt: skip
    ]
    search = config.search
    if search.reevaluate_top > 0:
        re_steps, _ = _rounded(
            problem.ppo, search.reevaluate_steps or problem.budget.training_steps
        )
        re_total = (search.reevaluate_top + 1) * search.reevaluate_seeds * re_steps
        re_parts = [(re_total, rate) for _, rate in ((0, p[1]) for p in parts)]
        steps.append(
            Step(
                "reevaluate",
                label,
                "evolve-generalization",
                argv,
                re_total * len(gen.tasks),
                estimate_seconds(re_parts),
                _reevaluate_status(exp.storage, study_name),
                study_name,
                request=request,
            )  # fmt: skip
        )
    return steps, config, study_name


# ---------------------------------------------------------------------------------------------
# State: what the storage and the folders say is done


def _storage_exists(url: str) -> bool:
    from ermrl.storage import parse_storage_url

    spec = parse_storage_url(url)
    path = getattr(spec, "path", None)
    return path is None or Path(path).exists()


@contextlib.contextmanager
def _study(storage: str, study_name: str) -> Iterator[Any]:
    """The study, read-only (``None`` when the storage or the study does not exist yet)."""
    from ermrl.storage import StorageError, StudyNotFound, load_study

    if not _storage_exists(storage):
        yield None
        return
    try:
        study = load_study(study_name, storage)
    except (StudyNotFound, StorageError):
        yield None
        return
    yield study


def _keep_study_backend(
    exp: ExperimentFile,
    where: str,
    args: Any,
    config: Any,
    study_name: str,
    build: Callable[[Any], Any],
    notes: list[str] | None = None,
) -> Any:
    """The configuration with the backend the study was created with, when the file sets no
    ``backend`` and the study exists (as the evolve command resumes it)."""
    from ermrl.runner._resolve import keep_study_backend

    if not _storage_exists(exp.storage):
        return config
    return _config_error(
        exp,
        where,
        lambda: keep_study_backend(
            args, config, exp.storage, study_name, build, [] if notes is None else notes
        )[1],
    )


def _check_study(exp: ExperimentFile, config: Any, study_name: str, where: str) -> None:
    """Refuse a file whose evolution contradicts the study already in the storage: its problem
    and search space, how the search proposes candidates (`_SEARCH_MUST_MATCH`), and the
    settings of a re-evaluation already recorded."""
    from ermrl.search import REEVALUATION_ATTR, STUDY_CONFIG_ATTR, resume_conflicts

    with _study(exp.storage, study_name) as study:
        if study is None:
            return
        stored = study.user_attrs.get(STUDY_CONFIG_ATTR)
        if stored is None:
            return
        diffs = resume_conflicts(config, stored) or _search_conflicts(config, stored)
        what = "evolved"
        ranking = study.user_attrs.get(REEVALUATION_ATTR)
        if not diffs and isinstance(ranking, Mapping):
            diffs, what = _reevaluation_conflicts(config, ranking), "re-evaluated"
    if diffs:
        raise ExperimentError(
            f"{where}: study {study_name!r} in {exp.storage} was {what} with other settings ("
            + "; ".join(diffs[:3])
            + (" ..." if len(diffs) > 3 else "")
            + "); change the file back, or set another out/storage"
        )


# How the search proposes candidates: changed mid-study, a CMA-ES generation would mix two
# population sizes, or the sampler would continue another sequence than the study's.
_SEARCH_MUST_MATCH = ("sampler", "sampler_seed", "restart", "popsize", "start")


def _search_conflicts(config: Any, stored: Mapping[str, Any]) -> list[str]:
    """Differences in `_SEARCH_MUST_MATCH` between the file and the stored study (an
    unset popsize is the default one, which is the same for both: the spaces match)."""
    from ermrl.config import to_dict
    from ermrl.search._evolve import default_popsize

    now = to_dict(config)["search"]
    old = stored.get("search")
    if not isinstance(old, Mapping):
        return []
    default = default_popsize(config)
    diffs = []
    for key in _SEARCH_MUST_MATCH:
        if key not in old:  # a study from before ermrl stored it
            continue
        new_value, old_value = now.get(key), old.get(key)
        if key == "popsize":
            new_value = default if new_value is None else new_value
            old_value = default if old_value is None else old_value
        if new_value != old_value:
            diffs.append(f"evolve.{key}: {old_value!r} in the study, {new_value!r} now")
    return diffs


def _reevaluation_conflicts(config: Any, ranking: Mapping[str, Any]) -> list[str]:
    """Differences between the file's ``reevaluate`` settings and the recorded re-evaluation
    (its ranking would be reported done while the resolved file claims other settings)."""
    search = config.search
    steps = search.reevaluate_steps or config.problem.budget.training_steps
    recorded = {
        "top": (ranking.get("top_k"), search.reevaluate_top),
        "steps": (ranking.get("training_steps"), steps),
        "seeds": (len(ranking.get("seeds") or []) or None, search.reevaluate_seeds),
    }
    if search.reevaluate_top == 0:  # no re-evaluation in the file: only its top differs
        recorded = {"top": recorded["top"]}
    return [
        f"reevaluate.{key}: {old!r} in the study, {new!r} now"
        for key, (old, new) in recorded.items()
        if old is not None and old != new
    ]


def _evolve_status(
    storage: str, study_name: str, n_trials: int
) -> Callable[[], tuple[bool, float, str]]:
    def status() -> tuple[bool, float, str]:
        from optuna.trial import TrialState

        with _study(storage, study_name) as study:
            if study is None:
                return False, 1.0, "not started"
            trials = study.get_trials(deepcopy=False)
            done = sum(t.state in (TrialState.COMPLETE, TrialState.PRUNED) for t in trials)
            busy = sum(t.state in (TrialState.RUNNING, TrialState.WAITING) for t in trials)
            finished = done >= n_trials and busy == 0
            left = max(n_trials - done, 0) / max(n_trials, 1)
            text = f"{min(done, n_trials)}/{n_trials} trials" + (
                f", {busy} running or queued" if busy else ""
            )
            return finished, left, text

    return status


def _reevaluate_status(storage: str, study_name: str) -> Callable[[], tuple[bool, float, str]]:
    def status() -> tuple[bool, float, str]:
        from ermrl.search import REEVALUATION_ATTR, stale_ranking

        with _study(storage, study_name) as study:
            if study is None:
                return False, 1.0, "not started"
            doc = study.user_attrs.get(REEVALUATION_ATTR)
            if not isinstance(doc, Mapping):
                return False, 1.0, "not started"
            if stale_ranking(study) is not None:
                return False, 0.5, "ranking stale (the study grew since): re-ranked when run"
            if not doc.get("complete"):
                return False, 0.5, "ranking incomplete"
            rows = doc.get("candidates") or []
            failed = sum(bool(row.get("failed")) for row in rows)
            if rows and failed == len(rows):
                # Failed for good (diverged, say): running it again would fail the same way.
                why = f"all {len(rows)} candidates failed: the test stage stops"
                return True, 0.0, f"ranking complete, but {why}; test one with ermrl test --trial N"
            tail = f"; {failed} failed, ranked last" if failed else ""
            return True, 0.0, f"ranking complete (best trial {doc.get('best_trial')}{tail})"

    return status


def _test_status(
    folder: Path, agents: Sequence[str], seeds: Sequence[int]
) -> Callable[[], tuple[bool, float, str]]:
    def status() -> tuple[bool, float, str]:
        from ermrl.analysis._results import RUNS_DIR

        total = len(agents) * len(seeds)
        done = sum(
            (folder / RUNS_DIR / agent / f"seed_{seed}" / "result.json").exists()
            for agent in agents
            for seed in seeds
        )
        if done == 0:
            return False, 1.0, "not started" if not folder.exists() else f"0/{total} runs"
        return done == total, (total - done) / total, f"{done}/{total} runs"

    return status


def _report_status(folder: Path, runs: Path | None) -> Callable[[], tuple[bool, float, str]]:
    def status() -> tuple[bool, float, str]:
        report = folder / "report.md"
        if not report.exists():
            return False, 1.0, "not written"
        summary = None if runs is None else runs / "summary.csv"
        if (
            summary is not None
            and summary.exists()
            and summary.stat().st_mtime > report.stat().st_mtime
        ):
            return False, 1.0, "older than the test results"
        return True, 0.0, f"written ({report})"

    return status


def resolved_document(exp: ExperimentFile, steps: Sequence[Step]) -> dict[str, Any]:
    """The experiment with every default filled in: each command's full options, as run."""
    commands: list[dict[str, Any]] = []
    for step in steps:
        if step.stage == "reevaluate":
            continue
        commands.append(_resolved_command(step))
    return {
        "name": exp.name,
        "variant": exp.variant,
        "file": str(exp.path),
        "out": str(exp.out),
        "storage": exp.storage,
        "publish": None if exp.publish is None else str(exp.publish),
        "description": exp.document.get("description"),
        "file_as_written": {k: v for k, v in exp.document.items()},
        "commands": commands,
    }


def _resolved_command(step: Step) -> dict[str, Any]:
    from ermrl.runner._parsers import PARSERS

    parser = PARSERS[step.command]()
    args = vars(parser.parse_args(step.argv))
    options = {k: _plain(v) for k, v in sorted(args.items())}
    return {
        "stage": step.stage if step.stage != "evolve" else "evolve+reevaluate",
        "task": step.label,
        "command": step.command_line,
        "options": options,
        "env_steps": step.env_steps,
    }


def _plain(value: Any) -> Any:
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "__dataclass_fields__"):
        from ermrl.config import to_dict

        return _plain(to_dict(value))
    return str(value)


def snapshot_path(exp: ExperimentFile, step: Step) -> Path:
    """Where an evolution step's study snapshot lives: ``<publish or out>/<task>/study.json``."""
    return (exp.publish or exp.out) / step.label / "study.json"


def hypothesis_of(exp: ExperimentFile, file: str | None = None) -> Any:
    """The experiment as a [`Hypothesis`][ermrl.analysis.Hypothesis] of the reproduction page."""
    from ermrl.analysis import Hypothesis, TaskFiles

    steps = experiment_plan(exp, build_agents=False)
    evolve = [s for s in steps if s.stage == "evolve"]
    base = exp.publish or exp.out
    tasks = []
    for test in (s for s in steps if s.stage == "test"):
        source = (
            evolve[0] if exp.generalization else next(s for s in evolve if s.label == test.label)
        )
        argv = source.argv
        n_trials = int(argv[argv.index("--n-trials") + 1]) if "--n-trials" in argv else 0
        tasks.append(
            TaskFiles(
                test.label,
                source.label,
                base / test.label,
                snapshot_path(exp, source),
                n_trials,
                _planned_runs(test),
            )
        )
    description = exp.document.get("description")
    claim = exp.document.get("claim")
    return Hypothesis(
        exp.name,
        file or str(exp.path),
        None if claim is None else str(claim).strip(),
        None if description is None else str(description),
        tuple(tasks),
        verdict_rule(exp),
    )


def _planned_runs(step: Step) -> dict[str, tuple[int, ...]]:
    """The runs a test step plans (`Step.runs`) as ``{agent: seeds}``."""
    planned: dict[str, tuple[int, ...]] = {}
    for agent, seed in step.runs:
        planned[agent] = (*planned.get(agent, ()), seed)
    return planned


def verdict_rule(exp: ExperimentFile) -> Any:
    """The file's ``verdict:`` block as a [`VerdictRule`][ermrl.analysis.VerdictRule] (``None``:
    none).

    Raises:
        ExperimentError: a block that cannot be used (one line, naming the key).
    """
    from ermrl.analysis import VerdictError, VerdictRule

    doc = exp.document.get("verdict")
    if doc is None:
        return None
    try:
        return VerdictRule.from_doc(doc, f"{exp.path}: verdict")
    except VerdictError as err:
        raise ExperimentError(str(err)) from None
