"""PPO hyperparameters: SB3 defaults, a packaged YAML table keyed by env id, CLI overrides."""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import yaml
from stable_baselines3 import PPO

from ermrl.config import ConfigError, PPOConfig

__all__ = [
    "load_hyperparams_table",
    "parse_overrides",
    "resolve_ppo_config",
    "ppo_kwargs",
    "linear_schedule",
]

# Keys of PPO(...) that a table or an override may set. `policy`, `env`, `seed`, `device`,
# `verbose` and `tensorboard_log` are owned by ermrl.
_PPO_KEYS = set(inspect.signature(PPO.__init__).parameters) - {
    "self",
    "policy",
    "env",
    "seed",
    "device",
    "verbose",
    "tensorboard_log",
    "_init_setup_model",
}
_ERMRL_KEYS = {"n_envs"}


def load_hyperparams_table(path: str | Path | None = None) -> dict[str, dict[str, Any]]:
    """Load a YAML table of PPO hyperparameters keyed by env id.

    Args:
        path: A YAML file; ``None`` loads the packaged ``ermrl/data/ppo.yml``.

    Returns:
        The table, with a ``default`` entry (possibly empty).
    """
    if path is None:
        text = resources.files("ermrl").joinpath("data/ppo.yml").read_text()
    else:
        try:
            text = Path(path).read_text()
        except OSError as err:
            raise ConfigError(f"cannot read hyperparameter file {path}: {err.strerror}") from err
    table = yaml.safe_load(text) or {}
    if not isinstance(table, dict):
        raise ConfigError(f"hyperparameter file {path} must map env ids to settings")
    table = {env_id: _coerce(entry or {}) for env_id, entry in table.items()}
    table.setdefault("default", {})
    for env_id, entry in table.items():
        _check_keys(entry or {}, f"{path or 'ppo.yml'}[{env_id}]")
    return table


def _coerce(value: Any) -> Any:
    """Read numeric strings as numbers: PyYAML (YAML 1.1) loads ``1e-4`` as the string "1e-4"."""
    if isinstance(value, str):
        for kind in (int, float):
            try:
                return kind(value)
            except ValueError:
                pass
        return value
    if isinstance(value, dict):
        return {k: _coerce(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_coerce(v) for v in value]
    return value


def _check_keys(entry: Mapping[str, Any], where: str) -> None:
    unknown = set(entry) - _PPO_KEYS - _ERMRL_KEYS
    if unknown:
        raise ConfigError(
            f"{where}: unknown PPO hyperparameter(s) {sorted(unknown)}; "
            f"valid keys: {sorted(_PPO_KEYS | _ERMRL_KEYS)}"
        )


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """Parse ``KEY=VALUE`` strings; values are read as YAML (``1e-4``, ``true``, ``[64, 64]``).

    Raises:
        ConfigError: a malformed item or an unknown key.
    """
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"PPO override {item!r} is not KEY=VALUE")
        try:
            out[key.strip()] = _coerce(yaml.safe_load(raw))
        except yaml.YAMLError as err:
            raise ConfigError(f"PPO override {item!r}: cannot parse value") from err
    _check_keys(out, "--ppo")
    return out


def resolve_ppo_config(
    env_id: str,
    overrides: Mapping[str, Any] | None = None,
    *,
    n_envs: int | None = None,
    table_path: str | Path | None = None,
    torch_threads: int = 1,
) -> PPOConfig:
    """Resolve an env's PPO settings: SB3 defaults < table ``default`` < table[env_id] < overrides.

    Args:
        env_id: Gymnasium id.
        overrides: Command-line overrides.
        n_envs: Explicit number of environments (wins over the table).
        table_path: Alternative YAML table.
        torch_threads: Torch threads per training process.
    """
    table = load_hyperparams_table(table_path)
    merged: dict[str, Any] = dict(table.get("default") or {})
    merged.update(table.get(env_id) or {})
    merged.update(overrides or {})
    table_n_envs = int(merged.pop("n_envs", 1))
    return PPOConfig(
        n_envs=n_envs if n_envs is not None else table_n_envs,
        hyperparams=merged,
        torch_threads=torch_threads,
    )


def linear_schedule(initial: float) -> Callable[[float], float]:
    """A schedule that goes linearly from ``initial`` to 0 over training."""

    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule


def ppo_kwargs(config: PPOConfig) -> dict[str, Any]:
    """Keyword arguments for ``PPO(...)`` from a config (``lin_X`` strings become schedules)."""
    kwargs: dict[str, Any] = {}
    for key, value in config.hyperparams.items():
        if isinstance(value, str) and value.startswith("lin_"):
            value = linear_schedule(float(value[4:]))
        kwargs[key] = value
    return kwargs
