"""Memory benchmark: which memory works under partial observability? Evolved reservoirs of three
kinds against learned memory and a plain delay line, on partially observable tasks.

Seven agents get the same training budget on new seeds (the test phase), each with its learner's
own settings table:

- ``ppo``: PPO on the masked observation (no memory);
- ``framestack-ppo``: PPO on the last 4 masked observations (a delay line);
- ``lstm-ppo``: RecurrentPPO with an LSTM (learned memory, BPTT; the zoo's ppo_lstm settings);
- ``rtu-ppo``: real-time PPO with recurrent trace units learned online by RTRL (learned memory);
- ``res-ppo``: PPO on an echo state network evolved by CMA-ES (``ermrl evolve``);
- ``rtu-res-ppo``: PPO on frozen RTUs whose ranges CMA-ES evolved (``ermrl evolve --encoder
  rtu``);
- ``nvar-res-ppo``: PPO on a next-generation reservoir (NVAR: delayed inputs and their
  monomials) whose delay, order, strides and input scaling CMA-ES evolved (``ermrl evolve
  --encoder nvar``).

For each task the benchmark runs, through the ``ermrl`` CLI as a user would: the three evolutions
(same trials, seeds and steps: by default the science benchmark's 30 CMA-ES trials x 2 seeds x 50k
steps, then the 3 best trials and the reference re-trained on 3 fresh seeds at the test budget,
whose ranking picks the evolved agent), the test phase of the ESN study (every agent but the
evolved RTU and NVAR) and those of the RTU and NVAR studies (their evolved agent), on the same test
seeds and budget. It prints a table per task: final return (mean of the last 10 training episodes)
mean, std and Student-t 95% CI over the seeds, and wall-clock per agent (its test runs; evolved
agents also show their evolution's wall time); then each evolved memory against ``framestack-ppo``,
``lstm-ppo`` and ``ppo`` (Welch's t: difference, its 95% CI, p), and which memory wins the task
(the best mean; "clearly" only when Welch's CI against the runner-up excludes 0). It writes JSON
and Markdown; it never fails on a result.

    python benchmarks/bench_memory.py                  # default budgets (hours on 2 cores)
    python benchmarks/bench_memory.py --quick          # smoke test, a few minutes
    python benchmarks/bench_memory.py --tasks CartPole-v1:positions --test-steps 50000

Tasks are ``ENV_ID:OBSERVE``; every budget is an argument (the test budget defaults to the
science benchmark's, 100k steps x 5 seeds). The full run takes longer than one sitting, so it
resumes at two grains:

- each finished task is written as a plain file, ``tasks/ENV_ID__OBSERVE.json`` next to
  ``--out`` (the published result, committed with the repository); a rerun with the same budgets
  reuses it instead of training again (``--remeasure`` trains it anew), even on another machine;
- within a task, the studies and run folders kept in the work folder (not committed) let a
  killed run skip its finished trials and test runs.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import machine  # noqa: E402
from benchmarks.bench_science import _evolution_facts, _run, add_budget_arguments  # noqa: E402

AGENTS = (
    "ppo",
    "framestack-ppo",
    "lstm-ppo",
    "rtu-ppo",
    "res-ppo",
    "rtu-res-ppo",
    "nvar-res-ppo",
)
TASKS = (
    "Pendulum-v1:positions",
    "CartPole-v1:positions",
    "popgym-RepeatFirstEasy-v0:all",
    "Hopper-v5:positions",
)
# The evolved agents and the encoder each one's study evolves. Each study's test phase trains
# its own evolved agent; the ESN study's also trains the baselines.
EVOLVED = {"res-ppo": "reservoir", "rtu-res-ppo": "rtu", "nvar-res-ppo": "nvar"}
# What each evolved memory is compared with.
BASELINES = ("framestack-ppo", "lstm-ppo", "ppo")
# The settings a published task result must share with a rerun to be reused.
BUDGETS = (
    "n_trials",
    "n_seeds",
    "training_steps",
    "reevaluate_top",
    "reevaluate_seeds",
    "reevaluate_steps",
    "test_steps",
    "test_seeds",
    "sampler_seed",
)


def _agent_rows(outs: list[Path], agents: tuple[str, ...]) -> dict[str, Any]:
    """Per-agent final returns, their statistics and wall time, from test-phase folders."""
    import pandas as pd

    from ermrl.analysis import final_returns_table, load_run_results

    frames = [load_run_results(out) for out in outs if out.exists()]
    runs = pd.concat([f for f in frames if not f.empty]) if frames else pd.DataFrame()
    table = final_returns_table(
        runs, [a for a in agents if not runs.empty and a in set(runs["agent"])]
    )
    rows: dict[str, Any] = {}
    for agent in agents:
        sub = runs[runs["agent"] == agent].sort_values("seed") if not runs.empty else runs
        stats = table[table["agent"] == agent]
        one = stats.iloc[0] if len(stats) else None
        rows[agent] = {
            "seeds": [int(s) for s in sub["seed"]] if len(sub) else [],
            "final_returns": [float(v) for v in sub["final_return"]] if len(sub) else [],
            "mean": None if one is None else float(one["mean"]),
            "std": None if one is None else float(one["std"]),
            "ci95": None if one is None else [float(one["ci95_low"]), float(one["ci95_high"])],
            "wall_seconds": float(sub["wall_seconds"].sum()) if len(sub) else 0.0,
            "env_steps": int(sub["env_steps"].sum()) if len(sub) else 0,
        }
    return rows


def reusable(path: Path, budgets: dict[str, Any], agents: list[str]) -> dict[str, Any] | None:
    """A finished task's published result, narrowed to ``agents``, or None when there is none,
    its budgets differ, or it lacks one of the agents (then the task is trained again)."""
    if not path.exists():
        return None
    saved = json.loads(path.read_text())
    task = saved["task"]
    if saved.get("budgets") != budgets or not set(agents) <= set(task["agents"]):
        print(
            f"{path}: other budgets or agents than asked for; training the task again",
            file=sys.stderr,
            flush=True,
        )
        return None
    rows = {a: task["agents"][a] for a in AGENTS if a in agents}
    return {
        **task,
        "studies": {a: s for a, s in task["studies"].items() if a in rows},
        "agents": rows,
        "comparisons": comparisons(rows),
        "winner": winner(rows),
        "evolution_seconds": {a: v for a, v in task["evolution_seconds"].items() if a in rows},
        "selected": {a: v for a, v in task["selected"].items() if a in rows},
    }


def comparisons(agents: dict[str, Any]) -> list[dict[str, Any]]:
    """Each evolved memory against each baseline: Welch's t on the per-seed final returns."""
    from ermrl.analysis import welch_t_test

    rows = []
    for evolved in EVOLVED:
        for baseline in BASELINES:
            a = agents.get(evolved, {}).get("final_returns") or []
            b = agents.get(baseline, {}).get("final_returns") or []
            if not a or not b:
                continue
            w = welch_t_test(a, b)
            rows.append(
                {
                    "agent": evolved,
                    "baseline": baseline,
                    "difference": sum(a) / len(a) - sum(b) / len(b),
                    "ci95": [w.ci_low, w.ci_high],
                    "p_value": w.p_value,
                }
            )
    return rows


def winner(agents: dict[str, Any]) -> dict[str, Any] | None:
    """The agent with the best mean final return; ``clear`` when Welch's 95% CI of its
    difference to the runner-up excludes 0."""
    from ermrl.analysis import welch_t_test

    ranked = sorted(
        (a for a, row in agents.items() if row["mean"] is not None),
        key=lambda a: agents[a]["mean"],
        reverse=True,
    )
    if not ranked:
        return None
    if len(ranked) == 1:
        return {"agent": ranked[0], "runner_up": None, "clear": False}
    w = welch_t_test(agents[ranked[0]]["final_returns"], agents[ranked[1]]["final_returns"])
    return {"agent": ranked[0], "runner_up": ranked[1], "clear": bool(w.ci_low > 0)}


def _fmt(value: float | None) -> str:
    if value is None or value != value:
        return "-"
    return f"{value:.3f}" if abs(value) < 10 else f"{value:.1f}"  # POPGym returns lie in [-1, 1]


def format_table(report: dict[str, Any]) -> str:
    """Markdown: one table per task, one row per agent (a CI of few seeds flagged)."""
    from ermrl.analysis import few_seeds_flag

    lines = []
    for task in report["tasks"]:
        measured = f"measured {task['measured']}; " if task.get("measured") else ""
        lines += [
            f"### {task['label']}",
            "",
            f"{measured}final return = mean of the last 10 training episodes",
            "",
            "| agent | seeds | final return mean ± std | 95% CI | test wall (all seeds) | "
            "evolution wall | flag |",
            "|---|---|---|---|---|---|---|",
        ]
        for agent, row in task["agents"].items():
            ci = row["ci95"]
            ci_text = "-" if ci is None else f"[{_fmt(ci[0])}, {_fmt(ci[1])}]"
            evolve = task["evolution_seconds"].get(agent)
            lines.append(
                f"| {agent} | {len(row['final_returns'])} | {_fmt(row['mean'])} ± "
                f"{_fmt(row['std'])} | {ci_text} | {row['wall_seconds'] / 60:.1f} min | "
                f"{'-' if evolve is None else f'{evolve / 60:.1f} min'} | "
                f"{few_seeds_flag(n) if (n := len(row['final_returns'])) else ''} |"
            )
        if task.get("comparisons"):
            lines += [
                "",
                "| evolved | against | difference | Welch 95% CI | p |",
                "|---|---|---|---|---|",
            ]
            for c in task["comparisons"]:
                lo, hi = c["ci95"]
                lines.append(
                    f"| {c['agent']} | {c['baseline']} | {_fmt(c['difference'])} | "
                    f"[{_fmt(lo)}, {_fmt(hi)}] | {_fmt(c['p_value'])} |"
                )
        best = task.get("winner")
        if best is not None and best["runner_up"] is None:  # one agent: nothing to rank
            lines.append(f"\nonly agent: {best['agent']} (no comparison)")
        elif best is not None:
            how = "clearly" if best["clear"] else "within the noise of the runner-up"
            runner = f" ({best['runner_up']})" if best["runner_up"] else ""
            lines.append(f"\nbest mean: {best['agent']}, {how}{runner}")
        for agent, sel in task["selected"].items():
            params = " ".join(f"{k}={v:.3g}" for k, v in sel["params"].items())
            tag = " (the unevolved reference)" if sel["is_reference"] else ""
            lines.append(f"\n{agent}: trial #{sel['trial']}{tag} {params}")
        lines.append("")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--tasks", nargs="+", default=list(TASKS), metavar="ENV_ID:OBSERVE")
    p.add_argument("--agents", nargs="+", default=list(AGENTS), choices=AGENTS)
    add_budget_arguments(p, "encoder")
    p.add_argument(
        "--out",
        default="benchmarks/results/memory/memory.json",
        help="the report (JSON, and Markdown beside it); finished tasks go to tasks/ next to it",
    )
    p.add_argument(
        "--workdir", default=None, help="studies and runs (default: work/ next to --out)"
    )
    p.add_argument(
        "--remeasure",
        action="store_true",
        help="train every task again, even one whose result file has the same budgets",
    )
    p.add_argument("--quick", action="store_true", help="tiny budgets: a smoke test")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.quick:
        args.n_trials, args.n_seeds, args.training_steps = 2, 1, 1024
        args.test_steps, args.test_seeds = 1024, 2
        args.reevaluate_top, args.reevaluate_seeds = 1, 1
    args.reevaluate_steps = args.reevaluate_steps or args.test_steps
    work = Path(args.workdir) if args.workdir else Path(args.out).parent / "work"
    published = Path(args.out).parent / "tasks"
    budgets = {k: getattr(args, k) for k in BUDGETS}
    storage = f"sqlite:///{(work / 'memory.db').resolve()}"
    log = work / "log.txt"
    py = [sys.executable, "-m", "ermrl"]
    seeds = [str(10 + i) for i in range(args.test_seeds)]
    report: dict[str, Any] = {"settings": vars(args), "machine": machine(), "tasks": []}
    for spec in args.tasks:
        env_id, _, observe = spec.partition(":")
        observe = observe or "all"
        label = f"{env_id}[{observe}]"
        task_file = published / f"{env_id}__{observe}.json"
        done = None if args.remeasure else reusable(task_file, budgets, args.agents)
        if done is not None:
            print(
                f"{label}: reusing {task_file} (measured {done.get('measured', '?')} with the same "
                "budgets; --remeasure trains it again)",
                file=sys.stderr,
                flush=True,
            )
            report["tasks"].append(done)
            continue
        work.mkdir(parents=True, exist_ok=True)  # only a task that trains needs it
        studies: dict[str, str] = {}
        for agent, encoder in EVOLVED.items():
            if agent not in args.agents:
                continue
            study = (
                f"memory__{env_id}__{observe}__{encoder}__{args.training_steps}__"
                f"{args.n_trials}x{args.n_seeds}"
            )
            studies[agent] = study
            _run(
                [*py, "evolve", "--env-id", env_id, "--observe", observe, "--encoder", encoder,
                 "--n-trials", str(args.n_trials), "--n-seeds", str(args.n_seeds),
                 "--training-steps", str(args.training_steps), "--n-procs", str(args.n_procs),
                 "--sampler-seed", str(args.sampler_seed),
                 "--reevaluate-top", str(args.reevaluate_top),
                 "--reevaluate-seeds", str(args.reevaluate_seeds),
                 "--reevaluate-steps", str(args.reevaluate_steps), "--storage", storage,
                 "--study-name", study, "--quiet"],
                log,
            )  # fmt: skip
        # The ESN study's test phase trains every agent but the other evolved encoders'; without
        # an ESN study (no res-ppo asked for), a tiny one is evolved to host the baselines.
        host = studies.get("res-ppo")
        host_agents = [a for a in args.agents if a not in EVOLVED or a == "res-ppo"]
        if host_agents and host is None:
            host = f"memory__{env_id}__{observe}__host"
            _run(
                [*py, "evolve", "--env-id", env_id, "--observe", observe, "--n-trials", "1",
                 "--n-seeds", "1", "--training-steps", "1000", "--storage", storage,
                 "--study-name", host, "--quiet"],
                log,
            )  # fmt: skip
        phases = [(host, host_agents)] + [
            (studies.get(agent), [agent]) for agent in EVOLVED if agent != "res-ppo"
        ]
        outs = []
        for tested, agents in phases:
            if tested is None or not agents:
                continue
            out = work / tested
            outs.append(out)
            _run(
                [*py, "test", "--study-name", tested, "--storage", storage,
                 "--training-steps", str(args.test_steps), "--seeds", *seeds,
                 "--agents", *agents, "--n-procs", str(args.n_procs), "--out", str(out),
                 "--no-save-models", "--quiet"],
                log,
            )  # fmt: skip
        facts = {agent: _evolution_facts(storage, study) for agent, study in studies.items()}
        task = {
            "env_id": env_id,
            "observe": observe,
            "label": label,
            "studies": studies,
            "agents": (rows := _agent_rows(outs, tuple(args.agents))),
            "comparisons": comparisons(rows),
            "winner": winner(rows),
            "evolution_seconds": {a: f["seconds"] for a, f in facts.items()},
            "selected": {a: f["selected"] for a, f in facts.items()},
            "measured": datetime.date.today().isoformat(),
            "machine": report["machine"],
        }
        published.mkdir(parents=True, exist_ok=True)
        task_file.write_text(
            json.dumps({"budgets": budgets, "task": task}, indent=2, default=str) + "\n"
        )
        report["tasks"].append(task)
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(report, indent=2, default=str))
    table = format_table(report)
    report["table"] = table
    Path(args.out).write_text(json.dumps(report, indent=2, default=str))
    Path(args.out).with_suffix(".md").write_text(table + "\n")
    print(table)
    print(f"wrote {args.out} and {Path(args.out).with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
