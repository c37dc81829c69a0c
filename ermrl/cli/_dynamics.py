"""``ermrl dynamics``: record an episode of a trained reservoir agent and analyse its states."""

from __future__ import annotations

import math
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path

from ermrl._interrupt import interruption
from ermrl.cli._common import add_run_folder_args, fail, run_folder_kwargs
from ermrl.runner._options import ArgumentParser, HelpFormatter, positive_int

__all__ = ["build_dynamics_parser", "dynamics_main"]

DESCRIPTION = textwrap.dedent(
    """\
    Run a trained agent of a test-phase folder for one episode (same env, mask and reservoir
    weights as in training) and record its observations, actions, rewards and reservoir states.
    Writes <agent>_seed<seed>_episode.npz (the arrays), _dynamics.png (observations, actions and
    the first reservoir units over time), _spectrum.png (power spectra) and _spectrum.json
    (dominant frequencies).

    example:
      ermrl dynamics --run runs/S --agent res-ppo --seed 10
    """
)


def build_dynamics_parser(prog: str = "ermrl dynamics") -> ArgumentParser:
    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    add_run_folder_args(
        parser,
        agent_help="agent whose model is replayed (res-ppo, random-res-ppo, ppo, ppo-full)",
        out_help="output folder (default: <run>/dynamics)",
    )
    parser.add_argument(
        "--units", type=positive_int, default=20, help="reservoir units shown over time"
    )
    parser.add_argument(
        "--window-steps",
        type=positive_int,
        default=200,
        help="steps shown in the time plot (the spectrum uses the whole episode)",
    )
    parser.add_argument("--quiet", action="store_true", help="no summary lines")
    return parser


def dynamics_main(argv: Sequence[str] | None = None, prog: str = "ermrl dynamics") -> int:
    """Entry point of ``ermrl dynamics``."""
    parser = build_dynamics_parser(prog)
    args = parser.parse_args(argv)
    from ermrl._io import staged_folder
    from ermrl.analysis import RunFolderError, record_dynamics, spectrum_summary, write_dynamics
    from ermrl.envs import UnknownEnvError

    try:
        recording = record_dynamics(**run_folder_kwargs(args))
    except (FileNotFoundError, UnknownEnvError, RunFolderError) as err:
        fail(prog, str(err))
    except KeyboardInterrupt as err:
        what, code = interruption(err)
        print(f"{prog}: {what}", file=sys.stderr)
        return code
    out = Path(args.out) if args.out else Path(args.run) / "dynamics"
    try:  # staged, then moved into out: a full disk or read-only folder leaves no partial file
        with staged_folder(out) as stage:
            staged = write_dynamics(
                recording, stage, n_units=args.units, window_steps=args.window_steps
            )
    except OSError as err:
        fail(
            prog,
            f"cannot write {out}: {err.strerror or err}; nothing was written (free space, or "
            "choose a writable --out)",
        )
    paths = {name: out / path.relative_to(stage) for name, path in staged.items()}
    if not args.quiet:
        summary = spectrum_summary(recording)
        unit = summary["frequency_unit"]
        print(
            f"{recording.agent} seed {recording.seed}: {recording.n_steps} steps, return "
            f"{recording.episode_return:.4g}"
        )
        for name, info in summary["signals"].items():
            f = info["dominant_frequency"]
            shown = "n/a" if f is None or not math.isfinite(f) else f"{f:.3g} {unit}"
            print(f"  dominant frequency of the {name}: {shown}")
        print("wrote " + ", ".join(str(p) for p in paths.values()), flush=True)
    return 0
