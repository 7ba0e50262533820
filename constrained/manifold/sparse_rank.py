"""Rank and independent rows of a large sparse constraint Jacobian, without dense QR or SVD.

The dense route (pivoted QR of the C × 3N Jacobian) costs O(C²·N) time and C·3N memory: for
a 10,000-link chain 20,000 × 30,000, 4.8 GB. Here the rows of J are scaled to unit length,
Ĵ = D J W (W = M^(-1/2) for the mass-weighted test of the solvers, I for the report), and the
Gram matrix

    G = Ĵ Ĵᵀ + δ I,        δ = SHIFT

is factored by SuperLU in a fill-reducing symmetric order without pivoting — for the SPD G
that is a (stable) Cholesky factorization, O(N) on a chain. Its pivots d_k are the squared
diagonal of R in the QR factorization of Ĵᵀ taken in that order: a row that is a combination
of the rows eliminated before it leaves d_k = δ + O(ε), and since G − δI is positive
semidefinite its whole remaining row is then at round-off too, so the factorization goes on
unharmed and one pass finds every dependent row. But forming G squares the round-off: a
dependent row's √d_k sits near √ε·κ (κ the condition of the rows before it), 1e-8 for two
equal rods, 5e-5 for a cube held by all 28 rods at a random shape. So √d_k only sorts the
rows: above CHECK_BELOW a row is independent; every other row's distance from the span of the
independent rows eliminated before it is computed by the semi-normal equations with
refinement (error ε·κ, as a QR's) and compared with ``dependent_rtol``, the dense pivoted
QR's threshold. Of a dependent set, the row latest in scene order is named (an exchange
with the rows it depends on), as the dense QR names it.
"""

from __future__ import annotations

import sys

import casadi as ca
import numpy as np

from .rank_policy import RANK, RankPolicy


class _Lazy:
    """A module imported on first use: ``sp`` below is scipy.sparse, which (with the scipy
    core it brings) costs 0.07 s of imports that a small model's run never needs."""

    def __init__(self, name: str):
        self._name = name

    def __getattr__(self, attribute: str):
        import importlib

        return getattr(importlib.import_module(self._name), attribute)


sp = _Lazy("scipy.sparse")

#: Rows whose Gram pivot √d_k is above this are independent without a further test: the
#: pivot's round-off is about √ε·κ, so a dependent row stays far below it unless κ > 1e5.
CHECK_BELOW = 1e-3
#: δ: keeps G definite where rows are dependent (on G's unit diagonal it must exceed ε to count;
#: √δ = 1e-7, below cholesky_rtol = 1e-6).
SHIFT = 1e-14


def as_scipy(J) -> sp.csr_matrix:
    """A CasADi DM (sparse or dense), a SciPy sparse matrix or an array as SciPy CSR."""
    if isinstance(J, ca.DM):
        rows, cols = J.sparsity().get_triplet()
        return sp.csr_matrix((np.asarray(J.nonzeros(), float), (rows, cols)), shape=J.shape)
    return sp.csr_matrix(J, dtype=float)


def as_dense(J) -> np.ndarray:
    """A CasADi DM, a SciPy sparse matrix or an array as a dense NumPy array (SciPy is not
    imported to ask: a small model's start runs without it)."""
    return J.toarray() if "scipy.sparse" in sys.modules and sp.issparse(J) else np.asarray(J, float)


def scaled_rows(J, weights: np.ndarray | None = None) -> sp.csr_matrix:
    """Ĵ = D J W: J's columns times ``weights`` (None: 1), then each row scaled to unit length
    (a zero row stays zero)."""
    Js = as_scipy(J)
    if weights is not None:
        Js = Js @ sp.diags(np.asarray(weights, float))
    norms = np.sqrt(np.asarray(Js.multiply(Js).sum(axis=1)).ravel())
    return sp.diags(np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 0.0)) @ Js


def _factor(G: sp.spmatrix):
    """SuperLU of the SPD G in a fill-reducing symmetric order without pivoting (a Cholesky
    factorization); None when a pivot is exactly 0."""
    try:
        return splu()(G.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                         options={"SymmetricMode": True})
    except RuntimeError:
        return None


def gram_pivots(Jhat: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray] | None:
    """(√d_k of each row of Ĵ in row order, the rows in elimination order) from the
    factorization of G = Ĵ Ĵᵀ + δ I; None when SuperLU meets an exactly zero pivot."""
    C = Jhat.shape[0]
    if C == 0:
        return np.zeros(0), np.zeros(0, dtype=int)
    lu = _factor(Jhat @ Jhat.T + SHIFT * sp.identity(C))
    if lu is None:
        return None
    pivots = np.abs(lu.U.diagonal())  # in elimination order: original row i sits at perm_c[i]
    return np.sqrt(pivots[lu.perm_c]), np.argsort(lu.perm_c)


def least_squares_distance(Jhat: sp.csr_matrix, rows: np.ndarray, k: int) -> tuple[float, np.ndarray] | None:
    """(|ĵ_k − Ĵ_Pᵀ c|, c) with c minimizing it (P = ``rows``): the distance of row k from the
    span of those rows, by the semi-normal equations with refinement (accurate to ε·κ(Ĵ_P),
    not ε·κ², unlike the Gram pivot); None when the factorization fails."""
    jk = np.asarray(Jhat[k].todense()).ravel()
    if rows.size == 0:
        return float(np.linalg.norm(jk)), np.zeros(0)
    A = Jhat[rows]
    lu = _factor(A @ A.T + SHIFT * sp.identity(rows.size))
    if lu is None:
        return None
    c = np.zeros(rows.size)
    r = jk
    for _ in range(3):
        c = c + lu.solve(A @ r)
        r = jk - A.T @ c
    return float(np.linalg.norm(r)), c


def split_rows(Jhat: sp.csr_matrix, policy: RankPolicy = RANK) -> tuple[np.ndarray, np.ndarray] | None:
    """(independent rows, dependent rows), each sorted, of the row-normalized Ĵ. Rows whose
    Gram pivot is clearly large (> CHECK_BELOW) are independent; each other row is taken in
    elimination order and is dependent when its distance from the span of the independent
    rows before it is at most ``dependent_rtol`` (the dense pivoted QR's test). Of a dependent
    set the row latest in scene order is named, as the dense QR does: a dependent row k that
    is a combination ĵ_k = Σ c_j ĵ_j with some c_j ≠ 0 for j > k trades places with the last
    such j (the rows kept still span the same space). None when a factorization fails."""
    found = gram_pivots(Jhat)
    if found is None:
        return None
    u, order = found
    keep = u > CHECK_BELOW
    for position, k in enumerate(order):
        if keep[k]:
            continue
        before = order[:position][keep[order[:position]]]
        found = least_squares_distance(Jhat, before, int(k))
        if found is None:
            return None
        distance, c = found
        keep[k] = distance > policy.dependent_rtol
        later = before[(before > k) & (np.abs(c) > 1e-6 * np.max(np.abs(c), initial=0.0))]
        if not keep[k] and later.size:
            keep[k], keep[later.max()] = True, False
    return np.flatnonzero(keep), np.flatnonzero(~keep)


def independent_rows_sparse(J, weights: np.ndarray | None = None,
                            policy: RankPolicy = RANK) -> np.ndarray | None:
    """A maximal set of independent rows of J (sorted): rank J is its size. ``weights``: the
    column weights W (√ of the inverse masses for the mass-weighted test). None when the
    factorization fails (then use the dense pivoted QR)."""
    split = split_rows(scaled_rows(J, weights), policy)
    return None if split is None else split[0]


def splu():
    """SciPy's sparse LU (scipy.sparse.linalg, which imports scipy.linalg: 0.1 s, on first use)."""
    from scipy.sparse.linalg import splu

    return splu
