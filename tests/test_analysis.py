"""ermrl.analysis without training: statistics, grids, spectra, study tables and figures."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import optuna
import pandas as pd
import pytest
from matplotlib.figure import Figure
from matplotlib.text import Text
from scipy import stats

import ermrl.analysis as analysis
from ermrl.analysis import (
    DynamicsRecording,
    GLBackendError,
    PaperFigure,
    aggregate_iqm,
    bootstrap_mean_diff_ci,
    compare_agents,
    curves_on_grid,
    dominant_frequency,
    dynamics_figure,
    few_seeds_flag,
    final_returns_figure,
    final_returns_table,
    generations_figure,
    generations_frame,
    iqm,
    is_generalization_study,
    learning_curves_figure,
    notebook_parameters,
    optimization_history_figure,
    param_contour_figure,
    param_importances,
    param_importances_figure,
    param_slices_figure,
    power_spectrum,
    spectrum_figure,
    spectrum_summary,
    study_overview,
    summarize,
    task_scores_figure,
    task_scores_frame,
    task_seed_scores,
    trials_frame,
    welch_t_test,
    write_gif,
    write_mp4,
)
from ermrl.config import (
    BudgetConfig,
    EncoderConfig,
    EvolveConfig,
    PPOConfig,
    Problem,
    ReservoirSpace,
    SearchConfig,
    TaskConfig,
    to_dict,
)
from tests._analysis_data import assert_self_contained_html

optuna.logging.set_verbosity(optuna.logging.WARNING)
AGENTS = ("ppo", "res-ppo", "random-res-ppo")


# -- helpers -----------------------------------------------------------------------------------


def _texts(fig: Figure) -> list[Text]:
    return [t for t in fig.findobj(Text) if t.get_text().strip() and t.get_visible()]


def assert_paper_ready(fig: Figure, *labels: str) -> None:
    """Every visible text is >= 9 pt and the figure renders as PNG with the expected labels."""
    assert isinstance(fig, PaperFigure)
    png = fig._repr_png_()  # draws the figure: tick labels exist only after a draw
    assert png.startswith(b"\x89PNG")
    texts = _texts(fig)
    small = [(t.get_text(), t.get_fontsize()) for t in texts if t.get_fontsize() < 9]
    assert not small, f"text below 9 pt: {small}"
    joined = "\n".join(t.get_text() for t in texts)
    for label in labels:
        assert label in joined, f"{label!r} not in the figure's texts"


def fake_results() -> pd.DataFrame:
    rng = np.random.default_rng(0)
    rows = []
    for offset, agent in zip((0.0, 50.0, 10.0), AGENTS):
        for seed in range(5):
            rows.append(
                {
                    "agent": agent,
                    "seed": 10 + seed,
                    "final_return": 100 + offset + rng.normal(0, 5),
                    "eval_return": None,
                }
            )
    return pd.DataFrame(rows)


def fake_curves() -> pd.DataFrame:
    rows = []
    for agent in AGENTS:
        for seed in range(3):
            for k in range(1, 21):
                rows.append(
                    {
                        "agent": agent,
                        "seed": seed,
                        "env_step": 1000 * k + seed,
                        "episode_return": k * (2 + AGENTS.index(agent)) + seed,
                    }
                )
    return pd.DataFrame(rows)


def make_study(n_trials: int = 12, *, generalization: bool = False) -> optuna.Study:
    """An in-memory study shaped like an ermrl one, with synthetic trials."""
    config = EvolveConfig(
        problem=Problem(
            task=TaskConfig("HalfCheetah-v5", "velocities"),
            encoder=EncoderConfig(),
            ppo=PPOConfig(),
            budget=BudgetConfig(training_steps=1000),
            seeds=(0,),
        ),
        space=ReservoirSpace(units=20),
        search=SearchConfig(n_trials=n_trials),
    )
    study = optuna.create_study(direction="maximize", study_name="fake")
    study.set_user_attr("ermrl_config", to_dict(config))
    study.set_user_attr("ermrl_kind", "evolve-generalization" if generalization else "evolve")
    dists = {
        name: optuna.distributions.FloatDistribution(r.low, r.high, log=r.log)
        for name, r in config.space.ranges().items()
    }
    rng = np.random.default_rng(1)
    for k in range(n_trials):
        params = {
            "sr": float(10 ** rng.uniform(-4, 2)),
            "lr": float(10 ** rng.uniform(-2, 0)),
            "input_scaling": float(10 ** rng.uniform(-1, 1)),
        }
        value = -abs(math.log10(params["sr"])) * 10 + params["lr"] + rng.normal()
        attrs = {}
        if generalization:
            attrs = {
                "task_normalized": {"HalfCheetah-v5": value / 10, "Ant-v5": value / 20},
                "task_returns": {"HalfCheetah-v5": value * 10, "Ant-v5": value * 5},
                # two seeds around each mean; references 0 and 100 give the normalized scores
                "task_seed_returns": {
                    "HalfCheetah-v5": [value * 10 - 1, value * 10 + 1],
                    "Ant-v5": [value * 5 - 2, value * 5 + 2],
                },
                "task_random_returns": {"HalfCheetah-v5": 0.0, "Ant-v5": 0.0},
                "task_target_returns": {"HalfCheetah-v5": 100.0, "Ant-v5": 100.0},
            }
        state = optuna.trial.TrialState.FAIL if k == 3 else optuna.trial.TrialState.COMPLETE
        study.add_trial(
            optuna.trial.create_trial(
                params=params,
                distributions=dists,
                value=value if state == optuna.trial.TrialState.COMPLETE else None,
                state=state,
                user_attrs=attrs,
            )
        )
    return study


# -- statistics --------------------------------------------------------------------------------


def test_welch_matches_the_formula_and_is_nan_when_undefined() -> None:
    a, b = [1.0, 2.0, 3.0, 4.0], [2.0, 4.0, 6.0]
    result = welch_t_test(a, b)
    va, vb = np.var(a, ddof=1) / 4, np.var(b, ddof=1) / 3
    assert result.statistic == pytest.approx((np.mean(a) - np.mean(b)) / math.sqrt(va + vb))
    assert result.dof == pytest.approx((va + vb) ** 2 / (va**2 / 3 + vb**2 / 2))
    assert 0 < result.p_value < 1
    assert math.isnan(welch_t_test([1.0], [2.0, 3.0]).p_value)
    assert math.isnan(welch_t_test([1.0, 1.0], [2.0, 2.0]).statistic)
    # Welch's interval: mean difference +- t(dof) * standard error.
    half = stats.t.ppf(0.975, result.dof) * math.sqrt(va + vb)
    diff = np.mean(a) - np.mean(b)
    assert (result.ci_low, result.ci_high) == pytest.approx((diff - half, diff + half))
    wide = welch_t_test(a, b, confidence=0.99)
    assert wide.ci_low < result.ci_low and wide.ci_high > result.ci_high


def test_welch_against_a_group_at_its_ceiling_is_exact_and_silent() -> None:
    """Every seed of one agent at the task's ceiling (ppo-full's 500 on CartPole): its variance is
    0, the other group's carries the test, and nothing warns of precision loss."""
    ceiling, other = [500.0] * 5, [500.0, 500.0, 447.9, 500.0, 500.0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = welch_t_test(other, ceiling)
    se = math.sqrt(np.var(other, ddof=1) / 5)
    assert result.statistic == pytest.approx((np.mean(other) - 500.0) / se)
    assert result.dof == pytest.approx(4.0)
    half = stats.t.ppf(0.975, 4.0) * se
    assert (result.ci_low, result.ci_high) == pytest.approx((-10.42 - half, -10.42 + half))


def test_two_seeds_are_flagged_and_welch_is_wider_than_the_bootstrap() -> None:
    """On 2 seeds the percentile bootstrap can exclude 0 where Welch's t interval does not."""
    data = pd.DataFrame(
        {"agent": ["res-ppo"] * 2 + ["ppo"] * 2, "seed": [0, 1, 0, 1],
         "final_return": [-700.0, -698.0, -690.0, -676.0]}
    )  # fmt: skip
    row = compare_agents(data, "res-ppo", ["ppo"]).iloc[0]
    assert bool(row["few_seeds"])
    assert row["boot_ci_high"] < 0 < row["welch_ci_high"]
    assert row["welch_ci_low"] < row["boot_ci_low"]
    five = compare_agents(fake_results(), "res-ppo", ["ppo"]).iloc[0]
    assert not bool(five["few_seeds"])


def test_bootstrap_ci_is_reproducible_and_covers_the_difference() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(10, 1, 30), rng.normal(0, 1, 30)
    low, high = bootstrap_mean_diff_ci(a, b, seed=3)
    assert (low, high) == bootstrap_mean_diff_ci(a, b, seed=3)
    assert low < a.mean() - b.mean() < high
    assert 8 < low and high < 12
    assert all(math.isnan(v) for v in bootstrap_mean_diff_ci([], [1.0]))


def test_final_returns_table_and_comparison() -> None:
    results = fake_results()
    table = final_returns_table(results, list(AGENTS))
    assert list(table["agent"]) == list(AGENTS)
    assert (table["n_seeds"] == 5).all()
    row = table.set_index("agent").loc["res-ppo"]
    assert row["ci95_low"] < row["mean"] < row["ci95_high"]
    comparison = compare_agents(results, "res-ppo", ["ppo", "random-res-ppo", "missing"])
    assert list(comparison["baseline"]) == ["ppo", "random-res-ppo"]
    vs_ppo = comparison.set_index("baseline").loc["ppo"]
    assert vs_ppo["mean_diff"] == pytest.approx(50, abs=10)
    assert vs_ppo["boot_ci_low"] > 0 and vs_ppo["p_value"] < 0.001


def test_few_seeds_flag_names_the_smallest_group() -> None:
    assert few_seeds_flag(2, 7) == "few seeds (n=2 < 5)"
    assert few_seeds_flag(5, 5) == few_seeds_flag() == ""


def test_iqm_is_the_25_percent_trimmed_mean() -> None:
    x = np.random.default_rng(0).normal(size=(7, 3))
    assert iqm(x) == pytest.approx(stats.trim_mean(x.ravel(), 0.25))
    assert iqm([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 1000.0]) == pytest.approx(3.5)
    assert iqm([1.0, np.nan, 3.0]) == 2.0
    assert math.isnan(iqm([]))


def test_aggregate_iqm_ci_covers_the_estimate_and_takes_every_layout() -> None:
    rng = np.random.default_rng(0)
    scores = rng.normal(size=(10, 4)) + np.array([0.0, 1.0, 2.0, 3.0])  # (n_runs, n_tasks)
    result = aggregate_iqm(scores, seed=1)
    assert result.iqm == pytest.approx(stats.trim_mean(scores.ravel(), 0.25))
    assert result.ci_low < result.iqm < result.ci_high
    assert (result.n_tasks, result.n_runs, result.few_seeds) == (4, 10, False)
    assert result == aggregate_iqm(scores, seed=1)  # reproducible
    by_task = {f"t{k}": scores[:, k] for k in range(4)}
    assert aggregate_iqm(by_task, seed=1) == result
    assert aggregate_iqm(list(scores.T), seed=1) == result
    ragged = aggregate_iqm({"a": [1.0, 2.0, np.nan], "b": [3.0, 4.0, 5.0], "c": [np.nan]})
    assert (ragged.n_tasks, ragged.n_runs, ragged.few_seeds) == (2, 2, True)
    assert ragged.ci_low <= ragged.iqm <= ragged.ci_high
    empty = aggregate_iqm({})
    assert empty.n_tasks == 0 and math.isnan(empty.iqm)


def test_aggregate_iqm_resamples_within_each_task() -> None:
    """Each resample keeps every task's share: with a constant score per task, the stratified
    IQM never moves, where a bootstrap of the pooled scores would."""
    result = aggregate_iqm({"a": [0.0] * 4, "b": [1.0] * 4}, n_resamples=2000)
    assert result.iqm == result.ci_low == result.ci_high == 0.5
    pooled = np.array([0.0] * 4 + [1.0] * 4)
    rng = np.random.default_rng(0)
    unstratified = stats.trim_mean(pooled[rng.integers(0, 8, size=(2000, 8))], 0.25, axis=1)
    assert unstratified.min() < 0.5 < unstratified.max()


def test_summarize_uses_the_sample_std() -> None:
    results = fake_results()
    summary = summarize(results, list(AGENTS)).set_index("agent")
    values = results.loc[results["agent"] == "ppo", "final_return"]
    assert summary.loc["ppo", "final_return_std"] == pytest.approx(values.std(ddof=1))


def test_curves_on_grid_has_ci_columns() -> None:
    grid = curves_on_grid(fake_curves(), n_points=20, smooth_episodes=1)
    assert {"mean", "std", "sem", "ci95", "n_seeds"} <= set(grid.columns)
    last = grid[grid["agent"] == "ppo"].iloc[-1]
    assert last["n_seeds"] == 3
    # Seeds differ by 1 return unit: std 1, sem 1/sqrt(3), t(0.975, 2) = 4.303.
    assert last["std"] == pytest.approx(1.0)
    assert last["ci95"] == pytest.approx(4.3027 / math.sqrt(3), rel=1e-3)
    one = curves_on_grid(fake_curves().query("seed == 0"), n_points=5)
    assert one["ci95"].isna().all() and (one["std"] == 0).all()


# -- figures -----------------------------------------------------------------------------------


@pytest.mark.parametrize("band", ["std", "ci95", "none"])
def test_learning_curves_figure(band: str) -> None:
    grid = curves_on_grid(fake_curves(), n_points=30)
    fig = learning_curves_figure(grid, title="HalfCheetah-v5, velocities only", band=band)  # type: ignore[arg-type]
    assert_paper_ready(fig, "Environment steps", "Episode return", "RES-PPO (evolved reservoir)")


def test_plot_learning_curves_keeps_its_signature(tmp_path: Path) -> None:
    path = analysis.plot_learning_curves(
        curves_on_grid(fake_curves()), tmp_path / "c.png", title="t", agents=list(AGENTS)
    )
    assert path.read_bytes().startswith(b"\x89PNG")


def test_final_returns_figure() -> None:
    fig = final_returns_figure(fake_results(), agents=list(AGENTS), title="Env")
    assert_paper_ready(fig, "Final return", "PPO", "mean")


def test_study_tables_and_figures() -> None:
    study = make_study()
    overview = study_overview(study)
    assert overview.counts["COMPLETE"] == 11 and overview.counts["FAIL"] == 1
    assert overview.env_id == "HalfCheetah-v5" and overview.best_number is not None
    frame = trials_frame(study)
    assert {"number", "state", "value", "sr", "lr", "input_scaling", "generation"} <= set(frame)
    importances = param_importances(study)
    assert set(importances) == {"sr", "lr", "input_scaling"}
    assert sum(importances.values()) == pytest.approx(1.0)
    ranges = analysis.param_ranges(study, analysis.study_config_or_none(study))
    assert ranges["sr"] == (1e-4, 1e2, True)
    assert_paper_ready(optimization_history_figure(frame, title="t"), "Trial number", "best so far")
    assert_paper_ready(param_importances_figure(importances), "Spectral radius sr")
    assert_paper_ready(
        param_slices_figure(frame, ["sr", "lr", "input_scaling"], ranges=ranges),
        "Leak rate lr (log scale)",
        "Trial number",
    )
    assert_paper_ready(
        param_contour_figure(frame, "lr", "sr", ranges=ranges), "Spectral radius sr (log scale)"
    )
    # No CMA-ES generations in a synthetic study: the figure says so instead of failing.
    assert_paper_ready(generations_figure(generations_frame(study)), "no trial was sampled")


def test_figures_of_an_empty_study_say_why() -> None:
    study = optuna.create_study(direction="maximize")
    frame = trials_frame(study)
    assert param_importances(study) == {}
    assert_paper_ready(optimization_history_figure(frame), "no COMPLETE trial yet")
    assert_paper_ready(param_importances_figure({}), "at least 2 COMPLETE trials")


def test_task_seed_scores_are_normalized_like_the_fitness() -> None:
    trial = make_study(3, generalization=True).trials[0]
    scores = task_seed_scores(trial.user_attrs)
    assert set(scores) == {"HalfCheetah-v5", "Ant-v5"}
    for env_id, values in scores.items():
        assert values.shape == (2,)
        assert values.mean() == pytest.approx(trial.user_attrs["task_normalized"][env_id])
    assert task_seed_scores({"task_normalized": {"Ant-v5": 0.5}}) == {}


def test_generalization_scores() -> None:
    single = make_study(4)
    assert not is_generalization_study(single)
    assert task_scores_frame(single).empty
    assert_paper_ready(task_scores_figure(task_scores_frame(single)), "single-task study")
    multi = make_study(6, generalization=True)
    assert is_generalization_study(multi)
    scores = task_scores_frame(multi)
    assert set(scores["env_id"]) == {"HalfCheetah-v5", "Ant-v5"}
    assert len(scores) == 12
    assert_paper_ready(task_scores_figure(scores, title="g"), "Normalized score", "Ant-v5")


# -- dynamics ------------------------------------------------------------------------------------


def synthetic_recording(n: int = 600, dt: float = 0.05, hz: float = 2.0) -> DynamicsRecording:
    t = np.arange(n) * dt
    wave = np.sin(2 * np.pi * hz * t)
    transient = np.exp(-t / 1.5)
    states = np.stack([0.3 * wave * (k % 3 + 1) + transient for k in range(25)], axis=1)
    return DynamicsRecording(
        observations=np.stack([wave, 2 * wave + transient], axis=1),
        actions=np.stack([0.5 * wave], axis=1),
        rewards=np.ones(n),
        states=np.tanh(states),
        dt=dt,
        env_id="HalfCheetah-v5",
        observe="velocities",
        agent="res-ppo",
        seed=10,
        obs_indices=np.array([8, 9]),
    )


def test_dominant_frequency_ignores_the_transient() -> None:
    rec = synthetic_recording()
    freqs, power = power_spectrum(rec.states, rec.dt)
    assert freqs[-1] == pytest.approx(10.0)  # Nyquist of dt = 0.05 s
    assert dominant_frequency(freqs, power) == pytest.approx(2.0, abs=0.1)
    summary = spectrum_summary(rec)
    assert summary["frequency_unit"] == "Hz"
    for info in summary["signals"].values():
        assert info["dominant_frequency"] == pytest.approx(2.0, abs=0.1)
        assert info["dominant_period"] == pytest.approx(0.5, abs=0.03)
    assert math.isnan(dominant_frequency(*power_spectrum(np.ones((100, 2)))))


def test_recording_round_trip_and_figures(tmp_path: Path) -> None:
    rec = synthetic_recording()
    back = DynamicsRecording.load(rec.save(tmp_path / "episode.npz"))
    np.testing.assert_array_equal(back.states, rec.states)
    assert (back.agent, back.seed, back.dt, back.env_id) == ("res-ppo", 10, 0.05, "HalfCheetah-v5")
    assert_paper_ready(dynamics_figure(rec), "Time (s)", "Reservoir unit", "obs[8]")
    assert_paper_ready(spectrum_figure(rec), "Frequency (Hz)", "peak 2.03 Hz")


def test_replay_normalizes_like_training(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run trained with ``normalize`` replays with training's final statistics, frozen."""
    from stable_baselines3 import PPO

    import ermrl.agents._normalize as normalize_module
    from ermrl.config import NormalizeConfig, ReservoirParams
    from ermrl.test_phase import AgentSpec, TestSettings, run_comparison

    saved: list = []  # the training VecNormalize, as training left it
    save = normalize_module.save_normalize_stats

    def keep(venv, path):  # noqa: ANN001, ANN202
        saved.append(venv)
        save(venv, path)

    monkeypatch.setattr(normalize_module, "save_normalize_stats", keep)
    task = TaskConfig("Pendulum-v1", "positions")
    reservoirs = (ReservoirParams(units=20, sr=0.9, lr=0.5),)
    ppo = PPOConfig(
        hyperparams={"n_steps": 128, "batch_size": 64, "n_epochs": 2},
        normalize=NormalizeConfig(),
    )
    run_comparison(
        task,
        EncoderConfig(reservoirs=reservoirs),
        ppo,
        [AgentSpec("res-ppo", reservoirs)],
        TestSettings(training_steps=512, seeds=(3,), out=tmp_path),
        quiet=True,
    )
    assert len(saved) == 1 and (tmp_path / "agents/res-ppo/seed_3/vecnormalize.json").is_file()

    seen: list[np.ndarray] = []  # what the replayed policy is given
    predict = PPO.predict

    def spy(self, observation, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        seen.append(np.array(observation, copy=True))
        return predict(self, observation, *args, **kwargs)

    monkeypatch.setattr(PPO, "predict", spy)
    trained = analysis.load_trained_agent(tmp_path, "res-ppo", 3)
    episode = analysis.rollout(trained, max_steps=5)
    assert len(seen) == 5
    for state, given in zip(episode.states, seen):
        expected = saved[0].normalize_obs(state[None].astype(np.float32))
        np.testing.assert_array_equal(given, expected)  # exactly what training would give
        assert not np.allclose(given, state)  # and not the raw states
    assert np.all(episode.rewards < 0)  # raw Pendulum rewards, not normalized ones

    (tmp_path / "agents/res-ppo/seed_3/vecnormalize.json").unlink()
    with pytest.raises(FileNotFoundError, match="trained with normalize"):
        analysis.load_trained_agent(tmp_path, "res-ppo", 3)


# -- notebooks, video helpers ------------------------------------------------------------------


def test_notebook_parameters_are_overridden_by_the_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for var in ("ERMRL_STUDY_NAME", "ERMRL_STORAGE", "ERMRL_RUNS"):
        monkeypatch.delenv(var, raising=False)
    assert notebook_parameters("s", "sqlite:///a.db") == ("s", "sqlite:///a.db", "runs/s")
    monkeypatch.setenv("ERMRL_STUDY_NAME", "other")
    monkeypatch.setenv("ERMRL_RUNS", "/x/runs")
    assert notebook_parameters("s", "sqlite:///a.db", "r") == ("other", "sqlite:///a.db", "/x/runs")


def test_no_gl_backend_error_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    from ermrl.analysis import _video

    monkeypatch.setattr(_video, "_selected", None)
    monkeypatch.setattr(_video, "_opengl_loaded", lambda: False)
    monkeypatch.setattr(_video, "_probe", lambda backend, timeout: (False, f"{backend} broken"))
    with pytest.raises(GLBackendError) as err:
        _video.select_gl_backend(candidates=["egl", "osmesa"])
    message = str(err.value)
    assert "egl: egl broken" in message and "osmesa: osmesa broken" in message
    assert "apt-get install" in message and "libosmesa6" in message
    with pytest.raises(ValueError, match="unknown GL backend"):
        _video.select_gl_backend("vulkan")


def test_mp4_and_gif_writers_round_trip(tmp_path: Path) -> None:
    import imageio.v2 as imageio

    frames = [np.full((64, 96, 3), 20 * k, dtype=np.uint8) for k in range(10)]
    mp4 = write_mp4(frames, tmp_path / "clip.mp4", fps=20)
    reader = imageio.get_reader(str(mp4))
    read = [frame for frame in reader]
    reader.close()
    assert len(read) == 10 and read[0].shape == (64, 96, 3)
    gif = write_gif(frames, tmp_path / "clip.gif", fps=20)
    assert imageio.mimread(str(gif))[0].shape[:2] == (32, 48)


# -- report without training -------------------------------------------------------------------


def _copy_to_sqlite(study: optuna.Study, storage: str, name: str) -> None:
    target = optuna.create_study(storage=storage, study_name=name, direction="maximize")
    for key, value in study.user_attrs.items():
        target.set_user_attr(key, value)
    target.add_trials(study.get_trials())


def test_report_of_a_generalization_study(tmp_path: Path) -> None:
    storage = f"sqlite:///{tmp_path / 'g.db'}"
    _copy_to_sqlite(make_study(8, generalization=True), storage, "gen")
    result = analysis.write_report(
        "gen", storage, runs=tmp_path / "none", out=tmp_path / "r", interactive=False
    )
    md = result.markdown.read_text()
    assert "## Generalization" in md and "Ant-v5" in md
    assert "interquartile mean (IQM)" in md and "95% stratified bootstrap CI [" in md
    assert "Few seeds (n=2 < 5)" in md  # two seeds per task
    assert result.figures["task_scores"].read_bytes().startswith(b"\x89PNG")
    assert (tmp_path / "r" / "generalization" / "task_scores.csv").exists()


def test_report_html_embeds_its_figures_and_opens_when_moved(tmp_path: Path) -> None:
    storage = f"sqlite:///{tmp_path / 'g.db'}"
    _copy_to_sqlite(make_study(8, generalization=True), storage, "gen")
    result = analysis.write_report(
        "gen", storage, runs=tmp_path / "none", out=tmp_path / "r", interactive=True
    )
    assert result.html is not None
    text = assert_self_contained_html(result.html, tmp_path / "elsewhere")
    assert text.count("<img ") == len(result.figures)  # evolution and generalization figures
    assert "<h2>Evolution</h2>" in text and "<h2>Generalization</h2>" in text
    assert "<code>interactive/" in text  # the interactive files are named, not linked
    md = result.markdown.read_text()
    assert "](evolution/optimization_history.png)" in md  # the Markdown still links its files


def test_report_of_a_study_without_trials(tmp_path: Path) -> None:
    storage = f"sqlite:///{tmp_path / 'e.db'}"
    optuna.create_study(storage=storage, study_name="empty", direction="maximize")
    result = analysis.write_report("empty", storage, out=tmp_path / "r", interactive=True)
    md = result.markdown.read_text()
    assert "No COMPLETE trial yet." in md
    assert "not created by ermrl" in md
    assert result.figures["optimization_history"].exists()


def test_the_gait_is_the_joint_angles_frequency_and_is_marked_on_the_spectra() -> None:
    from ermrl.analysis import gait_frequency, joint_angles, spectrum_comparison_figure

    n, dt = 800, 0.04  # Swimmer-v5: 3 position values (angles), then 5 velocities
    t = np.arange(n) * dt
    angles = np.stack([np.sin(2 * np.pi * 1.5 * t + k) for k in range(3)], axis=1)
    velocities = np.stack([np.sin(2 * np.pi * 4.0 * t + k) for k in range(5)], axis=1)
    states = np.tanh(np.stack([np.sin(2 * np.pi * 2.5 * t + k) for k in range(10)], axis=1))
    rec = DynamicsRecording(
        observations=np.concatenate([angles, 3 * velocities], axis=1),
        actions=angles[:, :2],
        rewards=np.ones(n),
        states=states,
        dt=dt,
        env_id="Swimmer-v5",
        observe="all",
        agent="res-ppo",
        seed=10,
        obs_indices=np.arange(8),
    )
    np.testing.assert_array_equal(joint_angles(rec), angles)
    assert gait_frequency(rec) == pytest.approx(1.5, abs=0.1)
    summary = spectrum_summary(rec)["signals"]
    assert summary["joint angles (gait)"]["dominant_frequency"] == pytest.approx(1.5, abs=0.1)
    assert summary["observations"]["dominant_frequency"] == pytest.approx(4.0, abs=0.1)
    fig = spectrum_comparison_figure({"res-ppo": rec})
    labels = [line.get_label() for line in fig.axes[0].get_lines()]
    gait = f"gait of RES-PPO (evolved reservoir) (joint angles): {gait_frequency(rec):.3g} Hz"
    assert gait in labels, labels
    # Velocities only: no joint angles, no gait.
    blind = DynamicsRecording(**{**rec.__dict__, "observe": "velocities"})
    assert joint_angles(blind) is None and math.isnan(gait_frequency(blind))


@pytest.mark.parametrize(
    ("env_id", "joints"),
    [("Swimmer-v5", True), ("Hopper-v5", True), ("HalfCheetah-v5", True),
     ("CartPole-v1", False), ("Pendulum-v1", False), ("InvertedPendulum-v5", False),
     ("NoSuchEnv-v0", False)],
)  # fmt: skip
def test_only_mujoco_locomotion_has_joints(env_id: str, joints: bool) -> None:
    from ermrl.analysis import has_joints

    assert has_joints(env_id) is joints


@pytest.mark.parametrize("observe", ["all", "positions"])
def test_a_cartpole_spectrum_is_not_labelled_a_gait(observe: str) -> None:
    """CartPole's positions (the cart's position, the pole's angle) oscillate, but they are no
    gait: neither the spectra nor their summary call them joint angles."""
    from ermrl.analysis import gait_frequency, joint_angles, spectrum_comparison_figure

    n, dt = 400, 0.02
    t = np.arange(n) * dt
    positions = np.stack([np.sin(2 * np.pi * 1.5 * t + k) for k in range(2)], axis=1)
    observations = positions if observe == "positions" else np.repeat(positions, 2, axis=1)
    rec = DynamicsRecording(
        observations=observations,
        actions=np.zeros((n, 1)),
        rewards=np.ones(n),
        states=np.tanh(np.stack([np.sin(2 * np.pi * 2.5 * t + k) for k in range(10)], axis=1)),
        dt=dt,
        env_id="CartPole-v1",
        observe=observe,
        agent="res-ppo",
        seed=10,
        obs_indices=np.arange(observations.shape[1]),
    )
    assert joint_angles(rec) is None and math.isnan(gait_frequency(rec))
    assert not any("gait" in name for name in spectrum_summary(rec)["signals"])
    for fig in (spectrum_comparison_figure({"res-ppo": rec}), analysis.spectrum_figure(rec)):
        labels = [str(line.get_label()) for ax in fig.axes for line in ax.get_lines()]
        legend = [
            t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()
        ]
        assert not any("gait" in x or "joint" in x for x in labels + legend), labels + legend


def test_a_short_episode_without_a_peak_has_no_dominant_frequency() -> None:
    """A 21-step episode's largest bin is the spectral resolution, not an oscillation."""
    steps = np.arange(21, dtype=float)[:, None]
    drift = np.hstack([np.exp(-steps / 5), 1 - np.exp(-steps / 8)])  # a transient, no cycle
    freqs, power = power_spectrum(drift, 0.05)
    assert math.isnan(dominant_frequency(freqs, power))
    wave = np.sin(2 * np.pi * 4.0 * np.arange(200)[:, None] * 0.05)  # 4 Hz, 40 cycles
    assert dominant_frequency(*power_spectrum(wave, 0.05)) == pytest.approx(4.0, abs=0.1)


def test_the_report_and_study_export_write_the_same_trials_table(tmp_path: Path) -> None:
    from ermrl.cli._study import study_main

    storage = f"sqlite:///{tmp_path / 'g.db'}"
    study = make_study(8, generalization=True)  # dict and list user attributes, a FAIL trial
    _copy_to_sqlite(study, storage, "gen")
    analysis.write_report(
        "gen", storage, runs=tmp_path / "none", out=tmp_path / "r", interactive=False,
        html_page=False,
    )  # fmt: skip
    exported = tmp_path / "export.csv"
    assert (
        study_main(["export", "--storage", storage, "--study-name", "gen", "--out", str(exported)])
        == 0
    )
    report = pd.read_csv(tmp_path / "r" / "trials.csv")
    export = pd.read_csv(exported)
    pd.testing.assert_frame_equal(report, export)
    # Optuna's own columns first, in its order, then ermrl's.
    loaded = optuna.load_study(study_name="gen", storage=storage)
    optuna_columns = list(loaded.trials_dataframe(multi_index=False).columns)
    assert list(report.columns) == optuna_columns + list(analysis.TRIALS_TABLE_EXTRA)
    assert {"params_sr", "user_attrs_task_seed_returns", "duration_s", "generation"} <= set(report)
    assert list(report["state"]) == [t.state.name for t in loaded.trials]
    # A dict attribute is JSON text, read back as it was stored.
    first = json.loads(report.loc[0, "user_attrs_task_normalized"])
    assert first == loaded.trials[0].user_attrs["task_normalized"]
    parquet = tmp_path / "export.parquet"
    assert (
        study_main(["export", "--storage", storage, "--study-name", "gen", "--out", str(parquet)])
        == 0
    )
    assert list(pd.read_parquet(parquet).columns) == list(report.columns)
    # JSON lines: the same table, one record per trial.
    jsonl = tmp_path / "export.jsonl"
    assert (
        study_main(["export", "--storage", storage, "--study-name", "gen", "--out", str(jsonl)])
        == 0
    )
    records = [json.loads(line) for line in jsonl.read_text().splitlines()]
    assert len(records) == len(report) and list(records[0]) == list(report.columns)
    assert [r["number"] for r in records] == list(report["number"])
    assert [r["state"] for r in records] == list(report["state"])
    assert records[0]["user_attrs_task_normalized"] == report.loc[0, "user_attrs_task_normalized"]
    assert records[0]["datetime_start"].startswith(str(loaded.trials[0].datetime_start.date()))


@pytest.mark.parametrize("name", ["result.json", "episodes.csv"])
@pytest.mark.parametrize("how", ["device", "huge", "folder"])
def test_a_run_file_that_is_a_device_or_huge_is_refused_unread(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, how: str
) -> None:
    """A record that is a device (``/dev/zero``: reading it to its end never stops) or larger
    than any record ermrl writes is a RunFolderError naming it, not a MemoryError."""
    from ermrl.analysis import RunFolderError, _results
    from ermrl.analysis._results import read_episodes, read_run_result

    path = tmp_path / name
    if how == "device":
        path.symlink_to("/dev/zero")
    elif how == "folder":
        path.mkdir()
    else:  # the cap made small here, so that the test reads kilobytes, not half a gigabyte
        monkeypatch.setattr(_results, "MAX_RUN_FILE_BYTES", 1024)
        path.write_text("env_step,episode_return\n" + "1,0.5\n" * 400)
    read = read_run_result if name == "result.json" else read_episodes
    expected = {
        "device": "not a regular file",
        "huge": "over .* MiB: not a record",
        "folder": "a folder",
    }
    with pytest.raises(RunFolderError, match=expected[how]) as info:
        read(path)
    assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)
