"""Inner learners: the registry.

Each learner is one module (see :mod:`ermrl.learners._ppo`, the reference) holding a
:class:`Learner` subclass; add a line to :data:`LEARNERS` to register it. The CLI's
``--learner`` choices, the test phase's agents (:data:`ermrl.config.AGENT_KINDS` names a learner
per agent), the report's labels and replays all read this table.
"""

from __future__ import annotations

from collections.abc import Mapping

from ermrl.config import ConfigError
from ermrl.learners._base import Learner
from ermrl.learners._bc import BCLearner
from ermrl.learners._dagger import DAggerLearner
from ermrl.learners._framestack_ppo import FrameStackPPOLearner
from ermrl.learners._hebbian import HebbianLearner
from ermrl.learners._imitation_sac import ImitationSACLearner
from ermrl.learners._lstm_ppo import LstmPPOLearner
from ermrl.learners._ppo import PPOLearner
from ermrl.learners._rtu_ppo import RTUPPOLearner
from ermrl.learners._sac import SACLearner

__all__ = ["LEARNERS", "Learner", "get_learner", "learner_names"]

# One line per learner (and its import above): the registry order is the CLI's and the docs'.
_REGISTERED: tuple[Learner, ...] = (
    PPOLearner(),
    LstmPPOLearner(),
    FrameStackPPOLearner(),
    RTUPPOLearner(),
    HebbianLearner(),
    SACLearner(),
    BCLearner(),
    DAggerLearner(),
    ImitationSACLearner(),
)
LEARNERS: Mapping[str, Learner] = {learner.name: learner for learner in _REGISTERED}


def learner_names() -> tuple[str, ...]:
    """The registered learners' names, in registry order."""
    return tuple(LEARNERS)


def get_learner(name: str) -> Learner:
    """The learner registered as ``name``.

    Raises:
        ConfigError: no such learner (the message lists the registered ones).
    """
    learner = LEARNERS.get(name)
    if learner is None:
        raise ConfigError(f"unknown learner {name!r}; choose from {', '.join(LEARNERS)}")
    return learner
