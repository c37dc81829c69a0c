"""The benchmarks keep working: CI runs them in quick mode (timings are not asserted)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_quick(script: str, *args: str, timeout: float = 900) -> subprocess.CompletedProcess[str]:
    """``python benchmarks/SCRIPT --quick ARGS`` from the repository root; it must succeed."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--quick", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def test_differences_show_welch_and_p_and_flag_few_seeds() -> None:
    """The benchmarks' difference cells: bootstrap CI, Welch's CI and p, and the flag."""
    from benchmarks._harness import difference, format_difference

    d = difference([-700.0, -698.0], [-690.0, -676.0], [0, 1], [0, 1])
    assert d["ci95"][1] < 0 < d["welch_ci95"][1]  # the bootstrap alone would overclaim
    assert d["few_seeds"] == "few seeds (n=2 < 5)" and d["paired_ci95"] is not None
    text = format_difference(d)
    assert "; Welch [" in text and ", p=0." in text and text.endswith("; few seeds (n=2 < 5)")
    five = difference([1.0, 2.0, 3.0, 4.0, 5.0], [0.0, 2.0, 1.0, 3.0, 2.0])
    assert five["few_seeds"] == "" and five["paired_ci95"] is None  # no seeds: not paired
    assert format_difference(difference([], [1.0])) == "-"
    # Results written before Welch's interval was recorded show the bootstrap CI alone.
    assert format_difference({"diff": 1.0, "ci95": [0.5, 1.5]}) == "+1.0 [+0.5, +1.5]"


@pytest.mark.slow
def test_benchmarks_run_in_quick_mode(tmp_path: Path) -> None:
    proc = run_quick("run_all.py", "--results", str(tmp_path), timeout=1500)
    for name in ("encoder", "plan", "trial", "pruning", "workers", "science"):
        data = json.loads((tmp_path / f"{name}.json").read_text())
        assert data["machine"]["cpus"] >= 1
    encoder = json.loads((tmp_path / "encoder.json").read_text())["rows"][0]
    assert (
        encoder["raw_steps_s"] > 0 and encoder["ermrl_steps_s"] > 0 and encoder["node_steps_s"] > 0
    )
    # The encoder's and the node wrapper's own costs, measured over a replayed trajectory.
    assert encoder["ermrl_alone_us"] > 0 and encoder["node_alone_us"] > 0
    assert encoder["alone_cheaper_x"] == pytest.approx(
        encoder["node_alone_us"] / encoder["ermrl_alone_us"]
    )
    plan = json.loads((tmp_path / "plan.json").read_text())["rows"]
    assert [r["variant"] for r in plan][:2] == ["python -c pass", "import ermrl.cli"]
    assert plan[2]["variant"].startswith("dry-run ") and plan[2]["median_s"] > 0
    assert "target" in proc.stdout  # thresholds are printed, not enforced
    # Long runs report each measurement as it ends (on stderr; stdout keeps the tables).
    assert "HalfCheetah-v5 100 units 8 envs repeat 1/" in proc.stderr
    assert "workers (trials/min) repeat 1/1 2 workers:" in proc.stderr
    pruning = json.loads((tmp_path / "pruning.json").read_text())
    assert {s["pruner"] for s in pruning["summary"]} == {"none", "median", "halving"}
    assert all(r["env_steps"] > 0 for r in pruning["rows"])
    # Each study's best parameters are re-trained on fresh seeds (the unbiased comparison).
    assert all(len(r["reeval_returns"]) == len(pruning["reeval_seeds"]) for r in pruning["rows"])
    assert all(isinstance(r["best_reevaluated"], float) for r in pruning["rows"])
    # Science: evolve then test per task; the table and the targets are reported, never enforced.
    science = json.loads((tmp_path / "science.json").read_text())
    assert [t["env_id"] for t in science["tasks"]] == ["Pendulum-v1", "CartPole-v1"]
    for task in science["tasks"]:
        agents = task["test"]["agents"]
        assert set(agents) == {
            "ppo", "ppo-full", "lstm-ppo", "framestack-ppo", "random-res-ppo", "res-ppo"
        }  # fmt: skip
        assert all(len(a["final_returns"]) == 2 for a in agents.values())
        low, high = task["test"]["res_minus_random"]["ci95"]
        assert low <= task["test"]["res_minus_random"]["diff"] <= high
        assert task["evolution"]["reevaluation"]["complete"]
        assert task["evolution"]["selected"]["how"].startswith("re-evaluated best")
        assert task["env_steps"] > 0 and task["wall_seconds"] > 0
    assert "res − random [95% CI]" in science["table"]
    assert "| lstm-ppo | framestack-ppo |" in science["table"]
    assert "targets:" in science["table"]
    trial = json.loads((tmp_path / "trial.json").read_text())["rows"]
    comparisons = {r["comparison"] for r in trial}
    assert "3 seeds: --n-procs 2 (3 procs on 2 cores) / 1 proc" in comparisons
    # Workers: launch to exit, and the steady rate read back from the study's trial times.
    assert {
        "2 workers / 1 worker (trials/min, one SQLite study, launch to exit)",
        "2 workers / 1 worker (trials/min, first trial start to last end)",
    } <= comparisons
    assert all(r["a_steps_s"] > 0 and r["b_steps_s"] > 0 for r in trial if "a_steps_s" in r)


@pytest.mark.slow
def test_the_backend_benchmarks_run_in_quick_mode(tmp_path: Path) -> None:
    """bench_backends and calibrate_backends run end to end and write what they promise."""
    import csv

    run_quick("bench_backends.py", "--tasks", "Pendulum-v1:positions", "--out", str(tmp_path / "b"))
    with (tmp_path / "b" / "backends.csv").open() as fh:
        rows = {r["backend"]: r for r in csv.DictReader(fh)}
    assert set(rows) == {"sb3", "population", "physics"}
    # The physics limit steps the same envs as often as either backend trains them.
    assert (
        rows["sb3"]["env_steps"] == rows["population"]["env_steps"] == rows["physics"]["env_steps"]
    )
    assert rows["physics"]["processes"] == rows["population"]["processes"]
    assert all(float(r["steps_per_s"]) > 0 and r["failed"] == "0" for r in rows.values())
    # The population's time breakdown is measured, and its parts add up to at most its total.
    parts = sum(
        float(rows["population"][k]) for k in ("env_s", "reservoir_s", "policy_s", "update_s")
    )
    assert 0 < parts <= float(rows["population"]["total_s"]) * 1.001
    md = (tmp_path / "b" / "backends.md").read_text()
    assert "population / sb3" in md and "population / physics" in md
    assert ">= 7x" in md  # Pendulum's target

    run_quick("calibrate_backends.py", "--tasks", "CartPole-v1:positions", "CartPole-v1:positions@rtu",
        "CartPole-v1:positions@nvar", "--out", str(tmp_path / "c"))  # fmt: skip
    with (tmp_path / "c" / "runs.csv").open() as fh:
        runs = list(csv.DictReader(fh))
    assert sorted((r["task"], r["backend"], r["seed"]) for r in runs) == sorted(
        (task, backend, seed)
        for task in (
            "CartPole-v1[positions]",
            "CartPole-v1[positions] rtu",
            "CartPole-v1[positions] nvar",
        )
        for backend in ("population", "sb3")
        for seed in ("0", "1")
    )
    assert all(r["last_return"] and not r["error"] for r in runs)
    summary = (tmp_path / "c" / "summary.md").read_text()
    assert "Mann-Whitney" in summary and "| CartPole-v1[positions] rtu | last |" in summary
    assert "Reservoir (rtu): (RTUParams(" in summary
    assert "| CartPole-v1[positions] nvar | eval |" in summary
    assert "Reservoir (nvar): (NVARParams(" in summary


def test_a_quick_backend_run_does_not_replace_the_published_table() -> None:
    """Without --out, --quick writes under runs/ (not committed); a full run writes the
    published benchmarks/results/backends, and --out always wins."""
    from benchmarks.bench_backends import parse_args

    assert parse_args([]).out == "benchmarks/results/backends"
    quick = parse_args(["--quick"]).out
    assert quick.startswith("runs/") and "results" not in quick
    assert parse_args(["--quick", "--out", "elsewhere"]).out == "elsewhere"
    ignored = subprocess.run(
        ["git", "check-ignore", "-q", f"{quick}/backends.md"], cwd=ROOT, check=False
    )
    assert ignored.returncode == 0, f"{quick} is not ignored by git"


@pytest.mark.slow
def test_the_startup_benchmark_times_each_phase_of_a_fresh_worker(tmp_path: Path) -> None:
    """bench_startup starts a real spawn pool and reports each phase before the first step."""
    out = tmp_path / "startup.json"
    run_quick("bench_startup.py", "--out", str(out), timeout=600)
    data = json.loads(out.read_text())
    median = data["median"]
    phases = ("spawn", "import", "model", "first_step")
    assert all(median[k] > 0 for k in (*phases, "envs_again"))
    # The phases run one after another inside the time to the first step (one process here).
    assert sum(median[k] for k in phases) <= median["to_first_step"] * 1.01
    modules = {r["module"] for r in data["imports"]}
    assert {"(all)", "torch"} <= modules


@pytest.mark.slow
def test_the_memory_benchmark_runs_in_quick_mode(tmp_path: Path) -> None:
    """bench_memory evolves an ESN, an RTU and an NVAR, tests the seven agents on the same
    seeds, reports every agent's returns with a CI and its wall time, each evolved memory
    against the baselines (Welch) and the best mean."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_memory.py"), "--quick",
         "--tasks", "popgym-RepeatFirstEasy-v0:all", "--out", str(tmp_path / "memory.json")],
        cwd=ROOT, capture_output=True, text=True, timeout=1200,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    report = json.loads((tmp_path / "memory.json").read_text())
    (task,) = report["tasks"]
    assert task["label"] == "popgym-RepeatFirstEasy-v0[all]"
    agents = task["agents"]
    assert list(agents) == [
        "ppo", "framestack-ppo", "lstm-ppo", "rtu-ppo", "res-ppo", "rtu-res-ppo", "nvar-res-ppo"
    ]  # fmt: skip
    for row in agents.values():
        assert row["seeds"] == [10, 11]
        low, high = row["ci95"]
        assert low <= row["mean"] <= high and row["wall_seconds"] > 0
    assert set(task["selected"]) == {"res-ppo", "rtu-res-ppo", "nvar-res-ppo"}
    assert "rtu-res-ppo: trial #" in report["table"] and "r_max=" in report["table"]
    assert "nvar-res-ppo: trial #" in report["table"] and "delay=" in report["table"]
    pairs = {(c["agent"], c["baseline"]) for c in task["comparisons"]}
    assert ("nvar-res-ppo", "framestack-ppo") in pairs and len(pairs) == 9
    for c in task["comparisons"]:
        mean = agents[c["agent"]]["mean"] - agents[c["baseline"]]["mean"]
        assert c["difference"] == pytest.approx(mean)
    best = max(agents, key=lambda a: agents[a]["mean"])
    assert task["winner"]["agent"] == best
    text = (tmp_path / "memory.md").read_text()
    assert "| rtu-ppo | 2 |" in text and "| nvar-res-ppo | framestack-ppo |" in text
    assert f"best mean: {best}" in text
    # The finished task is published as a plain file; a rerun with the same budgets (here on
    # fewer agents, and without the work folder: another machine) reuses it and trains nothing.
    published = tmp_path / "tasks" / "popgym-RepeatFirstEasy-v0__all.json"
    assert json.loads(published.read_text())["task"]["agents"] == agents
    shutil.rmtree(tmp_path / "work")
    again = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_memory.py"), "--quick",
         "--tasks", "popgym-RepeatFirstEasy-v0:all", "--agents", "ppo", "nvar-res-ppo",
         "--out", str(tmp_path / "again.json")],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert "reusing" in again.stderr and "$ " not in again.stderr  # no ermrl command ran
    (reused,) = json.loads((tmp_path / "again.json").read_text())["tasks"]
    assert reused["agents"] == {a: agents[a] for a in ("ppo", "nvar-res-ppo")}
    assert [(c["agent"], c["baseline"]) for c in reused["comparisons"]] == [("nvar-res-ppo", "ppo")]
    assert set(reused["selected"]) == {"nvar-res-ppo"}
    assert not (tmp_path / "work").exists()


def test_the_memory_benchmark_reuses_a_task_only_with_the_same_budgets(tmp_path: Path) -> None:
    """A published task is reused only when its budgets match and it holds every agent asked
    for; otherwise the task is trained again."""
    from benchmarks.bench_memory import BUDGETS, reusable

    budgets = dict.fromkeys(BUDGETS, 1)
    row = {"final_returns": [1.0, 2.0, 3.0], "mean": 2.0}
    task = {
        "label": "T[all]",
        "studies": {"res-ppo": "s"},
        "agents": {"ppo": dict(row), "res-ppo": {"final_returns": [4.0, 5.0, 6.0], "mean": 5.0}},
        "evolution_seconds": {"res-ppo": 9.0},
        "selected": {"res-ppo": {"trial": 3}},
        "measured": "2026-11-27",
    }
    path = tmp_path / "T__all.json"
    assert reusable(path, budgets, ["ppo"]) is None  # nothing published yet
    path.write_text(json.dumps({"budgets": budgets, "task": task}))
    both = reusable(path, budgets, ["res-ppo", "ppo"])
    assert both is not None and list(both["agents"]) == ["ppo", "res-ppo"]
    assert both["winner"]["agent"] == "res-ppo"
    assert [c["baseline"] for c in both["comparisons"]] == ["ppo"]
    only = reusable(path, budgets, ["ppo"])
    assert only is not None and only["selected"] == {} and only["comparisons"] == []
    assert reusable(path, {**budgets, "test_steps": 2}, ["ppo"]) is None
    assert reusable(path, budgets, ["ppo", "lstm-ppo"]) is None


def test_the_memory_table_of_one_agent_claims_no_ranking() -> None:
    """With one agent (``--agents nvar-res-ppo``) there is no runner-up to be within the noise
    of: the table says so instead of ranking."""
    from benchmarks.bench_memory import format_table, winner

    row = {"final_returns": [1.0, 2.0, 3.0], "mean": 2.0, "std": 1.0, "ci95": [-0.5, 4.5],
           "wall_seconds": 6.0, "env_steps": 30}  # fmt: skip
    task = {
        "label": "T[all]", "agents": {"nvar-res-ppo": row}, "comparisons": [],
        "evolution_seconds": {"nvar-res-ppo": 9.0}, "selected": {},
        "winner": winner({"nvar-res-ppo": row}),
    }  # fmt: skip
    text = format_table({"tasks": [task]})
    assert "only agent: nvar-res-ppo (no comparison)" in text
    assert "runner-up" not in text
    pair = {**task, "agents": {"ppo": row, "nvar-res-ppo": {**row, "mean": 3.0}}}
    pair["winner"] = winner(pair["agents"])
    assert "best mean: nvar-res-ppo, within the noise of the runner-up (ppo)" in format_table(
        {"tasks": [pair]}
    )


@pytest.mark.slow
def test_the_learner_cost_benchmark_runs_in_quick_mode(tmp_path: Path) -> None:
    def run(suite: str) -> dict[str, dict]:
        out = tmp_path / f"{suite}.json"
        proc = subprocess.run(
            [sys.executable, str(ROOT / "benchmarks" / "bench_learner_cost.py"), "--quick",
             "--suite", suite, "--out", str(out)],
            cwd=ROOT, capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        return {s["variant"]: s for s in json.loads(out.read_text())["summary"]}

    rtu = run("rtu")
    assert set(rtu) == {"ppo", "rtu-ppo", "rtu-ppo --no-stale-gradient"}
    assert rtu["ppo"]["vs_ppo"] == 1.0 and rtu["ppo"]["carries_mb"] == 0
    # One 2048-step rollout of carries at d_rec 192: 2 * 192 * 64 + 6 * 192 floats per step.
    assert rtu["rtu-ppo"]["carries_mb"] == pytest.approx(2048 * (2 * 192 * 64 + 6 * 192) * 4 / 1e6)
    assert all(s["steps_per_s"] > 0 for s in rtu.values())
    hebbian = run("hebbian")
    assert set(hebbian) == {"ppo", "hebbian"}
    assert hebbian["hebbian"]["update_share"] is None  # no SB3 rollout/update split
    assert hebbian["hebbian"]["vs_ppo"] == pytest.approx(
        hebbian["hebbian"]["steps_per_s"] / hebbian["ppo"]["steps_per_s"]
    )


@pytest.mark.slow
def test_the_hebbian_benchmark_runs_in_quick_mode(tmp_path: Path) -> None:
    """bench_hebbian evolves the Hebbian genes on Ant-v5, tests hebbian, random-hebbian and ppo
    on the same seeds, and reports CIs of the differences and the zero-action return."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_hebbian.py"), "--quick",
         "--out", str(tmp_path / "hebbian.json")],
        cwd=ROOT, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    report = json.loads((tmp_path / "hebbian.json").read_text())
    assert list(report["agents"]) == ["hebbian", "random-hebbian", "ppo"]
    for row in report["agents"].values():
        assert row["seeds"] == [100, 101] and len(row["final_returns"]) == 2
    diff = report["differences"]["hebbian - random-hebbian"]
    rows = report["agents"]
    assert diff["diff"] == pytest.approx(rows["hebbian"]["mean"] - rows["random-hebbian"]["mean"])
    assert diff["ci95"][0] <= diff["diff"] <= diff["ci95"][1]
    assert len(report["zero_action_returns"]) == 2
    assert all(800 < r <= 1000 for r in report["zero_action_returns"])  # Ant's healthy bonus
    assert set(report["selected"]["params"]) >= {"sigma", "trace_horizon", "learning_rate"}
    assert Path(report["learning_curves"]).is_file()
    assert "| hebbian - random-hebbian |" in (tmp_path / "hebbian.md").read_text()


@pytest.mark.slow
def test_the_learners_benchmark_runs_in_quick_mode(tmp_path: Path) -> None:
    """bench_learners trains a tiny expert, then every learner with and without positions on the
    same seeds, with evaluation checkpoints; it writes the runs, the summary, curves and meta."""
    import csv
    import math

    from ermrl.learners import learner_names

    learners = ["ppo", "sac", "dagger"]
    if "imitation-sac" in learner_names():
        learners.append("imitation-sac")
    out = tmp_path / "learners"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_learners.py"), "--quick",
         "--env-id", "Pendulum-v1", "--train-expert-steps", "300", "--learners", *learners,
         "--out", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for name in ("runs.csv", "summary.csv", "summary.md", "curves.png", "meta.json"):
        assert (out / name).is_file(), name
    with (out / "runs.csv").open() as fh:
        runs = list(csv.DictReader(fh))
    assert sorted((r["learner"], r["observe"], r["seed"]) for r in runs) == sorted(
        (name, observe, seed)
        for name in learners
        for observe in ("all", "positions")
        for seed in ("200", "201")
    )
    for r in runs:
        assert r["error"] == "", r["error"]
        for key in ("final_eval_return", "last10_return", "return_at_25pct", "wall_seconds"):
            if key == "last10_return" and r["learner"] in ("dagger", "imitation-sac"):
                continue  # the expert acts in every episode of 1000 steps: none is the learner's
            assert math.isfinite(float(r[key])), (key, r)
        assert int(r["env_steps"]) >= 1000
        steps = [step for step, _ in json.loads(r["checkpoints"])]
        assert steps == [250, 500, 750, 1000]
        # The 25% return is the checkpoint at 250 steps.
        assert float(r["return_at_25pct"]) == json.loads(r["checkpoints"])[0][1]
        if r["steps_to_expert"]:
            assert int(r["steps_to_expert"]) in steps
    with (out / "summary.csv").open() as fh:
        summary = list(csv.DictReader(fh))
    assert len(summary) == 2 * len(learners)
    for row in summary:
        assert row["n_runs"] == "2"
        low, mean, high = (float(row[k]) for k in ("final_ci_low", "final_mean", "final_ci_high"))
        assert low <= mean <= high
        assert math.isfinite(float(row["at25_mean"]))
    meta = json.loads((out / "meta.json").read_text())
    assert meta["expert"]["steps"] == 300 and math.isfinite(meta["expert"]["eval_return"])
    assert meta["expert"]["trained_here_seconds"] > 0
    assert meta["checkpoints"] == [250, 500, 750, 1000]
    assert "| imitation-sac |" in proc.stdout or "imitation-sac" not in learners


def test_the_fault_pass_lists_its_cases_and_counts_each_problem(tmp_path: Path) -> None:
    """Every case the reliability round named is in the fault pass, and a case's problems are
    counted in the summary and written to the CSV (no command run here)."""
    from benchmarks import fault_pass

    names = {f"{c.family}/{c.name}" for c in fault_pass.cases()}
    families = {name.split("/")[0] for name in names}
    assert {f.split("-")[0] for f in families} == {str(i) for i in range(1, 19)}
    assert set(fault_pass.QUICK) <= names
    # Glued records, as sed '/"op_code":4/{N;s/\n//}' makes them.
    assert (
        fault_pass._glue('{"op_code": 4}\n{"a": 1}\n{"b": 2}\n')
        == '{"op_code": 4}{"a": 1}\n{"b": 2}\n'
    )
    # A library's warning (and its source line) is not one more line of a one-line error.
    err = "lib.py:3: UserWarning: few trials\n  warn(\nermrl report: error: bad\n"
    assert fault_pass._said(err) == ["ermrl report: error: bad"]
    assert fault_pass._storage_names("sqlite:///disk/s.db") == ["disk/s.db"]
    ok = {"family": "f", "case": "a", "rc": "0", "seconds": 1.0, "outcome": "ok",
          **dict.fromkeys((*fault_pass.COUNTS, "hang", "other"), 0)}  # fmt: skip
    bad = {**ok, "case": "b", "traceback": 2, "outcome": "traceback in evolve: ValueError"}
    skipped = {**ok, "case": "c", "outcome": "skipped (needs redis)", "traceback": ""}
    assert fault_pass.report([ok, bad, skipped], tmp_path, 1.0) == 1
    assert fault_pass.report([ok, skipped], tmp_path, 1.0) == 0
    rows = (tmp_path / "fault_pass.csv").read_text().splitlines()
    assert rows[0].startswith("family,case,rc,traceback,bricked,code-run,files-left,trials-lost")
    assert len(rows) == 3


@pytest.mark.slow  # three command start-ups (a few seconds each on a loaded machine)
def test_the_fault_pass_runs_in_quick_mode(tmp_path: Path) -> None:
    proc = run_quick("fault_pass.py", "--out", str(tmp_path), timeout=300)
    assert "| traceback | 0 |" in proc.stdout and "| files-left | 0 |" in proc.stdout
    rows = (tmp_path / "fault_pass.csv").read_text().splitlines()
    assert len(rows) == 4 and all(row.endswith(",ok") for row in rows[1:]), rows


@pytest.mark.slow
def test_the_blas_benchmark_runs_in_quick_mode(tmp_path: Path) -> None:
    """bench_blas trains one generation under the CPU's own OpenBLAS kernel and the pinned one."""
    run_quick("bench_blas.py", "--tasks", "Pendulum-v1:positions", "--out", str(tmp_path))
    row = json.loads((tmp_path / "blas.json").read_text())["rows"][0]
    assert row["task"] == "Pendulum-v1:positions" and row["runs"] == 2
    assert row["native_kernel"] and row["native_steps_per_s"] > 0 < row["pinned_steps_per_s"]
    assert row["pinned_over_native"] == pytest.approx(
        row["pinned_steps_per_s"] / row["native_steps_per_s"], rel=0.01
    )
    if row["native_kernel"].lower() == "haswell":  # one variant: the same kernel, same returns
        assert row["same_returns"] is True


def test_published_groups_compare_with_welch_and_bootstrap(tmp_path: Path) -> None:
    """compare_published.py: groups from two folders, the difference and its intervals as
    scipy's Welch test gives them, and one-line errors for a bad group."""
    from scipy import stats

    values = {"a": [10.0, 12.0, 11.0, 13.0, 9.0], "b": [1.0, 2.0, 0.0, 3.0, 1.5]}
    for folder, agent in (("one", "a"), ("two", "b")):
        for i, v in enumerate(values[agent]):
            run = tmp_path / folder / "agents" / "res-ppo" / f"seed_{10 + i}"
            run.mkdir(parents=True)
            (run / "result.json").write_text(json.dumps(
                {"agent": "res-ppo", "seed": 10 + i, "final_return": v, "last100_return": v,
                 "eval_return": v}))  # fmt: skip
            # By step 100 each run had returned v / 2 (then v): --at-step 100 reads the half.
            (run / "episodes.csv").write_text(f"env_step,episode_return\n100,{v / 2}\n200,{v}\n")
    script = str(ROOT / "benchmarks" / "compare_published.py")
    out = tmp_path / "cmp.csv"
    proc = subprocess.run(
        [sys.executable, script, f"a={tmp_path / 'one'}:res-ppo", f"b={tmp_path / 'two'}:res-ppo",
         "--candidate", "a", "--baselines", "b", "--at-step", "100", "--out", str(out)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "no multiple-comparison correction" in proc.stdout
    table = pd.read_csv(out).set_index("metric")
    assert table.loc["last10", "mean_diff"] == pytest.approx(11.0 - 1.5)
    p = stats.ttest_ind(values["a"], values["b"], equal_var=False).pvalue
    assert table.loc["last10", "p_value"] == pytest.approx(p)
    assert table.loc["last10", "welch_ci_low"] > 0 and table.loc["eval", "n_candidate"] == 5
    assert table.loc["last10@100", "mean_diff"] == pytest.approx((11.0 - 1.5) / 2)
    bad = subprocess.run(
        [sys.executable, script, f"a={tmp_path / 'one'}:lstm-ppo", "--candidate", "a",
         "--baselines", "a"], capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert bad.returncode == 2 and "a: no finished run of lstm-ppo in" in bad.stderr
    assert len(bad.stderr.strip().splitlines()[-1]) < 200
