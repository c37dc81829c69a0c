"""``ppo``: Stable-Baselines3 PPO with an MLP policy, the ER-MRL paper's inner learner.

The reference learner: read this module and :mod:`ermrl.learners` to add another. Its settings
table is ``ermrl/data/ppo.yml`` (rl-baselines3-zoo's tuned PPO settings for classic control,
SB3's defaults for MuJoCo as in the paper).
"""

from __future__ import annotations

from ermrl.learners._base import Learner

__all__ = ["PPOLearner"]


class PPOLearner(Learner):
    name = "ppo"
    description = "Stable-Baselines3 PPO, MLP policy (the ER-MRL paper's learner)"
    table = "ppo.yml"
