"""The options of an evolution, defined once: ``ermrl evolve``, ``ermrl evolve-generalization``
and ``ermrl study create`` generate their options from these fields, an experiment file's
``evolve:`` stage is validated by them, and so are [`ermrl.evolve`][ermrl.runner.evolve]'s
keywords (`ermrl._schema`).

The fields are those of the problem (task, learner, reservoirs), the search and the workers.
Each registered encoder's settings (`ermrl.encoders.Encoder.settings`) become fields of the
``reservoirs`` section: an encoder added to the registry has its settings on the command
line, in experiment files and in Python without further code. So the options are a dataclass
built from the registry (`evolve_options`),
again when the registry changes.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from ermrl._schema import Option, fields_of, option
from ermrl.config import FITNESS_MODES, PRUNERS, RESET_MODES, STARTS, Range
from ermrl.encoders import ENCODERS, reference_encoder
from ermrl.learners import LEARNERS
from ermrl.storage import DEFAULT_STORAGE

__all__ = [
    "GENES",
    "INNER",
    "OUTER",
    "RESERVOIRS",
    "TASKS",
    "WORKERS",
    "encoder_fields",
    "encoder_settings",
    "evolve_options",
    "section",
]

# The help sections of the evolve commands (argument groups), in the order they show them.
INNER = "inner loop (the learner: PPO by default)"
RESERVOIRS = "reservoirs (the evolved encoder)"
GENES = (
    "learner genes (a learner with genes, --learner hebbian, has no encoder: evolution shapes "
    "the learner itself)"
)
OUTER = "outer loop (Optuna)"
WORKERS = "workers sharing a study (crash and preemption recovery)"
TASKS = "tasks"

_Field = tuple[str, Any, Any]


def _learner_help() -> str:
    return (
        "the inner learner, trained on the reservoir states: "
        + "; ".join(f"{name}: {learner.description}" for name, learner in LEARNERS.items())
        + ". Its settings come from its own table (see --hyperparams) and --ppo"
    )


def _range_text(r: Range) -> str:
    return f"[{r.low:g}, {r.high:g}]{'' if r.log else ' lin'}"


def _gene_help() -> str:
    genes = "; ".join(
        f"{name}: " + ", ".join(f"{g} {_range_text(r)}" for g, r in learner.genes.items())
        for name, learner in LEARNERS.items()
        if learner.genes
    )
    return (
        "another search range for a gene (log scale when the default range is; "
        f"NAME=LOW:HIGH:lin or :log to choose). Genes and default ranges: {genes}"
    )


def _tasks() -> list[_Field]:
    """The task set of ``ermrl evolve-generalization`` (one of ``env_ids`` and ``suite``)."""
    return [
        ("env_ids", Sequence[str] | None, option(
            None, "the task set, e.g. Ant-v5 Swimmer-v5", metavar="ENV_ID", group=TASKS)),
        ("suite", str | None, option(
            None, "a named task set: ant_swimmer, ant_cheetah, cheetah_swimmer, no_ant, "
            "no_halfcheetah, no_hopper, no_swimmer, no_walker2d, forward_mujoco, or one of "
            "--suites-file", group=TASKS)),
        ("suites_file", str | Path | None, option(
            None, "your own suites (same format as ermrl/data/suites.yml), added to the "
            "packaged ones", metavar="YAML", group=TASKS)),
        ("env_version", str | None, option(
            None, "with --suite: use this version of every env (the packaged suites are v5)",
            metavar="vN", group=TASKS)),
        ("scores", str | Path | None, option(
            None, "reference table of random and target returns (default: "
            "ermrl/data/scores.csv)", metavar="CSV", group=TASKS)),
        ("target_column", Literal["target", "provisional_target"], option(
            "target", "R_target: 'target' (PPO at 1M steps, rl-baselines3-zoo) or "
            "'provisional_target' (the original ER-MRL code's values)", group=TASKS)),
    ]  # fmt: skip


def _problem(multi_task: bool) -> list[_Field]:
    """The task's mask and the inner loop (the learner, its budget, fitness and layout)."""
    from ermrl.test_phase._prepare import FOR_LEARNER_HELP, STALE_GRADIENT_HELP, check_for_learner

    env_id: list[_Field] = [] if multi_task else [("env_id", str | None, option(
        None, "gymnasium env id, e.g. Pendulum-v1, HalfCheetah-v5, popgym-RepeatFirstEasy-v0",
        required=True))]  # fmt: skip
    return env_id + [
        ("observe", Literal["all", "positions", "velocities"], option(
            "all", "keep the whole observation, only its positions (velocities hidden) or only "
            "its velocities")),
        ("learner", str, option(
            "ppo", _learner_help, choices=lambda: tuple(LEARNERS), group=INNER)),
        ("stale_gradient", bool | None, option(None, STALE_GRADIENT_HELP, group=INNER)),
        ("for_learner", Mapping[str, Mapping[str, Any]], option(
            {}, FOR_LEARNER_HELP, metavar=("LEARNER", "KEY=VALUE"), group=INNER,
            check=lambda v: check_for_learner(v))),
        ("backend", Literal["population", "sb3"] | None, option(
            None, "what trains the agents: population (a whole generation's candidates x seeds "
            "trained in lockstep with the same PPO, several times faster per core; ppo learner "
            "only, no --pruner) or sb3 (the reference implementation: one Stable-Baselines3 "
            "process per agent). Default: population where it applies, else sb3 with one line "
            "saying why. Stored with the study: a study never mixes backends, and a resumed "
            "study keeps its own", group=INNER)),
        ("training_steps", int, option(
            300_000, "env steps per agent (paper: 300000)", low=1, group=INNER)),
        ("n_seeds", int, option(
            3, "agents (seeds) per trial; fitness is their mean", low=1, group=INNER)),
        ("seed", int, option(
            0, "first training seed; a trial uses seed .. seed+n_seeds-1", low=0, group=INNER)),
        ("fitness", Literal[FITNESS_MODES], option(
            "last", "'last': mean return of the last --n-last-episodes training episodes "
            "(paper); 'eval': mean return of --n-eval-episodes deterministic episodes after "
            "training", group=INNER)),
        ("n_last_episodes", int, option(
            10, "training episodes averaged by --fitness last", low=1, group=INNER)),
        ("n_eval_episodes", int, option(
            5, "evaluation episodes of --fitness eval", low=1, group=INNER)),
        ("n_envs", int | None, option(
            None, "environments per agent stepped in lockstep (DummyVecEnv); PPO collects "
            "n_steps*n_envs transitions per update. Default: the packaged table's value for the "
            "env, else 1 (paper)", low=1, group=INNER)),
        ("ppo", Mapping[str, Any] | Sequence[str], option(
            (), "the learner's hyperparameter overrides, e.g. --ppo learning_rate=1e-4 "
            "n_steps=1024 (rl-zoo's KEY:VALUE works too; framestack-ppo: frame_stack=K)",
            metavar="KEY=VALUE", words=True, group=INNER)),
        ("hyperparams", str | Path | None, option(
            None, "the learner's settings table keyed by env id (default: its packaged table, "
            "ermrl/data/ppo.yml for PPO)", metavar="YAML", group=INNER)),
        ("n_procs", int, option(
            1, "cores that train a trial's runs in parallel (one single-threaded process per "
            "core, or per run up to twice the cores when the runs do not divide evenly: 3 seeds "
            "on 2 cores run in 3 processes so that no core idles; needs --pruner none)", low=1,
            group=INNER)),
        ("torch_threads", int, option(
            1, "torch threads per training process", low=1, group=INNER)),
    ]  # fmt: skip


def _reservoirs_head() -> list[_Field]:
    return [
        ("encoder", str, option(
            reference_encoder().name,
            lambda: "; ".join(f"'{e.name}': {e.description}" for e in ENCODERS.values()),
            choices=lambda: tuple(ENCODERS), group=RESERVOIRS)),
        ("n_reservoirs", int, option(
            1, "reservoirs (or RTU layers, NVARs, ...) per agent, each with its own evolved "
            "parameters", low=1, group=RESERVOIRS)),
    ]  # fmt: skip


def _reservoirs_tail() -> list[_Field]:
    """What the reservoirs read and show the policy, shared by every encoder."""
    return [
        ("input_scaling_range", tuple[float, float], option(
            (1e-1, 10.0), "input scaling range (log scale)", metavar=("LOW", "HIGH"), above=0,
            group=RESERVOIRS)),
        ("fixed_input_scaling", float | None, option(
            None, "do not evolve input scaling; fix it at VALUE (1.0 when no value is given)",
            metavar="VALUE", above=0, const=1.0, group=RESERVOIRS)),
        ("skip_connection", bool, option(
            False, "the policy also sees [observation, previous action, previous reward]",
            group=RESERVOIRS)),
        ("reset", Literal[RESET_MODES], option(
            "episode", "reset reservoir states at each episode, or carry them across episodes",
            group=RESERVOIRS)),
        ("exposed_units", int | None, option(
            None, "show the policy only the first N units of each reservoir", low=1,
            group=RESERVOIRS)),
        ("reward_scale", float, option(
            1.0, "factor applied to the reward fed to the reservoir", group=RESERVOIRS)),
        ("dtype", Literal["float32", "float64"], option(
            "float32", "reservoir state precision: float32 is about twice as cheap per step; "
            "float64 reproduces reservoirpy's own states to 1e-10", group=RESERVOIRS)),
        ("feed_action", bool, option(
            True, "feed the previous action to the reservoir", group=RESERVOIRS)),
        ("feed_reward", bool, option(
            True, "feed the previous reward to the reservoir", group=RESERVOIRS)),
    ]  # fmt: skip


def encoder_fields() -> list[_Field]:
    """Every registered encoder's settings (`ermrl.encoders.Encoder.settings`) as fields of
    the ``reservoirs`` section; a setting that several encoders declare alike is one field
    whose help joins theirs.

    Raises:
        ValueError: Two encoders declare one setting differently (other than its help).
    """
    merged: dict[str, tuple[Any, Any, Option]] = {}
    for encoder in ENCODERS.values():
        if encoder.settings is None:
            continue
        hints = typing.get_type_hints(encoder.settings)
        for f in dataclasses.fields(encoder.settings):
            opt = dataclasses.replace(f.metadata["option"], group=RESERVOIRS)
            known = merged.get(f.name)
            if known is None:
                merged[f.name] = (hints[f.name], f.default, opt)
                continue
            hint, default, first = known
            alike = (hint, default) == (hints[f.name], f.default)
            if not alike or dataclasses.replace(first, help=opt.help) != opt:
                raise ValueError(f"encoders declare the setting {f.name} differently")
            if opt.help and opt.help not in str(first.help):
                helps = "; ".join(str(h) for h in (first.help, opt.help) if h)
                merged[f.name] = (hint, default, dataclasses.replace(first, help=helps))
    return [
        (name, hint, dataclasses.field(default=default, metadata={"option": opt}))
        for name, (hint, default, opt) in merged.items()
    ]


def _search() -> list[_Field]:
    """The outer loop: the sampler, the pruner and the re-evaluation of the best."""
    return [
        ("n_trials", int, option(
            100, "total trials of the study, all workers together", low=1, group=OUTER)),
        ("sampler", Literal["cmaes", "tpe", "random"], option(
            "cmaes", "search algorithm", group=OUTER)),
        ("sampler_seed", int | None, option(
            None, "sampler seed (default: nondeterministic)", low=0, group=OUTER)),
        ("restart", Literal["none", "ipop", "bipop"], option(
            "none", "CMA-ES restart strategy (larger populations on restart)", group=OUTER)),
        ("popsize", int | None, option(
            None, "CMA-ES population size (default: 4 + 3 ln(dim))", low=1, group=OUTER)),
        ("pruner", Literal[PRUNERS], option(
            "none", "stop unpromising trials early from intermediate training returns",
            group=OUTER)),
        ("cma_start", Literal[STARTS], option(
            "center", "first CMA-ES mean: 'center' = the centre of the log-scaled box, as in "
            "the ER-MRL paper's code (with the reference trial competing, it did at least as "
            "well in benchmarks/bench_science.py); 'reference' = the unevolved reservoir "
            "(reservoirpy defaults sr = lr = input_scaling = 1, clipped into the box), better "
            "for a handful of trials", group=OUTER)),
        ("reference_trial", bool, option(
            True, "queue the unevolved reference reservoir as the study's first trial, so that "
            "the study's best can never be worse than it without showing it", group=OUTER)),
        ("reevaluate_top", int, option(
            0, "when the budget is spent, re-train the K best trials and the reference trial "
            "on fresh seeds (study '<name>.reeval'); the test phase then uses that ranking (0: "
            "off)", metavar="K", low=0, group=OUTER)),
        ("reevaluate_seeds", int, option(
            3, "fresh seeds per re-evaluated candidate (seed + 1000 and up)", low=1,
            group=OUTER)),
        ("reevaluate_steps", int | None, option(
            None, "training steps of a re-evaluation run (default: --training-steps; the test "
            "budget removes the evolution/test budget mismatch)", low=1, group=OUTER)),
    ]  # fmt: skip


def _workers() -> list[_Field]:
    """Heartbeats, retries and the end of a worker that shares a study with others."""
    return [
        ("heartbeat_interval", int, option(
            60, "a running trial records a heartbeat this often; 0 turns heartbeats off (for "
            "every worker of the study: a trial that never sent one is failed after the grace "
            "period)", metavar="SECONDS", low=0, group=WORKERS)),
        ("grace_period", int, option(
            300, "a running trial without heartbeat for this long is failed and retried (its "
            "worker died)", metavar="SECONDS", low=1, group=WORKERS)),
        ("max_retry", int, option(
            3, "retries of a trial whose worker died or was preempted (SIGTERM), same "
            "parameters", low=0, group=WORKERS)),
        ("wait_for_running", bool, option(
            True, "when the budget is reached, wait for other workers' running trials (and "
            "retry those whose worker died) instead of exiting", group=WORKERS)),
    ]  # fmt: skip


def _logging() -> list[_Field]:
    """Progress, TensorBoard and Weights & Biases logs; the storage and the study's name
    (given by ``ermrl run`` or the call, never by a file's stage) and ``quiet``."""
    from ermrl._progress import PROGRESS_MODES

    return [
        ("progress", Literal[PROGRESS_MODES] | None, option(
            None, "progress inside each trial (the command line's own --progress)", cli=False)),
        ("tensorboard", str | Path | None, option(
            None, "also log each trial's training curves for TensorBoard under "
            "DIR/trial_<n>/seed_<s> (a trial on several tasks: DIR/trial_<n>/<env_id>/"
            "seed_<s>), the scalars SB3's PPO logs, on either backend (needs: pip install "
            "tensorboard)", metavar="DIR")),
        ("wandb", str | None, option(
            None, "also log each trial (its parameters and fitness) to the Weights & Biases "
            "project PROJECT, through optuna-integration's WeightsAndBiasesCallback: one W&B "
            "run per worker, grouped by study name (WANDB_MODE=offline logs locally; needs: "
            "pip install 'ermrl[wandb]')", metavar="PROJECT")),
        ("storage", str, dataclasses.field(default=DEFAULT_STORAGE)),
        ("study_name", str | None, dataclasses.field(default=None)),
        ("quiet", bool, dataclasses.field(default=False)),
    ]  # fmt: skip


_BUILT: dict[tuple[Any, ...], type] = {}


def evolve_options(*, multi_task: bool = False) -> type:
    """The options of an evolution as a dataclass, with the registered encoders' settings.

    Args:
        multi_task: The options of an evolution on a set of tasks (``ermrl
            evolve-generalization``: the task set in place of ``env_id``, no learner genes).

    Returns:
        ``EvolveOptions`` (or ``GeneralizationOptions``): every field has a default, and its
        attributes are those that `ermrl.runner._resolve.config_from_args`
        reads.

    Examples:
        >>> options = evolve_options()(env_id="CartPole-v1", n_trials=4)
        >>> options.n_trials, options.encoder
        (4, 'reservoir')
    """
    key = (multi_task, *ENCODERS.items())  # (the encoders themselves: an id may be reused)
    built = _BUILT.get(key)
    if built is None:
        genes: list[_Field] = [] if multi_task else [("gene", Sequence[str] | Mapping[str, Any] | None, option(
            None, _gene_help, metavar="NAME=LOW:HIGH", words=True, group=GENES))]  # fmt: skip
        fields = (
            (_tasks() if multi_task else []) + _problem(multi_task) + _reservoirs_head()
            + encoder_fields() + _reservoirs_tail() + genes + _search() + _workers()
            + _logging()
        )  # fmt: skip
        name = "GeneralizationOptions" if multi_task else "EvolveOptions"
        built = dataclasses.make_dataclass(name, fields, frozen=True)
        built.__module__ = __name__
        built.__doc__ = "The options of an evolution" + (
            " on a set of tasks." if multi_task else "."
        )
        _BUILT[key] = built
    return built


def section(cls: type, *titles: str | None) -> tuple[str, ...]:
    """The names of the command-line fields of ``cls`` in these help sections (``None``: the
    command's own options), in order."""
    return tuple(s.name for s in fields_of(cls) if s.option.cli and s.option.group in titles)


def encoder_settings(options: Any) -> dict[str, tuple[str, Any]]:
    """The encoder's settings of the options (the ``reservoirs`` section): name -> ``(flag,
    default)``, so that a learner with genes, which has no encoder, refuses them."""
    cls = evolve_options(multi_task=not hasattr(options, "env_id"))
    return {s.name: (s.flag, s.default) for s in fields_of(cls) if s.option.group == RESERVOIRS}
