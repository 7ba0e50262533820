"""The solvers behind constrained.analysis.statics: Newton and IPOPT on the KKT conditions, and a
trust-region descent of the potential on the constraint manifold."""
