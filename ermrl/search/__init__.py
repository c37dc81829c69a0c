"""The outer loop: search spaces, samplers (CMA-ES with real restarts, TPE, random), the fitness
of a reservoir, and the evolution loop over an Optuna study."""

from ermrl.search._evolve import (
    STUDY_COMMAND_ATTR,
    STUDY_CONFIG_ATTR,
    EvolutionSummary,
    Interrupted,
    create_or_resume_study,
    format_params,
    make_pruner,
    run_evolution,
    sample_params,
    study_config,
)
from ermrl.search._objective import FitnessResult, SeedRunner, evaluate_reservoir, library_versions
from ermrl.search._samplers import (
    RESTART_STRATEGIES,
    SAMPLERS,
    RestartCmaEsSampler,
    cma_generation_info,
    make_sampler,
)

__all__ = [
    "RESTART_STRATEGIES",
    "SAMPLERS",
    "STUDY_COMMAND_ATTR",
    "STUDY_CONFIG_ATTR",
    "EvolutionSummary",
    "FitnessResult",
    "Interrupted",
    "RestartCmaEsSampler",
    "SeedRunner",
    "cma_generation_info",
    "create_or_resume_study",
    "evaluate_reservoir",
    "format_params",
    "library_versions",
    "make_pruner",
    "make_sampler",
    "run_evolution",
    "sample_params",
    "study_config",
]
