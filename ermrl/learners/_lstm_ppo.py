"""``lstm-ppo``: sb3-contrib's ``RecurrentPPO`` with an LSTM policy, the standard memory baseline.

Its table, ``ermrl/data/ppo_lstm.yml``, holds rl-baselines3-zoo's ``ppo_lstm`` settings for the
velocity-masked tasks (the PPO settings, an LSTM of 64 units for the actor and one for the
critic, and ``normalize``). sb3-contrib moves in lockstep with stable-baselines3: both must be the
same version (checked when the learner is first used).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

from ermrl.config import AgentKind, ConfigError
from ermrl.learners._base import Learner

__all__ = ["LstmPPOLearner"]


class LstmPPOLearner(Learner):
    name = "lstm-ppo"
    agents: ClassVar[Mapping[str, AgentKind]] = {
        "lstm-ppo": AgentKind(
            "none", None,
            "RecurrentPPO (LSTM policy) on the raw (masked) observation: memory baseline",
            "lstm-ppo", "LSTM-PPO (raw observation)", "LSTM-PPO", "tab:purple", default=False,
        ),
    }  # fmt: skip
    description = "sb3-contrib RecurrentPPO, LSTM policy (memory baseline)"
    table = "ppo_lstm.yml"
    policy = "MlpLstmPolicy"
    recurrent = True

    def algorithm(self) -> type:
        import sb3_contrib
        import stable_baselines3
        from sb3_contrib import RecurrentPPO

        mine, theirs = sb3_contrib.__version__, stable_baselines3.__version__
        if mine.split(".")[:2] != theirs.split(".")[:2]:
            raise ConfigError(
                f"sb3-contrib {mine} does not match stable-baselines3 {theirs}; install "
                f"sb3-contrib=={theirs}"
            )
        return RecurrentPPO
