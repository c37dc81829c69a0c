"""Task construction and partial observability (``--observe {all,positions,velocities}``)."""

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

__all__ = [
    "OBSERVE_MODES",
    "ObservationMask",
    "ObservationSplit",
    "ObserveMode",
    "UnknownEnvError",
    "UnsupportedObserveError",
    "check_env_id",
    "make_env",
    "observation_indices",
    "observation_split",
    "supported_observe_envs",
]
