"""The sparse linear algebra of the manifold (SciPy sparse, SuperLU), for more than
``algebra.SPARSE_FROM`` constraint rows (``algebra.Sparse``): the full-rank test by a sparse LU,
independent rows by the Gram factorization (``sparse_rank``), and the minimum-norm Schur solve.

(J M⁻¹ Jᵀ) y = b for a large sparse J with dependent rows: the minimum-norm y, sparsely.

The dense ``manifold.schur_solve`` takes the SVD of Ĵ = D J M^(-1/2) (D = diag(J M⁻¹ Jᵀ)^(-1/2))
and returns y = D z with z the minimum-norm solution of (Ĵ Ĵᵀ) z = D b. For C rows beyond a
few thousand that SVD is out of reach (C × 3N dense). The same z, sparsely:

1. the independent rows I and the dependent rows R (constrained.sparse_rank);
2. a particular solution z_p: G_II z_I = (D b)_I by a sparse LU of G_II = Ĵ_I Ĵ_Iᵀ, z_R = 0;
3. the null space of G = Ĵ Ĵᵀ (that of Ĵᵀ): each dependent row is a combination of the
   independent ones, ĵ_r = Ĵ_Iᵀ c_r with G_II c_r = Ĵ_I ĵ_rᵀ, so n_r = e_r − c_r (on I) spans it;
4. z = P z_p with P = I − N (NᵀN)⁻¹ Nᵀ the projector onto range(G), and D b replaced by
   P D b in step 2 first: z = G⁺ D b, the minimum-norm least-squares solution, as the SVD's;
5. y = D z less its projection on null(Jᵀ) = D N: the multipliers of minimum Euclidean norm
   (``dense.without_self_stress``), as the dense solve returns them.

Cost: one sparse factorization and |R| + 1 solves, O(N) each on a chain.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .dense import without_self_stress
from .rank_policy import RANK, RankPolicy
from .sparse_rank import as_scipy, independent_rows_sparse, sp, split_rows, splu


def schur_solve(J, inverse_masses: np.ndarray, b: np.ndarray, *,
                       policy: RankPolicy = RANK) -> np.ndarray | None:
    """The minimum-norm y of (J M⁻¹ Jᵀ) y = b (scaled as ``schur_solve``), b of shape (C,) or
    (C, k); None when a factorization fails (the caller's dense route)."""
    Js = as_scipy(J)
    b = np.asarray(b, float)
    C = Js.shape[0]
    if C == 0:
        return np.zeros(b.shape)
    W = Js @ sp.diags(np.sqrt(np.asarray(inverse_masses, float)))
    d = np.sqrt(np.asarray(W.multiply(W).sum(axis=1)).ravel())
    s = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)  # zero rows left unscaled
    Jhat = sp.diags(s) @ W
    split = split_rows(Jhat, policy)
    if split is None:
        return None
    independent, dependent = split
    sb = s * b if b.ndim == 1 else s[:, None] * b
    z = np.zeros(b.shape)
    if independent.size:
        JI = Jhat[independent]
        try:
            lu = splu()((JI @ JI.T).tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                           options={"SymmetricMode": True})
        except RuntimeError:
            return None
        if dependent.size:
            N = np.zeros((C, dependent.size))
            N[dependent, np.arange(dependent.size)] = 1.0
            N[independent] = -lu.solve(np.asarray((JI @ Jhat[dependent].T).todense()))
            NtN = N.T @ N
            sb = sb - N @ np.linalg.solve(NtN, N.T @ sb)  # onto range(G): the least-squares b
        z[independent] = lu.solve(sb[independent])
        if dependent.size:
            z = z - N @ np.linalg.solve(NtN, N.T @ z)
    y = s * z if z.ndim == 1 else s[:, None] * z
    if independent.size and dependent.size:  # minimum |y|, not |D⁻¹ y|: null(Jᵀ) = D null(Ĵᵀ)
        y = without_self_stress(y, s[:, None] * N)
    return y


#: The floor on √ of every LDLᵀ pivot of D A D (unit diagonal) for CasADi's test below to call the
#: rows independent: a dependent row leaves a pivot at round-off, √ near 1e-8 (and the policy's
#: least-squares test cuts at 1e-9): this leaves five orders of magnitude (sparse_rank.CHECK_BELOW).
LDL_FLOOR = 1e-3


def full_row_rank(J, inverse_masses: np.ndarray, policy: RankPolicy = RANK) -> bool | None:
    """True when J shows full row rank by a sparse LU of D A D (O(N) on a chain); None when it
    cannot tell (a small pivot: use ``independent_rows``). A CasADi J is first tested by CasADi's
    sparse LDLᵀ (``clearly_full_row_rank``): when that settles it, SciPy is not imported (0.35 s)."""
    if isinstance(J, ca.DM) and clearly_full_row_rank(J, inverse_masses, policy):
        return True
    Js = as_scipy(J)
    A = (Js @ sp.diags(np.asarray(inverse_masses, float)) @ Js.T).tocsc()
    d = A.diagonal()
    if d.size == 0 or np.any(d <= 0):
        return None
    s = sp.diags(1.0 / np.sqrt(d))
    try:
        lu = splu()((s @ A @ s).tocsc(), diag_pivot_thresh=0.0)
    except RuntimeError:  # exactly singular
        return None
    u = np.sqrt(np.abs(lu.U.diagonal()))  # pivots of D A D are squares of Ĵ's
    return True if u.min() > policy.cholesky_rtol * u.max() else None


def clearly_full_row_rank(J: ca.DM, inverse_masses: np.ndarray, policy: RankPolicy = RANK) -> bool:
    """Whether every pivot of the LDLᵀ factorization of D A D = Ĵ Ĵᵀ (Ĵ = D J M^(-1/2), rows of unit
    length; CasADi's, in an approximate minimum degree order: O(N) on chains and cloth) has its √
    above LDL_FLOOR and the policy's ``cholesky_rtol`` of the largest: each row is then far from
    the span of the rows eliminated before it, so none is dependent. False when it cannot tell
    (a zero row, a small pivot: a redundant set, or rows merely near one)."""
    if J.numel() == 0 or J.size1() == 0:
        return False
    sparsity = J.sparsity()
    kept = getattr(J, "compressed_columns", None)  # (at_point.JacobianAt: kept as NumPy)
    colind, row = kept() if kept else (np.asarray(a, dtype=np.int64) for a in sparsity.get_ccs())
    col = np.repeat(np.arange(J.size2()), np.diff(colind))
    w = np.asarray(J.nonzeros(), float) * np.sqrt(np.asarray(inverse_masses, float))[col]
    norms = np.sqrt(np.bincount(row, weights=w * w, minlength=J.size1()))
    if not (np.all(np.isfinite(norms)) and np.all(norms > 0)):
        return False
    Jhat = ca.DM(sparsity, (w / norms[row]).tolist())  # (a list: 2x faster than an array)
    pivots = np.asarray(ca.ldl(ca.mtimes(Jhat, Jhat.T), True)[0], float).ravel()
    if not np.all(np.isfinite(pivots)):
        return False
    u = np.sqrt(np.maximum(pivots, 0.0))
    return bool(u.min() > max(LDL_FLOOR, policy.cholesky_rtol * u.max()))


def independent_rows(J, inverse_masses: np.ndarray, policy: RankPolicy = RANK) -> np.ndarray | None:
    """A maximal set of independent rows of J (sorted), by the mass-weighted Gram factorization
    (``sparse_rank``); None when a factorization fails."""
    return independent_rows_sparse(J, np.sqrt(np.asarray(inverse_masses, float)), policy)
