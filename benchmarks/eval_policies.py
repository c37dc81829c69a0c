"""Deterministic evaluation of a test phase's saved policies: the measure of rl-baselines3-zoo's
``benchmark.md`` (mean return of deterministic episodes of the final agent), beside ermrl's
training measure (mean of the last 10 training episodes, stochastic actions).

    python benchmarks/eval_policies.py runs/S --agents lstm-ppo --episodes 10

For each agent and seed with a saved ``policy.pt``: the mean return of ``--episodes`` deterministic
episodes (env seeds 10000, 10001, ...), then the mean ± std over seeds. Prints a table and writes
JSON (``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ermrl.analysis import load_trained_agent, rollout  # noqa: E402
from ermrl.analysis._replay import available_runs  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("run", help="a test-phase folder (test.py --out), run with --save-models")
    p.add_argument("--agents", nargs="+", required=True)
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--out", default=None, help="JSON file (default: none)")
    args = p.parse_args(argv)
    runs = available_runs(args.run)
    report: dict[str, dict] = {}
    for agent in args.agents:
        seeds = sorted(s for a, s in runs if a == agent)
        if not seeds:
            raise SystemExit(f"eval_policies: no saved policy of {agent!r} in {args.run}")
        per_seed = {}
        for seed in seeds:
            trained = load_trained_agent(args.run, agent, seed)
            returns = [
                float(rollout(trained, deterministic=True, env_seed=10_000 + k).rewards.sum())
                for k in range(args.episodes)
            ]
            per_seed[seed] = returns
            print(
                f"{agent} seed {seed}: {np.mean(returns):.1f} ± {np.std(returns):.1f}", flush=True
            )
        means = [float(np.mean(r)) for r in per_seed.values()]
        std = float(np.std(means, ddof=1)) if len(means) > 1 else 0.0
        report[agent] = {"per_seed": per_seed, "mean": float(np.mean(means)), "std": std}
        print(f"{agent}: {np.mean(means):.1f} ± {std:.1f} over {len(means)} seeds", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
