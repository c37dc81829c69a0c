"""Experts for imitation (BC, DAgger): trained here, saved as plain tensors plus JSON.

An expert is an SB3 policy of a learner of [`ermrl.learners`][ermrl.learners] (``sac`` or ``ppo``)
trained on a task's full observation (``observe="all"``). Its folder holds ``expert.json``
(settings, evaluation returns, versions), ``policy.pt`` (tensors only) and, with ``normalize``,
``vecnormalize.json``; no pickle. Learners that see a masked observation query the expert on the
full one::

    from ermrl.experts import evaluate_expert, load_expert, train_expert

    train_expert("Pendulum-v1", "sac", steps=5000, out="experts/pendulum")
    expert = load_expert("experts/pendulum")
    actions = expert.predict(full_observations)  # (n, obs_dim) raw -> (n, act_dim)
    print(evaluate_expert(expert, n_episodes=10, seed=0).mean)
"""

from ermrl.experts._expert import (
    EXPERT_FILE,
    EXPERT_FORMAT,
    Expert,
    ExpertEvaluation,
    ExpertInfo,
    evaluate_expert,
    expert_algos,
    is_expert_folder,
    load_expert,
)
from ermrl.experts._train import ExpertExists, TrainingProgress, check_expert_out, train_expert

__all__ = [
    "EXPERT_FILE",
    "EXPERT_FORMAT",
    "Expert",
    "ExpertEvaluation",
    "ExpertExists",
    "ExpertInfo",
    "TrainingProgress",
    "check_expert_out",
    "evaluate_expert",
    "expert_algos",
    "is_expert_folder",
    "load_expert",
    "train_expert",
]
