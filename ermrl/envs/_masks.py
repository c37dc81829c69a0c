"""Partial observability: which entries of a task's observation are positions, which velocities.

``--observe {all,positions,velocities}`` keeps only one part of a flat observation vector.
This module knows the split for each supported task and provides the wrapper that applies it:

* classic-control and Box2D tasks use documented index tables (`CLASSIC_SPLITS`);
* MuJoCo locomotion tasks (``Ant``, ``HalfCheetah``, ``Swimmer``, ``Hopper``, ``Walker2d`` in
  ``-v4`` and ``-v5``) derive the split from the simulator itself: the env is built once, and
  every ``data.qpos[i]`` / ``data.qvel[j]`` is nudged in turn while watching which entries of
  ``_get_obs()`` move (see `observation_split`).
"""

from __future__ import annotations

import difflib
import functools
import importlib
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.envs.registration import EnvSpec

__all__ = [
    "CLASSIC_SPLITS",
    "MUJOCO_OBSERVE_ENVS",
    "OBSERVE_MODES",
    "FULL_OBSERVATION_KEY",
    "ObservationMask",
    "ObservationSplit",
    "ObserveMode",
    "UnknownEnvError",
    "UnsupportedObserveError",
    "check_env_id",
    "observation_indices",
    "observation_split",
    "supported_observe_envs",
]

ObserveMode = Literal["all", "positions", "velocities"]
# The info key under which ObservationMask passes on the unmasked observation (for imitation:
# an expert acts on the full state while the learner sees the masked one).
FULL_OBSERVATION_KEY = "full_observation"
OBSERVE_MODES: tuple[str, ...] = ("all", "positions", "velocities")


class UnknownEnvError(ValueError):
    """The env id is not registered in gymnasium."""


class UnsupportedObserveError(ValueError):
    """A position/velocity mask was requested for an env without a known split."""


@dataclass(frozen=True)
class ObservationSplit:
    """Which entries of a flat observation are positions and which are velocities.

    Indices in neither tuple (e.g. Ant-v5's contact forces) are dropped by both masks.

    Attributes:
        obs_dim: Length of the flat observation vector, shape ``(obs_dim,)``.
        positions: Sorted indices into the observation that depend only on positions.
        velocities: Sorted indices into the observation that depend only on velocities.
        source: Where the split comes from: ``"table"`` (documented layout) or
            ``"mujoco-model"`` (probed from the simulator).
    """

    obs_dim: int
    positions: tuple[int, ...]
    velocities: tuple[int, ...]
    source: str


# ---------------------------------------------------------------------------------------------
# Classic control / Box2D: documented observation layouts.
#
# Sources (gymnasium documentation, "Observation Space" section of each env page):
# * CartPole      https://gymnasium.farama.org/environments/classic_control/cart_pole/
#                 [cart position x, cart velocity x_dot, pole angle theta, pole angular velocity]
# * Pendulum      https://gymnasium.farama.org/environments/classic_control/pendulum/
#                 [cos(theta), sin(theta), angular velocity theta_dot]
# * MountainCar   https://gymnasium.farama.org/environments/classic_control/mountain_car/
#   (and .../mountain_car_continuous/)   [position of the car, velocity of the car]
# * Acrobot       https://gymnasium.farama.org/environments/classic_control/acrobot/
#                 [cos(th1), sin(th1), cos(th2), sin(th2), th1_dot, th2_dot]
# * LunarLander   https://gymnasium.farama.org/environments/box2d/lunar_lander/
#                 [x, y, vx, vy, angle, angular velocity, leg1 contact, leg2 contact]
#   The same layout holds for ``continuous=True`` and for LunarLanderContinuous-v3.
#   The two boolean leg-contact flags are neither positions nor velocities; they stay with
#   ``positions`` so that ``velocities``' complement matches the original ER-MRL code and
#   rl-baselines3-zoo's ``MaskVelocityWrapper``, which delete / zero exactly the velocity
#   indices [2, 3, 5].  (ER-MRL's velocity-deletion indices: CartPole [1, 3], MountainCar [1],
#   Pendulum [2], LunarLander [2, 3, 5]; the tables below agree with all of them.)
# ---------------------------------------------------------------------------------------------
_CARTPOLE = ObservationSplit(obs_dim=4, positions=(0, 2), velocities=(1, 3), source="table")
_PENDULUM = ObservationSplit(obs_dim=3, positions=(0, 1), velocities=(2,), source="table")
_MOUNTAIN_CAR = ObservationSplit(obs_dim=2, positions=(0,), velocities=(1,), source="table")
_ACROBOT = ObservationSplit(obs_dim=6, positions=(0, 1, 2, 3), velocities=(4, 5), source="table")
_LUNAR_LANDER = ObservationSplit(
    obs_dim=8, positions=(0, 1, 4, 6, 7), velocities=(2, 3, 5), source="table"
)

CLASSIC_SPLITS: Mapping[str, ObservationSplit] = {
    "CartPole-v0": _CARTPOLE,
    "CartPole-v1": _CARTPOLE,
    "Pendulum-v1": _PENDULUM,
    "MountainCar-v0": _MOUNTAIN_CAR,
    "MountainCarContinuous-v0": _MOUNTAIN_CAR,
    "Acrobot-v1": _ACROBOT,
    "LunarLander-v3": _LUNAR_LANDER,
    "LunarLanderContinuous-v3": _LUNAR_LANDER,
}

# MuJoCo ids whose split is derived from the model and covered by tests.  Other gymnasium
# MuJoCo envs are accepted only when the probe classifies every observation entry cleanly.
MUJOCO_OBSERVE_ENVS: tuple[str, ...] = tuple(
    f"{family}-{version}"
    for family in ("Ant", "HalfCheetah", "Hopper", "Swimmer", "Walker2d")
    for version in ("v4", "v5")
)

# Probe step: small enough to stay inside clipping ranges (Hopper/Walker2d-v5 clip qvel to
# +-10) around the reset state, large enough that cos/sin of a nudged angle still moves by
# ~eps**2 / 2 = 5e-7 even at an extremum.
_PROBE_EPS = 1e-3
_PROBE_ATOL = 1e-10


# ---------------------------------------------------------------------------------------------
# Registry look-ups (cheap: never constructs an env).
# ---------------------------------------------------------------------------------------------
def _registered_spec(env_id: str) -> EnvSpec | None:
    """Return the registry entry for ``env_id``, importing a ``"module:Id"`` prefix first.

    Args:
        env_id: A gymnasium id, optionally prefixed ``"module:"`` like ``gymnasium.make`` accepts.

    Returns:
        The ``EnvSpec`` or ``None`` when the id is not registered.
    """
    name = env_id
    if ":" in env_id:
        module, name = env_id.split(":", 1)
        if not all(part.isidentifier() for part in module.split(".")):
            raise UnknownEnvError(
                f"unknown env id {env_id!r}: {module!r} before ':' is not a module name "
                "(use module.path:Env-v0, or the id alone)"
            )
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise UnknownEnvError(
                f"unknown env id {env_id!r}: cannot import module {module!r} ({exc})"
            ) from exc
    return gymnasium.registry.get(name)


def check_env_id(env_id: str) -> None:
    """Fail fast on an env id that gymnasium does not know, suggesting close matches.

    Only the registry is consulted; the env is not constructed.

    Args:
        env_id: A gymnasium id such as ``"HalfCheetah-v5"``.

    Raises:
        UnknownEnvError: When ``env_id`` is not registered, e.g. ``unknown env id
            'HalfCheetah-v9'; did you mean: HalfCheetah-v5, HalfCheetah-v4?``.
    """
    if not isinstance(env_id, str) or not env_id:
        raise UnknownEnvError(f"env id must be a non-empty string, got {env_id!r}")
    if _registered_spec(env_id) is not None:
        return
    name = env_id.split(":", 1)[-1]
    close = difflib.get_close_matches(name, list(gymnasium.registry.keys()), n=3, cutoff=0.6)
    if not close:  # case slips such as "halfcheetah-v5"
        by_lower = {key.lower(): key for key in gymnasium.registry}
        close = [by_lower[m] for m in difflib.get_close_matches(name.lower(), list(by_lower), n=3)]
    hint = f"did you mean: {', '.join(close)}?" if close else "no similar id is registered"
    raise UnknownEnvError(f"unknown env id {env_id!r}; {hint}")


def supported_observe_envs() -> list[str]:
    """List the env ids with a known position/velocity split.

    Returns:
        Sorted registered ids: the classic tables plus the tested MuJoCo families (v4 and v5).
    """
    ids = set(CLASSIC_SPLITS) | set(MUJOCO_OBSERVE_ENVS)
    return sorted(i for i in ids if i in gymnasium.registry)


def _unsupported(env_id: str, reason: str) -> UnsupportedObserveError:
    """Build the error for an env without a usable split.

    Args:
        env_id: The env id that was asked for.
        reason: Why no split is available.

    Returns:
        An ``UnsupportedObserveError`` listing the supported ids.
    """
    return UnsupportedObserveError(
        f"cannot keep only positions or velocities of {env_id!r}: it {reason}; "
        f"supported ids: {', '.join(supported_observe_envs())}; "
        f"use --observe all (observe='all') for this env"
    )


def _is_mujoco_entry_point(spec: EnvSpec) -> bool:
    """Tell, from the registry alone, whether an env is likely a MuJoCo env.

    Args:
        spec: The registry entry.

    Returns:
        True when the entry point names a ``mujoco`` module.
    """
    entry = spec.entry_point
    name = entry if isinstance(entry, str) else getattr(entry, "__module__", "") or ""
    return "mujoco" in name.lower()


# ---------------------------------------------------------------------------------------------
# MuJoCo: probe the split from the model.
# ---------------------------------------------------------------------------------------------
def _probe_mujoco(env: gymnasium.Env) -> tuple[np.ndarray, np.ndarray]:
    """Find which observation entries respond to each ``qpos`` and ``qvel`` coordinate.

    The env must already be reset.  Each ``data.qpos[i]`` and ``data.qvel[j]`` is nudged by
    ``+eps`` and ``-eps`` in turn (and restored bit-for-bit afterwards) and ``_get_obs()`` is
    re-read WITHOUT ``mj_forward``, so quantities the simulator derives (contact forces
    ``cfrc_ext``, body positions ``xpos``, ...) keep their values and do not respond.

    Args:
        env: A reset env whose ``unwrapped`` is a gymnasium ``MujocoEnv``.

    Returns:
        ``(pos_hits, vel_hits)``: boolean arrays of shape ``(obs_dim,)``; ``pos_hits[k]`` is
        True when observation entry ``k`` moved with some ``qpos`` coordinate, ``vel_hits[k]``
        likewise for ``qvel``.
    """
    base_env: Any = env.unwrapped
    data = base_env.data
    base = np.asarray(base_env._get_obs(), dtype=np.float64).ravel().copy()

    def hits(vector: np.ndarray) -> np.ndarray:
        moved = np.zeros(base.shape, dtype=bool)
        for i in range(vector.shape[0]):
            saved = float(vector[i])
            for sign in (1.0, -1.0):
                vector[i] = saved + sign * _PROBE_EPS
                obs = np.asarray(base_env._get_obs(), dtype=np.float64).ravel()
                moved |= ~np.isclose(obs, base, rtol=0.0, atol=_PROBE_ATOL)
            vector[i] = saved
        return moved

    pos_hits = hits(data.qpos)
    vel_hits = hits(data.qvel)
    restored = np.asarray(base_env._get_obs(), dtype=np.float64).ravel()
    if not np.array_equal(restored, base):  # pragma: no cover - would mean state leaked
        raise RuntimeError("MuJoCo observation probe failed to restore the simulator state")
    return pos_hits, vel_hits


def _derive_mujoco_split(
    env_id: str, env_kwargs: Mapping[str, Any] | None = None, *, strict: bool = False
) -> ObservationSplit:
    """Build a MuJoCo env once and derive its position/velocity split by probing.

    Args:
        env_id: A registered MuJoCo env id.
        env_kwargs: Extra ``gymnasium.make`` keyword arguments that may change the layout
            (e.g. ``include_cfrc_ext_in_observation=False``).
        strict: When True (envs outside `MUJOCO_OBSERVE_ENVS`), every observation entry
            must respond to exactly one of qpos/qvel; derived quantities are not allowed.

    Returns:
        The derived split with ``source="mujoco-model"``.

    Raises:
        UnsupportedObserveError: When the env is not a MuJoCo env exposing ``_get_obs``, its
            observation is not flat, or the probe cannot classify it cleanly.
    """
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

    kwargs = dict(env_kwargs or {})
    kwargs.pop("render_mode", None)
    with warnings.catch_warnings():
        # -v4 ids are deprecated in gymnasium 1.x but still build; the probe is internal.
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        warnings.filterwarnings("ignore", message=r".*is out of date.*")
        env = gymnasium.make(env_id, **kwargs)
    try:
        base_env = env.unwrapped
        if not isinstance(base_env, MujocoEnv) or not hasattr(base_env, "_get_obs"):
            raise _unsupported(env_id, "is not a gymnasium MujocoEnv with _get_obs()")
        space = env.observation_space
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise _unsupported(env_id, f"has a non-flat observation space {space}")
        env.reset(seed=0)
        pos_hits, vel_hits = _probe_mujoco(env)
    finally:
        env.close()

    obs_dim = int(space.shape[0])
    if pos_hits.shape != (obs_dim,):
        raise _unsupported(env_id, "returns observations that do not match its space")
    both = np.flatnonzero(pos_hits & vel_hits)
    if both.size:
        raise _unsupported(env_id, f"mixes positions and velocities in entries {both.tolist()}")
    positions = tuple(int(i) for i in np.flatnonzero(pos_hits))
    velocities = tuple(int(i) for i in np.flatnonzero(vel_hits))
    if not positions or not velocities:
        raise _unsupported(env_id, "does not observe both positions and velocities")
    if strict and len(positions) + len(velocities) != obs_dim:
        neither = np.flatnonzero(~(pos_hits | vel_hits)).tolist()
        shown = ", ".join(map(str, neither[:8])) + (", ..." if len(neither) > 8 else "")
        raise _unsupported(
            env_id,
            f"has {len(neither)} derived observation entries ([{shown}]) that are neither "
            "plain positions nor plain velocities",
        )
    return ObservationSplit(obs_dim, positions, velocities, source="mujoco-model")


@functools.lru_cache(maxsize=256)
def observation_split(env_id: str) -> ObservationSplit:
    """Return the position/velocity split of ``env_id``'s default observation.

    Classic-control/Box2D ids come from `CLASSIC_SPLITS`.  MuJoCo ids are probed once
    (see `_probe_mujoco`) and cached: an observation entry that responds only to
    ``qpos`` is a position, only to ``qvel`` a velocity, and anything else (Ant-v5's contact
    forces) is neither.  Other gymnasium MuJoCo envs are accepted when every entry classifies
    cleanly.

    Args:
        env_id: A registered gymnasium id.

    Returns:
        The split for the env built with default keyword arguments.

    Raises:
        UnknownEnvError: When ``env_id`` is not registered.
        UnsupportedObserveError: When no split is known for ``env_id``.
    """
    check_env_id(env_id)
    if env_id in CLASSIC_SPLITS:
        return CLASSIC_SPLITS[env_id]
    if env_id in MUJOCO_OBSERVE_ENVS:
        return _derive_mujoco_split(env_id)
    spec = _registered_spec(env_id)
    if spec is not None and _is_mujoco_entry_point(spec):
        return _derive_mujoco_split(env_id, strict=True)
    raise _unsupported(env_id, "has no known position/velocity split")


def _validate_observe(observe: str) -> None:
    """Reject anything but ``"all"``, ``"positions"`` or ``"velocities"``.

    Args:
        observe: The requested observation mode.

    Raises:
        ValueError: For an unknown mode.
    """
    if observe not in OBSERVE_MODES:
        raise ValueError(f"observe must be one of {', '.join(OBSERVE_MODES)}; got {observe!r}")


def _select(split: ObservationSplit, observe: ObserveMode) -> tuple[int, ...] | None:
    """Pick the kept indices of a split for an observation mode.

    Args:
        split: The env's split.
        observe: The observation mode (already validated).

    Returns:
        ``None`` for ``"all"``, else the kept indices.
    """
    if observe == "all":
        return None
    return split.positions if observe == "positions" else split.velocities


def observation_indices(env_id: str, observe: ObserveMode) -> tuple[int, ...] | None:
    """Indices of the flat observation kept by an observation mode.

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
    if observe == "all":
        return None
    return _select(observation_split(env_id), observe)


class ObservationMask(gymnasium.ObservationWrapper):
    """Keep only selected entries of a flat ``Box`` observation.

    ``observation(obs) == obs[indices]``; the new space is a ``Box`` with the kept ``low`` and
    ``high`` bounds and the original dtype. ``reset`` and ``step`` also put the unmasked
    observation, shape ``(obs_dim,)``, into ``info["full_observation"]``
    (`FULL_OBSERVATION_KEY`), so that an expert can act on the full state while a learner
    sees the masked one (the ``bc`` and ``dagger`` learners read it).
    """

    def __init__(self, env: gymnasium.Env, indices: Sequence[int]) -> None:
        """Wrap ``env``.

        Args:
            env: Env with a 1-D ``Box`` observation space of shape ``(obs_dim,)``.
            indices: Non-empty, distinct indices in ``[0, obs_dim)`` to keep, in output order;
                the masked observation has shape ``(len(indices),)``.

        Raises:
            TypeError: When the observation space is not a 1-D ``Box``.
            ValueError: When ``indices`` is empty, repeats an index or is out of range.
        """
        super().__init__(env)
        space = env.observation_space
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise TypeError(f"ObservationMask needs a 1-D Box observation space, got {space}")
        idx = np.asarray(list(indices), dtype=np.intp)
        if idx.ndim != 1 or idx.size == 0:
            raise ValueError("ObservationMask needs at least one index to keep")
        if np.unique(idx).size != idx.size:
            raise ValueError(f"ObservationMask indices repeat: {idx.tolist()}")
        obs_dim = space.shape[0]
        if idx.min() < 0 or idx.max() >= obs_dim:
            raise ValueError(f"ObservationMask indices {idx.tolist()} out of range [0, {obs_dim})")
        self.indices: tuple[int, ...] = tuple(int(i) for i in idx)
        self._idx = idx
        self.observation_space = spaces.Box(
            low=space.low[idx], high=space.high[idx], dtype=space.dtype
        )

    def observation(self, observation: np.ndarray) -> np.ndarray:
        """Select the kept entries.

        Args:
            observation: Full observation, shape ``(obs_dim,)``.

        Returns:
            Masked observation, shape ``(len(indices),)``, same dtype.
        """
        return np.asarray(observation)[self._idx]

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset the env; ``info["full_observation"]`` holds the unmasked observation."""
        obs, info = self.env.reset(seed=seed, options=options)
        info[FULL_OBSERVATION_KEY] = obs
        return self.observation(obs), info

    def step(self, action: Any) -> tuple[np.ndarray, Any, bool, bool, dict[str, Any]]:
        """Step the env; ``info["full_observation"]`` holds the unmasked observation."""
        obs, reward, terminated, truncated, info = self.env.step(action)
        info[FULL_OBSERVATION_KEY] = obs
        return self.observation(obs), reward, terminated, truncated, info
