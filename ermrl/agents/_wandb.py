"""Weights & Biases logging of one training run, through wandb's own SB3 callback.

A run of [`train_agent`][ermrl.agents.train_agent] with a [`WandbRun`][ermrl.agents.WandbRun] opens
one W&B run, syncs SB3's TensorBoard scalars into it (``sync_tensorboard``: rollout returns, losses,
...) with `wandb.integration.sb3.WandbCallback`, and stores the run's outcome in the W&B run's
summary (``ermrl/last_return``, ``ermrl/eval_return``, ``ermrl/env_steps``). ``WANDB_MODE``,
``WANDB_DIR`` and the other ``WANDB_*`` variables apply as usual (``WANDB_MODE=offline`` writes the
runs locally for a later ``wandb sync``).
"""

from __future__ import annotations

import importlib.util
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["WANDB_MISSING", "WandbRun", "study_wandb_callback", "wandb_installed", "wandb_run"]

WANDB_MISSING = (
    "--wandb needs the wandb and optuna-integration packages, which are not installed "
    "(pip install 'ermrl[wandb]')"
)


@dataclass(frozen=True)
class WandbRun:
    """Where and how one training run is logged to W&B (picklable: it travels to workers).

    Attributes:
        project: The W&B project.
        name: The run's name, e.g. ``res-ppo-seed10``.
        group: Groups the runs of one test phase or trial, e.g. the output folder's name.
        config: Stored as the W&B run's config (agent, seed, task, budget, ...).
        dir: Where wandb writes its files (``None``: ``WANDB_DIR`` or the working directory).
    """

    project: str
    name: str
    group: str | None = None
    config: dict[str, Any] = field(default_factory=dict)
    dir: str | None = None


def wandb_installed() -> bool:
    """Whether ``wandb`` and ``optuna_integration`` (the evolution's callback) can be imported."""
    return all(importlib.util.find_spec(m) is not None for m in ("wandb", "optuna_integration"))


def study_wandb_callback(
    project: str, study_name: str, config: dict[str, Any], metric_name: str = "fitness"
) -> tuple[Any, Any]:
    """optuna-integration's ``WeightsAndBiasesCallback`` for one evolution worker.

    The worker is one W&B run in the group ``study_name`` (several workers: several runs of one
    group); each recorded trial logs its parameters and ``metric_name`` at step = its number.

    Returns:
        ``(callback, finish)``: pass ``callback`` to
        [`ermrl.search.run_evolution`][ermrl.search.run_evolution] and call ``finish()`` when the
        worker is done.
    """
    import os
    import socket

    import wandb
    from optuna_integration.wandb import WeightsAndBiasesCallback

    callback = WeightsAndBiasesCallback(
        metric_name=metric_name,
        wandb_kwargs={
            "project": project,
            "group": study_name,
            "name": f"{study_name}/{socket.gethostname()}-{os.getpid()}",
            "job_type": "evolve",
            "config": config,
        },
    )
    return callback, wandb.finish


@contextmanager
def wandb_run(settings: WandbRun, tensorboard_log: str | None) -> Iterator[tuple[Any, str, Any]]:
    """Open the W&B run of ``settings``; yield ``(callback, tensorboard_log, run)``.

    ``tensorboard_log`` is kept when given, else a folder inside the W&B run: SB3 writes its
    TensorBoard events there and wandb syncs them. The run is finished on the way out, also
    when training raised (marked failed then).
    """
    import wandb
    from wandb.integration.sb3 import WandbCallback

    run = wandb.init(
        project=settings.project,
        name=settings.name,
        group=settings.group,
        config=settings.config,
        dir=settings.dir,
        sync_tensorboard=True,
        reinit="finish_previous",  # WandbCallback logs to the global wandb.run
    )
    log_dir = tensorboard_log or str(Path(run.dir) / "tensorboard")
    failed = True
    try:
        yield WandbCallback(verbose=0, log=None), log_dir, run
        failed = False
    finally:
        run.finish(exit_code=1 if failed else 0)
