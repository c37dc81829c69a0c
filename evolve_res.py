#!/usr/bin/env python
"""Evolve reservoirs for one task (same as ``ermrl evolve``)."""

from ermrl.cli import evolve_main

if __name__ == "__main__":
    raise SystemExit(evolve_main(prog="evolve_res.py"))
