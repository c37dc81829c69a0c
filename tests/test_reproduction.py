"""The reproduction page: verdicts from confidence intervals, numbers from the per-seed files."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from ermrl.analysis import (
    NOT_RUN,
    Hypothesis,
    TaskFiles,
    VerdictError,
    VerdictRule,
    bootstrap_mean_diff_ci,
    compare_agents,
    paired_bootstrap_mean_diff_ci,
    verdict_changes,
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


def _publish(
    folder: Path,
    values: dict[str, list[float]],
    *,
    trial: int = 7,
    selection: str = "re-evaluated best of 4 candidates",
    reevaluated: int | None = 7,
    finished: str | None = None,
    reference: bool = False,
    last100: bool = True,
) -> Path:
    """Publish a task's test phase as per-seed files, and its study snapshot; return it."""
    for agent, vs in values.items():
        for i, v in enumerate(vs):
            run = folder / "test" / "agents" / agent / f"seed_{10 + i}"
            run.mkdir(parents=True)
            record = {"agent": agent, "seed": 10 + i, "final_return": v, "env_steps": 1_000_000,
                      "wall_seconds": 1800.0, "eval_return": v + 1.0}  # fmt: skip
            if last100:
                record["last100_return"] = v - 1.0
            if finished:
                record["finished"] = finished
            (run / "result.json").write_text(json.dumps(record))
            (run / "episodes.csv").write_text(
                "env_step,episode_return\n" + "".join(f"{k},{v}\n" for k in range(1, 4))
            )
    evolved = [{"units": 100, "sr": 0.5, "lr": 0.2, "input_scaling": 1.0}]
    unevolved = [{"units": 100, "sr": 1.0, "lr": 1.0, "input_scaling": 1.0}]
    config = {"trial": trial, "selection": selection,
              "agents": {"res-ppo": unevolved if reference else evolved,
                         "random-res-ppo": unevolved}}  # fmt: skip
    (folder / "test" / "config.yaml").write_text(yaml.safe_dump(config))
    attrs = {}
    if reevaluated is not None:
        attrs["ermrl_reevaluation"] = {
            "complete": True, "best_trial": reevaluated, "seeds": [1000, 1001],
            "candidates": [{"trial": reevaluated, "fitness": 1.5}],
        }  # fmt: skip
    snapshot = folder / "study.json"
    trials = [{"number": trial, "state": "COMPLETE", "value": 1.0,
               "user_attrs": {"env_steps": 900_000, "wall_seconds": 60.0}}]  # fmt: skip
    snapshot.write_text(json.dumps({"trials": trials, "user_attrs": attrs, "related": {}}))
    return snapshot


RULE = {
    "adopted": "2026-11-28",
    "alpha": 0.05,
    "correction": "holm",
    "primary": "last10",
    "resamples": 2000,
    "questions": {
        "reservoir-vs-ppo": {"text": "does res-ppo beat ppo?", "compare": ["res-ppo - ppo"]},
        "evolved-vs-unevolved": {"text": "does evolution help?",
                                 "compare": ["res-ppo - random-res-ppo"]},
    },
}  # fmt: skip

PPO = [100.0, 95.0, 105.0, 98.0, 102.0, 101.0, 99.0, 97.0]
CLEARLY_ABOVE = [150.0, 147.0, 153.0, 149.0, 151.0, 152.0, 148.0, 150.0]
CLEARLY_BELOW = [50.0, 47.0, 53.0, 49.0, 51.0, 52.0, 48.0, 50.0]
OVERLAPPING = [90.0, 115.0, 85.0, 120.0, 95.0, 110.0, 100.0, 108.0]


def _hypothesis(tmp_path: Path, tasks: dict[str, dict[str, list[float]]], rule: dict | None = RULE,
                **publish: object) -> Hypothesis:  # fmt: skip
    files = []
    for label, values in tasks.items():
        snapshot = _publish(tmp_path / "pub" / label, values, **publish)  # type: ignore[arg-type]
        files.append(TaskFiles(label, label, tmp_path / "pub" / label, snapshot, 100))
    return Hypothesis(
        "h", "h.yaml", '"a claim"', "what it asks", tuple(files),
        None if rule is None else VerdictRule.from_doc(rule),
    )  # fmt: skip


def _tests_of(md: Path) -> dict[tuple[str, str, str], list[str]]:
    """The page's test rows: (task, comparison, metric) -> cells."""
    rows: dict[tuple[str, str, str], list[str]] = {}
    task = ""
    for line in md.read_text().splitlines():
        if line.startswith("### "):
            task = line[4:].split(" ")[0]
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 16 and cells[1].startswith("res-ppo −"):
            rows[(task, cells[1], cells[2])] = cells
    return rows


def test_each_label_follows_the_rule_on_crafted_per_seed_files(tmp_path: Path) -> None:
    """Supported, contradicted and inconclusive, recomputed here: Holm over the 3 tasks of the
    family, Welch's p from scipy, both intervals at the adjusted level."""
    from scipy import stats

    tasks = {
        "Up-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE, "random-res-ppo": PPO},
        "Down-v0": {"ppo": PPO, "res-ppo": CLEARLY_BELOW, "random-res-ppo": PPO},
        "Noise-v0": {"ppo": PPO, "res-ppo": OVERLAPPING, "random-res-ppo": PPO},
    }
    hyp = _hypothesis(tmp_path, tasks)
    md, html = write_reproduction_page([hyp], tmp_path / "docs" / "reproduction.md")
    rows = _tests_of(md)
    outcome = {task: rows[(task, "res-ppo − ppo", "last10")][12] for task in tasks}
    assert outcome == {"Up-v0": "**supported**", "Down-v0": "**contradicted**",
                       "Noise-v0": "**inconclusive**"}  # fmt: skip
    raw = {
        t: stats.ttest_ind(v["res-ppo"], v["ppo"], equal_var=False).pvalue for t, v in tasks.items()
    }
    order = sorted(raw, key=raw.__getitem__)
    adjusted, running = {}, 0.0
    for rank, task in enumerate(order):
        running = max(running, min(1.0, (3 - rank) * raw[task]))
        adjusted[task] = running
    for task in tasks:
        cells = rows[(task, "res-ppo − ppo", "last10")]
        assert cells[7] == f"{raw[task]:.4g}" or float(cells[7]) == pytest.approx(
            raw[task], rel=1e-3
        )
        assert cells[8].endswith("(3)")
        assert float(cells[8].split(" ")[0]) == pytest.approx(adjusted[task], rel=1e-3)
    noise = rows[("Noise-v0", "res-ppo − ppo", "last10")]
    assert noise[13].startswith("effects above +") and "are excluded at 95%" in noise[13]
    assert noise[15].isdigit() and int(noise[15]) > 8  # more seeds than it has would be needed
    # The other metrics are judged too: last100 (here final_return - 1) keeps the labels.
    assert rows[("Up-v0", "res-ppo − ppo", "last100")][12] == "**supported**"
    text = md.read_text()
    assert "Up-v0: **supported**; Down-v0: **contradicted**; Noise-v0: **inconclusive**" in text
    assert "1 supported, 1 contradicted, 1 inconclusive" in text
    assert html is not None and "<table>" in html.read_text()
    table = pd.read_csv(md.with_suffix(".csv"))  # every test, for other tools
    primary = table[(table["metric"] == "last10") & (table["question"] == "reservoir-vs-ppo")]
    assert dict(zip(primary["task"], primary["outcome"], strict=True)) == {
        "Up-v0": "supported", "Down-v0": "contradicted", "Noise-v0": "inconclusive"}  # fmt: skip
    assert primary["p_adjusted"].tolist() == pytest.approx([adjusted[t] for t in primary["task"]])


def test_equivalence_is_said_only_when_both_one_sided_tests_reject(tmp_path: Path) -> None:
    """On made-up data: the same returns are equivalent within a wide margin, not within a
    narrow one; the TOST p is scipy's two one-sided Welch tests at the adjusted level; a
    margin set after the results is flagged on the page."""
    from scipy import stats

    near = [v + 1.0 for v in PPO]
    rule = {**RULE, "equivalence": {"adopted": "2026-12-02",
                                    "margins": {"Wide-v0": 20.0, "Narrow-v0": 1.0}}}  # fmt: skip
    tasks = {"Wide-v0": {"ppo": PPO, "res-ppo": near, "random-res-ppo": PPO},
             "Narrow-v0": {"ppo": PPO, "res-ppo": near, "random-res-ppo": PPO},
             "None-v0": {"ppo": PPO, "res-ppo": near, "random-res-ppo": PPO}}  # fmt: skip
    hyp = _hypothesis(tmp_path, tasks, rule=rule, finished="2026-11-30T10:00:00+00:00")
    md, _ = write_reproduction_page([hyp], tmp_path / "r.md", html_page=False)
    table = pd.read_csv(md.with_suffix(".csv")).fillna({"equivalence": ""})
    rows = table[(table["metric"] == "last10") & (table["comparison"] == "res-ppo − ppo")]
    rows = rows.set_index("task")
    assert rows["outcome"].eq("inconclusive").all()
    assert rows.at["Wide-v0", "equivalence"] == "equivalent"
    assert rows.at["Narrow-v0", "equivalence"] == "not shown either way"
    assert rows.at["None-v0", "equivalence"] == "" and np.isnan(rows.at["None-v0", "margin"])
    for task, margin in (("Wide-v0", 20.0), ("Narrow-v0", 1.0)):
        a, b = np.array(near), np.array(PPO)
        p = max(
            stats.ttest_ind(a + margin, b, equal_var=False, alternative="greater").pvalue,
            stats.ttest_ind(a - margin, b, equal_var=False, alternative="less").pvalue,
        )
        assert rows.at[task, "tost_p"] == pytest.approx(p)
        inside = -margin < rows.at[task, "equiv_low"] and rows.at[task, "equiv_high"] < margin
        assert inside == (p <= rows.at[task, "level"]) == (task == "Wide-v0")
    text = md.read_text()
    assert "equivalent within ±20 (TOST p" in text
    assert "equivalence within ±1 not shown either way (TOST p" in text
    assert (
        "**Flag: the equivalence margins were set after the data.** Margins adopted 2026-12-02"
        in text
    )
    with pytest.raises(VerdictError, match=r"equivalence.margins.A-v0: a positive number"):
        VerdictRule.from_doc({**RULE, "equivalence": {"adopted": "2026-12-02",
                                                      "margins": {"A-v0": 0}}})  # fmt: skip


def test_holm_adjusts_and_stops_where_a_test_is_kept() -> None:
    from ermrl.analysis import holm

    adjusted, levels = holm([0.001, 0.2, 0.01, 0.03], 0.05)
    assert adjusted == pytest.approx([0.004, 0.2, 0.03, 0.06])
    # Ranks 1-2 rejected at 0.05/4, 0.05/3; rank 3 (p 0.03 > 0.05/2) stops: it and rank 4 are
    # judged at 0.025.
    assert levels == pytest.approx([0.0125, 0.025, 0.05 / 3, 0.025])
    # A tiny p is adjusted, not rounded away: the page printed H2 Ant-v5's 7 x 9.9e-23 as 0.
    assert holm([9.89e-23, 0.5], 0.05)[0] == [1.978e-22, 0.5]
    assert holm([0.03, 0.03], 0.05)[0] == [0.06, 0.06]  # not 0.060000000000000005


@pytest.mark.parametrize(("d", "seeds"), [(1.0, 17), (0.5, 64), (0.8, 26)])
def test_seeds_for_power_match_the_t_test_tables(d: float, seeds: int) -> None:
    from ermrl.analysis import seeds_for_power

    assert seeds_for_power(d * 10.0, 10.0, 10.0, 0.05, 0.8) == seeds
    assert seeds_for_power(0.0, 1.0, 1.0, 0.05) is None


def test_probability_of_improvement_is_rliables() -> None:
    from ermrl.analysis import probability_of_improvement

    poi, low, high = probability_of_improvement(
        {"a": ([1.0, 2.0, 3.0], [0.0, 0.0, 0.0]), "b": ([1.0, 1.0], [1.0, 2.0])},
        n_resamples=2000,
    )
    # Task a: every pair won (1); task b: ties count one half, losses 0 -> (0.5 + 0 + 0.5 + 0) / 4.
    assert poi == pytest.approx((1.0 + 0.25) / 2)
    assert low <= poi <= high and 0.5 <= low and high <= 0.75


def test_an_untraceable_selection_is_refused_naming_what_is_missing(tmp_path: Path) -> None:
    from ermrl.analysis import untraceable_tasks

    good = _hypothesis(tmp_path / "a", {"Up-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE}})
    lost = _hypothesis(tmp_path / "b", {"Lost-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE}},
                       reevaluated=None)  # fmt: skip
    other = _hypothesis(tmp_path / "c", {"Other-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE}},
                        reevaluated=3)  # fmt: skip
    md, _ = write_reproduction_page(
        [good, Hypothesis("h2", "h2.yaml", None, None, lost.tasks + other.tasks, lost.rule)],
        tmp_path / "r.md",
    )
    text = md.read_text()
    assert "### Lost-v0" in text and "**Not rendered: the tested trial cannot be traced" in text
    assert "holds no re-evaluation record" in text
    assert "ranks trial #3 best" in text
    rows = _tests_of(md)
    assert ("Up-v0", "res-ppo − ppo", "last10") in rows
    assert not any(key[0] in ("Lost-v0", "Other-v0") for key in rows)
    refused = untraceable_tasks([good, lost])
    assert len(refused) == 1 and refused[0].startswith("h Lost-v0: tested trial #7")
    # A trial named by hand is traced to that choice; the best evolution fitness to the study.
    hand = _hypothesis(tmp_path / "d", {"Hand-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE}},
                       selection="trial 7 (--trial)", reevaluated=None)  # fmt: skip
    best = _hypothesis(tmp_path / "e", {"Best-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE}},
                       selection="best evolution fitness (no re-evaluation)", reevaluated=None)  # fmt: skip
    assert untraceable_tasks([hand, best]) == []


def test_a_selected_reference_is_not_tested_against_itself(tmp_path: Path) -> None:
    """When the selection chose the unevolved reference, res-ppo and random-res-ppo are the same
    runs: no test, outside the family (m counts only the tests made)."""
    same = OVERLAPPING
    hyp = _hypothesis(tmp_path, {"Ref-v0": {"ppo": PPO, "res-ppo": same, "random-res-ppo": same}},
                      reference=True)  # fmt: skip
    md, _ = write_reproduction_page([hyp], tmp_path / "r.md")
    row = _tests_of(md)[("Ref-v0", "res-ppo − random-res-ppo", "last10")]
    assert row[12] == "**not tested**" and row[4] == "–"
    assert "selection chose the unevolved reference itself" in row[13]
    assert _tests_of(md)[("Ref-v0", "res-ppo − ppo", "last10")][8].endswith("(1)")


def test_runs_two_files_share_are_tested_once(tmp_path: Path) -> None:
    """A second file whose selection is the reference, and whose runs are the first file's (the
    same per-seed returns, found from the data): its tests on those runs are not made again, so
    each counts once in its family, and a baseline that is its own candidate is not tested."""
    first = _hypothesis(tmp_path / "a", {"Pen-v0": {"ppo": PPO, "res-ppo": OVERLAPPING,
                                                   "random-res-ppo": OVERLAPPING}},
                        reference=True)  # fmt: skip
    other = str(tmp_path / "a" / "pub" / "Pen-v0" / "test")
    rule = {**RULE, "questions": {**RULE["questions"], "vs-other": {
        "text": "does it beat the other file's reservoir?", "compare": ["res-ppo - other-res"]}},
        "references": {"other-res": {"agent": "res-ppo", "tests": {"Pen-v0": other}}}}  # fmt: skip
    # The second file re-ran the same setting: 6 of its 8 seeds are the first file's runs.
    again = [v + (0.5 if i < 2 else 0.0) for i, v in enumerate(OVERLAPPING)]
    second = _hypothesis(tmp_path / "b", {"Pen-v0": {"ppo": PPO, "res-ppo": again,
                                                    "random-res-ppo": again}},
                         rule=rule, reference=True)  # fmt: skip
    second = Hypothesis("h2", "h2.yaml", None, None, second.tasks, second.rule)
    md, _ = write_reproduction_page([first, second], tmp_path / "r.md", html_page=False)
    table = pd.read_csv(md.with_suffix(".csv"))
    rows = table[table["metric"] == "last10"].set_index(["hypothesis", "comparison"])
    assert rows.at[("h", "res-ppo − ppo"), "outcome"] == "inconclusive"
    assert rows.at[("h", "res-ppo − ppo"), "family_size"] == 1  # counted once
    copy = rows.loc[("h2", "res-ppo − ppo")]
    assert copy["outcome"] == "not tested"
    assert "the same runs as h Pen-v0's `res-ppo − ppo`" in copy["note"]
    assert "`res-ppo` on seeds 12–17" in copy["note"] and "the selection is the" in copy["note"]
    itself = rows.loc[("h2", "res-ppo − other-res")]
    assert itself["outcome"] == "not tested"
    assert "are the same runs on seeds 12–17 (6 of 8)" in itself["note"]
    text = md.read_text()
    assert "**Shared runs**" in text and "h Pen-v0 `ppo` and h2 Pen-v0 `ppo` on seeds 10–17" in text
    assert (
        "| h2 | does res-ppo beat ppo? | not tested on its one task | Pen-v0: not tested |" in text
    )


def test_families_pool_across_files_and_must_agree(tmp_path: Path) -> None:
    from ermrl.analysis import VerdictError

    one = _hypothesis(tmp_path / "a", {"A-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE}})
    two = _hypothesis(tmp_path / "b", {"B-v0": {"ppo": PPO, "res-ppo": OVERLAPPING}})
    two = Hypothesis("h2", "h2.yaml", None, None, two.tasks, two.rule)
    md, _ = write_reproduction_page([one, two], tmp_path / "r.md")
    assert _tests_of(md)[("A-v0", "res-ppo − ppo", "last10")][8].endswith("(2)")
    strict = VerdictRule.from_doc({**RULE, "alpha": 0.01})
    with pytest.raises(VerdictError, match="differ in alpha or correction"):
        write_reproduction_page(
            [one, Hypothesis("h2", "h2.yaml", None, None, two.tasks, strict)], tmp_path / "x.md"
        )


def test_a_baseline_published_by_another_file_is_compared_as_it_is(tmp_path: Path) -> None:
    """references: another experiment's published res-ppo runs enter the page under a name of
    their own, are compared like the task's own runs, and are not counted as this phase's."""
    from ermrl.analysis import VerdictError

    _publish(tmp_path / "other" / "Up-v0", {"res-ppo": PPO})
    other = str(tmp_path / "other" / "Up-v0" / "test")
    rule = {**RULE, "questions": {**RULE["questions"], "vs-other": {
        "text": "does it beat the other file's reservoir?", "compare": ["res-ppo - other-res"]}},
        "references": {"other-res": {"agent": "res-ppo", "tests": {"Up-v0": other}}}}  # fmt: skip
    hyp = _hypothesis(tmp_path, {"Up-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE}}, rule=rule)
    md, _ = write_reproduction_page([hyp], tmp_path / "r.md")
    row = _tests_of(md)[("Up-v0", "res-ppo − other-res", "last10")]
    assert row[12] == "**supported**" and row[3] == "8 / 8"
    assert float(row[4]) == pytest.approx(np.mean(CLEARLY_ABOVE) - np.mean(PPO), rel=1e-3)
    text = md.read_text()
    assert f"`other-res`: the published runs of `res-ppo` of `{other}`" in text
    # 16 own runs of 1M steps; the borrowed 8 are not this test phase's.
    assert "Test phase: 16M env steps" in text and "(the borrowed runs not counted)" in text
    # Another budget is another setting: refused in one line.
    record = Path(other) / "agents" / "res-ppo" / "seed_10" / "result.json"
    record.write_text(record.read_text().replace("1000000", "300000"))
    with pytest.raises(VerdictError, match=r"other-res \(Up-v0\): .* env_steps \[300000, "):
        write_reproduction_page([hyp], tmp_path / "x.md")
    missing = {
        **rule,
        "references": {"other-res": {"agent": "lstm-ppo", "tests": {"Up-v0": other}}},
    }
    hyp = _hypothesis(tmp_path / "m", {"Up-v0": {"ppo": PPO, "res-ppo": PPO}}, rule=missing)
    with pytest.raises(VerdictError, match="no finished run of lstm-ppo in"):
        write_reproduction_page([hyp], tmp_path / "y.md")
    # A name the task's own runs already use would mix two groups: refused.
    clash = {**rule, "references": {"ppo": {"agent": "res-ppo", "tests": {"Up-v0": other}}}}
    hyp = _hypothesis(tmp_path / "c", {"Up-v0": {"ppo": PPO, "res-ppo": PPO}}, rule=clash)
    with pytest.raises(VerdictError, match="the task has runs of its own named ppo"):
        write_reproduction_page([hyp], tmp_path / "z.md")


def test_a_rule_written_after_the_first_result_is_flagged(tmp_path: Path) -> None:
    tasks = {"Up-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE}}
    early = _hypothesis(tmp_path / "a", tasks, finished="2026-11-20T10:00:00+00:00")
    text = write_reproduction_page([early], tmp_path / "a.md")[0].read_text()
    assert "**Flag: the rule was written after results existed.**" in text
    assert "Rule adopted 2026-11-28; first test result 2026-11-20" in text
    later = _hypothesis(tmp_path / "b", tasks, finished="2026-12-01T10:00:00+00:00")
    text = write_reproduction_page([later], tmp_path / "b.md")[0].read_text()
    assert "Flag" not in text and "first test result 2026-12-01" in text


def test_last100_is_read_from_the_episodes_of_runs_that_predate_it(tmp_path: Path) -> None:
    from ermrl.analysis import load_test_runs

    folder = tmp_path / "T-v0"
    _publish(folder, {"ppo": [1.0, 2.0]}, last100=False)
    episodes = "env_step,episode_return\n" + "".join(f"{k},{k}\n" for k in range(1, 151))
    (folder / "test/agents/ppo/seed_10/episodes.csv").write_text(episodes)
    runs = load_test_runs(folder / "test").set_index("seed")
    assert runs.loc[10, "last100_return"] == pytest.approx(np.mean(np.arange(51, 151)))


def test_returns_at_step_reads_what_each_run_had_learned_by_then(tmp_path: Path) -> None:
    """The last 10 training episodes ended by the step, per run; NaN where none had ended."""
    from ermrl.analysis import returns_at_step

    folder = tmp_path / "T-v0"
    _publish(folder, {"ppo": [1.0, 2.0], "res-ppo": [5.0]})
    # Seed 10: an episode every 10 steps, returning its end step; seed 11 starts at step 500.
    rows = "".join(f"{k},{k}\n" for k in range(10, 1001, 10))
    (folder / "test/agents/ppo/seed_10/episodes.csv").write_text("env_step,episode_return\n" + rows)
    late = "".join(f"{k},{-k}\n" for k in range(500, 1001, 100))
    (folder / "test/agents/ppo/seed_11/episodes.csv").write_text("env_step,episode_return\n" + late)
    at = returns_at_step(folder / "test", 300, agent="ppo").set_index("seed")["return_at_step"]
    assert at[10] == pytest.approx(np.mean(np.arange(210, 301, 10)))  # 210..300: the last 10
    assert np.isnan(at[11])
    assert returns_at_step(folder / "test", 700, n=2, agent="ppo").set_index("seed").loc[
        11, "return_at_step"
    ] == (pytest.approx(-650.0))
    # res-ppo's one episode ended at step 3 with return 5; agent= reads that agent's runs only.
    assert (
        returns_at_step(folder / "test", 300).set_index("agent").loc["res-ppo", "return_at_step"]
        == 5.0
    )
    only = returns_at_step(folder / "test", 300, agent="ppo")
    assert sorted(only["seed"]) == [10, 11] and set(only["agent"]) == {"ppo"}
    assert returns_at_step(folder / "test", 300, agent="lstm-ppo").empty
    with pytest.raises(ValueError, match="step and n must be positive"):
        returns_at_step(folder / "test", 0)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"alpha": 1.5}, "alpha: a number in (0, 1)"),
        ({"correction": "bonferroni"}, "correction: one of holm, none"),
        ({"primary": "median"}, "primary: one of last10, last100, eval"),
        ({"adopted": "yesterday"}, "adopted: a date"),
        ({"questions": {}}, "questions: name at least one question"),
        ({"questions": {"q": {"compare": ["res-ppo vs ppo"]}}}, "is not 'CANDIDATE - BASELINE'"),
        ({"alpah": 0.05}, "unknown key 'alpah'"),
        ({"references": {"x": {"agent": "res-ppo"}}}, "references.x: a mapping with exactly"),
        ({"references": {"x": {"agent": "res-ppo", "tests": ["a"]}}}, "x.tests: a mapping TASK"),
        ({"references": {"x": {"agent": 3, "tests": {"A": "b"}}}}, "x.agent: an agent name"),
    ],
)
def test_a_bad_verdict_block_is_one_line(change: dict, message: str) -> None:
    from ermrl.analysis import VerdictError

    with pytest.raises(VerdictError, match=re.escape(message)):
        VerdictRule.from_doc({**RULE, **change})


def judged(*rows: tuple[str, str, str, float, str]) -> pd.DataFrame:
    """A page's tests: (task, metric, outcome, mean_diff, note) of H1's reservoir-vs-ppo."""
    return pd.DataFrame(
        [
            {"hypothesis": "paper-h1", "task": task, "question": "reservoir-vs-ppo",
             "comparison": "res-ppo − ppo", "metric": metric, "outcome": outcome,
             "n_candidate": 5, "n_baseline": 5, "mean_diff": diff, "p_adjusted": 0.5,
             "seeds_needed": 40, "note": note}
            for task, metric, outcome, diff, note in rows
        ]
    )  # fmt: skip


def test_verdict_changes_names_what_moved_appeared_and_went() -> None:
    before = judged(
        ("CartPole-v1", "last10", "inconclusive", 10.0, ""),
        ("CartPole-v1", "eval", "inconclusive", 1.0, ""),
        ("Pendulum-v1", "last10", "inconclusive", 0.0, "not run yet: ppo has no finished run"),
        ("Old-v0", "last10", "supported", 3.0, ""),
    )
    after = judged(
        ("CartPole-v1", "last10", "supported", 12.0, ""),
        ("CartPole-v1", "eval", "inconclusive", 2.0, ""),
        ("Pendulum-v1", "last10", "inconclusive", -1.0, ""),
        ("Hopper-v5", "last10", "contradicted", -5.0, ""),
    )
    changes = verdict_changes(before, after)
    got = {(r["task"], r["metric"]): r for r in changes.to_dict("records")}
    assert got["CartPole-v1", "last10"]["change"] == "moved"
    assert got["CartPole-v1", "last10"]["mean_diff_before"] == 10.0
    assert got["CartPole-v1", "last10"]["mean_diff_after"] == 12.0
    assert got["CartPole-v1", "eval"]["change"] == "same"
    # A comparison that could not run has no verdict: running it moves it.
    assert got["Pendulum-v1", "last10"]["outcome_before"] == NOT_RUN
    assert got["Pendulum-v1", "last10"]["change"] == "moved"
    assert got["Hopper-v5", "last10"]["change"] == "new"
    assert pd.isna(got["Hopper-v5", "last10"]["outcome_before"])
    assert got["Old-v0", "last10"]["change"] == "gone"
    # The later page's order, then what only the earlier one has.
    assert list(changes["task"]) == ["CartPole-v1", "CartPole-v1", "Pendulum-v1", "Hopper-v5",
                                     "Old-v0"]  # fmt: skip
    with pytest.raises(VerdictError, match="before table has no column outcome"):
        verdict_changes(before.drop(columns="outcome"), after)


def test_the_command_reads_the_paper_files(tmp_path: Path) -> None:
    # An earlier page: one verdict the paper files now judge otherwise, one they no longer have.
    before = judged(
        ("CartPole-v1", "last10", "contradicted", -1.0, ""),
        ("Old-v0", "last10", "supported", 3.0, ""),
    )
    before.to_csv(tmp_path / "before.csv", index=False)
    done = subprocess.run(
        [sys.executable, "-m", "ermrl", "reproduction",
         *map(str, sorted((ROOT / "experiments" / "paper").glob("*.yaml"))),
         "--out", str(tmp_path / "r.md"), "--compare", str(tmp_path / "before.csv"),
         "--changes", str(tmp_path / "changes.csv")],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    text = (tmp_path / "r.md").read_text()
    for name in ("paper-h1", "paper-h2", "paper-h3"):
        assert name in text
    assert "**Rule** (`verdict:` block of" in text
    assert (tmp_path / "r.html").exists()
    page = pd.read_csv(tmp_path / "r.csv")
    changes = pd.read_csv(tmp_path / "changes.csv")
    assert len(changes) == len(page) + 1
    assert "1 moved" in done.stdout and "1 gone" in done.stdout
    assert re.search(r"^ *change +hypothesis .* p_adj +n80$", done.stdout, re.M), done.stdout
    assert f"{len(page) - 1} new" in done.stdout
    moved = changes[changes["change"] == "moved"].iloc[0]
    assert (moved["task"], moved["metric"], moved["outcome_before"]) == (
        "CartPole-v1", "last10", "contradicted")  # fmt: skip
    assert re.search(r"moved\s+paper-h1\s+CartPole-v1\s+res-ppo − ppo\s+last10\s+contradicted",
                     done.stdout)  # fmt: skip


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--changes", "c.csv"], "--changes needs --compare BEFORE.csv"),
        (["--compare", "missing.csv"], "cannot read missing.csv"),
    ],
)
def test_compare_options_fail_in_one_line(
    tmp_path: Path, args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from ermrl.cli._reproduction import reproduction_main

    with pytest.raises(SystemExit) as exit_info:
        reproduction_main(["experiments/paper/h1_partial_observability.yaml",
                           "--out", str(tmp_path / "r.md"), *args])  # fmt: skip
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "r.md").exists()


def test_a_multi_timescale_selection_shows_its_band_of_leak_rates() -> None:
    from ermrl.analysis._reproduction import _reservoir_text

    band = {"units": 100, "sr": 0.02, "lr": 0.001, "lr_max": 0.25, "input_scaling": 1.0}
    text = _reservoir_text({"trial": 7, "selection": "re-evaluated", "reservoirs": [band]})
    assert text == "trial #7 (re-evaluated): reservoir 0: sr 0.02, lr 0.001, lr_max 0.25, " \
        "input_scaling 1 (100 units)"  # fmt: skip


def test_a_task_evolving_or_not_started_says_which(tmp_path: Path) -> None:
    """A task with no test phase yet: "Not tested yet" once its evolution has finished trials
    (with how many), "Not run yet" before."""
    hyp = _hypothesis(tmp_path, {"Done-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE,
                                             "random-res-ppo": PPO}})  # fmt: skip
    files = []
    for label, trials in (("Evolving-v0", 2), ("Fresh-v0", 0)):
        folder = tmp_path / "pub" / label
        folder.mkdir(parents=True)
        snapshot = folder / "study.json"
        done = [{"number": i, "state": "COMPLETE", "value": 1.0,
                 "user_attrs": {"env_steps": 900_000, "wall_seconds": 60.0}}
                for i in range(trials)]  # fmt: skip
        snapshot.write_text(json.dumps({"trials": done, "user_attrs": {}, "related": {}}))
        files.append(TaskFiles(label, label, folder, snapshot, 10))
    hyp = dataclasses.replace(hyp, tasks=hyp.tasks + tuple(files))
    md, _ = write_reproduction_page([hyp], tmp_path / "r.md")
    text = md.read_text()
    evolving = text.split("### Evolving-v0")[1].split("###")[0]
    assert "**Not tested yet.** Evolution: 2/10 trials finished, 1.8M env steps" in evolving
    assert "The test phase has not run." in evolving
    fresh = text.split("### Fresh-v0")[1].split("###")[0]
    assert "**Not run yet.** Evolution: 0/10 trials finished." in fresh


def test_a_test_phase_published_in_part_gets_no_verdict_until_every_planned_run_is_in(
    tmp_path: Path,
) -> None:
    """Judging the seeds that happen to have finished would let the stopping point choose the
    result: a task short of the runs its file plans is described, not judged, and stays out of
    the Holm family; once every planned run is in, it is judged like the others."""
    values = {"ppo": PPO, "res-ppo": CLEARLY_ABOVE, "random-res-ppo": PPO}  # seeds 10-17
    hyp = _hypothesis(tmp_path, {"Whole-v0": values, "Part-v0": values})
    agents = ("ppo", "res-ppo", "random-res-ppo")

    def page(seeds: range) -> tuple[str, dict, pd.DataFrame]:
        part = dataclasses.replace(hyp.tasks[1], planned={a: tuple(seeds) for a in agents})
        md, _ = write_reproduction_page(
            [dataclasses.replace(hyp, tasks=(hyp.tasks[0], part))], tmp_path / "r.md"
        )
        return md.read_text(), _tests_of(md), pd.read_csv(md.with_suffix(".csv"))

    text, rows, table = page(range(10, 20))  # 2 of 10 planned seeds still missing per agent
    section = text.split("### Part-v0")[1]
    assert "**Test in progress: 24 of the 30 planned runs published** (`ppo` 8/10, " \
        "`res-ppo` 8/10, `random-res-ppo` 8/10). No verdict until every planned run is in" \
        in section  # fmt: skip
    assert "| res-ppo |" in section  # what is published is still shown
    assert set(table["task"]) == {"Whole-v0"} and ("Part-v0", "res-ppo − ppo", "last10") not in rows
    assert rows[("Whole-v0", "res-ppo − ppo", "last10")][8].endswith("(1)")  # a family of 1
    assert "Part-v0" not in text.split("### Whole-v0")[0]  # not in the verdicts at a glance

    text, rows, table = page(range(10, 18))  # every planned run published
    assert "Test in progress" not in text
    assert set(table["task"]) == {"Whole-v0", "Part-v0"}
    assert rows[("Part-v0", "res-ppo − ppo", "last10")][12] == "**supported**"
    assert rows[("Whole-v0", "res-ppo − ppo", "last10")][8].endswith("(2)")


def test_the_readme_results_table_is_the_pages() -> None:
    """README.md's and docs/getting-started.md's results are the table `ermrl reproduction
    --summary-in` writes from docs/reproduction.csv, not typed: regenerate the page with
    --summary-in README.md docs/getting-started.md when this fails."""
    from ermrl.analysis import read_summary, results_summary
    from ermrl.runner._experiment import hypothesis_of, load_experiment

    files = [*sorted((ROOT / "experiments" / "paper").glob("*.yaml")),
             ROOT / "experiments" / "multiscale.yaml"]  # fmt: skip
    hypotheses = [hypothesis_of(load_experiment(f), str(f.relative_to(ROOT))) for f in files]
    expected = results_summary(pd.read_csv(ROOT / "docs" / "reproduction.csv"), hypotheses)
    for name in ("README.md", "docs/getting-started.md"):
        assert read_summary(ROOT / name) == expected, f"{name}'s results table is not the page's"


def test_the_results_table_marks_metrics_that_disagree(tmp_path: Path) -> None:
    from ermrl.analysis import question_answer, read_summary, results_summary, write_summary

    tasks = {"Up-v0": {"ppo": PPO, "res-ppo": CLEARLY_ABOVE, "random-res-ppo": PPO},
             "Noise-v0": {"ppo": PPO, "res-ppo": OVERLAPPING, "random-res-ppo": PPO}}  # fmt: skip
    hyp = _hypothesis(tmp_path, tasks)
    md, _ = write_reproduction_page([hyp], tmp_path / "r.md", html_page=False)
    table = pd.read_csv(md.with_suffix(".csv"))
    # Make eval disagree on Up-v0, as a file could: the mark must show it.
    flip = (table["task"] == "Up-v0") & (table["metric"] == "eval")
    table.loc[flip, "outcome"] = "inconclusive"
    summary = results_summary(table, [hyp])
    assert (
        "| h | does res-ppo beat ppo? | mixed: supported on 1 of 2 tasks, inconclusive on 1 |"
        in summary
    )
    assert "Up-v0: supported [eval: inconclusive]; Noise-v0: inconclusive |" in summary
    readme = tmp_path / "README.md"
    readme.write_text("intro\n<!-- reproduction:start -->\nold\n<!-- reproduction:end -->\nend\n")
    assert write_summary(readme, summary) and read_summary(readme) == summary
    assert readme.read_text().startswith("intro\n") and readme.read_text().endswith("end\n")
    assert not write_summary(readme, summary)  # unchanged
    (tmp_path / "bare.md").write_text("no markers\n")
    with pytest.raises(VerdictError, match="no <!-- reproduction:start -->"):
        write_summary(tmp_path / "bare.md", summary)
    assert question_answer(["contradicted"] * 3) == "contradicted on all 3 tasks"
    # The glance table answers each sub-question in one line by the same rule.
    assert "| mixed: supported on 1 of 2 tasks, inconclusive on 1 |" in md.read_text()


def test_the_verdicts_on_the_seeds_run_after_the_rule_flag_what_changes(tmp_path: Path) -> None:
    """Seeds 10-13 finished before the rule (2026-11-28), 14-17 after: the sensitivity check
    judges 14-17 alone and flags the outcome the early seeds carried."""
    early, late = [200.0, 201.0, 199.0, 200.0], [100.0, 95.0, 105.0, 98.0]
    hyp = _hypothesis(tmp_path, {"Up-v0": {"ppo": PPO, "res-ppo": early + late}})
    for result in (tmp_path / "pub" / "Up-v0" / "test" / "agents").glob("*/seed_*/result.json"):
        record = json.loads(result.read_text())
        record["finished"] = "2026-11-20T10:00:00" if record["seed"] < 14 else "2026-12-01T10:00:00"
        result.write_text(json.dumps(record))
    md, _ = write_reproduction_page([hyp], tmp_path / "r.md", html_page=False)
    text = md.read_text()
    section = text.split("### Sensitivity: the seeds run after each rule")[1].split("\n## ")[0]
    assert "h Up-v0: 14–17" in section
    assert (
        "| h | Up-v0 | res-ppo − ppo | last10 | supported (8 / 8) | inconclusive (4 / 4) |"
        in section
    )


def test_groups_of_different_seeds_are_judged_again_on_the_seeds_both_have(
    tmp_path: Path,
) -> None:
    rule = {**RULE, "questions": {"vs-lstm": {"text": "does it beat the LSTM?",
                                              "compare": ["res-ppo - lstm-ppo"]}}}  # fmt: skip
    res = [101.0, 96.0, 104.0, 150.0, 147.0, 153.0, 149.0, 151.0]
    hyp = _hypothesis(tmp_path, {"Up-v0": {"res-ppo": res, "lstm-ppo": PPO[:3]}}, rule=rule)
    md, _ = write_reproduction_page([hyp], tmp_path / "r.md", html_page=False)
    section = md.read_text().split("### Sensitivity: the seeds both groups have")[1]
    section = section.split("\n## ")[0]
    assert "3 comparison(s) set groups of different seeds" in section
    assert (
        "| h | Up-v0 | res-ppo − lstm-ppo | last10 | supported (8 / 3) | inconclusive (3 / 3) |"
        in section
    )
