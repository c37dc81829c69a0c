"""The population backend's PPO update alone: microseconds per minibatch and per agent-step.

A population of ``--agents`` agents (the unevolved reference reservoir, ``EncoderConfig()``, seeds
0, 1, ...) with the packaged PPO settings of the task is updated on synthetic rollouts of the
task's shapes (``n_steps x n_envs`` steps per agent, standard normal observations, actions,
values and advantages). No environment is stepped, so the measurement is the update's own cost:
forward and backward passes, losses, per-agent gradient clipping and Adam. Each repeat runs
``--epochs`` epochs of minibatches (``batch_size`` from the settings) and is timed in CPU time of
this process (steadier than wall time on a shared machine; the update runs on one thread, torch's
and BLAS's, as in training).

Reported per repeat, then the median: ``us_per_minibatch`` and ``update_us_per_agent_step``, the
cost of the settings' full update (``n_epochs`` epochs) divided by the agents' env steps, the unit
of the population benchmark's time breakdown (``bench_backends.py``).

    python benchmarks/bench_update.py                    # HalfCheetah-v5, 8 agents, 5 repeats
    python benchmarks/bench_update.py --quick            # smoke test: Pendulum-v1, 2 agents
    python benchmarks/bench_update.py --out results.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import median, table, write_json  # noqa: E402


def synthetic_rollout(population: Any, n_steps: int, seed: int = 0) -> list[Any]:
    """Flattened rollouts ``[P, T, ...]`` of the population's shapes, as ``update`` reads them.

    Args:
        population: A :class:`~ermrl.population.PopulationPPO`.
        n_steps: Steps per agent ``T``.
        seed: Seed of the numpy generator that draws the data.

    Returns:
        ``[obs, actions, old_values, old_log_probs, advantages, returns]`` torch tensors.
    """
    import numpy as np
    import torch

    rng = np.random.default_rng(seed)
    P, d = population.n_agents, population.envs.policy_dim
    spec = population.spec
    obs = rng.standard_normal((P, n_steps, d)).astype(np.float32)
    if population.discrete:
        actions = rng.integers(0, spec.action_dim, (P, n_steps))
    else:
        actions = rng.standard_normal((P, n_steps, spec.action_dim)).astype(np.float32)
    values, advantages, returns = (
        rng.standard_normal((P, n_steps)).astype(np.float32) for _ in range(3)
    )
    log_probs = (-np.abs(rng.standard_normal((P, n_steps))) - 1.0).astype(np.float32)
    arrays = [obs, actions, values, log_probs, advantages, returns]
    return [torch.from_numpy(a) for a in arrays]


def measure(task_spec: str, n_agents: int, epochs: int, repeats: int) -> dict[str, Any]:
    """Time ``repeats`` updates of ``epochs`` epochs each; one result row."""
    import threadpoolctl
    import torch

    from ermrl.agents import resolve_ppo_config, with_overrides
    from ermrl.config import EncoderConfig, TaskConfig
    from ermrl.population import PopulationJob, PopulationPPO

    env_id, _, observe = task_spec.partition(":")
    task = TaskConfig(env_id, observe or "all")
    packaged = resolve_ppo_config(env_id)
    ppo = with_overrides(packaged, {"n_epochs": epochs})
    # One thread for torch and for BLAS (numpy's products in the update), as a training
    # process runs (train_population sets both from torch_threads, 1 by default).
    torch.set_num_threads(1)
    threadpoolctl.threadpool_limits(1)
    jobs = [PopulationJob(EncoderConfig(), seed) for seed in range(n_agents)]
    population = PopulationPPO(task, ppo, jobs)
    try:
        s = population.s
        T = int(s["n_steps"]) * ppo.n_envs
        n_minibatches = epochs * -(-T // int(s["batch_size"]))
        data = synthetic_rollout(population, T)
        population.update(1.0, *data)  # warm-up
        seconds = []
        for r in range(repeats):
            start = time.process_time()
            population.update(1.0, *data)
            seconds.append(time.process_time() - start)
            print(
                f"{task_spec} {n_agents} agents repeat {r + 1}/{repeats}: "
                f"{seconds[-1] / n_minibatches * 1e6:.0f} us per minibatch",
                file=sys.stderr,
                flush=True,
            )
        per_minibatch = median(seconds) / n_minibatches
        full_epochs = int(packaged.hyperparams.get("n_epochs", 10))  # SB3 default: 10
        per_epoch = median(seconds) / epochs
        return {
            "task": task_spec,
            "agents": n_agents,
            "steps_per_agent": T,
            "batch_size": int(s["batch_size"]),
            "n_epochs": full_epochs,
            "us_per_minibatch": per_minibatch * 1e6,
            "update_us_per_agent_step": per_epoch * full_epochs / (n_agents * T) * 1e6,
            "seconds": seconds,
        }
    finally:
        population.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="HalfCheetah-v5:all", help="ENV_ID[:observe]")
    parser.add_argument("--agents", type=int, default=8, help="population size")
    parser.add_argument("--epochs", type=int, default=1, help="epochs per timed update")
    parser.add_argument("--repeats", type=int, default=5, help="timed updates")
    parser.add_argument("--quick", action="store_true", help="Pendulum-v1, 2 agents, 2 repeats")
    parser.add_argument("--out", type=Path, default=None, help="write the row as JSON here")
    args = parser.parse_args(argv)
    if args.quick:
        args.task, args.agents, args.repeats = "Pendulum-v1:positions", 2, 2
    row = measure(args.task, args.agents, args.epochs, args.repeats)
    columns = ["task", "agents", "steps_per_agent", "batch_size", "n_epochs"]
    print(table([row], [*columns, "us_per_minibatch", "update_us_per_agent_step"]))
    if args.out is not None:
        write_json(args.out, {"rows": [row]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
