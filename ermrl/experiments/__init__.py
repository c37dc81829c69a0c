"""Deprecated: the test phase's old package name; use [`ermrl.test_phase`][ermrl.test_phase].

``import ermrl.experiments`` (and its private modules, ``ermrl.experiments._test_phase``, ...)
still works and gives the very objects of [`ermrl.test_phase`][ermrl.test_phase], with a
`DeprecationWarning`. It will be removed in a later release.
"""

import importlib
import sys
import warnings

from ermrl.test_phase import *  # noqa: F403  (the alias re-exports the whole public API)
from ermrl.test_phase import __all__  # noqa: F401

warnings.warn(
    "ermrl.experiments is renamed ermrl.test_phase (the test phase against baselines); "
    "the old name will be removed in a later release",
    DeprecationWarning,
    stacklevel=2,
)

for _module in ("_prepare", "_results", "_test_phase"):
    sys.modules[f"{__name__}.{_module}"] = importlib.import_module(f"ermrl.test_phase.{_module}")
