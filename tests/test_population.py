"""The population backend: each agent trains as SB3 PPO would, whatever the population around it."""

from __future__ import annotations

import dataclasses
import io
import warnings
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecNormalize

import ermrl.population._ppo as ppo_module
from ermrl._progress import Progress
from ermrl.agents import (
    derive_seeds,
    frozen_normalize_env,
    load_normalize_stats,
    load_policy,
    make_vec_env,
    policy_path,
    resolve_ppo_config,
    with_overrides,
)
from ermrl.agents._normalize import normalize_env, stats_path
from ermrl.agents._train import RunResult, TrainingDiverged
from ermrl.config import (
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    NormalizeConfig,
    PPOConfig,
    ReservoirParams,
    RTUParams,
    TaskConfig,
)
from ermrl.learners import get_learner
from ermrl.population import (
    Checkpoint,
    PopulationEnvs,
    PopulationJob,
    PopulationPPO,
    check_population_config,
    compute_gae,
    train_population,
)
from ermrl.population._policy import ROW_ALIGN, StackedAdam, StackedPolicy, policy_spec


def encoder(k: int, units: int = 12, **options: Any) -> EncoderConfig:
    """An encoder whose reservoir hyperparameters depend on ``k`` (same structure for all k)."""
    params = ReservoirParams(
        units=units, sr=0.6 + 0.1 * k, lr=0.3 + 0.1 * k, input_scaling=0.5 + 0.2 * k
    )
    return EncoderConfig(reservoirs=(params,), **options)


def rtu_encoder(k: int, units: int = 6, **options: Any) -> EncoderConfig:
    """A frozen RTU layer whose ranges depend on ``k`` (same structure for all k)."""
    params = RTUParams(
        units=units, r_min=0.2, r_max=0.99 - 0.05 * k, theta_max=1.0 + k, input_scaling=0.5 + k
    )
    return EncoderConfig(reservoirs=(params,), **options)


def ppo_for(env_id: str, **overrides: Any) -> PPOConfig:
    return with_overrides(resolve_ppo_config(env_id), overrides)


# -- 1. an agent's result does not depend on the population ------------------------------------
CASES = {
    "cartpole": (
        TaskConfig("CartPole-v1", "positions"),
        {"n_steps": 16, "batch_size": 64, "n_epochs": 2},
        512,
        True,
    ),
    "pendulum-gsde": (
        TaskConfig("Pendulum-v1", "positions"),
        {"n_steps": 64, "batch_size": 64, "n_epochs": 2},
        1024,
        True,
    ),
    "pendulum-normalize": (
        TaskConfig("Pendulum-v1", "positions"),
        {"n_steps": 64, "batch_size": 64, "n_epochs": 2, "normalize": True},
        1024,
        True,
    ),
    "pendulum-raw": (
        TaskConfig("Pendulum-v1", "all"),
        {"n_steps": 64, "batch_size": 64, "n_epochs": 2},
        1024,
        False,
    ),
    "halfcheetah": (
        TaskConfig("HalfCheetah-v5", "velocities"),
        {"n_steps": 256, "batch_size": 64, "n_epochs": 2},
        1024,
        True,
    ),
    # A MuJoCo v4 task with the other mask, episodes ending early (termination), 2 reservoirs.
    "hopper-v4-two-reservoirs": (
        TaskConfig("Hopper-v4", "positions"),
        {"n_steps": 128, "batch_size": 64, "n_epochs": 2},
        512,
        True,
    ),
    # A frozen RTU layer (a linear reservoir; the policy sees tanh of its states).
    "cartpole-rtu": (
        TaskConfig("CartPole-v1", "positions"),
        {"n_steps": 16, "batch_size": 64, "n_epochs": 2},
        512,
        "rtu",
    ),
}


@pytest.mark.parametrize(
    "case",
    CASES,
)
def test_an_agents_result_does_not_depend_on_the_population(case: str) -> None:
    """The same (encoder, seed) alone and at position 5 of 8 gives exactly the same results."""
    task, overrides, steps, with_encoder = CASES[case]
    ppo = ppo_for(task.env_id, **overrides)
    if case == "pendulum-normalize":
        assert ppo.normalize is not None
    budget = BudgetConfig(
        training_steps=steps, fitness="eval", n_eval_episodes=1, n_last_episodes=1
    )

    def make(k: int) -> EncoderConfig | None:
        if not with_encoder:
            return None
        if with_encoder == "rtu":
            return rtu_encoder(k)
        enc = encoder(k)
        if "two-reservoirs" in case:
            second = dataclasses.replace(enc.reservoirs[0], sr=1.5 - 0.1 * k, units=8)
            enc = enc.with_reservoirs((*enc.reservoirs, second))
        return enc

    jobs = [PopulationJob(make(k), 100 + 7 * k) for k in range(8)]
    together = train_population(task, ppo, budget, jobs)
    alone = train_population(task, ppo, budget, [jobs[5]])
    a, b = together[5], alone[0]
    assert isinstance(a, RunResult) and isinstance(b, RunResult)
    assert a.episode_returns, "no episode ended: the comparison would be empty"
    assert a.episode_returns == b.episode_returns
    assert a.episode_steps == b.episode_steps
    assert a.eval_returns == b.eval_returns and len(a.eval_returns) == 1
    # The others trained too, and differently (the comparison is not between clones).
    others = [r for r in together if isinstance(r, RunResult)]
    assert len(others) == 8
    assert len({tuple(r.episode_returns) for r in others}) > 1


def test_an_agents_update_does_not_depend_on_the_population_size() -> None:
    """The same agent updated on the same data alone and at position 5 of 8 ends bitwise equal."""
    task = TaskConfig("Pendulum-v1", "positions")
    ppo = ppo_for("Pendulum-v1", n_steps=64, batch_size=64, n_epochs=2, use_sde=False)
    jobs = [PopulationJob(None, 100 + 7 * k) for k in range(8)]
    big, alone = PopulationPPO(task, ppo, jobs), PopulationPPO(task, ppo, [jobs[5]])
    rng = np.random.default_rng(0)
    T, d = 256, big.envs.policy_dim
    data = [rng.standard_normal((8, T, d)), rng.standard_normal((8, T, 1))]
    data += [rng.standard_normal((8, T)) for _ in range(4)]
    data[3] = -np.abs(data[3]) - 1.0  # log-probabilities
    tensors = [torch.from_numpy(a.astype(np.float32)) for a in data]
    for _ in range(3):
        big.update(0.9, *tensors)
        alone.update(0.9, *[x[5:6].clone() for x in tensors])
    for name, value in big.policy.params.items():
        np.testing.assert_array_equal(
            value.detach()[5].numpy(), alone.policy.params[name].detach()[0].numpy(), err_msg=name
        )


# -- 2. reservoir encodings equal ReservoirVecEnv's ---------------------------------------------
ENCODER_OPTIONS = {
    "default": {},
    "skip-exposed": {"skip_connection": True, "exposed_units": 5},
    "two-reservoirs": {"two": True},
    "reset-never": {"reset": "never"},
    "float64": {"dtype": "float64"},
    # Frozen RTU layers: the linear update, tanh of the states shown to the policy.
    "rtu": {"rtu": True},
    "rtu-two-skip-exposed-float64": {
        "rtu": True,
        "two": True,
        "skip_connection": True,
        "exposed_units": 5,
        "dtype": "float64",
    },
}


def option_encoder(k: int, option: str) -> EncoderConfig:
    options = dict(ENCODER_OPTIONS[option])
    rtu = options.pop("rtu", False)
    two = options.pop("two", False)
    enc = rtu_encoder(k, **options) if rtu else encoder(k, **options)
    if two:
        second: ReservoirParams | RTUParams = (
            RTUParams(units=6, r_max=0.8, theta_max=0.5 + k, input_scaling=2.0)
            if rtu
            else ReservoirParams(units=12, sr=1.1 - 0.1 * k, lr=0.9, input_scaling=1.0 + k)
        )
        enc = dataclasses.replace(enc, reservoirs=(*enc.reservoirs, second))
    return enc


@pytest.mark.parametrize(
    ("option", "env_id"),
    [
        pytest.param(
            option,
            env_id,
        )
        for option in ENCODER_OPTIONS
        for env_id in ("CartPole-v1", "Pendulum-v1")
    ],
)
def test_population_encodings_equal_reservoir_vec_env_over_episode_ends(
    option: str, env_id: str
) -> None:
    """Observations, rewards, dones and terminal encodings equal the SB3 path's, step by step."""
    task = TaskConfig(env_id, "all")
    encoders = [option_encoder(k, option) for k in range(3)]
    env_seeds, res_seeds = [11, 222, 3333], [5, 66, 777]
    pop = PopulationEnvs(task, 2, env_seeds, encoders, res_seeds, None, 0.99)
    venvs = [make_vec_env(task, 2, env_seeds[p], encoders[p], res_seeds[p]) for p in range(3)]
    assert pop.reservoir is not None
    # The encoding of every finished row's last state, just before its reset (all episode ends,
    # terminated ones included, which ``step`` does not return).
    captured: dict[tuple[int, int], np.ndarray] = {}
    reset_rows = pop.reservoir.reset_rows

    def spy(p: int, rows: np.ndarray, obs: np.ndarray) -> None:
        assert pop.reservoir is not None
        enc = pop.reservoir.policy_obs(p, rows)
        for j, i in enumerate(rows):
            captured[(p, int(i))] = enc[j].copy()
        reset_rows(p, rows, obs)

    pop.reservoir.reset_rows = spy  # type: ignore[method-assign]
    try:
        obs = pop.reset()
        for p, venv in enumerate(venvs):
            np.testing.assert_array_equal(obs[p], venv.reset())
        rng = np.random.default_rng(0)
        ends = truncations = 0
        for _ in range(300):
            if pop.discrete:
                actions = rng.integers(0, 2, (3, 2))
            else:
                actions = rng.uniform(-2, 2, (3, 2, 1)).astype(np.float32)
            captured.clear()
            obs, _, raw, dones, terminal, episodes = pop.step(actions)
            assert obs.dtype == np.float32
            for p, venv in enumerate(venvs):
                o, r, d, infos = venv.step(actions[p])
                np.testing.assert_array_equal(obs[p], o)
                np.testing.assert_array_equal(raw[p].astype(np.float32), r)
                np.testing.assert_array_equal(dones[p], d)
                for i in np.flatnonzero(d):
                    ends += 1
                    expected = infos[i]["terminal_observation"]
                    np.testing.assert_array_equal(captured[(p, i)], expected)
                    truncated = bool(infos[i].get("TimeLimit.truncated", False))
                    assert ((p, i) in terminal) == truncated
                    if truncated:
                        truncations += 1
                        np.testing.assert_array_equal(terminal[(p, i)], expected)
            assert len(episodes) == int(dones.sum()) == len(captured)
        assert ends > 0
        if env_id == "Pendulum-v1":
            assert truncations == 6  # every env's 200-step limit
    finally:
        pop.close()
        for venv in venvs:
            venv.close()


# -- 3. the same update as SB3 ------------------------------------------------------------------
SB3_CASES = {
    "pendulum-gsde": ("Pendulum-v1", {"use_sde": True}),
    "pendulum-gauss": ("Pendulum-v1", {"use_sde": False}),
    "cartpole": ("CartPole-v1", {}),  # linear learning rate and clip range schedules
    # The value loss on values clipped around the old ones (constant, then a linear schedule).
    "pendulum-clip-range-vf": ("Pendulum-v1", {"use_sde": False, "clip_range_vf": 0.05}),
    "cartpole-clip-range-vf-schedule": ("CartPole-v1", {"clip_range_vf": "lin_0.05"}),
}


def sb3_rollout(env_id: str, overrides: dict[str, Any]) -> tuple[Any, PPOConfig, TaskConfig]:
    """An SB3 PPO built as training builds it, after one collected rollout (not trained)."""
    task = TaskConfig(env_id, "all")
    ppo = ppo_for(
        env_id,
        n_envs=4,
        n_steps=128,
        batch_size=64,
        n_epochs=40,
        ent_coef=0.01,
        **overrides,
    )
    env = make_vec_env(task, ppo.n_envs, 3, None, 0)
    model = get_learner("ppo").build(env, ppo, seed=4)
    collect_one_rollout(model)
    return model, ppo, task


def flat(a: np.ndarray) -> np.ndarray:
    """SB3's swap_and_flatten: ``(n_steps, n_envs, ...)`` to ``(n_envs * n_steps, ...)``."""
    return np.swapaxes(a, 0, 1).reshape(a.shape[0] * a.shape[1], *a.shape[2:])


@pytest.mark.parametrize("case", list(SB3_CASES))
def test_the_population_update_equals_sb3_ppo_train(case: str) -> None:
    """Agent 0 fed SB3's rollout, weights and minibatches ends with SB3's weights; no leaks."""
    env_id, overrides = SB3_CASES[case]
    torch.set_num_threads(1)
    model, ppo, task = sb3_rollout(env_id, overrides)
    buf = model.rollout_buffer
    T = buf.buffer_size * buf.n_envs
    discrete = env_id == "CartPole-v1"
    data0 = [flat(buf.observations), flat(buf.actions)]
    if discrete:
        data0[1] = data0[1][..., 0].astype(np.int64)
    data0 += [flat(getattr(buf, k)) for k in ("values", "log_probs", "advantages", "returns")]
    np.random.seed(1234)
    perms0 = [np.random.permutation(T) for _ in range(model.n_epochs)]
    start = {k: v.detach().clone() for k, v in model.policy.state_dict().items()}
    np.random.seed(1234)
    model.train()
    rng = np.random.default_rng(9)
    others = [[rng.permutation(T) for _ in range(model.n_epochs)] for _ in range(2)]

    def run(
        first: list[np.ndarray], first_perms: list[np.ndarray], settings: PPOConfig = ppo
    ) -> PopulationPPO:
        jobs = [PopulationJob(None, s) for s in (1, 2, 3)]
        population = PopulationPPO(task, settings, jobs)
        population.policy.load_sb3_state(0, start)
        population.policy.refresh()
        stacked = []
        for j, a in enumerate(first):
            other = data0[j] if j == 1 else data0[j] * 1.5 + 0.1 * (j + 1)
            other2 = data0[j] if j == 1 else data0[j] * 0.5 - 0.2
            stacked.append(torch.from_numpy(np.stack([a, other, other2]).astype(a.dtype)))
        perms = [np.stack([first_perms[e], others[0][e], others[1][e]]) for e in range(len(perms0))]
        population.update(model._current_progress_remaining, *stacked, permutations=perms)
        assert population.n_agents == 3
        return population

    population = run(data0, perms0)
    ours, theirs = population.policy.sb3_state(0), model.policy.state_dict()
    assert set(ours) == set(theirs)
    moved = max(float((theirs[k] - start[k]).abs().max()) for k in ours)
    diff = max(float((ours[k] - theirs[k]).abs().max()) for k in ours)
    print(f"{case}: SB3 weights moved by {moved:.3g}, max |population - SB3| = {diff:.3g}")
    assert moved > 1e-3
    # Not bitwise: SB3 runs nn.Linear (addmm) and clip_grad_norm_ as a norm of per-parameter
    # norms; the population runs baddbmm and one norm over each agent's row of its flat gradient.
    # Last-bit differences grow over the 320 Adam steps to ~1e-6 (measured 0.18e-6 to 0.54e-6);
    # a semantic difference is >1e-3.
    assert diff < 3e-6
    if "clip_range_vf" in overrides:
        # The clipping is engaged: without it, the same data ends far from SB3's weights.
        unclipped = dataclasses.replace(
            ppo, hyperparams={k: v for k, v in ppo.hyperparams.items() if k != "clip_range_vf"}
        )
        other = run(data0, perms0, unclipped).policy.sb3_state(0)
        apart = max(float((other[k] - theirs[k]).abs().max()) for k in other)
        print(f"{case}: without clip_range_vf, max |population - SB3| = {apart:.3g}")
        assert apart > 1e-3
    # Agents 1 and 2 end the same whatever agent 0's data.
    shuffled = [a[::-1].copy() * (1 if j == 1 else 2) for j, a in enumerate(data0)]
    again = run(shuffled, [p[::-1].copy() for p in perms0])
    for name, value in population.policy.params.items():
        np.testing.assert_array_equal(
            value.detach()[1:].numpy(), again.policy.params[name].detach()[1:].numpy()
        )
    assert any(
        not torch.equal(value.detach()[0], again.policy.params[name].detach()[0])
        for name, value in population.policy.params.items()
    )


@pytest.mark.parametrize("use_sde", [False, True])
def test_the_flat_buffer_adam_equals_torch_adam_per_agent(use_sde: bool) -> None:
    """The parameters are views of one flat [P, N] buffer (rows padded to ROW_ALIGN), and
    StackedAdam over it steps each agent as torch.optim.Adam over that agent's own tensors."""
    policy = StackedPolicy(policy_spec({}, 5, 2, False, use_sde), [11, 22, 33])
    flat = policy.flat
    assert flat.is_contiguous() and flat.shape[1] % ROW_ALIGN == 0
    for param in policy.parameters():
        assert param.untyped_storage().data_ptr() == flat.untyped_storage().data_ptr()
    start = {name: p.detach().clone() for name, p in policy.params.items()}
    optimizer = StackedAdam(flat, 3e-4, eps=1e-5)
    gen = torch.Generator().manual_seed(0)
    grads = [[torch.randn(p.shape, generator=gen) for p in policy.parameters()] for _ in range(5)]
    for step in grads:
        buffer = np.zeros((3, policy.row_size), np.float32)
        views = policy.grad_views(buffer)
        for name, g in zip(policy.params, step):
            views[name][...] = g.numpy()
        assert all(np.shares_memory(view, buffer) for view in views.values())
        optimizer.step(torch.from_numpy(buffer))
    used = sum(int(np.prod(shape)) for shape in policy.layout.values())
    assert used < flat.shape[1] and not flat[:, used:].any()  # the padding stays zero
    # The numpy views follow the in-place updates.
    np.testing.assert_array_equal(policy.np["action.w"], policy.params["action.w"].detach().numpy())
    assert not np.array_equal(policy.np["action.w"], start["action.w"].numpy())
    for agent in range(3):
        theirs = [start[name][agent].clone().requires_grad_() for name in policy.params]
        reference = torch.optim.Adam(theirs, lr=3e-4, eps=1e-5, foreach=False)
        for step in grads:
            for p, g in zip(theirs, step):
                p.grad = g[agent].clone()
            reference.step()
        for name, p in zip(policy.params, theirs):
            # Bitwise up to the SIMD tails of torch's per-tensor kernels (a bias of 2 elements).
            np.testing.assert_allclose(
                policy.params[name][agent].detach().numpy(), p.detach().numpy(), rtol=0, atol=1e-7
            )


# -- 3b. the same rollouts, GAE and normalization as SB3 ----------------------------------------
# CartPole cut at 20 steps: a rollout with terminations and truncations.
SHORT_CARTPOLE = "ErmrlTestShortCartPole-v0"


class ReplayedNoise:
    """Stands in for an agent's numpy stream in a rollout: hands back the noise SB3 drew.

    ``normals`` are the standard normal tensors SB3's torch distributions drew, in order (a
    Gaussian action's, or gSDE's exploration matrices); ``skip`` is a shape the population never
    asks for (gSDE's single ``exploration_mat``, which SB3 draws besides the per-env matrices and
    does not use in rollouts). ``choices`` are SB3's categorical actions: with two actions, the
    population's inverse-CDF draw ``u = a`` picks action ``a``.
    """

    def __init__(
        self,
        normals: list[np.ndarray],
        choices: list[np.ndarray],
        skip: tuple[int, ...] | None = None,
    ) -> None:
        self.normals, self.choices, self.skip = list(normals), list(choices), skip

    def standard_normal(self, shape: tuple[int, ...], dtype: Any = np.float64) -> np.ndarray:
        x = self.normals.pop(0)
        while x.shape == self.skip:
            x = self.normals.pop(0)
        assert x.shape == tuple(shape), (x.shape, shape)
        return x.astype(dtype)

    def random(self, n: int) -> np.ndarray:
        u = self.choices.pop(0).reshape(-1).astype(np.float64)
        assert u.shape == (n,)
        return u

    @property
    def unused(self) -> int:
        return len([x for x in self.normals if x.shape != self.skip]) + len(self.choices)


class EpisodeEnds(BaseCallback):
    """Counts SB3's episode ends in a rollout: ``(terminated, truncated)``."""

    def __init__(self) -> None:
        super().__init__()
        self.terminated = self.truncated = 0

    def _on_step(self) -> bool:
        for done, info in zip(self.locals["dones"], self.locals["infos"]):
            if done:
                if info.get("TimeLimit.truncated", False):
                    self.truncated += 1
                else:
                    self.terminated += 1
        return True


BUFFER_FIELDS = ("observations", "actions", "values", "log_probs", "advantages", "returns")


def collect_one_rollout(model: Any, callback: BaseCallback | None = None) -> None:
    """SB3's ``learn`` up to the end of its first ``collect_rollouts`` (no training)."""
    collect_rollouts(model, 1, callback)


def collect_rollouts(
    model: Any, n: int, callback: BaseCallback | None = None
) -> list[dict[str, np.ndarray]]:
    """SB3's ``learn`` for ``n`` rollouts with ``train`` skipped between them; a copy of the
    rollout buffer after each."""
    total = 4 * model.n_steps * model.n_envs  # progress remaining 0.75 after one rollout
    total, callback = model._setup_learn(total, callback)
    callback.on_training_start(locals(), globals())
    fields = (*BUFFER_FIELDS, "rewards", "episode_starts")
    buffers = []
    for _ in range(n):
        assert model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)
        model._update_current_progress_remaining(model.num_timesteps, total)
        buffers.append({k: getattr(model.rollout_buffer, k).copy() for k in fields})
    return buffers


ROLLOUT_CASES = {
    # Pendulum's 200-step limit inside the rollout: truncations, bootstrapped from the last state.
    "pendulum-gauss": ("Pendulum-v1", {"n_steps": 256, "use_sde": False}),
    "pendulum-gauss-normalize": (
        "Pendulum-v1",
        {"n_steps": 256, "use_sde": False, "normalize": True},
    ),
    # gSDE, new matrices every 4 steps. Its noise is a function of the state, so the closed loop
    # amplifies last-bit differences (1e-7 at the first steps, 4e-4 in the observations after 256
    # steps): a shorter rollout, without truncation (the cases above bootstrap).
    "pendulum-gsde": ("Pendulum-v1", {"n_steps": 64}),
    "cartpole-terminations-and-truncations": (SHORT_CARTPOLE, {"n_steps": 96, "batch_size": 64}),
    # The same PPO on reservoir states (the agents' own encoders): an echo state network, and a
    # frozen RTU layer (the policy sees tanh of its linear states), over episode ends.
    "pendulum-gauss-esn-normalize": (
        "Pendulum-v1",
        {"n_steps": 256, "use_sde": False, "normalize": True},
        encoder,
    ),
    "pendulum-gauss-rtu-normalize": (
        "Pendulum-v1",
        {"n_steps": 256, "use_sde": False, "normalize": True},
        rtu_encoder,
    ),
    "cartpole-rtu-terminations-and-truncations": (
        SHORT_CARTPOLE,
        {"n_steps": 96, "batch_size": 64},
        rtu_encoder,
    ),
    # Two rollouts (the update skipped between them): what carries over from one to the next.
    # gSDE draws new matrices at each rollout's start and then every 4 of its steps, counted
    # from that start (30 is not a multiple of 4: a period carried over would draw elsewhere).
    "pendulum-gsde-two-rollouts": ("Pendulum-v1", {"n_steps": 30, "sde_sample_freq": 4}),
    # Episodes of 20 steps cross the rollout boundary: the last observation and episode start
    # carry over; an episode truncated at the boundary is bootstrapped.
    "cartpole-two-rollouts": (SHORT_CARTPOLE, {"n_steps": 30, "batch_size": 30}),
}
# Cases trained for more than one rollout.
ROLLOUTS = {"pendulum-gsde-two-rollouts": 2, "cartpole-two-rollouts": 2}


@pytest.fixture
def short_cartpole(monkeypatch: pytest.MonkeyPatch) -> str:
    """CartPole with a 20-step time limit, registered for one test."""
    spec = gymnasium.envs.registration.EnvSpec(
        SHORT_CARTPOLE,
        entry_point="gymnasium.envs.classic_control.cartpole:CartPoleEnv",
        max_episode_steps=20,
    )
    monkeypatch.setitem(gymnasium.registry, SHORT_CARTPOLE, spec)
    return SHORT_CARTPOLE


@pytest.mark.parametrize("case", list(ROLLOUT_CASES))
def test_a_population_rollout_equals_sb3_collect_rollouts(
    case: str, short_cartpole: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Same env seeds, weights and noise: agent 0's rollout (observations, actions, log-probs,
    values, rewards with the truncation bootstrap, episode starts) and its advantages and returns
    equal SB3's RolloutBuffer after collect_rollouts (with an encoder: on the SB3 path's
    ReservoirVecEnv with the agent's reservoir seed); with several rollouts, each of them."""
    env_id, overrides, *make_encoder = ROLLOUT_CASES[case]
    n_rollouts = ROLLOUTS.get(case, 1)
    torch.set_num_threads(1)
    table_id = "CartPole-v1" if env_id == SHORT_CARTPOLE else env_id
    ppo = ppo_for(table_id, n_envs=2, **overrides)
    task = TaskConfig(env_id, "all")
    encoders = [make_encoder[0](k) if make_encoder else None for k in (0, 1)]
    population = PopulationPPO(
        task, ppo, [PopulationJob(encoders[0], 21), PopulationJob(encoders[1], 22)]
    )
    seeds = population.seeds[0]
    env = normalize_env(
        make_vec_env(task, ppo.n_envs, seeds.env, encoders[0], seeds.reservoir), ppo
    )
    model = get_learner("ppo").build(env, ppo, seed=4)
    env.seed(population.seeds[0].env)  # as train_agent: building seeded the envs with the agent's
    population.policy.load_sb3_state(0, model.policy.state_dict())
    population.policy.refresh()

    # SB3's rollout, recording the noise its torch distributions draw.
    normals: list[np.ndarray] = []
    choices: list[np.ndarray] = []
    draw_normal = torch.distributions.normal._standard_normal
    draw_choice = torch.distributions.Categorical.sample

    def recorded_normal(*args: Any, **kwargs: Any) -> torch.Tensor:
        x = draw_normal(*args, **kwargs)
        normals.append(x.numpy().copy())
        return x

    def recorded_choice(self: Any, *args: Any, **kwargs: Any) -> torch.Tensor:
        x = draw_choice(self, *args, **kwargs)
        choices.append(x.numpy().copy())
        return x

    ends = EpisodeEnds()
    with monkeypatch.context() as m:
        m.setattr(torch.distributions.normal, "_standard_normal", recorded_normal)
        m.setattr(torch.distributions.Categorical, "sample", recorded_choice)
        buffers = collect_rollouts(model, n_rollouts, ends)
    if model.n_steps > 200:
        assert ends.truncated > 0, "no truncation: the bootstrap is not exercised"
    if env_id == SHORT_CARTPOLE:
        assert ends.terminated > 0 and ends.truncated > 0
        assert population.spec.action_dim == 2

    # The population's rollout, agent 0 fed the same noise; the update is skipped.
    skip = tuple(model.policy.log_std.shape) if population.spec.use_sde else None
    replay = ReplayedNoise(normals, choices, skip)
    population.rngs[0] = replay  # type: ignore[call-overload]
    seen: list[dict[str, np.ndarray]] = []  # one per rollout
    gae = ppo_module.compute_gae

    def spy_gae(*args: Any) -> tuple[np.ndarray, np.ndarray]:
        seen.append({"rewards": args[0], "episode_starts": args[2]})
        return gae(*args)

    def spy_train(progress: float, *arrays: np.ndarray) -> None:
        seen[-1].update(zip(BUFFER_FIELDS, arrays))

    monkeypatch.setattr(ppo_module, "compute_gae", spy_gae)
    monkeypatch.setattr(population, "_train", spy_train)
    population.learn(n_rollouts * model.n_steps * model.n_envs)
    assert replay.unused == 0
    assert len(seen) == len(buffers) == n_rollouts

    for i, (ours_all, buf) in enumerate(zip(seen, buffers)):
        diffs = {}
        for key, ours in ours_all.items():
            theirs = buf[key]
            diffs[key] = float(np.abs(ours[0].reshape(theirs.shape) - theirs).max())
        print(
            f"{case} rollout {i}: max |population - SB3| "
            + ", ".join(f"{k} {v:.2g}" for k, v in diffs.items())
        )
        assert diffs["episode_starts"] == 0.0
        if population.discrete:
            assert diffs["actions"] == 0.0
        # Not bitwise: SB3 runs torch, the rollout numpy (last-bit differences in the MLP and the
        # Gaussian log-probability); a semantic difference (a missing bootstrap, a wrong start)
        # is > 1e-2.
        assert max(diffs.values()) < 1e-4
    if n_rollouts > 1:
        # The boundary is crossed mid-episode (a carry-over is exercised, not a fresh start).
        assert not buffers[1]["episode_starts"][0].all()
    population.close()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compute_gae_equals_sb3_rollout_buffer(seed: int) -> None:
    """Random rewards, values and episode ends (a done on the last step too): the population's
    GAE equals RolloutBuffer.compute_returns_and_advantage for each agent."""
    rng = np.random.default_rng(seed)
    P, T, E, gamma, lam = 3, 16, 4, 0.97, 0.9
    rewards = rng.standard_normal((P, T, E)).astype(np.float32)
    values = rng.standard_normal((P, T, E)).astype(np.float32)
    starts = (rng.random((P, T, E)) < 0.2).astype(np.float32)
    starts[:, 0] = 1.0
    last_values = rng.standard_normal((P, E)).astype(np.float32)
    dones = rng.random((P, E)) < 0.5
    dones[:, 0], dones[:, 1] = True, False
    advantages, returns = compute_gae(rewards, values, starts, last_values, dones, gamma, lam)
    box = spaces.Box(-1.0, 1.0, (1,), np.float32)
    for p in range(P):
        buf = RolloutBuffer(T, box, box, gamma=gamma, gae_lambda=lam, n_envs=E)
        for t in range(T):
            buf.add(
                np.zeros((E, 1), np.float32),
                np.zeros((E, 1), np.float32),
                rewards[p, t],
                starts[p, t],
                torch.from_numpy(values[p, t]),
                torch.zeros(E),
            )
        buf.compute_returns_and_advantage(torch.from_numpy(last_values[p]), dones[p])
        # The same float32 operations in the same order: bitwise equal.
        np.testing.assert_array_equal(advantages[p], buf.advantages)
        np.testing.assert_array_equal(returns[p], buf.returns)


@pytest.mark.parametrize(
    ("env_id", "with_encoder", "normalize"),
    [
        ("Pendulum-v1", False, NormalizeConfig()),
        ("Pendulum-v1", True, NormalizeConfig(clip_obs=1.0, clip_reward=0.5)),
        ("CartPole-v1", True, NormalizeConfig(norm_reward=False)),
        ("CartPole-v1", False, NormalizeConfig(norm_obs=False)),
    ],
    ids=["pendulum", "pendulum-reservoir-clipped", "cartpole-reservoir-obs", "cartpole-reward"],
)
def test_per_agent_normalization_equals_sb3_vec_normalize(
    env_id: str, with_encoder: bool, normalize: NormalizeConfig
) -> None:
    """Three agents' normalized observations and rewards and their running statistics (mean,
    variance, count of observations and discounted returns) equal one SB3 VecNormalize each,
    fed the same actions, over episode ends."""
    task = TaskConfig(env_id, "all")
    gamma = 0.95
    encoders = [encoder(k) for k in range(3)] if with_encoder else None
    env_seeds, res_seeds = [11, 222, 3333], [5, 66, 777]
    pop = PopulationEnvs(task, 2, env_seeds, encoders, res_seeds, normalize, gamma)
    venvs = [
        VecNormalize(
            make_vec_env(task, 2, env_seeds[p], encoders[p] if encoders else None, res_seeds[p]),
            norm_obs=normalize.norm_obs,
            norm_reward=normalize.norm_reward,
            clip_obs=normalize.clip_obs,
            clip_reward=normalize.clip_reward,
            gamma=gamma,
            epsilon=normalize.epsilon,
        )
        for p in range(3)
    ]
    worst = {"obs": 0.0, "reward": 0.0, "stats": 0.0}

    def compare_stats() -> None:
        for p, venv in enumerate(venvs):
            pairs: list[tuple[Any, Any]] = [(pop.ret_rms, venv.ret_rms)]
            if normalize.norm_obs:
                pairs.append((pop.obs_rms, venv.obs_rms))
            for ours, theirs in pairs:
                assert ours is not None
                assert ours.count[p] == theirs.count
                for name in ("mean", "var"):
                    diff = np.abs(getattr(ours, name)[p] - getattr(theirs, name)).max()
                    worst["stats"] = max(worst["stats"], float(diff))
            np.testing.assert_allclose(pop.returns[p], venv.returns, atol=1e-6, rtol=0)

    try:
        obs = pop.reset()
        for p, venv in enumerate(venvs):
            worst["obs"] = max(worst["obs"], float(np.abs(obs[p] - venv.reset()).max()))
        rng = np.random.default_rng(0)
        ends = 0
        for _ in range(250):
            if pop.discrete:
                actions = rng.integers(0, 2, (3, 2))
            else:
                actions = rng.uniform(-2, 2, (3, 2, 1)).astype(np.float32)
            obs, rewards, _, dones, _, _ = pop.step(actions)
            ends += int(dones.sum())
            for p, venv in enumerate(venvs):
                o, r, d, _ = venv.step(actions[p])
                np.testing.assert_array_equal(dones[p], d)
                worst["obs"] = max(worst["obs"], float(np.abs(obs[p] - o).max()))
                # As PPO stores them: float32 (VecNormalize casts, the population's learn does).
                ours = rewards[p].astype(np.float32)
                worst["reward"] = max(worst["reward"], float(np.abs(ours - r).max()))
            compare_stats()
        assert ends > 0
        print(f"{env_id}: max |population - VecNormalize| {worst}")
        # float32 batches are averaged in another order (axis 1 of [P, n, d] against axis 0
        # of [n, d]): last-bit differences only; a wrong rule (clip, epsilon, discount, reset
        # of the return) is > 1e-3.
        assert max(worst.values()) < 1e-6
    finally:
        pop.close()
        for venv in venvs:
            venv.close()


# -- 4. a diverged agent is dropped -------------------------------------------------------------
def tiny_pendulum(**extra: Any) -> tuple[TaskConfig, PPOConfig, list[PopulationJob]]:
    task = TaskConfig("Pendulum-v1", "positions")
    ppo = ppo_for("Pendulum-v1", n_steps=64, batch_size=64, n_epochs=2, **extra)
    jobs = [PopulationJob(encoder(k), 40 + k) for k in range(3)]
    return task, ppo, jobs


def test_an_agent_with_nan_weights_is_dropped_and_the_others_are_unaffected() -> None:
    """NaN weights at the start: that job fails with TrainingDiverged, the others train as alone."""
    task, ppo, jobs = tiny_pendulum()
    population = PopulationPPO(task, ppo, jobs)
    population.policy.params["action.w"].data[1] = float("nan")
    population.learn(1024)
    reference = PopulationPPO(task, ppo, [jobs[0], jobs[2]])
    reference.learn(1024)
    assert set(population.failed) == {1}
    assert isinstance(population.failed[1], TrainingDiverged)
    assert population.alive == [0, 2]
    assert population.episodes[1] == []
    assert population.episodes[0] and population.episodes[0] == reference.episodes[0]
    assert population.episodes[2] == reference.episodes[1]
    for name, value in population.policy.params.items():
        np.testing.assert_array_equal(
            value.detach().numpy(), reference.policy.params[name].detach().numpy()
        )


def test_an_agent_diverging_in_an_update_is_dropped_and_the_others_are_unaffected() -> None:
    """NaN in one agent's second update: dropped after it; shared Adam/loss leak nothing."""
    task, ppo, jobs = tiny_pendulum()
    population = PopulationPPO(task, ppo, jobs)
    train, calls = population._train, []

    def poisoned(progress: float, obs: np.ndarray, *rest: np.ndarray) -> np.ndarray | None:
        calls.append(population.n_agents)
        if len(calls) == 2:
            obs = obs.copy()
            obs[1] = np.nan
        return train(progress, obs, *rest)

    population._train = poisoned  # type: ignore[method-assign]
    population.learn(1024)
    assert calls == [3, 3, 2, 2]  # dropped at the end of the poisoned update
    assert set(population.failed) == {1}
    assert isinstance(population.failed[1], TrainingDiverged)
    reference = PopulationPPO(task, ppo, [jobs[0], jobs[2]])
    reference.learn(1024)
    assert population.episodes[0] == reference.episodes[0]
    assert population.episodes[2] == reference.episodes[1]
    for name, value in population.policy.params.items():
        assert torch.isfinite(value).all()
        np.testing.assert_array_equal(
            value.detach().numpy(), reference.policy.params[name].detach().numpy()
        )


def test_train_population_reports_the_diverged_job_and_keeps_the_others() -> None:
    """train_population returns TrainingDiverged for a job whose weights become NaN."""
    task, ppo, jobs = tiny_pendulum()
    budget = BudgetConfig(training_steps=1024, fitness="last", n_last_episodes=1)
    original = PopulationPPO.__init__

    def init(self: PopulationPPO, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **kwargs)
        self.policy.params["vf0.w"].data[2] = float("inf") * 0.0  # NaN

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(PopulationPPO, "__init__", init)
        results = train_population(task, ppo, budget, jobs)
    assert isinstance(results[2], TrainingDiverged)
    assert "seed 42" in str(results[2])
    assert all(isinstance(r, RunResult) for r in results[:2])


def test_a_sigterm_dropped_in_a_weakref_callback_stops_the_population(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The handler's exception raised inside a weakref callback is dropped by Python; the
    training loop raises it again at its next rollout instead of training to the end."""
    import signal
    import sys
    import weakref

    from ermrl._interrupt import Terminated, catch_sigterm, swallowed_signal

    task, ppo, jobs = tiny_pendulum()
    budget = BudgetConfig(training_steps=4096, fitness="last", n_last_episodes=1)
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)  # catch_sigterm sets it
    handler = signal.getsignal(signal.SIGTERM)
    collect = PopulationPPO._collect_rollout
    rollouts = []

    def collect_then_signal(self, *args: Any, **kwargs: Any) -> Any:  # noqa: ANN001
        rollouts.append(self.num_timesteps)
        if len(rollouts) == 1:

            class Owner:
                pass

            owner = Owner()
            ref = weakref.ref(owner, lambda _: signal.raise_signal(signal.SIGTERM))
            del owner  # the callback runs here; Python drops its exception
            assert ref() is None
        return collect(self, *args, **kwargs)

    monkeypatch.setattr(PopulationPPO, "_collect_rollout", collect_then_signal)
    catch_sigterm()
    try:
        with pytest.raises(Terminated):
            train_population(task, ppo, budget, jobs)
    finally:
        signal.signal(signal.SIGTERM, handler)
        swallowed_signal(0)  # forget a signal left noted (when the test fails), for the next tests
    assert len(rollouts) == 1  # stopped before its second rollout, not after 4096 steps


# -- 5. exported agents load and act the same ---------------------------------------------------
@pytest.mark.parametrize("normalize", [False, True], ids=["raw", "normalize"])
def test_exported_agents_load_and_act_as_in_the_population(normalize: bool, tmp_path: Path) -> None:
    """Each exported agent, reloaded from policy.pt on the SB3 env, predicts the same actions."""
    task, ppo, jobs = tiny_pendulum(normalize=normalize)
    population = PopulationPPO(task, ppo, jobs)
    population.learn(512)
    rng = np.random.default_rng(0)
    for pos in range(population.n_agents):
        model_path = tmp_path / f"agent{pos}" / "model.zip"
        model_path.parent.mkdir()
        population.export(pos, model_path)
        assert model_path.is_file() and policy_path(model_path).is_file()
        assert stats_path(model_path).is_file() == normalize
        seeds = derive_seeds(jobs[pos].seed)
        env = make_vec_env(task, 1, seeds.eval_env, jobs[pos].encoder, seeds.reservoir)
        if normalize:
            env = frozen_normalize_env(env, load_normalize_stats(stats_path(model_path)))
        try:
            model = load_policy(policy_path(model_path), ppo, env)
            obs = env.reset()
            for _ in range(30):
                theirs, _ = model.predict(obs, deterministic=True)
                stacked = np.repeat(np.asarray(obs, np.float32)[None], population.n_agents, 0)
                actions, _, _ = population._act(stacked, deterministic=True)
                ours = population._clip(actions)[pos]
                np.testing.assert_allclose(ours, theirs, atol=1e-5, rtol=0)
                obs, _, _, _ = env.step(rng.uniform(-2, 2, (1, 1)).astype(np.float32))
        finally:
            env.close()
    population.close()


def test_export_does_not_warn_about_a_batch_size_it_never_trains_with(tmp_path: Path) -> None:
    """The exported model is built on one env; SB3 warns when n_steps x 1 is not a multiple of
    batch_size, which concerns only training with it (the population trained 4 envs: 192)."""
    task = TaskConfig("Pendulum-v1", "positions")
    ppo = ppo_for("Pendulum-v1", n_steps=48, batch_size=64, n_epochs=1)
    population = PopulationPPO(task, ppo, [PopulationJob(encoder(0), 40)])
    population.learn(192)
    model_path = tmp_path / "model.zip"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        population.export(0, model_path)
    population.close()
    assert model_path.is_file()
    assert not [w for w in caught if "mini-batch" in str(w.message)]


def test_train_population_saves_the_asked_models(tmp_path: Path) -> None:
    """model_paths: a saved model, policy and statistics for each job that asks, none otherwise."""
    task, ppo, jobs = tiny_pendulum(normalize=True)
    budget = BudgetConfig(training_steps=1024, fitness="last", n_last_episodes=1)
    paths = [tmp_path / "a" / "model.zip", None, tmp_path / "c" / "model.zip"]
    for path in paths:
        if path is not None:
            path.parent.mkdir()
    results = train_population(task, ppo, budget, jobs, model_paths=paths)
    assert all(isinstance(r, RunResult) for r in results)
    for path in (paths[0], paths[2]):
        assert path is not None
        assert path.is_file() and policy_path(path).is_file() and stats_path(path).is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "c"]


# -- 6. refusals --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "ppo",
    [
        resolve_ppo_config("Pendulum-v1", learner="lstm-ppo"),
        ppo_for("Pendulum-v1", target_kl=0.01),
        ppo_for("Pendulum-v1", policy_kwargs={"squash_output": True}),
        ppo_for("Pendulum-v1", policy_kwargs={"activation_fn": "relu"}),
    ],
    ids=["lstm-ppo", "target_kl", "policy_kwargs", "activation_fn"],
)
def test_unsupported_settings_are_refused_in_one_line(ppo: PPOConfig) -> None:
    """Another learner, target_kl, an unknown policy_kwargs key or an activation other than
    tanh: a one-line --backend sb3 hint."""
    with pytest.raises((ConfigError, ValueError), match="--backend sb3") as info:
        check_population_config(ppo)
    assert "\n" not in str(info.value)
    with pytest.raises((ConfigError, ValueError), match="--backend sb3"):
        PopulationPPO(TaskConfig("Pendulum-v1"), ppo, [PopulationJob(None, 0)])


def test_tanh_named_as_the_activation_is_accepted() -> None:
    """SB3's default activation, named in policy_kwargs, is what the population backend trains."""
    check_population_config(ppo_for("Pendulum-v1", policy_kwargs={"activation_fn": "tanh"}))


def test_a_progress_total_is_the_steps_whole_rollouts_make() -> None:
    """A budget that is not a whole number of rollouts is rounded up, as SB3 does: a progress
    line's total is what the agents make (Pendulum's zoo rollout is 1024 x 4 envs, so 50k steps
    are 53,248; a line read '53,248/50,000 steps each (100%)')."""
    from ermrl.population import steps_trained

    assert steps_trained(ppo_for("Pendulum-v1"), 50_000) == 53_248
    assert steps_trained(ppo_for("Pendulum-v1"), 4096) == 4096
    task = TaskConfig("Pendulum-v1", "positions")
    ppo = ppo_for("Pendulum-v1", n_steps=48, batch_size=64, n_epochs=1)
    assert ppo.n_envs * 48 == 192
    population = PopulationPPO(task, ppo, [PopulationJob(encoder(0), 40)])
    population.learn(200)
    assert population.num_timesteps == steps_trained(ppo, 200) == 384
    population.close()


# -- 6. checkpoints ---------------------------------------------------------------------------
class StopAfter(Progress):
    """A progress that raises KeyboardInterrupt (a kill) once the agents pass ``steps``."""

    def __init__(self, steps: int) -> None:
        super().__init__("stop", 10**9, mode="none")
        self.stop = steps

    def update(self, done: int) -> None:
        super().update(done)
        if done > self.stop:
            raise KeyboardInterrupt


def checkpoint_population() -> tuple[TaskConfig, PPOConfig, list[PopulationJob]]:
    """Pendulum positions with normalization and gSDE: every kind of state a checkpoint keeps."""
    task = TaskConfig("Pendulum-v1", "positions")
    ppo = ppo_for("Pendulum-v1", n_steps=64, batch_size=64, n_epochs=2, normalize=True)
    assert ppo.normalize is not None and ppo.hyperparams.get("use_sde")
    return task, ppo, [PopulationJob(encoder(k), 50 + k) for k in range(3)]


class KilledAfterSave(Checkpoint):
    """A checkpoint whose training is killed (KeyboardInterrupt) right after its save at
    1024 steps: the live population then holds exactly the state the file holds."""

    def save(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        super().save(meta, arrays)
        if meta["num_timesteps"] >= 1024:
            raise KeyboardInterrupt


def test_a_checkpoint_restores_every_part_of_the_training_state(tmp_path: Path) -> None:
    """Killed right after a save, the live population equals the one restored from the file:
    weights, Adam, normalization, random streams, episodes, steps; resumed, it trains on."""
    task, ppo, jobs = checkpoint_population()
    checkpoint = KilledAfterSave(tmp_path / "c.npz", every=256)
    live = PopulationPPO(task, ppo, jobs)
    with pytest.raises(KeyboardInterrupt):
        live.learn(2048, None, checkpoint)
    saved = checkpoint.load(live.checkpoint_key(2048))
    assert saved is not None and saved[0]["num_timesteps"] == live.num_timesteps == 1024
    back = PopulationPPO(task, ppo, jobs)
    back._restore(*saved)
    assert back.num_timesteps == back.resumed_at == 1024
    np.testing.assert_array_equal(back.policy.flat.numpy(), live.policy.flat.numpy())
    np.testing.assert_array_equal(back.policy.np["pi0.w"], live.policy.np["pi0.w"])  # the views
    for name in ("exp_avg", "exp_avg_sq"):
        np.testing.assert_array_equal(getattr(back.optimizer, name), getattr(live.optimizer, name))
    assert back.optimizer.steps == live.optimizer.steps > 0
    for rms in ("obs_rms", "ret_rms"):
        a, b = getattr(back.envs, rms), getattr(live.envs, rms)
        for part in ("mean", "var", "count"):
            np.testing.assert_array_equal(getattr(a, part), getattr(b, part))
    for a, b in zip(back.rngs, live.rngs):  # the streams draw on as the live ones
        assert a.standard_normal(3).tolist() == b.standard_normal(3).tolist()
    assert back.episodes == live.episodes and any(live.episodes)
    # Resumed, it trains the rest of the budget only, and its episodes go on from the saved ones.
    resumed = PopulationPPO(task, ppo, jobs)
    resumed.learn(2048, None, Checkpoint(checkpoint.path, every=256))
    assert resumed.resumed_at == 1024 and resumed.num_timesteps == 2048
    for before, after in zip(live.episodes, resumed.episodes):
        assert after[: len(before)] == before and len(after) > len(before)
        assert all(t > 1024 for _, t in after[len(before) :])


def test_a_checkpoint_of_another_training_or_a_damaged_one_is_not_resumed(tmp_path: Path) -> None:
    """Other seeds, another budget, or a torn file: the training starts from step 0."""
    task, ppo, jobs = checkpoint_population()
    checkpoint = Checkpoint(tmp_path / "c.npz", every=256)
    with pytest.raises(KeyboardInterrupt):
        PopulationPPO(task, ppo, jobs).learn(1024, StopAfter(256), checkpoint)
    key = PopulationPPO(task, ppo, jobs).checkpoint_key(1024)
    assert checkpoint.load(key) is not None
    assert checkpoint.load(PopulationPPO(task, ppo, jobs).checkpoint_key(2048)) is None
    others = [PopulationJob(job.encoder, job.seed + 1) for job in jobs]
    other = PopulationPPO(task, ppo, others)
    assert checkpoint.load(other.checkpoint_key(1024)) is None
    other.learn(512, None, checkpoint)
    assert other.resumed_at == 0
    checkpoint.path.write_bytes(checkpoint.path.read_bytes()[:100])
    assert checkpoint.load(key) is None


def test_a_checkpoint_saved_by_other_code_is_not_resumed_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The same training saved by other code (another source hash): one line, from step 0."""
    task, ppo, jobs = checkpoint_population()
    checkpoint = Checkpoint(tmp_path / "c.npz", every=256)
    with pytest.raises(KeyboardInterrupt):
        PopulationPPO(task, ppo, jobs).learn(1024, StopAfter(256), checkpoint)
    key = PopulationPPO(task, ppo, jobs).checkpoint_key(1024)
    meta, arrays = checkpoint.load(key)  # type: ignore[misc]
    from ermrl._code import code_identity

    assert meta["code"] == code_identity()
    meta["code"] = {**meta["code"], "source": "0" * 64, "commit": "abcdef1234"}
    checkpoint.save(meta, arrays)
    other = PopulationPPO(task, ppo, jobs)
    other.learn(1024, None, checkpoint)
    assert other.resumed_at == 0 and other.num_timesteps == 1024
    err = capsys.readouterr().err
    assert f"not resumed: {checkpoint.path} was saved by other code" in err
    assert "at abcdef1234" in err and "training from the start" in err


def test_train_population_resumes_and_removes_its_checkpoint(tmp_path: Path) -> None:
    """A killed train_population leaves one checkpoint; the rerun resumes from it, says so,
    returns every job's result over the whole budget, and removes the file."""
    task, ppo, jobs = checkpoint_population()
    budget = BudgetConfig(training_steps=2048, fitness="last", n_last_episodes=1)
    with pytest.raises(KeyboardInterrupt):
        train_population(task, ppo, budget, jobs, progress=StopAfter(1100), checkpoints=tmp_path)
    (saved,) = tmp_path.iterdir()
    assert saved.name.startswith("population-") and saved.suffix == ".npz"
    stream = io.StringIO()
    progress = Progress("again", 2048, mode="lines", stream=stream)
    results = train_population(
        task, ppo, budget, jobs, progress=progress, checkpoints=tmp_path, checkpoint_every=256
    )
    assert f"[again] resumed from {saved} at 1,024 steps each" in stream.getvalue()
    assert all(isinstance(r, RunResult) and r.env_steps == 2048 for r in results)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("case", ["pendulum-gsde", "pendulum-gauss", "cartpole"])
def test_the_population_logs_the_train_scalars_sb3_ppo_logs(case: str) -> None:
    """An update fed SB3's rollout, weights and minibatches logs the train/* values SB3's
    PPO.train records for it (TensorBoard on the population backend shows SB3's curves)."""
    env_id, overrides = SB3_CASES[case]
    torch.set_num_threads(1)
    model, ppo, task = sb3_rollout(env_id, overrides)
    buf = model.rollout_buffer
    T = buf.buffer_size * buf.n_envs
    data = [flat(buf.observations), flat(buf.actions)]
    if env_id == "CartPole-v1":
        data[1] = data[1][..., 0].astype(np.int64)
    data += [flat(getattr(buf, k)) for k in ("values", "log_probs", "advantages", "returns")]
    np.random.seed(1234)
    perms = [np.random.permutation(T)[None] for _ in range(model.n_epochs)]
    start = {k: v.detach().clone() for k, v in model.policy.state_dict().items()}
    np.random.seed(1234)
    model.train()
    theirs = dict(model.logger.name_to_value)
    population = PopulationPPO(task, ppo, [PopulationJob(None, 1)])
    population.policy.load_sb3_state(0, start)
    population.policy.refresh()
    population.policy.loss_terms = []
    progress = model._current_progress_remaining
    population.update(progress, *(torch.from_numpy(a[None]) for a in data), permutations=perms)
    ours = population._train_scalars(progress, data[2][None], data[5][None])
    names = [
        "policy_gradient_loss", "value_loss", "entropy_loss", "clip_fraction", "approx_kl",
        "loss", "explained_variance", "learning_rate", "clip_range",
    ]  # fmt: skip
    if env_id != "CartPole-v1":
        names.append("std")
    for name in names:
        assert ours[name][0] == pytest.approx(theirs[f"train/{name}"], rel=1e-3, abs=1e-5), name


def test_population_runs_write_tensorboard_scalars_without_changing_their_training(
    tmp_path: Path,
) -> None:
    """Each run's folder gets SB3's scalars (read back with TensorBoard's reader); a run
    without a folder logs nothing, and logging leaves the results bit for bit the same."""
    pytest.importorskip("tensorboard", reason="TensorBoard logs need the tensorboard package")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    task = TaskConfig("CartPole-v1", "all")
    ppo = ppo_for("CartPole-v1", n_envs=1, n_steps=64, batch_size=32, n_epochs=2)
    budget = BudgetConfig(training_steps=512, fitness="last", n_last_episodes=5)
    jobs = [PopulationJob(None, 1), PopulationJob(None, 2)]
    logged = train_population(task, ppo, budget, jobs, tensorboard_logs=[tmp_path / "a", None])
    plain = train_population(task, ppo, budget, jobs)
    for a, b in zip(logged, plain):
        assert isinstance(a, RunResult) and isinstance(b, RunResult)
        assert a.episode_returns == b.episode_returns
    (events,) = (tmp_path / "a").rglob("events.out.tfevents.*")
    assert events.parent.name == "PPO_1"  # SB3's layout of tensorboard_log
    acc = EventAccumulator(str(events))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"rollout/ep_rew_mean", "rollout/ep_len_mean", "time/fps", "train/loss"} <= tags
    assert {"train/value_loss", "train/approx_kl", "train/explained_variance"} <= tags
    rewards = acc.Scalars("rollout/ep_rew_mean")
    assert [e.step for e in acc.Scalars("time/fps")] == list(range(64, 513, 64))
    result = logged[0]
    assert isinstance(result, RunResult)
    assert rewards[-1].value == pytest.approx(np.mean(result.episode_returns[-100:]), rel=1e-6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]
