#!/usr/bin/env python
"""Test phase: the best evolved reservoir against PPO baselines (same as ``ermrl test``)."""

from ermrl.cli import test_main

if __name__ == "__main__":
    raise SystemExit(test_main(prog="test.py"))
