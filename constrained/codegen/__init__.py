"""Compiled evaluation: C code generated from CasADi Functions and cached on disk, and fast calls of
CasADi Functions from NumPy. Below the model; imports only the ground floor."""
