"""Benchmark 1: encoder overhead.

Env steps per second of a raw ``VecEnv`` against the same ``VecEnv`` wrapped by ermrl's
``ReservoirVecEnv`` (default float32 state; ``ermrl-f64`` is the exact float64 mode), and, as a reference, against the original ER-MRL pattern: a gymnasium wrapper
that calls a reservoirpy ``Reservoir`` node once per step per env. Variants alternate within
each repeat; the table gives medians and ratios. Everything runs in this process on one thread
(BLAS pinned), and rates use this process's CPU time, so other load on the machine does not skew
the comparison.

    python benchmarks/bench_encoder.py            # full grid (HalfCheetah/Ant x 100/500 units x 1/8 envs)
    python benchmarks/bench_encoder.py --quick    # a small, fast version (CI)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import alternate, median, table, timed_rate, write_json  # noqa: E402
from ermrl.config import EncoderConfig, ReservoirParams  # noqa: E402
from ermrl.encoders import ReservoirVecEnv  # noqa: E402

TARGET_OVERHEAD = 0.05  # at 100 units and 8 envs
TARGET_VS_NODE = 10.0  # ermrl's per-step overhead at least 10x smaller than the node wrapper's


class PerStepNodeWrapper(gym.Wrapper):
    """The original ER-MRL pattern: one reservoirpy node per env, one node call per step."""

    def __init__(self, env: gym.Env, units: int, seed: int) -> None:
        super().__init__(env)
        from reservoirpy.nodes import Reservoir

        obs_dim = env.observation_space.shape[0]
        act_dim = env.action_space.shape[0]
        self.node = Reservoir(
            units=units, sr=0.9, lr=0.3, input_dim=obs_dim + act_dim + 1, seed=seed
        )
        self.node.initialize(np.zeros(obs_dim + act_dim + 1))
        self.act_dim = act_dim
        self.observation_space = gym.spaces.Box(-1.0, 1.0, shape=(units,), dtype=np.float32)

    def reset(self, **kwargs):  # noqa: ANN003, ANN201
        obs, info = self.env.reset(**kwargs)
        self.node.reset()
        u = np.concatenate([obs, np.zeros(self.act_dim), [0.0]])
        return self.node.step(u).astype(np.float32), info

    def step(self, action):  # noqa: ANN001, ANN201
        obs, reward, terminated, truncated, info = self.env.step(action)
        u = np.concatenate([obs, action, [reward]])
        return self.node.step(u).astype(np.float32), reward, terminated, truncated, info


def make_raw(env_id: str, n_envs: int) -> gym.vector.VectorEnv:
    from stable_baselines3.common.vec_env import DummyVecEnv

    venv = DummyVecEnv([lambda: gym.make(env_id)] * n_envs)
    venv.seed(0)
    return venv


def make_variants(env_id: str, units: int, n_envs: int, steps: int) -> dict:
    from stable_baselines3.common.vec_env import DummyVecEnv

    raw = make_raw(env_id, n_envs)
    reservoirs = (ReservoirParams(units=units, sr=0.9, lr=0.3),)
    encoded = ReservoirVecEnv(make_raw(env_id, n_envs), EncoderConfig(reservoirs), seed=0)
    encoded64 = ReservoirVecEnv(
        make_raw(env_id, n_envs), EncoderConfig(reservoirs, dtype="float64"), seed=0
    )
    node = DummyVecEnv(
        [lambda i=i: PerStepNodeWrapper(gym.make(env_id), units, i) for i in range(n_envs)]
    )
    node.seed(0)
    space = raw.action_space
    rng = np.random.default_rng(0)
    actions = rng.uniform(space.low, space.high, size=(steps, n_envs, space.shape[0])).astype(
        np.float32
    )
    for venv in (raw, encoded, encoded64, node):
        venv.reset()

    def runner(venv):  # noqa: ANN001, ANN202
        def work() -> int:
            for t in range(steps):
                venv.step(actions[t])
            return steps * n_envs

        return lambda: timed_rate(work, clock=time.process_time)

    return {
        "raw": runner(raw),
        "ermrl": runner(encoded),
        "ermrl-f64": runner(encoded64),
        "node-per-step": runner(node),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="small grid, few steps (CI)")
    parser.add_argument("--steps", type=int, default=None, help="vector steps per measurement")
    parser.add_argument("--repeats", type=int, default=None, help="measurements per variant")
    parser.add_argument("--out", default="benchmarks/results/encoder.json", help="JSON results")
    args = parser.parse_args(argv)
    import threadpoolctl

    threadpoolctl.threadpool_limits(1)
    if args.quick:
        grid = [("HalfCheetah-v5", 100, 8)]
        steps, repeats = args.steps or 100, args.repeats or 2
    else:
        grid = [(e, u, n) for e in ("HalfCheetah-v5", "Ant-v5") for u in (100, 500) for n in (1, 8)]
        steps, repeats = args.steps or 1000, args.repeats or 7

    rows = []
    for env_id, units, n_envs in grid:
        rates = alternate(make_variants(env_id, units, n_envs, steps), repeats)
        raw, ours, ours64, node = (
            median(rates[k]) for k in ("raw", "ermrl", "ermrl-f64", "node-per-step")
        )
        # Per env-step cost added on top of the raw env, in microseconds.
        ours_us = max(1e6 / ours - 1e6 / raw, 0.0)
        ours64_us = max(1e6 / ours64 - 1e6 / raw, 0.0)
        node_us = max(1e6 / node - 1e6 / raw, 0.0)
        rows.append(
            {
                "env": env_id,
                "units": units,
                "n_envs": n_envs,
                "raw_steps_s": raw,
                "ermrl_steps_s": ours,
                "node_steps_s": node,
                "ermrl_f64_steps_s": ours64,
                "ermrl_overhead_%": 100 * (raw / ours - 1),
                "ermrl_f64_overhead_%": 100 * (raw / ours64 - 1),
                "node_overhead_%": 100 * (raw / node - 1),
                "ermrl_us_per_step": ours_us,
                "ermrl_f64_us_per_step": ours64_us,
                "node_us_per_step": node_us,
                "cheaper_than_node_x": node_us / ours_us if ours_us > 0 else float("inf"),
                "repeats": repeats,
                "steps": steps,
                "rates": rates,
            }
        )
    columns = [
        "env", "units", "n_envs", "raw_steps_s", "ermrl_steps_s", "ermrl_f64_steps_s", "node_steps_s",
        "ermrl_overhead_%", "ermrl_f64_overhead_%", "node_overhead_%",
        "ermrl_us_per_step", "ermrl_f64_us_per_step", "node_us_per_step", "cheaper_than_node_x",
    ]  # fmt: skip
    print(table(rows, columns))
    checks = [r for r in rows if r["units"] == 100 and r["n_envs"] == 8]
    for r in checks:
        ok_overhead = r["ermrl_overhead_%"] <= 100 * TARGET_OVERHEAD
        ok_node = r["cheaper_than_node_x"] >= TARGET_VS_NODE
        print(
            f"target {r['env']} 100 units 8 envs: overhead {r['ermrl_overhead_%']:.1f}% "
            f"(<= {100 * TARGET_OVERHEAD:.0f}%: {'met' if ok_overhead else 'NOT met'}); "
            f"{r['cheaper_than_node_x']:.1f}x cheaper per step than the node wrapper "
            f"(>= {TARGET_VS_NODE:.0f}x: {'met' if ok_node else 'NOT met'})"
        )
    path = write_json(args.out, {"benchmark": "encoder", "quick": args.quick, "rows": rows})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
