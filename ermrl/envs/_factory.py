"""Build gymnasium envs the way ermrl uses them: validated id, optional observation mask.

POPGym ids (``popgym-<Name>-v0``) are registered on first use, so
[`check_env_id`][ermrl.envs.check_env_id], [`observation_split`][ermrl.envs.observation_split] and
[`observation_indices`][ermrl.envs.observation_indices] here wrap those of `ermrl.envs._masks` to
import ``popgym`` first (see `ermrl.envs._popgym`).
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Mapping
from os import PathLike
from typing import Any

import gymnasium
from gymnasium import spaces

from ermrl.envs import _masks
from ermrl.envs._masks import (
    CLASSIC_SPLITS,
    MUJOCO_OBSERVE_ENVS,
    ObservationMask,
    ObservationSplit,
    ObserveMode,
    UnknownEnvError,
    UnsupportedObserveError,
    _derive_mujoco_split,
    _is_mujoco_entry_point,
    _registered_spec,
    _select,
    _unsupported,
    _validate_observe,
)
from ermrl.envs._popgym import (
    check_popgym_observe,
    is_popgym_id,
    make_popgym_env,
    register_popgym,
)

__all__ = [
    "check_env_id",
    "check_registered_env_id",
    "make_env",
    "observation_indices",
    "observation_split",
]

# MuJoCo >= 3.3 warns, on every model load, that gymnasium's own XML files use the deprecated
# `settotalmass` attribute. Nothing ermrl or its users can fix; it would flood progress output.
_HARMLESS_MUJOCO_WARNINGS = ("'settotalmass' is deprecated",)
_mujoco_handler_installed = False


def _filter_mujoco_warnings() -> None:
    """Route MuJoCo's C-level warnings through Python warnings, minus the known harmless ones."""
    global _mujoco_handler_installed
    if _mujoco_handler_installed:
        return
    try:
        import mujoco
    except ImportError:
        return

    def handler(message: str) -> None:
        if not any(text in message for text in _HARMLESS_MUJOCO_WARNINGS):
            warnings.warn(f"MuJoCo: {message}", RuntimeWarning, stacklevel=2)

    mujoco.set_mju_user_warning(handler)
    _mujoco_handler_installed = True


_filter_mujoco_warnings()


def check_env_id(env_id: str) -> None:
    """Fail fast on an env id that gymnasium does not know, suggesting close matches.

    `ermrl.envs._masks.check_env_id`, after registering POPGym tasks for a ``popgym-``
    id. Only the registry is consulted; the env is not constructed.

    Args:
        env_id: A gymnasium id such as ``"HalfCheetah-v5"`` or ``"popgym-RepeatFirstEasy-v0"``.

    Raises:
        UnknownEnvError: When ``env_id`` is not registered (or ``popgym`` is not installed).
    """
    register_popgym(env_id)
    _masks.check_env_id(env_id)


def check_registered_env_id(env_id: object, source: str | PathLike[str]) -> str:
    """Check an env id read from a file: it must be registered already; nothing is imported.

    ``gymnasium.make("module:Env-v0")`` imports ``module``, so a ``module:`` id in a file that
    someone else wrote (a run folder's ``config.yaml``, an expert's ``expert.json``) would run
    that module's code when ermrl builds the env. An id read from a file must therefore be in
    gymnasium's registry already: gymnasium's own tasks, ermrl's variants (registered when
    [`ermrl.envs`][ermrl.envs] is imported) or a POPGym task (ermrl imports the ``popgym`` package
    itself, whatever the file says). A ``module:`` prefix passes only when that module is
    imported already (importing it again runs nothing). Ids the user types on the command line
    go through [`check_env_id`][ermrl.envs.check_env_id], which may import their module.

    Args:
        env_id: The id as read from the file.
        source: The file it was read from, named in the error.

    Returns:
        ``env_id``, now known to be a registered id.

    Raises:
        UnknownEnvError: One line naming ``source``, when the id is not a string, names a
            module that is not imported yet, or is not registered.
    """
    if not isinstance(env_id, str) or not env_id:
        raise UnknownEnvError(f"{source}: env id must be a non-empty string, got {env_id!r}")
    module, name = env_id.split(":", 1) if ":" in env_id else ("", env_id)
    if module and module not in sys.modules and not (module == "popgym" and is_popgym_id(name)):
        raise UnknownEnvError(
            f"{source}: env id {env_id!r} names the module {module!r}, which gymnasium would "
            "import; an env id read from a file must be a registered id (ermrl never imports "
            "a module that a file names)"
        )
    try:
        register_popgym(name)  # imports the popgym package for a popgym- id, nothing else
    except UnknownEnvError as err:
        raise UnknownEnvError(f"{source}: {err}") from None
    if name not in gymnasium.registry:
        raise UnknownEnvError(
            f"{source}: unknown env id {env_id!r}: not a registered gymnasium id (an env id "
            "read from a file is never imported)"
        )
    return env_id


def observation_split(env_id: str) -> ObservationSplit:
    """Return the position/velocity split of ``env_id``'s default observation.

    `ermrl.envs._masks.observation_split` (cached), refusing POPGym tasks with their own
    message.

    Args:
        env_id: A registered gymnasium id.

    Returns:
        The split for the env built with default keyword arguments.

    Raises:
        UnknownEnvError: When ``env_id`` is not registered.
        UnsupportedObserveError: When no split is known for ``env_id`` (always for POPGym).
    """
    check_env_id(env_id)
    if is_popgym_id(env_id):
        check_popgym_observe(env_id, "positions")
    return _masks.observation_split(env_id)


def observation_indices(env_id: str, observe: ObserveMode) -> tuple[int, ...] | None:
    """Indices of the flat observation kept by an observation mode.

    `ermrl.envs._masks.observation_indices`, refusing a mask for a POPGym task with its
    own message.

    Args:
        env_id: A registered gymnasium id.
        observe: ``"all"``, ``"positions"`` or ``"velocities"``.

    Returns:
        ``None`` for ``"all"`` (keep everything), else sorted indices into the observation.

    Raises:
        ValueError: For an unknown ``observe`` value.
        UnknownEnvError: When ``env_id`` is not registered.
        UnsupportedObserveError: When a mask is requested for an env without a known split.
    """
    _validate_observe(observe)
    check_env_id(env_id)
    if is_popgym_id(env_id):
        check_popgym_observe(env_id, observe)
    return _masks.observation_indices(env_id, observe)


def _split_for(env_id: str, env_kwargs: Mapping[str, Any]) -> ObservationSplit:
    """Split for ``env_id`` built with ``env_kwargs``.

    Without keyword arguments this is the cached
    [`observation_split`][ermrl.envs.observation_split]. With them, a MuJoCo env is probed again as
    configured (options such as ``include_cfrc_ext_in_observation`` or
    ``exclude_current_positions_from_observation`` change the layout); table envs keep their table
    and are checked against the built space.

    Args:
        env_id: A registered gymnasium id.
        env_kwargs: Keyword arguments for ``gymnasium.make`` (without ``render_mode``).

    Returns:
        The position/velocity split.

    Raises:
        UnsupportedObserveError: When no split is known for this env.
    """
    if not env_kwargs or env_id in CLASSIC_SPLITS:
        return observation_split(env_id)
    if env_id in MUJOCO_OBSERVE_ENVS:
        return _derive_mujoco_split(env_id, env_kwargs)
    spec = _registered_spec(env_id)
    if spec is not None and _is_mujoco_entry_point(spec):
        return _derive_mujoco_split(env_id, env_kwargs, strict=True)
    raise _unsupported(env_id, "has no known position/velocity split")


def make_env(
    env_id: str,
    observe: ObserveMode = "all",
    *,
    render_mode: str | None = None,
    **env_kwargs: Any,
) -> gymnasium.Env:
    """Create a gymnasium env, optionally keeping only its positions or its velocities.

    Everything cheap is validated first (``observe`` value, env id in the registry, a known
    split for masked modes) before the env itself is built.

    A POPGym task (``popgym-<Name>-v0``, see `ermrl.envs._popgym`) takes only
    ``observe="all"``; its observation is flattened to a float32 vector (one-hot for each
    discrete part).

    Args:
        env_id: A registered gymnasium id, e.g. ``"HalfCheetah-v5"``.
        observe: ``"all"`` (full observation), ``"positions"`` or ``"velocities"``.
        render_mode: Passed to ``gymnasium.make``.
        **env_kwargs: Further keyword arguments for ``gymnasium.make``.

    Returns:
        The env; for a masked mode, wrapped in [`ObservationMask`][ermrl.envs.ObservationMask] so
        observations have shape ``(len(indices),)`` instead of ``(obs_dim,)``; for a POPGym task,
        wrapped so observations are float32 of shape ``(flatdim,)``.

    Raises:
        ValueError: For an unknown ``observe`` value.
        UnknownEnvError: When ``env_id`` is not registered (for a POPGym id: or ``popgym`` is
            not installed).
        UnsupportedObserveError: When a mask is requested for an env without a known split (any
            POPGym task), or the built env's observation does not have the split's layout.
        ConfigError: When a POPGym env does not take ``render_mode`` or ``env_kwargs``.
    """
    _validate_observe(observe)
    check_env_id(env_id)
    if is_popgym_id(env_id):
        check_popgym_observe(env_id, observe)
        return make_popgym_env(env_id, render_mode, **env_kwargs)
    split = None if observe == "all" else _split_for(env_id, env_kwargs)

    env = gymnasium.make(env_id, render_mode=render_mode, **env_kwargs)
    if split is None:
        return env
    space = env.observation_space
    if not isinstance(space, spaces.Box) or space.shape != (split.obs_dim,):
        env.close()
        raise UnsupportedObserveError(
            f"{env_id!r} built with {env_kwargs!r} has observation space {space}, but its "
            f"position/velocity split expects shape ({split.obs_dim},); use --observe all"
        )
    indices = _select(split, observe)
    assert indices is not None
    return ObservationMask(env, indices)
