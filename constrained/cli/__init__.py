"""The ``constrained`` command: ``main`` (parser, exit statuses) and one module per verb family.

The command runs NumPy's BLAS on one thread unless its environment sets
``OPENBLAS_NUM_THREADS``: the package's dense algebra is small per call (constrained.threads),
and OpenBLAS's thread pool costs about 0.04 s of CPU to start and spins between calls (a 1 cm
rope of 10,000 links: 0.80 -> 0.75 s of CPU for its whole fixed cost). Set here, before any
verb imports NumPy."""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
