#!/usr/bin/env python
"""Test reservoirs evolved on a set of tasks on another task (same as ``ermrl test-generalization``)."""

from ermrl.cli import run_command

if __name__ == "__main__":
    raise SystemExit(run_command("test-generalization", prog="test_generalization.py"))
