"""Loading test-phase run folders, learning curves on a common grid, and summaries."""

from __future__ import annotations

import io
import json
import os
import stat
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

__all__ = [
    "KEPT_RECORD_DIR",
    "RUNS_DIR",
    "RunFolderError",
    "check_run_folder",
    "run_dir",
    "load_run_results",
    "load_curves",
    "curves_on_grid",
    "summarize",
    "load_run_config",
    "t_quantile",
]

RUNS_DIR = "agents"
#: A run folder's subfolder holding the published records of a run trained again only for the
#: model the report replays (a published run carries no model): they replace the new training's
#: records as it ends ([`keep_published_record`][ermrl.test_phase._results.keep_published_record]), so a result
#: once published never changes.
KEPT_RECORD_DIR = "published-record"
#: Beside a run's published records: what the model trained again for the report's replay
#: returned (written by [`keep_published_record`][ermrl.test_phase._results.keep_published_record]).
REPLAY_MODEL_FILE = "replay-model.json"
CURVE_COLUMNS = ["agent", "seed", "env_step", "episode_return"]
GRID_COLUMNS = ["agent", "env_step", "mean", "std", "sem", "ci95", "n_seeds"]
CONFIG_FILE = "config.yaml"
RESULT_FILE = "result.json"
EPISODES_FILE = "episodes.csv"
SETTINGS_FILE = "settings.json"
EPISODE_COLUMNS = ("env_step", "episode_return")
# config.yaml entries that are mappings when present (ermrl test writes them so).
CONFIG_MAPPINGS = ("task", "encoder", "ppo", "settings", "agents", "agent_observe", "agent_ppo")


class RunFolderError(ValueError):
    """A file of a test-phase folder that is not what ``ermrl test`` writes.

    Raised before anything is written from it; ``str(err)`` is one line naming the file and
    the problem.

    Attributes:
        path: The damaged file.
        problem: What is wrong with it.
    """

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


#: The most bytes read from one file of a run folder: a record of ``ermrl test`` is far smaller
#: (an ``episodes.csv`` of 10^7 one-step episodes is about 300 MB); a device (``/dev/zero``) or
#: a huge file is refused rather than read into memory.
MAX_RUN_FILE_BYTES = 512 << 20


def _read_text(path: Path) -> str:
    limit = MAX_RUN_FILE_BYTES
    try:
        with path.open("rb") as handle:
            if not stat.S_ISREG(os.fstat(handle.fileno()).st_mode):
                raise RunFolderError(path, "not a regular file (a device, a pipe, ...)")
            data = handle.read(limit + 1)
    except FileNotFoundError:
        raise RunFolderError(path, "missing (the run folder is incomplete)") from None
    except IsADirectoryError:
        raise RunFolderError(path, "a folder, not a file") from None
    except OSError as err:
        raise RunFolderError(path, f"cannot be read: {err.strerror or err}") from None
    if len(data) > limit:
        raise RunFolderError(path, f"over {limit >> 20} MiB: not a record ermrl test writes")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise RunFolderError(path, "not UTF-8 text") from None


def read_run_text(path: str | Path) -> str:
    """A run folder's text file, read as the records are: a regular file of at most
    `MAX_RUN_FILE_BYTES`, UTF-8.

    Raises:
        RunFolderError: missing, not a regular file, too large or not UTF-8.
    """
    return _read_text(Path(path))


def _read_json_object(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(_read_text(path))
    except json.JSONDecodeError as err:
        raise RunFolderError(path, f"not JSON ({err.msg} at line {err.lineno})") from None
    except RecursionError:
        raise RunFolderError(path, "not JSON (nested too deeply)") from None
    if not isinstance(data, dict):
        raise RunFolderError(path, f"not a JSON object ({_kind(data)})")
    return data


def _kind(value: Any) -> str:
    """``value``'s JSON/YAML type with its article: ``a list``, ``an integer``, ``null``."""
    if value is None:
        return "null"
    names = {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}
    names.update({list: "a list", dict: "a mapping"})
    return names.get(type(value), f"a {type(value).__name__}")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def read_run_result(path: str | Path) -> dict[str, Any]:
    """A run's ``result.json``, checked: an object with ``agent``, ``seed`` and ``final_return``.

    Raises:
        RunFolderError: the file is missing, not a JSON object, or lacks one of those keys or
            holds a value of the wrong type (``eval_return`` too, when present).
    """
    path = Path(path)
    record = _read_json_object(path)
    for key in ("agent", "seed", "final_return"):
        if key not in record:
            raise RunFolderError(path, f"no {key!r} key")
    if not isinstance(record["agent"], str) or not record["agent"]:
        raise RunFolderError(path, f"'agent' is {_kind(record['agent'])}, not a name")
    if not isinstance(record["seed"], int) or isinstance(record["seed"], bool):
        raise RunFolderError(path, f"'seed' is {_kind(record['seed'])}, not an integer")
    for key in ("final_return", "eval_return"):
        value = record.get(key)
        if value is not None and not _is_number(value):
            raise RunFolderError(path, f"{key!r} is {_kind(value)}, not a number")
    return record


def read_episodes(path: str | Path) -> pd.DataFrame:
    """A run's ``episodes.csv``, checked: numeric columns ``env_step`` and ``episode_return``.

    Raises:
        RunFolderError: the file is missing, empty, not CSV, lacks a column or holds a value
            that is not a number.
    """
    path = Path(path)
    text = _read_text(path)  # missing, unreadable, not text, a device, huge
    try:
        episodes = pd.read_csv(io.StringIO(text))
    except pd.errors.EmptyDataError:
        raise RunFolderError(path, "empty (no header line)") from None
    except (pd.errors.ParserError, ValueError) as err:
        raise RunFolderError(path, f"not CSV ({str(err).strip().splitlines()[0]})") from None
    missing = [c for c in EPISODE_COLUMNS if c not in episodes.columns]
    if missing:
        raise RunFolderError(
            path,
            f"no column {' and '.join(missing)} (columns: {', '.join(map(str, episodes.columns))})",
        )
    for column in EPISODE_COLUMNS:
        values = pd.to_numeric(episodes[column], errors="coerce")
        bad = values.isna() & episodes[column].notna()
        if bad.any():
            row = int(bad.to_numpy().argmax())
            raise RunFolderError(
                path,
                f"{column} {episodes[column].iloc[row]!r} on data line {row + 1} is not a number",
            )
        episodes[column] = values
    return episodes


def read_run_settings(path: str | Path) -> dict[str, Any]:
    """A run's ``settings.json``, checked: a JSON object whose ``ppo``, if any, is an object.

    Raises:
        RunFolderError: the file is not a JSON object, or its ``ppo`` is not one.
    """
    path = Path(path)
    settings = _read_json_object(path)
    ppo = settings.get("ppo")
    if ppo is not None and not isinstance(ppo, dict):
        raise RunFolderError(path, f"'ppo' is {_kind(ppo)}, not a mapping")
    return settings


def _finished_runs(out: str | Path) -> list[Path]:
    return sorted(Path(out).glob(f"{RUNS_DIR}/*/seed_*/{RESULT_FILE}"))


def check_run_folder(out: str | Path) -> None:
    """Read every file of a test-phase folder that the report and replays use, and check it.

    Checks ``config.yaml`` (when present: [`load_run_config`][ermrl.analysis.load_run_config]) and,
    for each finished run, ``result.json``, ``episodes.csv`` and ``settings.json`` (when present).
    Call it before writing anything derived from the folder, so that a damaged file stops the
    command cleanly.

    Raises:
        RunFolderError: a damaged file, named with its problem.
        ermrl.envs.UnknownEnvError: ``config.yaml`` names an env id that is not registered.
    """
    out = Path(out)
    if (out / CONFIG_FILE).exists():
        load_run_config(out)
    for path in _finished_runs(out):
        read_run_result(path)
        read_episodes(path.parent / EPISODES_FILE)
        if (path.parent / SETTINGS_FILE).exists():
            read_run_settings(path.parent / SETTINGS_FILE)


def run_dir(out: str | Path, agent: str, seed: int) -> Path:
    """Folder of one (agent, seed) run inside a test-phase output folder."""
    return Path(out) / RUNS_DIR / agent / f"seed_{seed}"


def load_run_results(out: str | Path) -> pd.DataFrame:
    """One row per finished run (those with a ``result.json``) under ``out``.

    Raises:
        RunFolderError: a ``result.json`` is damaged (see `read_run_result`).
    """
    return pd.DataFrame([read_run_result(path) for path in _finished_runs(out)])


def load_curves(out: str | Path) -> pd.DataFrame:
    """All finished runs' training episodes: columns ``agent, seed, env_step, episode_return``.

    Raises:
        RunFolderError: a ``result.json`` or ``episodes.csv`` is damaged or missing.
    """
    frames = []
    for path in _finished_runs(out):
        record = read_run_result(path)
        episodes = read_episodes(path.parent / EPISODES_FILE)
        episodes.insert(0, "seed", record["seed"])
        episodes.insert(0, "agent", record["agent"])
        frames.append(episodes)
    if not frames:
        return pd.DataFrame(columns=CURVE_COLUMNS)
    return pd.concat(frames, ignore_index=True)[CURVE_COLUMNS]


def curves_on_grid(
    curves: pd.DataFrame, n_points: int = 100, smooth_episodes: int = 10
) -> pd.DataFrame:
    """Learning curves of every agent on a common env-step grid, mean and std across seeds.

    Each run's episode returns are smoothed with a trailing mean over ``smooth_episodes``
    episodes, then read at each grid step as the value of the latest finished episode.

    Args:
        curves: Columns ``agent, seed, env_step, episode_return``.
        n_points: Grid size, from the first to the last episode end of all runs.
        smooth_episodes: Trailing window of the smoothing.

    Returns:
        Columns ``agent, env_step, mean, std, sem, ci95, n_seeds``: ``std`` is the sample
        standard deviation across seeds (``ddof=1``; 0 with one seed), ``sem`` the standard error
        of the mean and ``ci95`` the half-width of the Student-t 95% confidence interval of the
        mean (NaN with one seed). Grid points before a run's first episode do not count for
        that run.
    """
    if curves.empty:
        return pd.DataFrame(columns=GRID_COLUMNS)
    grid = np.unique(
        np.linspace(curves["env_step"].min(), curves["env_step"].max(), n_points).astype(np.int64)
    )
    rows = []
    for agent, group in curves.groupby("agent", sort=False):
        per_seed = []
        for _, run in group.groupby("seed"):
            run = run.sort_values("env_step")
            smooth = run["episode_return"].rolling(smooth_episodes, min_periods=1).mean().to_numpy()
            idx = np.searchsorted(run["env_step"].to_numpy(), grid, side="right") - 1
            values = np.where(idx >= 0, smooth[np.clip(idx, 0, None)], np.nan)
            per_seed.append(values)
        stack = np.vstack(per_seed)
        counts = np.sum(~np.isnan(stack), axis=0)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(np.where(counts > 0, stack, 0.0), axis=0)
            std = np.nanstd(np.where(counts > 0, stack, 0.0), axis=0, ddof=1)
        std = np.where(counts > 1, std, 0.0)
        sem = np.where(counts > 1, std / np.sqrt(np.maximum(counts, 1)), np.nan)
        ci95 = sem * t_quantile(counts - 1)
        for step, m, s, e, h, c in zip(grid, mean, std, sem, ci95, counts):
            if c > 0:
                rows.append(
                    {
                        "agent": agent,
                        "env_step": int(step),
                        "mean": m,
                        "std": s,
                        "sem": e,
                        "ci95": h,
                        "n_seeds": int(c),
                    }
                )
    return pd.DataFrame(rows, columns=GRID_COLUMNS)


def t_quantile(dof: np.ndarray | int, confidence: float = 0.95) -> np.ndarray:
    """Two-sided Student-t quantile for ``dof`` degrees of freedom (NaN where ``dof < 1``)."""
    from scipy import stats

    dof_arr = np.asarray(dof, dtype=float)
    with np.errstate(all="ignore"):
        q = stats.t.ppf(0.5 + confidence / 2, np.where(dof_arr >= 1, dof_arr, 1.0))
    return np.where(dof_arr >= 1, q, np.nan)


def summarize(results: pd.DataFrame, agents: Sequence[str] | None = None) -> pd.DataFrame:
    """Final returns per agent: ``agent, n_seeds, final_return_mean, final_return_std, ...``.

    The final return of a run is the mean return of its last training episodes (the fitness
    measure of evolution); with evaluation episodes, their mean is summarized too. Standard
    deviations are sample standard deviations across seeds (``ddof=1``; 0 with one seed).
    """
    columns = [
        "agent",
        "n_seeds",
        "final_return_mean",
        "final_return_std",
        "eval_return_mean",
        "eval_return_std",
        "seeds",
    ]
    if results.empty:
        return pd.DataFrame(columns=columns)
    rows = []
    order = list(agents) if agents else list(dict.fromkeys(results["agent"]))
    for agent in order:
        group = results[results["agent"] == agent]
        if group.empty:
            continue
        final = group["final_return"].astype(float)
        evals = (
            group["eval_return"].astype(float) if "eval_return" in group else pd.Series(dtype=float)
        )
        rows.append(
            {
                "agent": agent,
                "n_seeds": len(group),
                "final_return_mean": final.mean(),
                "final_return_std": final.std(ddof=1) if len(final) > 1 else 0.0,
                "eval_return_mean": evals.mean() if evals.notna().any() else np.nan,
                "eval_return_std": (
                    (evals.std(ddof=1) if evals.notna().sum() > 1 else 0.0)
                    if evals.notna().any()
                    else np.nan
                ),
                "seeds": " ".join(str(s) for s in sorted(group["seed"])),
            }
        )
    return pd.DataFrame(rows, columns=columns)


def load_run_config(out: str | Path) -> dict[str, Any]:
    """The ``config.yaml`` of a test-phase folder (task, encoder, agents, study, ...).

    The task's env id is checked against the registry
    ([`ermrl.envs.check_registered_env_id`][ermrl.envs.check_registered_env_id]): a ``module:Id``
    there is refused, never imported, since the file may come from anyone.

    Raises:
        FileNotFoundError: ``out`` has no ``config.yaml`` (not a test-phase folder).
        RunFolderError: it is not YAML, not a mapping, has no ``task.env_id``, or an entry of
            the wrong type.
        ermrl.envs.UnknownEnvError: its task's env id is not a registered id.
    """
    import yaml

    from ermrl._io import load_yaml
    from ermrl.envs import check_registered_env_id

    path = Path(out) / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found: {out} is not a test-phase folder (made by `ermrl test --out`)"
        )
    try:
        config = load_yaml(_read_text(path))
    except yaml.YAMLError as err:
        where = getattr(err, "problem_mark", None)
        line = f" at line {where.line + 1}" if where is not None else ""
        raise RunFolderError(
            path, f"not YAML ({getattr(err, 'problem', None) or 'parse error'}{line})"
        ) from None
    except RecursionError:
        raise RunFolderError(path, "not YAML (nested too deeply)") from None
    if not isinstance(config, dict):
        raise RunFolderError(path, f"not a mapping ({_kind(config)})")
    for key in CONFIG_MAPPINGS:
        value = config.get(key)
        if value is not None and not isinstance(value, dict):
            raise RunFolderError(path, f"{key!r} is {_kind(value)}, not a mapping")
    task = config.get("task")
    if not task or "env_id" not in task:
        raise RunFolderError(path, "no 'task' with an 'env_id' (not written by ermrl test)")
    if not isinstance(task["env_id"], str):
        raise RunFolderError(path, f"'task.env_id' is {_kind(task['env_id'])}, not an id")
    if not isinstance(task.get("observe", ""), str):
        raise RunFolderError(path, f"'task.observe' is {_kind(task['observe'])}, not a mask")
    seeds = (config.get("settings") or {}).get("seeds")
    if seeds is not None and not (
        isinstance(seeds, list)
        and all(isinstance(s, int) and not isinstance(s, bool) for s in seeds)
    ):
        raise RunFolderError(path, "'settings.seeds' is not a list of integers")
    params = config.get("params")
    if params is not None and not (
        isinstance(params, dict) and all(_is_number(v) for v in params.values())
    ):
        raise RunFolderError(path, "'params' is not a mapping of numbers")
    check_registered_env_id(task["env_id"], path)
    return config
