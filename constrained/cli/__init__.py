"""The ``constrained`` command: ``main`` (parser, exit statuses) and one module per verb family.

Two settings of the process, made here before any verb imports NumPy, each unless the
environment already chose:

- NumPy's BLAS on one thread (``OPENBLAS_NUM_THREADS``): the package's dense algebra is small
  per call (constrained.threads), and OpenBLAS's thread pool costs about 0.04 s of CPU to start
  and spins between calls (a 1 cm rope of 10,000 links: 0.80 -> 0.75 s for its fixed cost).
- glibc's malloc keeps freed blocks of up to 32 MB for reuse (``mallopt``: M_MMAP_THRESHOLD,
  M_TRIM_THRESHOLD) instead of mapping each large array afresh and returning it when freed, its
  pages faulted in again at every use (a 100 x 100 cloth: 76,000 -> 58,000 page faults, 1.12 ->
  1.08 s for its fixed cost). Not where ``GLIBC_TUNABLES`` or ``MALLOC_*_`` are set, nor off
  glibc.
"""

import ctypes
import os
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

#: Freed blocks up to this size are kept by malloc for reuse (and the heap's top trimmed only
#: beyond twice it).
KEPT_BLOCKS = 32 << 20


def _keep_freed_blocks() -> bool:
    """glibc's mallopt as above; whether it was set."""
    if not sys.platform.startswith("linux") or "GLIBC_TUNABLES" in os.environ or any(
            name.startswith("MALLOC_") for name in os.environ):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # (musl and others: no mallopt)
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    return bool(mallopt(m_mmap_threshold, KEPT_BLOCKS)) and bool(mallopt(m_trim_threshold, 2 * KEPT_BLOCKS))


KEEPS_FREED_BLOCKS = _keep_freed_blocks()
