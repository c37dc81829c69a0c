"""``imitation-sac``: SAC whose actor starts as a DAgger imitator of an expert, then learns by RL.

The phases (DAgger pretraining, a critic warm-start with the actor frozen, SAC re-anchored to
the expert by occasional DAgger iterations) and how env steps are counted are in
`ermrl.learners._imitation_sac_model`. Settings (``ermrl/data/imitation_sac.yml``): SAC's
own (the ``sac`` learner's table and checks) and the own keys below; ``learning_starts`` is
refused, ``pretrain_steps`` takes its place.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

from ermrl.config import AgentKind, ConfigError, PPOConfig
from ermrl.learners._bc import _whole, check_expert
from ermrl.learners._sac import SACLearner

__all__ = ["ImitationSACLearner"]


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


class ImitationSACLearner(SACLearner):
    """``imitation-sac``. Own keys: ``expert`` (required), ``pretrain_steps``,
    ``steps_per_iteration``, ``beta_schedule``, ``beta_iterations`` (DAgger pretraining),
    ``bc_epochs``, ``bc_learning_rate`` (its fits), ``critic_warmup_steps``,
    ``initial_log_std`` (the critic warm-start), ``anchor_schedule``, ``anchor_iterations``,
    ``bc_weight`` (re-anchoring during SAC)."""

    name = "imitation-sac"
    agents: ClassVar[Mapping[str, AgentKind]] = {
        "imitation-sac": AgentKind(
            "none", None,
            "SAC seeded by DAgger from an expert that sees the full state, on the raw (masked) "
            "observation (--for-learner imitation-sac expert=DIR)",
            "imitation-sac", "Imitation-SAC (raw observation)", "Imit.-SAC", "chocolate",
            default=False,
        ),
    }  # fmt: skip
    description = (
        "SAC seeded by DAgger from an expert, critic warm-started, re-anchored by DAgger "
        "(--ppo expert=DIR)"
    )
    table = "imitation_sac.yml"
    own_keys = {
        "expert": None,
        "pretrain_steps": 10_000,
        "steps_per_iteration": 1000,
        "beta_schedule": "linear",
        "beta_iterations": 5,
        "bc_epochs": 5,
        "bc_learning_rate": 1e-3,
        "critic_warmup_steps": 2000,
        "initial_log_std": -1.5,
        "anchor_schedule": "linear",
        "anchor_iterations": 10,
        "bc_weight": 0.4,
    }

    def algorithm(self) -> type:
        from ermrl.learners._imitation_sac_model import ImitationSAC

        return ImitationSAC

    def check(self, config: PPOConfig) -> None:
        from ermrl.learners._imitation import BETA_SCHEDULES

        super().check(config)
        name = self.name
        hp = config.hyperparams
        for key, why in (
            ("learning_starts", "pretrain_steps takes its place"),
            ("use_sde", "the actor's log-std head is reset after pretraining"),
        ):
            if key in hp and not (key == "use_sde" and hp[key] is False):
                raise ConfigError(f"learner {name!r} does not take {key} ({why})")
        check_expert(name, self.option(config, "expert"))
        _whole(name, "pretrain_steps", self.option(config, "pretrain_steps"), 0)
        _whole(name, "steps_per_iteration", self.option(config, "steps_per_iteration"), 1)
        _whole(name, "beta_iterations", self.option(config, "beta_iterations"), 1)
        _whole(name, "anchor_iterations", self.option(config, "anchor_iterations"), 1)
        _whole(name, "bc_epochs", self.option(config, "bc_epochs"), 1)
        _whole(name, "critic_warmup_steps", self.option(config, "critic_warmup_steps"), 0)
        for key in ("beta_schedule", "anchor_schedule"):
            if self.option(config, key) not in BETA_SCHEDULES:
                raise ConfigError(
                    f"{name} {key} must be one of {', '.join(BETA_SCHEDULES)}, "
                    f"got {self.option(config, key)!r}"
                )
        rate = self.option(config, "bc_learning_rate")
        if not _number(rate) or rate <= 0:
            raise ConfigError(f"{name} bc_learning_rate must be a number > 0, got {rate!r}")
        weight = self.option(config, "bc_weight")
        if not _number(weight) or weight < 0:
            raise ConfigError(f"{name} bc_weight must be a number >= 0, got {weight!r}")
        log_std = self.option(config, "initial_log_std")
        if not _number(log_std) or not -20 <= log_std <= 2:
            raise ConfigError(
                f"{name} initial_log_std must be a number in [-20, 2] (SB3's clamp), "
                f"got {log_std!r}"
            )

    def kwargs(self, config: PPOConfig) -> dict[str, Any]:
        """SAC's keyword arguments plus ``imitation``: every own setting (checked)."""
        kwargs = super().kwargs(config)
        kwargs["imitation"] = {key: self.option(config, key) for key in self.own_keys}
        return kwargs
