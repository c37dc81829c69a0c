"""Science benchmark: does evolution find reservoirs better than the unevolved one?

For each task (default: Pendulum-v1 and CartPole-v1, both with ``--observe positions``), one
command runs the whole pipeline as a user would, through the ``ermrl`` CLI:

1. ``ermrl evolve``: CMA-ES over sr, lr and input_scaling, with the unevolved reference
   reservoir as a candidate, then ``--reevaluate-top K`` (the K best trials and the reference
   re-trained on fresh seeds at the test budget);
2. ``ermrl test``: ``ppo``, ``ppo-full`` (full observation: the ceiling), the memory baselines
   ``lstm-ppo`` (RecurrentPPO) and ``framestack-ppo`` (4 stacked observations), ``random-res-ppo``
   (reservoirpy's defaults sr = lr = input_scaling = 1) and ``res-ppo`` (the selected trial) on
   new seeds.

It writes a JSON file and prints a table per task: final return (mean of the last 10 training
episodes) mean ± std over the test seeds, the bootstrap 95% CI of ``res-ppo − random-res-ppo``,
``res-ppo − ppo`` and ``res-ppo − lstm-ppo``, wall-clock time and env steps. The targets of the issue are printed
next to the measurements; the benchmark never fails on a result.

    python benchmarks/bench_science.py            # default budget, about 45-60 min on 2 cores
    python benchmarks/bench_science.py --quick    # smoke test (CI), a few minutes

All budgets are arguments. The same settings serve every task: nothing here is tuned per task.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import difference, format_difference, machine  # noqa: E402

AGENTS = ("ppo", "ppo-full", "lstm-ppo", "framestack-ppo", "random-res-ppo", "res-ppo")
BASELINES = ("ppo", "ppo-full", "lstm-ppo", "framestack-ppo", "random-res-ppo")
PENDULUM_TARGET = -300.0


def _run(cmd: list[str], log: Path) -> float:
    """Run an ermrl command, echoing its output to stderr and to ``log``; return its seconds."""
    print(f"$ {shlex.join(cmd)}", file=sys.stderr, flush=True)
    start = time.perf_counter()
    with log.open("a") as fh:
        fh.write(f"$ {shlex.join(cmd)}\n")
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert proc.stdout is not None
        for line in proc.stdout:
            sys.stderr.write(line)
            fh.write(line)
        code = proc.wait()
    if code != 0:
        bench = Path(sys.argv[0]).stem or "benchmark"
        raise SystemExit(f"{bench}: {cmd[3]} failed with exit code {code} (log: {log})")
    return time.perf_counter() - start


def _evolution_facts(storage: str, study_name: str) -> dict[str, Any]:
    """Best trial, re-evaluated ranking and env steps of the evolution (and re-evaluation)."""
    import optuna

    from ermrl.search import REEVALUATION_ATTR, reevaluation_study_name, select_trial

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.load_study(study_name=study_name, storage=storage)
    trials = study.get_trials(deepcopy=False)
    steps = sum(int(t.user_attrs.get("env_steps", 0)) for t in trials)
    reeval_steps = 0
    rstudy = None
    try:
        rstudy = optuna.load_study(study_name=reevaluation_study_name(study_name), storage=storage)
        reeval_steps = sum(int(t.user_attrs.get("env_steps", 0)) for t in rstudy.trials)
    except KeyError:
        pass
    # Wall time of evolution and re-evaluation from the trials' own timestamps, so that a resumed
    # benchmark still reports the time the studies really took.
    stamped = [
        t for t in trials + (list(rstudy.trials) if reeval_steps else []) if t.datetime_complete
    ]
    seconds = (
        (
            max(t.datetime_complete for t in stamped) - min(t.datetime_start for t in stamped)
        ).total_seconds()
        if stamped
        else 0.0
    )
    chosen, how = select_trial(study)
    reference = next((t for t in trials if t.user_attrs.get("reference")), None)
    return {
        "n_trials": len(trials),
        "seconds": seconds,
        "evolution_env_steps": steps,
        "reevaluation_env_steps": reeval_steps,
        "best_by_fitness": {
            "trial": study.best_trial.number,
            "value": study.best_value,
            "params": study.best_trial.params,
        },
        "reference_fitness": None if reference is None else reference.value,
        "selected": {
            "trial": chosen.number,
            "params": chosen.params,
            "how": how,
            "is_reference": bool(chosen.user_attrs.get("reference")),
        },
        "reevaluation": study.user_attrs.get(REEVALUATION_ATTR),
    }


def _task_result(out: Path) -> dict[str, Any]:
    """Per-agent final returns of a test folder and the differences with their CIs and p."""
    import numpy as np

    from ermrl.analysis import load_run_results

    runs = load_run_results(out)
    agents: dict[str, Any] = {}
    for agent in AGENTS:
        rows = runs[runs["agent"] == agent].sort_values("seed") if not runs.empty else runs
        values = [float(v) for v in rows["final_return"]] if len(rows) else []
        agents[agent] = {
            "seeds": [int(s) for s in rows["seed"]] if len(rows) else [],
            "final_returns": values,
            "mean": float(np.mean(values)) if values else None,
            "std": float(np.std(values, ddof=1)) if len(values) > 1 else None,
            "env_steps": int(rows["env_steps"].sum()) if len(rows) else 0,
        }

    def ci(a: str, b: str) -> dict[str, Any]:
        # Bootstrap and Welch CIs, p, the few-seeds flag; and, over the seeds both agents ran
        # (same env and PPO streams), the paired CI of the per-seed differences.
        return difference(
            agents[a]["final_returns"],
            agents[b]["final_returns"],
            agents[a]["seeds"],
            agents[b]["seeds"],
        )

    return {
        "agents": agents,
        "res_minus_random": ci("res-ppo", "random-res-ppo"),
        "res_minus_ppo": ci("res-ppo", "ppo"),
        "res_minus_lstm": ci("res-ppo", "lstm-ppo"),
    }


def _reuse_baselines(source: Path, out: Path, env_id: str, observe: str) -> None:
    """Copy the baseline agents' runs of the same task from another benchmark's workdir."""
    import shutil

    matches = sorted(source.glob(f"science__{env_id}__{observe}__*/agents"))
    if not matches:
        raise SystemExit(f"bench_science: no runs of {env_id}[{observe}] under {source}")
    for agent in BASELINES:
        src = matches[0] / agent
        if src.is_dir() and not (out / "agents" / agent).exists():
            shutil.copytree(src, out / "agents" / agent)
            print(f"reusing {src}", file=sys.stderr, flush=True)


def _targets(env_id: str, result: dict[str, Any]) -> dict[str, bool | None]:
    agents = result["agents"]
    rr = result["res_minus_random"]
    rp = result["res_minus_ppo"]
    out: dict[str, bool | None] = {
        "res-ppo >= random-res-ppo, CI not entirely below 0": (
            None if rr["diff"] is None else bool(rr["diff"] >= 0 and rr["ci95"][1] >= 0)
        ),
        "res-ppo > ppo, bootstrap and Welch CIs entirely above 0": (
            None
            if rp["diff"] is None
            else bool(rp["ci95"][0] > 0 and (rp.get("welch_ci95") or [0.0])[0] > 0)
        ),
    }
    if env_id.startswith("Pendulum"):
        mean = agents["res-ppo"]["mean"]
        out[f"res-ppo >= {PENDULUM_TARGET:g}"] = None if mean is None else mean >= PENDULUM_TARGET
    return out


def _fmt(value: float | None, std: float | None = None) -> str:
    if value is None:
        return "-"
    return f"{value:.1f}" + ("" if std is None else f" ± {std:.1f}")


def format_table(report: dict[str, Any]) -> str:
    """The Markdown table of a benchmark report (one row per task)."""
    columns = [*AGENTS, "res − random [95% CI]", "res − ppo [95% CI]", "res − lstm [95% CI]"]
    # each difference: bootstrap [CI]; Welch's t [CI] and p; a flag below FEW_SEEDS seeds
    columns += ["selected trial", "wall", "env steps"]
    head = "| task | " + " | ".join(columns) + " |\n" + "|---" * (len(columns) + 1) + "|\n"
    rows = []
    for task in report["tasks"]:
        agents = task["test"]["agents"]
        cells = [_fmt(agents[a]["mean"], agents[a]["std"]) for a in AGENTS]

        ci = format_difference

        sel = task["evolution"]["selected"]
        params = " ".join(f"{k}={v:.3g}" for k, v in sel["params"].items())
        tag = " (reference)" if sel["is_reference"] else ""
        rows.append(
            f"| {task['label']} | "
            + " | ".join(cells)
            + f" | {ci(task['test']['res_minus_random'])}"
            f" | {ci(task['test']['res_minus_ppo'])}"
            f" | {ci(task['test']['res_minus_lstm'])} | #{sel['trial']}{tag} {params} | "
            f"{task['wall_seconds'] / 60:.1f} min | {task['env_steps'] / 1e6:.2f}M |"
        )
    lines = [head + "\n".join(rows), ""]
    for task in report["tasks"]:
        n = len(task["test"]["agents"]["res-ppo"]["final_returns"])
        for key, name in (
            ("res_minus_random", "res − random"),
            ("res_minus_ppo", "res − ppo"),
            ("res_minus_lstm", "res − lstm"),
        ):
            paired = task["test"][key].get("paired_ci95")
            if paired:
                lines.append(
                    f"{task['label']}: {name} paired by seed, 95% CI "
                    f"[{paired[0]:+.1f}, {paired[1]:+.1f}]"
                )
        lines.append(f"{task['label']} ({n} test seeds), targets:")
        for name, ok in task["targets"].items():
            lines.append(f"  - {name}: {'met' if ok else 'NOT met' if ok is False else '-'}")
    return "\n".join(lines)


def add_budget_arguments(p: argparse.ArgumentParser, per: str) -> None:
    """The evolution, re-evaluation and test budgets, shared with ``bench_memory.py``; ``per``
    names what one evolution is for (a task, an encoder)."""
    p.add_argument("--n-trials", type=int, default=30, help=f"evolution trials per {per}")
    p.add_argument("--n-seeds", type=int, default=2, help="seeds per evolution trial")
    p.add_argument("--training-steps", type=int, default=50_000, help="steps per evolution run")
    p.add_argument(
        "--reevaluate-top",
        type=int,
        default=3,
        help="the K best trials of each evolution and its reference re-trained on fresh seeds; "
        "the evolved agent is the best of that ranking (0: the best evolution trial)",
    )
    p.add_argument("--reevaluate-seeds", type=int, default=3)
    p.add_argument("--reevaluate-steps", type=int, default=None, help="default: the test budget")
    p.add_argument("--test-steps", type=int, default=100_000, help="steps per test run")
    p.add_argument("--test-seeds", type=int, default=5)
    p.add_argument("--sampler-seed", type=int, default=0)
    p.add_argument("--n-procs", type=int, default=2)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--env-ids", nargs="+", default=["Pendulum-v1", "CartPole-v1"])
    p.add_argument("--observe", default="positions", choices=("all", "positions", "velocities"))
    add_budget_arguments(p, "task")
    p.add_argument("--cma-start", default="center", choices=("reference", "center"))
    p.add_argument(
        "--backend",
        default="sb3",
        choices=("sb3", "population"),
        help="what trains the evolution's agents (population: whole generations in lockstep)",
    )
    p.add_argument(
        "--test-backend",
        default="sb3",
        choices=("sb3", "population"),
        help="what trains the test phase's agents (sb3 keeps the test measure of earlier runs)",
    )
    p.add_argument(
        "--agents",
        nargs="+",
        default=list(AGENTS),
        choices=AGENTS,
        help="test-phase agents (default: all; drop lstm-ppo to save most of the test time)",
    )
    p.add_argument(
        "--workdir", default=None, help="studies and runs (default: --out without its suffix)"
    )
    p.add_argument("--out", default="benchmarks/results/science.json")
    p.add_argument("--quick", action="store_true", help="tiny budgets: a smoke test (CI)")
    p.add_argument(
        "--reuse-baselines",
        default=None,
        metavar="WORKDIR",
        help="copy the finished ppo, ppo-full and random-res-ppo runs of another benchmark's "
        "workdir (same tasks, test budget and seeds); the test phase checks their recorded "
        "settings and trains only what differs (to compare --cma-start variants cheaply)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.quick:
        args.n_trials, args.n_seeds, args.training_steps = 3, 1, 2048
        args.reevaluate_top, args.reevaluate_seeds = 1, 1
        args.test_steps, args.test_seeds = 2048, 2
    reeval_steps = args.reevaluate_steps or args.test_steps
    work = Path(args.workdir) if args.workdir else Path(args.out).with_suffix("")
    work.mkdir(parents=True, exist_ok=True)
    storage = f"sqlite:///{(work / 'science.db').resolve()}"
    log = work / "log.txt"
    py = [sys.executable, "-m", "ermrl"]
    report: dict[str, Any] = {
        "settings": vars(args) | {"reevaluate_steps": reeval_steps},
        "machine": machine(),
        "tasks": [],
    }
    # Evolve every task first, then test them all: the test phase may be re-run on its own
    # (finished runs are kept), and a resumed benchmark skips what is done.
    tasks = []
    for env_id in args.env_ids:
        study = f"science__{env_id}__{args.observe}__{args.training_steps}__{args.n_trials}"
        if args.cma_start != "center":
            study += f"__{args.cma_start}"
        if args.backend != "sb3":
            study += f"__{args.backend}"
        if args.quick:
            study += "__quick"
        evolve_s = _run(
            [*py, "evolve", "--env-id", env_id, "--observe", args.observe,
             "--n-trials", str(args.n_trials), "--n-seeds", str(args.n_seeds),
             "--training-steps", str(args.training_steps), "--n-procs", str(args.n_procs),
             "--sampler-seed", str(args.sampler_seed), "--cma-start", args.cma_start,
             "--reevaluate-top", str(args.reevaluate_top),
             "--reevaluate-seeds", str(args.reevaluate_seeds),
             "--reevaluate-steps", str(reeval_steps), "--backend", args.backend,
             "--storage", storage, "--study-name", study],
            log,
        )  # fmt: skip
        tasks.append((env_id, study, evolve_s))
    for env_id, study, evolve_s in tasks:
        evolution = _evolution_facts(storage, study)
        seeds = [str(10 + i) for i in range(args.test_seeds)]
        out = work / study
        if args.reuse_baselines:
            _reuse_baselines(Path(args.reuse_baselines), out, env_id, args.observe)
        test_s = _run(
            [*py, "test", "--study-name", study, "--storage", storage,
             "--training-steps", str(args.test_steps), "--seeds", *seeds,
             "--agents", *args.agents, "--n-procs", str(args.n_procs), "--out", str(out),
             "--no-save-models", "--backend", args.test_backend],
            log,
        )  # fmt: skip
        test = _task_result(out)
        test_steps = sum(a["env_steps"] for a in test["agents"].values())
        task = {
            "env_id": env_id,
            "observe": args.observe,
            "label": f"{env_id}[{args.observe}]",
            "study": study,
            "evolution": evolution,
            "test": test,
            "evolve_seconds": max(evolve_s, evolution["seconds"]),
            "test_seconds": test_s,
            "wall_seconds": max(evolve_s, evolution["seconds"]) + test_s,
            "env_steps": evolution["evolution_env_steps"]
            + evolution["reevaluation_env_steps"]
            + test_steps,
        }
        task["targets"] = _targets(env_id, test)
        report["tasks"].append(task)
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(report, indent=2, default=str))
    table = format_table(report)
    report["table"] = table
    Path(args.out).write_text(json.dumps(report, indent=2, default=str))
    (Path(args.out).with_suffix(".md")).write_text(table + "\n")
    print(table)
    print(f"\nwrote {args.out} and {Path(args.out).with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
