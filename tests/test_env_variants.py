"""ermrl's registered task variants: AntNoContact-v5 (Ant-v5 without contact forces)."""

from __future__ import annotations

import numpy as np

from ermrl.agents import resolve_ppo_config
from ermrl.envs import make_env, observation_split


def test_ant_without_contact_forces_is_ant_v5_minus_its_contact_entries() -> None:
    plain, variant = make_env("Ant-v5"), make_env("AntNoContact-v5")
    try:
        assert plain.observation_space.shape == (105,)
        assert variant.observation_space.shape == (27,)
        a, _ = plain.reset(seed=3)
        b, _ = variant.reset(seed=3)
        np.testing.assert_array_equal(a[:27], b)
        action = np.full(8, 0.3, dtype=np.float32)
        for _ in range(20):
            a, ra, *_ = plain.step(action)
            b, rb, *_ = variant.step(action)
        np.testing.assert_array_equal(a[:27], b)
        assert ra == rb
        assert variant.spec is not None and variant.spec.max_episode_steps == 1000
    finally:
        plain.close()
        variant.close()


def test_its_masks_keep_ant_v5s_positions_and_velocities() -> None:
    split = observation_split("AntNoContact-v5")
    assert len(split.positions) == 13 and len(split.velocities) == 14
    assert observation_split("Ant-v5").positions == split.positions
    assert make_env("AntNoContact-v5", "velocities").observation_space.shape == (14,)


def test_it_takes_the_zoo_mujoco_sac_settings() -> None:
    sac = resolve_ppo_config("AntNoContact-v5", {}, learner="sac")
    assert sac.hyperparams["learning_starts"] == 10000
