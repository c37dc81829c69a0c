"""``ermrl video``: render an episode of a trained agent to MP4 (and GIF), headless."""

from __future__ import annotations

import argparse
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path

from ermrl._interrupt import interruption
from ermrl.cli._common import add_run_folder_args, fail, run_folder_kwargs
from ermrl.runner._options import ArgumentParser, HelpFormatter

__all__ = ["build_video_parser", "video_main"]

EXIT_NO_GL = 3

DESCRIPTION = textwrap.dedent(
    """\
    Render one episode of a trained agent of a test-phase folder, on the CPU without a display,
    and write it as MP4 (H.264) and optionally GIF. Any task with an rgb_array renderer works:
    MuJoCo tasks through MuJoCo's offscreen renderer, whose OpenGL backend (EGL or OSMesa from
    Mesa) is chosen automatically by trying a tiny render (--gl forces one), and classic
    control (CartPole, Pendulum) through pygame. Exit code 3 when no OpenGL backend works (the
    message says what to install).

    example:
      ermrl video --run runs/S --agent res-ppo --seed 10
    """
)


def build_video_parser(prog: str = "ermrl video") -> ArgumentParser:
    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    add_run_folder_args(
        parser,
        agent_help="agent to film (res-ppo, ppo, ppo-full, random-res-ppo)",
        out_help="MP4 path (default: <run>/videos/<agent>_seed<seed>.mp4)",
    )
    parser.add_argument(
        "--gif",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="also write a GIF (half size, every other frame) next to the MP4",
    )
    parser.add_argument(
        "--gl",
        choices=("auto", "egl", "osmesa", "glfw"),
        default="auto",
        help="OpenGL backend (auto: the first of MUJOCO_GL, egl, osmesa that renders)",
    )
    parser.add_argument(
        "--fast",
        action="store_true",
        help="no shadows or reflections: about 5x faster with Mesa's software renderer",
    )
    parser.add_argument("--quiet", action="store_true", help="no summary line")
    return parser


def video_main(argv: Sequence[str] | None = None, prog: str = "ermrl video") -> int:
    """Entry point of ``ermrl video``."""
    parser = build_video_parser(prog)
    args = parser.parse_args(argv)
    from ermrl.analysis import GLBackendError, RunFolderError, record_video
    from ermrl.envs import UnknownEnvError

    try:
        result = record_video(
            out=args.out,
            gif=args.gif,
            gl=None if args.gl == "auto" else args.gl,
            fast=args.fast,
            **run_folder_kwargs(args),
        )
    except GLBackendError as err:
        fail(prog, str(err), code=EXIT_NO_GL)
    except (FileNotFoundError, UnknownEnvError, RunFolderError) as err:
        fail(prog, str(err))
    except OSError as err:  # a read-only folder, a full disk: the video was staged, not written
        fail(
            prog,
            f"cannot write the video {args.out or Path(args.run) / 'videos'}: "
            f"{err.strerror or err}; "
            "nothing was written (free space, or choose a writable --out)",
        )
    except KeyboardInterrupt as err:
        what, code = interruption(err)
        print(f"{prog}: {what}", file=sys.stderr)
        return code
    if not args.quiet:
        height, width = result.size
        print(
            f"{result.n_frames} frames ({width}x{height}, {result.fps:g} fps, GL backend "
            f"{result.backend or 'none needed'}), episode return {result.episode_return:.4g}; "
            "wrote " + ", ".join(str(p) for p in result.paths),
            flush=True,
        )
    return 0
