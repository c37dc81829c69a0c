#!/usr/bin/env python
"""Evolve reservoirs on a set of tasks (same as ``ermrl evolve-generalization``)."""

from ermrl.cli._generalization import evolve_generalization_main

if __name__ == "__main__":
    raise SystemExit(evolve_generalization_main(prog="evolve_generalization.py"))
