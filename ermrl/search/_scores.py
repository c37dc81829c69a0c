"""Reference returns for normalizing fitness across tasks: random-policy and target returns.

The multi-task fitness of ``evolve-generalization`` is the mean over tasks of

.. math:: \\frac{R - R_\\text{random}}{R_\\text{target} - R_\\text{random}}

so 0 is a uniformly random policy and 1 is the target. Both references come from a CSV table,
by default the packaged ``ermrl/data/scores.csv``:

- ``random_mean`` (R_random) is the mean **episodic** return of a uniformly random policy
  (``env.action_space.sample()``), measured by
  [`measure_random_returns`][ermrl.search.measure_random_returns] / ``ermrl scores``. The original
  ER-MRL code averaged per-step rewards instead, which made its random references about 1000x too
  small on 1000-step tasks.
- ``target`` (R_target, the default) is a published PPO return at 1M steps, cited per row in
  ``target_source`` (rl-baselines3-zoo ``benchmark.md``).
- ``provisional_target`` keeps the ER-MRL code's provisional targets, cited in
  ``provisional_target_source``; ``--target-column provisional_target`` selects it.
"""

from __future__ import annotations

import csv
import io
import math
import os
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ermrl._io import write_atomic
from ermrl.config import ConfigError

__all__ = [
    "PROVISIONAL_TARGETS",
    "REFERENCE_TARGETS",
    "SCORE_COLUMNS",
    "TARGET_COLUMNS",
    "MissingScoreError",
    "RandomScore",
    "ReferenceScore",
    "env_family",
    "format_scores",
    "load_scores",
    "measure_random_returns",
    "reference_returns",
    "scores_path",
    "update_scores",
    "write_scores",
]

TargetColumn = Literal["target", "provisional_target"]
TARGET_COLUMNS: tuple[str, ...] = ("target", "provisional_target")

_ZOO = (
    "rl-baselines3-zoo benchmark.md: ppo {env}-v3, 1M steps, deterministic eval, one run "
    "({value} +- {std})"
)
#: Default R_target per env family: PPO at 1M steps in rl-baselines3-zoo's ``benchmark.md``
#: (MuJoCo v3, tuned hyperparameters with VecNormalize, deterministic evaluation, one run).
REFERENCE_TARGETS: dict[str, tuple[float, str]] = {
    "Ant": (1327.158, _ZOO.format(env="Ant", value=1327.158, std=451.577)),
    "HalfCheetah": (5819.099, _ZOO.format(env="HalfCheetah", value=5819.099, std=663.530)),
    "Hopper": (2410.435, _ZOO.format(env="Hopper", value=2410.435, std=10.026)),
    "Swimmer": (281.561, _ZOO.format(env="Swimmer", value=281.561, std=9.671)),
    "Walker2d": (3478.798, _ZOO.format(env="Walker2d", value=3478.798, std=821.708)),
}
_ERMRL = "ER-MRL code (corentinlger/ER-MRL, er_mrl/experiments.py env_target_reward), provisional"
#: The original ER-MRL code's provisional targets (marked there "update values with PPO
#: benchmark code").
PROVISIONAL_TARGETS: dict[str, tuple[float, str]] = {
    "Ant": (125.0, _ERMRL),
    "HalfCheetah": (750.0, _ERMRL),
    "Hopper": (1250.0, _ERMRL),
    "Swimmer": (60.0, _ERMRL),
    "Walker2d": (800.0, _ERMRL),
    "Humanoid": (375.0, _ERMRL),
}


class MissingScoreError(ConfigError):
    """The reference table has no usable random or target return for an env."""


@dataclass(frozen=True)
class RandomScore:
    """Episodic returns of a uniformly random policy on one env.

    Attributes:
        env_id: Gymnasium id.
        returns: Return of each episode, shape ``(episodes,)``.
        lengths: Length of each episode, shape ``(episodes,)``.
        seed: Seed of the first reset and of the action space.
        gymnasium: Gymnasium version used.
        wall_seconds: Time the measurement took.
    """

    env_id: str
    returns: tuple[float, ...]
    lengths: tuple[int, ...]
    seed: int
    gymnasium: str
    wall_seconds: float = 0.0

    @property
    def mean(self) -> float:
        return float(np.mean(self.returns))

    @property
    def std(self) -> float:
        return float(np.std(self.returns))

    @property
    def mean_length(self) -> float:
        return float(np.mean(self.lengths))


@dataclass(frozen=True)
class ReferenceScore:
    """One row of the reference table (empty cells are ``None``).

    Attributes:
        env_id: Gymnasium id.
        random_mean: Mean episodic return of the random policy (R_random).
        random_std: Its standard deviation over episodes.
        random_episodes: Episodes measured.
        random_mean_length: Mean episode length of the random policy.
        random_seed: Seed of the measurement.
        gymnasium: Gymnasium version of the measurement.
        target: Default target return (R_target).
        target_source: Where ``target`` comes from.
        provisional_target: The ER-MRL code's provisional target.
        provisional_target_source: Where ``provisional_target`` comes from.
    """

    env_id: str
    random_mean: float | None = None
    random_std: float | None = None
    random_episodes: int | None = None
    random_mean_length: float | None = None
    random_seed: int | None = None
    gymnasium: str | None = None
    target: float | None = None
    target_source: str = ""
    provisional_target: float | None = None
    provisional_target_source: str = ""


SCORE_COLUMNS: tuple[str, ...] = tuple(f.name for f in fields(ReferenceScore))
_FLOATS = {"random_mean", "random_std", "random_mean_length", "target", "provisional_target"}
_INTS = {"random_episodes", "random_seed"}


def env_family(env_id: str) -> str:
    """The body of an env id without namespace and version: ``"HalfCheetah-v5"`` -> ``"HalfCheetah"``."""
    name = env_id.split(":", 1)[-1].split("/", 1)[-1]
    base, sep, version = name.rpartition("-v")
    return base if sep and version.isdigit() else name


def scores_path(path: str | os.PathLike[str] | None = None) -> Path:
    """The reference table: ``path``, or the packaged ``ermrl/data/scores.csv``."""
    if path is not None:
        return Path(path)
    return Path(str(resources.files("ermrl").joinpath("data/scores.csv")))


def _parse_row(row: Mapping[str, str | None], where: str) -> ReferenceScore:
    values: dict[str, Any] = {}
    for name in SCORE_COLUMNS:
        raw = (row.get(name) or "").strip()
        if name in _FLOATS or name in _INTS:
            if raw == "":
                values[name] = None
                continue
            try:
                value = int(raw) if name in _INTS else float(raw)
            except ValueError as err:
                raise ConfigError(f"{where}: column {name!r} has a bad value {raw!r}") from err
            if not math.isfinite(value) or (name in _INTS and value < 0):
                raise ConfigError(
                    f"{where}: column {name!r} has a bad value {raw!r} (a finite number, and a "
                    "count or seed >= 0, is expected)"
                )
            values[name] = value
        else:
            values[name] = raw
    if not values["env_id"]:
        raise ConfigError(f"{where}: a row has no env_id")
    return ReferenceScore(**values)


def load_scores(path: str | os.PathLike[str] | None = None) -> dict[str, ReferenceScore]:
    """Read a reference table.

    Args:
        path: A CSV file with the columns of `SCORE_COLUMNS`; ``None`` reads the
            packaged table.

    Returns:
        Rows keyed by env id (empty when the file does not exist).

    Raises:
        ConfigError: the file cannot be read or has a malformed row.
    """
    file = scores_path(path)
    if not file.exists():
        if path is not None:
            raise ConfigError(f"score table {file} does not exist")
        return {}
    try:
        text = file.read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"cannot read score table {file}: {err.strerror}") from err
    except UnicodeDecodeError as err:
        raise ConfigError(
            f"score table {file} is not UTF-8 text (byte {err.start}: {err.reason})"
        ) from err
    reader = csv.DictReader(io.StringIO(text))
    table: dict[str, ReferenceScore] = {}
    try:
        if reader.fieldnames is None or "env_id" not in reader.fieldnames:
            raise ConfigError(f"score table {file} has no env_id column")
        for row in reader:
            score = _parse_row(row, f"{file}:{reader.line_num}")
            table[score.env_id] = score
    except csv.Error as err:  # a field over csv.field_size_limit(), ...
        raise ConfigError(
            f"score table {file} is not a CSV table (line {reader.line_num}: {err})"
        ) from err
    return table


def reference_returns(
    env_id: str,
    table: Mapping[str, ReferenceScore],
    *,
    target_column: str = "target",
    path: str | os.PathLike[str] | None = None,
) -> tuple[float, float]:
    """``(R_random, R_target)`` of an env, for ``(R - R_random) / (R_target - R_random)``.

    Args:
        env_id: Gymnasium id.
        table: From [`load_scores`][ermrl.search.load_scores].
        target_column: ``target`` or ``provisional_target``.
        path: The file ``table`` was read from, for error messages (``None``: the packaged one).

    Raises:
        MissingScoreError: no random score, no target, or a target equal to the random score.
    """
    if target_column not in TARGET_COLUMNS:
        raise ConfigError(f"target column must be one of {TARGET_COLUMNS}, got {target_column!r}")
    where = f"score table {scores_path(path)}"
    row = table.get(env_id)
    if row is None or row.random_mean is None:
        then = ""
        if path is None:  # the packaged table is never written: measure into a table of one's own
            out, then = " --out scores.csv", " and pass --scores scores.csv"
        else:
            out = f" --out {path}"
        raise MissingScoreError(
            f"no random-policy score for {env_id!r} in {where}; run "
            f"`ermrl scores --env-ids {env_id}{out}` to measure it{then}"
        )
    target = getattr(row, target_column)
    if target is None:
        raise MissingScoreError(
            f"no {target_column} return for {env_id!r} in {where}; fill in its {target_column} "
            f"and {target_column}_source columns"
        )
    if not (math.isfinite(target) and math.isfinite(row.random_mean)):
        raise MissingScoreError(f"non-finite reference returns for {env_id!r} in {where}")
    if target == row.random_mean:
        raise MissingScoreError(
            f"the {target_column} return of {env_id!r} equals its random return "
            f"({target:g}) in {where}: the normalized return is undefined"
        )
    return float(row.random_mean), float(target)


def measure_random_returns(env_id: str, episodes: int = 100, seed: int = 0) -> RandomScore:
    """Run a uniformly random policy and record its episodic returns.

    The env is reset with ``seed`` once (later resets continue its generator) and the action
    space is seeded with ``seed``, so the measurement is reproducible. Episodes run until
    termination or the env's time limit.

    Args:
        env_id: Gymnasium id (no observation mask: returns do not depend on it).
        episodes: Number of episodes.
        seed: Seed of the env and of the action sampling.

    Returns:
        The returns and lengths of every episode.
    """
    import gymnasium

    if episodes < 1:
        raise ConfigError(f"episodes must be >= 1, got {episodes}")
    start = time.perf_counter()
    env = gymnasium.make(env_id)
    env.action_space.seed(seed)
    returns: list[float] = []
    lengths: list[int] = []
    try:
        for episode in range(episodes):
            env.reset(seed=seed if episode == 0 else None)
            total, length, done = 0.0, 0, False
            while not done:
                _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
                total += float(reward)
                length += 1
                done = terminated or truncated
            returns.append(total)
            lengths.append(length)
    finally:
        env.close()
    return RandomScore(
        env_id=env_id,
        returns=tuple(returns),
        lengths=tuple(lengths),
        seed=seed,
        gymnasium=gymnasium.__version__,
        wall_seconds=time.perf_counter() - start,
    )


def _fmt(value: Any) -> str:
    if value is None:
        return ""
    return repr(value) if isinstance(value, float) else str(value)


def write_scores(table: Mapping[str, ReferenceScore], path: str | os.PathLike[str]) -> None:
    """Write a reference table as CSV, rows sorted by env id (atomically: a full disk leaves
    the old table whole and no temporary file).

    Raises:
        OSError: the file cannot be written.
    """
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(SCORE_COLUMNS)
    for env_id in sorted(table):
        row = table[env_id]
        writer.writerow([_fmt(getattr(row, name)) for name in SCORE_COLUMNS])
    write_atomic(Path(path), buffer.getvalue())


def update_scores(
    measured: Iterable[RandomScore],
    path: str | os.PathLike[str] | None = None,
    *,
    start_from: str | os.PathLike[str] | None = None,
) -> dict[str, ReferenceScore]:
    """Write measured random scores into a table, keeping its other rows and its targets.

    A row that is new to the table takes its targets from `REFERENCE_TARGETS` and
    `PROVISIONAL_TARGETS` (by env family) when they are known, and stays empty otherwise.

    Args:
        measured: New random-policy measurements.
        path: The table to update (``None``: the packaged one).
        start_from: When ``path`` does not exist yet, the table whose rows it starts with
            (e.g. the packaged one); ``None``: an empty table.

    Returns:
        The updated table.
    """
    file = scores_path(path)
    if file.exists():
        table = load_scores(file)
    else:
        table = load_scores(start_from) if start_from is not None else {}
    for score in measured:
        old = table.get(score.env_id)
        if old is None:
            family = env_family(score.env_id)
            target, source = REFERENCE_TARGETS.get(family, (None, ""))
            provisional, provisional_source = PROVISIONAL_TARGETS.get(family, (None, ""))
            old = ReferenceScore(
                env_id=score.env_id,
                target=target,
                target_source=source,
                provisional_target=provisional,
                provisional_target_source=provisional_source,
            )
        table[score.env_id] = ReferenceScore(
            env_id=score.env_id,
            random_mean=round(score.mean, 3),
            random_std=round(score.std, 3),
            random_episodes=len(score.returns),
            random_mean_length=round(score.mean_length, 1),
            random_seed=score.seed,
            gymnasium=score.gymnasium,
            target=old.target,
            target_source=old.target_source,
            provisional_target=old.provisional_target,
            provisional_target_source=old.provisional_target_source,
        )
    write_scores(table, file)
    return table


def format_scores(rows: Sequence[ReferenceScore]) -> str:
    """A plain-text table of reference rows (for the terminal)."""
    lines = [
        f"{'env_id':<16} {'random_mean':>12} {'random_std':>10} {'episodes':>8} {'target':>10}"
    ]
    for r in rows:
        lines.append(
            f"{r.env_id:<16} {_fmt(r.random_mean):>12} {_fmt(r.random_std):>10} "
            f"{_fmt(r.random_episodes):>8} {_fmt(r.target):>10}"
        )
    return "\n".join(lines)
