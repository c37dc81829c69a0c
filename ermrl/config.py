"""Frozen configuration dataclasses shared by every part of ermrl.

A run's whole configuration is one :class:`EvolveConfig`. It is saved as a study user attribute
(``ermrl_config``) and as ``config.yaml`` next to results, so the test phase and the analysis need
only the study name and the storage URL.

Derived values are properties, never fields filled in after parsing.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, Protocol, TypeVar, runtime_checkable

ObserveMode = Literal["all", "positions", "velocities"]
FitnessMode = Literal["last", "eval"]
ResetMode = Literal["episode", "never"]
PrunerName = Literal["none", "median", "halving"]
StartName = Literal["reference", "center"]
BiasInit = Literal["none", "original"]

FITNESS_MODES: tuple[str, ...] = ("last", "eval")
RESET_MODES: tuple[str, ...] = ("episode", "never")
PRUNERS: tuple[str, ...] = ("none", "median", "halving")
STARTS: tuple[str, ...] = ("reference", "center")
BACKENDS: tuple[str, ...] = ("sb3", "population")
BIAS_INITS: tuple[str, ...] = ("none", "original")
# Encoder families: echo state networks (reservoirpy) and frozen recurrent trace units.
FAMILIES: tuple[str, ...] = ("esn", "rtu")


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
            ``"unevolved"`` (reservoirpy's defaults, :meth:`ReservoirSpace.default_reservoirs`).
            In a study of a learner's genes (:class:`LearnerSpace`) the agent sees the raw
            observation and ``"evolved"``/``"unevolved"`` are the learner's genes.
        observe: The agent's own observation mask (``None``: the test task's).
        description: One line for ``--help`` and the docs.
        learner: Its learner (a name of :data:`ermrl.learners.LEARNERS`); ``None``: the
            study's own learner, with the study's settings. An agent with another learner than
            the study's takes that learner's table settings for the task (and ``--ppo``).
        label: Its name in figure legends.
        short_label: Its name on crowded axes.
        color: Its matplotlib colour, the same in every figure.
        default: Trained when ``--agents`` is not given (in a study of its family).
        family: The encoder family of a study it can be tested in (``"esn"``: evolved with
            ``--encoder reservoir``, ``"rtu"``: with ``--encoder rtu``, ``"hebbian"``: a study
            of the Hebbian learner's genes); ``None``: any study.
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


# The registry of test-phase agents (ermrl.experiments builds them): CLI choices, defaults, the
# analysis' agent order, labels and colours are read from it. One line adds an agent.
AGENT_KINDS: Mapping[str, AgentKind] = {
    "ppo": AgentKind(
        "none", None, "PPO on the raw (masked) observation", "ppo",
        "PPO (raw observation)", "PPO", "tab:blue",
    ),
    "ppo-full": AgentKind(
        "none", "all", "PPO on the full, unmasked observation: the ceiling memory should approach",
        "ppo", "PPO (full observation)", "PPO\n(full obs.)", "tab:gray",
    ),
    "res-ppo": AgentKind(
        "evolved", None, "the study's learner on the selected evolved reservoir(s)", None,
        "RES-PPO (evolved reservoir)", "RES-PPO\n(evolved)", "tab:orange", family="esn",
    ),
    "random-res-ppo": AgentKind(
        "unevolved", None,
        "the study's learner on unevolved reservoirs (reservoirpy's defaults): what evolution adds",
        None, "RES-PPO (unevolved reservoir)", "RES-PPO\n(unevolved)", "tab:green",
        family="esn",
    ),
    "rtu-res-ppo": AgentKind(
        "evolved", None,
        "the study's learner on the selected evolved frozen RTU layer(s) (--encoder rtu studies)",
        None, "RTU-RES-PPO (evolved RTU)", "RTU-RES\n(evolved)", "tab:red", family="rtu",
    ),
    "random-rtu-res-ppo": AgentKind(
        "unevolved", None,
        "the study's learner on frozen RTUs of the paper's initialization (--encoder rtu studies)",
        None, "RTU-RES-PPO (unevolved RTU)", "RTU-RES\n(unevolved)", "tab:pink", family="rtu",
    ),
    "lstm-ppo": AgentKind(
        "none", None, "RecurrentPPO (LSTM policy) on the raw (masked) observation: memory baseline",
        "lstm-ppo", "LSTM-PPO (raw observation)", "LSTM-PPO", "tab:purple", default=False,
    ),
    "framestack-ppo": AgentKind(
        "none", None, "PPO on the last k raw (masked) observations (frame_stack, default 4)",
        "framestack-ppo", "PPO (4 stacked frames)", "PPO\n(stacked)", "tab:brown", default=False,
    ),
    "rtu-ppo": AgentKind(
        "none", None,
        "PPO with recurrent trace units learned online by RTRL (real-time PPO): learned memory",
        "rtu-ppo", "RTU-PPO (learned RTU)", "RTU-PPO", "tab:olive", default=False,
    ),
    "hebbian": AgentKind(
        "evolved", None,
        "the Hebbian learner with the selected evolved genes (evolve --learner hebbian studies)",
        None, "Hebbian (evolved genes)", "Hebbian\n(evolved)", "tab:cyan", family="hebbian",
    ),
    "random-hebbian": AgentKind(
        "unevolved", None,
        "the Hebbian learner with its default genes (the original's values; --learner hebbian "
        "studies)",
        None, "Hebbian (default genes)", "Hebbian\n(default)", "darkgoldenrod", family="hebbian",
    ),
    "sac": AgentKind(
        "none", None, "SAC (off-policy) on the raw (masked) observation", "sac",
        "SAC (raw observation)", "SAC", "black", default=False,
    ),
    "res-sac": AgentKind(
        "evolved", None, "SAC on the selected evolved reservoir(s) (its replay holds their states)",
        "sac", "RES-SAC (evolved reservoir)", "RES-SAC\n(evolved)", "teal", default=False,
        family="esn",
    ),
    "dagger": AgentKind(
        "none", None,
        "DAgger on the raw (masked) observation; its expert sees the full state "
        "(--for-learner dagger expert=DIR)",
        "dagger", "DAgger (raw observation)", "DAgger", "navy", default=False,
    ),
    "res-dagger": AgentKind(
        "evolved", None,
        "DAgger on the selected evolved reservoir(s)' states; its expert sees the full state",
        "dagger", "RES-DAgger (evolved reservoir)", "RES-DAgger\n(evolved)", "magenta",
        default=False, family="esn",
    ),
    "imitation-sac": AgentKind(
        "none", None,
        "SAC seeded by DAgger from an expert that sees the full state, on the raw (masked) "
        "observation (--for-learner imitation-sac expert=DIR)",
        "imitation-sac", "Imitation-SAC (raw observation)", "Imit.-SAC", "chocolate",
        default=False,
    ),
    "res-imitation-sac": AgentKind(
        "evolved", None,
        "imitation-seeded SAC on the selected evolved reservoir(s)' states; its expert sees the "
        "full state",
        "imitation-sac", "RES-Imitation-SAC (evolved reservoir)", "RES-Imit.-SAC\n(evolved)",
        "slateblue", default=False, family="esn",
    ),
}  # fmt: skip
AGENTS: tuple[str, ...] = tuple(AGENT_KINDS)


def evolved_agent(family: str = "esn") -> str:
    """The agent on the selected evolved encoder of a study of ``family``: what the report
    compares and replays."""
    return next(
        n for n, k in AGENT_KINDS.items() if k.reservoirs == "evolved" and k.family == family
    )


def unevolved_agent(family: str = "esn") -> str:
    """The agent on the unevolved reference encoder of a study of ``family``."""
    return next(
        n for n, k in AGENT_KINDS.items() if k.reservoirs == "unevolved" and k.family == family
    )


EVOLVED_AGENT = evolved_agent()
UNEVOLVED_AGENT = unevolved_agent()


def default_agents(observe: str, family: str = "esn") -> tuple[str, ...]:
    """The default agents of a study of encoder ``family``, less those whose own mask is the
    task's: ``ppo-full`` on an unmasked task would repeat ``ppo`` run for run."""
    return tuple(
        a
        for a, kind in AGENT_KINDS.items()
        if kind.default and kind.observe != observe and kind.family in (None, family)
    )


@dataclass(frozen=True)
class ReservoirParams:
    """Hyperparameters of one echo state network (reservoirpy ``Reservoir`` arguments).

    The defaults are reservoirpy's own, which is what ``random-res-ppo`` uses as the unevolved
    reference reservoir.

    Attributes:
        units: Number of reservoir neurons.
        sr: Spectral radius of the recurrent matrix ``W``.
        lr: Leak rate in (0, 1]: ``x <- (1 - lr) x + lr tanh(W x + Win u + b)``.
        input_scaling: Scale of the input matrix ``Win`` (Bernoulli +-input_scaling entries).
        rc_connectivity: Density of ``W``.
        input_connectivity: Density of ``Win``.
        bias_scaling: Scale of a dense Bernoulli bias (every unit +-bias_scaling); 0 means no
            bias (reservoirpy 0.4's default).
        bias_init: ``"none"``: the bias above. ``"original"``: reservoirpy 0.3's default bias,
            which the original ER-MRL code used: Bernoulli +-1 on ``input_connectivity`` of
            the units (10 of 100), zero elsewhere; needs ``bias_scaling`` 0. Left out of
            :func:`to_dict` while ``"none"``, so configs stored before it existed are unchanged.
    """

    units: int = 100
    sr: float = 1.0
    lr: float = 1.0
    input_scaling: float = 1.0
    rc_connectivity: float = 0.1
    input_connectivity: float = 0.1
    bias_scaling: float = 0.0
    bias_init: BiasInit = field(default="none", metadata={"omit_if_default": True})

    family: ClassVar[str] = "esn"

    @property
    def state_dim(self) -> int:
        """Width of the state the policy can see: one value per unit."""
        return self.units

    def __post_init__(self) -> None:
        if self.bias_init not in BIAS_INITS:
            raise ConfigError(f"bias_init must be one of {BIAS_INITS}, got {self.bias_init!r}")
        if self.bias_init == "original" and self.bias_scaling > 0:
            raise ConfigError(
                "bias_init 'original' draws reservoirpy 0.3's +-1 sparse bias; it cannot be "
                f"combined with bias_scaling {self.bias_scaling} (a dense bias)"
            )
        _check_units(self.units)
        if not (self.sr > 0 and math.isfinite(self.sr)):
            raise ConfigError(f"spectral radius sr must be positive, got {self.sr}")
        if not (0 < self.lr <= 1):
            raise ConfigError(f"leak rate lr must be in (0, 1], got {self.lr}")
        if not (self.input_scaling > 0 and math.isfinite(self.input_scaling)):
            raise ConfigError(f"input_scaling must be positive, got {self.input_scaling}")
        for name in ("rc_connectivity", "input_connectivity"):
            value = getattr(self, name)
            if not (0 < value <= 1):
                raise ConfigError(f"{name} must be in (0, 1], got {value}")
        if not (self.bias_scaling >= 0 and math.isfinite(self.bias_scaling)):
            raise ConfigError(f"bias_scaling must be finite and >= 0, got {self.bias_scaling}")


@dataclass(frozen=True)
class RTUParams:
    """Hyperparameters of one frozen layer of recurrent trace units (a complex-diagonal reservoir).

    The units of Elelimy et al. (2024), with fixed random weights: each of the ``units`` complex
    units holds ``(c1, c2)``; with ``g = r cos(theta)``, ``phi = r sin(theta)`` and
    ``gamma = sqrt(1 - r^2)``::

        c1 <- g c1 - phi c2 + gamma (W1 u)
        c2 <- g c2 + phi c1 + gamma (W2 u)

    The policy sees ``tanh([c1; c2])`` (``2 * units`` values). ``r^2 ~ U(r_min^2, r_max^2)`` and
    ``theta ~ U(0, theta_max)`` per unit; ``W1`` and ``W2`` are dense ``N(0, input_scaling^2 /
    input_dim)``. The defaults are the paper's initialization (r in (0, 1), theta in (0, 2 pi)),
    the unevolved reference of ``--encoder rtu``.

    Attributes:
        units: Complex units (the state has ``2 * units`` values).
        r_min: Lower bound of the decay rates' range, in [0, r_max].
        r_max: Upper bound of the decay rates' range, in (0, 1].
        theta_max: Upper bound of the rotation frequencies' range (radians per step).
        input_scaling: Scale of ``W1`` and ``W2``.
        family: Always ``"rtu"`` (tells stored configurations apart from echo state networks).
    """

    units: int = 50
    r_min: float = 0.0
    r_max: float = 1.0
    theta_max: float = 2 * math.pi
    input_scaling: float = 1.0
    family: Literal["rtu"] = "rtu"

    @property
    def state_dim(self) -> int:
        """Width of the state the policy can see: two values per complex unit."""
        return 2 * self.units

    def __post_init__(self) -> None:
        if self.family != "rtu":
            raise ConfigError(f"RTUParams family must be 'rtu', got {self.family!r}")
        _check_units(2 * self.units)
        if not (0 < self.r_max <= 1):
            raise ConfigError(f"r_max must be in (0, 1], got {self.r_max}")
        if not (0 <= self.r_min <= self.r_max):
            raise ConfigError(f"r_min must be in [0, r_max = {self.r_max}], got {self.r_min}")
        if not (self.theta_max > 0 and math.isfinite(self.theta_max)):
            raise ConfigError(f"theta_max must be positive, got {self.theta_max}")
        if not (self.input_scaling > 0 and math.isfinite(self.input_scaling)):
            raise ConfigError(f"input_scaling must be positive, got {self.input_scaling}")


EncoderParams = ReservoirParams | RTUParams


@dataclass(frozen=True)
class EncoderConfig:
    """How the reservoir(s) turn observations into the policy's input.

    Attributes:
        reservoirs: One :class:`ReservoirParams` (echo state network) or :class:`RTUParams`
            (frozen recurrent trace units) per reservoir, all of one family; their states are
            concatenated.
        skip_connection: The policy sees ``[state, observation, action, reward]``, not only the state.
        reset: ``"episode"`` zeroes a row's state when its episode ends; ``"never"`` carries it.
        exposed_units: Expose only the first N units of each reservoir to the policy (``None``: all).
        reward_scale: Factor applied to the previous reward before it enters the reservoir.
        feed_action: Feed the previous action (one-hot or scaled to [-1, 1]) to the reservoir.
        feed_reward: Feed the previous reward to the reservoir.
        dtype: Float type of the reservoir state and weights. ``float32`` (default) is about
            twice as cheap per step. How closely it follows float64 depends on the dynamics
            (100 units, lr 1, 100 steps of N(0, 1) input, worst of 5 seeds): within ~1e-6 up to
            sr 1.5, up to 6e-4 at sr 2, and from sr ~2.5 the two trajectories decorrelate
            (sr 3: 3e-2 apart by step 50, 2.0, the whole tanh range, by step 100). There the
            reservoir is chaotic and any rounding change separates trajectories; the states
            stay statistically alike but are not reservoirpy's. ``float64`` reproduces
            reservoirpy's own states to 1e-10.
    """

    reservoirs: tuple[EncoderParams, ...] = (ReservoirParams(),)
    skip_connection: bool = False
    reset: ResetMode = "episode"
    exposed_units: int | None = None
    reward_scale: float = 1.0
    feed_action: bool = True
    feed_reward: bool = True
    dtype: Literal["float64", "float32"] = "float32"

    def __post_init__(self) -> None:
        if self.dtype not in ("float64", "float32"):
            raise ConfigError(f"dtype must be float64 or float32, got {self.dtype!r}")
        if not self.reservoirs:
            raise ConfigError("an encoder needs at least one reservoir")
        if len({p.family for p in self.reservoirs}) > 1:
            raise ConfigError("the reservoirs of one encoder must all be of one family")
        if self.total_units > MAX_UNITS:
            raise ConfigError(
                f"the reservoirs have {self.total_units} units together; at most {MAX_UNITS} "
                "are allowed"
            )
        if self.reset not in RESET_MODES:
            raise ConfigError(f"reset must be one of {RESET_MODES}, got {self.reset!r}")
        if self.exposed_units is not None:
            smallest = min(p.state_dim for p in self.reservoirs)
            if not (1 <= self.exposed_units <= smallest):
                raise ConfigError(
                    f"exposed_units must be in [1, {smallest}] (state size per reservoir), "
                    f"got {self.exposed_units}"
                )
        if not math.isfinite(self.reward_scale):
            raise ConfigError(f"reward_scale must be finite, got {self.reward_scale}")

    @property
    def n_reservoirs(self) -> int:
        return len(self.reservoirs)

    @property
    def family(self) -> str:
        """``"esn"`` or ``"rtu"``: the reservoirs' family."""
        return self.reservoirs[0].family

    @property
    def total_units(self) -> int:
        """Width of the concatenated states (an RTU's complex unit counts twice)."""
        return sum(p.state_dim for p in self.reservoirs)

    @property
    def exposed_total(self) -> int:
        if self.exposed_units is None:
            return self.total_units
        return self.exposed_units * self.n_reservoirs

    def with_reservoirs(self, reservoirs: tuple[EncoderParams, ...]) -> EncoderConfig:
        """Return a copy with other reservoir hyperparameters (same encoding options)."""
        return dataclasses.replace(self, reservoirs=tuple(reservoirs))


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
class NormalizeConfig:
    """Running normalization of observations and rewards (SB3's ``VecNormalize``).

    rl-baselines3-zoo's ``normalize`` key: ``true`` means these defaults, a mapping sets some of
    them. The wrapper is the outermost one, so with a reservoir it normalizes the reservoir
    states the policy sees; episode returns are still recorded raw. Reward normalization uses
    PPO's own ``gamma`` for its running discounted return, as the zoo does. Evaluation and
    replays use the statistics reached at the end of training, frozen, with raw rewards.

    Attributes:
        norm_obs: Normalize the policy's input by a running mean and variance.
        norm_reward: Divide rewards by the running standard deviation of the discounted return.
        clip_obs: Clip normalized observations to ``[-clip_obs, clip_obs]``.
        clip_reward: Clip normalized rewards to ``[-clip_reward, clip_reward]``.
        epsilon: Added to variances before the square root.
    """

    norm_obs: bool = True
    norm_reward: bool = True
    clip_obs: float = 10.0
    clip_reward: float = 10.0
    epsilon: float = 1e-8

    def __post_init__(self) -> None:
        for name in ("norm_obs", "norm_reward"):
            value = getattr(self, name)
            if not isinstance(value, bool):
                raise ConfigError(f"normalize: {name} must be true or false, got {value!r}")
        if not (self.norm_obs or self.norm_reward):
            raise ConfigError(
                "normalize: norm_obs and norm_reward are both false; use normalize: false instead"
            )
        for name in ("clip_obs", "clip_reward", "epsilon"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"normalize: {name} must be a number, got {value!r}")
            if not (value > 0 and math.isfinite(value)):
                raise ConfigError(f"normalize: {name} must be positive, got {value}")


@dataclass(frozen=True)
class PPOConfig:
    """An inner learner's settings (PPO's, or those of another learner of :mod:`ermrl.learners`).

    Attributes:
        n_envs: Environments stepped in lockstep by one agent (a ``DummyVecEnv``). PPO collects
            ``n_steps * n_envs`` transitions per update; more envs means fewer, larger updates
            for the same budget.
        hyperparams: Keyword arguments for ``PPO(...)`` on top of SB3's defaults, resolved from the
            packaged YAML table and command-line overrides (see :mod:`ermrl.agents`).
        torch_threads: ``torch.set_num_threads`` for each training process (1 is fastest for the
            small MLPs used here and avoids oversubscription when seeds run in parallel).
        device: Torch device; ermrl runs everything on the CPU by default.
        normalize: Wrap the environment in ``VecNormalize`` (rl-baselines3-zoo's ``normalize``
            key); ``None``: no normalization. Left out of :meth:`to_dict` while ``None``, so
            configs stored before it existed are unchanged.
        learner: The inner learner that takes these settings (a name of
            :data:`ermrl.learners.LEARNERS`; ``hyperparams`` are its algorithm's arguments).
            Left out of :meth:`to_dict` while ``"ppo"``, so configs stored before learners were
            plug-ins read as PPO, unchanged.
        backend: What trains the agents: ``"sb3"`` (one Stable-Baselines3 process per agent, the
            default) or ``"population"`` (:mod:`ermrl.population`: a whole generation's agents in
            lockstep, PPO only). Part of a study's stored configuration, so a study never mixes
            backends; left out of :meth:`to_dict` while ``"sb3"``.
    """

    n_envs: int = 1
    hyperparams: Mapping[str, Any] = field(default_factory=dict)
    torch_threads: int = 1
    device: str = "cpu"
    normalize: NormalizeConfig | None = field(default=None, metadata={"omit_if_default": True})
    learner: str = field(default="ppo", metadata={"omit_if_default": True})
    backend: str = field(default="sb3", metadata={"omit_if_default": True})

    def __post_init__(self) -> None:
        if not isinstance(self.learner, str) or not self.learner:
            raise ConfigError(f"learner must be a learner's name, got {self.learner!r}")
        if self.backend not in BACKENDS:
            raise ConfigError(f"unknown backend {self.backend!r}; choose one of {BACKENDS}")
        if self.backend == "population" and self.learner != "ppo":
            raise ConfigError(
                f"the population backend trains the ppo learner only, not {self.learner!r}; "
                "use --backend sb3"
            )
        if not 1 <= self.n_envs <= MAX_N_ENVS:
            raise ConfigError(f"n_envs must be in [1, {MAX_N_ENVS}], got {self.n_envs}")
        if self.torch_threads < 1:
            raise ConfigError(f"torch_threads must be >= 1, got {self.torch_threads}")


@dataclass(frozen=True)
class BudgetConfig:
    """How long one agent trains and how its return is measured.

    Attributes:
        training_steps: Environment steps per agent (summed over ``n_envs``).
        fitness: ``"last"``: mean return of the last ``n_last_episodes`` training episodes (the
            paper's measure); ``"eval"``: mean return of ``n_eval_episodes`` deterministic
            episodes on a separate environment after training.
        n_last_episodes: Training episodes averaged by the ``"last"`` measure.
        n_eval_episodes: Deterministic episodes run by the ``"eval"`` measure.
        n_reports: Intermediate returns reported to the pruner during training.
    """

    training_steps: int
    fitness: FitnessMode = "last"
    n_last_episodes: int = 10
    n_eval_episodes: int = 5
    n_reports: int = 4

    def __post_init__(self) -> None:
        _check_steps("training steps", self.training_steps)
        if self.fitness not in FITNESS_MODES:
            raise ConfigError(f"fitness must be one of {FITNESS_MODES}, got {self.fitness!r}")
        for name in ("n_last_episodes", "n_eval_episodes"):
            value = getattr(self, name)
            if not 1 <= value <= MAX_EPISODES:
                raise ConfigError(f"{name} must be in [1, {MAX_EPISODES}], got {value}")
        if self.n_reports < 0:
            raise ConfigError(f"n_reports must be >= 0, got {self.n_reports}")


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
    """What the outer loop needs of an encoder's search space (:class:`ReservoirSpace` is one).

    The search samples plain ``{name: value}`` points in :meth:`ranges`; the encoder turns a
    point into its settings (:meth:`ermrl.encoders.Encoder.decode`), so search code never
    handles an encoder's own types.
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


class _PerReservoirSpace:
    """What the search spaces share: each reservoir has the same evolved parameters, named
    ``name`` with one reservoir and ``name_0``, ``name_1``, ... with several."""

    n_reservoirs: int

    def _per_reservoir(self) -> dict[str, Range]:
        """One reservoir's evolved parameters and their ranges, in order."""
        raise NotImplementedError

    def _reference_values(self) -> dict[str, float]:
        """One unevolved reference reservoir's evolved parameters."""
        raise NotImplementedError

    @property
    def evolved(self) -> tuple[str, ...]:
        """Names of the evolved hyperparameters of one reservoir."""
        return tuple(self._per_reservoir())

    def param_name(self, name: str, index: int) -> str:
        return name if self.n_reservoirs == 1 else f"{name}_{index}"

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(self.param_name(n, k) for k in range(self.n_reservoirs) for n in self.evolved)

    def ranges(self) -> dict[str, Range]:
        """Search ranges keyed by Optuna parameter name, in a fixed order."""
        per = self._per_reservoir()
        return {self.param_name(n, k): r for k in range(self.n_reservoirs) for n, r in per.items()}

    def _values(self, params: Mapping[str, float], k: int) -> dict[str, float]:
        """Reservoir ``k``'s evolved values in a trial's parameters.

        Raises:
            ConfigError: a parameter of this space is missing.
        """
        try:
            return {n: float(params[self.param_name(n, k)]) for n in self.evolved}
        except KeyError as err:
            raise ConfigError(f"parameter {err.args[0]!r} missing from {dict(params)}") from err

    def reference_params(self) -> dict[str, float]:
        """The unevolved reference reservoirs (``default_reservoirs()``) as trial parameters."""
        one = self._reference_values()
        return {self.param_name(n, k): one[n] for k in range(self.n_reservoirs) for n in one}

    def contains(self, params: Mapping[str, float]) -> bool:
        """Whether ``params`` name exactly this space's parameters, each within its range."""
        return _box_contains(self.ranges(), params)

    def center_params(self) -> dict[str, float]:
        """The centre of the box (geometric mean of the bounds on a log scale): the paper's start."""
        return _box_center(self.ranges())


@dataclass(frozen=True)
class ReservoirSpace(_PerReservoirSpace):
    """The evolved search space of echo state networks: data, not code. Defaults follow the
    ER-MRL paper.

    Every range is log-scale. The space has a fixed dimension so that CMA-ES never falls back to
    independent sampling. With one reservoir the parameters are named ``sr``, ``lr`` and
    ``input_scaling``; with several, ``sr_0``, ``lr_0``, ``input_scaling_0``, ``sr_1``, ...

    Attributes:
        n_reservoirs: Reservoirs per agent, each with its own hyperparameters and weights.
        units: Fixed number of units per reservoir.
        sr: Spectral-radius range.
        lr: Leak-rate range (within (0, 1]).
        input_scaling: Input-scaling range, or ``None`` to fix it at ``fixed_input_scaling``.
        fixed_input_scaling: The value used when ``input_scaling`` is ``None``.
        rc_connectivity: Fixed recurrent connectivity.
        input_connectivity: Fixed input connectivity.
        bias_scaling: Fixed bias scaling.
        bias_init: Fixed bias initialization (:attr:`ReservoirParams.bias_init`).
    """

    n_reservoirs: int = 1
    units: int = 100
    sr: Range = Range(1e-4, 1e2)
    lr: Range = Range(1e-2, 1.0)
    input_scaling: Range | None = Range(1e-1, 10.0)
    fixed_input_scaling: float = 1.0
    rc_connectivity: float = 0.1
    input_connectivity: float = 0.1
    bias_scaling: float = 0.0
    bias_init: BiasInit = field(default="none", metadata={"omit_if_default": True})

    family: ClassVar[str] = "esn"

    def __post_init__(self) -> None:
        if self.n_reservoirs < 1:
            raise ConfigError(f"n_reservoirs must be >= 1, got {self.n_reservoirs}")
        _check_units(self.units)
        if self.n_reservoirs * self.units > MAX_UNITS:
            raise ConfigError(
                f"{self.n_reservoirs} reservoirs of {self.units} units: at most {MAX_UNITS} "
                "units are allowed in all"
            )
        if self.lr.high > 1:
            raise ConfigError(f"the leak-rate range must stay within (0, 1], got {self.lr.high}")
        # Fail early on a bad fixed value.
        ReservoirParams(
            units=self.units,
            input_scaling=self.fixed_input_scaling,
            rc_connectivity=self.rc_connectivity,
            input_connectivity=self.input_connectivity,
            bias_scaling=self.bias_scaling,
            bias_init=self.bias_init,
        )

    def _per_reservoir(self) -> dict[str, Range]:
        per: dict[str, Range] = {"sr": self.sr, "lr": self.lr}
        if self.input_scaling is not None:
            per["input_scaling"] = self.input_scaling
        return per

    def _reference_values(self) -> dict[str, float]:
        one = self.default_reservoirs()[0]
        return {name: float(getattr(one, name)) for name in self.evolved}

    def _reservoir(self, values: Mapping[str, float]) -> ReservoirParams:
        return ReservoirParams(
            units=self.units,
            sr=values["sr"],
            lr=values["lr"],
            input_scaling=values.get("input_scaling", self.fixed_input_scaling),
            rc_connectivity=self.rc_connectivity,
            input_connectivity=self.input_connectivity,
            bias_scaling=self.bias_scaling,
            bias_init=self.bias_init,
        )

    def reservoirs_from(self, params: Mapping[str, float]) -> tuple[ReservoirParams, ...]:
        """Build the reservoirs described by a trial's parameters.

        Raises:
            ConfigError: a parameter of this space is missing.
        """
        return tuple(self._reservoir(self._values(params, k)) for k in range(self.n_reservoirs))

    def default_reservoirs(self) -> tuple[ReservoirParams, ...]:
        """Unevolved reservoirs (reservoirpy defaults for sr, lr and input scaling)."""
        one = ReservoirParams(
            units=self.units,
            input_scaling=self.fixed_input_scaling if self.input_scaling is None else 1.0,
            rc_connectivity=self.rc_connectivity,
            input_connectivity=self.input_connectivity,
            bias_scaling=self.bias_scaling,
            bias_init=self.bias_init,
        )
        return (one,) * self.n_reservoirs


@dataclass(frozen=True)
class RTUSpace(_PerReservoirSpace):
    """The evolved search space of frozen recurrent trace units (``--encoder rtu``).

    Evolution shapes the ranges the units' parameters are drawn from, as it shapes an ESN's
    spectral radius: the upper decay rate ``r_max`` (linear scale), the lower one as a fraction
    of it, ``r_min_ratio`` (linear; ``r_min = r_min_ratio * r_max`` keeps the range ordered in a
    box), the largest rotation frequency ``theta_max`` (log scale) and the input scaling (log
    scale). The reference is the paper's initialization: ``r in (0, 1)``, ``theta in (0, 2 pi)``,
    input scaling 1.

    Attributes:
        n_reservoirs: RTU layers per agent, each with its own ranges and weights.
        units: Complex units per layer (the policy sees ``2 * units`` values per layer).
        r_max: Range of ``r_max``, within (0, 1].
        r_min_ratio: Range of ``r_min / r_max``, within [0, 1].
        theta_max: Range of ``theta_max``.
        input_scaling: Input-scaling range, or ``None`` to fix it at ``fixed_input_scaling``.
        fixed_input_scaling: The value used when ``input_scaling`` is ``None``.
        family: Always ``"rtu"`` (stored, so that a study's space reads back as this class).
    """

    n_reservoirs: int = 1
    units: int = 50
    r_max: Range = Range(0.05, 1.0, log=False)
    r_min_ratio: Range = Range(0.0, 1.0, log=False)
    theta_max: Range = Range(1e-2, 2 * math.pi)
    input_scaling: Range | None = Range(1e-1, 10.0)
    fixed_input_scaling: float = 1.0
    family: Literal["rtu"] = "rtu"

    def __post_init__(self) -> None:
        if self.family != "rtu":
            raise ConfigError(f"RTUSpace family must be 'rtu', got {self.family!r}")
        if self.n_reservoirs < 1:
            raise ConfigError(f"n_reservoirs must be >= 1, got {self.n_reservoirs}")
        if self.n_reservoirs * 2 * self.units > MAX_UNITS:
            raise ConfigError(
                f"{self.n_reservoirs} RTU layers of {self.units} complex units: at most "
                f"{MAX_UNITS} state values are allowed in all"
            )
        if not (0 < self.r_max.low and self.r_max.high <= 1):
            raise ConfigError(f"the r_max range must stay within (0, 1], got {self.r_max}")
        if not (0 <= self.r_min_ratio.low and self.r_min_ratio.high <= 1):
            raise ConfigError(
                f"the r_min_ratio range must stay within [0, 1], got {self.r_min_ratio}"
            )
        RTUParams(units=self.units, input_scaling=self.fixed_input_scaling)

    def _per_reservoir(self) -> dict[str, Range]:
        per = {"r_max": self.r_max, "r_min_ratio": self.r_min_ratio, "theta_max": self.theta_max}
        if self.input_scaling is not None:
            per["input_scaling"] = self.input_scaling
        return per

    def _reference_values(self) -> dict[str, float]:
        one = self.default_reservoirs()[0]
        ref = {"r_max": one.r_max, "r_min_ratio": one.r_min / one.r_max}
        ref["theta_max"] = one.theta_max
        if self.input_scaling is not None:
            ref["input_scaling"] = one.input_scaling
        return ref

    def _reservoir(self, values: Mapping[str, float]) -> RTUParams:
        return RTUParams(
            units=self.units,
            r_min=values["r_min_ratio"] * values["r_max"],
            r_max=values["r_max"],
            theta_max=values["theta_max"],
            input_scaling=values.get("input_scaling", self.fixed_input_scaling),
        )

    def reservoirs_from(self, params: Mapping[str, float]) -> tuple[RTUParams, ...]:
        """Build the RTU layers described by a trial's parameters.

        Raises:
            ConfigError: a parameter of this space is missing.
        """
        return tuple(self._reservoir(self._values(params, k)) for k in range(self.n_reservoirs))

    def default_reservoirs(self) -> tuple[RTUParams, ...]:
        """Unevolved RTU layers: the paper's initialization ranges, input scaling 1."""
        one = RTUParams(
            units=self.units,
            input_scaling=self.fixed_input_scaling if self.input_scaling is None else 1.0,
        )
        return (one,) * self.n_reservoirs


EncoderSpace = ReservoirSpace | RTUSpace


@dataclass(frozen=True)
class LearnerSpace:
    """The evolved genes of an inner learner (``evolve --learner hebbian``): data, not code.

    Evolution then shapes the learner itself, plasticity included, and the agent sees the raw
    (masked) observation: the study has no encoder. Each gene is a named :class:`Range`; the
    learner turns a point into settings (:meth:`ermrl.learners.Learner.decode_genes`), so search
    code never handles a learner's own settings. The space has a fixed dimension, so that CMA-ES
    works; a categorical choice (the Hebbian learner's baseline) is fixed per study through the
    learner's settings (``--ppo baseline=critic``).

    Attributes:
        learner: The learner whose genes these are (a name of :data:`ermrl.learners.LEARNERS`).
        genes: Gene name -> search range, in order.
        reference: The unevolved genes: the study's own learner settings (the learner's table
            for the task and ``--ppo``) as gene values, what ``random-<learner>`` trains with.
            Its trial (``--reference-trial``) is clipped into the box.
    """

    learner: str
    genes: Mapping[str, Range]
    reference: Mapping[str, float]

    n_reservoirs: ClassVar[int] = 0

    def __post_init__(self) -> None:
        if not self.genes:
            raise ConfigError(f"learner {self.learner!r} has no genes to evolve")
        if set(self.reference) != set(self.genes):
            raise ConfigError(
                f"the reference genes {sorted(self.reference)} must be the genes "
                f"{sorted(self.genes)}"
            )
        for name, value in self.reference.items():
            if not math.isfinite(value):
                raise ConfigError(f"reference gene {name} must be finite, got {value}")

    @property
    def family(self) -> str:
        """What the study evolves: the learner's name (the test phase's agents follow it)."""
        return self.learner

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(self.genes)

    def ranges(self) -> dict[str, Range]:
        return dict(self.genes)

    def reference_params(self) -> dict[str, float]:
        """The reference genes clipped into the box (a gene whose default lies outside a
        log-scale range, as an l2 of 0, takes the nearest bound)."""
        return {
            name: min(max(float(self.reference[name]), r.low), r.high)
            for name, r in self.genes.items()
        }

    def center_params(self) -> dict[str, float]:
        return _box_center(self.genes)

    def contains(self, params: Mapping[str, float]) -> bool:
        return _box_contains(self.genes, params)

    def values(self, params: Mapping[str, float]) -> dict[str, float]:
        """A trial's gene values, in gene order.

        Raises:
            ConfigError: a gene is missing.
        """
        try:
            return {name: float(params[name]) for name in self.genes}
        except KeyError as err:
            raise ConfigError(f"gene {err.args[0]!r} missing from {dict(params)}") from err


SearchSpaceConfig = EncoderSpace | LearnerSpace


@dataclass(frozen=True)
class SearchConfig:
    """The outer loop: how candidates are proposed.

    Attributes:
        sampler: ``cmaes`` (default), ``tpe`` or ``random``.
        sampler_seed: Seed of the sampler (``None``: nondeterministic).
        restart: CMA-ES restart strategy: ``none``, ``ipop`` or ``bipop``.
        popsize: CMA-ES population size (``None``: CMA-ES's default, 4 + 3 ln(dim)).
        pruner: ``none``, ``median`` or ``halving``; prunes on intermediate training returns.
        n_trials: Total trials of the study, all workers together.
        start: Where CMA-ES starts: ``center`` (the centre of the log-scaled box, as the
            ER-MRL paper's code did; the default, which did at least as well as ``reference``
            in the science benchmark once the reference competes as a trial) or ``reference``
            (the unevolved reference reservoir, reservoirpy's defaults sr = lr = input_scaling
            = 1, clipped into the box; better for a handful of trials).
        reference_trial: Queue the unevolved reference reservoir as the study's first trial, so
            that it competes with the evolved candidates (and is told to CMA-ES like them).
        reevaluate_top: After the budget, re-train the ``reevaluate_top`` best trials (and the
            reference trial) on fresh seeds; the test phase then uses that ranking. 0: off.
        reevaluate_seeds: Seeds per re-evaluated candidate.
        reevaluate_steps: Training steps of a re-evaluation run (``None``: the evolution
            budget; the test budget removes the budget mismatch at a higher cost).
    """

    sampler: str = "cmaes"
    sampler_seed: int | None = None
    restart: str = "none"
    popsize: int | None = None
    pruner: PrunerName = "none"
    n_trials: int = 100
    start: StartName = "center"
    reference_trial: bool = True
    reevaluate_top: int = 0
    reevaluate_seeds: int = 3
    reevaluate_steps: int | None = None

    def __post_init__(self) -> None:
        if self.sampler not in ("cmaes", "tpe", "random"):
            raise ConfigError(f"unknown sampler {self.sampler!r}; choose cmaes, tpe or random")
        if self.restart not in ("none", "ipop", "bipop"):
            raise ConfigError(f"unknown restart strategy {self.restart!r}")
        if self.restart != "none" and self.sampler != "cmaes":
            raise ConfigError("--restart applies to the cmaes sampler only")
        if self.popsize is not None and self.popsize < 2:
            raise ConfigError(f"popsize must be >= 2, got {self.popsize}")
        if self.pruner not in PRUNERS:
            raise ConfigError(f"unknown pruner {self.pruner!r}; choose one of {PRUNERS}")
        if not 1 <= self.n_trials <= MAX_TRIALS:
            raise ConfigError(f"n_trials must be in [1, {MAX_TRIALS}], got {self.n_trials}")
        if self.start not in STARTS:
            raise ConfigError(f"unknown CMA-ES start {self.start!r}; choose one of {STARTS}")
        if self.reevaluate_top < 0:
            raise ConfigError(f"reevaluate_top must be >= 0, got {self.reevaluate_top}")
        if not 1 <= self.reevaluate_seeds <= MAX_SEEDS:
            raise ConfigError(
                f"reevaluate_seeds must be in [1, {MAX_SEEDS}], got {self.reevaluate_seeds}"
            )
        if self.reevaluate_steps is not None:
            _check_steps("reevaluate_steps", self.reevaluate_steps)


@dataclass(frozen=True)
class Problem:
    """How the fitness of a reservoir is computed (independent of how candidates are proposed).

    Attributes:
        task: The environment.
        encoder: Encoding options; its ``reservoirs`` are replaced by each candidate's.
            ``None``: no encoder (a study of a learner's genes, :class:`LearnerSpace`).
        ppo: Agent settings.
        budget: Training budget and fitness measure.
        seeds: Training seeds; fitness is the mean over them.
    """

    task: TaskConfig
    encoder: EncoderConfig | None
    ppo: PPOConfig
    budget: BudgetConfig
    seeds: tuple[int, ...] = (0, 1, 2)

    def __post_init__(self) -> None:
        if not self.seeds:
            raise ConfigError("at least one seed is needed")
        if len(self.seeds) > MAX_SEEDS:
            raise ConfigError(f"at most {MAX_SEEDS} seeds are allowed, got {len(self.seeds)}")
        if len(set(self.seeds)) != len(self.seeds):
            raise ConfigError(f"seeds must be distinct, got {self.seeds}")


@dataclass(frozen=True)
class GeneralizationTask:
    """One task of a multi-task (generalization) problem, with its normalization references.

    Attributes:
        task: The environment and observation mask.
        ppo: PPO settings resolved for this env (SB3 defaults for MuJoCo).
        random_return: R_random, the mean episodic return of a uniformly random policy.
        target_return: R_target, the documented reference return that normalizes to 1.
    """

    task: TaskConfig
    ppo: PPOConfig
    random_return: float
    target_return: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.random_return) and math.isfinite(self.target_return)):
            raise ConfigError(f"{self.task.env_id}: reference returns must be finite")
        if self.target_return == self.random_return:
            raise ConfigError(
                f"{self.task.env_id}: the target return equals the random return "
                f"({self.target_return:g}), so the normalized return is undefined"
            )

    def normalize(self, value: float) -> float:
        """``(value - random_return) / (target_return - random_return)``: 0 random, 1 target."""
        return (value - self.random_return) / (self.target_return - self.random_return)


@dataclass(frozen=True)
class GeneralizationConfig:
    """The task set of ``evolve-generalization``.

    A candidate's fitness is the mean over tasks of the normalized return
    ``(R - R_random) / (R_target - R_random)``, where each task's ``R`` is the mean over the
    problem's seeds. Every task uses the same reservoirs: the same hyperparameters and, for a
    given seed, the same recurrent weights ``W`` and bias; only the input matrix ``Win`` is drawn
    per task (its shape depends on the task's observation and action sizes).

    Attributes:
        tasks: The tasks, in order.
        suite: Name of the suite they come from (``None`` for an explicit list of ids).
        scores: The reference table the returns were read from (``packaged`` or a path).
        target_column: The table column used as R_target (``target`` or ``provisional_target``).
        ppo_overrides: ``--ppo`` overrides applied on top of each env's table entry (also applied
            to the env of a generalization test).
        n_envs: Explicit ``--n-envs`` (``None``: each env's table value).
        hyperparams: The PPO table used (``None``: the packaged one).
    """

    tasks: tuple[GeneralizationTask, ...]
    suite: str | None = None
    scores: str = "packaged"
    target_column: str = "target"
    ppo_overrides: Mapping[str, Any] = field(default_factory=dict)
    n_envs: int | None = None
    hyperparams: str | None = None

    def __post_init__(self) -> None:
        if not self.tasks:
            raise ConfigError("a generalization problem needs at least one task")
        ids = self.env_ids
        if len(set(ids)) != len(ids):
            raise ConfigError(f"each task may appear once, got {', '.join(ids)}")

    @property
    def env_ids(self) -> tuple[str, ...]:
        return tuple(t.task.env_id for t in self.tasks)


@dataclass(frozen=True)
class EvolveConfig:
    """Everything an evolution run needs; stored in the study so that it can be resumed or tested.

    Attributes:
        problem: How fitness is computed.
        space: What is searched: an encoder's space, or a learner's genes
            (:class:`LearnerSpace`, with no encoder).
        search: How it is searched.
        n_procs: Processes that train a trial's seeds in parallel.
        generalization: The task set of a multi-task run (``evolve-generalization``); then
            ``problem`` holds the shared encoder, budget and seeds, and its ``task``/``ppo``
            are the first task's. ``None`` (single task) is left out of :meth:`to_dict`.
    """

    problem: Problem
    space: SearchSpaceConfig
    search: SearchConfig
    n_procs: int = 1
    generalization: GeneralizationConfig | None = field(
        default=None, metadata={"omit_if_default": True}
    )

    def __post_init__(self) -> None:
        if self.n_procs < 1:
            raise ConfigError(f"n_procs must be >= 1, got {self.n_procs}")
        if self.search.pruner != "none" and self.n_procs > 1:
            raise ConfigError(
                "pruning reads intermediate returns while a trial's seeds train one after "
                "another: use --n-procs 1 with --pruner (or run more workers instead)"
            )
        if self.search.pruner != "none" and self.problem.ppo.backend == "population":
            raise ConfigError(
                "the population backend trains a whole generation at once and reports no "
                "intermediate returns: use --pruner none with --backend population"
            )
        encoder = self.problem.encoder
        if isinstance(self.space, LearnerSpace):
            if encoder is not None:
                raise ConfigError(
                    f"a study of the {self.space.learner} learner's genes has no encoder "
                    "(the learner's own network is the evolved one)"
                )
            if self.space.learner != self.problem.ppo.learner:
                raise ConfigError(
                    f"the genes of learner {self.space.learner!r} cannot evolve learner "
                    f"{self.problem.ppo.learner!r}"
                )
            if self.generalization is not None:
                raise ConfigError(
                    "evolve-generalization evolves encoders only; evolve a learner's genes "
                    "with evolve"
                )
        elif encoder is None:
            raise ConfigError("an encoder's search space needs the problem's encoder")
        elif self.space.n_reservoirs != encoder.n_reservoirs:
            raise ConfigError("the encoder and the search space disagree on n_reservoirs")
        elif self.space.family != encoder.family:
            raise ConfigError("the encoder and the search space are of different families")
        if self.generalization is not None and self.problem.task not in (
            t.task for t in self.generalization.tasks
        ):
            raise ConfigError("the problem's task must be one of the generalization tasks")

    @property
    def default_study_name(self) -> str:
        task = self.problem.task
        parts = [task.env_id, task.observe, f"{self.problem.budget.training_steps}steps"]
        if self.space.family != "esn":
            parts.append(self.space.family)
        if self.space.n_reservoirs > 1:
            parts.append(f"{self.space.n_reservoirs}res")
        return "__".join(parts)

    def to_dict(self) -> dict[str, Any]:
        return to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> EvolveConfig:
        return from_dict(cls, data)


# --------------------------------------------------------------------------------------------
# (De)serialization of the nested dataclasses to plain JSON/YAML-friendly dicts.

_T = TypeVar("_T")


def to_dict(obj: Any) -> Any:
    """Convert nested frozen dataclasses (and tuples, mappings) to JSON-friendly values."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {
            f.name: to_dict(getattr(obj, f.name))
            for f in dataclasses.fields(obj)
            # Optional additions keep older configs' dicts unchanged while unset.
            if not (f.metadata.get("omit_if_default") and getattr(obj, f.name) == f.default)
        }
    if isinstance(obj, Mapping):
        return {str(k): to_dict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    return obj


def from_dict(cls: type[_T], data: Mapping[str, Any]) -> _T:
    """Inverse of :func:`to_dict` for the dataclasses of this module."""
    hints = {
        (EvolveConfig, "problem"): Problem,
        (EvolveConfig, "space"): ReservoirSpace,
        (EvolveConfig, "search"): SearchConfig,
        (Problem, "task"): TaskConfig,
        (Problem, "encoder"): EncoderConfig,
        (Problem, "ppo"): PPOConfig,
        (Problem, "budget"): BudgetConfig,
        (ReservoirSpace, "sr"): Range,
        (ReservoirSpace, "lr"): Range,
        (ReservoirSpace, "input_scaling"): Range,
        (RTUSpace, "r_max"): Range,
        (RTUSpace, "r_min_ratio"): Range,
        (RTUSpace, "theta_max"): Range,
        (RTUSpace, "input_scaling"): Range,
        (EvolveConfig, "generalization"): GeneralizationConfig,
        (GeneralizationTask, "task"): TaskConfig,
        (GeneralizationTask, "ppo"): PPOConfig,
        (PPOConfig, "normalize"): NormalizeConfig,
    }
    kwargs: dict[str, Any] = {}
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    if cls is SearchConfig:
        # Studies stored before these options existed started at the box centre, without the
        # reference trial: read them as what they were.
        data = {"start": "center", "reference_trial": False, **data}
    for key, value in data.items():
        if key not in names:
            continue  # tolerate fields added by newer versions
        sub = hints.get((cls, key))
        if sub is ReservoirSpace and isinstance(value, Mapping) and value.get("family") == "rtu":
            sub = RTUSpace
        if sub is ReservoirSpace and isinstance(value, Mapping) and "learner" in value:
            sub = LearnerSpace
        if cls is LearnerSpace and key == "genes":
            value = {str(k): from_dict(Range, v) for k, v in value.items()}
        elif cls is LearnerSpace and key == "reference":
            value = {str(k): float(v) for k, v in value.items()}
        elif sub is not None and value is not None:
            value = from_dict(sub, value)
        elif cls is EncoderConfig and key == "reservoirs":
            value = tuple(
                from_dict(RTUParams if v.get("family") == "rtu" else ReservoirParams, v)
                for v in value
            )
        elif cls is Problem and key == "seeds":
            value = tuple(int(v) for v in value)
        elif cls is PPOConfig and key == "hyperparams":
            value = dict(value)
        elif cls is GeneralizationConfig and key == "tasks":
            value = tuple(from_dict(GeneralizationTask, v) for v in value)
        elif cls is GeneralizationConfig and key == "ppo_overrides":
            value = dict(value)
        kwargs[key] = value
    return cls(**kwargs)
