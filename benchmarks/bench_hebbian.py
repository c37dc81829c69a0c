"""Hebbian benchmark: do evolved plasticity genes beat the original's default genes?

Through the ``ermrl`` CLI, as a user would, on one task (default: Ant-v5, full observation):

1. ``ermrl evolve --learner hebbian``: CMA-ES over the Hebbian learner's nine genes (spectral
   radius, input scaling, bias scale, tau_min, tau_max / tau_min, sigma, the trace's horizon
   1 / (1 - lambda), the learning rate and l2), the default genes competing as the first trial;
2. ``ermrl test --agents hebbian random-hebbian ppo`` on new seeds: the evolved genes, the
   original's default genes (N 500, sigma 0.25, lambda 0.99, learning rate 1e-4, ...) and PPO
   with its own table's settings, at the same budget.

The measure is ermrl's own, the same for every agent: the final return is the mean *task*
return of the last 10 training episodes (not the original's running mean of the torso's
x-velocity). The benchmark prints, per agent, the mean, std and Student-t 95% CI over the test
seeds, and the bootstrap 95% CI (independent, and paired on the shared seeds) of
``hebbian - random-hebbian`` and ``hebbian - ppo``. It writes JSON and Markdown next to
``--out``; the learning curves are the test phase's ``learning_curves.png`` in the work folder.
It never fails on a result, and a rerun resumes (the study and run folders are kept).

    python benchmarks/bench_hebbian.py              # default budget, about 45 min on 2 cores
    python benchmarks/bench_hebbian.py --quick      # smoke test, about a minute
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import difference, format_difference, machine  # noqa: E402
from benchmarks.bench_memory import _agent_rows  # noqa: E402
from benchmarks.bench_science import _evolution_facts, _run  # noqa: E402

AGENTS = ("hebbian", "random-hebbian", "ppo")


def differences(rows: dict[str, Any], a: str, b: str) -> dict[str, Any]:
    """``mean(a) - mean(b)`` of the final returns with 95% CIs (bootstrap, Welch's t with its
    p-value, and paired on the seeds both agents trained with) and the few-seeds flag."""
    return difference(
        rows[a]["final_returns"], rows[b]["final_returns"], rows[a]["seeds"], rows[b]["seeds"]
    )


def zero_action_returns(env_id: str, observe: str, seeds: list[int]) -> list[float]:
    """The return of one episode with all-zero actions per seed: what standing still earns
    (on Ant the healthy bonus alone gives up to 1 per step), the floor a learner must clear."""
    import numpy as np

    from ermrl.envs import make_env

    out = []
    for seed in seeds:
        env = make_env(env_id, observe)  # type: ignore[arg-type]
        env.reset(seed=seed)
        total, done = 0.0, False
        zero = np.zeros(env.action_space.shape, dtype=env.action_space.dtype)
        while not done:
            _, reward, terminated, truncated, _ = env.step(zero)
            total += float(reward)
            done = terminated or truncated
        env.close()
        out.append(total)
    return out


def _fmt(value: float | None) -> str:
    return "-" if value is None or value != value else f"{value:.1f}"


def _ci(ci: list[float] | None) -> str:
    return "-" if ci is None else f"[{_fmt(ci[0])}, {_fmt(ci[1])}]"


def format_table(report: dict[str, Any]) -> str:
    """Markdown: the agents' final returns, then the differences and the selected genes."""
    from ermrl.analysis import few_seeds_flag

    s = report["settings"]
    lines = [
        f"### {report['label']}: {s['n_trials']} trials x {s['n_seeds']} seeds x "
        f"{s['training_steps']} steps of evolution; test {s['test_seeds']} seeds x "
        f"{s['test_steps']} steps",
        "",
        "| agent | seeds | final return mean ± std | 95% CI | test wall (all seeds) | flag |",
        "|---|---|---|---|---|---|",
    ]
    for agent, row in report["agents"].items():
        n = len(row["final_returns"])
        lines.append(
            f"| {agent} | {n} | {_fmt(row['mean'])} ± "
            f"{_fmt(row['std'])} | {_ci(row['ci95'])} | {row['wall_seconds'] / 60:.1f} min | "
            f"{few_seeds_flag(n) if n else ''} |"
        )
    lines += [
        "",
        "| difference | mean, bootstrap 95% CI; Welch 95% CI, p; flag | paired 95% CI |",
        "|---|---|---|",
    ]
    for name, d in report["differences"].items():
        lines.append(f"| {name} | {format_difference(d)} | {_ci(d['paired_ci95'])} |")
    zero = report["zero_action_returns"]
    lines.append(
        f"\nzero actions (standing still): {_fmt(sum(zero) / len(zero))} "
        f"(min {_fmt(min(zero))}, max {_fmt(max(zero))}) over {len(zero)} seeds"
    )
    sel = report["selected"]
    params = " ".join(f"{k}={v:.3g}" for k, v in sel["params"].items())
    tag = " (the default genes)" if sel["is_reference"] else ""
    lines += [
        "",
        f"hebbian: trial #{sel['trial']}{tag} {params}; evolution "
        f"{report['evolution_seconds'] / 60:.1f} min",
    ]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--env-id", default="Ant-v5")
    p.add_argument("--observe", default="all", choices=("all", "positions", "velocities"))
    p.add_argument("--n-trials", type=int, default=24, help="evolution trials")
    p.add_argument("--n-seeds", type=int, default=3, help="seeds per evolution trial")
    p.add_argument("--training-steps", type=int, default=40_000, help="steps per evolution run")
    p.add_argument("--test-steps", type=int, default=100_000, help="steps per test run")
    p.add_argument("--test-seeds", type=int, default=10)
    p.add_argument("--sampler-seed", type=int, default=0)
    p.add_argument("--n-procs", type=int, default=2)
    p.add_argument(
        "--ppo",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="hebbian settings for the study and both Hebbian agents (e.g. units=100)",
    )
    p.add_argument("--out", default="benchmarks/results/hebbian.json")
    p.add_argument("--workdir", default=None, help="study and runs (default: next to --out)")
    p.add_argument("--quick", action="store_true", help="tiny budgets: a smoke test")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.quick:
        args.n_trials, args.n_seeds, args.training_steps = 2, 1, 1000
        args.test_steps, args.test_seeds = 1000, 2
        args.ppo = args.ppo or ["units=50"]
    work = Path(args.workdir) if args.workdir else Path(args.out).with_suffix("")
    work.mkdir(parents=True, exist_ok=True)
    storage = f"sqlite:///{(work / 'hebbian.db').resolve()}"
    log = work / "log.txt"
    py = [sys.executable, "-m", "ermrl"]
    study = (
        f"hebbian__{args.env_id}__{args.observe}__{args.training_steps}__{args.n_trials}"
        f"x{args.n_seeds}"
    )
    ppo = ["--ppo", *args.ppo] if args.ppo else []
    _run(
        [*py, "evolve", "--env-id", args.env_id, "--observe", args.observe,
         "--learner", "hebbian", "--n-trials", str(args.n_trials), "--n-seeds",
         str(args.n_seeds), "--training-steps", str(args.training_steps), "--n-procs",
         str(args.n_procs), "--sampler-seed", str(args.sampler_seed), *ppo,
         "--storage", storage, "--study-name", study, "--quiet"],
        log,
    )  # fmt: skip
    out = work / study
    seeds = [str(100 + i) for i in range(args.test_seeds)]
    _run(
        [*py, "test", "--study-name", study, "--storage", storage, "--training-steps",
         str(args.test_steps), "--seeds", *seeds, "--agents", *AGENTS, "--n-procs",
         str(args.n_procs), "--out", str(out), "--no-save-models", "--quiet"],
        log,
    )  # fmt: skip
    rows = _agent_rows([out], AGENTS)
    facts = _evolution_facts(storage, study)
    report: dict[str, Any] = {
        "settings": vars(args),
        "machine": machine(),
        "label": f"{args.env_id}[{args.observe}]",
        "study": study,
        "agents": rows,
        "differences": {
            "hebbian - random-hebbian": differences(rows, "hebbian", "random-hebbian"),
            "hebbian - ppo": differences(rows, "hebbian", "ppo"),
            "random-hebbian - ppo": differences(rows, "random-hebbian", "ppo"),
        },
        "zero_action_returns": zero_action_returns(
            args.env_id, args.observe, [int(s) for s in seeds]
        ),
        "evolution_seconds": facts["seconds"],
        "selected": facts["selected"],
        "learning_curves": str(out / "learning_curves.png"),
    }
    table = format_table(report)
    report["table"] = table
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=2, default=str))
    Path(args.out).with_suffix(".md").write_text(table + "\n")
    print(table)
    print(f"wrote {args.out}, {Path(args.out).with_suffix('.md')} and {out}/learning_curves.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
