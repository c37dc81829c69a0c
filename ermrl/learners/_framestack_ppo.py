"""``framestack-ppo``: PPO on the last k observations (SB3's ``VecFrameStack``).

The simplest memory: the policy sees the current (masked) observation and the k - 1 before it,
zeros before an episode's first step. ``k`` is the setting ``frame_stack`` (rl-baselines3-zoo's
key; default 4). The stack is the outermost wrapper, as in the zoo: it stacks what the policy
would otherwise see (normalized observations, reservoir states). The other settings are PPO's
(``ermrl/data/ppo.yml``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from ermrl.config import AgentKind, ConfigError, PPOConfig
from ermrl.learners._base import Learner

__all__ = ["FrameStackPPOLearner"]


class FrameStackPPOLearner(Learner):
    name = "framestack-ppo"
    agents: ClassVar[Mapping[str, AgentKind]] = {
        "framestack-ppo": AgentKind(
            "none", None, "PPO on the last k raw (masked) observations (frame_stack, default 4)",
            "framestack-ppo", "PPO (4 stacked frames)", "PPO\n(stacked)", "tab:brown",
            default=False,
        ),
    }  # fmt: skip
    description = "PPO on the last k observations stacked (frame_stack=k, default 4)"
    table = "ppo.yml"
    own_keys = {"frame_stack": 4}

    def check(self, config: PPOConfig) -> None:
        super().check(config)
        k = self.option(config, "frame_stack")
        if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= 1000:
            raise ConfigError(f"frame_stack must be a whole number in [1, 1000], got {k!r}")

    def wrap_env(self, venv: Any, config: PPOConfig) -> Any:
        from stable_baselines3.common.vec_env import VecFrameStack

        self.check(config)
        return VecFrameStack(venv, n_stack=self.option(config, "frame_stack"))
