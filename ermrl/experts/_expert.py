"""A trained expert: its folder of plain files, loading it without pickles, and evaluating it.

Reading a folder (`ExpertInfo`, `Expert`, `load_expert`) lives in
`ermrl.learners._expert`, below the training loop, because imitation learners load their
expert when they are built; it is re-exported here. Evaluating an expert runs it in the
agents' environments, so it lives here, above them.

An expert folder holds:

- ``expert.json``: `ExpertInfo` (env id, algorithm, the learner settings used, steps,
  seed, wall time, the evaluation returns, library versions, observation and action shapes);
- ``policy.pt``: the policy's ``state_dict()`` as plain tensors, read with
  ``torch.load(..., weights_only=True)`` ([`ermrl.agents.load_policy`][ermrl.agents.load_policy]);
- ``vecnormalize.json``: only when the settings use ``normalize``, the observation statistics
  reached at the end of training ([`ermrl.agents.normalize_stats`][ermrl.agents.normalize_stats]).

Nothing in it is a pickle, so loading an expert someone else trained cannot run code. The
expert always sees the task's full observation (``observe="all"``): imitation learners that see
a masked observation query it on the full one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ermrl.config import TaskConfig
from ermrl.learners._expert import (
    EXPERT_FILE,
    EXPERT_FORMAT,
    NORMALIZE_FILE,
    Expert,
    ExpertInfo,
    expert_algos,
    is_expert_folder,
    load_expert,
)

__all__ = [
    "EXPERT_FILE",
    "EXPERT_FORMAT",
    "NORMALIZE_FILE",
    "Expert",
    "ExpertEvaluation",
    "ExpertInfo",
    "evaluate_expert",
    "expert_algos",
    "is_expert_folder",
    "load_expert",
]


@dataclass(frozen=True)
class ExpertEvaluation:
    """Deterministic episodes of an expert.

    Attributes:
        returns: Episode returns, in order.
        lengths: Episode lengths (steps), in order.
        seed: The seed the episodes were run with (see `evaluate_expert`).
    """

    returns: tuple[float, ...]
    lengths: tuple[int, ...]
    seed: int

    @property
    def mean(self) -> float:
        return float(np.mean(self.returns))

    @property
    def std(self) -> float:
        return float(np.std(self.returns))


def evaluate_expert(
    expert: Expert,
    n_episodes: int = 10,
    seed: int = 0,
    *,
    deterministic: bool = True,
) -> ExpertEvaluation:
    """Run episodes of an expert on its task's full observation.

    The episodes are those of SB3's ``evaluate_policy`` in training: one environment seeded
    with ``derive_seeds(seed).eval_env`` at its first reset, so ``seed=expert.info.seed``
    reproduces the recorded evaluation.

    Args:
        expert: The expert.
        n_episodes: Episodes to run.
        seed: Seed of the evaluation environment (see
            [`ermrl.agents.derive_seeds`][ermrl.agents.derive_seeds]).
        deterministic: The policy's mean action (``False`` samples).

    Returns:
        The episodes' returns and lengths.
    """
    from ermrl.agents import derive_seeds, make_vec_env

    if n_episodes < 1:
        raise ValueError(f"n_episodes must be >= 1, got {n_episodes}")
    env = make_vec_env(TaskConfig(expert.env_id, "all"), 1, derive_seeds(seed).eval_env)
    returns: list[float] = []
    lengths: list[int] = []
    try:
        obs = env.reset()
        while len(returns) < n_episodes:
            obs, _, dones, infos = env.step(expert.predict(obs, deterministic=deterministic))
            if dones[0]:
                episode = infos[0]["episode"]  # Monitor's record: the raw return
                returns.append(float(episode["r"]))
                lengths.append(int(episode["l"]))
    finally:
        env.close()
    return ExpertEvaluation(tuple(returns), tuple(lengths), seed)


def _versions(names: Sequence[str]) -> dict[str, str]:
    import platform
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version()}
    for name in names:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            continue
    return out
