"""The test phase: train the best evolved reservoir against baselines over many seeds.

Agents:

- ``ppo``: PPO on the raw (masked) observation;
- ``ppo-full``: PPO on the full, unmasked observation (the ceiling memory should approach);
- ``res-ppo``: PPO on the states of the best evolved reservoir(s);
- ``random-res-ppo``: PPO on reservoirs with default, unevolved hyperparameters (what evolution adds);
- ``leaky-res-ppo``, ``ema-ppo``: ablations of the selected reservoir (``W = 0``; moving averages
  of its input at its leak rate), derived from it by their `AgentKind.derive`;
- ``lstm-ppo``, ``framestack-ppo``: memory baselines (RecurrentPPO; PPO on stacked observations);
- ``sac``, ``res-sac``, ``dagger``, ``res-dagger``: other learners on the raw observation and on
  the selected evolved reservoir(s) (DAgger's expert sees the full state).

The agents are the table `AGENT_KINDS` (learner, encoder, evolved or not).

Every (agent, seed) run is saved in its own folder as soon as it finishes, so a test phase that
is interrupted, or split across SLURM array tasks, resumes and merges: the aggregated
``curves.csv``, ``summary.csv`` and ``learning_curves.png`` are rebuilt from all finished runs.
Each run also records the settings that produced it (``settings.json``,
[`run_settings`][ermrl.test_phase.run_settings]), so that a rerun never mixes runs made with other
settings into one folder: it skips finished runs only when their settings are these, and refuses
otherwise ([`check_finished_runs`][ermrl.test_phase.check_finished_runs]).
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shlex
import shutil
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import optuna
import pandas as pd
import yaml

from ermrl._io import load_yaml, write_atomic
from ermrl._progress import Progress, ProgressMode, duration
from ermrl._text import plural
from ermrl.agents import (
    RunCheckpoint,
    RunResult,
    WandbRun,
    pool_size,
    steps_trained,
    train_agent,
    training_pool,
)
from ermrl.analysis import (
    curves_on_grid,
    load_curves,
    load_run_results,
    plot_learning_curves,
    run_dir,
    summarize,
)
from ermrl.analysis._results import (
    EPISODES_FILE,
    RUNS_DIR,
    RunFolderError,
    read_episodes,
    read_run_result,
    read_run_settings,
    read_run_text,
)
from ermrl.config import (
    BACKENDS,
    AgentKind,
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    EncoderParams,
    EvolveConfig,
    LearnerSpace,
    ObserveMode,
    PPOConfig,
    TaskConfig,
    to_dict,
)
from ermrl.encoders import encoder_families, encoder_of_family
from ermrl.learners import AGENT_KINDS, AGENTS, default_agents, evolved_agent, unevolved_agent
from ermrl.test_phase._results import REPLAY_MODEL_FILE, keep_published_record, write_run

__all__ = [
    "AGENTS",
    "AGENT_KINDS",
    "AgentKind",
    "AgentSpec",
    "agent_specs",
    "learner_settings_for",
    "default_agents",
    "TestSettings",
    "default_test_seeds",
    "Selection",
    "select_reservoirs",
    "study_reservoirs",
    "study_agents",
    "selection_metadata",
    "describe_selection",
    "run_comparison",
    "run_settings",
    "check_finished_runs",
    "settings_diff",
    "aggregate",
]


@dataclass(frozen=True)
class AgentSpec:
    """One agent of a comparison.

    Attributes:
        name: Agent name (its folder under ``agents/``).
        reservoirs: Its reservoirs (``None`` for plain PPO).
        observe: Its own observation mask, overriding the comparison task's (``None``: the
            task's); ``ppo-full`` sees ``"all"``.
        ppo: Its own learner settings (``None``: the comparison's), for an agent whose learner
            is not the study's (``lstm-ppo`` in a PPO study).
    """

    name: str
    reservoirs: tuple[EncoderParams, ...] | None
    observe: ObserveMode | None = None
    ppo: PPOConfig | None = None

    def task(self, task: TaskConfig) -> TaskConfig:
        """The task this agent trains on: ``task`` with the agent's own mask, if it has one."""
        return task if self.observe is None else dataclasses.replace(task, observe=self.observe)


def agent_specs(
    names: Sequence[str],
    evolved: tuple[EncoderParams, ...] | None,
    unevolved: tuple[EncoderParams, ...],
    learner_settings: Callable[[str], PPOConfig | None] | None = None,
    *,
    family: str | None = None,
    evolved_ppo: PPOConfig | None = None,
) -> list[AgentSpec]:
    """Build the agents named in ``names`` from `AGENT_KINDS`.

    Args:
        names: Agent names, in order.
        evolved: The selected trial's reservoirs (needed when ``res-ppo`` is asked for).
        unevolved: Unevolved reservoirs (for ``random-res-ppo``); empty in a study of a
            learner's genes.
        learner_settings: The settings of an agent whose learner is given by name (``None``
            returned: the comparison's own settings); default: every agent takes the
            comparison's settings.
        family: What the study evolved (default: the family of ``unevolved``); a learner's name
            for a study of its genes.
        evolved_ppo: In a study of a learner's genes, the comparison's settings with the
            selected trial's genes (the evolved agent's); its unevolved agent keeps the
            comparison's own settings.

    Raises:
        ConfigError: an unknown name, an agent of another family than the study's, or an
            evolved agent without the selected trial.
    """
    specs = []
    family = family or (unevolved[0].family if unevolved else None)
    for name in names:
        kind = AGENT_KINDS.get(name)
        if kind is None:
            raise ConfigError(f"unknown agent {name!r}; choose from {', '.join(AGENT_KINDS)}")
        if kind.family is not None and family is not None and kind.family != family:
            owner = encoder_of_family(kind.family)
            flag = f"--learner {kind.family}" if owner is None else f"--encoder {owner.name}"
            raise ConfigError(
                f"agent {name!r} needs a study evolved with {flag}; this study evolved "
                f"{family!r} (its agents: {evolved_agent(family)}, {unevolved_agent(family)})"
            )
        ppo = None
        if kind.learner is not None and learner_settings is not None:
            ppo = learner_settings(kind.learner)
        if kind.reservoirs != "none" and family not in (None, *encoder_families()):  # genes
            if kind.reservoirs == "evolved":
                if evolved_ppo is None:
                    raise ConfigError(f"agent {name!r} needs the evolved genes")
                ppo = evolved_ppo
            specs.append(AgentSpec(name, None, kind.observe, ppo))
            continue
        reservoirs = {"none": None, "evolved": evolved, "unevolved": unevolved}[kind.reservoirs]
        if kind.reservoirs == "evolved" and reservoirs is None:
            raise ConfigError(f"agent {name!r} needs the evolved reservoirs")
        if reservoirs is not None and kind.derive is not None:  # an ablation
            reservoirs = tuple(kind.derive(p) for p in reservoirs)
        specs.append(AgentSpec(name, reservoirs, kind.observe, ppo))
    return specs


def learner_settings_for(
    base: PPOConfig,
    env_id: str,
    overrides: Mapping[str, Any] | None = None,
    learner_overrides: Mapping[str, Mapping[str, Any]] | None = None,
) -> Callable[[str], PPOConfig | None]:
    """Settings of each learner in a comparison whose own settings are ``base``.

    ``base.learner`` keeps ``base`` (``None``: the comparison's); another learner takes its own
    table's settings for ``env_id`` with the same ``overrides`` (``--ppo``) and threads, plus its
    entry of ``learner_overrides`` (settings of one learner only, on top of ``overrides``:
    ``--for-learner dagger expert=DIR``, ``--no-stale-gradient``).
    """
    from ermrl.agents import resolve_ppo_config

    def settings(learner: str) -> PPOConfig | None:
        if learner == base.learner:
            return None
        own = (learner_overrides or {}).get(learner, {})
        return resolve_ppo_config(
            env_id, {**(overrides or {}), **own}, torch_threads=base.torch_threads, learner=learner
        )

    return settings


def study_agents(
    study: optuna.Study,
    config: EvolveConfig,
    names: Sequence[str],
    trial_number: int | None = None,
    learner_settings: Callable[[str], PPOConfig | None] | None = None,
    ppo: PPOConfig | None = None,
) -> tuple[list[AgentSpec], Selection | None]:
    """The agents named in ``names`` for a study, and the evolved trial when one is needed.

    ``learner_settings`` gives agents of another learner than the study's their settings (see
    [`learner_settings_for`][ermrl.test_phase.learner_settings_for]). In a study of a learner's
    genes, the evolved agent takes the selected genes on top of ``ppo``, the comparison's settings
    (default: the study's).

    Returns:
        The agents (see [`agent_specs`][ermrl.test_phase.agent_specs]) and the
        [`Selection`][ermrl.test_phase.Selection] behind ``res-ppo`` (``None`` when no agent uses
        the evolved reservoirs).
    """
    chosen = None
    if any(AGENT_KINDS[n].reservoirs == "evolved" for n in names if n in AGENT_KINDS):
        chosen = select_reservoirs(study, config, trial_number)
    space = config.space
    if isinstance(space, LearnerSpace):
        evolved_ppo = None
        if chosen is not None:
            from ermrl.learners import get_learner

            base = ppo or config.problem.ppo
            evolved_ppo = get_learner(space.learner).with_genes(base, space.values(chosen.params))
        agents = agent_specs(
            names, None, (), learner_settings, family=space.family, evolved_ppo=evolved_ppo
        )
        return agents, chosen
    agents = agent_specs(
        names,
        evolved=None if chosen is None else chosen.reservoirs,
        unevolved=space.default_reservoirs(),
        learner_settings=learner_settings,
    )
    return agents, chosen


def selection_metadata(chosen: Selection | None) -> dict[str, Any]:
    """What ``config.yaml`` records of the selected trial."""
    if chosen is None:
        return {"trial": None, "params": {}, "selection": None}
    return {"trial": chosen.number, "params": chosen.params, "selection": chosen.how}


def describe_selection(chosen: Selection | None) -> str:
    """One phrase for a test phase's header line."""
    if chosen is None:
        return "-"
    params = ", ".join(f"{k}={v:.3g}" for k, v in chosen.params.items())
    return f"trial {chosen.number} ({params}; {chosen.how})"


@dataclass(frozen=True)
class TestSettings:
    """How a comparison runs.

    Attributes:
        training_steps: Steps per run.
        seeds: Seeds; each agent trains once per seed.
        out: Output folder.
        n_procs: Cores for the runs (single-threaded processes; see
            [`pool_size`][ermrl.agents.pool_size]).
        evaluate: Also run deterministic evaluation episodes after training.
        n_eval_episodes: Their number.
        n_last_episodes: Training episodes averaged into a run's final return.
        save_models: Save each trained model as ``model.zip`` in its run folder.
        overwrite: Retrain runs that already have results (default: skip them, i.e. resume).
        tensorboard: Log training curves for TensorBoard under ``<tensorboard>/<agent>/seed_<s>``
            (needs the ``tensorboard`` package).
        wandb: Log each run to this Weights & Biases project, as run ``<agent>-seed<s>`` in
            the group named after ``out`` (needs the ``wandb`` package).
        progress: ``"lines"``: a progress line of each run every tenth of its steps or 30 s
            (`ermrl._progress.Progress`); ``"bar"``: a live bar of each run instead;
            ``"none"``: a line per finished run only.
        checkpoint_every: Runs save their training state every this many steps per run, and
            a rerun resumes them from there: population runs under ``out/checkpoints`` (see
            [`Checkpoint`][ermrl.population.Checkpoint]), on-policy sb3 runs in their run folder's
            ``checkpoints`` ([`RunCheckpoint`][ermrl.agents.RunCheckpoint]). ``None``: a tenth of
            ``training_steps``; 0: no checkpoints.
    """

    __test__ = False  # not a pytest test class

    training_steps: int
    seeds: tuple[int, ...]
    out: Path
    n_procs: int = 1
    evaluate: bool = False
    n_eval_episodes: int = 5
    n_last_episodes: int = 10
    save_models: bool = True
    overwrite: bool = False
    tensorboard: Path | None = None
    wandb: str | None = None
    progress: ProgressMode = "lines"
    checkpoint_every: int | None = None

    def __post_init__(self) -> None:
        if self.training_steps < 1:
            raise ConfigError(f"training steps must be positive, got {self.training_steps}")
        if self.checkpoint_every is not None and self.checkpoint_every < 0:
            raise ConfigError(f"checkpoint_every must be >= 0, got {self.checkpoint_every}")
        if not self.seeds:
            raise ConfigError("at least one seed is needed")
        if self.n_procs < 1:
            raise ConfigError(f"n_procs must be >= 1, got {self.n_procs}")


def default_test_seeds(evolution_seeds: Sequence[int], n: int = 5) -> tuple[int, ...]:
    """``n`` seeds that evolution never trained on: the ones after its largest seed."""
    start = max(evolution_seeds) + 1 if evolution_seeds else 0
    return tuple(range(start, start + n))


@dataclass(frozen=True)
class Selection:
    """The evolved trial a test phase uses, and how it was chosen.

    Attributes:
        params: The trial's parameters.
        reservoirs: Its reservoirs (``None`` in a study of a learner's genes: ``params`` are
            the genes).
        number: Its number.
        how: How it was selected (``--trial``, the re-evaluated ranking, or the best evolution
            fitness); printed and saved in ``config.yaml`` as ``selection``.
    """

    params: dict[str, float]
    reservoirs: tuple[EncoderParams, ...] | None
    number: int
    how: str


def select_reservoirs(
    study: optuna.Study, config: EvolveConfig, trial_number: int | None = None
) -> Selection:
    """The reservoirs to test: ``trial_number``, else the re-evaluated best, else the best trial.

    Raises:
        ConfigError: the study has no complete trial, or no such trial.
    """
    from ermrl.search import select_trial

    trial, how = select_trial(study, trial_number)
    space = config.space
    reservoirs = None if isinstance(space, LearnerSpace) else space.reservoirs_from(trial.params)
    return Selection(dict(trial.params), reservoirs, trial.number, how)


def study_reservoirs(
    study: optuna.Study, config: EvolveConfig, trial_number: int | None = None
) -> tuple[dict[str, float], tuple[EncoderParams, ...] | None, int]:
    """The parameters, reservoirs and number of the trial
    [`select_reservoirs`][ermrl.test_phase.select_reservoirs] picks."""
    chosen = select_reservoirs(study, config, trial_number)
    return chosen.params, chosen.reservoirs, chosen.number


def _train_job(args: tuple[Any, ...]) -> RunResult:
    (
        task, encoder, ppo, budget, seed, evaluate, model_path, tensorboard_log, wandb, progress,
        checkpoint,
    ) = args  # fmt: skip
    return train_agent(
        task,
        encoder,
        ppo,
        budget,
        seed,
        evaluate=evaluate,
        model_path=model_path,
        tensorboard_log=tensorboard_log,
        wandb=wandb,
        progress=progress,
        checkpoint=checkpoint,
    )


def _say(stream: TextIO | None, quiet: bool, line: str) -> None:
    if not quiet:
        print(line, file=stream or sys.stdout, flush=True)


RUN_SETTINGS_FILE = "settings.json"
# Record keys that every agent of one comparison shares (the rest depend on the agent).
_SHARED_KEYS = ("env_id", "ppo", "budget")


def run_settings(
    task: TaskConfig,
    encoder: EncoderConfig | None,
    ppo: PPOConfig,
    budget: BudgetConfig,
    agent: str,
    seed: int,
) -> dict[str, Any]:
    """Everything that determines one test-phase run, as plain JSON data.

    Saved as ``settings.json`` in the run's folder, so that a rerun into the same folder can
    tell a finished run made with these settings (skip it) from one made with others (refuse).
    Parallelism (``torch_threads``, ``--n-procs``), output options and the evaluation
    episode count without ``--eval`` are left out: they do not change the run's results.

    Args:
        task: The agent's env and observation mask.
        encoder: Its encoding, reservoirs included (``None`` for plain PPO).
        ppo: PPO settings.
        budget: Training steps and returns measured.
        agent: Agent name.
        seed: The run's seed.
    """
    ppo_doc = {k: v for k, v in to_dict(ppo).items() if k != "torch_threads"}
    budget_doc = {k: v for k, v in to_dict(budget).items() if k != "n_reports"}
    if budget.fitness != "eval":
        budget_doc.pop("n_eval_episodes")
    record = {
        "agent": agent,
        "seed": int(seed),
        "env_id": task.env_id,
        "observe": task.observe,
        "encoder": None if encoder is None else to_dict(encoder),
        "ppo": ppo_doc,
        "budget": budget_doc,
    }
    return json.loads(json.dumps(record))  # JSON types, as read back from the file


def _flat(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict) and value:
        out: dict[str, Any] = {}
        for key, item in value.items():
            out.update(_flat(item, f"{prefix}.{key}" if prefix else str(key)))
        return out
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        out = {}
        for i, item in enumerate(value):
            out.update(_flat(item, f"{prefix}.{i}"))
        return out
    return {prefix: value}


_MISSING = object()


#: Keys of a run's record that say what was measured after training, not how it trained:
#: whether deterministic evaluation episodes ran (``fitness`` ``eval``) and how many. A run
#: trained with them and one without are the same training, so a test phase can add the
#: evaluation metric on new seeds beside runs made without it (each run's ``result.json`` says
#: how many evaluation episodes it holds).
MEASUREMENT_KEYS = frozenset({"budget.fitness", "budget.n_eval_episodes"})


def settings_diff(stored: Mapping[str, Any], expected: Mapping[str, Any]) -> list[str]:
    """Dotted keys whose values differ between two [`run_settings`][ermrl.test_phase.run_settings]
    records, sorted.

    `MEASUREMENT_KEYS` are left out: they do not change the training.
    """
    a, b = _flat(dict(stored)), _flat(dict(expected))
    keys = (set(a) | set(b)) - MEASUREMENT_KEYS
    return sorted(k for k in keys if a.get(k, _MISSING) != b.get(k, _MISSING))


def _learner_of(ppo_doc: Mapping[str, Any]) -> str:
    return str(ppo_doc.get("learner", "ppo"))  # left out of stored settings for PPO


def finished_backend(out: str | Path, learner: str) -> str | None:
    """The backend that made the finished runs of ``learner`` under ``out`` (``None``: none).

    Read from each run's ``settings.json`` (the first finished run of that learner whose record
    names a known backend); records that cannot be read are left to
    [`check_finished_runs`][ermrl.test_phase.check_finished_runs].
    """
    for path in sorted(Path(out).glob(f"{RUNS_DIR}/*/seed_*/{RUN_SETTINGS_FILE}")):
        if not (path.parent / "result.json").is_file():
            continue
        try:
            ppo_doc = json.loads(read_run_text(path)).get("ppo")
        except (RunFolderError, ValueError, AttributeError):
            continue
        if not isinstance(ppo_doc, dict) or _learner_of(ppo_doc) != learner:
            continue
        backend = ppo_doc.get("backend", "sb3")  # left out of stored settings for sb3
        if backend in BACKENDS:
            return str(backend)
    return None


def check_finished_runs(
    out: Path,
    expected: Mapping[str, Any],
    seeds: Sequence[int],
    overwrite: bool,
) -> None:
    """Refuse to mix: every finished run under ``out`` must have been made with these settings.

    Runs of the agents and seeds this call trains are compared in full; other finished runs
    in the folder (other seeds, e.g. other SLURM array tasks, or agents not asked for now) on
    what every agent shares (env, PPO settings, budget). With ``overwrite``, the runs this call
    retrains are not checked.

    Args:
        out: The test-phase folder.
        expected: Agent name -> its [`run_settings`][ermrl.test_phase.run_settings] for seed 0 (the
            seed is replaced).
        seeds: The seeds this call trains.
        overwrite: ``--overwrite``: the requested runs are retrained, whatever they hold.

    Raises:
        ConfigError: some finished runs were made with other settings, or have no record
            (written before ermrl kept one), naming them and the differing keys.
        RunFolderError: a finished run that would be kept (and read back by the summary) has
            a damaged ``result.json``, ``episodes.csv`` or ``settings.json``.
    """
    if not expected:
        return
    differing: list[str] = []
    unrecorded: list[str] = []
    outside: list[str] = []
    shared = {k: v for k, v in next(iter(expected.values())).items() if k in _SHARED_KEYS}
    # Learner settings are shared by the agents of one learner.
    shared_ppo = {_learner_of(e["ppo"]): e["ppo"] for e in expected.values()}
    for path in sorted(Path(out).glob(f"{RUNS_DIR}/*/seed_*/result.json")):
        name, folder = path.parent.parent.name, path.parent
        try:
            seed = int(folder.name.removeprefix("seed_"))
        except ValueError:
            continue
        requested = name in expected and seed in seeds
        if requested and overwrite:
            continue
        label = f"{name} seed {seed}"
        keys = _finished_run_diff(folder, name, seed, expected, shared, shared_ppo)
        if keys is None:
            unrecorded.append(label)
        elif keys:
            shown = ", ".join(keys[:4]) + (", ..." if len(keys) > 4 else "")
            differing.append(f"{label} differs in {shown}")
        else:
            continue
        outside += [] if requested else [label]
    if differing or unrecorded:
        raise _mixed_runs_error(out, differing, unrecorded, outside)


def _finished_run_diff(
    folder: Path,
    name: str,
    seed: int,
    expected: Mapping[str, Any],
    shared: Mapping[str, Any],
    shared_ppo: Mapping[str, Any],
) -> list[str] | None:
    """The keys in which the finished run of agent ``name`` in ``folder`` differs from
    ``expected`` (see [`check_finished_runs`][ermrl.test_phase.check_finished_runs]), or ``None``
    when it has no settings record.

    The run of an agent not in ``expected`` is compared on ``shared`` (what every agent
    shares), with its own learner's settings from ``shared_ppo`` (learner name -> settings);
    learner settings are left out when no agent asked for has its learner.

    Raises:
        RunFolderError: the run's ``result.json``, ``episodes.csv`` or ``settings.json`` is
            damaged.
    """
    # A run that is kept is read back by the summary: a damaged one stops us now.
    read_run_result(folder / "result.json")
    read_episodes(folder / EPISODES_FILE)
    record_path = folder / RUN_SETTINGS_FILE
    if not record_path.is_file():
        return None
    stored = read_run_settings(record_path)
    if name in expected:
        return settings_diff(stored, {**expected[name], "seed": seed})
    own = {**shared, "ppo": shared_ppo.get(_learner_of(stored.get("ppo") or {}))}
    return [
        key
        for key in settings_diff({k: stored.get(k) for k in _SHARED_KEYS}, own)
        if own["ppo"] is not None or not key.startswith("ppo")
    ]


def _mixed_runs_error(
    out: Path, differing: list[str], unrecorded: list[str], outside: list[str]
) -> ConfigError:
    """The error of [`check_finished_runs`][ermrl.test_phase.check_finished_runs]: the runs that
    differ (a few of them), those without a settings record, and those ``--overwrite`` would not
    retrain."""
    problems = differing[:3] + (["..."] if len(differing) > 3 else [])
    if unrecorded:
        problems.append(
            f"{len(unrecorded)} run(s) ({', '.join(unrecorded[:3])}"
            f"{', ...' if len(unrecorded) > 3 else ''}) have no {RUN_SETTINGS_FILE} (written by "
            "an older ermrl), so whether they match is unknown"
        )
    advice = "use another --out, or --overwrite to retrain them"
    if outside:
        advice += (
            f" (--overwrite retrains only the agents and seeds asked for, not "
            f"{', '.join(outside[:3])}{', ...' if len(outside) > 3 else ''})"
        )
    return ConfigError(
        f"{out} holds finished runs made with other settings than these: "
        + "; ".join(problems)
        + f"; {advice}"
    )


# A results folder that cannot take more data: a full disk, a quota, a read-only mount, no
# permission. The CLI reports them on one line with exit code 2.
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM})


def check_out_folder(out: str | Path) -> None:
    """Refuse an output folder that cannot be created or written, before anything runs.

    Args:
        out: The test phase's ``--out``; it may not exist yet.

    Raises:
        ConfigError: ``out`` (or the nearest part of it that exists) is not a folder, is
            not writable, or is a symbolic link that leads nowhere (a loop, a missing target).
    """
    out = Path(out)
    existing = out
    while not existing.exists() and existing.parent != existing:
        if existing.is_symlink():  # its name exists: it could not be created
            try:
                existing.stat()
            except OSError as err:
                raise ConfigError(
                    f"--out {out}: {existing} is a symbolic link that cannot be followed "
                    f"({err.strerror or err})"
                ) from None
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"--out {out}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"--out {out}: cannot write in {existing} (read-only or no permission)")


def write_error_message(err: OSError, out: str | Path) -> str:
    """One line for an ``OSError`` of `WRITE_ERRNOS` met while writing results."""
    where = err.filename or out
    return (
        f"cannot write {where}: {err.strerror or err}; finished runs are kept in {out} and "
        "no partial file is left under its final name: free space (or fix the folder) and rerun"
    )


# One run to train: its agent, its seed and the arguments of _train_job.
_Job = tuple[AgentSpec, int, tuple[Any, ...]]
# What a comparison does with each finished run (see _run_recorder).
_Finished = Callable[[AgentSpec, int, RunResult], None]


def run_comparison(
    task: TaskConfig,
    encoder: EncoderConfig,
    ppo: PPOConfig,
    agents: Sequence[AgentSpec],
    settings: TestSettings,
    *,
    metadata: Mapping[str, Any] | None = None,
    quiet: bool = False,
    stream: TextIO | None = None,
    command: str | None = None,
) -> pd.DataFrame:
    """Train every agent on every seed and write the comparison's results.

    Args:
        task: The environment and mask (an agent with its own ``observe`` overrides the mask).
        encoder: Encoding options (its reservoirs are replaced by each agent's).
        ppo: PPO settings shared by all agents.
        agents: The agents to compare.
        settings: Budget, seeds, output folder, parallelism.
        metadata: Saved in ``config.yaml`` (study name, storage, trial, ...).
        quiet: No progress lines.
        stream: Where progress lines go.
        command: The command line that runs this test phase, written to ``command.txt``
            (default: this process's own, ``sys.argv``).

    Returns:
        The summary table (also written as ``summary.csv``).

    Raises:
        ConfigError: ``settings.out`` holds finished runs made with other settings (see
            [`check_finished_runs`][ermrl.test_phase.check_finished_runs]); nothing is written then.
    """
    out = Path(settings.out)
    budget = _comparison_budget(settings)
    expected = {
        a.name: run_settings(
            a.task(task), _agent_encoder(a, encoder), a.ppo or ppo, budget, a.name, 0
        )
        for a in agents
    }
    check_finished_runs(out, expected, settings.seeds, settings.overwrite)
    out.mkdir(parents=True, exist_ok=True)
    phase_agents = _write_config(out, task, encoder, ppo, agents, settings, metadata, command)
    jobs = _plan_runs(
        out, task, encoder, ppo, agents, settings, budget, expected, metadata, stream, quiet
    )
    total = len(jobs)
    # The ETA counts the units of the current phase only: populations (whose runs all finish
    # at once, so counting their runs read 23 min after the first of 5 runs of a 3-min phase),
    # then the other runs. _train_populations counts its populations itself.
    phase: dict[str, Any] = {
        "started": time.perf_counter(),
        "done": 0,
        "units": 1,
        "per_run": False,
    }
    jobs, twins = _twin_runs(jobs, expected, settings)
    if twins:
        names = sorted({f"{t.name} = {a}" for (a, _), ts in twins.items() for t in ts})
        _say(
            stream,
            quiet,
            f"trained once for both agents of each pair (the same reservoirs and settings): "
            f"{', '.join(names)}",
        )
    finished = _run_recorder(out, task, expected, twins, total, phase, stream, quiet)
    jobs = _train_populations(jobs, budget, settings, finished, stream, quiet, phase)
    phase.update(started=time.perf_counter(), done=0, units=len(jobs), per_run=True)
    _train_runs(jobs, settings.n_procs, finished)
    return aggregate(out, phase_agents, title=task.label)


def _comparison_budget(settings: TestSettings) -> BudgetConfig:
    """The budget of every run of a comparison: its steps, and its returns measured."""
    return BudgetConfig(
        training_steps=settings.training_steps,
        n_last_episodes=settings.n_last_episodes,
        n_eval_episodes=settings.n_eval_episodes,
        fitness="eval" if settings.evaluate else "last",
        n_reports=0,
    )


def _agent_encoder(agent: AgentSpec, encoder: EncoderConfig) -> EncoderConfig | None:
    """The comparison's encoding with the agent's own reservoirs (``None``: plain PPO)."""
    return None if agent.reservoirs is None else encoder.with_reservoirs(agent.reservoirs)


def _write_config(
    out: Path,
    task: TaskConfig,
    encoder: EncoderConfig,
    ppo: PPOConfig,
    agents: Sequence[AgentSpec],
    settings: TestSettings,
    metadata: Mapping[str, Any] | None,
    command: str | None,
) -> list[str]:
    """Write the comparison's ``config.yaml`` and ``command.txt`` (see
    [`run_comparison`][ermrl.test_phase.run_comparison]); return the agents the folder's summary
    lists.

    A piece of a phase (``ermrl test --agents res-ppo --seeds 15 16`` into a folder that holds
    the phase's other runs, or one task of a SLURM array) adds to the folder's records instead
    of replacing them (`_merged_config`): ``config.yaml`` lists the agents and seeds of
    every piece, ``command.txt`` each piece's command, and the summary every agent.
    """
    # The encoding options every reservoir agent shares; each agent's own reservoirs are under
    # `agents` (a top-level `reservoirs` read as the evolved one's, while it was the reference).
    shared_encoder = (
        None
        if encoder is None
        else {k: v for k, v in to_dict(encoder).items() if k != "reservoirs"}
    )
    config_doc = {
        "task": to_dict(task),
        "encoder": shared_encoder,
        "ppo": to_dict(ppo),
        "settings": {
            k: (str(v) if isinstance(v, Path) else to_dict(v))
            for k, v in dataclasses.asdict(settings).items()
        },
        "agents": {a.name: None if a.reservoirs is None else to_dict(a.reservoirs) for a in agents},
        # Agents that observe otherwise than `task` (ppo-full: the whole observation).
        "agent_observe": {a.name: a.observe for a in agents if a.observe is not None},
        # Agents with their own learner settings (another learner than the study's).
        **(
            {"agent_ppo": {a.name: to_dict(a.ppo) for a in agents if a.ppo is not None}}
            if any(a.ppo is not None for a in agents)
            else {}
        ),
        **dict(metadata or {}),
    }
    line = command or shlex.join(sys.argv)
    commands = [line]
    merged = _merged_config(out / "config.yaml", config_doc)
    if merged is not None:
        config_doc = merged
        earlier = _read_lines(out / "command.txt")
        commands = [*earlier, line] if line not in earlier else earlier
    write_atomic(out / "config.yaml", yaml.safe_dump(config_doc, sort_keys=False))
    write_atomic(out / "command.txt", "\n".join(commands) + "\n")
    return list(config_doc["agents"])


# Settings that may differ between the pieces of one phase: where and how a piece ran, not
# what its runs are (those are checked run by run, check_finished_runs).
_PIECE_SETTINGS = frozenset(
    {"seeds", "out", "n_procs", "overwrite", "progress", "tensorboard", "wandb", "save_models"}
)


def _merged_config(path: Path, doc: Mapping[str, Any]) -> dict[str, Any] | None:
    """``doc`` (a comparison's ``config.yaml``) joined with the earlier one at ``path`` when
    both describe one phase: the same task, encoding, learner settings, budget and selected
    trial (or none, in a piece whose agents use none), and the same reservoirs for an agent
    both list. Its agents are then those of both,
    in the registry's order, and its seeds both's, sorted. ``None``: nothing to join (no
    earlier file, an unreadable one, or another phase, which ``doc`` replaces).
    """
    try:
        old = load_yaml(path.read_text())
    except (OSError, yaml.YAMLError):
        return None
    if not isinstance(old, dict) or not isinstance(old.get("agents"), dict):
        return None
    new: dict[str, Any] = load_yaml(yaml.safe_dump(dict(doc), sort_keys=False))  # as read
    # A piece whose agents use no selected trial (ppo alone) records none: it joins the phase's
    # selection, whichever piece came first.
    chosen = [k for k in selection_metadata(None) if k in new or k in old]
    if new.get("trial") is None and old.get("trial") is not None:
        new.update({k: old.get(k) for k in chosen})
    elif old.get("trial") is None and new.get("trial") is not None:
        old.update({k: new.get(k) for k in chosen})
    maps = ("agents", "agent_observe", "agent_ppo")

    def phase(d: Mapping[str, Any]) -> dict[str, Any]:
        settings = {k: v for k, v in (d.get("settings") or {}).items() if k not in _PIECE_SETTINGS}
        return {**{k: v for k, v in d.items() if k not in maps}, "settings": settings}

    if phase(old) != phase(new):
        return None
    for key in maps:
        both = set(old.get(key) or {}) & set(new.get(key) or {})
        if any(old[key][name] != new[key][name] for name in both):
            return None
    order = {name: k for k, name in enumerate(AGENT_KINDS)}

    def joined(key: str) -> dict[str, Any]:
        union = {**(old.get(key) or {}), **(new.get(key) or {})}
        return {n: union[n] for n in sorted(union, key=lambda n: (order.get(n, len(order)), n))}

    seeds = sorted({*old["settings"].get("seeds", ()), *new["settings"]["seeds"]})
    merged = {**new, "settings": {**new["settings"], "seeds": seeds}}
    for key in maps:
        if key in new or key in old:
            merged[key] = joined(key)
    return merged


def _read_lines(path: Path) -> list[str]:
    try:
        return [ln for ln in path.read_text().splitlines() if ln.strip()]
    except OSError:
        return []


def _plan_runs(
    out: Path,
    task: TaskConfig,
    encoder: EncoderConfig,
    ppo: PPOConfig,
    agents: Sequence[AgentSpec],
    settings: TestSettings,
    budget: BudgetConfig,
    expected: Mapping[str, Mapping[str, Any]],
    metadata: Mapping[str, Any] | None,
    stream: TextIO | None,
    quiet: bool,
) -> list[_Job]:
    """The runs left to train, seed by seed, each with its folder made.

    A run that already finished is skipped (one line), unless ``settings.overwrite``. Each run
    gets its model path, TensorBoard folder, W&B run, progress and checkpoint as ``settings``
    ask.
    """
    jobs = []
    for seed in settings.seeds:
        for agent in agents:
            folder = run_dir(out, agent.name, seed)
            if (folder / "result.json").exists() and not settings.overwrite:
                _say(stream, quiet, f"[skip] {agent.name} seed {seed}: already done in {folder}")
                continue
            folder.mkdir(parents=True, exist_ok=True)
            enc = _agent_encoder(agent, encoder)
            model_path = str(folder / "model.zip") if settings.save_models else None
            tb_log = (
                None
                if settings.tensorboard is None
                else str(Path(settings.tensorboard) / agent.name / f"seed_{seed}")
            )
            wandb = _wandb_of(out, task, agent, seed, settings, budget, metadata)
            progress = Progress(
                f"{agent.name} seed {seed}",
                steps_trained(agent.ppo or ppo, budget.training_steps),  # whole rollouts
                mode="none" if quiet else settings.progress,
                stream=stream if settings.n_procs == 1 else None,  # a worker prints to stdout
            )
            record = {**expected[agent.name], "seed": seed}
            checkpoint = _run_checkpoint(folder, settings, budget, record)
            job = (
                agent.task(task), enc, agent.ppo or ppo, budget, seed, settings.evaluate,
                model_path, tb_log, wandb, progress, checkpoint,
            )  # fmt: skip
            jobs.append((agent, seed, job))
    return jobs


def _wandb_of(
    out: Path,
    task: TaskConfig,
    agent: AgentSpec,
    seed: int,
    settings: TestSettings,
    budget: BudgetConfig,
    metadata: Mapping[str, Any] | None,
) -> WandbRun | None:
    """The run's W&B run (``<agent>-seed<s>`` in the group named after ``out``), if asked for."""
    if settings.wandb is None:
        return None
    return WandbRun(
        project=settings.wandb,
        name=f"{agent.name}-seed{seed}",
        group=out.resolve().name,
        config={
            "agent": agent.name, "seed": seed, "env_id": agent.task(task).env_id,
            "observe": agent.task(task).observe, "training_steps": budget.training_steps,
            **{k: v for k, v in (metadata or {}).items() if isinstance(v, (int, float, str))},
        },
    )  # fmt: skip


def _run_checkpoint(
    folder: Path, settings: TestSettings, budget: BudgetConfig, record: Mapping[str, Any]
) -> RunCheckpoint | None:
    """The run's own checkpoint in ``folder``, for an on-policy sb3 run (``None``: none asked).

    ``record`` is the run's [`run_settings`][ermrl.test_phase.run_settings] with its seed: a
    checkpoint made with others is not resumed. With ``settings.overwrite`` an existing checkpoint
    is removed first.
    """
    if settings.checkpoint_every == 0:
        return None
    if settings.overwrite:
        shutil.rmtree(folder / CHECKPOINT_DIR, ignore_errors=True)
    return RunCheckpoint(
        folder / CHECKPOINT_DIR,
        settings.checkpoint_every or max(budget.training_steps // 10, 1),
        json.dumps(record, sort_keys=True),
    )


def _run_recorder(
    out: Path,
    task: TaskConfig,
    expected: Mapping[str, Mapping[str, Any]],
    twins: Mapping[tuple[str, int], Sequence[AgentSpec]],
    total: int,
    phase: dict[str, Any],
    stream: TextIO | None,
    quiet: bool,
) -> _Finished:
    """What a comparison does with each finished run: write its records, copy its model to its
    twins and write theirs (see `_twin_runs`), and print one line per run.

    The lines count the runs out of ``total`` and give an ETA from ``phase`` (the current
    phase's start and its units done and in all; with ``phase["per_run"]``, each run counts
    one unit done).
    """
    done = 0

    def record(agent: AgentSpec, seed: int, result: RunResult) -> None:
        nonlocal done
        done += 1
        if phase["per_run"]:
            phase["done"] += 1
        published = _write_records(out, task, agent, seed, expected[agent.name], result)
        kept = (
            ""
            if published is None
            else f" (the published run's {published:.4g} kept; this training made the model "
            "the report replays)"
        )
        elapsed = time.perf_counter() - phase["started"]
        eta = elapsed / max(phase["done"], 1) * max(phase["units"] - phase["done"], 0)
        _say(
            stream,
            quiet,
            f"[run {done}/{total}] {agent.name} seed {seed}: final return "
            f"{result.last_return:.4g}{kept} | {result.steps_per_second:.0f} steps/s | "
            f"{result.wall_seconds:.0f}s | ETA {duration(eta)}",
        )

    def finished(agent: AgentSpec, seed: int, result: RunResult) -> None:
        record(agent, seed, result)
        for twin in twins.get((agent.name, seed), ()):
            # The model files (model.zip, policy.pt, normalization stats) for the replay;
            # record() writes the run's own records.
            for f in run_dir(out, agent.name, seed).iterdir():
                if f.is_file() and f.name not in _RECORD_FILES:
                    shutil.copyfile(f, run_dir(out, twin.name, seed) / f.name)
            record(twin, seed, result)

    return finished


def _write_records(
    out: Path,
    task: TaskConfig,
    agent: AgentSpec,
    seed: int,
    expected: Mapping[str, Any],
    result: RunResult,
) -> float | None:
    """Write a finished run's records in its folder: its settings, then its result.

    Args:
        out: The test-phase folder.
        task: The comparison's task.
        agent: The run's agent.
        seed: Its seed.
        expected: The agent's [`run_settings`][ermrl.test_phase.run_settings] (its seed is replaced
            by ``seed``).
        result: What the run produced.

    Returns:
        The published run's final return, kept in place of this run's (see
        `keep_published_record`), or ``None``.
    """
    extra = {
        "env_id": task.env_id,
        "observe": agent.task(task).observe,  # what this agent saw
        "reservoirs": None if agent.reservoirs is None else to_dict(agent.reservoirs),
    }
    folder = run_dir(out, agent.name, seed)
    # The settings record first: result.json, written last, marks the run as finished.
    stored = {**expected, "seed": seed}
    write_atomic(folder / RUN_SETTINGS_FILE, json.dumps(stored, indent=1) + "\n")
    write_run(folder, agent.name, result, extra)
    return keep_published_record(folder)


def _train_runs(jobs: list[_Job], n_procs: int, finished: _Finished) -> None:
    """Train ``jobs`` one after the other, or in a pool of ``n_procs`` processes, and hand each
    run to ``finished`` as it ends.

    On an error or an interrupt, the pool's runs not started are cancelled and its processes
    terminated before the error is raised ([`training_pool`][ermrl.agents.training_pool]).
    """
    if n_procs == 1 or len(jobs) <= 1:
        for agent, seed, args in jobs:
            finished(agent, seed, _train_job(args))
        return
    with training_pool(pool_size(len(jobs), n_procs)) as pool:
        pending: dict[Future[RunResult], tuple[AgentSpec, int]] = {
            pool.submit(_train_job, args): (agent, seed) for agent, seed, args in jobs
        }
        while pending:
            ready, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in ready:
                agent, seed = pending.pop(future)
                finished(agent, seed, future.result())


# The population runs' checkpoints, inside a test phase's output folder.
CHECKPOINT_DIR = "checkpoints"

# A run's own records (written for each run), not copied from one twin to the other.
_RECORD_FILES = frozenset({RUN_SETTINGS_FILE, "episodes.csv", "result.json", REPLAY_MODEL_FILE})


def _twin_runs(
    jobs: list[_Job],
    expected: Mapping[str, Mapping[str, Any]],
    settings: TestSettings,
) -> tuple[list[_Job], dict[tuple[str, int], list[AgentSpec]]]:
    """The runs to train, and the runs that would repeat one of them exactly.

    Two agents whose runs differ by their name only (``res-ppo`` when the selection chose the
    unevolved reference: ``random-res-ppo``'s reservoirs) would train the same run twice, and
    side by side (the same population, or the same sb3 process layout) bit for bit the same.
    The second, its *twin*, is written from the first one's result instead. Runs logged to
    TensorBoard or W&B are all trained (each writes its own log).

    Returns:
        ``(jobs, twins)``: the jobs to train, and per trained ``(agent, seed)`` its twin agents.
    """
    if settings.tensorboard is not None or settings.wandb is not None:
        return jobs, {}

    def key(agent: AgentSpec, seed: int) -> str:
        doc = {k: v for k, v in expected[agent.name].items() if k != "agent"}
        return json.dumps({**doc, "seed": seed}, sort_keys=True)

    first: dict[str, tuple[str, int]] = {}
    kept: list[_Job] = []
    twins: dict[tuple[str, int], list[AgentSpec]] = {}
    for agent, seed, args in jobs:
        k = key(agent, seed)
        if k in first:
            twins.setdefault(first[k], []).append(agent)
        else:
            first[k] = (agent.name, seed)
            kept.append((agent, seed, args))
    return kept, twins


def _population_key(args: tuple[Any, ...]) -> str:
    """Runs that can share one population: same task and settings, same encoder structure."""
    from ermrl.population import encoder_structure

    task, encoder, ppo = args[0], args[1], args[2]
    enc = None if encoder is None else repr(encoder_structure(encoder))
    return json.dumps({"task": to_dict(task), "ppo": to_dict(ppo), "encoder": enc}, sort_keys=True)


def _train_populations(
    jobs: list[_Job],
    budget: BudgetConfig,
    settings: TestSettings,
    finished: _Finished,
    stream: TextIO | None,
    quiet: bool,
    phase: dict[str, Any],
) -> list[_Job]:
    """Train the runs whose settings ask for the population backend, one population per group
    of runs that can share one (an agent's seeds, and agents alike: res-ppo and random-res-ppo
    train together); returns the other runs. A run that diverged is raised once the others of
    its population are written. ``phase["done"]`` and ``phase["units"]`` count populations,
    for the ETA of the runs' lines."""
    from ermrl.population import PopulationJob, steps_trained, train_population_parallel

    checkpoints = None if settings.checkpoint_every == 0 else Path(settings.out) / CHECKPOINT_DIR
    if checkpoints is not None and settings.overwrite:
        shutil.rmtree(checkpoints, ignore_errors=True)  # retrain from the start

    groups: dict[str, list[_Job]] = {}
    rest = []
    for job in jobs:
        if job[2][2].backend == "population":
            groups.setdefault(_population_key(job[2]), []).append(job)
        else:
            rest.append(job)
    phase.update(units=len(groups), done=0)
    for group in groups.values():
        task, _, ppo = group[0][2][:3]
        names = sorted({agent.name for agent, _, _ in group})
        _say(
            stream,
            quiet,
            f"[population] {plural(len(group), 'run')} ({', '.join(names)}) on {task.label}, trained in "
            f"lockstep in {min(settings.n_procs, len(group))} process(es)",
        )
        results = train_population_parallel(
            task,
            ppo,
            budget,
            [PopulationJob(args[1], seed) for _, seed, args in group],
            n_procs=settings.n_procs,
            evaluate=settings.evaluate,
            model_paths=[args[6] for _, _, args in group],
            tensorboard_logs=[args[7] for _, _, args in group],
            checkpoints=checkpoints,
            checkpoint_every=settings.checkpoint_every,
            progress=Progress(
                f"population of {plural(len(group), 'run')} ({', '.join(names)})",
                steps_trained(ppo, budget.training_steps),
                mode="none" if quiet else settings.progress,
                stream=stream if min(settings.n_procs, len(group)) == 1 else None,
                unit="steps each",
            ),
        )
        phase["done"] += 1  # its runs' lines count it finished
        failure: BaseException | None = None
        for (agent, seed, _), result in zip(group, results):
            if isinstance(result, BaseException):
                failure = failure or result
            else:
                finished(agent, seed, result)
        if failure is not None:
            raise failure
    if checkpoints is not None and checkpoints.is_dir() and not any(checkpoints.iterdir()):
        checkpoints.rmdir()
    return rest


def aggregate(
    out: str | Path, agents: Sequence[str] | None = None, *, title: str = ""
) -> pd.DataFrame:
    """Rebuild ``curves.csv``, ``summary.csv`` and ``learning_curves.png`` from finished runs."""
    out = Path(out)
    curves = load_curves(out)
    results = load_run_results(out)
    summary = summarize(results, agents)
    write_atomic(out / "curves.csv", curves.to_csv(index=False))
    write_atomic(out / "summary.csv", summary.to_csv(index=False))
    if not curves.empty:
        plot_learning_curves(
            curves_on_grid(curves), out / "learning_curves.png", title=title, agents=agents
        )
    return summary
