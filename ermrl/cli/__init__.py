"""The ``ermrl`` command. Each subcommand is also a root script (``evolve_res.py``, ``test.py``).

Subcommands are imported only when run, so ``ermrl --help`` is instant.
"""

from __future__ import annotations

import atexit
import functools
import gc
import importlib
import os
import sys
from collections.abc import Sequence
from typing import Any

__all__ = ["main", "evolve_main", "run_command", "test_main", "COMMANDS"]

# name -> ("module:function", one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "evolve": ("ermrl.cli._evolve:evolve_main", "evolve reservoirs for one task (evolve_res.py)"),
    "study": (
        "ermrl.cli._study:study_main",
        "create, list, show, export, import, delete, fail-stale, repair",
    ),
    "test": (
        "ermrl.cli._test:test_main",
        "train the best reservoir against PPO baselines (test.py)",
    ),
    "report": ("ermrl.cli._report:report_main", "figures, tables and report.md of a study"),
    "dynamics": ("ermrl.cli._dynamics:dynamics_main", "reservoir states and spectra of an episode"),
    "video": ("ermrl.cli._video:video_main", "MP4/GIF of a trained agent's episode (headless)"),
    "evolve-generalization": (
        "ermrl.cli._generalization:evolve_generalization_main",
        "evolve reservoirs on a set of tasks (evolve_generalization.py)",
    ),
    "test-generalization": (
        "ermrl.cli._generalization:test_generalization_main",
        "test evolved reservoirs on another task (test_generalization.py)",
    ),
    "scores": (
        "ermrl.cli._scores:scores_main",
        "measure random-policy returns for the normalized fitness",
    ),
    "run": (
        "ermrl.cli._run:run_main",
        "a whole experiment from one YAML file: evolve, re-evaluate, test, report",
    ),
    "reproduction": (
        "ermrl.cli._reproduction:reproduction_main",
        "the reproduction page of experiment files, from their published results",
    ),
    "expert": (
        "ermrl.cli._expert:expert_main",
        "train and evaluate experts for imitation (BC, DAgger)",
    ),
}


def _load(target: str) -> Any:
    module, _, func = target.partition(":")
    return getattr(importlib.import_module(module), func)


def run_command(name: str, argv: Sequence[str] | None = None, prog: str | None = None) -> int:
    """Run the subcommand ``name``; return its exit code.

    Ctrl-C during its start-up (imports, env construction: several seconds), before the
    command's own handling takes over, is one line on stderr and exit code 130, not a
    traceback; SIGTERM is one line and exit code 143 (`ermrl._interrupt.catch_sigterm`).
    A signal whose exception was dropped (raised in a weakref callback) and that nothing raised
    again (`ermrl._interrupt.raise_swallowed_signal`) still ends with its line and code.
    A reader that closes the pipe early (``ermrl study show | head``) ends the command quietly
    with exit code 141, as SIGPIPE ends other Unix tools.
    """
    from ermrl._interrupt import catch_sigint, catch_sigterm, interruption, swallowed_signal

    prog = prog or f"ermrl {name}"
    _skip_last_collection()
    catch_sigint()  # a Ctrl-C that a library swallows during start-up is raised again later
    catch_sigterm()
    try:
        code = int(_load(COMMANDS[name][0])(argv, prog=prog))
    except KeyboardInterrupt as err:
        what, code = interruption(err)
        print(f"{prog}: {what}", file=sys.stderr)
        return code
    except BrokenPipeError:
        return _closed_pipe()
    late = swallowed_signal(code)  # a signal whose exception a weakref callback dropped
    if late != code:
        print(f"{prog}: {'stopped by SIGTERM' if late == 143 else 'interrupted'}", file=sys.stderr)
    return late


@functools.cache
def _skip_last_collection() -> None:
    """Freeze every object at exit, so that Python's last garbage collection skips them.

    That collection, of torch's and the envs' objects, took 3 to 4 s of a worker's exit after
    SIGTERM (its trial closed and its line printed within 0.2 s); the process is ending and the
    memory goes back with it. Registered once, as an ``atexit`` hook: a process that runs
    commands in-process (tests) collects as usual until it exits.
    """
    atexit.register(gc.freeze)


def _closed_pipe() -> int:
    """The exit code 141 of a reader that closed the pipe (as SIGPIPE ends other Unix tools).

    Nothing more can be written to stdout; it is pointed at /dev/null so that the flush at exit
    does not complain about the closed pipe either.
    """
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    return 141


def evolve_main(argv: Sequence[str] | None = None, prog: str = "ermrl evolve") -> int:
    return run_command("evolve", argv, prog)


def test_main(argv: Sequence[str] | None = None, prog: str = "ermrl test") -> int:
    return run_command("test", argv, prog)


test_main.__test__ = False  # type: ignore[attr-defined]  # not a pytest test


def _usage() -> str:
    width = max(len(name) for name in COMMANDS)
    lines = [f"  {name:<{width}}  {help_}" for name, (_, help_) in COMMANDS.items()]
    return (
        "usage: ermrl COMMAND [options]    (ermrl COMMAND --help for each command's options)\n\n"
        "Evolving reservoirs for meta reinforcement learning.\n\ncommands:\n" + "\n".join(lines)
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Dispatch ``ermrl COMMAND ...``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help", "--version"):
        from ermrl import __version__

        text = f"ermrl {__version__}" if args and args[0] == "--version" else _usage()
        try:  # `ermrl --help | head -3`: a closed pipe ends quietly, as in run_command
            print(text, flush=True)
        except BrokenPipeError:
            return _closed_pipe()
        return 0 if args else 2
    name, rest = args[0], args[1:]
    if name not in COMMANDS:
        print(
            f"ermrl: error: unknown command {name!r}; choose from {', '.join(COMMANDS)} (see --help)",
            file=sys.stderr,
        )
        return 2
    return run_command(name, rest)


if __name__ == "__main__":
    raise SystemExit(main())
