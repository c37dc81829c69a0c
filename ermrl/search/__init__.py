"""The outer loop: search spaces, samplers (CMA-ES with real restarts, TPE, random), the fitness
of a reservoir, the multi-task (generalization) fitness and its reference scores, and the evolution
loop over an Optuna study."""

from ermrl.search._evolve import (
    EvolutionSummary,
    PopulationWarning,
    cma_popsize,
    run_evolution,
)
from ermrl.search._generalization import (
    GeneralizationFitness,
    TaskOutcome,
    create_or_resume_generalization_study,
    evaluate_generalization,
    generalization_config,
    generalization_evaluator,
    generalization_study_name,
    generalization_tasks,
)
from ermrl.search._objective import (
    FitnessResult,
    SeedRunner,
    decode_candidate,
    evaluate_encoder,
    library_versions,
    pool_size,
)
from ermrl.search._progress import format_params
from ermrl.search._pruning import make_pruner
from ermrl.search._reevaluate import (
    REEVALUATION_ATTR,
    evolve_and_reevaluate,
    reevaluate_study,
    reevaluation_seeds,
    reevaluation_study_name,
    select_trial,
    stale_ranking,
    top_candidates,
    used_reevaluation_seeds,
)
from ermrl.search._samplers import (
    RESTART_STRATEGIES,
    SAMPLERS,
    RestartCmaEsSampler,
    cma_generation_info,
    make_sampler,
)
from ermrl.search._scores import (
    MissingScoreError,
    RandomScore,
    ReferenceScore,
    load_scores,
    measure_random_returns,
    reference_returns,
    scores_path,
    update_scores,
)
from ermrl.search._signals import Interrupted
from ermrl.search._study import (
    STUDY_COMMAND_ATTR,
    STUDY_CONFIG_ATTR,
    check_stored_env_ids,
    create_or_resume_study,
    resume_conflicts,
    sample_params,
    study_config,
)

__all__ = [
    "check_stored_env_ids",
    "REEVALUATION_ATTR",
    "RESTART_STRATEGIES",
    "SAMPLERS",
    "STUDY_COMMAND_ATTR",
    "STUDY_CONFIG_ATTR",
    "resume_conflicts",
    "EvolutionSummary",
    "FitnessResult",
    "GeneralizationFitness",
    "Interrupted",
    "PopulationWarning",
    "cma_popsize",
    "MissingScoreError",
    "RandomScore",
    "ReferenceScore",
    "RestartCmaEsSampler",
    "SeedRunner",
    "pool_size",
    "TaskOutcome",
    "cma_generation_info",
    "create_or_resume_generalization_study",
    "create_or_resume_study",
    "decode_candidate",
    "evaluate_encoder",
    "evaluate_generalization",
    "format_params",
    "generalization_config",
    "generalization_evaluator",
    "generalization_study_name",
    "generalization_tasks",
    "library_versions",
    "load_scores",
    "make_pruner",
    "make_sampler",
    "measure_random_returns",
    "evolve_and_reevaluate",
    "reevaluate_study",
    "reevaluation_seeds",
    "reevaluation_study_name",
    "reference_returns",
    "select_trial",
    "stale_ranking",
    "top_candidates",
    "run_evolution",
    "sample_params",
    "scores_path",
    "study_config",
    "update_scores",
    "used_reevaluation_seeds",
]
