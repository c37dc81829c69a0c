#!/usr/bin/env python
"""Evolve reservoirs on a set of tasks (same as ``ermrl evolve-generalization``)."""

from ermrl.cli import run_command

if __name__ == "__main__":
    raise SystemExit(run_command("evolve-generalization", prog="evolve_generalization.py"))
