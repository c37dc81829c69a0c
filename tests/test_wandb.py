"""``--wandb PROJECT``: an evolution's trials through optuna-integration's callback, a test
phase's runs through wandb's own SB3 callback; checked on the files wandb really writes in
offline mode (``WANDB_MODE=offline``; no server is reached)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("wandb", reason="wandb is not installed (pip install 'ermrl[wandb]')")
pytest.importorskip("optuna_integration", reason="optuna-integration is not installed")
OFFLINE = {"WANDB_MODE": "offline", "WANDB_SILENT": "true"}

TINY = ["--n-envs", "1", "--ppo", "n_steps=64", "batch_size=32", "n_epochs=1", "--units", "10"]


def ermrl(
    *args: str, cwd: Path, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args],
        cwd=cwd, env={**os.environ, **(env or {})}, capture_output=True, text=True, timeout=600,
    )  # fmt: skip


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[str]]:
    """A one-trial CartPole study (positions) and the storage options that name it."""
    root = tmp_path_factory.mktemp("wandb")
    names = ["--storage", f"sqlite:///{root}/s.db", "--study-name", "wb"]
    proc = ermrl(
        "evolve", "--env-id", "CartPole-v1", "--observe", "positions", "--n-trials", "1",
        "--n-seeds", "1", "--training-steps", "256", *TINY, *names, "--quiet", cwd=root,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return root, names


def test_each_run_is_a_wandb_run_with_synced_curves_and_its_outcome(
    study: tuple[Path, list[str]], tmp_path: Path
) -> None:
    root, names = study
    out = tmp_path / "phase"
    proc = ermrl(
        "test", *names, "--agents", "ppo", "res-ppo", "--seeds", "20", "21",
        "--training-steps", "512", "--out", str(out), "--wandb", "ermrl-tests", "--quiet",
        cwd=root, env={"WANDB_MODE": "offline", "WANDB_DIR": str(tmp_path), "WANDB_SILENT": "true"},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    # No --backend: the population backend would apply, so the switch to sb3 is one line.
    notes = [line for line in proc.stderr.splitlines() if "--wandb" in line]
    assert notes == [
        "ermrl test: training with the sb3 backend: --wandb logs through wandb's callback for "
        "the sb3 backend"
    ]
    runs = sorted((tmp_path / "wandb").glob("offline-run-*/run-*.wandb"))
    assert len(runs) == 4  # 2 agents x 2 seeds, one W&B run each
    for run in runs:
        data = run.read_bytes()
        assert b"ermrl/last_return" in data  # the outcome, in the summary
        assert b"rollout/ep_rew_mean" in data  # SB3's scalars, synced from TensorBoard
        assert b"ermrl-tests" in data and b"phase" in data  # project and group
    named = b"".join(r.read_bytes() for r in runs)
    for name in (b"ppo-seed20", b"ppo-seed21", b"res-ppo-seed20", b"res-ppo-seed21"):
        assert name in named
    assert len(list(out.glob("agents/*/seed_*/result.json"))) == 4  # the test phase itself is whole


def test_wandb_with_the_population_backend_is_one_line(
    study: tuple[Path, list[str]], tmp_path: Path
) -> None:
    root, names = study
    proc = ermrl(
        "test", *names, "--agents", "ppo", "--seeds", "20", "--training-steps", "512",
        "--backend", "population", "--wandb", "p", "--out", str(tmp_path / "o"), cwd=root,
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "ermrl test: error: --wandb logs come from the sb3 backend; use --backend sb3"
    ]
    assert not (tmp_path / "o").exists()


def test_missing_wandb_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """wandb is installed here, so its absence is simulated (the only mock in this file)."""
    import ermrl.agents
    from ermrl.cli import test_main

    monkeypatch.setattr(ermrl.agents, "wandb_installed", lambda: False)
    with pytest.raises(SystemExit) as exit_:
        test_main(["--study-name", "x", "--storage", "sqlite:///x.db", "--wandb", "p"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        "ermrl test: error: --wandb needs the wandb and optuna-integration packages, which are "
        "not installed (pip install 'ermrl[wandb]')"
    ]


def test_evolution_logs_each_trial_to_one_run_per_worker(tmp_path: Path) -> None:
    proc = ermrl(
        "evolve", "--env-id", "CartPole-v1", "--observe", "positions", "--n-trials", "3",
        "--n-seeds", "1", "--training-steps", "256", *TINY, "--backend", "sb3",
        "--storage", f"sqlite:///{tmp_path}/e.db", "--study-name", "wbevo",
        "--wandb", "ermrl-evo", "--quiet",
        cwd=tmp_path, env={**OFFLINE, "WANDB_DIR": str(tmp_path)},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    (run,) = (tmp_path / "wandb").glob("offline-run-*/run-*.wandb")  # one run: one worker
    data = run.read_bytes()
    for needle in (b"ermrl-evo", b"wbevo", b"input_scaling"):
        assert needle in data, needle
    assert data.count(b"fitness") >= 3  # each trial's record


def test_evolution_without_wandb_packages_is_one_line_and_writes_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The packages are installed here, so their absence is simulated."""
    import ermrl.agents
    from ermrl.cli import evolve_main

    monkeypatch.setattr(ermrl.agents, "wandb_installed", lambda: False)
    db = tmp_path / "e.db"
    with pytest.raises(SystemExit) as exit_:
        evolve_main(["--env-id", "CartPole-v1", "--storage", f"sqlite:///{db}", "--wandb", "p"])
    assert exit_.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "ermrl evolve: error: --wandb needs the wandb and optuna-integration packages, which are "
        "not installed (pip install 'ermrl[wandb]')"
    ]
    assert not db.exists()


def test_run_passes_wandb_to_the_evolve_and_test_stages_and_plans_the_test_on_sb3(
    tmp_path: Path,
) -> None:
    """``ermrl run FILE --wandb PROJECT`` gives ``--wandb`` to evolve and test (not to the
    report), plans the test stage at sb3's speed (its command will train with sb3), and refuses
    a test stage whose file sets ``backend: population`` in one line before anything runs."""
    from ermrl.cli._run import build_run_parser
    from ermrl.cli._test import build_test_parser
    from ermrl.runner._experiment import load_experiment
    from ermrl.runner._run import plan_experiment, stage_argv

    path = tmp_path / "exp.yaml"
    path.write_text(
        "name: wb\ntasks: [HalfCheetah-v5]\nout: out\n"
        "evolve: {n_trials: 2, n_seeds: 1, training_steps: 100000}\n"
        "test: {agents: [ppo, res-ppo], seeds: [10], training_steps: 100000}\n"
        "report: {html: true}\n"
    )
    exp = load_experiment(path)
    _, plain, _ = plan_experiment(exp, build_agents=False)
    _, logged, _ = plan_experiment(exp, wandb=True, build_agents=False)
    seconds = {s.stage: s.seconds for s in plain}
    with_wandb = {s.stage: s.seconds for s in logged}
    assert with_wandb["test"] > 2 * seconds["test"]  # sb3, several times slower
    args = build_run_parser().parse_args([str(path), "--wandb", "proj"])
    by_stage = {s.stage: stage_argv(s, None, None, wandb=args.wandb) for s in logged}
    assert by_stage["evolve"][-2:] == ["--wandb", "proj"]
    assert build_test_parser().parse_args(by_stage["test"]).wandb == "proj"
    assert "--wandb" not in by_stage["report"]

    path.write_text(path.read_text().replace("seeds: [10]", "seeds: [10], backend: population"))
    proc = ermrl("run", str(path), "--wandb", "proj", cwd=tmp_path)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "--wandb logs come from the sb3 backend" in proc.stderr
    assert not (tmp_path / "out").exists()
