"""The mechanism of an evolved reservoir's gain: spectra near the gait and the W = 0 ablation."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from ermrl.analysis import (
    DynamicsRecording,
    Hypothesis,
    SpectralCriterion,
    TaskFiles,
    VerdictRule,
    band_share,
    dominant_frequency,
    gait_segment,
    lowest_bin,
    mechanism_question,
    mechanism_verdict,
    power_spectrum,
    read_mechanism,
    reservoir_spectra,
    spectral_outcome,
    write_reproduction_page,
)
from ermrl.analysis._mechanism import MECHANISM_COLUMNS, MECHANISM_FILE, without_gait

ROOT = Path(__file__).resolve().parents[1]
DT = 0.04  # Swimmer's
STEPS = 1000
GAIT = 0.78125  # a bin of a 256-step Welch segment at DT: 8 / (256 * DT)
RESOLUTION = 1 / (256 * DT)


def _sine(units: int = 10, seed: int = 0) -> np.ndarray:
    """Units oscillating at the gait, each with its phase, and a little noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(STEPS)[:, None] * DT
    phases = rng.uniform(0, 2 * np.pi, units)
    return np.sin(2 * np.pi * GAIT * t + phases) + 0.05 * rng.standard_normal((STEPS, units))


def _ema(units: int = 10, lr: float = 0.02, seed: int = 0) -> np.ndarray:
    """A leaky integrator of white noise: smooth, its power at the lowest frequencies."""
    noise = np.random.default_rng(seed).standard_normal((STEPS, units))
    states, x = np.empty_like(noise), np.zeros(units)
    for t, u in enumerate(noise):
        x = (1 - lr) * x + lr * u
        states[t] = x
    return states


def test_a_sine_at_the_gait_holds_its_power_near_it_and_an_ema_does_not() -> None:
    criterion = SpectralCriterion()
    band = criterion.gait_band(GAIT, RESOLUTION)
    assert band == pytest.approx((0.8 * GAIT, 1.2 * GAIT))  # ±20%, wider than one bin
    freqs, sine = power_spectrum(_sine(), DT)
    _, ema = power_spectrum(_ema(), DT)
    assert dominant_frequency(freqs, sine) == pytest.approx(GAIT)
    assert band_share(freqs, sine, band) > 0.9
    ema_share = band_share(freqs, ema, band)
    assert ema_share < 0.1
    ema_peak = dominant_frequency(freqs, ema)
    assert not band[0] <= ema_peak <= band[1]  # NaN (no peak) or a noise peak elsewhere
    # The share is of the total: a column twice as loud weighs four times as much.
    both = np.concatenate([_sine(1), 2 * _ema(1)], axis=1)
    _, power = power_spectrum(both, DT)
    share = band_share(freqs, power, band)
    alone = [band_share(freqs, power[:, [k]], band) for k in (0, 1)]
    weights = power[freqs > 0].sum(axis=0)
    assert share == pytest.approx(np.average(alone, weights=weights))
    # The criterion: at least twice the ablation's share and the state's own peak in the band.
    sine_share = band_share(freqs, sine, band)
    assert criterion.carries(sine_share, ema_share, GAIT, band)
    assert not criterion.carries(ema_share, sine_share, ema_peak, band)
    assert not criterion.carries(sine_share, 0.6 * sine_share, GAIT, band)  # less than 2x
    assert not criterion.carries(sine_share, ema_share, 2 * GAIT, band)  # peak outside
    assert not criterion.carries(sine_share, ema_share, math.nan, band)


def test_the_band_is_at_least_one_bin_and_unknown_without_a_gait() -> None:
    criterion = SpectralCriterion()
    low, high = criterion.gait_band(0.2, RESOLUTION)  # 20% of 0.2 Hz is under a bin
    assert (low, high) == pytest.approx((max(0.2 - RESOLUTION, 0.0), 0.2 + RESOLUTION))
    assert all(math.isnan(v) for v in criterion.gait_band(math.nan, RESOLUTION))
    freqs, power = power_spectrum(_sine(), DT)
    assert math.isnan(band_share(freqs, power, (math.nan, math.nan)))
    assert math.isnan(band_share(freqs, np.zeros_like(power), (0.5, 1.0)))


def test_a_gait_slower_than_a_segment_is_resolved_with_the_whole_episode() -> None:
    """Swimmer's gait can be slower than 256-step segments resolve (0.098 Hz at dt 0.04 s): with
    them the joint angles' power is largest in the lowest bin and has no peak; the whole episode
    as one segment finds it. A gait the segments resolve keeps them."""
    t = np.arange(STEPS)[:, None] * DT
    slow_gait = 2 / (STEPS * DT)  # 0.05 Hz: two cycles in the 40 s episode
    slow = np.sin(2 * np.pi * slow_gait * t + np.array([0.0, 1.0, 2.0]))
    freqs, power = power_spectrum(slow, DT)
    assert math.isnan(dominant_frequency(freqs, power)) and lowest_bin(freqs, power)
    assert gait_segment(slow, DT) == STEPS
    freqs, power = power_spectrum(slow, DT, STEPS)
    assert dominant_frequency(freqs, power) == pytest.approx(slow_gait)
    assert not lowest_bin(freqs, power)
    assert gait_segment(_sine(3), DT) == 256  # 0.78 Hz: resolved by 256-step segments
    assert gait_segment(_sine(3)[:200], DT) == 256  # shorter than a segment: nothing to widen
    assert gait_segment(None, DT) == 256


def test_a_gait_below_the_resolution_is_told_apart_from_no_gait(tmp_path: Path) -> None:
    """A table whose joint angles peak in the lowest bin even over the whole episode says
    "gait below resolution"; one without that column (written before it existed) or without
    such power says "no gait"; both leave the criterion unjudged."""
    table = _spectra_table(0.5, 0.1, GAIT).assign(
        gait_frequency=math.nan, resolution=1 / (STEPS * DT), lowest_bin=False
    )
    table.loc[table["signal"] == "joint angles", "lowest_bin"] = True
    (tmp_path / "below").mkdir()
    table.to_csv(tmp_path / "below" / MECHANISM_FILE, index=False)
    read = read_mechanism(tmp_path / "below")
    assert read is not None
    outcome = spectral_outcome(read)
    assert outcome.holds is None
    assert outcome.reason.startswith("gait below resolution: the joint angles' power is largest")
    assert "(0.025 Hz) even with the whole 1000-step episode as one segment" in outcome.reason
    old = table.drop(columns="lowest_bin")
    (tmp_path / "old").mkdir()
    old.to_csv(tmp_path / "old" / MECHANISM_FILE, index=False)
    read_old = read_mechanism(tmp_path / "old")
    assert read_old is not None and list(read_old.columns) == list(table.columns)
    assert spectral_outcome(read_old).reason.startswith("no gait")
    flat = table.assign(lowest_bin=False)
    assert spectral_outcome(flat).reason.startswith("no gait")


def _recording_of_a_reservoir_env(encoder: object, seed: int, steps: int = 200) -> object:
    """An episode of Swimmer-v5 under random actions, recorded as the replay records one."""
    from ermrl.agents import derive_seeds, make_vec_env
    from ermrl.config import TaskConfig

    venv = make_vec_env(
        TaskConfig("Swimmer-v5", "all"), 1, 5, encoder, derive_seeds(seed).reservoir
    )
    rng = np.random.default_rng(0)
    observations, actions, rewards, states = [], [], [], []
    venv.reset()
    for _ in range(steps):
        observations.append(venv.get_inputs()[0, : venv.obs_dim].copy())
        states.append(venv.get_states()[0].astype(np.float64))
        action = rng.uniform(-1, 1, (1, 2)).astype(np.float32)
        _, reward, _, _ = venv.step(action)
        actions.append(action[0].astype(np.float64))
        rewards.append(float(reward[0]))
    venv.close()
    return DynamicsRecording(
        observations=np.asarray(observations),
        actions=np.asarray(actions),
        rewards=np.asarray(rewards),
        states=np.asarray(states),
        dt=DT,
        env_id="Swimmer-v5",
        observe="all",
        agent="res-ppo",
        seed=seed,
        obs_indices=np.arange(8),
    )


def test_the_recorded_input_stream_replays_the_recorded_states() -> None:
    """The input stream rebuilt from an episode (observation, previous action, previous reward)
    drives the evolved reservoir to the very states the policy saw; its W = 0 ablation differs,
    and every weight seed gives a row per reservoir."""
    import dataclasses

    from ermrl.config import EncoderConfig, ReservoirParams

    evolved = (ReservoirParams(units=30, sr=0.9, lr=0.3),)
    encoder = EncoderConfig(reservoirs=evolved, reward_scale=0.5)
    recording = _recording_of_a_reservoir_env(encoder, seed=11)
    leaky = tuple(dataclasses.replace(p, ablation="leaky") for p in evolved)
    measured = reservoir_spectra(
        recording,
        encoder,
        {"res-ppo": evolved, "leaky-res-ppo": leaky},
        [10, 11, 12],
    )
    assert measured.replay_error < 1e-5  # float32 states, so rounding only
    table = measured.table
    assert list(table.columns) == MECHANISM_COLUMNS
    assert table["signal"].tolist() == ["joint angles"] + ["res-ppo"] * 3 + ["leaky-res-ppo"] * 3
    assert table["weight_seed"].tolist()[1:] == [10, 11, 12] * 2
    assert set(measured.spectra.columns) == {
        "frequency",
        "joint angles",
        "res-ppo",
        "leaky-res-ppo",
    }
    # Another weight seed, or W = 0, is another reservoir: the replay is not vacuous.
    other = reservoir_spectra(recording, encoder, {"res-ppo": evolved}, [12])
    assert math.isnan(other.replay_error)
    assert not np.allclose(measured.spectra["res-ppo"], measured.spectra["leaky-res-ppo"])


# -- the page: crafted per-seed files and spectra ------------------------------------------------

RULE = {
    "adopted": "2026-11-29",
    "resamples": 2000,
    "questions": {
        "evolved-vs-unevolved": {"text": "does evolution help?",
                                 "compare": ["res-ppo - random-res-ppo"]},
        "evolved-vs-leaky": {"text": "does the evolved reservoir beat W = 0?",
                             "compare": ["res-ppo - leaky-res-ppo"], "adopted": "2026-11-30"},
    },
    "equivalence": {"adopted": "2026-12-02", "margins": {"Leaky-v0": 5.0, "Same-v0": 20.0}},
}  # fmt: skip
LOW = [100.0, 95.0, 105.0, 98.0, 102.0, 101.0, 99.0, 97.0]
HIGH = [150.0, 147.0, 153.0, 149.0, 151.0, 152.0, 148.0, 150.0]
SPREAD = [90.0, 115.0, 85.0, 120.0, 95.0, 110.0, 100.0, 108.0]
BELOW = [50.0, 47.0, 53.0, 49.0, 51.0, 52.0, 48.0, 50.0]


def _spectra_table(evolved_share: float, ablation_share: float, peak: float) -> pd.DataFrame:
    """A report's mechanism.csv: the joint angles, and 4 weight seeds of each reservoir."""
    criterion = SpectralCriterion()
    low, high = criterion.gait_band(GAIT, RESOLUTION)
    base = {"env_id": "Swimmer-v5", "recorded_seed": 10, "n_steps": STEPS, "dt": DT,
            "frequency_unit": "Hz", "resolution": RESOLUTION, "gait_frequency": GAIT,
            "band_low": low, "band_high": high, "replay_error": 0.0}  # fmt: skip
    rows = [{**base, "signal": "joint angles", "weight_seed": 10, "dominant_frequency": GAIT,
             "share_near_gait": 0.7}]  # fmt: skip
    for signal, share, dominant in [
        ("res-ppo", evolved_share, peak),
        ("random-res-ppo", 0.02, math.nan),
        ("leaky-res-ppo", ablation_share, math.nan),
    ]:
        for seed in (10, 11, 12, 13):
            rows.append({**base, "signal": signal, "weight_seed": seed,
                         "dominant_frequency": dominant, "share_near_gait": share})  # fmt: skip
    return pd.DataFrame(rows, columns=MECHANISM_COLUMNS)


def _publish(folder: Path, values: dict[str, list[float]], spectra: pd.DataFrame | None) -> Path:
    for agent, returns in values.items():
        for i, value in enumerate(returns):
            run = folder / "test" / "agents" / agent / f"seed_{10 + i}"
            run.mkdir(parents=True)
            record = {"agent": agent, "seed": 10 + i, "final_return": value,
                      "last100_return": value, "eval_return": value, "env_steps": 1000,
                      "wall_seconds": 1.0, "finished": "2026-11-30T00:00:00"}  # fmt: skip
            (run / "result.json").write_text(json.dumps(record))
    reservoir = [{"units": 100, "sr": 0.03, "lr": 0.25, "input_scaling": 1.0}]
    config = {"trial": 7, "selection": "re-evaluated best of 4 candidates",
              "agents": {"res-ppo": reservoir, "random-res-ppo": [{"units": 100}]}}  # fmt: skip
    (folder / "test" / "config.yaml").write_text(yaml.safe_dump(config))
    if spectra is not None:
        (folder / "report" / "dynamics").mkdir(parents=True)
        spectra.to_csv(folder / "report" / "dynamics" / MECHANISM_FILE, index=False)
    attrs = {"ermrl_reevaluation": {"complete": True, "best_trial": 7, "seeds": [1],
                                    "candidates": [{"trial": 7, "fitness": 1.0}]}}  # fmt: skip
    snapshot = folder / "study.json"
    trials = [{"number": 7, "state": "COMPLETE", "value": 1.0, "user_attrs": {}}]
    snapshot.write_text(json.dumps({"trials": trials, "user_attrs": attrs, "related": {}}))
    return snapshot


def test_each_mechanism_label_follows_the_rule_on_crafted_files(tmp_path: Path) -> None:
    """Oscillatory dynamics, leaky integration suffices (with its bound, and when the ablation
    learns better), inconclusive and not run yet, each on its own crafted task."""
    tasks = {
        # the ablation learns worse, and the evolved reservoir carries the gait (0.5 vs 0.1)
        "Osc-v0": ({"res-ppo": HIGH, "random-res-ppo": LOW, "leaky-res-ppo": LOW},
                   _spectra_table(0.5, 0.1, GAIT)),
        # not shown worse, and not shown equivalent within its margin (±5): not shown either
        # way, its bound the upper end of the adjusted intervals
        "Leaky-v0": ({"res-ppo": SPREAD, "random-res-ppo": LOW, "leaky-res-ppo": LOW},
                     _spectra_table(0.5, 0.1, GAIT)),
        # the same returns: equivalent within its margin (±20), leaky integration suffices
        "Same-v0": ({"res-ppo": LOW, "random-res-ppo": BELOW,
                     "leaky-res-ppo": [v + 0.5 for v in LOW]},
                    _spectra_table(0.5, 0.1, GAIT)),
        # the ablation learns better
        "Better-v0": ({"res-ppo": BELOW, "random-res-ppo": LOW, "leaky-res-ppo": LOW},
                      _spectra_table(0.1, 0.1, math.nan)),
        # worse without W, but no gait component the ablation lacks (0.15 < 2 x 0.1)
        "NoGait-v0": ({"res-ppo": HIGH, "random-res-ppo": LOW, "leaky-res-ppo": LOW},
                      _spectra_table(0.15, 0.1, GAIT)),
        # worse without W, spectra never recorded
        "Unrecorded-v0": ({"res-ppo": HIGH, "random-res-ppo": LOW, "leaky-res-ppo": LOW}, None),
        # no leaky-res-ppo run
        "Missing-v0": ({"res-ppo": HIGH, "random-res-ppo": LOW}, _spectra_table(0.5, 0.1, GAIT)),
        # a task known to have no gait: its comparison is judged, with no mechanism verdict
        "CartPole-v1": ({"res-ppo": HIGH, "random-res-ppo": LOW, "leaky-res-ppo": LOW}, None),
    }  # fmt: skip
    files = []
    for label, (values, spectra) in tasks.items():
        snapshot = _publish(tmp_path / "pub" / label, values, spectra)
        files.append(TaskFiles(label, label, tmp_path / "pub" / label, snapshot, 10))
    rule = VerdictRule.from_doc(RULE)
    hyp = Hypothesis("h", "h.yaml", None, None, tuple(files), rule)
    md, _ = write_reproduction_page([hyp], tmp_path / "docs" / "reproduction.md", html_page=False)
    text = md.read_text()
    tests = pd.read_csv(md.with_suffix(".csv"))

    def line(task: str) -> str:
        head = "**Mechanism (last10):** "
        section = text.split(f"#### {task}: mechanism")[1]
        return next(x for x in section.splitlines() if x.startswith(head)).removeprefix(head)

    def bound(task: str) -> float:
        row = tests[(tests["task"] == task) & (tests["question"] == "evolved-vs-leaky")
                    & (tests["metric"] == "last10")].iloc[0]  # fmt: skip
        return max(row["adj_welch_high"], row["adj_boot_high"])

    assert line("Osc-v0").startswith("oscillatory dynamics: **supported**; the W = 0 ablation")
    assert "the criterion holds on 4 of 4 weight seeds" in line("Osc-v0")
    leaky = line("Leaky-v0")
    assert leaky.startswith("**not shown either way**; the ablation is not shown to learn worse")
    assert "equivalence within ±5 not shown either way (TOST p" in leaky
    assert f"it could learn up to {bound('Leaky-v0'):.4g} worse" in leaky
    same = line("Same-v0")
    assert same.startswith("leaky integration suffices: **supported**; the ablation learns as well")
    assert "equivalent within ±20 (TOST p" in same
    row = tests[(tests["task"] == "Same-v0") & (tests["question"] == "evolved-vs-leaky")
                & (tests["metric"] == "last10")].iloc[0]  # fmt: skip
    assert row["equivalence"] == "equivalent" and row["outcome"] == "inconclusive"
    assert -20 < row["equiv_low"] < row["equiv_high"] < 20 and row["tost_p"] <= row["level"]
    better = line("Better-v0")
    assert better.startswith("leaky integration suffices: **supported**; the ablation learns bett")
    assert f"by at least {-bound('Better-v0'):.4g}" in better
    assert line("NoGait-v0").startswith("**inconclusive**; the W = 0 ablation learns worse")
    assert "holds on 0 of 4 weight seeds" in line("NoGait-v0")
    assert "spectra not recorded yet" in line("Unrecorded-v0")
    assert line("Missing-v0").startswith("**not run yet**; `leaky-res-ppo` has no finished run")
    # The family: Holm over the 6 tasks that ran (the missing one does not count).
    family = tests[(tests["question"] == "evolved-vs-leaky") & (tests["metric"] == "last10")]
    family = family.set_index("task")
    assert family["family_size"].drop("Missing-v0").eq(7).all()
    assert family.at["CartPole-v1", "outcome"] == "supported"
    assert "#### CartPole-v1: mechanism" not in text
    summary = next(x for x in text.splitlines() if x.startswith("**Mechanism: oscillations"))
    assert "Missing-v0" in summary and "CartPole-v1" not in summary
    assert "evolved-vs-leaky: **supported**" in text.split("### CartPole-v1")[1]
    assert family.at["Missing-v0", "outcome"] == "not run yet"  # in the CSV too, not inconclusive
    # The summary, the glance table, the task's verdict line and the question's adoption date.
    assert (
        "Osc-v0: oscillatory dynamics: **supported**; Leaky-v0: **not shown either way**; "
        "Same-v0: leaky integration suffices: **supported**; Better-v0: leaky integration "
        "suffices: **supported**; NoGait-v0: "
        "**inconclusive**; Unrecorded-v0: **inconclusive**; Missing-v0: **not run yet**"
    ) in text
    assert "evolved-vs-leaky: **not run yet**" in text.split("### Missing-v0")[1]
    assert "`res-ppo − leaky-res-ppo`; added 2026-11-30)" in text
    # The spectra behind it: the joint angles' gait and each reservoir's share near it.
    osc = text.split("#### Osc-v0: mechanism")[1].split("###")[0]
    assert "gait 0.781 Hz, band [0.625, 0.938]" in osc
    assert "| evolved reservoir (res-ppo) | 4 | 0.781 (4/4 with a peak) | 0.5 [0.5, 0.5] |" in osc
    assert "| evolved, W = 0 (leaky-res-ppo) | 4 | no peak (0/4) | 0.1 [0.1, 0.1] |" in osc
    # A task that did not run the ablation has no row for it in its tests table.
    missing = text.split("### Missing-v0")[1]
    assert "res-ppo − leaky-res-ppo |" not in missing


def test_the_verdict_of_a_task_without_spectra_or_comparison() -> None:
    empty = spectral_outcome(None)
    assert empty.holds is None and empty.reason == "spectra not recorded yet"
    verdict = mechanism_verdict(None, empty)
    assert verdict.label == "not run yet" and math.isnan(verdict.worse_by_at_most)
    untested = {"note": "not tested: leaky-res-ppo has fewer than 2 runs with this metric"}
    assert mechanism_verdict(untested, empty).label == "inconclusive"
    no_gait = _spectra_table(0.5, 0.1, GAIT).assign(gait_frequency=math.nan)
    outcome = spectral_outcome(no_gait)
    assert outcome.holds is None and outcome.reason.startswith("no gait")


def test_the_paper_file_asks_the_mechanism_question_of_locomotion_only() -> None:
    rules = {
        path.name: VerdictRule.from_doc(yaml.safe_load(path.read_text())["verdict"])
        for path in sorted((ROOT / "experiments" / "paper").glob("*.yaml"))
    }
    question = mechanism_question(rules["h2_locomotion.yaml"])
    assert question is not None and question.adopted == "2026-11-29"
    assert [c.label for c in question.comparisons] == ["res-ppo − leaky-res-ppo"]
    # H1 asks the same question, on tasks without a gait: judged, with no mechanism verdict.
    h1 = mechanism_question(rules["h1_partial_observability.yaml"])
    assert h1 is not None and h1.name == question.name
    assert without_gait("CartPole-v1") and without_gait("Pendulum-v1")
    assert not any(without_gait(t) for t in ("Swimmer-v5", "HalfCheetah-v5", "Ant-v5",
                                              "Hopper-v5", "Walker2d-v5"))  # fmt: skip


@pytest.mark.slow
def test_the_report_writes_the_mechanism_of_a_trained_agent(tmp_path: Path) -> None:
    """A tiny Swimmer test phase with the ablation: the report's dynamics section records an
    episode, drives the three reservoirs with it and judges res-ppo − leaky-res-ppo."""
    import dataclasses

    from ermrl.analysis._report import _dynamics_section, _State
    from ermrl.config import EncoderConfig, PPOConfig, ReservoirParams, TaskConfig
    from ermrl.test_phase import AgentSpec, TestSettings, run_comparison

    evolved = (ReservoirParams(units=20, sr=0.05, lr=0.3),)
    leaky = tuple(dataclasses.replace(p, ablation="leaky") for p in evolved)
    ppo = PPOConfig(hyperparams={"n_steps": 128, "batch_size": 64, "n_epochs": 1,
                                 "policy_kwargs": {"net_arch": [16, 16]}})  # fmt: skip
    runs = tmp_path / "runs"
    run_comparison(
        TaskConfig("Swimmer-v5", "all"),
        EncoderConfig(reservoirs=evolved),
        ppo,
        [
            AgentSpec("res-ppo", evolved),
            AgentSpec("random-res-ppo", (ReservoirParams(units=20),)),
            AgentSpec("leaky-res-ppo", leaky),
        ],  # fmt: skip
        TestSettings(training_steps=1024, seeds=(3, 4), out=runs),
        quiet=True,
    )
    state = _State(out=tmp_path / "report", study=None, storage="")
    _dynamics_section(state, runs)
    table = pd.read_csv(tmp_path / "report" / "dynamics" / MECHANISM_FILE)
    assert table["replay_error"].iloc[0] < 1e-5
    assert {"res-ppo", "random-res-ppo", "leaky-res-ppo"} <= set(table["signal"])
    assert sorted(table.loc[table["signal"] == "leaky-res-ppo", "weight_seed"]) == [3, 4]
    assert (tmp_path / "report" / "dynamics" / "mechanism_spectra.png").exists()
    text = "\n".join(str(v) for kind, v in state.sections[-1].blocks if kind == "p")
    assert "**Mechanism (last10):**" in text and "res-ppo − leaky-res-ppo" in text
