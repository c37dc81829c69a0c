"""PPO hyperparameters: SB3 defaults, a packaged YAML table keyed by env id, CLI overrides."""

from __future__ import annotations

import dataclasses
import inspect
import math
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import yaml
from stable_baselines3 import PPO, SAC

from ermrl._io import load_yaml
from ermrl.config import (
    ConfigError,
    EncoderConfig,
    NormalizeConfig,
    PPOConfig,
    TaskConfig,
)
from ermrl.learners._kwargs import (
    ACTIVATIONS,
    ERMRL_KEYS,
    activation_fn,
    linear_schedule,
    ppo_kwargs,
)

__all__ = [
    "ACTIVATIONS",
    "activation_fn",
    "load_hyperparams_table",
    "parse_normalize",
    "parse_overrides",
    "resolve_ppo_config",
    "with_overrides",
    "ppo_kwargs",
    "linear_schedule",
    "check_ppo_config",
]

# Keys of PPO(...) and SAC(...) that a table or an override may set. `policy`, `env`, `seed`,
# `device`, `verbose` and `tensorboard_log` are owned by ermrl. (A key of the other algorithm,
# such as SAC's learning_starts given to PPO, is refused when the agent is built.)
_OWNED_KEYS = {
    "self",
    "policy",
    "env",
    "seed",
    "device",
    "verbose",
    "tensorboard_log",
    "_init_setup_model",
}
_PPO_KEYS = set(inspect.signature(PPO.__init__).parameters) - _OWNED_KEYS
_SAC_KEYS = set(inspect.signature(SAC.__init__).parameters) - _OWNED_KEYS
_ERMRL_KEYS = ERMRL_KEYS  # read by ermrl, not PPO(...) arguments
_NORMALIZE_KEYS = tuple(f.name for f in dataclasses.fields(NormalizeConfig))


def parse_normalize(value: Any, where: str = "normalize") -> NormalizeConfig | None:
    """Read rl-baselines3-zoo's ``normalize`` value.

    Args:
        value: ``true``/``false``, ``null``, or a mapping of
            [`NormalizeConfig`][ermrl.config.NormalizeConfig] fields
            (``{norm_obs: true, norm_reward: false}``). A string is read as YAML, so the zoo's
            quoted form ``"{'norm_obs': False, 'norm_reward': True}"`` works too.
        where: Where the value comes from, for error messages.

    Returns:
        The settings, or ``None`` for no normalization.

    Raises:
        ConfigError: any other value, or an unknown or invalid field.
    """
    if isinstance(value, str):
        try:
            value = load_yaml(value)
        except yaml.YAMLError:
            pass  # reported below as not a mapping
    if value is None or value is False:
        return None
    if value is True:
        return NormalizeConfig()
    if not isinstance(value, Mapping):
        raise ConfigError(
            f"{where}: normalize must be true, false or a mapping such as "
            f"{{norm_obs: true, norm_reward: false}}, got {value!r}"
        )
    unknown = sorted(set(map(str, value)) - set(_NORMALIZE_KEYS))
    if unknown:
        raise ConfigError(
            f"{where}: unknown normalize key(s) {unknown}; valid keys: {list(_NORMALIZE_KEYS)} "
            "(the discount of reward normalization is PPO's gamma)"
        )
    try:
        return NormalizeConfig(**{str(k): _coerce(v) for k, v in value.items()})
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from None


def load_hyperparams_table(
    path: str | Path | None = None, learner: str = "ppo"
) -> dict[str, dict[str, Any]]:
    """Load a YAML table of a learner's settings keyed by env id.

    Args:
        path: A YAML file; ``None`` loads the learner's packaged table (``ermrl/data/ppo.yml``
            for PPO).
        learner: The learner whose settings these are (see [`ermrl.learners`][ermrl.learners]).

    Returns:
        The table, with a ``default`` entry (possibly empty).
    """
    from ermrl.learners import get_learner

    if path is None:
        text = resources.files("ermrl").joinpath(f"data/{get_learner(learner).table}").read_text()
    else:
        try:
            text = Path(path).read_text()
        except OSError as err:
            raise ConfigError(f"cannot read hyperparameter file {path}: {err.strerror}") from err
        except UnicodeDecodeError:
            raise ConfigError(f"hyperparameter file {path} is not a text (UTF-8) file") from None
    try:
        table = load_yaml(text) or {}
    except yaml.YAMLError as err:  # malformed, or a tag such as !!python/object (refused)
        raise ConfigError(
            f"hyperparameter file {path} is not valid plain YAML: {_one_line(err)}"
        ) from None
    if not isinstance(table, dict):
        raise ConfigError(f"hyperparameter file {path} must map env ids to settings")
    for env_id, entry in table.items():
        if entry is not None and not isinstance(entry, dict):
            raise ConfigError(
                f"hyperparameter file {path}: the entry of {env_id!r} must be a mapping of PPO "
                f"settings, got {entry!r}"
            )
    table = {env_id: _coerce(entry or {}) for env_id, entry in table.items()}
    table.setdefault("default", {})
    for env_id, entry in table.items():
        _check_keys(entry or {}, f"{path or get_learner(learner).table}[{env_id}]")
    return table


def _one_line(err: BaseException) -> str:
    """An exception's message on one line."""
    return " ".join(str(err).split()) or type(err).__name__


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


def _valid_keys() -> set[str]:
    """Keys a table or an override may set: any learner's algorithm arguments or own settings."""
    from ermrl.learners import LEARNERS

    keys = _PPO_KEYS | _SAC_KEYS | _ERMRL_KEYS
    for learner in LEARNERS.values():
        keys |= set(learner.own_keys)
    return keys


def _check_keys(entry: Mapping[str, Any], where: str) -> None:
    valid = _valid_keys()
    unknown = set(entry) - valid
    if unknown:
        raise ConfigError(
            f"{where}: unknown PPO hyperparameter(s) {sorted(unknown)}; valid keys: {sorted(valid)}"
        )
    if "normalize" in entry:
        parse_normalize(entry["normalize"], where)
    policy_kwargs = entry.get("policy_kwargs")
    if isinstance(policy_kwargs, Mapping) and "activation_fn" in policy_kwargs:
        activation_fn(policy_kwargs["activation_fn"], where)


def learner_keys(learner: str) -> set[str]:
    """The keys one learner's settings may hold: its algorithm's arguments (PPO's or SAC's),
    its own and shared settings, and the ones ermrl reads (``n_envs``, ``normalize``)."""
    from ermrl.learners import get_learner

    spec = get_learner(learner)
    algorithm_class: type = spec.algorithm()
    algorithm = set(inspect.signature(algorithm_class).parameters) - _OWNED_KEYS
    return algorithm | set(spec.own_keys) | set(spec.shared_keys) | _ERMRL_KEYS


def _split_override(item: str) -> tuple[str, str] | None:
    """``KEY=VALUE`` or, as rl-zoo writes them, ``KEY:VALUE``; None when it is neither."""
    eq, colon = item.find("="), item.find(":")
    # The first separator wins: `policy_kwargs=dict(a=1)` and `net_arch:[64, 64]` both split
    # at their first one; a value may hold either character.
    cut = min(i for i in (eq, colon) if i >= 0) if max(eq, colon) >= 0 else -1
    if cut <= 0:
        return None
    return item[:cut].strip(), item[cut + 1 :]


def parse_overrides(items: Sequence[str], learner: str | None = None) -> dict[str, Any]:
    """Parse ``KEY=VALUE`` (or rl-zoo's ``KEY:VALUE``) strings; values are read as YAML
    (``1e-4``, ``true``, ``[64, 64]``).

    Args:
        items: The option's words.
        learner: The learner they are for: an unknown key is then matched against its keys
            only (a did-you-mean, or the learner whose setting it is). None: any learner's.

    Raises:
        ConfigError: a malformed item or an unknown key.

    Examples:
        >>> parse_overrides(["learning_rate:1e-4", "n_steps=512"])
        {'learning_rate': 0.0001, 'n_steps': 512}
    """
    out: dict[str, Any] = {}
    for item in items:
        split = _split_override(item)
        if split is None or not split[0]:
            raise ConfigError(f"PPO override {item!r} is not KEY=VALUE (or KEY:VALUE)")
        key, raw = split
        try:
            out[key] = _coerce(load_yaml(raw))
        except yaml.YAMLError as err:
            raise ConfigError(
                f"PPO override {key!r}: cannot parse value ({_one_line(err)})"
            ) from None
    if learner is None:
        _check_keys(out, "--ppo")
    else:
        _check_learner_keys(out, learner, "--ppo")
    return out


def _check_learner_keys(entry: Mapping[str, Any], learner: str, where: str) -> None:
    """Refuse keys the learner does not take, with a did-you-mean among its own keys only."""
    import difflib

    from ermrl.learners import LEARNERS

    valid = learner_keys(learner)
    for key in sorted(set(entry) - valid):
        owners = [name for name in LEARNERS if name != learner and key in learner_keys(name)]
        if owners:
            raise ConfigError(
                f"{where}: {key!r} is a setting of another learner ({', '.join(owners[:3])}), "
                f"not of {learner!r}"
            )
        close = difflib.get_close_matches(key, sorted(valid), n=3)
        hint = (
            f"did you mean {' or '.join(repr(c) for c in close)}?"
            if close
            else f"learner {learner!r} takes: {', '.join(sorted(valid))}"
        )
        raise ConfigError(f"{where}: unknown setting {key!r} of learner {learner!r}; {hint}")
    _check_keys(entry, where)


def resolve_ppo_config(
    env_id: str,
    overrides: Mapping[str, Any] | None = None,
    *,
    n_envs: int | None = None,
    table_path: str | Path | None = None,
    torch_threads: int = 1,
    learner: str = "ppo",
    backend: str = "sb3",
) -> PPOConfig:
    """Resolve an env's PPO settings: SB3 defaults < table ``default`` < table[env_id] < overrides.

    ``n_envs`` and ``normalize`` go to their own [`PPOConfig`][ermrl.config.PPOConfig] fields; every
    other key is a ``PPO(...)`` argument.

    Args:
        env_id: Gymnasium id.
        overrides: Command-line overrides.
        n_envs: Explicit number of environments (wins over the table).
        table_path: Alternative YAML table (default: the learner's own).
        torch_threads: Torch threads per training process.
        learner: The learner (see [`ermrl.learners`][ermrl.learners]); its table is read.
        backend: What trains the agents (``sb3`` or ``population``, see
            [`ermrl.population`][ermrl.population]).
    """
    table = load_hyperparams_table(table_path, learner)
    merged: dict[str, Any] = dict(table.get("default") or {})
    merged.update(table.get(env_id) or {})
    merged.update(overrides or {})
    table_n_envs = _int_n_envs(merged.pop("n_envs", 1))
    return PPOConfig(
        n_envs=n_envs if n_envs is not None else table_n_envs,
        hyperparams=merged,
        torch_threads=torch_threads,
        normalize=parse_normalize(merged.pop("normalize", None), env_id),
        learner=learner,
        backend=backend,
    )


def with_overrides(config: PPOConfig, overrides: Mapping[str, Any]) -> PPOConfig:
    """``config`` with ``--ppo`` overrides applied (``n_envs`` and ``normalize`` to their fields).

    Args:
        config: Resolved settings (a study's, for example).
        overrides: From [`parse_overrides`][ermrl.agents.parse_overrides].
    """
    rest = dict(overrides)
    changes: dict[str, Any] = {}
    if "n_envs" in rest:
        changes["n_envs"] = _int_n_envs(rest.pop("n_envs"))
    if "normalize" in rest:
        changes["normalize"] = parse_normalize(rest.pop("normalize"), "--ppo")
    return dataclasses.replace(config, hyperparams={**config.hyperparams, **rest}, **changes)


def _int_n_envs(value: Any) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not math.isfinite(value)
        or value != int(value)
    ):
        raise ConfigError(f"n_envs must be a whole number, got {value!r}")
    return int(value)


# Ranges of numeric PPO(...) arguments that SB3 itself does not check at construction (a bad
# value would only fail, or silently misbehave, in the middle of training).
_NUMBER_RANGES: dict[str, tuple[float, float, bool]] = {
    # key: (low, high, low is exclusive)
    "learning_rate": (0.0, math.inf, True),
    "clip_range": (0.0, math.inf, True),
    "gamma": (0.0, 1.0, False),
    "gae_lambda": (0.0, 1.0, False),
    "ent_coef": (0.0, math.inf, False),
    "vf_coef": (0.0, math.inf, False),
    "max_grad_norm": (0.0, math.inf, True),
}
_INT_RANGES: dict[str, int] = {"n_steps": 1, "batch_size": 2, "n_epochs": 1}
# n_steps * n_envs transitions fill PPO's rollout buffer, allocated when the agent is built.
MAX_ROLLOUT = 10_000_000


def _check_values(config: PPOConfig) -> None:
    from ermrl.learners import get_learner

    # Settings the learner checks itself (SAC's ent_coef may be "auto").
    own_checks = get_learner(config.learner).checks_itself
    for key, value in config.hyperparams.items():
        if key in own_checks:
            continue
        if key in _INT_RANGES:
            if isinstance(value, bool) or not isinstance(value, int):
                raise ConfigError(f"PPO {key} must be an integer, got {value!r}")
            if value < _INT_RANGES[key]:
                raise ConfigError(f"PPO {key} must be >= {_INT_RANGES[key]}, got {value}")
        elif key in _NUMBER_RANGES:
            low, high, open_low = _NUMBER_RANGES[key]
            number = value
            if isinstance(value, str) and value.startswith("lin_"):
                number = _coerce(value[4:])
            if isinstance(number, bool) or not isinstance(number, (int, float)):
                raise ConfigError(
                    f"PPO {key} must be a number"
                    + (" or lin_<number>" if key in ("learning_rate", "clip_range") else "")
                    + f", got {value!r}"
                )
            above = number > low if open_low else number >= low
            if not (math.isfinite(number) and above and number <= high):
                bound = f"{'>' if open_low else '>='} {low:g}"
                if math.isfinite(high):
                    bound += f" and <= {high:g}"
                raise ConfigError(f"PPO {key} must be {bound}, got {value!r}")
    n_steps = config.hyperparams.get("n_steps", 2048)
    if n_steps * config.n_envs > MAX_ROLLOUT:
        raise ConfigError(
            f"n_steps * n_envs = {n_steps * config.n_envs} transitions per rollout; at most "
            f"{MAX_ROLLOUT} are allowed"
        )


def check_ppo_config(
    task: TaskConfig, encoder: EncoderConfig | None, ppo: PPOConfig, where: str = "PPO"
) -> None:
    """Refuse PPO settings that would fail or misbehave only once training runs.

    Checks the ranges of the common numeric settings, then builds the agent as training does
    (the real env, the reservoir encoder and normalization, the learner's wrappers and its
    algorithm with its policy network) without taking a step, so that whatever Stable-Baselines3 or torch refuses
    (``n_steps=1``, ``policy_kwargs={net_arch: foo}``, ...) is reported before a study or a run
    folder is touched.

    Args:
        task: Env id and observation mask.
        encoder: Reservoir encoding (``None``: plain PPO).
        ppo: The resolved settings.
        where: Names the settings in the message (``"PPO"``, an env id, ...).

    Raises:
        ConfigError: a setting is refused, with a one-line reason.
    """
    from ermrl.agents._normalize import normalize_env
    from ermrl.agents._train import make_vec_env
    from ermrl.learners import get_learner

    _check_values(ppo)
    learner = get_learner(ppo.learner)
    learner.check(ppo)
    ppo_kwargs(ppo)  # a malformed lin_X schedule is reported as such
    env = normalize_env(make_vec_env(task, ppo.n_envs, 0, encoder, 0), ppo)
    try:
        learner.build(learner.wrap_env(env, ppo), ppo, seed=0)
    except Exception as err:  # noqa: BLE001 - any refusal is bad input; its text says which
        raise ConfigError(f"{where} settings refused: {_one_line(err)}") from None
    finally:
        env.close()
