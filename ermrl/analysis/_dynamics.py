"""Reservoir dynamics: record an episode of a trained agent, plot states and power spectra.

The ER-MRL hypothesis is that evolved reservoirs produce oscillations that help locomotion. An
episode of a trained ``res-ppo`` agent is recorded (observations, actions, rewards and the
reservoir states the policy saw), saved as arrays, and analysed with a power spectrum.

Power spectrum of a signal ``x`` of shape ``(T, d)`` sampled every ``dt`` seconds: Welch's
method, i.e. the periodograms of half-overlapping Hann-windowed segments of ``nperseg`` steps
(256 by default, or ``T``), each linearly detrended, are averaged; the power spectral density of
each column is then averaged over the ``d`` columns. The dominant frequency is the strongest
peak of that mean spectrum (a local maximum at least twice as high as its surroundings), so the
power that a decaying start-of-episode transient puts into the lowest bins is not taken for an
oscillation. The frequency resolution is ``1 / (nperseg dt)``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ermrl.analysis._style import (
    AGENT_LABELS,
    PaperFigure,
    agent_color,
    empty_axes,
    new_figure,
    paper_style,
    save_figure,
    task_title,
)

__all__ = [
    "DynamicsRecording",
    "dominant_frequency",
    "dynamics_figure",
    "gait_frequency",
    "has_joints",
    "joint_angles",
    "power_spectrum",
    "record_dynamics",
    "spectrum_comparison_figure",
    "spectrum_figure",
    "spectrum_summary",
    "write_dynamics",
]

_MAX_OBS_LINES = 10


@dataclass
class DynamicsRecording:
    """One recorded episode of a trained agent.

    Attributes:
        observations: Raw (masked) observations, shape ``(T, obs_dim)``.
        actions: Actions, shape ``(T, act_dim)``.
        rewards: Rewards, shape ``(T,)``.
        states: Reservoir states the policy saw before each action, shape ``(T, units)``
            (``(T, 0)`` for plain PPO).
        dt: Seconds of simulated time per step (NaN when unknown: spectra are then per step).
        env_id: Gymnasium id.
        observe: Observation mask.
        agent: Agent name.
        seed: The run's seed.
        obs_indices: Index of each observation column in the env's full observation,
            shape ``(obs_dim,)``.
    """

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    states: np.ndarray
    dt: float
    env_id: str
    observe: str
    agent: str
    seed: int
    obs_indices: np.ndarray

    @property
    def n_steps(self) -> int:
        return int(len(self.rewards))

    @property
    def episode_return(self) -> float:
        return float(np.sum(self.rewards))

    @property
    def time(self) -> np.ndarray:
        """Time of each step, shape ``(T,)``: seconds, or steps when ``dt`` is unknown."""
        step = self.dt if math.isfinite(self.dt) else 1.0
        return np.arange(self.n_steps) * step

    def save(self, path: str | Path) -> Path:
        """Write the arrays and metadata to an ``.npz`` file."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            path,
            observations=self.observations,
            actions=self.actions,
            rewards=self.rewards,
            states=self.states,
            obs_indices=self.obs_indices,
            dt=np.float64(self.dt),
            meta=np.array(
                json.dumps(
                    {
                        "env_id": self.env_id,
                        "observe": self.observe,
                        "agent": self.agent,
                        "seed": self.seed,
                    }
                )
            ),
        )
        return path

    @classmethod
    def load(cls, path: str | Path) -> DynamicsRecording:
        """Read a recording written by [`save`][ermrl.analysis.DynamicsRecording.save].

        Raises:
            ermrl.envs.UnknownEnvError: its env id is not a registered id (never imported).
        """
        from ermrl.envs import check_registered_env_id

        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            check_registered_env_id(meta["env_id"], path)  # never import a module it names
            return cls(
                observations=data["observations"],
                actions=data["actions"],
                rewards=data["rewards"],
                states=data["states"],
                dt=float(data["dt"]),
                env_id=meta["env_id"],
                observe=meta["observe"],
                agent=meta["agent"],
                seed=int(meta["seed"]),
                obs_indices=data["obs_indices"],
            )


def record_dynamics(
    run: str | Path,
    agent: str = "res-ppo",
    seed: int | None = None,
    *,
    max_steps: int | None = None,
    deterministic: bool = True,
    env_seed: int | None = None,
) -> DynamicsRecording:
    """Run a trained agent of a test-phase folder for one episode and record it.

    Args:
        run: The test-phase folder (``--out`` of ``ermrl test``).
        agent: Agent name (a reservoir agent for states: ``res-ppo`` or ``random-res-ppo``).
        seed: The run's seed (default: the smallest seed with a saved model).
        max_steps: Stop after this many steps (default: the whole episode).
        deterministic: Use the policy's mean action.
        env_seed: Seed of the episode (default: the run's evaluation seed).

    Returns:
        The recording.

    Raises:
        FileNotFoundError: no saved model for that agent and seed.
    """
    from ermrl.analysis._replay import load_trained_agent, rollout

    trained = load_trained_agent(run, agent, seed)
    episode = rollout(trained, max_steps=max_steps, deterministic=deterministic, env_seed=env_seed)
    return DynamicsRecording(
        observations=episode.observations,
        actions=episode.actions,
        rewards=episode.rewards,
        states=episode.states,
        dt=math.nan if episode.dt is None else float(episode.dt),
        env_id=trained.env_id,
        observe=trained.observe,
        agent=trained.agent,
        seed=trained.seed,
        obs_indices=_obs_indices(trained.env_id, trained.observe, episode.observations.shape[1]),
    )


def power_spectrum(
    signals: np.ndarray, dt: float = 1.0, nperseg: int = 256
) -> tuple[np.ndarray, np.ndarray]:
    """Welch power spectral density of each column (linearly detrended Hann segments).

    Args:
        signals: Shape ``(T, d)`` (or ``(T,)``), sampled every ``dt``.
        dt: Sampling interval (seconds; 1 for "per step").
        nperseg: Segment length in steps (``min(nperseg, T)`` is used).

    Returns:
        ``freqs`` of shape ``(F,)`` (Hz when ``dt`` is in seconds) and ``power`` of shape
        ``(F, d)``, with ``F = min(nperseg, T) // 2 + 1``.
    """
    from scipy.signal import welch

    x = np.asarray(signals, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    n = x.shape[0]
    if n < 4 or x.shape[1] == 0:
        return np.zeros(1), np.zeros((1, x.shape[1]))
    freqs, power = welch(
        x, fs=1.0 / dt, window="hann", nperseg=min(nperseg, n), detrend="linear", axis=0
    )
    # A constant column has no spectrum (only rounding noise): give it exactly zero power.
    constant = np.ptp(x, axis=0) <= 1e-12 * (1.0 + np.abs(x).max(axis=0))
    power[:, constant] = 0.0
    return freqs, power


def dominant_frequency(
    freqs: np.ndarray, power: np.ndarray, min_prominence_decades: float = 0.3
) -> float:
    """Frequency of the strongest peak of the mean power spectrum (NaN if it has none).

    A peak is a local maximum of ``log10(mean power)`` above 0 Hz standing out from its
    surroundings by at least ``min_prominence_decades`` (0.3: a factor of 2), so it completes
    at least two cycles in the window (the lowest bin cannot be a local maximum). The slow
    decay of a start-of-episode transient piles power into the lowest bins without a peak, so
    it is not mistaken for an oscillation; nor is the largest bin of a spectrum without a peak
    (on a short episode, that is only the spectral resolution): both give NaN.

    Args:
        freqs: Shape ``(F,)``, from [`power_spectrum`][ermrl.analysis.power_spectrum].
        power: Shape ``(F, d)`` or ``(F,)``.
        min_prominence_decades: Minimum prominence of a peak, in decades of power.
    """
    from scipy.signal import find_peaks

    mean = power.mean(axis=1) if power.ndim == 2 else power
    if len(freqs) < 3 or not np.any(mean[1:] > 0):
        return math.nan
    positive = mean[1:]
    log_power = np.log10(np.maximum(positive, positive[positive > 0].min() * 1e-6))
    peaks, _ = find_peaks(log_power, prominence=min_prominence_decades)
    if not len(peaks):
        return math.nan
    best = peaks[int(np.argmax(positive[peaks]))]
    return float(freqs[1 + best])


def _peak_text(frequency: float, unit: str) -> str:
    return f"peak {frequency:.3g} {unit}" if math.isfinite(frequency) else "no peak"


def spectrum_summary(recording: DynamicsRecording) -> dict[str, Any]:
    """Dominant frequency and period of the reservoir states, observations and actions.

    Returns:
        ``{"dt": ..., "frequency_unit": "Hz" | "1/step", "resolution": ..., "signals": {name:
        {"dominant_frequency": ..., "dominant_period": ..., "dims": ...}}}``.
    """
    dt = recording.dt if math.isfinite(recording.dt) else 1.0
    out: dict[str, Any] = {
        "env_id": recording.env_id,
        "observe": recording.observe,
        "agent": recording.agent,
        "seed": recording.seed,
        "n_steps": recording.n_steps,
        "episode_return": recording.episode_return,
        "dt": recording.dt if math.isfinite(recording.dt) else None,
        "frequency_unit": "Hz" if math.isfinite(recording.dt) else "1/step",
        "resolution": (
            1.0 / (min(256, recording.n_steps) * dt) if recording.n_steps >= 4 else None
        ),
        "signals": {},
    }
    for name, values in _signals(recording).items():
        freqs, power = power_spectrum(values, dt)
        f = dominant_frequency(freqs, power)
        out["signals"][name] = {
            "dominant_frequency": None if not math.isfinite(f) else f,
            "dominant_period": None if not math.isfinite(f) or f == 0 else 1.0 / f,
            "dims": int(values.shape[1]),
        }
    return out


def dynamics_figure(
    recording: DynamicsRecording,
    *,
    n_units: int = 20,
    window_steps: int | None = 200,
    title: str | None = None,
) -> PaperFigure:
    """Observations, actions and the first ``n_units`` reservoir units over time.

    Args:
        recording: From [`record_dynamics`][ermrl.analysis.record_dynamics].
        n_units: Reservoir units shown (the first ones).
        window_steps: Steps shown from the start of the episode (``None``: all).
        title: Figure title (default names the agent, env, mask and seed).

    Returns:
        The figure.
    """
    n = recording.n_steps if window_steps is None else min(recording.n_steps, window_steps)
    t = recording.time[:n]
    unit = "s" if math.isfinite(recording.dt) else "steps"
    has_states = recording.states.shape[1] > 0
    with paper_style():
        fig, axes = new_figure(
            3 if has_states else 2,
            1,
            figsize=(8.0, 8.0 if has_states else 5.5),
            sharex=True,
            gridspec_kw={"height_ratios": [1.0, 0.8, 1.1] if has_states else [1.0, 0.8]},
        )
        obs_ax, act_ax = axes[0], axes[1]
        obs = recording.observations[:n]
        labels = [f"obs[{int(i)}]" for i in recording.obs_indices]
        if obs.shape[1] <= _MAX_OBS_LINES:
            for k in range(obs.shape[1]):
                obs_ax.plot(t, obs[:, k], lw=1.0, label=labels[k], color=f"C{k % 10}")
            obs_ax.legend(
                frameon=False, loc="upper left", bbox_to_anchor=(1.0, 1.02), title="Observation"
            )
            obs_ax.set_ylabel(f"Observation\n({_obs_unit(recording.observe)})")
        else:
            z = (obs - obs.mean(axis=0)) / (obs.std(axis=0) + 1e-12)
            image = obs_ax.imshow(
                z.T,
                aspect="auto",
                origin="lower",
                extent=(t[0], t[-1] if n > 1 else 1, -0.5, obs.shape[1] - 0.5),
                cmap="RdBu_r",
                vmin=-3,
                vmax=3,
                interpolation="nearest",
            )
            fig.colorbar(image, ax=obs_ax, pad=0.01).set_label("z-score")
            obs_ax.set_ylabel("Observation index")
            obs_ax.yaxis.get_major_locator().set_params(integer=True)
            obs_ax.grid(False)
        obs_ax.set_title("Observations", loc="left", fontsize=10)

        act = recording.actions[:n]
        for k in range(act.shape[1]):
            act_ax.plot(t, act[:, k], lw=1.0, label=f"a[{k}]", color=f"C{k % 10}")
        act_ax.set_ylabel("Action")
        act_ax.set_title("Actions", loc="left", fontsize=10)
        if act.shape[1] <= _MAX_OBS_LINES:
            act_ax.legend(
                frameon=False, loc="upper left", bbox_to_anchor=(1.0, 1.02), title="Action"
            )

        if has_states:
            res_ax = axes[2]
            shown = min(n_units, recording.states.shape[1])
            states = recording.states[:n, :shown]
            limit = float(np.quantile(np.abs(states), 0.99)) if states.size else 1.0
            limit = limit if limit > 0 else 1.0
            image = res_ax.imshow(
                states.T,
                aspect="auto",
                origin="lower",
                extent=(t[0], t[-1] if n > 1 else 1, -0.5, shown - 0.5),
                cmap="RdBu_r",
                vmin=-limit,
                vmax=limit,
                interpolation="nearest",
            )
            res_ax.yaxis.get_major_locator().set_params(integer=True)
            bar = fig.colorbar(image, ax=res_ax, pad=0.01)
            bar.set_label("Unit state")
            res_ax.set_ylabel("Reservoir unit")
            res_ax.set_title(
                f"First {shown} of {recording.states.shape[1]} reservoir units",
                loc="left",
                fontsize=10,
            )
            res_ax.grid(False)
        axes[-1].set_xlabel(f"Time ({unit})")
        if title is None:
            span = f"first {t[-1] + (t[1] - t[0] if n > 1 else 0):.3g} {unit}" if n else ""
            title = (
                f"{AGENT_LABELS.get(recording.agent, recording.agent)}, seed {recording.seed}: "
                f"{task_title(recording.env_id, recording.observe)} ({span} of the episode)"
            )
        fig.suptitle(title)
    return fig


def spectrum_figure(recording: DynamicsRecording, *, title: str | None = None) -> PaperFigure:
    """Power spectra of the reservoir states, observations and actions of one episode.

    Each curve is the power averaged over the signal's dimensions, divided by its maximum above
    0 Hz; dashed lines mark the dominant frequencies.

    Args:
        recording: From [`record_dynamics`][ermrl.analysis.record_dynamics].
        title: Figure title.

    Returns:
        The figure.
    """
    dt = recording.dt if math.isfinite(recording.dt) else 1.0
    unit = "Hz" if math.isfinite(recording.dt) else "cycles per step"
    colors = {
        "reservoir states": "tab:orange",
        "observations": "tab:blue",
        "joint angles (gait)": "black",
        "actions": "tab:green",
    }
    with paper_style():
        fig, ax = new_figure(figsize=(7.0, 4.4))
        if recording.n_steps < 4:
            empty_axes(ax, "episode too short for a spectrum")
            return fig
        for name, values in _signals(recording).items():
            freqs, power = power_spectrum(values, dt)
            mean = power.mean(axis=1)
            peak = float(np.max(mean[1:])) if len(mean) > 1 else 0.0
            if peak <= 0 or not np.isfinite(peak):
                continue
            f = dominant_frequency(freqs, power)
            color = colors.get(name)
            ax.plot(
                freqs[1:],
                mean[1:] / peak,
                color=color,
                lw=1.2,
                label=f"{name} (d = {values.shape[1]}): " + _peak_text(f, unit),
            )
            if math.isfinite(f):
                ax.axvline(f, color=color, ls="--", lw=1.0, alpha=0.8)
        ax.set_yscale("log")
        ax.set_xlabel(f"Frequency ({unit})")
        ax.set_ylabel("Relative power spectral density\n(mean over dimensions, peak = 1)")
        ax.set_xlim(0, (0.5 / dt))
        ax.legend(frameon=False, loc="upper right")
        if title is None:
            title = (
                f"Power spectrum, {AGENT_LABELS.get(recording.agent, recording.agent)}, "
                f"seed {recording.seed}\n{task_title(recording.env_id, recording.observe)}, "
                f"{recording.n_steps}-step episode"
            )
        ax.set_title(title)
    return fig


def spectrum_comparison_figure(
    recordings: Mapping[str, DynamicsRecording], *, title: str | None = None
) -> PaperFigure:
    """Reservoir power spectra of several agents (e.g. evolved vs unevolved reservoir).

    Args:
        recordings: ``{agent: recording}``; agents without reservoir states are skipped.
        title: Figure title.

    Returns:
        The figure.
    """
    with paper_style():
        fig, ax = new_figure(figsize=(7.0, 4.4))
        drawn = 0
        first: DynamicsRecording | None = None
        for index, (agent, rec) in enumerate(recordings.items()):
            if rec.states.shape[1] == 0 or rec.n_steps < 4:
                continue
            first = first or rec
            dt = rec.dt if math.isfinite(rec.dt) else 1.0
            freqs, power = power_spectrum(rec.states, dt)
            mean = power.mean(axis=1)
            peak = float(np.max(mean[1:]))
            if peak <= 0:
                continue
            f = dominant_frequency(freqs, power)
            unit = "Hz" if math.isfinite(rec.dt) else "cycles/step"
            color = agent_color(agent, index)
            ax.plot(
                freqs[1:],
                mean[1:] / peak,
                color=color,
                lw=1.2,
                label=f"{AGENT_LABELS.get(agent, agent)}: " + _peak_text(f, unit),
            )
            if math.isfinite(f):
                ax.axvline(f, color=color, ls="--", lw=1.0, alpha=0.8)
            drawn += 1
        if not drawn or first is None:
            empty_axes(ax, "no reservoir agent recorded")
            return fig
        # The gait of the first (evolved) agent's learned policy: its joint-angle spectrum.
        gait = gait_frequency(first)
        if math.isfinite(gait):
            unit_short = "Hz" if math.isfinite(first.dt) else "cycles/step"
            ax.axvline(
                gait,
                color="black",
                ls=":",
                lw=1.6,
                label=f"gait of {AGENT_LABELS.get(first.agent, first.agent)} "
                f"(joint angles): {gait:.3g} {unit_short}",
            )
        unit = "Hz" if math.isfinite(first.dt) else "cycles per step"
        ax.set_yscale("log")
        ax.set_xlabel(f"Frequency ({unit})")
        ax.set_ylabel("Relative power spectral density\nof the reservoir states (mean over units)")
        ax.set_xlim(0, 0.5 / (first.dt if math.isfinite(first.dt) else 1.0))
        ax.legend(frameon=False, loc="upper right")
        ax.set_title(
            title
            or f"Reservoir power spectra, seed {first.seed}\n"
            f"{task_title(first.env_id, first.observe)}"
        )
    return fig


def write_dynamics(
    recording: DynamicsRecording,
    folder: str | Path,
    *,
    n_units: int = 20,
    window_steps: int | None = 200,
) -> dict[str, Path]:
    """Save a recording's arrays, figures and dominant frequencies in ``folder``.

    Files are named ``<agent>_seed<seed>_{episode.npz, dynamics.png, spectrum.png,
    spectrum.json}``.

    Returns:
        ``{"arrays" | "dynamics" | "spectrum" | "summary": path}``.
    """
    folder = Path(folder)
    stem = f"{recording.agent}_seed{recording.seed}"
    paths = {
        "arrays": recording.save(folder / f"{stem}_episode.npz"),
        "dynamics": save_figure(
            dynamics_figure(recording, n_units=n_units, window_steps=window_steps),
            folder / f"{stem}_dynamics.png",
        ),
        "spectrum": save_figure(spectrum_figure(recording), folder / f"{stem}_spectrum.png"),
    }
    summary_path = folder / f"{stem}_spectrum.json"
    summary_path.write_text(json.dumps(spectrum_summary(recording), indent=2) + "\n")
    paths["summary"] = summary_path
    return paths


# MuJoCo tasks whose bodies walk, hop or swim on joints: the only ones with a gait.
_LOCOMOTION = ("Ant", "HalfCheetah", "Hopper", "Humanoid", "Swimmer", "Walker2d")


def has_joints(env_id: str) -> bool:
    """Whether the task is MuJoCo locomotion, whose observed positions are joint angles.

    Elsewhere (CartPole's cart position and pole angle, Pendulum's angle) the positions are no
    gait, and the spectra do not call them one.
    """
    import gymnasium

    from ermrl.envs._masks import _is_mujoco_entry_point

    try:
        spec = gymnasium.spec(env_id)
    except Exception:  # an id that is not registered: no claim about its joints
        return False
    return _is_mujoco_entry_point(spec) and spec.name in _LOCOMOTION


def joint_angles(recording: DynamicsRecording) -> np.ndarray | None:
    """The position part of the recorded observations of a locomotion task (joint angles and
    body orientation).

    Its spectrum is the gait: the frequency at which a locomotion policy moves its joints.

    Returns:
        Shape ``(T, k)``; ``None`` when the task is not MuJoCo locomotion
        ([`has_joints`][ermrl.analysis.has_joints]), the episode's observation holds no positions
        (``observe="velocities"``) or the task has no known position/velocity split.
    """
    if not has_joints(recording.env_id):
        return None
    obs = recording.observations
    if recording.observe == "positions":
        return obs
    if recording.observe != "all":
        return None
    try:
        from ermrl.envs import observation_indices

        indices = observation_indices(recording.env_id, "positions")
    except Exception:  # a task without a known split
        return None
    if not indices or max(indices) >= obs.shape[1]:
        return None
    return obs[:, list(indices)]


def gait_frequency(recording: DynamicsRecording) -> float:
    """Dominant frequency of the joint angles ([`joint_angles`][ermrl.analysis.joint_angles]); NaN
    when unknown."""
    angles = joint_angles(recording)
    if angles is None or recording.n_steps < 4:
        return math.nan
    dt = recording.dt if math.isfinite(recording.dt) else 1.0
    freqs, power = power_spectrum(angles, dt)
    return dominant_frequency(freqs, power)


def _signals(recording: DynamicsRecording) -> dict[str, np.ndarray]:
    out = {}
    if recording.states.shape[1] > 0:
        out["reservoir states"] = recording.states
    out["observations"] = recording.observations
    angles = joint_angles(recording)
    if angles is not None and recording.observe == "all":
        out["joint angles (gait)"] = angles
    out["actions"] = recording.actions
    return out


def _obs_unit(observe: str) -> str:
    return {
        "velocities": "velocities: m/s or rad/s",
        "positions": "positions: m, rad or cos/sin",
    }.get(observe, "env units")


def _obs_indices(env_id: str, observe: str, obs_dim: int) -> np.ndarray:
    try:
        from ermrl.envs import observation_indices

        indices = observation_indices(env_id, observe)  # type: ignore[arg-type]
    except Exception:  # an env without a known split: plain positions
        indices = None
    if indices is None or len(indices) != obs_dim:
        return np.arange(obs_dim)
    return np.asarray(indices, dtype=np.int64)
