"""The one dense/sparse choice: a ``LinearAlgebra`` picked once per model (by its number of
constraint rows) and asked by the manifold, the start, the quantities and the reports for every
numeric solve with J, so that no call decides again which linear algebra to use.

Both implementations answer the same questions with the same numbers (tests/test_scale_analysis.py
compares them):

- ``matrix(J)``: a CasADi J as the implementation's matrix (dense NumPy, or SciPy CSR: never
  C × 3N dense for a large model);
- ``schur_solve(J, m⁻¹, b)``: (J M⁻¹ Jᵀ) y = b, scaled, the minimum-norm y for dependent rows;
- ``full_row_rank(J, m⁻¹)``: True when a cheap factorization shows full rank, None when unsure;
- ``independent_rows(J, m⁻¹)``: a maximal independent set of rows, in scene order.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from . import dense, sparse
from .rank_policy import RANK, RankPolicy
from .sparse_rank import as_dense, as_scipy

#: From this many constraint rows on, a model's linear algebra is the sparse one.
SPARSE_FROM = 100


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
