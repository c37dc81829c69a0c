"""``--tensorboard DIR`` on the population backend (the default): each run's folder gets the
scalars SB3's PPO logs for one run, and logging leaves the results unchanged."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("tensorboard", reason="--tensorboard needs the tensorboard package")


def ermrl(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args], cwd=cwd, capture_output=True, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"}, timeout=600,
    )  # fmt: skip


def test_a_population_test_phase_logs_each_run_for_tensorboard(tmp_path: Path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    names = ["--storage", f"sqlite:///{tmp_path}/s.db", "--study-name", "p"]
    proc = ermrl(
        "evolve", "--env-id", "CartPole-v1", "--n-trials", "1", "--n-seeds", "1",
        "--training-steps", "128", "--n-envs", "1", "--units", "10", "--backend", "population",
        "--ppo", "n_steps=64", "batch_size=64", "n_epochs=1", *names, "--quiet", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    common = [
        "test", *names, "--agents", "ppo", "res-ppo", "--seeds", "20", "21",
        "--training-steps", "512", "--n-procs", "1", "--quiet",
    ]  # fmt: skip
    logged = ermrl(*common, "--out", "a", "--tensorboard", "tb", cwd=tmp_path)
    assert logged.returncode == 0, logged.stderr
    assert "sb3" not in logged.stderr  # no fallback to the sb3 backend
    plain = ermrl(*common, "--out", "b", cwd=tmp_path)
    assert plain.returncode == 0, plain.stderr
    for agent in ("ppo", "res-ppo"):
        for seed in (20, 21):
            run = f"agents/{agent}/seed_{seed}"
            settings = json.loads((tmp_path / "a" / run / "settings.json").read_text())
            assert settings["ppo"]["backend"] == "population"
            a = json.loads((tmp_path / "a" / run / "result.json").read_text())
            b = json.loads((tmp_path / "b" / run / "result.json").read_text())
            assert a["final_return"] == b["final_return"]  # logging changes no training
            (events,) = (tmp_path / "tb" / agent / f"seed_{seed}").rglob("events.out.tfevents.*")
            acc = EventAccumulator(str(events))
            acc.Reload()
            tags = set(acc.Tags()["scalars"])
            assert {"rollout/ep_rew_mean", "time/fps", "train/loss", "train/value_loss"} <= tags
            assert [e.step for e in acc.Scalars("time/fps")] == list(range(64, 513, 64))


def test_a_generation_logs_each_run_under_its_candidates_trial(tmp_path: Path) -> None:
    """train_generation with TensorBoard: (candidate, seed) -> <tb>/trial_<n>/seed_<s>, with n
    the candidate's trial number (runner.trials), each run's own returns in its folder."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from ermrl.agents import resolve_ppo_config, with_overrides
    from ermrl.config import BudgetConfig, EncoderConfig, ReservoirParams, TaskConfig
    from ermrl.search import SeedRunner
    from ermrl.search._objective import train_generation

    task = TaskConfig("CartPole-v1", "positions")
    ppo = dataclasses.replace(
        with_overrides(
            resolve_ppo_config("CartPole-v1"), {"n_steps": 64, "batch_size": 64, "n_epochs": 1}
        ),
        n_envs=1,
        backend="population",
    )
    encoders = [
        EncoderConfig(reservoirs=(ReservoirParams(units=8, sr=0.5 + 0.3 * k, lr=0.5),))
        for k in range(2)
    ]
    with SeedRunner(1, tensorboard=tmp_path / "tb") as runner:
        with pytest.raises(ValueError, match="one trial number per candidate"):
            train_generation(encoders, [(task, ppo)], BudgetConfig(256), (3, 4), runner=runner)
        runner.trials = (7, 2)
        trained = train_generation(
            encoders, [(task, ppo)], BudgetConfig(256), (3, 4), runner=runner
        )
    assert sorted(p.name for p in (tmp_path / "tb").iterdir()) == ["trial_2", "trial_7"]
    for trial, (runs,) in zip((7, 2), trained):
        for seed, run in zip((3, 4), runs):
            assert not isinstance(run, BaseException) and run.seed == seed
            (events,) = (tmp_path / "tb" / f"trial_{trial}" / f"seed_{seed}").rglob(
                "events.out.tfevents.*"
            )
            acc = EventAccumulator(str(events))
            acc.Reload()
            last = acc.Scalars("rollout/ep_rew_mean")[-1]
            assert last.step == 256
            assert last.value == pytest.approx(np.mean(run.episode_returns[-100:]), rel=1e-6)
