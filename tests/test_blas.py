"""One OpenBLAS kernel on every x86-64 CPU with AVX2 (ermrl._blas): when it is pinned, when it is
left alone, and that every record names it."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from ermrl._blas import PINNED_KERNEL, _cpu_flags, blas_kernel, pin_blas_kernel
from ermrl._code import code_identity, describe_code, same_code

AVX2 = {"avx2", "fma", "sse4_2"}


def test_the_kernel_is_pinned_only_where_it_is_safe_and_in_time() -> None:
    env: dict[str, str] = {}
    assert pin_blas_kernel(env, machine="x86_64", flags=AVX2, numpy_loaded=False) == "Haswell"
    assert env == {"OPENBLAS_CORETYPE": PINNED_KERNEL}
    # The user's own choice is kept.
    env = {"OPENBLAS_CORETYPE": "Zen"}
    assert pin_blas_kernel(env, machine="x86_64", flags=AVX2, numpy_loaded=False) == "Zen"
    assert env == {"OPENBLAS_CORETYPE": "Zen"}
    # Another architecture, or a CPU without AVX2 or FMA (the Haswell kernels would stop it with
    # an illegal instruction): nothing is set.
    # Too late: numpy has loaded OpenBLAS; the workers are to run the kernel it chose.
    env = {}
    assert pin_blas_kernel(env, machine="x86_64", flags=AVX2, numpy_loaded=True) is None
    assert env == {"OPENBLAS_CORETYPE": blas_kernel().split()[-1]}
    for kwargs in (
        {"machine": "aarch64", "flags": AVX2, "numpy_loaded": False},
        {"machine": "x86_64", "flags": {"sse4_2", "avx"}, "numpy_loaded": False},
        {"machine": "x86_64", "flags": {"avx2"}, "numpy_loaded": False},
    ):
        env = {}
        assert pin_blas_kernel(env, **kwargs) is None, kwargs
        assert env == {}


def test_cpu_flags_are_read_from_cpuinfo(tmp_path) -> None:
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 fma\nbugs\t\t: none\n")
    assert _cpu_flags(info) == {"fpu", "sse2", "avx2", "fma"}
    assert _cpu_flags(tmp_path / "missing") == set()


def _python(code: str, **env: str) -> dict:
    environ = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"} | env
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=environ, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


REPORT = (
    "import json, os; from ermrl._code import code_identity; "
    "print(json.dumps({'env': os.environ.get('OPENBLAS_CORETYPE'), "
    "'blas': code_identity()['blas']}))"
)


@pytest.mark.skipif(
    platform.machine().lower() not in ("x86_64", "amd64") or not {"avx2", "fma"} <= _cpu_flags(),
    reason="the pin applies to x86-64 CPUs with AVX2 and FMA only",
)
def test_importing_ermrl_first_runs_numpy_on_the_pinned_kernel_and_records_it() -> None:
    """In a fresh process: ``import ermrl`` before numpy gives OpenBLAS's Haswell kernels, as
    threadpoolctl reads them off the loaded library; numpy imported first keeps the CPU's own
    choice, and the record says which."""
    pinned = _python("import ermrl; " + REPORT)
    assert pinned["env"] == "Haswell"
    assert pinned["blas"].startswith("openblas ") and pinned["blas"].endswith(" Haswell")
    late = _python("import numpy, ermrl; " + REPORT)
    assert late["blas"].startswith("openblas ")
    assert late["env"] == late["blas"].split()[-1]  # its workers take the kernel it runs
    chosen = _python("import ermrl; " + REPORT, OPENBLAS_CORETYPE="SandyBridge")
    assert chosen["env"] == "SandyBridge" and chosen["blas"].lower().endswith(" sandybridge")


def test_a_record_of_another_kernel_is_other_code() -> None:
    here = code_identity()
    assert isinstance(here["blas"], str) and here["blas"]
    assert f"BLAS {here['blas']}" in describe_code(here)
    assert same_code(here) is True
    assert same_code({**here, "blas": "openblas 0.0 Prescott"}) is False
    older = {k: v for k, v in here.items() if k != "blas"}  # written before the field existed
    assert same_code(older) is True
