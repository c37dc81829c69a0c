"""Checkpoints of one training run on the sb3 backend: a killed run resumes from its last save.

A run of an on-policy Stable-Baselines3 learner (PPO and the learners built on SB3's
``OnPolicyAlgorithm``: ``lstm-ppo``, ``framestack-ppo``, ``rtu-ppo``) saves, every ``every`` env
steps at the start of a rollout (after an update), its model with SB3's ``model.save`` (the
policy's weights and the optimizer's state), the running normalization statistics (JSON, as
[`normalize_stats`][ermrl.agents.normalize_stats] writes them) and its episode records. A rerun of
the same run (the same ``key``) loads them with SB3's ``set_parameters`` and trains the remaining
steps with ``reset_num_timesteps=False``, so the learning-rate and clip schedules go on where they
were. The environments restart from fresh episodes (seeded anew), and the learner's other state (a
recurrent learner's hidden state, its random streams) starts afresh: a resumed run is not bit for
bit the uninterrupted one. Off-policy learners (SAC, whose replay buffer is not saved) and learners
that are no SB3 algorithm are not checkpointed: they restart from step 0.

A checkpoint is data someone else may have written: its model is read with ``weights_only``
tensors and no pickled class data, and a checkpoint that cannot be read back whole (a truncated
or foreign zip, a pickle, a state file of the wrong types, weights of the wrong shapes) is set
aside as ``<folder>.unreadable-<UTC time>`` with one line on stderr, and the run trains from the
start.
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import shutil
import sys
import time
import warnings
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ermrl._code import code_identity, describe_code, same_code
from ermrl._io import write_atomic

__all__ = ["RunCheckpoint", "can_checkpoint"]

CHECKPOINT_VERSION = 1
STATE_FILE = "state.json"
MAX_STATE_BYTES = 256 << 20  # a state file larger than this is not ermrl's (episode lists)
_MODEL_NAME = re.compile(r"model-\d+\.zip")


def can_checkpoint(model: Any) -> bool:
    """Whether ``model``'s training can be saved and resumed (an SB3 on-policy algorithm)."""
    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

    return isinstance(model, OnPolicyAlgorithm)


@dataclass(frozen=True)
class RunCheckpoint:
    """Where one run saves its training state, how often, and what run it is.

    Attributes:
        folder: The run's checkpoint folder (``state.json`` and ``model-<step>.zip``).
        every: Env steps between saves.
        key: The run's settings as text; a checkpoint saved under another key is not resumed.
    """

    folder: Path
    every: int
    key: str

    def load(self) -> dict[str, Any] | None:
        """The saved state (with ``model``, the path of its model file), or ``None``: no
        checkpoint, one of another run (the run starts over and its saves replace it), or an
        unreadable one, which is set aside first
        ([`set_aside`][ermrl.agents.RunCheckpoint.set_aside]).

        Everything is checked that can be without the model: the state file's fields and
        types, and that the model file is a zip whose tensors load with ``weights_only``."""
        path = self.folder / STATE_FILE
        try:
            with path.open("rb") as handle:
                raw = handle.read(MAX_STATE_BYTES + 1)
        except FileNotFoundError:
            return None
        except OSError as err:
            self.set_aside(f"{STATE_FILE}: {err.strerror or err}")
            return None
        if len(raw) > MAX_STATE_BYTES:
            self.set_aside(f"{STATE_FILE} is over {MAX_STATE_BYTES >> 20} MiB")
            return None
        try:
            state = json.loads(raw.decode("utf-8"))
        except (ValueError, RecursionError) as err:  # JSONDecodeError, UnicodeDecodeError
            self.set_aside(f"{STATE_FILE} is not JSON ({str(err).splitlines()[0]})")
            return None
        if isinstance(state, dict) and (
            state.get("version") != CHECKPOINT_VERSION or state.get("key") != self.key
        ):
            return None  # another version's or another run's: not resumed, replaced
        problem = _state_problem(state)
        if problem is None:
            problem = _model_problem(self.folder / state["model"])
        if problem is not None:
            self.set_aside(problem)
            return None
        if not same_code(state.get("code")):
            # The same run saved by other code: its state may not mean what this code reads.
            print(
                f"not resumed: {self.folder} was saved by other code "
                f"({describe_code(state.get('code'))}; this is {describe_code(code_identity())}): "
                "training from the start",
                file=sys.stderr,
                flush=True,
            )
            return None
        return {**state, "model": self.folder / state["model"]}

    def restore(self, model: Any, normalized: Any) -> dict[str, Any] | None:
        """Load the saved state into ``model`` (weights, optimizer) and ``normalized`` (its
        running statistics, when it is a ``VecNormalize``): the state as
        [`load`][ermrl.agents.RunCheckpoint.load] gives it, or ``None`` with both left as they were
        (no checkpoint, or one set aside, e.g. weights of the wrong shapes for this model)."""
        saved = self.load()
        if saved is None:
            return None
        before = copy.deepcopy(model.get_parameters())
        stats = [copy.deepcopy(getattr(normalized, a, None)) for a in ("obs_rms", "ret_rms")]
        try:
            model.set_parameters(str(saved["model"]), exact_match=True)
            if saved["normalize"] is not None:
                restore_normalization(normalized, saved["normalize"])
        except Exception as err:  # noqa: BLE001 (whatever a foreign file makes torch raise)
            model.set_parameters(before, exact_match=True)
            for attr, value in zip(("obs_rms", "ret_rms"), stats):
                if value is not None:
                    setattr(normalized, attr, value)
            detail = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            self.set_aside(f"{saved['model'].name} does not fit this model ({detail})")
            return None
        return saved

    def set_aside(self, reason: str) -> None:
        """Move the checkpoint folder aside (``<folder>.unreadable-<UTC time>``) and say so in
        one line on stderr (the run then trains from the start)."""
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        aside = self.folder.with_name(f"{self.folder.name}.unreadable-{stamp}")
        n = 1
        while aside.exists():
            n += 1
            aside = self.folder.with_name(f"{self.folder.name}.unreadable-{stamp}-{n}")
        try:
            os.replace(self.folder, aside)
            where = f"set aside as {aside}"
        except OSError:
            shutil.rmtree(self.folder, ignore_errors=True)
            where = "removed"
        print(
            f"checkpoint {self.folder} is unreadable ({reason}); {where}, and the run trains "
            "from the start",
            file=sys.stderr,
            flush=True,
        )

    def save(self, model: Any, normalized: Any, records: dict[str, Any]) -> None:
        """Save ``model`` (at its ``num_timesteps``), the statistics of ``normalized`` (when it
        is a ``VecNormalize``) and ``records`` (the run's episodes so far, JSON-ready). The
        state file is written last and atomically, so a kill leaves the previous save whole."""
        from stable_baselines3.common.vec_env import VecNormalize

        from ermrl.agents._normalize import normalize_stats

        step = int(model.num_timesteps)
        self.folder.mkdir(parents=True, exist_ok=True)
        name = f"model-{step}.zip"
        partial = self.folder / f".{name}.partial"
        with partial.open("wb") as handle:
            model.save(handle)
        os.replace(partial, self.folder / name)
        state = {
            "version": CHECKPOINT_VERSION,
            "key": self.key,
            "code": code_identity(),
            "num_timesteps": step,
            "model": name,
            "normalize": normalize_stats(normalized)
            if isinstance(normalized, VecNormalize)
            else None,
            **records,
        }
        write_atomic(self.folder / STATE_FILE, json.dumps(state) + "\n")
        for old in self.folder.glob("model-*.zip"):
            if old.name != name:
                old.unlink(missing_ok=True)

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _numbers(value: Any, integers: bool = False) -> bool:
    kind = int if integers else (int, float)
    return isinstance(value, list) and all(_is_number(v) and isinstance(v, kind) for v in value)


def _rms_problem(stats: Any, where: str) -> str | None:
    if not isinstance(stats, Mapping):
        return f"{where} is not a mapping"
    for key in ("mean", "var"):
        value = stats.get(key)
        if not (_is_number(value) or _numbers(value)):
            return f"{where}.{key} is not a number or a list of numbers"
    if not _is_number(stats.get("count")):
        return f"{where}.count is not a number"
    return None


def _state_problem(state: Any) -> str | None:
    """What makes a state file (of this version and run) unusable, or ``None``."""
    if not isinstance(state, dict):
        return f"{STATE_FILE} is not a JSON object"
    model = state.get("model")
    if not isinstance(model, str) or not _MODEL_NAME.fullmatch(model):
        return f"{STATE_FILE}: model {model!r} is not a model-<step>.zip file name"
    steps = state.get("num_timesteps")
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 0:
        return f"{STATE_FILE}: num_timesteps {steps!r} is not a step count"
    checks = {
        "episode_returns": _numbers(state.get("episode_returns")),
        "episode_steps": _numbers(state.get("episode_steps"), integers=True),
        "checkpoint_returns": isinstance(state.get("checkpoint_returns"), list)
        and all(
            isinstance(p, list) and len(p) == 2 and _numbers(p) for p in state["checkpoint_returns"]
        ),  # fmt: skip
        "wall_seconds": _is_number(state.get("wall_seconds")),
    }
    bad = [key for key, ok in checks.items() if not ok]
    if bad:
        return f"{STATE_FILE}: {bad[0]} is missing or of the wrong type"
    normalize = state.get("normalize")
    if normalize is not None:
        if not isinstance(normalize, Mapping):
            return f"{STATE_FILE}: normalize is not a mapping"
        if normalize.get("obs_rms") is not None:
            problem = _rms_problem(normalize["obs_rms"], "normalize.obs_rms")
            if problem is not None:
                return f"{STATE_FILE}: {problem}"
        problem = _rms_problem(normalize.get("ret_rms"), "normalize.ret_rms")
        if problem is not None:
            return f"{STATE_FILE}: {problem}"
    return None


def _model_problem(path: Path) -> str | None:
    """What keeps the model file from loading (a truncated or foreign zip, a pickle where
    tensors belong), or ``None``. Tensors load with ``weights_only``; class data (SB3's
    ``data`` entry, which may hold pickles) is not read, as ``set_parameters`` does not."""
    from stable_baselines3.common.save_util import load_from_zip_file

    if not path.is_file():
        return f"its model file {path.name} is missing"
    if not zipfile.is_zipfile(path):
        return f"{path.name} is not a whole zip file"
    try:
        with warnings.catch_warnings():  # torch's on a foreign pickle protocol: it refuses it
            warnings.simplefilter("ignore")
            _, params, _ = load_from_zip_file(path, device="cpu", load_data=False)
    except Exception as err:  # noqa: BLE001 (whatever a damaged file makes zipfile/torch raise)
        detail = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        return f"{path.name} cannot be read ({detail})"
    policy = params.get("policy") if isinstance(params, dict) else None
    if not isinstance(policy, Mapping) or not policy:
        return f"{path.name} holds no policy weights"
    return None


def restore_normalization(normalized: Any, stats: dict[str, Any]) -> None:
    """Set a training ``VecNormalize``'s running statistics to saved ones (it keeps updating)."""
    from ermrl.agents._normalize import set_running_stats

    if stats.get("obs_rms") is not None:
        set_running_stats(normalized.obs_rms, stats["obs_rms"])
    set_running_stats(normalized.ret_rms, stats["ret_rms"])


def saver_callback(checkpoint: RunCheckpoint, normalized: Any, records: Any) -> Any:
    """An SB3 callback that saves ``checkpoint`` at the start of a rollout once ``every`` steps
    have passed since the last save (``records()`` gives the episode records to save)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class CheckpointSaver(BaseCallback):
        last = -1

        def _on_training_start(self) -> None:
            self.last = int(self.model.num_timesteps)

        def _on_rollout_start(self) -> None:
            if self.model.num_timesteps - self.last >= checkpoint.every:
                checkpoint.save(self.model, normalized, records())
                self.last = int(self.model.num_timesteps)

        def _on_step(self) -> bool:
            return True

    return CheckpointSaver()
