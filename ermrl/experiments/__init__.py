"""Experiments built on evolved reservoirs: the test phase against baselines."""

from ermrl.experiments._test_phase import (
    AGENTS,
    AgentSpec,
    TestSettings,
    aggregate,
    default_test_seeds,
    run_comparison,
    study_reservoirs,
)

__all__ = [
    "AGENTS",
    "AgentSpec",
    "TestSettings",
    "aggregate",
    "default_test_seeds",
    "run_comparison",
    "study_reservoirs",
]
