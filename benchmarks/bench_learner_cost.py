"""What a learner costs beside PPO: env steps per second, and the memory it holds.

Each variant trains in a fresh process (one torch thread) on the same task and budget, one after
the other, alternating over ``--repeats``. Two suites:

- ``rtu`` (Pendulum-v1 positions): ``ppo`` with the rtu-ppo learner's own rollout settings (2048
  steps, 4 epochs, 32 minibatches, normalization), ``rtu-ppo`` at its defaults (``d_rec`` 192,
  stale gradients) and ``rtu-ppo --no-stale-gradient`` (the rollout re-scanned after each epoch);
- ``hebbian`` (Ant-v5, full observation): ``ppo`` (SB3's defaults, as ermrl trains MuJoCo) and
  ``hebbian`` at its defaults (500 leaky units, readout updated at episode ends).

It reports steps/s, the time split between rollouts and updates (SB3 learners), the stored
carries' size (rtu-ppo) and the peak resident memory growth over training (``ru_maxrss`` after
building the model, and at the end).

    python benchmarks/bench_learner_cost.py                    # the rtu suite, 8192 steps, 3 repeats
    python benchmarks/bench_learner_cost.py --suite hebbian    # Ant-v5
    python benchmarks/bench_learner_cost.py --quick            # a smoke test
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import machine  # noqa: E402

# Settings shared by the memoryless reference: rtu-ppo's table without its own keys.
RTU_ROLLOUT = {"n_steps": 2048, "n_epochs": 4, "batch_size": 64, "learning_rate": 1e-4,
               "max_grad_norm": 0.5, "gamma": 0.99, "gae_lambda": 0.95, "normalize": True}  # fmt: skip
SUITES: dict[str, dict[str, Any]] = {
    "rtu": {
        "task": ("Pendulum-v1", "positions"),
        "variants": {
            "ppo": ("ppo", RTU_ROLLOUT),
            "rtu-ppo": ("rtu-ppo", {}),
            "rtu-ppo --no-stale-gradient": ("rtu-ppo", {"stale_gradient": False}),
        },
    },
    "hebbian": {
        "task": ("Ant-v5", "all"),
        "variants": {"ppo": ("ppo", {}), "hebbian": ("hebbian", {})},
    },
}


def measure(env_id: str, observe: str, learner: str, overrides: dict[str, Any], steps: int) -> dict:
    """Train one agent in this process and return its timings and memory (the child's job)."""
    import resource
    import time

    import torch

    from ermrl.agents import make_vec_env, normalize_env, resolve_ppo_config
    from ermrl.config import TaskConfig
    from ermrl.learners import get_learner

    torch.set_num_threads(1)
    ppo = resolve_ppo_config(env_id, overrides, learner=learner)
    env = normalize_env(make_vec_env(TaskConfig(env_id, observe), ppo.n_envs, 0), ppo)
    model = get_learner(learner).build(env, ppo, seed=0)

    def rss_mb() -> float:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    base = rss_mb()
    spent = {"collect_rollouts": 0.0, "train": 0.0}
    for name in spent:
        original = getattr(model, name, None)
        if original is None:  # not an SB3 algorithm: no rollout/update split
            continue

        def timed(*args: Any, _f: Any = original, _n: str = name, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return _f(*args, **kwargs)
            finally:
                spent[_n] += time.perf_counter() - start

        setattr(model, name, timed)
    start = time.perf_counter()
    model.learn(steps)
    wall = time.perf_counter() - start
    carries = getattr(getattr(model, "rollout_buffer", None), "carries", None) or []
    return {
        "steps": int(model.num_timesteps),
        "wall_s": wall,
        "steps_per_s": model.num_timesteps / wall,
        "rollout_s": spent["collect_rollouts"],
        "update_s": spent["train"],
        "carries_mb": sum(c.numel() * c.element_size() for c in carries) / 1e6,
        "rss_after_build_mb": base,
        "rss_growth_mb": rss_mb() - base,
    }


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--suite", choices=tuple(SUITES), default="rtu")
    p.add_argument("--steps", type=int, default=8192)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default=None, help="default: benchmarks/results/<suite>_cost.json")
    p.add_argument("--quick", action="store_true", help="one repeat of 2048 steps")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    suite = SUITES[args.suite]
    env_id, observe = suite["task"]
    variants = suite["variants"]
    if args.child is not None:
        learner, overrides = variants[args.child]
        print(json.dumps(measure(env_id, observe, learner, overrides, args.steps)))
        return 0
    if args.quick:
        args.steps, args.repeats = 2048, 1
    rows: dict[str, list[dict[str, Any]]] = {name: [] for name in variants}
    for repeat in range(args.repeats):
        for name in variants:
            proc = subprocess.run(
                [sys.executable, __file__, "--child", name, "--suite", args.suite,
                 "--steps", str(args.steps)],
                capture_output=True, text=True, check=True,
            )  # fmt: skip
            rows[name].append(json.loads(proc.stdout.strip().splitlines()[-1]))
            r = rows[name][-1]
            print(f"repeat {repeat + 1}/{args.repeats} {name}: {r['steps_per_s']:.0f} steps/s",
                  file=sys.stderr, flush=True)  # fmt: skip
    ppo_rate = statistics.median(r["steps_per_s"] for r in rows["ppo"])
    summary = []
    for name, runs in rows.items():
        rate = statistics.median(r["steps_per_s"] for r in runs)
        summary.append(
            {
                "variant": name,
                "steps_per_s": rate,
                "vs_ppo": rate / ppo_rate,
                "update_share": (
                    statistics.median(r["update_s"] / r["wall_s"] for r in runs)
                    if any(r["rollout_s"] for r in runs)
                    else None  # not an SB3 algorithm: no rollout/update split
                ),
                "carries_mb": max(r["carries_mb"] for r in runs),
                "rss_growth_mb": max(r["rss_growth_mb"] for r in runs),
            }
        )
    table = (
        f"{env_id}[{observe}], {args.steps} steps, median of {args.repeats}\n\n"
        "| variant | steps/s | / ppo | update share | stored carries | peak RSS growth |\n"
        "|---|---|---|---|---|---|\n"
        + "\n".join(
            f"| {s['variant']} | {s['steps_per_s']:.0f} | {s['vs_ppo']:.2f}× | "
            f"{'-' if s['update_share'] is None else format(s['update_share'], '.0%')} | "
            f"{s['carries_mb']:.0f} MB | {s['rss_growth_mb']:.0f} MB |"
            for s in summary
        )
    )
    print(table)
    out = Path(args.out or f"benchmarks/results/{args.suite}_cost.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    report = {"settings": vars(args), "machine": machine(), "rows": rows, "summary": summary}
    out.write_text(json.dumps(report | {"table": table}, indent=2))
    out.with_suffix(".md").write_text(table + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
