"""``--tensorboard DIR`` on ``ermrl evolve`` and ``ermrl run``: a real tiny evolution whose runs
write TensorBoard event files, read back with TensorBoard's own reader."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("tensorboard", reason="--tensorboard needs the tensorboard package")


def ermrl(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args], cwd=cwd, capture_output=True, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"}, timeout=600,
    )  # fmt: skip


TINY = [
    "evolve", "--env-id", "CartPole-v1", "--n-trials", "2", "--n-seeds", "1",
    "--training-steps", "256", "--n-envs", "1", "--units", "10",
    "--ppo", "n_steps=128", "batch_size=64", "n_epochs=1", "--quiet",
]  # fmt: skip


def scalars(folder: Path) -> dict[str, int]:
    """``{tag: number of points}`` of the event files under ``folder`` (TensorBoard's reader)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    found: dict[str, int] = {}
    for events in folder.rglob("events.out.tfevents.*"):
        acc = EventAccumulator(str(events))
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            found[tag] = found.get(tag, 0) + len(acc.Scalars(tag))
    return found


def test_evolve_logs_every_trials_runs_for_tensorboard_with_the_sb3_backend(
    tmp_path: Path,
) -> None:
    tb = tmp_path / "tb"
    proc = ermrl(
        *TINY, "--backend", "sb3", "--storage", f"sqlite:///{tmp_path}/s.db",
        "--tensorboard", str(tb), cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    for trial in (0, 1):
        found = scalars(tb / f"trial_{trial}" / "seed_0")
        # Two rollouts of 128 steps: SB3 dumps its logger after each.
        assert found.get("time/fps", 0) >= 2, found
        assert "train/loss" in found and "train/entropy_loss" in found, found
    assert sorted(p.name for p in tb.iterdir()) == ["trial_0", "trial_1"]


def test_a_population_evolution_logs_each_trials_runs_as_sb3_would(tmp_path: Path) -> None:
    """--backend left out: the population backend trains the generation (no fallback to sb3),
    and each (trial, seed) run gets its own folder with SB3's PPO scalars."""
    import optuna

    tb = tmp_path / "tb"
    proc = ermrl(
        "evolve", "--env-id", "CartPole-v1", "--n-trials", "2", "--n-seeds", "2",
        "--training-steps", "512", "--n-envs", "1", "--units", "10",
        "--ppo", "n_steps=128", "batch_size=64", "n_epochs=1", "--quiet",
        "--storage", f"sqlite:///{tmp_path}/s.db", "--study-name", "p",
        "--tensorboard", str(tb), cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "sb3" not in proc.stderr + proc.stdout
    study = optuna.load_study(study_name="p", storage=f"sqlite:///{tmp_path}/s.db")
    assert {t.user_attrs["backend"] for t in study.trials} == {"population"}
    for trial in (0, 1):
        for seed in (0, 1):
            found = scalars(tb / f"trial_{trial}" / f"seed_{seed}")
            assert found.get("time/fps") == 4, found  # four rollouts of 128 steps
            assert found.get("rollout/ep_rew_mean") == 4, found
            assert {"train/loss", "train/value_loss", "train/entropy_loss"} <= set(found), found
    assert sorted(p.name for p in tb.iterdir()) == ["trial_0", "trial_1"]


def test_run_passes_tensorboard_and_progress_to_the_stages_that_take_them(
    tmp_path: Path,
) -> None:
    from ermrl.cli._run import build_run_parser
    from ermrl.cli._test import build_test_parser
    from ermrl.runner._experiment import experiment_plan, load_experiment
    from ermrl.runner._run import stage_argv

    path = tmp_path / "exp.yaml"
    path.write_text(
        "name: tb\ntasks: [CartPole-v1]\n"
        "evolve: {units: 10, n_trials: 1, n_seeds: 1, training_steps: 256, n_envs: 1}\n"
        "test: {agents: [ppo], seeds: [10], training_steps: 256}\nreport: {html: true}\n"
    )
    steps = experiment_plan(load_experiment(path), build_agents=False)
    args = build_run_parser().parse_args(
        [str(path), "--tensorboard", str(tmp_path / "tb"), "--progress", "none"]
    )
    by_stage = {s.stage: stage_argv(s, args.progress, args.tensorboard) for s in steps}
    evolve, test, report = by_stage["evolve"], by_stage["test"], by_stage["report"]
    assert evolve[-4:] == [
        "--progress", "none", "--tensorboard", str(tmp_path / "tb" / "CartPole-v1" / "evolve")
    ]  # fmt: skip
    parsed = build_test_parser().parse_args(test)  # the command's own parser takes them
    assert parsed.tensorboard == str(tmp_path / "tb" / "CartPole-v1" / "test")
    assert parsed.progress == "none"
    assert "--tensorboard" not in report and "--progress" not in report


def test_run_plans_tensorboard_stages_as_they_will_run(tmp_path: Path) -> None:
    """With ``ermrl run --tensorboard``, the evolve and test stages keep the backend they
    would choose without it (both log on either backend): the plan's estimates are unchanged,
    and an evolve stage whose file sets ``backend: population`` is planned, not refused."""
    from ermrl.runner._experiment import experiment_plan, load_experiment

    path = tmp_path / "exp.yaml"
    path.write_text(
        "name: tb\ntasks: [HalfCheetah-v5]\nout: out\n"
        "evolve: {n_trials: 2, n_seeds: 1, training_steps: 100000}\n"
        "test: {agents: [ppo, res-ppo], seeds: [10], training_steps: 100000}\n"
    )
    exp = load_experiment(path)
    plain = {s.stage: s.seconds for s in experiment_plan(exp, build_agents=False)}
    logged = {
        s.stage: s.seconds
        for s in experiment_plan(dataclasses.replace(exp, tensorboard=True), build_agents=False)
    }
    assert logged == plain

    path.write_text(path.read_text().replace("n_trials: 2", "n_trials: 2, backend: population"))
    exp = dataclasses.replace(load_experiment(path), tensorboard=True)
    steps = experiment_plan(exp, build_agents=False)
    assert {s.stage: s.seconds for s in steps}["evolve"] == plain["evolve"]


@pytest.mark.slow  # an evolution, then a test phase
def test_test_generalization_logs_each_agents_runs_for_tensorboard(tmp_path: Path) -> None:
    storage = f"sqlite:///{tmp_path}/s.db"
    assert ermrl(*TINY, "--storage", storage, cwd=tmp_path).returncode == 0
    tb = tmp_path / "tb"
    proc = ermrl(
        "test-generalization", "--storage", storage, "--study-name",
        "CartPole-v1__all__256steps", "--env-id", "CartPole-v1", "--agents", "ppo", "res-ppo",
        "--seeds", "5", "--training-steps", "256", "--ppo", "n_steps=128", "batch_size=64",
        "n_epochs=1", "--quiet", "--tensorboard", str(tb), cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    for agent in ("ppo", "res-ppo"):
        found = scalars(tb / agent / "seed_5")
        assert found.get("time/fps", 0) >= 2 and "train/loss" in found, (agent, found)
    assert sorted(p.name for p in tb.iterdir()) == ["ppo", "res-ppo"]


def test_every_command_ermrl_run_gives_tensorboard_to_takes_it() -> None:
    from ermrl.cli._evolve import build_evolve_parser
    from ermrl.cli._generalization import (
        build_evolve_generalization_parser,
        build_test_generalization_parser,
    )
    from ermrl.cli._test import build_test_parser
    from ermrl.runner._run import TENSORBOARD_COMMANDS

    parsers = {
        "evolve": build_evolve_parser(),
        "evolve-generalization": build_evolve_generalization_parser(),
        "test": build_test_parser(),
        "test-generalization": build_test_generalization_parser(),
    }
    assert set(TENSORBOARD_COMMANDS) == set(parsers)
    for command, parser in parsers.items():
        options = {o for a in parser._actions for o in a.option_strings}
        assert "--tensorboard" in options, command
