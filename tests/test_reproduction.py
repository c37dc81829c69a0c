"""The reproduction page: verdicts from confidence intervals, numbers from the per-seed files."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from ermrl.analysis import (
    Hypothesis,
    TaskFiles,
    bootstrap_mean_diff_ci,
    compare_agents,
    paired_bootstrap_mean_diff_ci,
    verdict,
    write_reproduction_page,
)

ROOT = Path(__file__).resolve().parents[1]


def runs(values: dict[str, list[float]]) -> pd.DataFrame:
    rows = [
        {"agent": agent, "seed": 10 + i, "final_return": v, "env_steps": 1000, "wall_seconds": 2.0}
        for agent, vs in values.items()
        for i, v in enumerate(vs)
    ]
    return pd.DataFrame(rows)


@pytest.mark.parametrize(
    ("res", "word"),
    [
        ([120.0, 125.0, 130.0, 128.0, 122.0], "reproduced"),
        ([90.0, 140.0, 60.0, 150.0, 85.0], "partly"),
        ([80.0, 85.0, 90.0, 95.0, 70.0], "not reproduced"),
    ],
)
def test_the_verdict_follows_the_ci_of_res_ppo_minus_ppo(res: list[float], word: str) -> None:
    data = runs({"res-ppo": res, "ppo": [100.0, 101.0, 99.0, 102.0, 98.0], "random-res-ppo": res})
    got, why = verdict(compare_agents(data, "res-ppo", ["ppo", "random-res-ppo"]))
    assert got == word, why
    assert "res-ppo − random-res-ppo = +0" in why and "inside the noise" in why


def test_reproduced_needs_welchs_interval_above_zero_too() -> None:
    """Two seeds whose percentile bootstrap lies above 0 are not enough to call it reproduced."""
    data = runs({"res-ppo": [110.0, 104.0], "ppo": [100.0, 101.0]})
    comparison = compare_agents(data, "res-ppo", ["ppo"])
    row = comparison.iloc[0]
    assert row["boot_ci_low"] > 0 > row["welch_ci_low"]
    word, why = verdict(comparison)
    assert word == "partly", why
    assert "Welch CI" in why and "unreliable" in why


def test_the_other_agents_tested_are_compared_too(tmp_path: Path) -> None:
    """H1 also asks about learned memory: res-ppo against every agent the test phase trained,
    the paper's baselines first; the verdict still rests on res-ppo − ppo alone."""
    from ermrl.analysis import task_result

    values = {
        "ppo": [100.0, 95.0, 105.0, 98.0, 102.0],
        "random-res-ppo": [110.0, 100.0, 120.0, 105.0, 115.0],
        "res-ppo": [125.0, 122.0, 130.0, 121.0, 127.0],
        "framestack-ppo": [150.0, 151.0, 149.0, 152.0, 148.0],
        "lstm-ppo": [90.0, 160.0, 100.0, 150.0, 120.0],
        "ppo-full": [200.0, 201.0, 199.0, 202.0, 198.0],
    }
    _publish(tmp_path / "CartPole-v1", values)
    result = task_result(tmp_path / "CartPole-v1", "CartPole-v1", 100, tmp_path / "none")
    assert list(result.comparison["baseline"]) == [
        "ppo", "random-res-ppo", "ppo-full", "lstm-ppo", "framestack-ppo",
    ]  # fmt: skip
    word, why = verdict(result.comparison)
    assert word == "reproduced", why
    assert "res-ppo − framestack-ppo = -25, " in why
    assert "framestack-ppo = -25, 95% bootstrap CI" in why
    clauses = dict(c.split(" = ", 1) for c in why.split("; ")[1:])
    assert clauses["res-ppo − framestack-ppo"].endswith("behind (both CIs below 0)")
    assert clauses["res-ppo − lstm-ppo"].endswith("inside the noise (a CI spans 0)")
    assert clauses["res-ppo − ppo-full"].endswith("behind (both CIs below 0)")


def test_no_runs_is_not_a_verdict() -> None:
    assert verdict(pd.DataFrame())[0] == "not run"


def test_paired_ci_resamples_seed_differences() -> None:
    a = np.array([10.0, 20.0, 30.0, 40.0])
    b = a - 1.0  # every seed exactly 1 better: the paired CI is a point, the independent one wide
    assert paired_bootstrap_mean_diff_ci(a, b) == (1.0, 1.0)
    low, high = bootstrap_mean_diff_ci(a, b)
    assert low < 0 < high
    with pytest.raises(ValueError):
        paired_bootstrap_mean_diff_ci(a, b[:3])
    data = runs({"res-ppo": list(a), "ppo": list(b)})
    row = compare_agents(data, "res-ppo", ["ppo"]).iloc[0]
    assert row["n_paired"] == 4 and row["paired_ci_low"] == row["paired_ci_high"] == 1.0


def _publish(folder: Path, values: dict[str, list[float]]) -> None:
    for agent, vs in values.items():
        for i, v in enumerate(vs):
            run = folder / "test" / "agents" / agent / f"seed_{10 + i}"
            run.mkdir(parents=True)
            record = {"agent": agent, "seed": 10 + i, "final_return": v, "env_steps": 1_000_000,
                      "wall_seconds": 1800.0}  # fmt: skip
            (run / "result.json").write_text(json.dumps(record))
    config = {"trial": 7, "selection": "re-evaluated best of 4 candidates",
              "agents": {"res-ppo": [{"units": 100, "sr": 0.5, "lr": 0.2, "input_scaling": 1.0}]}}  # fmt: skip
    (folder / "test" / "config.yaml").write_text(yaml.safe_dump(config))


def test_the_page_is_recomputed_from_the_published_per_seed_files(tmp_path: Path) -> None:
    values = {
        "ppo": [100.0, 95.0, 105.0, 98.0, 102.0],
        "random-res-ppo": [110.0, 100.0, 120.0, 105.0, 115.0],
        "res-ppo": [125.0, 122.0, 130.0, 121.0, 127.0],
    }
    _publish(tmp_path / "pub" / "Swimmer-v5", values)
    snapshot = tmp_path / "pub" / "Swimmer-v5" / "study.json"
    trials = [{"state": "COMPLETE", "user_attrs": {"env_steps": 900_000, "wall_seconds": 60.0}}]
    snapshot.write_text(json.dumps({"trials": trials * 40 + [{"state": "WAITING"}], "related": {}}))
    pending = TaskFiles("Ant-v5", "Ant-v5", tmp_path / "pub" / "Ant-v5", tmp_path / "none", 60)
    hyp = Hypothesis(
        "h2", "h2.yaml", '"a claim"', "what it asks",
        (TaskFiles("Swimmer-v5", "Swimmer-v5", tmp_path / "pub" / "Swimmer-v5", snapshot, 100),
         pending),
    )  # fmt: skip
    md, html = write_reproduction_page([hyp], tmp_path / "docs" / "reproduction.md")
    text = md.read_text()
    low, high = bootstrap_mean_diff_ci(values["res-ppo"], values["ppo"])
    diff = np.mean(values["res-ppo"]) - np.mean(values["ppo"])
    assert f"res-ppo − ppo = {diff:+.4g}, 95% bootstrap CI [{low:+.4g}, {high:+.4g}]" in text
    assert "**Verdict: reproduced.**" in text and "**Verdict: not run yet.**" in text
    assert "reproduced (on 1 of 2 tasks; pending: Ant-v5)" in text
    assert "40/100 trials finished" in text and "36M env steps" in text
    assert "trial #7 (re-evaluated best of 4 candidates)" in text and "sr 0.5" in text
    assert '"a claim"' in text
    assert html is not None and "<table>" in html.read_text()


def test_the_command_reads_the_paper_files(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "ermrl", "reproduction",
         *map(str, sorted((ROOT / "experiments" / "paper").glob("*.yaml"))),
         "--out", str(tmp_path / "r.md")],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    text = (tmp_path / "r.md").read_text()
    for name in ("paper-h1", "paper-h2", "paper-h3"):
        assert name in text
    assert (tmp_path / "r.html").exists()


def test_a_selected_reference_makes_the_evolution_clause_say_so() -> None:
    """When the selection chose the unevolved reference, res-ppo and random-res-ppo are the
    same runs: the page says the difference is 0 by construction, not 'inside the noise' with
    unpaired CIs of [-420, +416] around two copies of one sample (H1 Pendulum)."""
    same = [-1136.0, -150.0, -600.0, -300.0, -364.0]
    data = runs({"res-ppo": same, "random-res-ppo": same, "ppo": [-1100.0, -1150.0, -1200.0,
                                                                   -1120.0, -1140.0]})  # fmt: skip
    comparison = compare_agents(data, "res-ppo", ["ppo", "random-res-ppo"])
    _, plain = verdict(comparison)
    assert "inside the noise" in plain
    word, why = verdict(comparison, reference_selected=True)
    assert word == "reproduced"
    assert "0 by construction" in why and "unevolved reference itself" in why
    assert "res-ppo − random-res-ppo = +0" not in why
