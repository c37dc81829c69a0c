"""The reservoir encoder: reservoirpy equivalence, inputs really fed, batching and resets."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces
from reservoirpy.nodes import Reservoir
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

from ermrl.config import ConfigError, EncoderConfig, ReservoirParams
from ermrl.encoders import (
    ActionEncoder,
    ReservoirBank,
    ReservoirVecEnv,
    reservoir_seeds,
    reservoir_weights,
)


@pytest.mark.parametrize(
    "params",
    [
        ReservoirParams(units=50, sr=0.9, lr=0.3, input_scaling=1.0),
        ReservoirParams(units=30, sr=5.0, lr=1.0, input_scaling=0.2, bias_scaling=0.5),
        ReservoirParams(units=40, sr=1e-3, lr=0.01, input_scaling=8.0, rc_connectivity=0.3),
        ReservoirParams(units=60, sr=1.2, lr=0.5, bias_init="original"),
    ],
)
def test_states_equal_reservoirpy_reservoir(params: ReservoirParams) -> None:
    """Our weights and batched update reproduce reservoirpy's own Reservoir to 1e-10."""
    rng = np.random.default_rng(0)
    inputs = rng.normal(size=(200, 6))
    weights = reservoir_weights(params, input_dim=6, seed=123)
    ours = ReservoirBank([weights]).run(inputs)

    # 1. reservoirpy built from the same hyperparameters and seed: proves the weights match.
    from ermrl.encoders import reservoir_node

    node = reservoir_node(params, 6, 123)
    theirs = node.run(inputs)
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-10)

    # 2. reservoirpy given our dense matrices: proves the update rule matches.
    node2 = Reservoir(
        units=params.units, lr=params.lr, W=weights.W, Win=weights.Win, bias=weights.bias
    )
    np.testing.assert_allclose(ours, node2.run(inputs), rtol=0, atol=1e-10)


def test_spectral_radius_and_connectivity_follow_params() -> None:
    params = ReservoirParams(units=100, sr=2.5, lr=0.5, input_scaling=3.0)
    w = reservoir_weights(params, input_dim=10, seed=1)
    assert np.max(np.abs(np.linalg.eigvals(w.W))) == pytest.approx(2.5, rel=1e-6)
    assert set(np.unique(np.abs(w.Win[w.Win != 0]))) == {3.0}
    assert 0.05 < np.mean(w.W != 0) < 0.15  # rc_connectivity 0.1
    assert w.Win.shape == (100, 10) and w.bias.shape == (100,)


def test_original_bias_is_reservoirpy_0_3s_sparse_bernoulli() -> None:
    """reservoirpy 0.3's default bias: +-1 on input_connectivity (10%) of the units."""
    for seed in (0, 1, 2):
        bias = reservoir_weights(ReservoirParams(bias_init="original"), 4, seed=seed).bias
        nonzero = bias[bias != 0]
        assert len(nonzero) == 10  # 10% of 100 units
        assert set(np.abs(nonzero)) == {1.0} and set(np.sign(nonzero)) == {-1.0, 1.0}
    denser = ReservoirParams(bias_init="original", input_connectivity=0.3)
    assert np.count_nonzero(reservoir_weights(denser, 4, seed=0).bias) == 30
    # --bias-scaling, by contrast, is dense: every unit +-scale.
    dense = reservoir_weights(ReservoirParams(bias_scaling=0.5), 4, seed=0).bias
    assert set(np.abs(dense)) == {0.5}
    assert not np.any(reservoir_weights(ReservoirParams(), 4, seed=0).bias)  # default: none


def test_bias_init_is_validated_and_absent_from_old_configs() -> None:
    from ermrl.config import ReservoirSpace, from_dict, to_dict

    assert "bias_init" not in to_dict(ReservoirParams())  # stored configs stay as they were
    assert "bias_init" not in to_dict(ReservoirSpace())
    original = ReservoirParams(bias_init="original")
    assert to_dict(original)["bias_init"] == "original"
    assert from_dict(ReservoirParams, to_dict(original)) == original
    space = ReservoirSpace(bias_init="original")
    assert all(r.bias_init == "original" for r in space.default_reservoirs())
    assert space.reservoirs_from({"sr": 1.0, "lr": 0.5, "input_scaling": 1.0})[0].bias_init == (
        "original"
    )
    with pytest.raises(ConfigError, match="cannot be combined with bias_scaling"):
        ReservoirParams(bias_init="original", bias_scaling=0.5)
    with pytest.raises(ConfigError, match="bias_init must be one of"):
        ReservoirParams(bias_init="dense")  # type: ignore[arg-type]


def test_same_seed_same_recurrent_weights_for_any_input_dim() -> None:
    """What 'the same reservoir on another task' means: same W and bias, Win drawn per task."""
    params = ReservoirParams(units=20, bias_scaling=1.0)
    a = reservoir_weights(params, 5, seed=7)
    b = reservoir_weights(params, 12, seed=7)
    c = reservoir_weights(params, 5, seed=8)
    np.testing.assert_array_equal(a.W, b.W)
    np.testing.assert_array_equal(a.bias, b.bias)
    assert not np.array_equal(a.W, c.W)
    assert a.Win.shape == (20, 5) and b.Win.shape == (20, 12)


def test_bank_fuses_reservoirs_like_separate_runs() -> None:
    p0 = ReservoirParams(units=15, sr=0.5, lr=0.2)
    p1 = ReservoirParams(units=25, sr=3.0, lr=0.9, input_scaling=2.0)
    w0, w1 = reservoir_weights(p0, 4, 1), reservoir_weights(p1, 4, 2)
    inputs = np.random.default_rng(3).normal(size=(50, 4))
    fused = ReservoirBank([w0, w1]).run(inputs)
    np.testing.assert_allclose(fused[:, :15], ReservoirBank([w0]).run(inputs), atol=1e-12)
    np.testing.assert_allclose(fused[:, 15:], ReservoirBank([w1]).run(inputs), atol=1e-12)


def test_batched_rows_equal_single_runs() -> None:
    w = reservoir_weights(ReservoirParams(units=30, sr=1.2, lr=0.4), 3, 0)
    bank = ReservoirBank([w])
    inputs = np.random.default_rng(1).normal(size=(40, 4, 3))  # T, n_envs, D
    states = np.zeros((4, 30))
    for t in range(40):
        bank.step(states, inputs[t])
    for i in range(4):
        np.testing.assert_allclose(states[i], bank.run(inputs[:, i])[-1], atol=1e-12)


# --------------------------------------------------------------------------------------------
# The VecEnv wrapper


class ScriptedEnv(gym.Env):
    """Deterministic env whose observation and reward are known functions of the step."""

    def __init__(self, action_space: spaces.Space, episode_len: int = 5) -> None:
        self.observation_space = spaces.Box(-10.0, 10.0, shape=(2,), dtype=np.float32)
        self.action_space = action_space
        self.episode_len = episode_len
        self.t = 0
        self.episode = 0

    def _obs(self) -> np.ndarray:
        return np.array([self.t, self.episode], dtype=np.float32) / 10

    def reset(self, *, seed=None, options=None):  # noqa: ANN001
        super().reset(seed=seed)
        self.t = 0
        self.episode += 1
        return self._obs(), {}

    def step(self, action):  # noqa: ANN001
        self.t += 1
        reward = 0.5 * self.t
        truncated = self.t >= self.episode_len
        return self._obs(), reward, False, truncated, {}


def _venv(action_space: spaces.Space, n_envs: int = 1, episode_len: int = 5) -> DummyVecEnv:
    return DummyVecEnv([lambda: Monitor(ScriptedEnv(action_space, episode_len))] * n_envs)


def _encoder(**kwargs: object) -> EncoderConfig:
    kwargs.setdefault("dtype", "float64")  # exact comparisons below; float32 is tested separately
    return EncoderConfig(reservoirs=(ReservoirParams(units=20, sr=0.9, lr=0.5),), **kwargs)  # type: ignore[arg-type]


def test_previous_action_is_fed_to_the_reservoir() -> None:
    """Catches the original ER-MRL bug: zeros were fed instead of the action.

    Two runs see the same observations and rewards and differ only in the actions; the
    reservoir states must differ, and the action block of the input must equal the encoding.
    """
    space = spaces.Box(-2.0, 2.0, shape=(1,), dtype=np.float32)
    runs = []
    for action in (-2.0, 2.0):
        env = ReservoirVecEnv(_venv(space), _encoder(), seed=0)
        env.reset()
        env.step(np.array([[action]], dtype=np.float32))
        u = env.get_inputs()[0]
        # layout: obs (2), action (1), reward (1)
        assert u[2] == pytest.approx(action / 2.0)  # scaled to [-1, 1]
        runs.append(env.get_states()[0])
    assert not np.allclose(runs[0], runs[1])


def test_feeding_zeros_instead_of_actions_would_be_detected() -> None:
    """With feed_action disabled (the original's behaviour), the action has no effect."""
    space = spaces.Box(-2.0, 2.0, shape=(1,), dtype=np.float32)
    states = []
    for action in (-2.0, 2.0):
        env = ReservoirVecEnv(_venv(space), _encoder(feed_action=False), seed=0)
        env.reset()
        env.step(np.array([[action]], dtype=np.float32))
        states.append(env.get_states()[0])
    np.testing.assert_array_equal(states[0], states[1])


def test_discrete_action_is_one_hot() -> None:
    env = ReservoirVecEnv(_venv(spaces.Discrete(3), n_envs=2), _encoder(), seed=0)
    env.reset()
    env.step(np.array([2, 0]))
    u = env.get_inputs()
    np.testing.assert_array_equal(u[:, 2:5], [[0, 0, 1], [1, 0, 0]])


def test_action_encoder_spaces() -> None:
    out = np.zeros((2, 5))
    ActionEncoder(spaces.MultiDiscrete([2, 3]))(np.array([[1, 2], [0, 0]]), out)
    np.testing.assert_array_equal(out, [[0, 1, 0, 0, 1], [1, 0, 1, 0, 0]])
    box = ActionEncoder(spaces.Box(np.array([0.0, -1.0]), np.array([4.0, 1.0])))
    out2 = np.zeros((1, 2))
    box(np.array([[3.0, 0.5]]), out2)
    np.testing.assert_allclose(out2, [[0.5, 0.5]])
    box(np.array([[9.0, -7.0]]), out2)  # out of bounds is clipped
    np.testing.assert_allclose(out2, [[1.0, -1.0]])


def test_reward_is_fed_and_scaled() -> None:
    env = ReservoirVecEnv(_venv(spaces.Discrete(2)), _encoder(reward_scale=0.1), seed=0)
    env.reset()
    env.step(np.array([1]))
    assert env.get_inputs()[0, -1] == pytest.approx(0.05)  # reward 0.5 * 0.1
    env.step(np.array([1]))
    assert env.get_inputs()[0, -1] == pytest.approx(0.1)


def test_observation_is_fed() -> None:
    env = ReservoirVecEnv(_venv(spaces.Discrete(2)), _encoder(), seed=0)
    env.reset()
    env.step(np.array([1]))
    np.testing.assert_allclose(env.get_inputs()[0, :2], [0.1, 0.1])


def test_states_match_reference_recurrence_over_episodes() -> None:
    """Replays the wrapper's documented input sequence through reservoirpy-equivalent math."""
    space = spaces.Discrete(2)
    env = ReservoirVecEnv(_venv(space, episode_len=3), _encoder(), seed=4)
    bank = env.bank
    obs0 = env.reset()
    x = np.zeros(20)

    def step(x: np.ndarray, u: list[float]) -> np.ndarray:
        return bank.run(np.array([u]), state=x)[-1]

    x = step(x, [0.0, 0.1, 0, 0, 0])
    np.testing.assert_allclose(obs0[0], x.astype(np.float32))
    actions = [1, 0, 1, 1]
    for t, a in enumerate(actions, start=1):
        obs, rewards, dones, infos = env.step(np.array([a]))
        one_hot = [1 - a, a]
        if t < 3:
            x = step(x, [t / 10, 0.1, *one_hot, 0.5 * t])
            np.testing.assert_allclose(obs[0], x.astype(np.float32), atol=1e-7)
            assert not dones[0]
        elif t == 3:
            assert dones[0]
            x_term = step(x, [0.3, 0.1, *one_hot, 1.5])
            np.testing.assert_allclose(
                infos[0]["terminal_observation"], x_term.astype(np.float32), atol=1e-7
            )
            x = step(np.zeros(20), [0.0, 0.2, 0, 0, 0])  # reset row, new episode, no prev action
            np.testing.assert_allclose(obs[0], x.astype(np.float32), atol=1e-7)
        else:
            x = step(x, [0.1, 0.2, *one_hot, 0.5])
            np.testing.assert_allclose(obs[0], x.astype(np.float32), atol=1e-7)


def test_row_reset_only_for_finished_env_and_carry_mode() -> None:
    space = spaces.Discrete(2)
    # env 0 ends after 2 steps, env 1 after 4
    venv = DummyVecEnv(
        [lambda: Monitor(ScriptedEnv(space, 2)), lambda: Monitor(ScriptedEnv(space, 4))]
    )
    env = ReservoirVecEnv(venv, _encoder(), seed=0)
    env.reset()
    env.step(np.array([1, 1]))
    before = env.get_states()
    _, _, dones, _ = env.step(np.array([1, 1]))
    assert dones.tolist() == [True, False]
    after = env.get_states()
    fresh = env.bank.run(np.array([[0.0, 0.2, 0, 0, 0]]))[-1]
    np.testing.assert_allclose(after[0], fresh)  # row 0 restarted from zero
    assert not np.allclose(after[1], before[1])  # row 1 simply went on

    carry = ReservoirVecEnv(
        DummyVecEnv([lambda: Monitor(ScriptedEnv(space, 2))]), _encoder(reset="never"), seed=0
    )
    carry.reset()
    carry.step(np.array([1]))
    carry.step(np.array([1]))
    assert not np.allclose(carry.get_states()[0], fresh)


def test_skip_connection_layout_and_bounds() -> None:
    space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
    env = ReservoirVecEnv(_venv(space), _encoder(skip_connection=True), seed=0)
    assert env.observation_space.shape == (20 + 2 + 2 + 1,)
    np.testing.assert_array_equal(env.observation_space.low[:20], -1)
    np.testing.assert_array_equal(env.observation_space.low[20:22], -10)  # obs bounds kept
    assert env.observation_space.high[-1] == np.inf
    env.reset()
    obs, _, _, _ = env.step(np.array([[0.5, -1.0]], dtype=np.float32))
    np.testing.assert_allclose(obs[0, 20:22], [0.1, 0.1])
    np.testing.assert_allclose(obs[0, 22:24], [0.5, -1.0])
    assert obs[0, 24] == pytest.approx(0.5)
    assert env.observation_space.contains(obs[0])


def test_exposed_units_and_multiple_reservoirs() -> None:
    config = EncoderConfig(
        reservoirs=(ReservoirParams(units=10, sr=0.5), ReservoirParams(units=10, sr=2.0, lr=0.3)),
        exposed_units=4,
        dtype="float64",
    )
    env = ReservoirVecEnv(_venv(spaces.Discrete(2)), config, seed=0)
    assert env.observation_space.shape == (8,)
    obs = env.reset()
    full = env.get_states()[0]
    np.testing.assert_allclose(obs[0], np.r_[full[:4], full[10:14]].astype(np.float32))
    # each reservoir has its own weights and hyperparameters
    assert env.weight_seeds[0] != env.weight_seeds[1]
    assert env.weights[1].lr == 0.3
    with pytest.raises(ConfigError):
        EncoderConfig(reservoirs=(ReservoirParams(units=10),), exposed_units=11)


def test_reservoir_seeds_are_distinct_and_stable() -> None:
    assert reservoir_seeds(5, 3) == reservoir_seeds(5, 3)
    assert len(set(reservoir_seeds(5, 3))) == 3


def test_float32_encoder_tracks_float64() -> None:
    space = spaces.Box(-2.0, 2.0, shape=(1,), dtype=np.float32)
    actions = np.random.default_rng(0).uniform(-2, 2, size=(30, 2, 1)).astype(np.float32)
    states = {}
    for dtype in ("float64", "float32"):
        env = ReservoirVecEnv(_venv(space, n_envs=2, episode_len=7), _encoder(dtype=dtype), seed=0)
        assert env.bank.M.dtype == np.dtype(dtype) and env.states.dtype == np.dtype(dtype)
        env.reset()
        for a in actions:
            obs, *_ = env.step(a)
        assert obs.dtype == np.float32
        states[dtype] = env.get_states()
    np.testing.assert_allclose(states["float32"], states["float64"], atol=1e-5)
    with pytest.raises(ConfigError):
        _encoder(dtype="float16")


def test_unit_box_fast_path_matches_general_scaling() -> None:
    unit = ActionEncoder(spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32), dtype=np.float32)
    general = ActionEncoder(
        spaces.Box(-1.0, 1.000001, shape=(3,), dtype=np.float32), dtype=np.float32
    )
    assert unit._encode == unit._unit_box and general._encode == general._box
    actions = np.array([[0.5, -2.0, 1.0], [0.0, 0.25, 3.0]], dtype=np.float32)
    a, b = np.zeros((2, 3), np.float32), np.zeros((2, 3), np.float32)
    unit(actions, a)
    general(actions, b)
    np.testing.assert_allclose(a, [[0.5, -1.0, 1.0], [0.0, 0.25, 1.0]])
    np.testing.assert_allclose(a, b, atol=1e-5)
