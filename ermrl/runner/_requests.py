"""What a stage of an experiment runs, resolved from its options: the configuration objects
of the library function that runs it (`ermrl.runner._commands`).

The plan ([`ermrl.runner.experiment_plan`][ermrl.runner.experiment_plan]) builds one per evolve,
test and report step; ``ermrl run`` adds its own options (`with_run_options`) and runs it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from ermrl._config_base import ObserveMode
from ermrl._schema import option

if TYPE_CHECKING:
    from ermrl._progress import ProgressMode
    from ermrl.config import EvolveConfig
    from ermrl.test_phase import TestOptions

__all__ = [
    "EvolveRequest",
    "ReportRequest",
    "TestGeneralizationRequest",
    "TestRequest",
    "with_run_options",
]


@dataclass(frozen=True)
class EvolveRequest:
    """What ``ermrl evolve`` runs: the configuration and the options of this worker.

    Attributes:
        config: The run's configuration.
        storage: The Optuna storage URL.
        study_name: The study.
        command: The command line the study keeps.
        notes: Why the run trains with its backend when none was asked for (one line each).
        quiet: No progress lines and no summary.
        progress: ``bar``, ``lines`` or ``none`` inside each trial (``None``: the default for
            where stdout goes).
        tensorboard: The TensorBoard folder (``None``: no logs).
        wandb: A Weights & Biases project (``None``: none).
        heartbeat_interval: Seconds between a running trial's heartbeats (0: off).
        grace_period: Seconds without heartbeat before a running trial is failed.
        max_retry: Retries of a trial whose worker died.
        wait_for_running: At the end, wait for other workers' running trials.
    """

    config: EvolveConfig
    storage: str
    study_name: str
    command: str
    notes: tuple[str, ...] = ()
    quiet: bool = False
    progress: ProgressMode | None = None
    tensorboard: str | None = None
    wandb: str | None = None
    heartbeat_interval: int = 60
    grace_period: int = 300
    max_retry: int = 3
    wait_for_running: bool = True

    @classmethod
    def from_options(
        cls,
        config: EvolveConfig,
        storage: str,
        study_name: str,
        options: Any,
        *,
        command: str = "",
        notes: tuple[str, ...] | list[str] = (),
        tensorboard: str | None = None,
    ) -> EvolveRequest:
        """A request from the worker options of an evolve parser's namespace (``quiet``,
        ``progress``, ``tensorboard`` unless given, ``wandb``, ``heartbeat_interval``,
        ``grace_period``, ``max_retry`` and ``wait_for_running``)."""
        return cls(
            config, storage, study_name, command, tuple(notes), options.quiet, options.progress,
            options.tensorboard if tensorboard is None else tensorboard, options.wandb,
            options.heartbeat_interval, options.grace_period, options.max_retry,
            options.wait_for_running,
        )  # fmt: skip


@dataclass(frozen=True)
class TestRequest:
    """What ``ermrl test`` runs.

    Attributes:
        study_name: The evolution study.
        storage: Its storage URL.
        options: The test phase's options.
        quiet: No progress lines and no summary table.
        command: The command line the test folder keeps (``command.txt``).
    """

    __test__ = False  # not a pytest test class

    study_name: str
    storage: str
    options: TestOptions
    quiet: bool = False
    command: str | None = None


@dataclass(frozen=True)
class TestGeneralizationRequest:
    """What ``ermrl test-generalization`` runs: the study's reservoirs tested on ``env_id``.

    Attributes:
        study_name: The evolution study (one task or a set).
        storage: Its storage URL.
        env_id: The test task.
        options: The test phase's options.
        observe: The test task's observation mask (``None``: the study's).
        n_envs: Environments per agent (``None``: the study's, else the PPO table's).
        hyperparams: The PPO table keyed by env id (``None``: the study's, else the packaged).
        scores: The reference scores for normalized returns (``None``: the study's).
        quiet: No progress lines and no summary table.
        command: The command line the test folder keeps (``command.txt``).
    """

    __test__ = False  # not a pytest test class

    study_name: str
    storage: str
    env_id: str
    options: TestOptions
    observe: ObserveMode | None = option(
        None, "observation mask of the test task (default: the study's)"
    )
    n_envs: int | None = option(
        None, "environments per agent (default: the study's --n-envs, else the PPO table's)", low=1
    )
    hyperparams: str | None = option(
        None, "PPO table keyed by env id (default: the study's, else ermrl/data/ppo.yml)",
        metavar="YAML",
    )  # fmt: skip
    scores: str | None = option(
        None, "reference table for the normalized returns (default: the study's)", metavar="CSV"
    )
    quiet: bool = False
    command: str | None = None


@dataclass(frozen=True)
class ReportRequest:
    """What ``ermrl report`` writes (the arguments of [`ermrl.report`][ermrl.runner.report]):
    one definition for the command's options, an experiment file's ``report:`` stage and the
    function's keywords."""

    study_name: str
    storage: str
    runs: str | Path | None = option(
        None, "test-phase folder (--out of ermrl test; default: runs/<study name> if it exists)"
    )
    out: str | Path | None = option(None, "report folder (default: reports/<study name>)")
    band: Literal["ci95", "std", "sem", "none"] = option(
        "ci95", "learning-curve band across seeds: Student-t 95%% CI of the mean, std or s.e.m."
    )
    dynamics: bool = option(True, "record one res-ppo episode for the reservoir-dynamics section")
    interactive: bool = option(True, "also write interactive plotly HTML figures of the search")
    html: bool = option(True, "also write report.html next to report.md")
    quiet: bool = False


def with_run_options(
    request: Any,
    *,
    quiet: bool,
    progress: ProgressMode | None,
    tensorboard: str | None,
    wandb: str | None,
    command: str,
) -> Any:
    """A planned request with ``ermrl run``'s own options on top of the file's (``None``:
    the file's): ``--quiet``, ``--progress``, ``--tensorboard`` and ``--wandb``, and the
    stage's command line."""
    if isinstance(request, EvolveRequest):
        return dataclasses.replace(
            request,
            quiet=request.quiet or quiet,
            progress=progress if progress is not None else request.progress,
            tensorboard=tensorboard if tensorboard is not None else request.tensorboard,
            wandb=wandb if wandb is not None else request.wandb,
            command=command,
        )
    if isinstance(request, (TestRequest, TestGeneralizationRequest)):
        options = request.options
        options = dataclasses.replace(
            options,
            progress=progress if progress is not None else options.progress,
            tensorboard=tensorboard if tensorboard is not None else options.tensorboard,
            wandb=wandb if wandb is not None else options.wandb,
        )
        return dataclasses.replace(
            request, options=options, quiet=request.quiet or quiet, command=command
        )
    if isinstance(request, ReportRequest):
        return dataclasses.replace(request, quiet=request.quiet or quiet)
    raise TypeError(f"not a stage's request: {request!r}")
