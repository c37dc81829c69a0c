"""Tests for ermrl.envs: env-id validation, position/velocity splits, observation masks."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from typing import Any

import gymnasium
import numpy as np
import pytest
from gymnasium import spaces

import ermrl.envs as envs
from ermrl.envs import (
    OBSERVE_MODES,
    ObservationMask,
    ObservationSplit,
    UnknownEnvError,
    UnsupportedObserveError,
    check_env_id,
    make_env,
    observation_indices,
    observation_split,
    supported_observe_envs,
)

# Independent expectations, copied from the gymnasium docs' "Observation Space" sections
# (LunarLander's leg-contact flags go with positions, as in ER-MRL / rl-zoo MaskVelocityWrapper).
CLASSIC_EXPECTED: dict[str, tuple[int, tuple[int, ...], tuple[int, ...]]] = {
    "CartPole-v0": (4, (0, 2), (1, 3)),
    "CartPole-v1": (4, (0, 2), (1, 3)),
    "Pendulum-v1": (3, (0, 1), (2,)),
    "MountainCar-v0": (2, (0,), (1,)),
    "MountainCarContinuous-v0": (2, (0,), (1,)),
    "Acrobot-v1": (6, (0, 1, 2, 3), (4, 5)),
    "LunarLander-v3": (8, (0, 1, 4, 6, 7), (2, 3, 5)),
    "LunarLanderContinuous-v3": (8, (0, 1, 4, 6, 7), (2, 3, 5)),
}
# ER-MRL's velocity-deletion indices.
ERMRL_VELOCITY_INDICES = {
    "CartPole-v1": (1, 3),
    "MountainCar-v0": (1,),
    "Pendulum-v1": (2,),
    "LunarLander-v3": (2, 3, 5),
    "LunarLanderContinuous-v3": (2, 3, 5),
}

FAMILIES = ("Ant", "HalfCheetah", "Hopper", "Swimmer", "Walker2d")
MUJOCO_IDS = [f"{family}-{v}" for family in FAMILIES for v in ("v4", "v5")]
# Root coordinates dropped when _exclude_current_positions_from_observation is set
# (gymnasium docs: Ant and Swimmer drop x and y, the planar walkers drop x).
EXCLUDED_ROOT = {"Ant": 2, "HalfCheetah": 1, "Hopper": 1, "Swimmer": 2, "Walker2d": 1}
# Entries after qpos/qvel: Ant-v5 appends 13 bodies x 6 clipped cfrc_ext values.
EXTRA_ENTRIES = {"Ant-v5": 78}


def _family(env_id: str) -> str:
    return env_id.split("-")[0]


def _build(env_id: str, **kwargs: Any) -> gymnasium.Env:
    """gymnasium.make without the -v4 deprecation noise."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return gymnasium.make(env_id, **kwargs)


@pytest.fixture
def mujoco_env(request: pytest.FixtureRequest) -> Iterator[gymnasium.Env]:
    env = _build(request.param)
    env.reset(seed=0)
    yield env
    env.close()


def _responding(env: gymnasium.Env, vector_name: str, i: int, delta: float = 0.25) -> set[int]:
    """Obs indices that change when data.<vector_name>[i] moves by ``delta`` (no mj_forward)."""
    u: Any = env.unwrapped
    vector = getattr(u.data, vector_name)
    base = u._get_obs().copy()
    saved = float(vector[i])
    vector[i] = saved + delta
    moved = u._get_obs()
    vector[i] = saved
    return set(np.flatnonzero(moved != base).tolist())


def _rollout(env: gymnasium.Env, seed: int, n_steps: int) -> list[np.ndarray]:
    obs, _ = env.reset(seed=seed)
    out = [obs]
    env.action_space.seed(seed)
    for _ in range(n_steps):
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        out.append(obs)
        if terminated or truncated:
            break
    return out


# ---------------------------------------------------------------------------------------------
# Public API surface
# ---------------------------------------------------------------------------------------------
def test_public_api_exported() -> None:
    expected = {
        "OBSERVE_MODES",
        "ObservationMask",
        "ObservationSplit",
        "ObserveMode",
        "UnknownEnvError",
        "UnsupportedObserveError",
        "check_env_id",
        "make_env",
        "observation_indices",
        "observation_split",
        "supported_observe_envs",
    }
    assert expected <= set(envs.__all__)
    assert all(hasattr(envs, name) for name in expected)
    assert OBSERVE_MODES == ("all", "positions", "velocities")
    assert issubclass(UnknownEnvError, ValueError)
    assert issubclass(UnsupportedObserveError, ValueError)


def test_supported_observe_envs_lists_tested_ids() -> None:
    ids = supported_observe_envs()
    assert ids == sorted(ids)
    assert set(ids) == set(CLASSIC_EXPECTED) | set(MUJOCO_IDS)


def test_observation_split_is_cached_and_frozen() -> None:
    assert observation_split("HalfCheetah-v5") is observation_split("HalfCheetah-v5")
    split = observation_split("CartPole-v1")
    with pytest.raises(AttributeError):
        split.obs_dim = 5  # type: ignore[misc]


# ---------------------------------------------------------------------------------------------
# Classic control / Box2D tables
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("env_id", sorted(CLASSIC_EXPECTED))
def test_classic_table(env_id: str) -> None:
    obs_dim, positions, velocities = CLASSIC_EXPECTED[env_id]
    split = observation_split(env_id)
    assert split == ObservationSplit(obs_dim, positions, velocities, "table")
    env = _build(env_id)
    try:
        assert env.observation_space.shape == (split.obs_dim,)
    finally:
        env.close()
    every = split.positions + split.velocities
    assert all(0 <= i < split.obs_dim for i in every)
    assert not set(split.positions) & set(split.velocities)
    assert sorted(every) == list(range(split.obs_dim))  # classic tables cover everything


@pytest.mark.parametrize("env_id", sorted(ERMRL_VELOCITY_INDICES))
def test_classic_velocities_match_ermrl(env_id: str) -> None:
    assert observation_indices(env_id, "velocities") == ERMRL_VELOCITY_INDICES[env_id]


@pytest.mark.parametrize("observe", ["positions", "velocities"])
@pytest.mark.parametrize("env_id", sorted(CLASSIC_EXPECTED) + MUJOCO_IDS)
def test_masked_env_is_slice_of_full_env(env_id: str, observe: str) -> None:
    indices = observation_indices(env_id, observe)  # type: ignore[arg-type]
    assert indices
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        full, masked = make_env(env_id), make_env(env_id, observe)  # type: ignore[arg-type]
    try:
        assert isinstance(masked, ObservationMask)
        assert masked.observation_space.shape == (len(indices),)
        full_obs = _rollout(full, seed=7, n_steps=4)
        masked_obs = _rollout(masked, seed=7, n_steps=4)
        assert len(full_obs) == len(masked_obs)
        for f, m in zip(full_obs, masked_obs):
            np.testing.assert_array_equal(m, f[list(indices)])
            assert m.dtype == f.dtype
            assert masked.observation_space.contains(m)
    finally:
        full.close()
        masked.close()


@pytest.mark.parametrize("observe", ["positions", "velocities"])
def test_lunar_lander_continuous_kwarg_keeps_layout(observe: str) -> None:
    env = make_env("LunarLander-v3", observe, continuous=True)  # type: ignore[arg-type]
    try:
        assert isinstance(env.action_space, spaces.Box)
        obs, _ = env.reset(seed=0)
        assert obs.shape == (len(observation_indices("LunarLander-v3", observe)),)  # type: ignore[arg-type]
    finally:
        env.close()


@pytest.mark.parametrize("observe", ["positions", "velocities"])
def test_lunar_lander_continuous_id_masks_like_lunar_lander(observe: Any) -> None:
    # The id of its own (the zoo's PPO table has an entry for it) keeps LunarLander's layout.
    split = observation_indices("LunarLanderContinuous-v3", observe)
    assert split == observation_indices("LunarLander-v3", observe)
    env = make_env("LunarLanderContinuous-v3", observe)
    try:
        assert isinstance(env.action_space, spaces.Box) and env.action_space.shape == (2,)
        obs, _ = env.reset(seed=0)
        assert obs.shape == (len(split),)
    finally:
        env.close()


# ---------------------------------------------------------------------------------------------
# MuJoCo: split derived from the model
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("mujoco_env", MUJOCO_IDS, indirect=True, ids=MUJOCO_IDS)
def test_mujoco_split_matches_model(mujoco_env: gymnasium.Env) -> None:
    env_id = mujoco_env.spec.id  # type: ignore[union-attr]
    u: Any = mujoco_env.unwrapped
    nq, nv = int(u.model.nq), int(u.model.nv)
    assert u._exclude_current_positions_from_observation is True
    excluded = (
        EXCLUDED_ROOT[_family(env_id)] if u._exclude_current_positions_from_observation else 0
    )
    n_pos = nq - excluded
    obs_dim = mujoco_env.observation_space.shape[0]

    split = observation_split(env_id)
    assert split.source == "mujoco-model"
    assert split.obs_dim == obs_dim == n_pos + nv + EXTRA_ENTRIES.get(env_id, 0)
    assert len(split.positions) == n_pos
    assert len(split.velocities) == nv
    # gymnasium's documented layout: [qpos[excluded:], qvel, extras]
    assert split.positions == tuple(range(n_pos))
    assert split.velocities == tuple(range(n_pos, n_pos + nv))
    assert not set(split.positions) & set(split.velocities)


@pytest.mark.parametrize("mujoco_env", MUJOCO_IDS, indirect=True, ids=MUJOCO_IDS)
def test_mujoco_each_coordinate_lands_on_one_side(mujoco_env: gymnasium.Env) -> None:
    env_id = mujoco_env.spec.id  # type: ignore[union-attr]
    u: Any = mujoco_env.unwrapped
    split = observation_split(env_id)
    excluded = EXCLUDED_ROOT[_family(env_id)]
    for i in range(u.model.nq):
        hit = _responding(mujoco_env, "qpos", i)
        if i < excluded:  # excluded root x (and y) must not appear anywhere
            assert hit == set(), f"qpos[{i}] leaks into obs {hit}"
        else:
            assert len(hit) == 1 and hit <= set(split.positions), (i, hit)
    for j in range(u.model.nv):
        hit = _responding(mujoco_env, "qvel", j)
        assert len(hit) == 1 and hit <= set(split.velocities), (j, hit)
        assert not hit & set(split.positions)


@pytest.mark.parametrize("family", FAMILIES)
def test_mujoco_v4_v5_agree_on_shared_part(family: str) -> None:
    v4, v5 = observation_split(f"{family}-v4"), observation_split(f"{family}-v5")
    assert v4.positions == tuple(i for i in v5.positions if i < v4.obs_dim)
    assert v4.velocities == tuple(i for i in v5.velocities if i < v4.obs_dim)
    assert all(i < v4.obs_dim for i in v5.positions + v5.velocities)


@pytest.mark.parametrize("env_id", ["HalfCheetah-v4", "HalfCheetah-v5"])
def test_halfcheetah_forward_velocity_is_not_a_position(env_id: str) -> None:
    split = observation_split(env_id)
    assert (len(split.positions), len(split.velocities)) == (8, 9)
    env = _build(env_id)
    try:
        env.reset(seed=1)
        root_x_vel = _responding(env, "qvel", 0)
        assert root_x_vel == {8}
        assert root_x_vel <= set(split.velocities)
        assert not root_x_vel & set(split.positions)
        assert _responding(env, "qpos", 0) == set()  # root x position excluded everywhere
    finally:
        env.close()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        masked = make_env(env_id, "positions")
    try:
        obs, _ = masked.reset(seed=1)
        u: Any = masked.unwrapped
        np.testing.assert_array_equal(obs, u.data.qpos[1:])  # no qvel[0] leak
    finally:
        masked.close()


def test_ant_v5_contact_forces_in_neither() -> None:
    split = observation_split("Ant-v5")
    contact = set(range(27, 105))
    assert len(contact) == 78
    assert not contact & set(split.positions)
    assert not contact & set(split.velocities)
    assert (len(split.positions), len(split.velocities)) == (13, 14)
    env = _build("Ant-v5")
    try:
        env.reset(seed=0)
        env.action_space.seed(0)
        obs, *_ = env.step(env.action_space.sample())
        u: Any = env.unwrapped
        np.testing.assert_array_equal(obs[27:], u.contact_forces[1:].ravel())
    finally:
        env.close()


@pytest.mark.parametrize(
    ("env_id", "kwargs", "n_pos", "n_vel", "obs_dim"),
    [
        ("Ant-v5", {"include_cfrc_ext_in_observation": False}, 13, 14, 27),
        ("Ant-v5", {"exclude_current_positions_from_observation": False}, 15, 14, 107),
        ("HalfCheetah-v5", {"exclude_current_positions_from_observation": False}, 9, 9, 18),
        ("Hopper-v5", {"exclude_current_positions_from_observation": False}, 6, 6, 12),
    ],
)
def test_make_env_reprobes_layout_changing_kwargs(
    env_id: str, kwargs: dict[str, Any], n_pos: int, n_vel: int, obs_dim: int
) -> None:
    for observe, n in (("positions", n_pos), ("velocities", n_vel)):
        env = make_env(env_id, observe, **kwargs)  # type: ignore[arg-type]
        try:
            assert env.unwrapped.observation_space.shape == (obs_dim,)
            obs, _ = env.reset(seed=0)
            assert obs.shape == (n,)
            assert env.observation_space.contains(obs)
        finally:
            env.close()


def test_generic_mujoco_env_with_clean_split_is_accepted() -> None:
    split = observation_split("InvertedPendulum-v5")  # obs = [qpos, qvel]
    assert split == ObservationSplit(4, (0, 1), (2, 3), "mujoco-model")
    assert "InvertedPendulum-v5" not in supported_observe_envs()


def test_generic_mujoco_env_with_derived_entries_is_rejected() -> None:
    # Reacher's fingertip-target vector comes from body positions (xpos), not qpos directly.
    with pytest.raises(UnsupportedObserveError, match="use --observe all"):
        observation_split("Reacher-v5")


# ---------------------------------------------------------------------------------------------
# ObservationMask
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("env_id", "indices"),
    [
        ("CartPole-v1", (0, 2)),
        ("CartPole-v1", (3, 1)),
        ("Pendulum-v1", (2,)),
        ("Acrobot-v1", (5, 0)),
    ],
)
def test_observation_mask_space(env_id: str, indices: tuple[int, ...]) -> None:
    base = _build(env_id)
    env = ObservationMask(base, indices)
    try:
        full = base.observation_space
        assert isinstance(env.observation_space, spaces.Box)
        np.testing.assert_array_equal(env.observation_space.low, full.low[list(indices)])
        np.testing.assert_array_equal(env.observation_space.high, full.high[list(indices)])
        assert env.observation_space.dtype == full.dtype
        assert env.observation_space.shape == (len(indices),)
        obs, _ = env.reset(seed=3)
        assert env.observation_space.contains(obs)
        for _ in range(3):
            obs, *_ = env.step(env.action_space.sample())
            assert env.observation_space.contains(obs)
    finally:
        env.close()


def test_observation_mask_pendulum_velocity_bounds() -> None:
    env = make_env("Pendulum-v1", "velocities")
    try:
        assert env.observation_space == spaces.Box(-8.0, 8.0, (1,), np.float32)
    finally:
        env.close()


@pytest.mark.parametrize(
    ("indices", "error"),
    [((), ValueError), ((0, 4), ValueError), ((-1,), ValueError), ((1, 1), ValueError)],
)
def test_observation_mask_rejects_bad_indices(indices: tuple[int, ...], error: type) -> None:
    with pytest.raises(error):
        ObservationMask(_build("CartPole-v1"), indices)


def test_observation_mask_rejects_non_box() -> None:
    with pytest.raises(TypeError):
        ObservationMask(_build("Blackjack-v1"), (0,))


# ---------------------------------------------------------------------------------------------
# Errors and validation order
# ---------------------------------------------------------------------------------------------
def test_unknown_env_id_suggests_close_matches() -> None:
    with pytest.raises(
        UnknownEnvError, match=r"unknown env id 'HalfCheetah-v9'; did you mean: "
    ) as info:
        check_env_id("HalfCheetah-v9")
    assert "HalfCheetah-v5" in str(info.value) and "HalfCheetah-v4" in str(info.value)
    with pytest.raises(UnknownEnvError, match="CartPole-v1"):
        make_env("CartPol-v1")
    with pytest.raises(UnknownEnvError):
        observation_split("NoSuchEnv-v0")
    with pytest.raises(UnknownEnvError):
        observation_indices("NoSuchEnv-v0", "all")


def test_check_env_id_does_not_build(monkeypatch: pytest.MonkeyPatch) -> None:
    def boom(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("gymnasium.make must not be called")

    monkeypatch.setattr(gymnasium, "make", boom)
    check_env_id("Humanoid-v5")
    check_env_id("CartPole-v1")
    with pytest.raises(ValueError, match="observe must be one of"):
        make_env("Humanoid-v5", "pixels")  # type: ignore[arg-type]
    with pytest.raises(UnknownEnvError):
        make_env("Humanoid-v9", "positions")
    with pytest.raises(UnsupportedObserveError):
        make_env("Blackjack-v1", "velocities")


@pytest.mark.parametrize("env_id", ["Blackjack-v1", "FrozenLake-v1", "BipedalWalker-v3"])
@pytest.mark.parametrize("observe", ["positions", "velocities"])
def test_unsupported_env_lists_supported_ids(env_id: str, observe: str) -> None:
    with pytest.raises(UnsupportedObserveError) as info:
        make_env(env_id, observe)  # type: ignore[arg-type]
    message = str(info.value)
    assert env_id in message
    assert "Pendulum-v1" in message and "HalfCheetah-v5" in message
    assert "use --observe all" in message.lower()
    with pytest.raises(UnsupportedObserveError):
        observation_indices(env_id, observe)  # type: ignore[arg-type]


@pytest.mark.parametrize("observe", ["", "Positions", "pos", None, "velocity"])
def test_bad_observe_value(observe: Any) -> None:
    with pytest.raises(ValueError, match="observe must be one of"):
        make_env("CartPole-v1", observe)
    with pytest.raises(ValueError, match="observe must be one of"):
        observation_indices("CartPole-v1", observe)


def test_observe_all_is_unmasked_for_any_env() -> None:
    assert observation_indices("Blackjack-v1", "all") is None
    assert observation_indices("HalfCheetah-v5", "all") is None
    env = make_env("Blackjack-v1")
    try:
        assert not isinstance(env, ObservationMask)
        assert isinstance(env.observation_space, spaces.Tuple)
    finally:
        env.close()


def test_make_env_passes_render_mode_and_kwargs() -> None:
    env = make_env("CartPole-v1", "positions", render_mode="rgb_array", max_episode_steps=3)
    try:
        assert env.render_mode == "rgb_array"
        env.reset(seed=0)
        truncated = False
        for _ in range(3):
            *_, terminated, truncated, _ = env.step(0)
        assert truncated or terminated
    finally:
        env.close()


def test_v4_probe_is_silent() -> None:
    from ermrl.envs._masks import _derive_mujoco_split

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        split = _derive_mujoco_split("Hopper-v4")
    assert split == observation_split("Hopper-v4")
    assert not [w for w in caught if "out of date" in str(w.message)]
