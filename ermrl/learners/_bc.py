"""``bc``: behaviour cloning of an expert; also the settings shared with ``dagger``.

BC regresses an MLP policy's mean onto the expert's actions (mean squared error in the scaled
action space ``[-1, 1]``) on ``n_expert_transitions`` states visited by the expert itself. The
expert (``--ppo expert=DIR``, a folder written by ``ermrl expert train``) acts on the task's
raw full observation; the imitator sees the learner's observation (masked by ``--observe``,
maybe reservoir-encoded). The agent is `ImitationAgent`;
how env steps are counted is in that module's docstring (the expert's data collection is
counted apart, as ``expert_env_steps``; the budget is the imitator's own steps).

Settings (``ermrl/data/bc.yml``): the own keys below plus ``learning_rate`` (Adam) and
``batch_size``, shared with PPO. Any other key is refused in one line.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

from ermrl.config import ConfigError, PPOConfig
from ermrl.learners._base import Learner

__all__ = ["BCLearner", "ImitationLearner"]

# PPO keys the imitation learners read too (with these defaults when the table does not set them).
SHARED_KEYS: Mapping[str, Any] = {"learning_rate": 1e-3, "batch_size": 256}
# Keys read by ermrl itself, never an algorithm's.
_ERMRL_KEYS = {"n_envs", "normalize"}
MAX_WIDTH = 4096


def _whole(learner: str, key: str, value: Any, least: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ConfigError(f"{learner} {key} must be a whole number >= {least}, got {value!r}")
    return value


def check_expert(learner: str, expert: Any) -> None:
    """Refuse a missing ``expert`` setting of an imitation learner, in one line."""
    if not isinstance(expert, str) or not expert:
        raise ConfigError(
            f"learner {learner!r} needs an expert: --ppo expert=DIR, or in a test phase "
            f"--for-learner {learner} expert=DIR (a folder written by ermrl expert train), "
            f"got {expert!r}"
        )


class ImitationLearner(Learner):
    """What ``bc`` and ``dagger`` share: the expert, the network, the regression's settings."""

    policy = "ImitationPolicy"
    shared_keys = SHARED_KEYS
    common_keys: ClassVar[Mapping[str, Any]] = {
        "expert": None,
        "hidden_sizes": [64, 64],
        "epochs": 5,
    }

    def settings(self, config: PPOConfig) -> dict[str, Any]:
        """Every setting of the agent (own and shared keys, and ``mode``), checked.

        Raises:
            ConfigError: a bad value, with a one-line reason.
        """
        return {**super().settings(config), "mode": self.name}

    def check(self, config: PPOConfig) -> None:
        super().check(config)
        name = self.name
        foreign = set(config.hyperparams) - set(self.own_keys) - set(SHARED_KEYS) - _ERMRL_KEYS
        if foreign:
            raise ConfigError(
                f"learner {name!r} does not take {', '.join(sorted(foreign))} (a setting of "
                "another learner)"
            )
        check_expert(name, self.option(config, "expert"))
        sizes = self.option(config, "hidden_sizes")
        if not isinstance(sizes, (list, tuple)) or not all(
            isinstance(h, int) and not isinstance(h, bool) and 1 <= h <= MAX_WIDTH for h in sizes
        ):
            raise ConfigError(
                f"{name} hidden_sizes must be a list of whole numbers in [1, {MAX_WIDTH}], "
                f"got {sizes!r}"
            )
        _whole(name, "epochs", self.option(config, "epochs"), 1)
        _whole(name, "batch_size", self.option(config, "batch_size"), 1)
        rate = self.option(config, "learning_rate")
        if (
            isinstance(rate, bool)
            or not isinstance(rate, (int, float))
            or not math.isfinite(rate)
            or rate <= 0
        ):
            raise ConfigError(f"{name} learning_rate must be a number > 0, got {rate!r}")

    def kwargs(self, config: PPOConfig) -> dict[str, Any]:
        """The agent's settings (no PPO argument is passed on)."""
        return self.settings(config)

    def algorithm(self) -> type:
        from ermrl.learners._dagger_model import ImitationAgent

        return ImitationAgent

    def build(
        self,
        env: Any,
        config: PPOConfig,
        *,
        seed: int | None = None,
        device: str | None = None,
        tensorboard_log: str | None = None,
    ) -> Any:
        """A new, untrained imitator on ``env``; loads the expert (on the CPU: ``device`` and
        ``tensorboard_log`` are ignored).

        Raises:
            ConfigError: a bad setting, no expert at ``expert``, an expert of another task, or
                an action space that is not a Box.
        """
        from ermrl.learners._dagger_model import ImitationAgent

        return ImitationAgent(env, self.settings(config), seed=seed)


class BCLearner(ImitationLearner):
    """``bc``. Own keys: ``expert`` (required), ``n_expert_transitions`` (expert env steps of
    data), ``hidden_sizes``, ``epochs`` (passes over the data)."""

    name = "bc"
    description = "behaviour cloning: an MLP regressed onto an expert's actions (--ppo expert=DIR)"
    table = "bc.yml"
    own_keys = {**ImitationLearner.common_keys, "epochs": 20, "n_expert_transitions": 10_000}

    def check(self, config: PPOConfig) -> None:
        super().check(config)
        _whole("bc", "n_expert_transitions", self.option(config, "n_expert_transitions"), 1)
