"""``sac``: Stable-Baselines3 SAC with an MLP policy, an off-policy inner learner.

Its table, ``ermrl/data/sac.yml``, holds rl-baselines3-zoo's SAC settings (``learning_starts``
10000 for the MuJoCo locomotion tasks, the zoo's tuned entries for Pendulum,
MountainCarContinuous and LunarLanderContinuous). SAC learns from a replay buffer: with a
reservoir, the buffer holds the encoded observations (the reservoir wraps the ``VecEnv``, and
[`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv] also encodes
``infos[i]["terminal_observation"]``, which SAC stores as the last ``next_observation`` of an
episode). Those are the states of the reservoir as it ran, which is exact for a frozen reservoir.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

from ermrl.config import AgentKind, ConfigError, PPOConfig
from ermrl.learners._base import Learner

__all__ = ["SACLearner"]

# Whole-number settings of SAC(...) and their least value.
_INT_MINIMUM = {"buffer_size": 1, "learning_starts": 0, "target_update_interval": 1}


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


class SACLearner(Learner):
    name = "sac"
    agents: ClassVar[Mapping[str, AgentKind]] = {
        "sac": AgentKind(
            "none", None, "SAC (off-policy) on the raw (masked) observation", "sac",
            "SAC (raw observation)", "SAC", "black", default=False,
        ),
    }  # fmt: skip
    description = "Stable-Baselines3 SAC, MLP policy (off-policy, replays encoded observations)"
    table = "sac.yml"
    # Settings whose values this learner checks itself (``ent_coef`` may be "auto" or
    # "auto_<initial value>", which the common PPO ranges would refuse).
    checks_itself: ClassVar[frozenset[str]] = frozenset({"ent_coef"})

    def algorithm(self) -> type:
        from stable_baselines3 import SAC

        return SAC

    def check(self, config: PPOConfig) -> None:
        """Refuse SAC settings that SB3 accepts at construction but that misbehave in training.

        Raises:
            ConfigError: with a one-line reason.
        """
        super().check(config)
        hp = config.hyperparams
        for key, least in _INT_MINIMUM.items():
            if key in hp and (not _is_int(hp[key]) or hp[key] < least):
                raise ConfigError(f"SAC {key} must be a whole number >= {least}, got {hp[key]!r}")
        if "gradient_steps" in hp:
            steps = hp["gradient_steps"]
            if not _is_int(steps) or (steps < 1 and steps != -1):
                raise ConfigError(
                    "SAC gradient_steps must be a whole number >= 1, or -1 (as many as env "
                    f"steps collected), got {steps!r}"
                )
        if "tau" in hp and not (_is_number(hp["tau"]) and 0.0 <= hp["tau"] <= 1.0):
            raise ConfigError(f"SAC tau must be a number in [0, 1], got {hp['tau']!r}")
        if "train_freq" in hp:
            freq = hp["train_freq"]
            pair = freq if isinstance(freq, (list, tuple)) else [freq, "step"]
            if (
                len(pair) != 2
                or not _is_int(pair[0])
                or pair[0] < 1
                or pair[1] not in ("step", "episode")
            ):
                raise ConfigError(
                    f"SAC train_freq must be a whole number >= 1 or [N, step|episode], got {freq!r}"
                )
        if "ent_coef" in hp:
            coef = hp["ent_coef"]
            if isinstance(coef, str) and coef.startswith("auto"):
                initial = coef[len("auto_") :] if coef.startswith("auto_") else "1.0"
                try:
                    ok = coef == "auto" or (coef.startswith("auto_") and float(initial) > 0)
                except ValueError:
                    ok = False
            else:
                ok = _is_number(coef) and coef >= 0
            if not ok:
                raise ConfigError(
                    "SAC ent_coef must be a number >= 0, 'auto' or 'auto_<initial value > 0>', "
                    f"got {coef!r}"
                )
        if "target_entropy" in hp:
            target = hp["target_entropy"]
            if target != "auto" and not _is_number(target):
                raise ConfigError(f"SAC target_entropy must be 'auto' or a number, got {target!r}")

    def kwargs(self, config: PPOConfig) -> dict[str, Any]:
        """SAC's keyword arguments: ``train_freq: [N, episode]`` (a YAML list) becomes a tuple."""
        kwargs = super().kwargs(config)
        if isinstance(kwargs.get("train_freq"), list):
            kwargs["train_freq"] = tuple(kwargs["train_freq"])
        return kwargs
