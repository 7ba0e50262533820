"""BLAS threads, set deliberately.

The dense algebra of a run or a rank test is small per call (J is C × 3N at most); a
multithreaded BLAS only adds spin-waiting, which on a busy 2-core machine made one 128 × 192
SVD take 0.1–1 s instead of 1.5 ms, and the DOF of a 500-link chain 13–42 s instead of 1.5 s
(sweeps run several workers at once). ``one_blas_thread()`` limits BLAS to one thread for a
block; the caller's setting is restored after.
"""

from __future__ import annotations

import functools
import os

from threadpoolctl import ThreadpoolController


@functools.cache
def _controller() -> ThreadpoolController:
    """The loaded BLAS/OpenMP libraries, found once (≈ 1 ms); limiting them then costs ≈ 20 µs."""
    return ThreadpoolController()


def one_blas_thread():
    """A context manager: BLAS on one thread inside it."""
    return _controller().limit(limits=1, user_api="blas")


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity where the OS tells, else all)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
