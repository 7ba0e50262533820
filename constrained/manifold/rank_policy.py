"""The thresholds that decide when constraint rows are dependent (one policy for every module)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RankPolicy:
    """The one set of thresholds that decides when constraint rows are dependent.

    ``dependent_rtol``: a row of the row-normalized, mass-weighted Jacobian ``Ĵ`` whose pivot
    (pivoted QR) or singular value falls below this fraction of the largest is dependent on
    the others (redundant), and is cut from minimum-norm solves. Exactly dependent rows sit
    at round-off, about 1e-16; 1e-9 leaves seven orders of magnitude on both sides.

    ``cholesky_rtol``: the fast path's test. A pivot of the Cholesky factor of ``D A D``
    below this fraction of the largest sends the solve to the SVD. It is larger than
    ``dependent_rtol`` because forming ``A`` squares the round-off: two identical rows leave
    a pivot near √ε ≈ 1e-8, not 0.

    ``singular_sigma``: a configuration is (nearly) singular when the smallest singular value
    of the row-normalized ``J`` falls below this; the diagnostics name the rows involved.

    ``cause_sigma``, ``cause_sigma_rows``: a stop is put down to a singular configuration
    (``diagnostics.likely_cause``) when that σ is below ``singular_cause(R)`` for R rows.
    """

    dependent_rtol: float = 1e-9
    cholesky_rtol: float = 1e-6
    singular_sigma: float = 1e-6
    cause_sigma: float = 1e-3
    cause_sigma_rows: float = 0.1

    def singular_cause(self, rows: int) -> float:
        """The σ below which a stop's last state, with ``rows`` independent rows, is called a
        singular configuration: ``cause_sigma``, or ``cause_sigma_rows`` / rows where that is less.
        A straight chain of R rods hanging from a point is regular, yet its rows couple each to the
        next by 1/2 (its rods in line), and its smallest σ, ≈ 1.1 / R, is its longest mode (R = 2,000:
        5.6e-4): a stop of ggl at t = 0 on such a chain was put down to "a singular configuration"
        at σ = 5.6e-4 < 1e-3. The threshold stays a tenth of that chain's σ; up to 100 rows (a
        four-bar at its dead centre) it is 1e-3 as before."""
        return min(self.cause_sigma, self.cause_sigma_rows / max(rows, 1))

    def singular_watch(self, tol: float, rows: int) -> float:
        """The singular watch's threshold for a run's ``singular_tol`` and ``rows`` independent
        rows: ``tol`` scaled as ``singular_cause`` (1/rows beyond 100 rows). A straight chain of
        12,000 rods at rest (σ ≈ 9.3e-5, its longest mode) was stopped at its first check as "a
        singular configuration" by tol = 1e-4."""
        return tol * self.singular_cause(rows) / self.cause_sigma


#: The policy every module uses unless a caller passes its own.
RANK = RankPolicy()
