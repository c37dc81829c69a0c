"""What every layer of ermrl shares: the configuration error, the limits, ranges, agent kinds
and tasks.

The bottom of the configuration: [`ermrl.encoders`][ermrl.encoders] builds its settings and search
spaces on it, and [`ermrl.config`][ermrl.config] (which sits above the encoders, to build a study's
configuration from the registered ones) re-exports every name, so
``from ermrl.config import ConfigError`` works everywhere.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal, Protocol, runtime_checkable

ObserveMode = Literal["all", "positions", "velocities"]
FitnessMode = Literal["last", "eval"]
ResetMode = Literal["episode", "never"]
PrunerName = Literal["none", "median", "halving"]
StartName = Literal["reference", "center"]

FITNESS_MODES: tuple[str, ...] = ("last", "eval")
RESET_MODES: tuple[str, ...] = ("episode", "never")
PRUNERS: tuple[str, ...] = ("none", "median", "halving")
STARTS: tuple[str, ...] = ("reference", "center")
BACKENDS: tuple[str, ...] = ("sb3", "population")


class ConfigError(ValueError):
    """A configuration value is invalid. The CLI turns it into a one-line error and exit code 2."""


# Upper limits: a value beyond them is a typo (``--units 1e9``, ``--training-steps 1e30``) that
# would exhaust memory or never finish; it is refused before anything is written.
MAX_UNITS = 10_000  # units of all reservoirs of one agent together
MAX_TRAINING_STEPS = 10**10  # env steps per agent
MAX_TRIALS = 1_000_000  # trials of one study
MAX_SEEDS = 1_000  # seeds (agents) per trial
MAX_N_ENVS = 1_024  # environments per agent
MAX_EPISODES = 100_000  # episodes averaged by a fitness measure


def _check_units(units: int) -> None:
    if not 1 <= units <= MAX_UNITS:
        raise ConfigError(f"units must be in [1, {MAX_UNITS}], got {units}")


def _check_steps(name: str, steps: int) -> None:
    if not 1 <= steps <= MAX_TRAINING_STEPS:
        raise ConfigError(f"{name} must be in [1, {MAX_TRAINING_STEPS:.0e}], got {steps}")


@dataclass(frozen=True)
class AgentKind:
    """What a test-phase agent is: a (learner, encoder, evolved or not) triple, and its labels.

    Attributes:
        reservoirs: ``"none"`` (the raw observation), ``"evolved"`` (the selected trial's) or
            ``"unevolved"`` (the encoder's reference, its space's ``default_reservoirs()``:
            reservoirpy's defaults for an echo state network). In a study of a learner's genes
            ([`LearnerSpace`][ermrl.config.LearnerSpace]) the agent sees the raw observation and
            ``"evolved"``/``"unevolved"`` are the learner's genes.
        observe: The agent's own observation mask (``None``: the test task's).
        description: One line for ``--help`` and the docs.
        learner: Its learner (a name of `ermrl.learners.LEARNERS`); ``None``: the
            study's own learner, with the study's settings. An agent with another learner than
            the study's takes that learner's table settings for the task (and ``--ppo``).
        label: Its name in figure legends.
        short_label: Its name on crowded axes.
        color: Its matplotlib colour, the same in every figure.
        default: Trained when ``--agents`` is not given (in a study of its family).
        family: The family of a study it can be tested in: a registered encoder's
            (`ermrl.encoders.Encoder.family`: ``"esn"`` for ``--encoder reservoir``, ...;
            the encoder declares its agents), or a learner's name for a study of its genes
            (``"hebbian"``); ``None``: any study.
        derive: What the agent makes of each of its reservoirs' settings (those
            ``reservoirs`` names): an ablation of them, as ``leaky-res-ppo`` takes the
            selected reservoir without its recurrent weights; ``None``: as they are.
    """

    reservoirs: Literal["none", "evolved", "unevolved"]
    observe: ObserveMode | None
    description: str
    learner: str | None = None
    label: str = ""
    short_label: str = ""
    color: str = ""
    default: bool = True
    family: str | None = None
    derive: Callable[[Any], Any] | None = None


@dataclass(frozen=True)
class TaskConfig:
    """The environment an agent learns.

    Attributes:
        env_id: Any registered gymnasium id (``Pendulum-v1``, ``HalfCheetah-v5``, ...).
        observe: Keep the whole observation, only its position part or only its velocity part.
    """

    env_id: str
    observe: ObserveMode = "all"

    @property
    def label(self) -> str:
        return self.env_id if self.observe == "all" else f"{self.env_id}[{self.observe}]"


@dataclass(frozen=True)
class Range:
    """A closed interval searched on a log or linear scale."""

    low: float
    high: float
    log: bool = True

    def __post_init__(self) -> None:
        if not (math.isfinite(self.low) and math.isfinite(self.high)):
            raise ConfigError(f"range bounds must be finite, got [{self.low}, {self.high}]")
        if not self.low < self.high:
            raise ConfigError(
                f"empty or inverted range [{self.low}, {self.high}]: low must be < high"
            )
        if self.log and self.low <= 0:
            raise ConfigError(f"a log-scale range needs low > 0, got [{self.low}, {self.high}]")


@runtime_checkable
class SearchSpace(Protocol):
    """What the outer loop needs of an encoder's search space
    ([`ReservoirSpace`][ermrl.encoders.ReservoirSpace] is one).

    The search samples plain ``{name: value}`` points in `ranges`; the encoder turns a
    point into its settings ([`ermrl.encoders.Encoder.decode`][ermrl.encoders.Encoder.decode]), so
    search code never handles an encoder's own types.
    """

    @property
    def param_names(self) -> tuple[str, ...]: ...

    def ranges(self) -> dict[str, Range]: ...

    def reference_params(self) -> dict[str, float]: ...

    def center_params(self) -> dict[str, float]: ...

    def contains(self, params: Mapping[str, float]) -> bool: ...


def _box_contains(ranges: Mapping[str, Range], params: Mapping[str, float]) -> bool:
    """Whether ``params`` name exactly the parameters of ``ranges``, each within its range."""
    return set(params) == set(ranges) and all(
        r.low <= params[name] <= r.high for name, r in ranges.items()
    )


def _box_center(ranges: Mapping[str, Range]) -> dict[str, float]:
    """The centre of a box (the geometric mean of the bounds on a log scale)."""
    return {
        name: math.sqrt(r.low * r.high) if r.log else (r.low + r.high) / 2
        for name, r in ranges.items()
    }
