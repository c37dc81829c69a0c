"""Inner learners: the registry.

Each learner is one module (see `ermrl.learners._ppo`, the reference) holding a
[`Learner`][ermrl.learners.Learner] subclass with its test-phase agents; add a line to `LEARNERS` to
register it. The CLI's ``--learner`` choices, the test phase's agents (`AGENT_KINDS`: the learners'
agents and the registered encoders' ones, each naming its learner), the report's labels and replays
all read this table.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping

from ermrl.config import AgentKind, ConfigError
from ermrl.encoders import encoder_agents, reference_encoder
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

__all__ = [
    "AGENTS",
    "AGENT_KINDS",
    "EVOLVED_AGENT",
    "LEARNERS",
    "UNEVOLVED_AGENT",
    "Learner",
    "default_agents",
    "evolved_agent",
    "get_learner",
    "learner_names",
    "unevolved_agent",
]

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


class _AgentTable(Mapping[str, AgentKind]):
    """The registry of test-phase agents, read afresh on each use: the reference learner's
    (``ppo``, ``ppo-full``), every registered encoder's in registry order, then the other
    learners' in registry order. A name declared twice is an error."""

    def _table(self) -> dict[str, AgentKind]:
        learners = list(LEARNERS.values())
        declared: list[tuple[str, Mapping[str, AgentKind]]] = [
            (f"learner {learners[0].name!r}", _own_agents(learners[0])),
            ("the encoders", encoder_agents()),
            *((f"learner {lr.name!r}", _own_agents(lr)) for lr in learners[1:]),
        ]
        table: dict[str, AgentKind] = {}
        for owner, agents in declared:
            for name, kind in agents.items():
                if name in table:
                    raise ConfigError(f"agent {name!r} is declared twice (again by {owner})")
                table[name] = kind
        return table

    def __getitem__(self, name: str) -> AgentKind:
        return self._table()[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._table())

    def __len__(self) -> int:
        return len(self._table())


def _own_agents(learner: Learner) -> Mapping[str, AgentKind]:
    """The agents ``learner``'s own class declares (a subclass never inherits its parent's)."""
    return vars(type(learner)).get("agents", {})


# The registry of test-phase agents (ermrl.test_phase builds them): CLI choices, defaults, the
# analysis' agent order, labels and colours are read from it. A learner's agents come with the
# learner (Learner.agents), an encoder's with the encoder (Encoder.agents).
AGENT_KINDS: Mapping[str, AgentKind] = _AgentTable()
AGENTS: tuple[str, ...] = tuple(AGENT_KINDS)  # the table when this module was imported


def _family(family: str | None) -> str:
    return family or reference_encoder().family


def evolved_agent(family: str | None = None) -> str:
    """The agent on the selected evolved encoder of a study of ``family`` (``None``: the
    reference encoder's): what the report compares and replays."""
    family = _family(family)
    return next(
        n for n, k in AGENT_KINDS.items() if k.reservoirs == "evolved" and k.family == family
    )


def unevolved_agent(family: str | None = None) -> str:
    """The agent on the unevolved reference encoder of a study of ``family``."""
    family = _family(family)
    return next(
        n for n, k in AGENT_KINDS.items() if k.reservoirs == "unevolved" and k.family == family
    )


EVOLVED_AGENT = evolved_agent()
UNEVOLVED_AGENT = unevolved_agent()


def default_agents(observe: str, family: str | None = None) -> tuple[str, ...]:
    """The default agents of a study of encoder ``family`` (``None``: the reference encoder's),
    less those whose own mask is the task's: ``ppo-full`` on an unmasked task would repeat
    ``ppo`` run for run."""
    family = _family(family)
    return tuple(
        a
        for a, kind in AGENT_KINDS.items()
        if kind.default and kind.observe != observe and kind.family in (None, family)
    )
