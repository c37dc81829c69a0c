"""``ppo``: Stable-Baselines3 PPO with an MLP policy, the ER-MRL paper's inner learner.

The reference learner: read this module and [`ermrl.learners`][ermrl.learners] to add another. Its
settings table is ``ermrl/data/ppo.yml`` (rl-baselines3-zoo's tuned PPO settings for classic
control, SB3's defaults for MuJoCo as in the paper).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

from ermrl.config import AgentKind
from ermrl.learners._base import Learner

__all__ = ["PPOLearner"]


class PPOLearner(Learner):
    name = "ppo"
    agents: ClassVar[Mapping[str, AgentKind]] = {
        "ppo": AgentKind(
            "none", None, "PPO on the raw (masked) observation", "ppo",
            "PPO (raw observation)", "PPO", "tab:blue",
        ),
        "ppo-full": AgentKind(
            "none", "all",
            "PPO on the full, unmasked observation: the ceiling memory should approach",
            "ppo", "PPO (full observation)", "PPO\n(full obs.)", "tab:gray",
        ),
    }  # fmt: skip
    description = "Stable-Baselines3 PPO, MLP policy (the ER-MRL paper's learner)"
    table = "ppo.yml"
