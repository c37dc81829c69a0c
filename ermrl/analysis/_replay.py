"""Replaying a trained agent of a test-phase folder: the same env, mask and reservoir weights.

A run folder ``<out>/agents/<agent>/seed_<s>/`` holds ``policy.pt``, ``model.zip``,
``result.json`` and ``settings.json``; the folder's ``config.yaml`` holds the task and encoding
options. The policy is read only from ``policy.pt`` (plain tensors, ``torch.load`` with
``weights_only=True``) and rebuilt from the run's PPO settings (``settings.json``, else
``config.yaml``) and the environment's spaces
([`ermrl.agents.load_policy`][ermrl.agents.load_policy]). ``model.zip`` is never read: SB3 unpickles
it, and a crafted one runs code. A run saved before ``policy.pt`` existed is refused; re-train it.
The reservoir weights are re-created from the run's seed exactly as in training
([`ermrl.agents.derive_seeds`][ermrl.agents.derive_seeds]), so the replayed policy sees the states
it was trained on. A run trained with ``normalize`` also has ``vecnormalize.json`` beside its model:
the replay normalizes the policy's input with those statistics, frozen, as training's own evaluation
did.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ermrl.analysis._results import (
    RUNS_DIR,
    RunFolderError,
    load_run_config,
    read_run_result,
    read_run_settings,
    run_dir,
)

__all__ = ["Rollout", "TrainedAgent", "available_runs", "load_trained_agent", "rollout"]


@dataclass(frozen=True)
class TrainedAgent:
    """A trained agent of a test-phase folder and everything needed to replay it.

    Attributes:
        run: The test-phase folder.
        agent: Agent name (``ppo``, ``ppo-full``, ``res-ppo``, ``random-res-ppo``).
        seed: The run's seed.
        env_id: Gymnasium id.
        observe: Observation mask.
        encoder: The reservoir encoding as a plain dict (``None`` for plain PPO).
        model_path: The run's SB3 model (``model.zip``); never read (see the module docstring).
        normalize_path: The run's normalization statistics (JSON), when it trained with
            ``normalize`` (``None`` otherwise).
        policy_path: The policy's weights as plain tensors (``policy.pt``).
        ppo: The run's PPO settings as plain data ([`PPOConfig`][ermrl.config.PPOConfig]'s dict).
    """

    run: Path
    agent: str
    seed: int
    env_id: str
    observe: str
    encoder: dict[str, Any] | None
    model_path: Path
    normalize_path: Path | None = None
    policy_path: Path | None = None
    ppo: dict[str, Any] | None = None

    @property
    def has_reservoir(self) -> bool:
        return self.encoder is not None


@dataclass
class Rollout:
    """One episode of a trained agent.

    Attributes:
        observations: Raw (masked) observations seen before each action, shape ``(T, obs_dim)``.
        actions: Actions taken, shape ``(T, act_dim)`` (``(T, 1)`` for discrete actions).
        rewards: Rewards received, shape ``(T,)``.
        states: Reservoir states the policy saw before each action, shape ``(T, units)``;
            without an encoder, a recurrent learner's own state when it is an array (hebbian:
            ``h``; rtu-ppo: ``(c1, c2)`` flattened) after each step; ``(T, 0)`` for plain PPO.
        frames: RGB frames, shape ``(height, width, 3)`` each (empty unless rendered).
        dt: Seconds of simulated time per step (``None`` when the env does not say).
        fps: Frames per second of real-time playback.
        ended: Whether the episode ended (terminated or truncated) rather than hit ``max_steps``.
    """

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    states: np.ndarray
    frames: list[np.ndarray] = field(default_factory=list)
    dt: float | None = None
    fps: float = 30.0
    ended: bool = True

    @property
    def n_steps(self) -> int:
        return int(len(self.rewards))

    @property
    def episode_return(self) -> float:
        return float(np.sum(self.rewards))


def available_runs(run: str | Path, agent: str | None = None) -> list[tuple[str, int]]:
    """``(agent, seed)`` of every run of a test-phase folder that saved its policy, sorted.

    Only runs with ``policy.pt`` count: a run with only SB3's ``model.zip`` (saved by an older
    ermrl) cannot be replayed, since ermrl never unpickles it.
    """
    return _runs_with(Path(run), "policy.pt", agent)


def _runs_with(run: Path, filename: str, agent: str | None) -> list[tuple[str, int]]:
    found = []
    for path in run.glob(f"{RUNS_DIR}/*/seed_*/{filename}"):
        name = path.parent.parent.name
        if agent is not None and name != agent:
            continue
        try:
            found.append((name, int(path.parent.name.removeprefix("seed_"))))
        except ValueError:
            continue
    return sorted(found, key=lambda p: (p[0], p[1]))


def load_trained_agent(
    run: str | Path, agent: str = "res-ppo", seed: int | None = None
) -> TrainedAgent:
    """Find a trained agent in a test-phase folder.

    Args:
        run: The test-phase folder (``--out`` of ``ermrl test``).
        agent: Agent name.
        seed: The run's seed (default: the smallest seed with a saved model).

    Returns:
        The agent, ready for [`rollout`][ermrl.analysis.rollout].

    Raises:
        FileNotFoundError: no such folder, no ``config.yaml``, or no saved model for that agent
            and seed (the message lists the available ones), or only an SB3 ``model.zip``
            without ``policy.pt`` (made before ermrl saved plain weights: it is never
            unpickled; re-train the run).
        RunFolderError: its ``config.yaml``, ``settings.json`` or ``result.json`` is damaged
            (the message names the file), checked before anything runs.
    """
    run = Path(run)
    if not run.is_dir():
        raise FileNotFoundError(f"test-phase folder {run} does not exist")
    config = load_run_config(run)
    models = available_runs(run)
    if seed is None:
        seeds = [s for a, s in models if a == agent]
        if not seeds and _runs_with(run, "model.zip", agent):
            raise FileNotFoundError(
                f"the {agent!r} runs in {run} have only model.zip, SB3's pickled format, which "
                "ermrl never loads (a crafted one runs code); re-train them with "
                "`ermrl test --overwrite`"
            )
        if not seeds:
            raise FileNotFoundError(
                f"no saved model of agent {agent!r} in {run}; available: {_describe(models)}"
            )
        seed = seeds[0]
    folder = run_dir(run, agent, seed)
    model_path = folder / "model.zip"
    from ermrl.agents import policy_path, stats_path

    weights = policy_path(model_path)
    if not weights.is_file():
        if model_path.is_file():
            raise FileNotFoundError(
                f"{weights} not found: {model_path} alone is SB3's pickled format, which ermrl "
                "never loads (a crafted one runs code); re-train this run with "
                "`ermrl test --overwrite`"
            )
        raise FileNotFoundError(
            f"{weights} not found (was the test phase run with --no-save-models?); "
            f"available: {_describe(models)}"
        )

    settings_path = folder / "settings.json"
    settings = read_run_settings(settings_path) if settings_path.is_file() else {}
    ppo = settings.get("ppo") or config.get("ppo")
    ppo_source = settings_path if settings.get("ppo") else run / "config.yaml"
    normalize_path: Path | None = stats_path(model_path)
    if not normalize_path.is_file():  # type: ignore[union-attr]
        if isinstance(ppo, dict) and ppo.get("normalize"):
            raise FileNotFoundError(
                f"{normalize_path} not found: the run trained with normalize (VecNormalize), "
                "and its policy cannot be replayed without the statistics"
            )
        normalize_path = None
    reservoirs = None
    task = config.get("task") or {}
    # The mask this agent trained with: its own (ppo-full: "all"), else the folder's task's.
    observe = (config.get("agent_observe") or {}).get(agent) or task.get("observe", "all")
    if not isinstance(ppo, dict):
        raise FileNotFoundError(
            f"no PPO settings for {folder} (neither its settings.json nor {run}/config.yaml "
            "has a 'ppo' entry): the policy cannot be rebuilt"
        )
    result_path = folder / "result.json"
    reservoirs_source = result_path
    if result_path.is_file():
        result = read_run_result(result_path)
        reservoirs = result.get("reservoirs")
        observe = result.get("observe") or observe
    agents = config.get("agents") or {}
    if reservoirs is None and agent in agents:
        reservoirs = agents[agent]
        reservoirs_source = run / "config.yaml"
    if not isinstance(observe, str):
        raise RunFolderError(result_path, f"'observe' is not a mask name: {observe!r}")
    encoder = None
    if reservoirs is not None:
        if not isinstance(reservoirs, list) or not all(isinstance(r, dict) for r in reservoirs):
            raise RunFolderError(
                reservoirs_source, f"the {agent} reservoirs are not a list of mappings"
            )
        encoder = {**dict(config.get("encoder") or {}), "reservoirs": reservoirs}
    _check_config("ppo", ppo, ppo_source)
    if encoder is not None:
        _check_config("encoder", encoder, reservoirs_source)
    return TrainedAgent(
        run=run,
        agent=agent,
        seed=int(seed),
        env_id=str(task["env_id"]),
        observe=str(observe),
        encoder=encoder,
        model_path=model_path,
        normalize_path=normalize_path,
        policy_path=weights,
        ppo=dict(ppo),
    )


def rollout(
    trained: TrainedAgent,
    *,
    max_steps: int | None = None,
    deterministic: bool = True,
    env_seed: int | None = None,
    render: bool = False,
    fast_render: bool = False,
) -> Rollout:
    """Run one episode of a trained agent and record what happened.

    The environment is built as in training (mask, ``Monitor``, reservoir with the run's
    weights). The episode is seeded with the run's evaluation seed unless ``env_seed`` is given.

    Args:
        trained: From [`load_trained_agent`][ermrl.analysis.load_trained_agent].
        max_steps: Stop after this many steps (default: the whole episode).
        deterministic: Use the policy's mean action (``False``: sample).
        env_seed: Seed of the episode's initial state.
        render: Record RGB frames (MuJoCo needs a GL backend: see
            [`select_gl_backend`][ermrl.analysis.select_gl_backend]).
        fast_render: Turn off MuJoCo's shadows and reflections (about 5x faster with a
            software renderer).

    Returns:
        The recorded episode.
    """
    from ermrl.agents import (
        derive_seeds,
        frozen_normalize_env,
        load_normalize_stats,
        load_policy,
        make_vec_env,
    )
    from ermrl.config import EncoderConfig, PPOConfig, TaskConfig, from_dict
    from ermrl.learners import get_learner

    if trained.policy_path is None or trained.ppo is None:
        raise ValueError("rollout needs the plain policy file and PPO settings")
    ppo = from_dict(PPOConfig, trained.ppo)

    seeds = derive_seeds(trained.seed)
    task = TaskConfig(env_id=trained.env_id, observe=trained.observe)  # type: ignore[arg-type]
    encoder = None if trained.encoder is None else from_dict(EncoderConfig, trained.encoder)
    venv = make_vec_env(
        task,
        1,
        seeds.eval_env if env_seed is None else env_seed,
        encoder,
        seeds.reservoir,
        render_mode="rgb_array" if render else None,
    )
    # The policy sees what it saw in training: with normalize, through VecNormalize frozen at
    # the statistics training ended with (the rollout still records raw observations/rewards).
    policy_env = venv
    normalized = trained.normalize_path is not None
    try:
        if trained.normalize_path is not None:
            policy_env = frozen_normalize_env(venv, load_normalize_stats(trained.normalize_path))
        policy_env = get_learner(ppo.learner).wrap_env(policy_env, ppo)  # a frame stack
        try:
            model = load_policy(trained.policy_path, ppo, policy_env)
        except ValueError as err:  # a damaged or foreign policy.pt, or settings that do not build
            where = str(trained.policy_path)
            text = str(err).removeprefix(where).lstrip(": ")
            raise RunFolderError(where, text) from None
        obs_dim = int(np.prod(venv.observation_space.shape))
        base = venv.venv if encoder is not None else venv
        unwrapped = base.envs[0].unwrapped
        dt = _env_dt(unwrapped)
        fps = float(base.envs[0].metadata.get("render_fps") or (1 / dt if dt else 30.0))
        obs = policy_env.reset()
        if render and fast_render:
            _plain_scene(unwrapped)
        state_width = int(venv.get_states().shape[1]) if encoder is not None else 0
        observations, actions, rewards, states, frames = [], [], [], [], []
        ended = False
        step = 0
        hidden = None
        while max_steps is None or step < max_steps:
            if encoder is not None:
                observations.append(venv.get_inputs()[0, : venv.obs_dim].copy())
                states.append(venv.get_states()[0].copy())
            else:
                raw = policy_env.get_original_obs() if normalized else obs
                # The newest observation: a frame stack puts it last.
                observations.append(np.asarray(raw[0], dtype=np.float64)[-obs_dim:].copy())
            if render:
                frames.append(np.asarray(base.envs[0].render()).copy())
            # A recurrent policy carries its hidden state (PPO ignores state and episode_start).
            action, hidden = model.predict(
                obs, state=hidden, episode_start=np.array([step == 0]), deterministic=deterministic
            )
            obs, reward, done, _ = policy_env.step(action)
            if normalized:
                reward = policy_env.get_original_reward()  # VecNormalize casts to float32
            if encoder is None and isinstance(hidden, np.ndarray):
                # A learner's own network (hebbian's h, rtu-ppo's (c1, c2)): the state the
                # action was computed from, as a reservoir's.
                states.append(np.asarray(hidden[0], dtype=np.float64).reshape(-1).copy())
            actions.append(np.atleast_1d(np.asarray(action[0], dtype=np.float64)))
            rewards.append(float(reward[0]))
            step += 1
            if done[0]:
                ended = True
                break
    finally:
        policy_env.close()
    n = len(rewards)
    # The encoder's whole state as its wrapper holds it (an NVAR's: its delay line), else the
    # learner's own.
    n_units = len(states[0]) if states else state_width
    return Rollout(
        observations=np.asarray(observations, dtype=np.float64).reshape(n, -1),
        actions=np.asarray(actions, dtype=np.float64).reshape(n, -1),
        rewards=np.asarray(rewards, dtype=np.float64),
        states=np.asarray(states, dtype=np.float64).reshape(n, n_units),
        frames=frames,
        dt=dt,
        fps=fps,
        ended=ended,
    )


def _check_config(kind: str, data: dict[str, Any], source: Path) -> None:
    """Refuse PPO or encoder settings that do not build (``RunFolderError`` naming ``source``)."""
    from ermrl.config import EncoderConfig, PPOConfig, from_dict

    cls = PPOConfig if kind == "ppo" else EncoderConfig
    try:
        from_dict(cls, data)
    except Exception as err:  # any damage: wrong types, unknown values, bad nesting
        detail = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise RunFolderError(source, f"its {kind} settings do not build: {detail}") from None


def _plain_scene(env: Any) -> None:
    """Turn off shadows and reflections of a MuJoCo env's offscreen renderer (best effort)."""
    renderer = getattr(env, "mujoco_renderer", None)
    if renderer is None:
        return
    try:
        import mujoco

        viewer = renderer._get_viewer("rgb_array")
        viewer.scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        viewer.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
    except Exception:  # another renderer layout: keep the default look
        return


def _env_dt(env: Any) -> float | None:
    for name in ("dt", "tau"):
        value = getattr(env, name, None)
        if isinstance(value, (int, float)) and value > 0:
            return float(value)
    return None


def _describe(models: list[tuple[str, int]]) -> str:
    if not models:
        return "none (no policy.pt under agents/*/seed_*/)"
    return ", ".join(f"{a} seed {s}" for a, s in models)
