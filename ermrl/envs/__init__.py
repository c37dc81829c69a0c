"""Task construction, partial observability (``--observe {all,positions,velocities}``), task
suites (``--suite NAME``) and POPGym memory tasks (``popgym-<Name>-v0``)."""

from ermrl.envs._factory import check_env_id, make_env, observation_indices, observation_split
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

__all__ = [
    "OBSERVE_MODES",
    "POPGYM_PREFIX",
    "ObservationMask",
    "ObservationSplit",
    "ObserveMode",
    "Suite",
    "UnknownEnvError",
    "UnknownSuiteError",
    "UnsupportedObserveError",
    "check_env_id",
    "get_suite",
    "is_popgym_id",
    "load_suites",
    "make_env",
    "observation_indices",
    "observation_split",
    "popgym_env_ids",
    "supported_observe_envs",
    "with_env_version",
]
