"""What a population worker spends before its first training step, phase by phase.

A worker of the population backend is a ``spawn`` process of :func:`ermrl.agents.training_pool`
(the pool every evolution, re-evaluation and test phase uses). Before its agents make their first
env step it pays, in order:

- ``spawn``: a fresh interpreter started and the pool's initializer run (which imports
  Stable-Baselines3 and ``ermrl.envs``, the training stack), measured from the pool's creation to
  the first line of the submitted job (``time.time()`` on both sides: one clock);
- ``import``: the rest of the population backend (``ermrl.population``: torch's autograd, the
  stacked policy);
- ``model``: :class:`~ermrl.population.PopulationPPO` for the job's agents: its
  :class:`~ermrl.population.PopulationEnvs` (``gym.make`` per env, MuJoCo's model compilation,
  the reservoirs' weights), policy initialization and Adam;
- ``first_step``: the first rollout step (reset, one policy forward pass, one env step), where
  torch and numpy run their first operations.

``envs_again`` is not a phase: the same envs built once more after the first step, to tell how
much of ``model`` the envs are (warm: a lower bound of their cold cost).

Each phase is reported per process (the slowest of the ``--n-procs`` processes, which is what
the pool waits for) as the median over ``--repeats`` fresh pools; ``import`` time of the heaviest
modules is read from ``python -X importtime`` in a fresh interpreter.

    python benchmarks/bench_startup.py                 # HalfCheetah-v5, 12 agents per process, 2 processes, 3 repeats
    python benchmarks/bench_startup.py --quick         # Pendulum-v1, 2 agents, 1 process, 1 repeat
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import median, table, write_json  # noqa: E402

PHASES = ("spawn", "import", "model", "first_step", "envs_again")


def phases_in_worker(created: float, env_id: str, observe: str, n_agents: int) -> dict[str, float]:
    """Run in a fresh pool process: the seconds of each phase up to the first rollout step."""
    t_entry = time.time()
    from ermrl.agents import resolve_ppo_config
    from ermrl.config import EncoderConfig, TaskConfig
    from ermrl.population import PopulationEnvs, PopulationJob, PopulationPPO

    t_import = time.time()
    task = TaskConfig(env_id, observe)
    ppo = resolve_ppo_config(env_id)
    jobs = [PopulationJob(EncoderConfig(), seed) for seed in range(n_agents)]
    population = PopulationPPO(task, ppo, jobs)
    t_model = time.time()
    obs = population.envs.reset()
    if population.spec.use_sde:
        population._reset_noise()
    actions, _, _ = population._act(obs)
    population.envs.step(actions if population.discrete else population._clip(actions))
    t_step = time.time()
    population.close()
    # The envs alone, built again now that MuJoCo and the reservoirs' code are warm.
    t_envs = time.time()
    envs = PopulationEnvs(task, ppo.n_envs, list(range(n_agents)), [j.encoder for j in jobs],
                          list(range(n_agents)))  # fmt: skip
    envs_again = time.time() - t_envs
    envs.close()
    return {
        "spawn": t_entry - created,
        "import": t_import - t_entry,
        "model": t_model - t_import,
        "envs_again": envs_again,
        "first_step": t_step - t_model,
    }


def measure_pool(args: argparse.Namespace) -> dict[str, float]:
    """One fresh pool of ``--n-procs`` processes; per phase, the slowest process."""
    from ermrl.agents import training_pool

    env_id, _, observe = args.task.partition(":")
    created = time.time()
    start = time.perf_counter()
    with training_pool(args.n_procs) as pool:
        futures = [pool.submit(phases_in_worker, created, env_id, observe or "all", args.agents)
                   for _ in range(args.n_procs)]  # fmt: skip
        per_process = [f.result() for f in futures]
        ready = time.perf_counter() - start
    row = {k: max(p[k] for p in per_process) for k in PHASES}
    row["to_first_step"] = ready
    return row


def heaviest_imports(n: int = 8) -> list[dict[str, Any]]:
    """The top-level packages with the largest cumulative import time, from ``-X importtime``."""
    # What a population worker imports: the pool's training stack, the backend, and reservoirpy
    # (imported when the first reservoir's weights are drawn, inside ``model``).
    code = "import stable_baselines3, ermrl.envs, ermrl.population, reservoirpy"
    proc = subprocess.run([sys.executable, "-X", "importtime", "-c", code],
                          capture_output=True, text=True, check=True)  # fmt: skip
    rows = []
    for line in proc.stderr.splitlines():
        if not line.startswith("import time:") or "|" not in line:
            continue
        parts = [p.strip() for p in line.removeprefix("import time:").split("|")]
        if not parts[1].isdigit():
            continue
        name = parts[2]
        if name.startswith(" ") or "." in name.strip():
            continue
        rows.append({"module": name.strip(), "cumulative_s": int(parts[1]) / 1e6})
    total = sum(r["cumulative_s"] for r in rows)
    rows.sort(key=lambda r: -r["cumulative_s"])
    return [{"module": "(all)", "cumulative_s": total}, *rows[:n]]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", default=None, help="ENV_ID[:observe] (HalfCheetah-v5:all)")
    parser.add_argument("--agents", type=int, default=None, help="agents per process (12)")
    parser.add_argument("--n-procs", type=int, default=None, help="pool processes (2)")
    parser.add_argument("--repeats", type=int, default=None, help="fresh pools (3)")
    parser.add_argument("--quick", action="store_true", help="Pendulum-v1, 2 agents, 1 process")
    parser.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    args = parser.parse_args(argv)
    args.task = args.task or ("Pendulum-v1:positions" if args.quick else "HalfCheetah-v5:all")
    args.agents = args.agents or (2 if args.quick else 12)
    args.n_procs = args.n_procs or (1 if args.quick else 2)
    args.repeats = args.repeats or (1 if args.quick else 3)

    runs = []
    for k in range(args.repeats):
        runs.append(measure_pool(args))
        print(f"pool {k + 1}/{args.repeats}: {runs[-1]['to_first_step']:.2f} s to the first step",
              file=sys.stderr, flush=True)  # fmt: skip
    keys = ("to_first_step", *PHASES)
    summary = {k: median([r[k] for r in runs]) for k in keys}
    imports = heaviest_imports()
    print(f"{args.task}, {args.agents} agents per process, {args.n_procs} processes, "
          f"median of {args.repeats} fresh pools (seconds; per phase the slowest process):")  # fmt: skip
    print(table([summary], list(keys)))
    print("\nheaviest imports (one fresh interpreter, -X importtime, cumulative seconds):")
    print(table(imports, ["module", "cumulative_s"]))
    if args.out is not None:
        write_json(args.out, {"settings": {k: v for k, v in vars(args).items() if k != "out"},
                              "runs": runs, "median": summary, "imports": imports})  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
