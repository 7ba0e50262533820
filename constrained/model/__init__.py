"""The model: plain descriptions (System, particles, constraints, effects, parameters, formulas) and
their assembly into an immutable Structure/Model of CasADi Functions of (x, v, t, p).

Nothing here solves a KKT system or runs a method: that is ``manifold`` and ``solvers`` above."""
