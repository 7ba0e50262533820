"""What becomes of the variants of a batched run (``run.ensemble``): why one did not finish."""
