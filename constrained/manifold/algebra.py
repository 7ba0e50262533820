"""The one dense/sparse choice: a ``LinearAlgebra`` picked once per model (by its number of
constraint rows) and asked by the manifold, the start, the quantities and the reports for every
numeric solve with J, so that no call decides again which linear algebra to use.

Both implementations answer the same questions with the same numbers (tests/test_scale_analysis.py
compares them):

- ``matrix(J)``: a CasADi J as the implementation's matrix (dense NumPy, or SciPy CSR: never
  C × 3N dense for a large model);
- ``schur_solve(J, m⁻¹, b)``: (J M⁻¹ Jᵀ) y = b, scaled, the minimum-norm y for dependent rows;
- ``full_row_rank(J, m⁻¹)``: True when a cheap factorization shows full rank, None when unsure;
- ``independent_rows(J, m⁻¹)``: a maximal independent set of rows, in scene order;
- ``multipliers(J, m⁻¹, F, γ)``: λ of the acceleration-level KKT system, refined on the
  equations of motion (accurate at any spread of the masses).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from . import dense, sparse
from .rank_policy import RANK, RankPolicy
from .sparse_rank import as_dense, as_scipy

#: From this many constraint rows on, a model's linear algebra is the sparse one.
SPARSE_FROM = 100
#: Rounds of iterative refinement of the multipliers (``LinearAlgebra.multipliers``), and the
#: relative residual of J a + γ below which none is needed (that of the sparse LDLᵀ's check).
REFINEMENTS = 2
REFINE_ABOVE = 1e-9


class LinearAlgebra:
    """The contract; ``Dense`` and ``Sparse`` implement it."""

    name = "?"

    def matrix(self, J: ca.DM):
        raise NotImplementedError

    def schur_solve(self, J, inverse_masses: np.ndarray, b: np.ndarray, *, policy: RankPolicy = RANK,
                    full_rank: bool = True) -> np.ndarray:
        raise NotImplementedError

    def full_row_rank(self, J, inverse_masses: np.ndarray, policy: RankPolicy = RANK) -> bool | None:
        raise NotImplementedError

    def multipliers(self, J, inverse_masses: np.ndarray, F: np.ndarray, gamma: np.ndarray, *,
                    policy: RankPolicy = RANK, full_rank: bool = True, start: np.ndarray | None = None
                    ) -> np.ndarray:
        """λ of (J M⁻¹ Jᵀ) λ = −γ − J M⁻¹ F (from ``start`` when given, else ``schur_solve``),
        refined on the equations of motion themselves: with a = M⁻¹ (F + Jᵀλ), the residual
        c = J a + γ is solved for again, λ ← λ + δλ with (J M⁻¹ Jᵀ) δλ = −c (REFINEMENTS
        rounds, where |c| exceeds REFINE_ABOVE of |γ| + |J M⁻¹ F|).

        Forming J M⁻¹ Jᵀ swamps a heavy bead's 1/m by a light one's: a 1 mg bead between two
        1 t beads on rods gives the 2 × 2 block (1/m_light) [[1, −1], [−1, 1]] plus 1e-3, and
        the tensions came out wrong by ε × the mass ratio (1.4e-7 of 19.6 kN, 138 times the
        light bead's weight). The residual c is computed through the forces F + Jᵀλ, where
        those tensions cancel before 1/m multiplies them, so each round gains the factor the
        solve loses (the tensions then to round-off)."""
        load = J @ (inverse_masses * F)
        lam = (self.schur_solve(J, inverse_masses, -gamma - load, policy=policy, full_rank=full_rank)
               if start is None else np.asarray(start, float))
        scale = np.max(np.abs(gamma), initial=0.0) + np.max(np.abs(load), initial=0.0) + 1e-300
        for _ in range(REFINEMENTS):
            c = J @ (inverse_masses * (F + J.T @ lam)) + gamma
            if not np.max(np.abs(c), initial=0.0) > REFINE_ABOVE * scale:
                break
            lam = lam + self.schur_solve(J, inverse_masses, -c, policy=policy, full_rank=full_rank)
        return lam

    def independent_rows(self, J, inverse_masses: np.ndarray, policy: RankPolicy = RANK) -> np.ndarray:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class Dense(LinearAlgebra):
    """NumPy/SciPy dense: Cholesky of D A D, the SVD of Ĵ for dependent rows, pivoted QR."""

    name = "dense"

    def matrix(self, J):
        return as_dense(J)

    def schur_solve(self, J, inverse_masses, b, *, policy=RANK, full_rank=True):
        return dense.schur_solve(J, inverse_masses, b, policy=policy, full_rank=full_rank)

    def full_row_rank(self, J, inverse_masses, policy=RANK):
        return dense.full_row_rank(as_dense(J), inverse_masses, policy)

    def independent_rows(self, J, inverse_masses, policy=RANK):
        return dense.independent_rows(J, inverse_masses, policy)


class Sparse(LinearAlgebra):
    """SciPy sparse with SuperLU: O(N) factorizations on chains, nets and cloth. Where a sparse
    factorization fails (an exactly zero pivot), the dense route answers instead."""

    name = "sparse"

    def matrix(self, J):
        return as_scipy(J)

    def schur_solve(self, J, inverse_masses, b, *, policy=RANK, full_rank=True):
        y = sparse.schur_solve(J, inverse_masses, b, policy=policy)
        return y if y is not None else DENSE.schur_solve(J, inverse_masses, b, policy=policy, full_rank=False)

    def full_row_rank(self, J, inverse_masses, policy=RANK):
        return sparse.full_row_rank(J, inverse_masses, policy)

    def independent_rows(self, J, inverse_masses, policy=RANK):
        if J.shape[0] == 0:
            return np.zeros(0, dtype=int)
        rows = sparse.independent_rows(J, inverse_masses, policy)
        return rows if rows is not None else DENSE.independent_rows(J, inverse_masses, policy)


DENSE, SPARSE = Dense(), Sparse()


def algebra_for(n_constraints: int) -> LinearAlgebra:
    """The linear algebra of a model with ``n_constraints`` rows: sparse beyond SPARSE_FROM."""
    return SPARSE if n_constraints > SPARSE_FROM else DENSE
