"""Policies are saved and read back as plain tensors; ``model.zip`` is never unpickled."""

from __future__ import annotations

import base64
import json
import pickle
import shutil
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ermrl import analysis
from ermrl.agents import load_policy, make_vec_env, policy_path, train_agent
from ermrl.config import BudgetConfig, EncoderConfig, PPOConfig, ReservoirParams, TaskConfig

TASK = TaskConfig("Pendulum-v1", "positions")
RESERVOIRS = (ReservoirParams(units=20, sr=0.9, lr=0.5),)
TINY_PPO = PPOConfig(
    hyperparams={
        "n_steps": 128,
        "batch_size": 64,
        "n_epochs": 2,
        "policy_kwargs": {"net_arch": [16, 16], "log_std_init": -1.0, "ortho_init": False},
    }
)


class _Marker:
    """Unpickling this creates a file: it stands for the code a crafted file would run."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (self.path,))


def craft_model_zip(path: Path, marker: Path) -> None:
    """An SB3 ``model.zip`` whose loading (``PPO.load``) creates ``marker``."""
    payload = base64.b64encode(pickle.dumps(_Marker(marker))).decode()
    data = {"policy_class": {":type:": "<class 'type'>", ":serialized:": payload}}
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("data", json.dumps(data))


@pytest.mark.parametrize("encoder", [None, EncoderConfig(reservoirs=RESERVOIRS)])
def test_plain_policy_acts_exactly_like_the_trained_model(
    tmp_path: Path, encoder: EncoderConfig | None
) -> None:
    from stable_baselines3 import PPO

    model_path = tmp_path / "model.zip"
    train_agent(TASK, encoder, TINY_PPO, BudgetConfig(training_steps=256), 0, model_path=model_path)
    assert policy_path(model_path) == tmp_path / "policy.pt"
    trusted = PPO.load(str(model_path), device="cpu")  # our own file, in a test
    env = make_vec_env(TASK, 1, 0, encoder, 0)
    try:
        plain = load_policy(tmp_path / "policy.pt", TINY_PPO, env)
    finally:
        env.close()
    observations = np.random.default_rng(0).normal(size=(50, *trusted.observation_space.shape))
    a, _ = trusted.predict(observations.astype(np.float32), deterministic=True)
    b, _ = plain.predict(observations.astype(np.float32), deterministic=True)
    np.testing.assert_array_equal(a, b)
    for name, tensor in trusted.policy.state_dict().items():
        np.testing.assert_array_equal(plain.policy.state_dict()[name].numpy(), tensor.numpy())


def test_plain_policy_file_holds_tensors_only(tmp_path: Path) -> None:
    import torch

    model_path = tmp_path / "model.zip"
    train_agent(TASK, None, TINY_PPO, BudgetConfig(training_steps=256), 0, model_path=model_path)
    state = torch.load(tmp_path / "policy.pt", weights_only=True)
    assert state and all(isinstance(v, torch.Tensor) for v in state.values())


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A test-phase folder with one tiny res-ppo run (policy.pt and model.zip)."""
    from ermrl.test_phase import AgentSpec, TestSettings, run_comparison

    out = tmp_path_factory.mktemp("runs")
    run_comparison(
        TASK,
        EncoderConfig(reservoirs=RESERVOIRS),
        TINY_PPO,
        [AgentSpec("res-ppo", RESERVOIRS)],
        TestSettings(training_steps=256, seeds=(3,), out=out),
        quiet=True,
    )
    return out


def test_replay_reads_the_plain_policy_and_never_model_zip(
    run_folder: Path, tmp_path: Path
) -> None:
    from stable_baselines3 import PPO

    folder = run_folder / "agents/res-ppo/seed_3"
    trusted = PPO.load(str(folder / "model.zip"), device="cpu")
    expected = analysis.rollout(analysis.load_trained_agent(run_folder, "res-ppo", 3), max_steps=20)
    # The trained model, given the states the replay saw, one step at a time as in the replay.
    for state, action in zip(expected.states.astype(np.float32), expected.actions):
        np.testing.assert_array_equal(
            trusted.predict(state[None], deterministic=True)[0][0], action
        )

    marker = tmp_path / "executed"
    runs = tmp_path / "runs"
    shutil.copytree(run_folder, runs)
    crafted = runs / "agents/res-ppo/seed_3/model.zip"
    craft_model_zip(crafted, marker)
    # The crafted file is live: SB3's loader would run it.
    with pytest.raises(Exception):  # noqa: B017, PT011 (whatever SB3 makes of the payload)
        PPO.load(str(crafted), device="cpu")
    assert marker.exists()
    marker.unlink()

    episode = analysis.rollout(analysis.load_trained_agent(runs, "res-ppo", 3), max_steps=20)
    np.testing.assert_array_equal(episode.actions, expected.actions)
    assert not marker.exists()

    # Without policy.pt, the run is refused in one line, whichever way it is asked for.
    (runs / "agents/res-ppo/seed_3/policy.pt").unlink()
    assert analysis.available_runs(runs) == []
    for seed in (3, None):
        with pytest.raises(FileNotFoundError, match="never loads") as info:
            analysis.load_trained_agent(runs, "res-ppo", seed)
        assert "re-train" in str(info.value) and "\n" not in str(info.value)
    assert not marker.exists()


@pytest.mark.parametrize("command", ["dynamics", "video"])
def test_cli_refuses_a_run_with_only_model_zip(
    run_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    from ermrl.cli._dynamics import dynamics_main
    from ermrl.cli._video import video_main

    marker = tmp_path / "executed"
    runs = tmp_path / "runs"
    shutil.copytree(run_folder, runs)
    (runs / "agents/res-ppo/seed_3/policy.pt").unlink(missing_ok=True)
    craft_model_zip(runs / "agents/res-ppo/seed_3/model.zip", marker)
    main = dynamics_main if command == "dynamics" else video_main
    for seed in ([], ["--seed", "3"]):
        with pytest.raises(SystemExit) as info:
            main(["--run", str(runs), *seed, "--out", str(tmp_path / "out")])
        assert info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert "re-train" in err and len(err.splitlines()) == 1
    assert not marker.exists()


def test_report_leaves_out_the_dynamics_of_a_run_with_only_model_zip(
    run_folder: Path, tmp_path: Path
) -> None:
    from ermrl.analysis._report import _dynamics_section, _State

    marker = tmp_path / "executed"
    runs = tmp_path / "runs"
    shutil.copytree(run_folder, runs)
    (runs / "agents/res-ppo/seed_3/policy.pt").unlink(missing_ok=True)
    craft_model_zip(runs / "agents/res-ppo/seed_3/model.zip", marker)
    state = _State(out=tmp_path / "report", study=None, storage="")
    _dynamics_section(state, runs)
    assert any("model.zip" in note and "re-train" in note for note in state.notes)
    assert not marker.exists()


def _craft_policy(path: Path, kind: str, marker: Path) -> None:
    """A ``policy.pt`` that is not one ermrl wrote (``kind`` says how)."""
    import io

    import torch

    if kind == "garbage":
        path.write_bytes(b"\x00not a torch file" * 8)
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "pickle":
        path.write_bytes(pickle.dumps({"weight": _Marker(marker)}))
    elif kind == "torch-pickle":
        buffer = io.BytesIO()
        torch.save({"weight": _Marker(marker)}, buffer)
        path.write_bytes(buffer.getvalue())
    elif kind == "not-a-state-dict":
        torch.save([torch.zeros(2)], path)
    elif kind == "wrong-shapes":
        state = torch.load(path, weights_only=True)
        torch.save({name: torch.zeros(3, 3) for name in state}, path)


CRAFTED_POLICIES = [
    "garbage",
    "empty",
    "pickle",
    "torch-pickle",
    "not-a-state-dict",
    "wrong-shapes",
]


@pytest.mark.parametrize("kind", CRAFTED_POLICIES)
def test_a_crafted_policy_file_is_one_line_in_dynamics_and_report(
    run_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str
) -> None:
    from ermrl.analysis import RunFolderError
    from ermrl.analysis._report import _dynamics_section, _State
    from ermrl.cli._dynamics import dynamics_main

    marker = tmp_path / "executed"
    runs = tmp_path / "runs"
    shutil.copytree(run_folder, runs)
    policy = runs / "agents/res-ppo/seed_3/policy.pt"
    _craft_policy(policy, kind, marker)
    with pytest.raises(SystemExit) as info:
        dynamics_main(["--run", str(runs), "--seed", "3", "--out", str(tmp_path / "out")])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{policy}: " in err, err
    assert not (tmp_path / "out").exists()
    # The report's dynamics section raises what ermrl report turns into one line.
    state = _State(out=tmp_path / "report", study=None, storage="")
    with pytest.raises(RunFolderError) as refused:
        _dynamics_section(state, runs)
    assert "\n" not in str(refused.value) and str(policy) in str(refused.value)
    assert not marker.exists()


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o027, 0o640)])
def test_policy_file_gets_the_usual_permissions(tmp_path: Path, umask: int, mode: int) -> None:
    """policy.pt is readable as the umask allows, like every other file of a run folder
    (``mkstemp`` alone makes it 0600, unreadable by colleagues sharing the results)."""
    import os
    import stat

    model_path = tmp_path / "model.zip"
    old = os.umask(umask)
    try:
        train_agent(
            TASK, None, TINY_PPO, BudgetConfig(training_steps=256), 0, model_path=model_path
        )
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "policy.pt").stat().st_mode) == mode
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
