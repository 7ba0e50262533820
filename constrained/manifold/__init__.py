"""The constraint manifold: THE mass-scaled KKT/Schur solve, projections onto f = 0 and J v + f_t = 0,
the rank policy, degrees of freedom and redundancy, residuals in metres, and the mapped (per-row
kernel) build of large models. Dense and sparse linear algebra are chosen here, once per model."""
