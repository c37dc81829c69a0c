"""The ``ermrl`` command. Each subcommand is also a root script (``evolve_res.py``, ``test.py``)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence

from ermrl.cli._evolve import evolve_main
from ermrl.cli._test import test_main

__all__ = ["main", "evolve_main", "test_main", "COMMANDS"]

COMMANDS: dict[str, tuple[Callable[..., int], str]] = {
    "evolve": (evolve_main, "evolve reservoirs for one task (evolve_res.py)"),
    "test": (test_main, "train the best reservoir against PPO baselines (test.py)"),
}


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
    if not args or args[0] in ("-h", "--help"):
        print(_usage())
        return 0 if args else 2
    if args[0] == "--version":
        from ermrl import __version__

        print(f"ermrl {__version__}")
        return 0
    name, rest = args[0], args[1:]
    if name not in COMMANDS:
        print(
            f"ermrl: error: unknown command {name!r}; choose from {', '.join(COMMANDS)} (see --help)",
            file=sys.stderr,
        )
        return 2
    func, _ = COMMANDS[name]
    return func(rest, prog=f"ermrl {name}")


if __name__ == "__main__":
    raise SystemExit(main())
