"""Task construction, partial observability (``--observe {all,positions,velocities}``), task
suites (``--suite NAME``), POPGym memory tasks (``popgym-<Name>-v0``) and ermrl's registered
variants (``AntNoContact-v5``)."""

from ermrl.envs._factory import (
    check_env_id,
    check_registered_env_id,
    make_env,
    observation_indices,
    observation_split,
)
from ermrl.envs._masks import (
    OBSERVE_MODES,
    ObservationMask,
    ObservationSplit,
    ObserveMode,
    UnknownEnvError,
    UnsupportedObserveError,
    supported_observe_envs,
)
from ermrl.envs._popgym import POPGYM_PREFIX, is_popgym_id, popgym_env_ids
from ermrl.envs._suites import Suite, UnknownSuiteError, get_suite, load_suites, with_env_version
from ermrl.envs._variants import VARIANTS, register_variants

register_variants()

__all__ = [
    "OBSERVE_MODES",
    "POPGYM_PREFIX",
    "VARIANTS",
    "ObservationMask",
    "ObservationSplit",
    "ObserveMode",
    "Suite",
    "UnknownEnvError",
    "UnknownSuiteError",
    "UnsupportedObserveError",
    "check_env_id",
    "check_registered_env_id",
    "get_suite",
    "is_popgym_id",
    "load_suites",
    "make_env",
    "observation_indices",
    "observation_split",
    "popgym_env_ids",
    "register_variants",
    "supported_observe_envs",
    "with_env_version",
]
