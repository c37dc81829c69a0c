"""Task construction, partial observability (``--observe {all,positions,velocities}``) and task
suites (``--suite NAME``)."""

from ermrl.envs._factory import make_env
from ermrl.envs._masks import (
    OBSERVE_MODES,
    ObservationMask,
    ObservationSplit,
    ObserveMode,
    UnknownEnvError,
    UnsupportedObserveError,
    check_env_id,
    observation_indices,
    observation_split,
    supported_observe_envs,
)
from ermrl.envs._suites import Suite, UnknownSuiteError, get_suite, load_suites, with_env_version

__all__ = [
    "OBSERVE_MODES",
    "ObservationMask",
    "ObservationSplit",
    "ObserveMode",
    "Suite",
    "UnknownEnvError",
    "UnknownSuiteError",
    "UnsupportedObserveError",
    "check_env_id",
    "get_suite",
    "load_suites",
    "make_env",
    "observation_indices",
    "observation_split",
    "supported_observe_envs",
    "with_env_version",
]
