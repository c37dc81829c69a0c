"""Processes that train agents in parallel: sized to keep every core busy, never orphaned.

Both the evolution (a trial's seeds, [`ermrl.search.SeedRunner`][ermrl.search.SeedRunner]) and the
test phase (agents x seeds) train in a pool made by [`training_pool`][ermrl.agents.training_pool]:

- ``spawn`` processes (no forked torch state), whose initializer imports the training stack once;
- on Linux each process is killed when its parent dies (``PR_SET_PDEATHSIG``), so a worker killed
  with SIGKILL or by the OOM killer does not leave its training runs burning CPU for hours;
- a pool whose ``with`` block ends with an error or an interrupt (Ctrl-C, SIGTERM) terminates
  its processes ([`stop_workers`][ermrl.agents.stop_workers]) instead of waiting for their runs to
  end: hours, with a population's, which trained on while the command had already said it stopped;
- [`pool_size`][ermrl.agents.pool_size] picks how many single-threaded processes finish the runs
  soonest.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
from concurrent.futures import ProcessPoolExecutor
from types import TracebackType

__all__ = ["pool_size", "stop_workers", "training_pool"]

_PR_SET_PDEATHSIG = 1  # from <linux/prctl.h>


def pool_size(n_jobs: int, n_procs: int) -> int:
    """Processes that finish ``n_jobs`` equally long runs soonest on ``n_procs`` cores.

    A pool of exactly ``n_procs`` processes leaves cores idle when the runs do not divide evenly
    (3 seeds on 2 cores: the third seed trains alone, so the trial is at most 1.5x faster than
    in one process). Single-threaded training processes time-share a core at little cost, so a
    few more processes than cores keep every core busy to the end (3 seeds on 2 cores: 3
    processes, up to 2x). Runs go in waves of ``q`` processes; a wave of ``k`` runs takes
    ``max(1, k / n_procs)`` run-times. The smallest pool in ``[n_procs, 2 * n_procs]`` with the
    shortest total wins, so the pool never holds more than twice as many processes as cores.

    Args:
        n_jobs: Runs per call (a trial's seeds; tasks x seeds in a generalization trial).
        n_procs: Cores the runs may use.

    Returns:
        The number of worker processes (1 means: run in this process).
    """
    if n_procs <= 1 or n_jobs <= 1:
        return 1
    if n_jobs <= n_procs:
        return n_jobs

    def wall(q: int) -> float:
        waves, rest = divmod(n_jobs, q)
        total = waves * max(1.0, q / n_procs)
        return total + (max(1.0, rest / n_procs) if rest else 0.0)

    candidates = range(n_procs, min(n_jobs, 2 * n_procs) + 1)
    return min(candidates, key=lambda q: (round(wall(q), 9), q))


def _die_with_parent(parent_pid: int) -> None:
    """Linux: have the kernel SIGKILL this process when the process that started it dies."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):  # no libc prctl: keep the default behaviour
        return
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)


def _initialize_worker(parent_pid: int) -> None:
    _die_with_parent(parent_pid)
    import stable_baselines3  # noqa: F401  (import the training stack once per process)

    import ermrl.envs  # noqa: F401


def stop_workers(pool: ProcessPoolExecutor) -> None:
    """Cancel the pool's runs not started and terminate its processes (SIGTERM), without
    waiting for the runs they train; the pool cannot be used afterwards.

    ``concurrent.futures`` has no public way to stop a running task before Python 3.14
    (``terminate_workers``): the processes are read from the executor's ``_processes``.
    """
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(timeout=30)


class _TrainingPool(ProcessPoolExecutor):
    """A ``ProcessPoolExecutor`` whose ``with`` block, ended by an exception, stops its
    processes ([`stop_workers`][ermrl.agents.stop_workers]) rather than waiting for their runs."""

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> bool | None:
        if exc_type is None:
            return super().__exit__(exc_type, exc, tb)
        stop_workers(self)
        return None


def training_pool(n_processes: int) -> ProcessPoolExecutor:
    """A pool of ``n_processes`` ``spawn`` processes for [`train_agent`][ermrl.agents.train_agent]
    runs.

    Call it from the thread that keeps the pool (the main thread of a worker): on Linux the
    processes die with the thread that started them. A ``with`` block that ends with an error
    or an interrupt terminates them ([`stop_workers`][ermrl.agents.stop_workers]).
    """
    return _TrainingPool(
        max_workers=n_processes,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_initialize_worker,
        initargs=(os.getpid(),),
    )
