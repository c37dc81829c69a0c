#!/usr/bin/env python
"""Test reservoirs evolved on a set of tasks on another task (same as ``ermrl test-generalization``)."""

from ermrl.cli._generalization import test_generalization_main

if __name__ == "__main__":
    raise SystemExit(test_generalization_main(prog="test_generalization.py"))
