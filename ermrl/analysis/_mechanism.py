"""The mechanism behind an evolved reservoir's gain on a locomotion task: oscillations at the
gait, or leaky integration?

ER-MRL explains its gains by "oscillatory dynamics that facilitate the learning of locomotion".
The reservoirs evolution selects can have a spectral radius near 0, where the echo state update
``x <- (1 - lr) x + lr tanh(W x + Win u + b)`` is little more than a leaky integrator of a random
projection of the input. Two measurements tell the two apart on a task.

**Spectra.** One recorded episode of the trained ``res-ppo`` agent
([`record_dynamics`][ermrl.analysis.record_dynamics]) gives the reservoir's input stream
``u_t = [observation_t, previous action, previous reward]`` (the encoding of
[`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv]). The same stream drives three reservoirs, each
built with the weights of every test seed of ``res-ppo``
([`reservoir_spectra`][ermrl.analysis.reservoir_spectra]): the evolved one (``res-ppo``'s), the
unevolved reference (``random-res-ppo``'s) and the evolved one with ``W = 0`` (``leaky-res-ppo``'s:
the same ``Win``, bias and leak rate). Driving all three with one stream isolates the reservoir from
the policy. For each, and for the episode's joint angles
([`joint_angles`][ermrl.analysis.joint_angles]): the Welch spectrum
([`power_spectrum`][ermrl.analysis.power_spectrum], mean over units), its dominant frequency
([`dominant_frequency`][ermrl.analysis.dominant_frequency]), and the share of its power above 0 Hz
inside the *gait band*: the joint angles' dominant frequency (the gait) ± `SpectralCriterion.band`
of it, at least ± one frequency bin ([`band_share`][ermrl.analysis.band_share]).

**The spectral criterion** ([`SpectralCriterion`][ermrl.analysis.SpectralCriterion]). The evolved
reservoir *carries a gait-frequency component that its W = 0 ablation lacks* on one weight seed when
its share in the gait band is at least `SpectralCriterion.ratio` times the ablation's and its own
dominant frequency lies inside the band; on the task, when that holds on more than half of the
weight seeds.

**The verdict** ([`mechanism_verdict`][ermrl.analysis.mechanism_verdict]) combines the criterion
with the comparison ``res-ppo − leaky-res-ppo`` of the verdict layer
([`judge`][ermrl.analysis.judge]: Holm over the page's family, both intervals):

- *oscillatory dynamics* (supported): the ablation learns worse (the comparison is supported) and
  the evolved reservoir carries a gait-frequency component its ablation lacks;
- *leaky integration suffices* (supported): the ablation learns better (the comparison is
  contradicted), or as well: the comparison is equivalent within the task's margin (two
  one-sided tests at its adjusted level, the rule's ``equivalence:`` block;
  [`equivalence_outcome`][ermrl.analysis.equivalence_outcome]);
- *not shown either way*: the ablation is neither shown to learn worse nor shown equivalent
  (or the rule states no margin for the task); the verdict says how much worse it could still
  be (the larger upper end of the adjusted Welch and bootstrap intervals);
- *inconclusive*: the ablation learns worse, but the spectra show no gait-frequency component it
  lacks, or have not been recorded, or the task has no gait; or the comparison could not be
  tested (fewer than 2 runs);
- *not run yet*: ``leaky-res-ppo`` (or ``res-ppo``) has no finished run on the task.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from ermrl.analysis._dynamics import (
    DynamicsRecording,
    dominant_frequency,
    joint_angles,
    power_spectrum,
)
from ermrl.analysis._verdicts import (
    EQUIVALENT,
    NOT_RUN,
    NOT_SHOWN,
    Comparison,
    Question,
    VerdictRule,
    equivalence_text,
    not_run,
)

__all__ = [
    "ABLATED",
    "MECHANISM_FILE",
    "MECHANISM_LABELS",
    "MECHANISM_SPECTRA_FILE",
    "MechanismVerdict",
    "ReservoirSpectra",
    "SpectralCriterion",
    "SpectralOutcome",
    "band_share",
    "describe_mechanism",
    "gait_segment",
    "lowest_bin",
    "mechanism_figure",
    "mechanism_question",
    "mechanism_reservoirs",
    "mechanism_table",
    "mechanism_verdict",
    "read_mechanism",
    "report_rule",
    "reservoir_inputs",
    "reservoir_spectra",
    "spectral_outcome",
    "without_gait",
    "write_mechanism",
]

EVOLVED = "res-ppo"
UNEVOLVED = "random-res-ppo"
#: The evolved reservoir with ``W = 0`` (``ReservoirParams.ablation = "leaky"``).
ABLATED = "leaky-res-ppo"
#: The reservoirs a mechanism compares, in the order the tables show them.
RESERVOIRS = (EVOLVED, UNEVOLVED, ABLATED)
#: The signal the gait is read from.
JOINTS = "joint angles"
#: A report's per-seed spectra summary and its mean spectra (in its ``dynamics/`` folder; the
#: reproduction page reads them from a task's published ``report/dynamics/``).
MECHANISM_FILE = "mechanism.csv"
MECHANISM_SPECTRA_FILE = "mechanism_spectra.csv"
#: The mechanism labels of a task.
MECHANISM_LABELS = (
    "oscillatory dynamics",
    "leaky integration suffices",
    NOT_SHOWN,
    "inconclusive",
    NOT_RUN,
)
#: Welch segment length (steps), as in [`power_spectrum`][ermrl.analysis.power_spectrum]; the whole episode
#: when the gait is slower than it resolves (`gait_segment`).
NPERSEG = 256
#: The columns every `MECHANISM_FILE` has (`read_mechanism` needs them).
REQUIRED_COLUMNS = [
    "env_id", "signal", "weight_seed", "recorded_seed", "n_steps", "dt", "frequency_unit",
    "resolution", "gait_frequency", "band_low", "band_high", "dominant_frequency",
    "share_near_gait", "replay_error",
]  # fmt: skip
#: ``lowest_bin``: the signal's power above 0 Hz is largest in the lowest non-zero frequency bin
#: (for the joint angles without a peak: a gait slower than the resolution). Files written
#: before it existed lack it; `read_mechanism` reads it as unknown.
MECHANISM_COLUMNS = [*REQUIRED_COLUMNS, "lowest_bin"]


@dataclass(frozen=True)
class SpectralCriterion:
    """When the evolved reservoir carries a gait-frequency component its W = 0 ablation lacks.

    Attributes:
        band: Half-width of the gait band, as a fraction of the gait frequency (at least one
            frequency bin).
        ratio: The evolved reservoir's share of state power in the band must be at least this
            many times the ablation's.
    """

    band: float = 0.2
    ratio: float = 2.0

    def gait_band(self, gait: float, resolution: float) -> tuple[float, float]:
        """``(low, high)`` of the band around ``gait`` (NaNs when the gait is unknown)."""
        if not (math.isfinite(gait) and gait > 0):
            return math.nan, math.nan
        half = max(self.band * gait, resolution if math.isfinite(resolution) else 0.0)
        return max(gait - half, 0.0), gait + half

    def carries(
        self,
        evolved_share: float,
        ablation_share: float,
        evolved_peak: float,
        band: Sequence[float],
    ) -> bool:
        """The criterion on one weight seed (see the module's docstring)."""
        low, high = float(band[0]), float(band[1])
        if not all(math.isfinite(v) for v in (evolved_share, ablation_share, low, high)):
            return False
        in_band = math.isfinite(evolved_peak) and low <= evolved_peak <= high
        return in_band and evolved_share > 0 and evolved_share >= self.ratio * ablation_share

    def describe(self) -> str:
        """The criterion in words, as the pages print it."""
        return (
            f"the gait band is the joint angles' dominant frequency ± {self.band:.0%} of it (at "
            "least ± one frequency bin); a reservoir's share is the share of its state power "
            f"above 0 Hz inside that band (Welch spectra, {NPERSEG}-step Hann segments, or the "
            "whole episode as one segment when the joint angles' power is largest in the lowest "
            f"frequency bin of {NPERSEG}-step ones, linearly detrended, mean over units); the evolved reservoir carries a gait-frequency "
            f"component its W = 0 ablation lacks when its share is at least {self.ratio:g}× the "
            "ablation's and its dominant frequency lies inside the band, on more than half of "
            "the weight seeds"
        )


def band_share(freqs: np.ndarray, power: np.ndarray, band: Sequence[float]) -> float:
    """Share of a spectrum's power above 0 Hz that lies inside ``band``.

    Args:
        freqs: Shape ``(F,)``, from [`power_spectrum`][ermrl.analysis.power_spectrum].
        power: Shape ``(F, d)`` (the columns are summed: the share of the total variance) or
            ``(F,)``.
        band: ``(low, high)``, inclusive.

    Returns:
        A number in [0, 1]; NaN when the band is unknown or the signal has no power.
    """
    total = power.sum(axis=1) if power.ndim == 2 else np.asarray(power, dtype=float)
    low, high = float(band[0]), float(band[1])
    above = freqs > 0
    whole = float(total[above].sum())
    if not (math.isfinite(low) and math.isfinite(high)) or not whole > 0:
        return math.nan
    tol = 1e-9 * max(high, 1e-12)
    inside = above & (freqs >= low - tol) & (freqs <= high + tol)
    return float(total[inside].sum() / whole)


def lowest_bin(freqs: np.ndarray, power: np.ndarray) -> bool:
    """Whether a spectrum's power above 0 Hz is largest in its lowest non-zero frequency bin.

    Such a signal varies more slowly than the spectrum resolves: a peak there cannot be told
    from a trend ([`dominant_frequency`][ermrl.analysis.dominant_frequency] gives none).

    Args:
        freqs: Shape ``(F,)``, from [`power_spectrum`][ermrl.analysis.power_spectrum].
        power: Shape ``(F, d)`` (mean over columns) or ``(F,)``.
    """
    mean = power.mean(axis=1) if power.ndim == 2 else np.asarray(power, dtype=float)
    above = mean[np.asarray(freqs) > 0]
    return bool(len(above) >= 2 and above.max() > 0 and int(np.argmax(above)) == 0)


def gait_segment(angles: np.ndarray | None, dt: float) -> int:
    """The Welch segment length (steps) that resolves the gait of an episode's joint angles.

    `NPERSEG` steps, unless the joint angles have no spectral peak with them and their power
    is largest in the lowest non-zero bin ([`lowest_bin`][ermrl.analysis.lowest_bin]): the gait is
    then slower than ``1 / (NPERSEG dt)`` (Swimmer's, at dt 0.04 s, can be under 0.1 Hz), and the
    whole episode is one segment, for a resolution of ``1 / (T dt)``.

    Args:
        angles: Shape ``(T, d)`` (``None``: no joint angles, `NPERSEG`).
        dt: Sampling interval.
    """
    if angles is None or len(angles) <= NPERSEG:
        return NPERSEG
    freqs, power = power_spectrum(angles, dt, NPERSEG)
    if math.isfinite(dominant_frequency(freqs, power)) or not lowest_bin(freqs, power):
        return NPERSEG
    return len(angles)


def reservoir_inputs(recording: DynamicsRecording, encoder: Any, action_space: Any) -> np.ndarray:
    """The reservoir input stream of a recorded episode, as the env wrapper built it.

    ``u_t = [observation_t, encoded action_{t-1}, reward_{t-1} * reward_scale]`` with a zero
    action and reward at ``t = 0`` (the parts the encoder does not feed left out).

    Args:
        recording: An episode of a reservoir agent.
        encoder: Its [`EncoderConfig`][ermrl.encoders.EncoderConfig].
        action_space: The task's action space (for the action's encoding).

    Returns:
        Shape ``(T, input_dim)``.
    """
    from ermrl.encoders import ActionEncoder

    n = recording.n_steps
    parts = [np.asarray(recording.observations, dtype=np.float64).reshape(n, -1)]
    if encoder.feed_action:
        actions = ActionEncoder(action_space, dtype=np.float64)
        encoded = np.zeros((n, actions.dim))
        if n > 1:
            actions(np.asarray(recording.actions)[:-1], encoded[1:])
        parts.append(encoded)
    if encoder.feed_reward:
        rewards = np.zeros((n, 1))
        rewards[1:, 0] = np.asarray(recording.rewards, dtype=np.float64)[:-1]
        parts.append(rewards * float(encoder.reward_scale))
    return np.concatenate(parts, axis=1)


@dataclass
class ReservoirSpectra:
    """Three reservoirs driven by one recorded input stream
    ([`reservoir_spectra`][ermrl.analysis.reservoir_spectra]).

    Attributes:
        table: One row per signal (``joint angles``, then each reservoir per weight seed):
            `MECHANISM_COLUMNS` (frequencies in Hz, or cycles per step when ``dt`` is
            unknown).
        spectra: ``frequency`` and each signal's power spectral density (summed over its
            dimensions, mean over weight seeds).
        replay_error: Largest absolute difference between the recorded states and the evolved
            reservoir replayed on the recorded seed's weights (the input stream is rebuilt
            right when it is rounding only).
    """

    table: pd.DataFrame
    spectra: pd.DataFrame
    replay_error: float


def reservoir_spectra(
    recording: DynamicsRecording,
    encoder: Any,
    reservoirs: Mapping[str, Sequence[Any]],
    weight_seeds: Sequence[int],
    *,
    action_space: Any = None,
    criterion: SpectralCriterion | None = None,
) -> ReservoirSpectra:
    """Drive each reservoir with a recorded episode's input stream and measure its spectrum.

    Args:
        recording: An episode of the trained evolved agent (its states are checked against the
            replay of ``reservoirs[EVOLVED]`` at the recorded seed, when that seed is listed).
        encoder: The agent's [`EncoderConfig`][ermrl.encoders.EncoderConfig] (its reservoirs are
            replaced by each entry of ``reservoirs``).
        reservoirs: ``{name: reservoir settings}``, e.g. ``res-ppo``, ``random-res-ppo`` and
            ``leaky-res-ppo``.
        weight_seeds: Run seeds whose weights are built (each run's reservoir seed,
            [`ermrl.agents.derive_seeds`][ermrl.agents.derive_seeds]), as in training.
        action_space: The task's action space (default: the env's).
        criterion: Sets the gait band (default
            [`SpectralCriterion`][ermrl.analysis.SpectralCriterion]).

    Returns:
        The per-seed table and the mean spectra.
    """
    from ermrl.agents import derive_seeds
    from ermrl.encoders import encoder_for

    criterion = criterion or SpectralCriterion()
    if action_space is None:
        import gymnasium

        env = gymnasium.make(recording.env_id)
        action_space = env.action_space
        env.close()
    inputs = reservoir_inputs(recording, encoder, action_space)
    dt = recording.dt if math.isfinite(recording.dt) else 1.0
    angles = joint_angles(recording)
    nperseg = gait_segment(angles, dt)
    resolution = 1.0 / (min(nperseg, max(recording.n_steps, 1)) * dt)
    freqs, joints = np.zeros(1), None
    gait = math.nan
    if angles is not None and recording.n_steps >= 4:
        freqs, joints = power_spectrum(angles, dt, nperseg)
        gait = dominant_frequency(freqs, joints)
    band = criterion.gait_band(gait, resolution)
    base = {
        "env_id": recording.env_id,
        "recorded_seed": recording.seed,
        "n_steps": recording.n_steps,
        "dt": recording.dt if math.isfinite(recording.dt) else math.nan,
        "frequency_unit": "Hz" if math.isfinite(recording.dt) else "1/step",
        "resolution": resolution,
        "gait_frequency": gait,
        "band_low": band[0],
        "band_high": band[1],
    }
    rows: list[dict[str, Any]] = []
    spectra: dict[str, list[np.ndarray]] = {}
    if joints is not None:
        rows.append(_row(base, JOINTS, recording.seed, freqs, joints, band))
        spectra[JOINTS] = [joints.sum(axis=1)]
    replay_error = math.nan
    for name, params in reservoirs.items():
        config = dataclasses.replace(encoder, reservoirs=tuple(params))
        for seed in weight_seeds:
            bank = encoder_for(config).bank(config, inputs.shape[1], derive_seeds(seed).reservoir)
            states = np.asarray(bank.run(inputs), dtype=np.float64)
            if (
                name == EVOLVED
                and seed == recording.seed
                and recording.states.shape == states.shape
            ):
                replay_error = float(np.max(np.abs(states - recording.states), initial=0.0))
            freqs, power = power_spectrum(states, dt, nperseg)
            rows.append(_row(base, name, seed, freqs, power, band))
            spectra.setdefault(name, []).append(power.sum(axis=1))
    table = pd.DataFrame(rows, columns=MECHANISM_COLUMNS)
    table["replay_error"] = replay_error
    mean = pd.DataFrame({"frequency": freqs})
    for name, columns in spectra.items():
        if len(columns[0]) == len(freqs):
            mean[name] = np.mean(columns, axis=0)
    return ReservoirSpectra(table, mean, replay_error)


def mechanism_reservoirs(
    run: str | Path, seed: int, reference: Sequence[Any] = ()
) -> tuple[Any, dict[str, tuple[Any, ...]]]:
    """The evolved agent's encoder settings and the reservoirs a mechanism compares.

    Args:
        run: A test-phase folder with a saved ``res-ppo`` model.
        seed: The run whose settings are read.
        reference: The unevolved reservoirs when the folder's ``config.yaml`` does not list
            ``random-res-ppo``'s (the study's reference).

    Returns:
        ``(encoder, {name: reservoirs})``: the evolved reservoirs (``res-ppo``), the unevolved
        ones as tested (``random-res-ppo``, else ``reference``; left out when neither), and the
        evolved ones as the ``leaky-res-ppo`` agent derives them (``W = 0``).

    Raises:
        FileNotFoundError: no saved ``res-ppo`` model for that seed.
        ValueError: the agent has no reservoir.
    """
    from ermrl.analysis._replay import load_trained_agent
    from ermrl.analysis._results import load_run_config
    from ermrl.config import EncoderConfig, from_dict
    from ermrl.learners import AGENT_KINDS

    trained = load_trained_agent(run, EVOLVED, seed)
    if trained.encoder is None:
        raise ValueError(f"{EVOLVED} of {run} has no reservoir")
    encoder = from_dict(EncoderConfig, trained.encoder)
    reservoirs: dict[str, tuple[Any, ...]] = {EVOLVED: tuple(encoder.reservoirs)}
    tested = (load_run_config(run).get("agents") or {}).get(UNEVOLVED)
    if tested:
        settings = {**trained.encoder, "reservoirs": tested}
        reservoirs[UNEVOLVED] = tuple(from_dict(EncoderConfig, settings).reservoirs)
    elif reference:
        reservoirs[UNEVOLVED] = tuple(reference)
    kind = AGENT_KINDS.get(ABLATED)
    if kind is not None and kind.derive is not None:
        reservoirs[ABLATED] = tuple(kind.derive(p) for p in encoder.reservoirs)
    return encoder, reservoirs


def _row(
    base: Mapping[str, Any],
    signal: str,
    seed: int,
    freqs: np.ndarray,
    power: np.ndarray,
    band: Sequence[float],
) -> dict[str, Any]:
    return {
        **base,
        "signal": signal,
        "weight_seed": int(seed),
        "dominant_frequency": dominant_frequency(freqs, power),
        "share_near_gait": band_share(freqs, power, band),
        "lowest_bin": lowest_bin(freqs, power),
    }


def write_mechanism(spectra: ReservoirSpectra, folder: str | Path) -> dict[str, Path]:
    """Write `MECHANISM_FILE` and `MECHANISM_SPECTRA_FILE` into ``folder``."""
    from ermrl._io import write_atomic

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {"mechanism": folder / MECHANISM_FILE, "spectra": folder / MECHANISM_SPECTRA_FILE}
    write_atomic(paths["mechanism"], spectra.table.to_csv(index=False))
    write_atomic(paths["spectra"], spectra.spectra.to_csv(index=False))
    return paths


def read_mechanism(folder: str | Path) -> pd.DataFrame | None:
    """A report's `MECHANISM_FILE` (``None`` when there is none, or it is damaged)."""
    path = Path(folder) / MECHANISM_FILE
    if not path.is_file():
        return None
    try:
        table = pd.read_csv(path)
    except (OSError, ValueError):
        return None
    if not set(REQUIRED_COLUMNS) <= set(table.columns):
        return None
    if "lowest_bin" not in table.columns:
        table["lowest_bin"] = pd.NA  # written before the column existed: unknown
    return table[MECHANISM_COLUMNS]


@dataclass(frozen=True)
class SpectralOutcome:
    """The spectral criterion on one task ([`spectral_outcome`][ermrl.analysis.spectral_outcome]).

    Attributes:
        holds: ``True``/``False``; ``None`` when it cannot be judged (no gait, no spectra).
        n_seeds: Weight seeds with both the evolved reservoir and its ablation.
        n_holding: Weight seeds on which the criterion holds.
        gait_frequency: The joint angles' dominant frequency (NaN when none).
        band: The gait band.
        unit: ``Hz`` or ``1/step``.
        summary: One row per signal: dominant frequency (median over the weight seeds with a
            peak, and how many had one), and the share of power in the gait band (median, min,
            max over weight seeds).
        reason: Why it cannot be judged (empty when it can).
    """

    holds: bool | None
    n_seeds: int
    n_holding: int
    gait_frequency: float
    band: tuple[float, float]
    unit: str
    summary: pd.DataFrame
    reason: str = ""


def spectral_outcome(
    table: pd.DataFrame | None, criterion: SpectralCriterion | None = None
) -> SpectralOutcome:
    """Apply the spectral criterion to a `MECHANISM_FILE` table.

    Args:
        table: From [`reservoir_spectra`][ermrl.analysis.reservoir_spectra] or
            [`read_mechanism`][ermrl.analysis.read_mechanism] (``None``: not recorded).
        criterion: The criterion (its ``band`` is the one the table's band was measured with).

    Returns:
        The outcome; ``holds`` is ``None`` without a table, a gait, or evolved and ablated rows.
    """
    criterion = criterion or SpectralCriterion()
    empty = pd.DataFrame()
    if table is None or table.empty:
        return SpectralOutcome(
            None, 0, 0, math.nan, (math.nan, math.nan), "", empty, "spectra not recorded yet"
        )
    first = table.iloc[0]
    gait = float(first["gait_frequency"])
    band = (float(first["band_low"]), float(first["band_high"]))
    unit = str(first["frequency_unit"])
    summary = _summary(table)
    evolved = table[table["signal"] == EVOLVED].set_index("weight_seed")
    ablated = table[table["signal"] == ABLATED].set_index("weight_seed")
    seeds = [s for s in evolved.index if s in ablated.index]
    if not math.isfinite(gait):
        reason = _no_gait_reason(table)
        return SpectralOutcome(None, len(seeds), 0, gait, band, unit, summary, reason)
    if not seeds:
        reason = f"no spectra of both {EVOLVED} and {ABLATED}"
        return SpectralOutcome(None, 0, 0, gait, band, unit, summary, reason)
    holding = sum(
        criterion.carries(
            float(evolved.at[s, "share_near_gait"]),
            float(ablated.at[s, "share_near_gait"]),
            float(evolved.at[s, "dominant_frequency"]),
            band,
        )
        for s in seeds
    )
    return SpectralOutcome(holding > len(seeds) / 2, len(seeds), holding, gait, band, unit, summary)


def _no_gait_reason(table: pd.DataFrame) -> str:
    """Why a table has no gait: the joint angles' power peaks below the resolution, or nowhere."""
    joints = table[table["signal"] == JOINTS]
    value = joints["lowest_bin"].iloc[0] if not joints.empty and "lowest_bin" in joints else None
    if not (isinstance(value, (bool, np.bool_)) and value):  # unknown in older files
        return "no gait: the joint angles have no spectral peak, or the task has none"
    first = joints.iloc[0]
    unit = str(first["frequency_unit"])
    return (
        f"gait below resolution: the joint angles' power is largest in the lowest frequency bin "
        f"({float(first['resolution']):.3g} {unit}) even with the whole "
        f"{int(first['n_steps'])}-step episode as one segment, so a gait, if there is one, is "
        "slower than one episode resolves"
    )


def _summary(table: pd.DataFrame) -> pd.DataFrame:
    rows = []
    order = [JOINTS, *RESERVOIRS]
    signals = [s for s in order if s in set(table["signal"])]
    signals += [s for s in dict.fromkeys(table["signal"]) if s not in order]
    for signal in signals:
        group = table[table["signal"] == signal]
        peaks = pd.to_numeric(group["dominant_frequency"], errors="coerce").dropna()
        shares = pd.to_numeric(group["share_near_gait"], errors="coerce").dropna()
        rows.append(
            {
                "signal": signal,
                "seeds": len(group),
                "dominant_frequency": float(peaks.median()) if len(peaks) else math.nan,
                "with_peak": len(peaks),
                "share": float(shares.median()) if len(shares) else math.nan,
                "share_min": float(shares.min()) if len(shares) else math.nan,
                "share_max": float(shares.max()) if len(shares) else math.nan,
            }
        )
    return pd.DataFrame(rows)


def without_gait(env_id: str) -> bool:
    """Whether a task is known not to be locomotion (a registered task without joints, such as
    CartPole or Pendulum): its ``res-ppo − leaky-res-ppo`` comparison is judged like any
    other, but it gets no mechanism verdict, having no gait to oscillate at. An id gymnasium
    does not know is not claimed either way."""
    import gymnasium

    from ermrl.analysis._dynamics import has_joints

    try:
        gymnasium.spec(env_id)
    except Exception:  # not registered
        return False
    return not has_joints(env_id)


def mechanism_question(rule: VerdictRule | None) -> Question | None:
    """The question of a rule that compares the evolved reservoir with its W = 0 ablation."""
    if rule is None:
        return None
    target = Comparison(EVOLVED, ABLATED)
    return next((q for q in rule.questions if target in q.comparisons), None)


@dataclass(frozen=True)
class MechanismVerdict:
    """A task's mechanism label ([`mechanism_verdict`][ermrl.analysis.mechanism_verdict]).

    Attributes:
        label: One of `MECHANISM_LABELS`.
        text: Why, in words, with the comparison's effect and interval bound.
        worse_by_at_most: How much worse the ablation could learn: the larger upper end of the
            adjusted Welch and bootstrap intervals of ``res-ppo − leaky-res-ppo`` (NaN when the
            comparison was not tested).
    """

    label: str
    text: str
    worse_by_at_most: float = math.nan

    @property
    def headline(self) -> str:
        """The label as the pages print it (bold outcome)."""
        if self.label in MECHANISM_LABELS[:2]:
            return f"{self.label}: **supported**"
        return f"**{self.label}**"


def mechanism_verdict(
    comparison: Mapping[str, Any] | None, spectral: SpectralOutcome
) -> MechanismVerdict:
    """A task's mechanism from its comparison and its spectra (see the module's docstring).

    Args:
        comparison: The judged ``res-ppo − leaky-res-ppo`` row of the primary metric (a row of
            [`judge`][ermrl.analysis.judge]); ``None`` when it was not judged.
        spectral: The spectral criterion on the task.

    Returns:
        The label and its reason.
    """
    if comparison is None or not_run(comparison):
        why = f"`{ABLATED}` has no finished run on this task"
        if comparison is not None:
            agent, _, rest = (
                str(comparison["note"]).removeprefix(NOT_RUN).lstrip(": ").partition(" ")
            )
            why = f"`{agent}` {rest}" if rest else why
        return MechanismVerdict(
            NOT_RUN, f"{why}, so neither oscillatory dynamics nor leaky integration is judged"
        )
    if comparison.get("note"):
        return MechanismVerdict("inconclusive", str(comparison["note"]))
    highs = [float(comparison["adj_welch_high"]), float(comparison["adj_boot_high"])]
    bound = max(highs)
    level = f"{100 * (1 - float(comparison['level'])):.4g}%"
    effect = (
        f"`{EVOLVED} − {ABLATED}` = {float(comparison['mean_diff']):+.4g}, "
        f"{comparison['outcome']} after Holm, Holm p {float(comparison['p_adjusted']):.3g}, "
        f"adjusted intervals up to {bound:+.4g} at {level}"
    )
    spectra = _spectral_text(spectral)
    if comparison["outcome"] == "supported":
        if spectral.holds:
            return MechanismVerdict(
                "oscillatory dynamics",
                f"the W = 0 ablation learns worse ({effect}) and the evolved reservoir carries "
                f"a gait-frequency component that its ablation lacks ({spectra})",
                bound,
            )
        why = (
            f"the evolved reservoir carries no gait-frequency component that its ablation lacks "
            f"({spectra})"
            if spectral.holds is False
            else f"the spectral criterion cannot be judged ({spectral.reason})"
        )
        return MechanismVerdict(
            "inconclusive",
            f"the W = 0 ablation learns worse ({effect}), but {why}: the recurrent weights "
            "help, not shown to be through oscillations at the gait",
            bound,
        )
    if comparison["outcome"] == "contradicted":
        worse = (
            f"the ablation learns better ({effect}): by at least {-bound:.4g}, both adjusted "
            "intervals lying below 0"
        )
    elif comparison.get("equivalence") == EQUIVALENT:
        worse = (
            f"the ablation learns as well as the evolved reservoir: {equivalence_text(comparison)}"
            f" ({effect})"
        )
    else:
        margin = comparison.get("margin")
        stated = isinstance(margin, (int, float)) and math.isfinite(float(margin))
        why = (
            equivalence_text(comparison)
            if stated
            else "no equivalence margin is stated for the task, so equivalence cannot be shown"
        )
        return MechanismVerdict(
            NOT_SHOWN,
            f"the ablation is not shown to learn worse ({effect}), and not shown to learn as well: "
            f"{why}; it could learn up to {bound:.4g} worse than the evolved reservoir; "
            f"spectra: {spectra}",
            bound,
        )
    return MechanismVerdict("leaky integration suffices", f"{worse}; spectra: {spectra}", bound)


def _spectral_text(spectral: SpectralOutcome) -> str:
    if spectral.holds is None:
        return spectral.reason
    return (
        f"the criterion holds on {spectral.n_holding} of {spectral.n_seeds} weight seeds; gait "
        f"{spectral.gait_frequency:.3g} {spectral.unit}"
    )


def mechanism_table(spectral: SpectralOutcome) -> pd.DataFrame:
    """The spectra behind a mechanism, one row per signal, as the pages show them."""
    if spectral.summary.empty:
        return pd.DataFrame()
    unit = spectral.unit
    rows = []
    for row in spectral.summary.itertuples(index=False):
        label = {
            JOINTS: "joint angles (the gait)",
            EVOLVED: f"evolved reservoir ({EVOLVED})",
            UNEVOLVED: f"unevolved reservoir ({UNEVOLVED})",
            ABLATED: f"evolved, W = 0 ({ABLATED})",
        }.get(str(row.signal), str(row.signal))
        peak = (
            f"{row.dominant_frequency:.3g} ({row.with_peak}/{row.seeds} with a peak)"
            if math.isfinite(row.dominant_frequency)
            else f"no peak (0/{row.seeds})"
        )
        share = (
            f"{row.share:.3g} [{row.share_min:.3g}, {row.share_max:.3g}]"
            if math.isfinite(row.share)
            else "–"
        )
        rows.append(
            {
                "signal": label,
                "weight seeds": row.seeds if str(row.signal) != JOINTS else "–",
                f"dominant frequency ({unit}, median)": peak,
                "share of power near the gait (median [min, max])": share,
            }
        )
    return pd.DataFrame(rows)


def report_rule(primary: str = "last10", n_resamples: int = 10_000) -> VerdictRule:
    """A one-question rule for a single task's ``res-ppo − leaky-res-ppo`` (its family is that
    one test: the reproduction page adjusts over every task of the question instead)."""
    question = Question(
        "evolved-vs-leaky",
        "does the evolved reservoir beat its W = 0 ablation?",
        (Comparison(EVOLVED, ABLATED),),
    )
    return VerdictRule((question,), primary=primary, n_resamples=n_resamples)


def mechanism_figure(
    spectra: pd.DataFrame, spectral: SpectralOutcome, *, title: str | None = None
) -> Any:
    """The mean spectra of the joint angles and of the three reservoirs, the gait band shaded.

    Args:
        spectra: `ReservoirSpectra.spectra` (or a report's `MECHANISM_SPECTRA_FILE`).
        spectral: The criterion's outcome on the same table (for the band and the counts).
        title: Figure title.

    Returns:
        A [`PaperFigure`][ermrl.analysis.PaperFigure]; each curve is divided by its maximum above 0.
    """
    from ermrl.analysis._style import (
        AGENT_LABELS,
        agent_color,
        empty_axes,
        new_figure,
        paper_style,
    )

    unit = spectral.unit or "Hz"
    with paper_style():
        fig, ax = new_figure(figsize=(7.0, 4.4))
        freqs = spectra["frequency"].to_numpy(dtype=float) if "frequency" in spectra else []
        drawn = 0
        for index, name in enumerate([JOINTS, *RESERVOIRS]):
            if name not in spectra or len(freqs) < 3:
                continue
            power = spectra[name].to_numpy(dtype=float)[1:]
            peak = float(np.max(power)) if len(power) else 0.0
            if not peak > 0:
                continue
            label = "joint angles (gait)" if name == JOINTS else AGENT_LABELS.get(name, name)
            color = "black" if name == JOINTS else agent_color(name, index)
            style = "--" if name == ABLATED else "-"  # on the evolved one when W barely acts
            ax.plot(freqs[1:], power / peak, color=color, lw=1.2, ls=style, label=label)
            drawn += 1
        if not drawn:
            empty_axes(ax, "no spectra")
            return fig
        low, high = spectral.band
        if math.isfinite(low) and math.isfinite(high):
            ax.axvspan(low, high, color="0.85", zorder=0, label=f"gait band ({low:.3g}-{high:.3g})")
        ax.set_yscale("log")
        ax.set_xlim(0, float(freqs[-1]))
        ax.set_xlabel(f"Frequency ({unit})")
        ax.set_ylabel("Relative power spectral density\n(sum over dimensions, peak = 1)")
        ax.legend(frameon=False, loc="upper right")
        counts = (
            f": criterion holds on {spectral.n_holding}/{spectral.n_seeds} weight seeds"
            if spectral.holds is not None
            else ""
        )
        ax.set_title(title or f"One input stream, three reservoirs{counts}")
    return fig


def describe_mechanism(criterion: SpectralCriterion | None = None) -> str:
    """How a task's mechanism label is decided, in words, as the pages print it."""
    criterion = criterion or SpectralCriterion()
    return (
        "one deterministic episode of the trained `res-ppo` agent gives the reservoir's input "
        "stream (observation, previous action, previous reward); it drives the evolved "
        f"reservoir, the unevolved one and the evolved one with W = 0 (`{ABLATED}`'s: the same "
        "input weights, bias and leak rate), each with the weights of every `res-ppo` test "
        f"seed; {criterion.describe()}. *Oscillatory dynamics* is supported when "
        f"`{EVOLVED} − {ABLATED}` is supported (the ablation learns worse) and the evolved "
        "reservoir carries that component; *leaky integration suffices* is supported when the "
        "ablation learns better (the comparison is contradicted) or as well (equivalent within "
        "the task's margin: two one-sided tests at the adjusted level); *not shown either way* "
        "when it is neither shown to learn worse nor shown equivalent, and the page gives how "
        "much worse it could still learn (the larger upper end of the adjusted intervals); "
        "*inconclusive* when the ablation learns worse but the spectra "
        "show no such component (or are not recorded, or the task has no gait); *not run yet* "
        f"without finished `{ABLATED}` runs"
    )
