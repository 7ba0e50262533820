"""Parameter sweeps: designs, chunks, the batched and per-run paths, Dask, the sweep's files and
figure. ``constrained.sweep`` (the function) is ``sweeps.sweep.sweep``."""
