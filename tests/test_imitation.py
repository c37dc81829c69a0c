"""The ``bc`` and ``dagger`` learners: beta schedules, labels, budgets, save/reload, the CLI."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from ermrl.agents import load_policy, policy_path, resolve_ppo_config
from ermrl.agents._train import NoEpisodeFinished, derive_seeds, make_vec_env, train_agent
from ermrl.config import BudgetConfig, ConfigError, EncoderConfig, ReservoirParams, TaskConfig
from ermrl.experts import load_expert
from ermrl.learners import get_learner
from ermrl.learners._imitation import (
    MIXTURE_EPISODE_KEY,
    FullObservations,
    ImitationPolicy,
    bc_fit,
    beta,
    dagger_rollout,
    scale_actions,
)

PENDULUM = "Pendulum-v1"


def _config(learner: str, expert: Path | str | None, **overrides: object) -> object:
    settings = dict(overrides)
    if expert is not None:
        settings["expert"] = str(expert)
    return resolve_ppo_config(PENDULUM, settings, learner=learner)


# -- beta schedules ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("i", "expected"), [(0, 1.0), (1, 0.75), (2, 0.5), (3, 0.25), (4, 0.0), (9, 0.0)]
)
def test_linear_beta_goes_from_one_to_zero_over_k(i: int, expected: float) -> None:
    assert beta("linear", i, 4) == pytest.approx(expected)


@pytest.mark.parametrize("i", [0, 1, 2, 5, 99])
def test_inverse_beta_is_one_over_one_plus_i(i: int) -> None:
    assert beta("inverse", i, 4) == pytest.approx(1.0 / (1.0 + i))


def test_bad_beta_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="unknown beta schedule"):
        beta("cosine", 0, 4)
    with pytest.raises(ValueError):
        beta("linear", -1, 4)
    with pytest.raises(ValueError):
        beta("linear", 0, 0)


# -- the rollout: who acts, what is labelled --------------------------------------------------


def test_rollout_executes_the_expert_with_probability_beta_and_always_labels_by_the_expert(
    tiny_expert: Path,
) -> None:
    expert = load_expert(tiny_expert)
    task = TaskConfig(PENDULUM, "positions")
    venv = make_vec_env(task, 2, 3)
    try:
        full = FullObservations(venv)
        obs = venv.reset()
        full_obs = full.after_reset()
        assert obs.shape == (2, 2) and full_obs.shape == (2, 3)
        np.testing.assert_allclose(full_obs[:, :2], obs)  # positions are the first two entries
        policy = ImitationPolicy(2, 1, [8])
        rollout = dagger_rollout(
            venv, policy, expert, 0.3, 1000, np.random.default_rng(7), obs, full_obs, full=full
        )
    finally:
        venv.close()
    n = 2000
    # The same draws from the same generator: exactly who acted.
    draws = np.random.default_rng(7).random((1000, 2)).reshape(-1) < 0.3
    np.testing.assert_array_equal(rollout.expert_executed, draws)
    # ... and within a binomial tolerance of beta * steps (4 standard deviations).
    assert abs(rollout.n_expert_executed - 0.3 * n) < 4 * np.sqrt(n * 0.3 * 0.7)
    assert rollout.n_expert_executed + rollout.n_learner_executed == n
    # Every label is the expert's action on that state's full observation, whoever acted.
    np.testing.assert_allclose(
        rollout.expert_actions, expert.predict(rollout.full_observations), atol=1e-5
    )
    np.testing.assert_allclose(rollout.full_observations[:, :2], rollout.observations, atol=1e-6)
    by_expert = rollout.expert_executed
    np.testing.assert_allclose(rollout.actions[by_expert], rollout.expert_actions[by_expert])
    learner_actions = rollout.actions[~by_expert]
    assert not np.allclose(learner_actions, rollout.expert_actions[~by_expert])


def test_rollout_hides_the_episodes_the_expert_acted_in(tiny_expert: Path) -> None:
    """Only episodes whose every executed action was the learner's keep their Monitor record."""
    expert = load_expert(tiny_expert)
    venv = make_vec_env(TaskConfig(PENDULUM, "positions"), 2, 3)
    records: list[tuple[int, str]] = []  # (env, key) of each finished episode, in order

    def on_step(infos: Any, dones: Any, rewards: Any, actions: Any) -> bool:
        for e, info in enumerate(infos):
            for key in ("episode", MIXTURE_EPISODE_KEY):
                if key in info:
                    records.append((e, key))
        return True

    try:
        full = FullObservations(venv)
        obs = venv.reset()
        mixed = np.zeros(2, dtype=bool)
        rollout = dagger_rollout(
            venv, ImitationPolicy(2, 1, [8]), expert, 0.004, 1000, np.random.default_rng(5),
            obs, full.after_reset(), full=full, on_step=on_step, episode_mixed=mixed,
        )  # fmt: skip
    finally:
        venv.close()
    # Pendulum episodes are 200 steps: 5 per env; an episode is mixed iff the expert acted in it
    who = rollout.expert_executed.reshape(1000, 2)
    expected = sorted(
        (e, MIXTURE_EPISODE_KEY if who[200 * k : 200 * (k + 1), e].any() else "episode")
        for k in range(5)
        for e in range(2)
    )
    assert sorted(records) == expected
    keys = {key for _, key in records}
    assert keys == {"episode", MIXTURE_EPISODE_KEY}  # beta 0.004 gives both kinds here
    assert not mixed.any()  # every episode ended: the next ones start learner-only


def test_dagger_training_returns_count_only_learner_only_episodes(tiny_expert: Path) -> None:
    # iteration 0 (steps 1-200, one Pendulum episode) is the expert's alone (beta 1); from
    # iteration 1 on beta is 0: the imitator's episodes end at steps 400 and 600
    ppo = _config("dagger", tiny_expert, steps_per_iteration=200, beta_iterations=1, epochs=1)
    budget = BudgetConfig(training_steps=600, fitness="last", n_last_episodes=10)
    result = train_agent(TaskConfig(PENDULUM), None, ppo, budget, seed=0)
    assert result.episode_steps == [400, 600]
    assert result.last_return == pytest.approx(np.mean(result.episode_returns))


def test_dagger_with_the_expert_acting_throughout_has_no_training_fitness(
    tiny_expert: Path,
) -> None:
    # one iteration, beta 1: every training episode is the expert's, none measures the learner
    ppo = _config("dagger", tiny_expert, steps_per_iteration=600, epochs=1)
    budget = BudgetConfig(training_steps=600, fitness="last")
    with pytest.raises(NoEpisodeFinished, match="none of the 3 episodes .* learner's alone"):
        train_agent(TaskConfig(PENDULUM), None, ppo, budget, seed=0)


def test_dagger_run_counts_expert_executed_steps_per_iteration(tiny_expert: Path) -> None:
    ppo = _config("dagger", tiny_expert, steps_per_iteration=500, beta_iterations=4, epochs=1)
    task = TaskConfig(PENDULUM, "velocities")
    venv = make_vec_env(task, 1, 0)
    try:
        model = get_learner("dagger").build(venv, ppo, seed=0)
        model.learn(2600)
    finally:
        venv.close()
    assert model.num_timesteps == 2600
    steps = [it["steps"] for it in model.iterations]
    assert steps == [500, 500, 500, 500, 500, 100]
    for i, it in enumerate(model.iterations):
        b = beta("linear", i, 4)
        assert it["beta"] == pytest.approx(b)
        assert it["expert_executed"] + it["learner_executed"] == it["steps"]
        sd = np.sqrt(it["steps"] * b * (1 - b))
        assert abs(it["expert_executed"] - b * it["steps"]) <= 4 * sd + 1e-9
    assert model.iterations[0]["expert_executed"] == 500  # beta 1: the expert only
    assert model.iterations[-1]["expert_executed"] == 0  # beta 0 from i = K on
    assert [it["dataset"] for it in model.iterations] == list(np.cumsum(steps))


# -- BC -----------------------------------------------------------------------------------------


def test_bc_fit_regresses_the_mean_onto_the_expert(tiny_expert: Path) -> None:
    expert = load_expert(tiny_expert)
    venv = make_vec_env(TaskConfig(PENDULUM), 1, 0)
    try:
        obs = venv.reset()
        data = dagger_rollout(
            venv,
            None,
            expert,
            1.0,
            2000,
            np.random.default_rng(0),
            obs,
            FullObservations(venv).after_reset(),
        )
        space = venv.action_space
    finally:
        venv.close()
    assert data.n_expert_executed == 2000
    torch.manual_seed(0)
    policy = ImitationPolicy(3, 1, [64, 64])
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    targets = scale_actions(space, data.expert_actions)
    losses = bc_fit(
        policy,
        optimizer,
        data.observations,
        targets,
        60,
        128,
        generator=torch.Generator().manual_seed(0),
    )
    assert losses[-1] < 0.2 * losses[0]
    with torch.no_grad():
        imitated = policy(torch.as_tensor(data.observations)).numpy()
    assert np.mean(np.abs(imitated - targets)) < 0.1  # scaled actions span [-1, 1]


def test_bc_learner_counts_expert_steps_apart(tiny_expert: Path) -> None:
    ppo = _config("bc", tiny_expert, n_expert_transitions=600, epochs=3)
    venv = make_vec_env(TaskConfig(PENDULUM, "positions"), 1, 0)
    try:
        model = get_learner("bc").build(venv, ppo, seed=0)
        model.learn(400)
    finally:
        venv.close()
    assert model.expert_env_steps == 600
    assert model.num_timesteps == 400
    assert model.iterations[0]["dataset"] == 600


# -- through train_agent ------------------------------------------------------------------------


class _Spy:
    """Wraps an expert and records the shapes of the observations it is given."""

    def __init__(self, expert: object) -> None:
        self.expert = expert
        self.shapes: set[tuple[int, ...]] = set()

    def __getattr__(self, name: str) -> object:
        return getattr(self.expert, name)

    def predict(self, obs: np.ndarray, deterministic: bool = True) -> np.ndarray:
        self.shapes.add(np.asarray(obs).shape)
        return self.expert.predict(obs, deterministic)  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    "encoder",
    [None, EncoderConfig(reservoirs=(ReservoirParams(units=20),))],
    ids=["raw", "reservoir"],
)
def test_dagger_through_train_agent(
    tiny_expert: Path,
    encoder: EncoderConfig | None,
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
) -> None:
    import ermrl.learners._dagger_model as model_module

    spies: list[_Spy] = []
    widths: list[int] = []
    real = model_module.load_expert_for

    def spying(env: Any, path: object, learner: str) -> _Spy:
        spy = _Spy(real(env, path, learner))
        spies.append(spy)
        widths.append(int(env.observation_space.shape[0]))
        return spy

    monkeypatch.setattr(model_module, "load_expert_for", spying)
    ppo = _config("dagger", tiny_expert, steps_per_iteration=300, epochs=2)
    task = TaskConfig(PENDULUM, "positions")
    budget = BudgetConfig(training_steps=1000, fitness="eval", n_eval_episodes=1)
    result = train_agent(task, encoder, ppo, budget, seed=1, model_path=tmp_path / "model.zip")
    assert result.env_steps == 1000
    # Pendulum episodes are 200 steps: 5 ended, all with beta > 0, so none is a training episode
    assert result.episode_returns == []
    assert result.eval_return is not None and np.isfinite(result.eval_return)
    assert spies and spies[0].shapes == {(1, 3)}  # the expert sees the full observation
    # the learner sees the masked (2) or encoded (20 units) observation
    assert widths[0] == (2 if encoder is None else 20)
    seeds = derive_seeds(1)
    env = make_vec_env(task, 1, seeds.eval_env, encoder, seeds.reservoir)
    try:
        reloaded = load_policy(policy_path(tmp_path / "model.zip"), ppo, env)
        obs = env.reset()
        trained = np.load(tmp_path / "model.zip", allow_pickle=False)
        assert "config" in trained.files
        for _ in range(5):
            action, _ = reloaded.predict(obs, deterministic=True)
            obs, *_ = env.step(action)
    finally:
        env.close()


def test_save_reload_gives_identical_actions_and_no_pickle(
    tiny_expert: Path, tmp_path: Path
) -> None:
    from ermrl.agents._train import save_trained

    ppo = _config("dagger", tiny_expert, steps_per_iteration=200, epochs=2)
    venv = make_vec_env(TaskConfig(PENDULUM, "positions"), 1, 0)
    try:
        model = get_learner("dagger").build(venv, ppo, seed=0)
        model.learn(400)
        save_trained(model, tmp_path / "model.zip", None)
        reloaded = load_policy(policy_path(tmp_path / "model.zip"), ppo, venv)
    finally:
        venv.close()
    obs = np.random.default_rng(0).uniform(-1, 1, (50, 2)).astype(np.float32)
    np.testing.assert_array_equal(model.predict(obs)[0], reloaded.predict(obs)[0])
    # policy.pt loads with weights_only; model.zip is a plain .npz (no pickled object inside)
    torch.load(policy_path(tmp_path / "model.zip"), weights_only=True)
    with np.load(tmp_path / "model.zip", allow_pickle=False) as npz:
        assert all(npz[name].dtype != object for name in npz.files)
    assert zipfile.is_zipfile(tmp_path / "model.zip")


# -- settings -------------------------------------------------------------------------------------


@pytest.mark.parametrize("learner", ["bc", "dagger"])
def test_missing_expert_is_refused_in_one_line(learner: str) -> None:
    with pytest.raises(ConfigError, match="needs an expert") as err:
        get_learner(learner).check(_config(learner, None))  # type: ignore[arg-type]
    assert "\n" not in str(err.value)


def test_a_folder_without_an_expert_is_refused_in_one_line(tmp_path: Path) -> None:
    ppo = _config("dagger", tmp_path)
    venv = make_vec_env(TaskConfig(PENDULUM), 1, 0)
    try:
        with pytest.raises(ConfigError, match="not an expert folder") as err:
            get_learner("dagger").build(venv, ppo, seed=0)
    finally:
        venv.close()
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("learner", "key", "value", "match"),
    [
        ("dagger", "beta_schedule", "cosine", "beta_schedule must be one of"),
        ("dagger", "beta_iterations", 0, "beta_iterations must be"),
        ("dagger", "steps_per_iteration", 0, "steps_per_iteration must be"),
        ("dagger", "n_expert_transitions", 10, "does not take"),
        ("bc", "n_expert_transitions", 0, "n_expert_transitions must be"),
        ("bc", "hidden_sizes", "big", "hidden_sizes must be"),
        ("bc", "epochs", 0, "epochs must be"),
        ("bc", "n_steps", 64, "does not take"),
    ],
)
def test_bad_settings_are_refused_in_one_line(
    tiny_expert: Path, learner: str, key: str, value: object, match: str
) -> None:
    with pytest.raises(ConfigError, match=match) as err:
        get_learner(learner).check(_config(learner, tiny_expert, **{key: value}))  # type: ignore[arg-type]
    assert "\n" not in str(err.value)


def test_expert_key_is_refused_by_ppo(tiny_expert: Path) -> None:
    with pytest.raises(ConfigError, match="does not take expert"):
        get_learner("ppo").check(resolve_ppo_config(PENDULUM, {"expert": str(tiny_expert)}))


def test_evolve_cli_with_dagger(tiny_expert: Path, tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    argv = [sys.executable, "-m", "ermrl", "evolve", "--env-id", PENDULUM, "--observe", "positions"]
    argv += ["--learner", "dagger", "--n-trials", "2", "--n-seeds", "1", "--training-steps", "400"]
    argv += ["--storage", url, "--study-name", "imitate", "--sampler-seed", "1"]
    # beta 1 over the first 200 steps, then 0: the last Pendulum episode is the imitator's alone
    argv += ["--ppo", f"expert={tiny_expert}", "steps_per_iteration=200", "beta_iterations=1"]
    argv += ["epochs=1"]
    proc = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    import optuna

    study = optuna.load_study(study_name="imitate", storage=url)
    complete = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    assert len(complete) == 2


def test_evolve_cli_without_expert_fails_in_one_line(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    argv = [sys.executable, "-m", "ermrl", "evolve", "--env-id", PENDULUM, "--learner", "dagger"]
    argv += ["--n-trials", "1", "--training-steps", "400", "--storage", url]
    proc = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    assert "needs an expert" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


# -- quality ----------------------------------------------------------------------------------------


@pytest.mark.slow
def test_dagger_imitates_a_good_expert(good_expert: Path) -> None:
    ppo = _config("dagger", good_expert, steps_per_iteration=400, beta_iterations=5)
    budget = BudgetConfig(training_steps=4000, fitness="eval", n_eval_episodes=10)
    result = train_agent(TaskConfig(PENDULUM), None, ppo, budget, seed=0)
    print("dagger eval", result.eval_return, "last", result.last_return)
    assert result.eval_return is not None and result.eval_return > -600  # random: about -1200
