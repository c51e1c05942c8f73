"""Thread budgets for stage processes.

A stage process gets ``threads`` compute threads (torch/OpenMP, MKL, OpenBLAS, numba): the cores this
process may run on (``os.sched_getaffinity``, so a container's or ``taskset``'s limit counts) shared
among the ``jobs`` stage runs that run at once, or an explicit ``--threads``. OpenMP threads wait
passively (``OMP_WAIT_POLICY=PASSIVE``): a spinning OpenMP worker burns its core while it waits, and
on a machine busy with other work that turned a stage ~30x slower.
"""

from __future__ import annotations

import os

THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; ``os.cpu_count()`` where affinity is unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def stage_threads(jobs: int = 1, threads: int | None = None) -> int:
    """Compute threads for one stage process: ``threads`` when given, else the available cores divided
    among ``jobs`` concurrent stage runs (at least 1)."""
    if threads is not None:
        return max(1, int(threads))
    return max(1, available_cores() // max(1, int(jobs)))


def thread_env(threads: int, env: dict[str, str] | None = None, override: bool = False) -> dict[str, str]:
    """``env`` (default: a copy of ``os.environ``) with the thread-count variables set to ``threads``
    (kept where already set unless ``override``) and OpenMP told not to spin while it waits."""
    out = dict(os.environ if env is None else env)
    for var in THREAD_VARS:
        if override or var not in out:
            out[var] = str(threads)
    out.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    out.setdefault("KMP_BLOCKTIME", "0")
    return out
