"""Build gymnasium envs the way ermrl uses them: validated id, optional observation mask."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

import gymnasium
from gymnasium import spaces

from ermrl.envs._masks import (
    CLASSIC_SPLITS,
    MUJOCO_OBSERVE_ENVS,
    ObservationMask,
    ObservationSplit,
    ObserveMode,
    UnsupportedObserveError,
    _derive_mujoco_split,
    _is_mujoco_entry_point,
    _registered_spec,
    _select,
    _unsupported,
    _validate_observe,
    check_env_id,
    observation_split,
)

__all__ = ["make_env"]

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


def _split_for(env_id: str, env_kwargs: Mapping[str, Any]) -> ObservationSplit:
    """Split for ``env_id`` built with ``env_kwargs``.

    Without keyword arguments this is the cached :func:`observation_split`.  With them, a
    MuJoCo env is probed again as configured (options such as
    ``include_cfrc_ext_in_observation`` or ``exclude_current_positions_from_observation``
    change the layout); table envs keep their table and are checked against the built space.

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

    Args:
        env_id: A registered gymnasium id, e.g. ``"HalfCheetah-v5"``.
        observe: ``"all"`` (full observation), ``"positions"`` or ``"velocities"``.
        render_mode: Passed to ``gymnasium.make``.
        **env_kwargs: Further keyword arguments for ``gymnasium.make``.

    Returns:
        The env; for a masked mode, wrapped in :class:`ObservationMask` so observations have
        shape ``(len(indices),)`` instead of ``(obs_dim,)``.

    Raises:
        ValueError: For an unknown ``observe`` value.
        UnknownEnvError: When ``env_id`` is not registered.
        UnsupportedObserveError: When a mask is requested for an env without a known split, or
            the built env's observation does not have the split's layout.
    """
    _validate_observe(observe)
    check_env_id(env_id)
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
