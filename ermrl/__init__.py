"""ermrl: evolve reservoirs with CMA-ES in an Optuna study, learn on top of them with PPO.

The Python API mirrors the command line (names re-exported from [`ermrl.runner`][ermrl.runner],
imported on first use so that ``import ermrl`` stays instant):

- [`Experiment`][ermrl.runner.Experiment]: load, plan and run an experiment file, as
  ``ermrl run FILE`` does;
- [`evolve`][ermrl.runner.evolve], [`test`][ermrl.runner.test], [`report`][ermrl.runner.report]: one
  stage each, as ``ermrl evolve``, ``ermrl test`` and ``ermrl report`` run it;
- [`Evolution`][ermrl.runner.Evolution] (an Optuna study that trials are added to), its selected
  [`Candidate`][ermrl.runner.Candidate] (the encoder, which trains a learner in front of it) and
  the [`Model`][ermrl.agents.Model] that returns (SB3's ``predict``; ``save`` and ``load``
  without pickle).

Examples:
    >>> import ermrl
    >>> exp = ermrl.Experiment.load("experiments/demo.yaml", variant="quick")
    >>> result = exp.run()
    >>> result["Pendulum-v1"].summary
"""

from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from ermrl._blas import pin_blas_kernel

# Before anything imports numpy: one OpenBLAS kernel on every x86-64 CPU with AVX2, so that a
# seed's result does not depend on the machine (ermrl._blas says why and when it is not set).
pin_blas_kernel()

try:
    __version__ = version("ermrl")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

# Public name -> the module that defines it (imported when the name is first used). No import of
# them, not even for type checkers: the package root is the bottom layer every module may import
# (tests/test_layers.py), and an arrow from it to the runner would close a cycle.
_LAZY = {
    "Candidate": "ermrl.runner",
    "ConfigError": "ermrl.config",
    "EvolveConfig": "ermrl.config",
    "Evolution": "ermrl.runner",
    "EvolveResult": "ermrl.runner",
    "Experiment": "ermrl.runner",
    "ExperimentError": "ermrl.runner",
    "ExperimentResult": "ermrl.runner",
    "Model": "ermrl.agents",
    "PlanStep": "ermrl.runner",
    "ReportResult": "ermrl.analysis",
    "StageFailed": "ermrl.runner",
    "TaskResult": "ermrl.runner",
    "TestOptions": "ermrl.test_phase",
    "TestResult": "ermrl.runner",
    "evolve": "ermrl.runner",
    "report": "ermrl.runner",
    "test": "ermrl.runner",
}

__all__ = [
    "Candidate",
    "ConfigError",
    "EvolveConfig",
    "Evolution",
    "EvolveResult",
    "Experiment",
    "ExperimentError",
    "ExperimentResult",
    "Model",
    "PlanStep",
    "ReportResult",
    "StageFailed",
    "TaskResult",
    "TestOptions",
    "TestResult",
    "__version__",
    "evolve",
    "report",
    "test",
]


def __getattr__(name: str) -> Any:
    """Import a public name's module on first use (PEP 562)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'ermrl' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
