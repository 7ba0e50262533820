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
    """

    dependent_rtol: float = 1e-9
    cholesky_rtol: float = 1e-6
    singular_sigma: float = 1e-6


#: The policy every module uses unless a caller passes its own.
RANK = RankPolicy()
