"""A killed sb3 training run resumes from its checkpoint (ermrl.agents._checkpoint).

Real SB3 training on real environments; the kill is a KeyboardInterrupt raised right after a
save, so the state at the kill is known exactly.
"""

from __future__ import annotations

import copy
import io
import json
from pathlib import Path
from typing import Any

import pytest
import torch
from stable_baselines3.common.callbacks import BaseCallback

from ermrl._progress import Progress
from ermrl.agents import RunCheckpoint, resolve_ppo_config, train_agent, with_overrides
from ermrl.config import BudgetConfig, EncoderConfig, ReservoirParams, TaskConfig

TASK = TaskConfig("Pendulum-v1", "positions")
ENCODER = EncoderConfig(reservoirs=(ReservoirParams(units=12),))
BUDGET = BudgetConfig(training_steps=2048, fitness="last", n_last_episodes=1)


def settings(learner: str = "ppo") -> Any:
    overrides = {"n_steps": 64, "batch_size": 64, "n_epochs": 2, "normalize": True}
    return with_overrides(resolve_ppo_config("Pendulum-v1", learner=learner), overrides)


class KilledAfterSave(RunCheckpoint):
    """Saves as a checkpoint does, then records the model's state and kills the run (once
    ``kill_at`` steps are saved)."""

    kill_at = 1024
    at_kill: dict[str, Any] = {}

    def save(self, model: Any, normalized: Any, records: dict[str, Any]) -> None:
        super().save(model, normalized, records)
        if model.num_timesteps >= self.kill_at:
            KilledAfterSave.at_kill = {
                "steps": int(model.num_timesteps),
                "policy": {k: v.clone() for k, v in model.policy.state_dict().items()},
                "optimizer": copy.deepcopy(model.policy.optimizer.state_dict()),
                "obs_count": float(normalized.obs_rms.count),
                "episodes": list(records["episode_returns"]),
            }
            raise KeyboardInterrupt


class AtStart(BaseCallback):
    """Records what the resumed learner holds when its training starts."""

    seen: dict[str, Any] = {}

    def _on_training_start(self) -> None:
        AtStart.seen = {
            "steps": int(self.model.num_timesteps),
            "total": int(self.model._total_timesteps),
            "policy": {k: v.clone() for k, v in self.model.policy.state_dict().items()},
            "optimizer": copy.deepcopy(self.model.policy.optimizer.state_dict()),
            "obs_count": float(self.model.get_vec_normalize_env().obs_rms.count),
        }

    def _on_step(self) -> bool:
        return True


@pytest.mark.parametrize("learner", ["ppo", "lstm-ppo"])
def test_a_killed_run_resumes_from_its_checkpoint(learner: str, tmp_path: Path) -> None:
    """The resumed learner starts from the saved weights, Adam state, normalization and steps;
    it trains only the rest of the budget, its schedules end at the budget, its episodes go on
    from the saved ones, it says so, and the checkpoint is removed at the end."""
    ppo = settings(learner)
    key = f"{learner} Pendulum seed 3"
    killed = KilledAfterSave(tmp_path / "checkpoints", every=256, key=key)
    with pytest.raises(KeyboardInterrupt):
        train_agent(TASK, ENCODER, ppo, BUDGET, 3, checkpoint=killed)
    at_kill = KilledAfterSave.at_kill
    assert at_kill["steps"] == 1024 and at_kill["episodes"]
    assert [p.name for p in (tmp_path / "checkpoints").glob("model-*.zip")] == ["model-1024.zip"]
    stream = io.StringIO()
    progress = Progress("again", BUDGET.training_steps, mode="lines", stream=stream)
    checkpoint = RunCheckpoint(tmp_path / "checkpoints", every=256, key=key)
    result = train_agent(
        TASK, ENCODER, ppo, BUDGET, 3, checkpoint=checkpoint, callbacks=[AtStart()],
        progress=progress,
    )  # fmt: skip
    seen = AtStart.seen
    assert seen["steps"] == 1024 and seen["total"] == BUDGET.training_steps
    for name, value in at_kill["policy"].items():
        assert torch.equal(seen["policy"][name], value), name
    assert seen["optimizer"]["state"].keys() == at_kill["optimizer"]["state"].keys()
    for k, state in at_kill["optimizer"]["state"].items():
        assert torch.equal(seen["optimizer"]["state"][k]["exp_avg_sq"], state["exp_avg_sq"])
    # The normalization goes on from the saved statistics: SB3's first reset of the resumed
    # envs adds their n_envs observations to them (a fresh one would count 1e-4 + n_envs).
    assert seen["obs_count"] == at_kill["obs_count"] + ppo.n_envs
    assert f"[again] resumed from {tmp_path / 'checkpoints'} at 1,024 steps" in stream.getvalue()
    assert result.env_steps == BUDGET.training_steps
    assert result.episode_returns[: len(at_kill["episodes"])] == at_kill["episodes"]
    assert len(result.episode_returns) > len(at_kill["episodes"])
    assert all(t > 1024 for t in result.episode_steps[len(at_kill["episodes"]) :])
    assert not (tmp_path / "checkpoints").exists()


def test_a_checkpoint_of_other_settings_is_not_resumed(tmp_path: Path) -> None:
    """Another key (the run's settings): the run starts from step 0 and says nothing of it."""
    killed = KilledAfterSave(tmp_path / "c", every=256, key="a")
    with pytest.raises(KeyboardInterrupt):
        train_agent(TASK, ENCODER, settings(), BUDGET, 3, checkpoint=killed)
    assert RunCheckpoint(tmp_path / "c", every=256, key="a").load() is not None
    other = RunCheckpoint(tmp_path / "c", every=256, key="b")
    assert other.load() is None
    stream = io.StringIO()
    progress = Progress("other", BUDGET.training_steps, mode="lines", stream=stream)
    train_agent(TASK, ENCODER, settings(), BUDGET, 3, checkpoint=other, callbacks=[AtStart()],
                progress=progress)  # fmt: skip
    assert AtStart.seen["steps"] == 0 and "resumed" not in stream.getvalue()


def test_a_checkpoint_saved_by_other_code_is_not_resumed_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The same run (same key) saved by other code: one line, and the run starts from step 0."""
    from ermrl._code import code_identity

    killed = KilledAfterSave(tmp_path / "c", every=256, key="a")
    with pytest.raises(KeyboardInterrupt):
        train_agent(TASK, ENCODER, settings(), BUDGET, 3, checkpoint=killed)
    state_file = next((tmp_path / "c").glob("*.json"))
    state = json.loads(state_file.read_text())
    assert state["code"] == code_identity()
    state["code"] = {**state["code"], "source": "0" * 64, "commit": "abcdef1234"}
    state_file.write_text(json.dumps(state))
    assert RunCheckpoint(tmp_path / "c", every=256, key="a").load() is None
    err = capsys.readouterr().err
    assert f"not resumed: {tmp_path / 'c'} was saved by other code (ermrl" in err
    assert "at abcdef1234" in err and "training from the start" in err


def test_an_off_policy_learner_is_not_checkpointed(tmp_path: Path) -> None:
    """SAC (its replay buffer is not saved) trains without writing a checkpoint."""
    sac = with_overrides(
        resolve_ppo_config("Pendulum-v1", learner="sac"),
        {"learning_starts": 100, "buffer_size": 1000, "batch_size": 32},
    )
    budget = BudgetConfig(training_steps=600, fitness="last", n_last_episodes=1)
    checkpoint = RunCheckpoint(tmp_path / "c", every=100, key="sac")
    result = train_agent(TASK, None, sac, budget, 3, checkpoint=checkpoint)
    assert result.env_steps == 600 and not (tmp_path / "c").exists()


# -- checkpoints that cannot be read back ---------------------------------------------------------


class Planted:
    """A class a pickle names: torch's ``weights_only`` loader refuses to build it."""


def _sb3_model(net_arch: list[int]) -> Any:
    from stable_baselines3 import PPO

    return PPO("MlpPolicy", "Pendulum-v1", n_steps=64, batch_size=64, seed=0,
               policy_kwargs={"net_arch": net_arch})  # fmt: skip


def _state(**fields: Any) -> dict[str, Any]:
    from ermrl._code import code_identity

    state = {
        "version": 1, "key": "k", "code": code_identity(), "num_timesteps": 64,
        "model": "model-64.zip",
        "normalize": None, "episode_returns": [-1.0], "episode_steps": [64],
        "checkpoint_returns": [], "wall_seconds": 1.0,
    }  # fmt: skip
    return {**state, **fields}


def _damaged(folder: Path, case: str) -> None:
    """A checkpoint folder of run ``k`` damaged as ``case`` says."""
    import json
    import pickle
    import zipfile

    folder.mkdir(parents=True)
    state = _state()
    zip_path = folder / "model-64.zip"
    _sb3_model([8]).save(zip_path)
    if case == "truncated":
        data = zip_path.read_bytes()
        zip_path.write_bytes(data[: len(data) // 2])
    elif case == "garbage":
        zip_path.write_bytes(b"\x00garbage" * 100)
    elif case in ("pickle", "torch-pickle"):
        payload = (pickle.dumps(Planted()) if case == "pickle"
                   else _torch_bytes({"weight": Planted()}))  # fmt: skip
        with zipfile.ZipFile(zip_path, "w") as archive:
            archive.writestr("policy.pth", payload)
    elif case == "state-garbage":
        (folder / "state.json").write_bytes(b"\xff{not json")
        return
    elif case == "state-types":
        state = _state(num_timesteps="64", episode_returns="many")
    elif case == "state-path":
        state = _state(model="../../elsewhere.zip")
    (folder / "state.json").write_text(json.dumps(state))


def _torch_bytes(obj: Any) -> bytes:
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return buffer.getvalue()


CASES = ["truncated", "garbage", "pickle", "torch-pickle", "state-garbage", "state-types",
         "state-path"]  # fmt: skip


@pytest.mark.parametrize("case", CASES)
def test_an_unreadable_checkpoint_is_set_aside_in_one_line(
    tmp_path: Path, case: str, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "checkpoints"
    _damaged(folder, case)
    assert RunCheckpoint(folder, every=64, key="k").load() is None
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert f"checkpoint {folder} is unreadable" in err and "trains from the start" in err
    (aside,) = tmp_path.glob("checkpoints.unreadable-*")
    assert (aside / "state.json").exists() and not folder.exists()
    assert RunCheckpoint(folder, every=64, key="k").load() is None  # nothing left to set aside
    assert capsys.readouterr().err == ""


def test_a_rerun_with_an_unreadable_checkpoint_trains_from_the_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A truncated model zip: the run trains from step 0 (it raised on every rerun)."""
    folder = tmp_path / "checkpoints"
    _damaged(folder, "truncated")
    budget = BudgetConfig(training_steps=256, fitness="eval", n_eval_episodes=1)
    checkpoint = RunCheckpoint(folder, every=64, key="k")
    result = train_agent(TASK, None, settings(), budget, 3, checkpoint=checkpoint,
                         callbacks=[AtStart()])  # fmt: skip
    assert AtStart.seen["steps"] == 0 and result.env_steps == 256
    assert "is unreadable" in capsys.readouterr().err


def test_weights_of_the_wrong_shapes_are_set_aside_and_the_model_left_as_it_was(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    folder = tmp_path / "checkpoints"
    folder.mkdir()
    _sb3_model([8]).save(folder / "model-64.zip")
    (folder / "state.json").write_text(json.dumps(_state()))
    checkpoint = RunCheckpoint(folder, every=64, key="k")
    assert checkpoint.load() is not None  # readable: only the model can tell
    model = _sb3_model([16])
    before = copy.deepcopy(model.get_parameters())
    assert checkpoint.restore(model, None) is None
    for name, state in before["policy"].items():
        assert torch.equal(model.get_parameters()["policy"][name], state), name
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "model-64.zip does not fit this model" in err
    assert not folder.exists() and list(tmp_path.glob("checkpoints.unreadable-*"))
    # A checkpoint of this model restores.
    good = tmp_path / "good"
    good.mkdir()
    saved_model = _sb3_model([16])
    saved_model.save(good / "model-64.zip")
    (good / "state.json").write_text(json.dumps(_state()))
    assert RunCheckpoint(good, every=64, key="k").restore(model, None) is not None
    for name, state in saved_model.get_parameters()["policy"].items():
        assert torch.equal(model.get_parameters()["policy"][name], state), name


def test_a_run_whose_checkpoint_does_not_fit_its_model_trains_from_the_start(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """train_agent restores through RunCheckpoint.restore: weights of another network (a readable
    checkpoint of the same key) are set aside in one line and the run trains from step 0."""
    import json

    folder = tmp_path / "checkpoints"
    folder.mkdir()
    _sb3_model([8]).save(folder / "model-64.zip")
    (folder / "state.json").write_text(json.dumps(_state(key="a")))
    checkpoint = RunCheckpoint(folder, every=4096, key="a")
    assert checkpoint.load() is not None
    result = train_agent(TASK, ENCODER, settings(), BUDGET, 3, checkpoint=checkpoint,
                         callbacks=[AtStart()])  # fmt: skip
    assert AtStart.seen["steps"] == 0 and result.env_steps >= BUDGET.training_steps
    err = capsys.readouterr().err
    assert "model-64.zip does not fit this model" in err
    assert list(tmp_path.glob("checkpoints.unreadable-*"))
