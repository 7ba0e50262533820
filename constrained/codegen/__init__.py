"""Compiled evaluation: C code generated from CasADi Functions and cached on disk, and fast calls of
CasADi Functions from NumPy; SX algorithms walked instruction by instruction (``scalar_c``: as C
statements; ``interval``: in interval arithmetic). Below the model; imports only the ground floor."""
