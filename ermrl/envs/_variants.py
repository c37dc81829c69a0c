"""Task variants that ermrl registers with gymnasium under ids of their own.

``AntNoContact-v5`` is Ant-v5 built with ``include_cfrc_ext_in_observation=False``: its
observation is the 27 position and velocity entries, without the 78 contact-force entries that
Ant-v5 appends by default (Ant-v4's default, and the observation rl-baselines3-zoo's Ant
results were trained on). An expert that should not depend on contact forces trains on it; the
variant has its own id so that studies, run folders, settings tables and experts name it.
``--observe positions|velocities`` masks it like Ant-v5 (its split is probed as for any MuJoCo
env). Registration happens when [`ermrl.envs`][ermrl.envs] is imported.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium

__all__ = ["VARIANTS", "register_variants"]

# variant id -> (base id, keyword arguments over the base's)
VARIANTS: Mapping[str, tuple[str, Mapping[str, Any]]] = {
    "AntNoContact-v5": ("Ant-v5", {"include_cfrc_ext_in_observation": False}),
}


def register_variants() -> None:
    """Register every variant not registered yet (idempotent)."""
    for env_id, (base, kwargs) in VARIANTS.items():
        if env_id in gymnasium.registry:
            continue
        spec = gymnasium.spec(base)
        gymnasium.register(
            env_id,
            entry_point=spec.entry_point,
            kwargs={**spec.kwargs, **kwargs},
            max_episode_steps=spec.max_episode_steps,
            reward_threshold=spec.reward_threshold,
        )
