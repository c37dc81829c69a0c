"""One BLAS kernel on every x86-64 machine, so that a seed's result does not depend on the CPU.

numpy's wheels ship OpenBLAS built with ``DYNAMIC_ARCH``: when it loads, it picks the kernels
of the CPU it finds (``Haswell`` for AVX2, ``SkylakeX`` for AVX-512, ``Zen``...). Their
products round differently, and reinforcement learning amplifies a last-bit difference into
another trajectory: the same test-phase run (same code, seed and population) gave a first
episode return of 4.2128 on an AVX2 machine and 4.0077 on an AVX-512 one, and final returns
of 41.2 and 45.5 after 1M steps. Results are then reproducible only on the CPU model they
were made on.

`pin_blas_kernel`, called when ``ermrl`` is imported, sets ``OPENBLAS_CORETYPE=Haswell``
(OpenBLAS's documented override of its runtime choice) before numpy loads OpenBLAS, on x86-64
CPUs that have AVX2 and FMA (every x86-64 server CPU since 2013 does). The population backend's
products then round alike on any such machine: a published run reruns bit-identically on
another CPU. A kernel set by the user (``OPENBLAS_CORETYPE`` in the environment) is kept, and
nothing is changed when numpy was imported before ``ermrl`` (too late: OpenBLAS has chosen) or
on other CPUs; when numpy came first, the variable is set to the kernel OpenBLAS chose, so that
the worker processes ermrl starts run the same one. `blas_kernel` names the kernel a process runs
with; every run and trial records it beside the code (`ermrl._code.code_identity`).

PyTorch's CPU wheels use MKL, whose own dispatch is not pinned here: the ``sb3`` backend's
results can still differ between CPUs (``MKL_CBWR`` pins it, at a speed cost not measured).
"""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

__all__ = ["PINNED_KERNEL", "blas_kernel", "pin_blas_kernel"]

#: The OpenBLAS kernel ermrl pins on x86-64 CPUs with AVX2 and FMA.
PINNED_KERNEL = "Haswell"
_ENV = "OPENBLAS_CORETYPE"


def _cpu_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> set[str]:
    """The CPU's feature flags (empty where ``/proc/cpuinfo`` cannot be read)."""
    try:
        text = cpuinfo.read_text(errors="replace")
    except OSError:
        return set()
    for line in text.splitlines():
        if line.startswith("flags"):
            return set(line.partition(":")[2].split())
    return set()


def pin_blas_kernel(
    environ: dict[str, str] | None = None,
    *,
    machine: str | None = None,
    flags: set[str] | None = None,
    numpy_loaded: bool | None = None,
) -> str | None:
    """Set ``OPENBLAS_CORETYPE`` to `PINNED_KERNEL` where it is safe and still in time.

    Args:
        environ: The environment to set it in (default ``os.environ``; child processes
            inherit it).
        machine: ``platform.machine()`` (for tests).
        flags: The CPU's flags (default: read from ``/proc/cpuinfo``).
        numpy_loaded: Whether numpy is already imported (default: ``"numpy" in sys.modules``).

    Returns:
        The kernel now asked for (the user's own, or the pinned one), or ``None`` when none is.
    """
    env = os.environ if environ is None else environ
    if env.get(_ENV):
        return env[_ENV]
    if numpy_loaded if numpy_loaded is not None else "numpy" in sys.modules:
        # Too late for this process: its child processes (the workers) take its kernel, so that
        # one job runs one kernel.
        parts = blas_kernel().split()
        if len(parts) == 3 and parts[0] == "openblas":  # library, version, kernel
            env[_ENV] = parts[2]
        return None
    if (machine or platform.machine()).lower() not in ("x86_64", "amd64"):
        return None
    if not {"avx2", "fma"} <= (flags if flags is not None else _cpu_flags()):
        return None
    env[_ENV] = PINNED_KERNEL
    return PINNED_KERNEL


def blas_kernel() -> str:
    """The BLAS numpy runs with, as ``<library> <version> <kernel>`` (``openblas 0.3.31
    Haswell``), from threadpoolctl; ``unknown`` when it cannot tell."""
    try:
        import numpy  # noqa: F401  (loads the BLAS that threadpoolctl inspects)
        import threadpoolctl
    except ImportError:
        return "unknown"
    blas = [lib for lib in threadpoolctl.threadpool_info() if lib.get("user_api") == "blas"]
    blas.sort(key=lambda lib: "numpy" not in str(lib.get("filepath", "")).lower())  # numpy's first
    if not blas:
        return "unknown"
    parts = [blas[0].get(key) for key in ("internal_api", "version", "architecture")]
    return " ".join(str(p) for p in parts if p) or "unknown"
