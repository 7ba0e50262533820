"""Explicit Runge–Kutta tableaus with an embedded error estimate, for ``dopri``'s step loop.

A new explicit method is one short module in ``solvers/tableaus/`` that builds a ``Tableau``
(its coefficients and orders), listed in ``solvers/tableaus/__init__.py``; ``method =
"dopri", base = "<name>"`` then runs it with the same projection, error control and
compiled loop as the others.

Conventions (SciPy's): stages ``K_0 … K_{s−1}`` with ``K_i = f(t + c_i h, y + h Σ_j A_ij K_j)``,
the solution ``y + h Σ b_i K_i``, and ``K_s = f(t + h, y_new)`` (first-same-as-last). Each
error vector ``E`` has s + 1 entries and gives the estimate ``h Σ E_i K_i``; two vectors
(DOP853) are blended as Hairer does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Tableau:
    name: str
    A: np.ndarray  # (s, s) strictly lower triangular
    B: np.ndarray  # (s,)
    C: np.ndarray  # (s,)
    E: tuple[np.ndarray, ...]  # each (s + 1,)
    order: int
    error_order: int

    def __post_init__(self):
        s = len(self.B)
        if self.A.shape[0] != s or len(self.C) != s or any(len(e) != s + 1 for e in self.E):
            raise ValueError(f"tableau {self.name}: inconsistent sizes")
        # consistency: c_i = Σ_j A_ij and Σ b_i = 1 (first-order conditions)
        if not (np.allclose(self.A.sum(axis=1), self.C, atol=1e-14) and abs(self.B.sum() - 1) < 1e-14):
            raise ValueError(f"tableau {self.name}: row sums of A must be c and Σ b must be 1")

    @property
    def stages(self) -> int:
        return len(self.B)

    @property
    def exponent(self) -> float:
        """The step-size controller's exponent −1/(q + 1), q the error estimator's order."""
        return -1.0 / (self.error_order + 1)


def from_scipy(name: str, solver, errors) -> Tableau:
    """The tableau SciPy's explicit solver class ``solver`` holds, with its error vectors."""
    s = solver.n_stages
    A = np.zeros((s, s))
    A[:, : solver.A.shape[1]] = solver.A[:s, :s]
    return Tableau(name, A, np.asarray(solver.B, float), np.asarray(solver.C[:s], float),
                   tuple(np.asarray(e, float) for e in errors), solver.order, solver.error_estimator_order)
