"""The population backend (the default; ``--backend sb3`` is the reference): many PPO agents
trained in lockstep.

[`train_population`][ermrl.population.train_population] trains a whole population (a CMA-ES
generation's candidates x seeds, or a test phase's runs) in one process, with the semantics of the
SB3 path per agent and several times its throughput;
[`train_population_parallel`][ermrl.population.train_population_parallel] splits it over processes.
See `ermrl.population._ppo` for what is shared and what stays per agent.
"""

from ermrl.population._choice import choose_backend, population_refusal
from ermrl.population._envs import (
    BatchedReservoir,
    PopulationEnvs,
    RunningStats,
    encoder_structure,
)
from ermrl.population._parallel import group_jobs, split_jobs, train_population_parallel
from ermrl.population._policy import PolicySpec, StackedPolicy, policy_spec
from ermrl.population._ppo import (
    Checkpoint,
    PopulationJob,
    PopulationPPO,
    check_population_config,
    compute_gae,
    steps_trained,
    train_population,
)
from ermrl.population._tensorboard import PopulationLogs

__all__ = [
    "PopulationLogs",
    "BatchedReservoir",
    "Checkpoint",
    "PolicySpec",
    "PopulationEnvs",
    "PopulationJob",
    "PopulationPPO",
    "RunningStats",
    "StackedPolicy",
    "check_population_config",
    "choose_backend",
    "compute_gae",
    "encoder_structure",
    "group_jobs",
    "policy_spec",
    "population_refusal",
    "split_jobs",
    "steps_trained",
    "train_population",
    "train_population_parallel",
]
