"""``reservoir``: echo state networks built with reservoirpy, frozen, wrapping the env.

The reference encoder, in one module: its search space
([`ReservoirSpace`][ermrl.encoders.ReservoirSpace]: spectral radius, leak rate and input scaling per
reservoir, log scale; or, for multi-timescale reservoirs (``--multiscale``), a band of leak rates in
place of the one leak rate), its ``ermrl evolve`` settings (`ReservoirSettings`), its test-phase agents
(`AGENTS`) and the encoder itself ([`ReservoirEncoder`][ermrl.encoders.ReservoirEncoder]). One
reservoir's settings ([`ReservoirParams`][ermrl.encoders.ReservoirParams], reservoirpy's defaults:
the unevolved reference) live with the weights they build, in `ermrl.encoders._reservoir`, below the
env wrapper ([`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv]) that steps them.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Hashable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from ermrl._config_base import MAX_UNITS, AgentKind, ConfigError, Range, _check_units
from ermrl._schema import option
from ermrl.encoders._base import Encoder
from ermrl.encoders._reservoir import (
    Ablation,
    BiasInit,
    ReservoirBank,
    ReservoirParams,
    encoder_weights,
    reservoir_seeds,
)
from ermrl.encoders._settings import EncoderConfig, PerReservoirSpace

__all__ = [
    "AGENTS", "ReservoirEncoder", "ReservoirParams", "ReservoirSettings", "ReservoirSpace",
]  # fmt: skip


@dataclass(frozen=True)
class ReservoirSpace(PerReservoirSpace):
    """The evolved search space of echo state networks: data, not code. Defaults follow the
    ER-MRL paper.

    Every range is log-scale. The space has a fixed dimension so that CMA-ES never falls back to
    independent sampling. With one reservoir the parameters are named ``sr``, ``lr`` and
    ``input_scaling``; with several, ``sr_0``, ``lr_0``, ``input_scaling_0``, ``sr_1``, ...

    With ``multiscale``, each reservoir is a multi-timescale one
    (`lr_max`: its units' leak rates spaced log-uniformly
    from ``lr_min`` to ``lr_max``) and the genes ``lr_max`` and ``lr_min_ratio`` replace ``lr``:
    ``lr_min = lr_min_ratio * lr_max``, which keeps ``lr_min <= lr_max`` everywhere in the box
    that CMA-ES needs (with the default ranges ``lr_min`` reaches down to 1e-6). The genes are
    then ``sr``, ``lr_max``, ``lr_min_ratio`` and ``input_scaling`` (when evolved). The
    reference is still reservoirpy's defaults: ``lr_max = lr_min_ratio = 1``, every unit at
    leak rate 1, the plain echo state network.

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
        bias_init: Fixed bias initialization (`ReservoirParams.bias_init`).
        multiscale: Evolve multi-timescale reservoirs (genes ``lr_max`` and ``lr_min_ratio``
            in place of ``lr``, whose range is then unused). Left out of stored spaces while
            off, as are the two ranges below at their defaults.
        lr_max: Range of the largest leak rate (within (0, 1]), with ``multiscale``.
        lr_min_ratio: Range of ``lr_min / lr_max`` (within (0, 1]), with ``multiscale``.
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
    multiscale: bool = field(default=False, metadata={"omit_if_default": True})
    lr_max: Range = field(default=Range(1e-3, 1.0), metadata={"omit_if_default": True})
    lr_min_ratio: Range = field(default=Range(1e-3, 1.0), metadata={"omit_if_default": True})

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
        for name in ("lr_max", "lr_min_ratio"):
            band: Range = getattr(self, name)
            if not (0 < band.low and band.high <= 1):
                raise ConfigError(
                    f"the {name} range must stay within (0, 1], got [{band.low}, {band.high}]"
                )
        # Fail early on a bad fixed value.
        ReservoirParams(
            units=self.units,
            input_scaling=self.fixed_input_scaling,
            rc_connectivity=self.rc_connectivity,
            input_connectivity=self.input_connectivity,
            bias_scaling=self.bias_scaling,
            bias_init=self.bias_init,
        )

    @property
    def study_tag(self) -> str:
        """What a study's default name adds for this space: ``"multiscale"``, or nothing."""
        return "multiscale" if self.multiscale else ""

    def _per_reservoir(self) -> dict[str, Range]:
        per: dict[str, Range] = {"sr": self.sr}
        if self.multiscale:
            per |= {"lr_max": self.lr_max, "lr_min_ratio": self.lr_min_ratio}
        else:
            per["lr"] = self.lr
        if self.input_scaling is not None:
            per["input_scaling"] = self.input_scaling
        return per

    def _reference_values(self) -> dict[str, float]:
        one = self.default_reservoirs()[0]
        lr_max = one.lr if one.lr_max is None else one.lr_max
        values = {"sr": one.sr, "lr": one.lr, "input_scaling": one.input_scaling}
        values |= {"lr_max": lr_max, "lr_min_ratio": one.lr / lr_max}
        return {name: float(values[name]) for name in self.evolved}

    def _reservoir(self, values: Mapping[str, float]) -> ReservoirParams:
        if self.multiscale:  # lr_min = lr_min_ratio * lr_max <= lr_max, the ratio being <= 1
            lr, lr_max = values["lr_min_ratio"] * values["lr_max"], values["lr_max"]
        else:
            lr, lr_max = values["lr"], None
        return ReservoirParams(
            units=self.units,
            sr=values["sr"],
            lr=lr,
            input_scaling=values.get("input_scaling", self.fixed_input_scaling),
            rc_connectivity=self.rc_connectivity,
            input_connectivity=self.input_connectivity,
            bias_scaling=self.bias_scaling,
            bias_init=self.bias_init,
            lr_max=lr_max,
        )

    def reservoirs_from(self, params: Mapping[str, float]) -> tuple[ReservoirParams, ...]:
        """Build the reservoirs described by a trial's parameters.

        Raises:
            ConfigError: a parameter of this space is missing.
        """
        return tuple(self._reservoir(self._values(params, k)) for k in range(self.n_reservoirs))

    def default_reservoirs(self) -> tuple[ReservoirParams, ...]:
        """Unevolved reservoirs (reservoirpy defaults for sr, lr and input scaling; with
        ``multiscale``, ``lr = lr_max = 1``: the same plain echo state network)."""
        one = ReservoirParams(
            units=self.units,
            input_scaling=self.fixed_input_scaling if self.input_scaling is None else 1.0,
            rc_connectivity=self.rc_connectivity,
            input_connectivity=self.input_connectivity,
            bias_scaling=self.bias_scaling,
            bias_init=self.bias_init,
            lr_max=1.0 if self.multiscale else None,
        )
        return (one,) * self.n_reservoirs


_PAIR = ("LOW", "HIGH")


@dataclass(frozen=True)
class ReservoirSettings:
    """The ``ermrl evolve`` settings of ``--encoder reservoir`` (`ermrl._schema` fields): each
    sets the [`ReservoirSpace`][ermrl.encoders.ReservoirSpace] field of its name, a
    ``<name>_range`` the range ``<name>``, on its default's scale."""

    units: int | None = option(
        None, "--encoder reservoir: units per reservoir, fixed (default 100)", low=1
    )
    sr_range: tuple[float, float] = option(
        (1e-4, 1e2), "spectral radius range (log scale)", metavar=_PAIR, above=0
    )
    lr_range: tuple[float, float] = option(
        (1e-2, 1.0), "leak rate range (log scale, within (0, 1]; not with --multiscale)",
        metavar=_PAIR, above=0,
    )  # fmt: skip
    multiscale: bool = option(
        False, "--encoder reservoir: multi-timescale reservoirs: each unit its own leak rate, "
        "spaced log-uniformly from lr_min (the first unit) to lr_max (the last); evolves "
        "lr_max and lr_min_ratio = lr_min / lr_max in place of lr (reference: both 1, the "
        "plain echo state network)",
    )  # fmt: skip
    lr_max_range: tuple[float, float] = option(
        (1e-3, 1.0), "--multiscale: range of the largest leak rate (log scale, within (0, 1])",
        metavar=_PAIR, above=0,
    )  # fmt: skip
    lr_min_ratio_range: tuple[float, float] = option(
        (1e-3, 1.0), "--multiscale: range of lr_min / lr_max (log scale, within (0, 1])",
        metavar=_PAIR, above=0,
    )  # fmt: skip
    rc_connectivity: float = option(0.1, "recurrent connectivity", above=0)
    input_connectivity: float = option(0.1, "input connectivity", above=0)
    bias_scaling: float = option(
        0.0, "dense Bernoulli bias: every unit +-scale (0: no bias, reservoirpy 0.4's default)"
    )
    bias_init: BiasInit = option(
        "none", "'original': reservoirpy 0.3's default bias, which the ER-MRL code had: +-1 on "
        "--input-connectivity of the units (10%%), zero elsewhere (needs --bias-scaling 0); "
        "'none': the bias of --bias-scaling",
    )  # fmt: skip


def _ablated(ablation: Ablation) -> functools.partial[ReservoirParams]:
    """An agent's `derive`: a reservoir's settings with
    ``ablation`` (`ReservoirParams.ablation`), all else kept."""
    return functools.partial(dataclasses.replace, ablation=ablation)


# Test-phase agents of ``--encoder reservoir`` studies.
AGENTS: dict[str, AgentKind] = {
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
    "leaky-res-ppo": AgentKind(
        "evolved", None,
        "the study's learner on the selected reservoir(s) without recurrent weights (W = 0; the "
        "same input weights, bias and leak rate(s)): a leaky integrator of a random projection",
        None, "RES-PPO (evolved, W = 0)", "RES-PPO\n(W = 0)", "goldenrod", default=False,
        family="esn", derive=_ablated("leaky"),
    ),
    "ema-ppo": AgentKind(
        "evolved", None,
        "the study's learner on the reservoir's input (observation, previous action and "
        "reward) next to its exponential moving averages at the selected leak rate(s), in the "
        "reservoir's place: no projection, no tanh",
        None, "EMA-PPO (selected leak rate)", "EMA-PPO", "dimgray", default=False,
        family="esn", derive=_ablated("ema"),
    ),
    "res-sac": AgentKind(
        "evolved", None, "SAC on the selected evolved reservoir(s) (its replay holds their states)",
        "sac", "RES-SAC (evolved reservoir)", "RES-SAC\n(evolved)", "teal", default=False,
        family="esn",
    ),
    "res-dagger": AgentKind(
        "evolved", None,
        "DAgger on the selected evolved reservoir(s)' states; its expert sees the full state",
        "dagger", "RES-DAgger (evolved reservoir)", "RES-DAgger\n(evolved)", "magenta",
        default=False, family="esn",
    ),
    "res-imitation-sac": AgentKind(
        "evolved", None,
        "imitation-seeded SAC on the selected evolved reservoir(s)' states; its expert sees the "
        "full state",
        "imitation-sac", "RES-Imitation-SAC (evolved reservoir)", "RES-Imit.-SAC\n(evolved)",
        "slateblue", default=False, family="esn",
    ),
}  # fmt: skip


class ReservoirEncoder(Encoder):
    """Echo state networks: [`ReservoirSpace`][ermrl.encoders.ReservoirSpace] decoded into
    [`ReservoirParams`][ermrl.encoders.ReservoirParams], stepped by a
    [`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv]."""

    name = "reservoir"
    description = (
        "echo state networks initialized by reservoirpy (evolved sr, lr, input_scaling; with "
        "--multiscale, a log-uniform band of leak rates lr_min..lr_max); frozen, wraps the env"
    )
    place = "env"
    family = "esn"
    config_cls = EncoderConfig
    params_cls: ClassVar[type] = ReservoirParams
    space_cls: ClassVar[type] = ReservoirSpace
    settings: ClassVar[type | None] = ReservoirSettings
    agents: ClassVar[Mapping[str, AgentKind]] = AGENTS
    population = True

    def bank(self, config: EncoderConfig, input_dim: int, seed: int) -> ReservoirBank:
        """One weight seed per reservoir derived from ``seed``, the weights from reservoirpy's
        initializers ([`encoder_weights`][ermrl.encoders.encoder_weights]), fused into one bank."""
        weights = [
            encoder_weights(p, input_dim, s)
            for p, s in zip(config.reservoirs, reservoir_seeds(seed, config.n_reservoirs))
        ]
        return ReservoirBank(weights, dtype=config.dtype)

    def space_from_args(self, args: Any) -> Any:
        """The search space of the flags; the leak-rate flags of the other mode are refused.

        Raises:
            ConfigError: ``--lr-range`` with ``--multiscale``, ``--lr-max-range`` or
                ``--lr-min-ratio-range`` without it, or a bad value.
        """
        space = super().space_from_args(args)
        if isinstance(space, ReservoirSpace):
            unused = ("lr",) if space.multiscale else ("lr_max", "lr_min_ratio")
            for name in unused:
                spec = next(s for s in self.setting_specs() if s.name == f"{name}_range")
                given = getattr(args, spec.name, None)
                if given is not None and list(given) != list(spec.default):
                    mode = "with" if space.multiscale else "without"
                    raise ConfigError(f"{spec.flag} is unused {mode} --multiscale")
        return space

    def describe(self, space: Any) -> str:
        """``n x units units``, and ``multi-timescale`` with ``--multiscale``."""
        text = super().describe(space)
        return f"{text}, multi-timescale" if getattr(space, "multiscale", False) else text

    def wrap_env(self, venv: Any, config: EncoderConfig, seed: int) -> Any:
        from ermrl.encoders._vec_env import ReservoirVecEnv

        return ReservoirVecEnv(venv, config, seed=seed)

    def layout(self, params: Any) -> Hashable:
        """Its state width; an EMA's (the ``"ema"`` ablation's) is its input's, whatever its
        ``units``: EMAs share a population only with EMAs."""
        if isinstance(params, ReservoirParams) and params.ablation == "ema":
            return "ema"
        return int(params.state_dim)
