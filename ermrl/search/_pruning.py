"""Pruning: the study's pruner and the callback through which a trial reports its returns."""

from __future__ import annotations

from collections.abc import Callable

import optuna

from ermrl.config import ConfigError

__all__ = ["make_pruner", "pruning_reporter"]


def make_pruner(name: str) -> optuna.pruners.BasePruner:
    """``none``, ``median`` (median of earlier trials at the same step) or ``halving``."""
    if name == "median":
        return optuna.pruners.MedianPruner(n_startup_trials=4, n_warmup_steps=0)
    if name == "halving":
        return optuna.pruners.SuccessiveHalvingPruner()
    if name == "none":
        return optuna.pruners.NopPruner()
    raise ConfigError(f"unknown pruner {name!r}")


def pruning_reporter(trial: optuna.Trial) -> Callable[[int, float], None]:
    """Report intermediate returns to the study and raise TrialPruned when the pruner says so."""

    def report(step: int, value: float) -> None:
        trial.report(value, step)
        if trial.should_prune():
            # Seeds run one after another, so `step` counts the env steps the trial used.
            trial.set_user_attr("env_steps", int(step))
            raise optuna.TrialPruned(f"pruned at step {step} (return {value:.4g})")

    return report
