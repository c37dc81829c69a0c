"""POPGym memory tasks (``popgym-<Name>-v0``): lazy registration and flat float observations.

The ``popgym`` package registers its tasks with gymnasium when it is imported. ermrl imports it
only when a ``popgym-`` id is checked, looked up for a mask or built, so other tasks never load it.

POPGym observations are ``Discrete`` (RepeatFirst, HigherLower), ``MultiDiscrete`` (CountRecall,
Concentration), a ``Tuple`` of ``Discrete`` (Autoencode) or a ``Box`` (the CartPole and Pendulum
variants). ermrl's reservoir encoder and SB3's ``MlpPolicy`` need a flat float ``Box``, so every
POPGym env is wrapped in gymnasium's ``FlattenObservation`` (a one-hot vector per discrete part, a
``Box`` raveled), then ``DtypeObservation(float32)``. popgym's own ``popgym.wrappers.Flatten`` is
not used: it flattens only ``Tuple``/``Dict`` observations (a bare ``Discrete`` stays an integer),
keeps integer dtypes, and asserts that it wraps a bare ``POPGymEnv``, which the env checker that
``gymnasium.make`` adds is not.

Action spaces are kept as they are: ``Discrete``, ``MultiDiscrete`` (Battleship, MineSweeper) and
``Box`` (the Pendulum variants), all of which SB3's PPO supports.

POPGym tasks are partially observable by design, so only ``observe="all"`` is accepted.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import warnings
from typing import Any

import gymnasium
import numpy as np
from gymnasium.wrappers import DtypeObservation, FlattenObservation

from ermrl._config_base import ConfigError
from ermrl.envs._masks import UnknownEnvError, UnsupportedObserveError

__all__ = [
    "POPGYM_PREFIX",
    "check_popgym_observe",
    "flat_float_observation",
    "is_popgym_id",
    "make_popgym_env",
    "popgym_env_ids",
    "register_popgym",
]

POPGYM_PREFIX = "popgym-"
# The pin in pyproject.toml, named in the error for a missing package.
_POPGYM_REQUIREMENT = "popgym==1.0.7"


def is_popgym_id(env_id: object) -> bool:
    """Tell whether an env id names a POPGym task.

    Args:
        env_id: A gymnasium id such as ``"popgym-RepeatFirstEasy-v0"``, optionally prefixed
            ``"popgym:"`` as ``gymnasium.make`` accepts.

    Returns:
        True when the id (after any ``"module:"`` prefix) starts with ``"popgym-"``.
    """
    return isinstance(env_id, str) and env_id.split(":", 1)[-1].startswith(POPGYM_PREFIX)


def _import_popgym(env_id: str) -> None:
    """Import ``popgym`` (which registers its tasks) without letting it write to stdout.

    Args:
        env_id: The id that needs it, for the error message.

    Raises:
        UnknownEnvError: When the ``popgym`` package is not installed.
    """
    if importlib.util.find_spec("popgym") is None:
        raise UnknownEnvError(
            f"{env_id!r} is a POPGym task but the popgym package is not installed; "
            f"install it with: pip install {_POPGYM_REQUIREMENT}"
        )
    # stdout carries ermrl's progress output; popgym 1.0.7 prints nothing, but stay sure of it.
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        importlib.import_module("popgym")


def register_popgym(env_id: str) -> None:
    """Make sure a POPGym id is registered with gymnasium, importing ``popgym`` if needed.

    Does nothing for other ids. Importing ``popgym`` registers every task it ships.

    Args:
        env_id: Any gymnasium id.

    Raises:
        UnknownEnvError: When ``popgym`` is not installed, or the id is a Labyrinth task, which
            popgym registers only when ``mazelib`` is installed.
    """
    if not is_popgym_id(env_id):
        return
    name = env_id.split(":", 1)[-1]
    if name not in gymnasium.registry:
        _import_popgym(env_id)
    if (
        name not in gymnasium.registry
        and name.startswith(f"{POPGYM_PREFIX}Labyrinth")
        and importlib.util.find_spec("mazelib") is None
    ):
        raise UnknownEnvError(
            f"{env_id!r} is not available: popgym registers its Labyrinth tasks only when the "
            "optional mazelib package is installed, which ermrl does not require"
        )


def popgym_env_ids() -> list[str]:
    """List the POPGym ids registered by the installed ``popgym``.

    Returns:
        Sorted ids ``popgym-<Name>-v0`` (42 with popgym 1.0.7 and no mazelib).

    Raises:
        UnknownEnvError: When ``popgym`` is not installed.
    """
    _import_popgym(f"{POPGYM_PREFIX}*")
    return sorted(key for key in gymnasium.registry if key.startswith(POPGYM_PREFIX))


def check_popgym_observe(env_id: str, observe: str) -> None:
    """Refuse a position/velocity mask for a POPGym task.

    Args:
        env_id: A POPGym id.
        observe: The requested observation mode (already validated).

    Raises:
        UnsupportedObserveError: For any mode but ``"all"``.
    """
    if observe != "all":
        raise UnsupportedObserveError(
            f"{env_id!r} is a POPGym task, partially observable by design: it has no "
            f"position/velocity split to keep {observe!r}; use --observe all (observe='all')"
        )


def make_popgym_env(
    env_id: str, render_mode: str | None = None, **env_kwargs: Any
) -> gymnasium.Env:
    """Build a POPGym task with a flat float32 observation.

    ``render_mode`` is passed on only when given: most POPGym envs take no ``render_mode``
    argument (they render text); the CartPole and Pendulum variants take gymnasium's.

    Args:
        env_id: A registered POPGym id (see `register_popgym`).
        render_mode: Passed to ``gymnasium.make`` when not ``None``.
        **env_kwargs: Further keyword arguments for ``gymnasium.make``; the ``Easy``, ``Medium``
            and ``Hard`` envs take none.

    Returns:
        The env wrapped by `flat_float_observation`.

    Raises:
        ConfigError: When the env does not accept ``render_mode`` or ``env_kwargs``.
    """
    # No passive env checker: its only finding on POPGym is harmless (CountRecall's infos share
    # one array between steps) and would print two warnings in every training process. ermrl's
    # tests check every task's observations against its space instead.
    kwargs: dict[str, Any] = {"disable_env_checker": True, **env_kwargs}
    if render_mode is not None:
        kwargs["render_mode"] = render_mode
    try:
        env = gymnasium.make(env_id, **kwargs)
    except TypeError as err:
        given = {key: value for key, value in kwargs.items() if key != "disable_env_checker"}
        if not given:
            raise
        raise ConfigError(
            f"POPGym task {env_id!r} cannot be built with {given!r}: {str(err).splitlines()[0]}"
        ) from err
    return flat_float_observation(env)


def flat_float_observation(env: gymnasium.Env) -> gymnasium.Env:
    """Flatten an env's observation to a float32 vector.

    ``Discrete(n)`` becomes a one-hot vector of length ``n``, ``MultiDiscrete(nvec)`` the
    concatenation of one one-hot vector per entry (length ``sum(nvec)``), a ``Tuple`` the
    concatenation of its flattened parts, and a ``Box`` is raveled.

    Args:
        env: Any env whose observation space gymnasium can flatten.

    Returns:
        The env wrapped in ``FlattenObservation`` then ``DtypeObservation(np.float32)``: its
        observation space is a ``Box`` of shape ``(flatdim,)`` and dtype float32.
    """
    return DtypeObservation(FlattenObservation(env), np.float32)
