"""The dense linear algebra of the manifold (NumPy/SciPy): the scaled Schur solve with its
minimum-norm fallback, independent rows by pivoted QR, the full-rank test, the tangent basis.

Used for up to ``algebra.SPARSE_FROM`` constraint rows (``algebra.Dense``), and wherever a
small dense J is at hand (statics, one-sided constraints, diagnostics)."""

from __future__ import annotations

import numpy as np

from .rank_policy import RANK, RankPolicy
from .sparse_rank import as_dense


def schur_matrix(J: np.ndarray, inverse_masses: np.ndarray) -> np.ndarray:
    """A = J M⁻¹ Jᵀ for a (C, 3N) Jacobian and the flat inverse masses (3N,)."""
    return (J * inverse_masses) @ J.T


def row_scale(J: np.ndarray, inverse_masses: np.ndarray) -> np.ndarray:
    """D = diag(J M⁻¹ Jᵀ)^(-1/2), rows of zero weight left unscaled."""
    d = np.sqrt(np.einsum("ij,ij,j->i", J, J, inverse_masses))
    return np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), 1.0)


def schur_solve(J: np.ndarray, inverse_masses: np.ndarray, b: np.ndarray, *,
                policy: RankPolicy = RANK, full_rank: bool = True) -> np.ndarray:
    """Solve (J M⁻¹ Jᵀ) y = b; for dependent rows the least-squares y of minimum Euclidean
    norm |y| (the rows as written): of all multipliers giving the same constraint forces Jᵀy,
    the one with no component along the self-stress space null(Jᵀ).

    ``full_rank=False`` skips the Cholesky attempt (the caller knows rows are redundant).
    ``b`` may be a vector (C,) or a matrix (C, k).
    """
    J = as_dense(J)
    b = np.asarray(b, float)
    if J.shape[0] == 0:
        return np.zeros(b.shape)
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(b))):  # (a rod's 0/0 direction): no
        return np.full(b.shape, np.nan)  # solve; NaN for the caller's non-finite checks, not LAPACK's error
    s = row_scale(J, inverse_masses)
    sb = s * b if b.ndim == 1 else s[:, None] * b
    if full_rank:
        A = s[:, None] * schur_matrix(J, inverse_masses) * s[None, :]
        try:
            import scipy.linalg as sla  # (imported on first use: 0.1 s)

            L, lower = sla.cho_factor(A, lower=True, check_finite=False)
            d = np.abs(np.diag(L))
            if d.size and d.min() > policy.cholesky_rtol * d.max():
                z = sla.cho_solve((L, lower), sb, check_finite=False)
                return s * z if z.ndim == 1 else s[:, None] * z
        except (np.linalg.LinAlgError, ValueError):
            pass
    # SVD of Ĵ = D J M^(-1/2): A's scaled form is Ĵ Ĵᵀ = U Σ² Uᵀ, so z = U Σ⁻² Uᵀ (D b)
    Jhat = s[:, None] * J * np.sqrt(inverse_masses)[None, :]
    U, sv, _ = np.linalg.svd(Jhat, full_matrices=J.shape[0] > J.shape[1])
    keep = sv > policy.dependent_rtol * sv[0] if sv.size and sv[0] > 0 else np.zeros(sv.shape, bool)
    Uk, w = U[:, :sv.size][:, keep], 1.0 / sv[keep] ** 2
    z = Uk @ (w * (Uk.T @ sb)) if sb.ndim == 1 else Uk @ (w[:, None] * (Uk.T @ sb))
    y = s * z if z.ndim == 1 else s[:, None] * z
    # null(Ĵᵀ) is spanned by U's other columns, and null(Jᵀ) = D null(Ĵᵀ): z is minimum-norm
    # in the scaled rows, |D⁻¹ y|; the multipliers' own minimum norm takes null(Jᵀ) out of y
    dropped = np.concatenate([~keep, np.ones(U.shape[1] - sv.size, bool)])
    return without_self_stress(y, s[:, None] * U[:, dropped])


def without_self_stress(y: np.ndarray, N: np.ndarray) -> np.ndarray:
    """y less its Euclidean projection on span(N) (columns: a basis of null(Jᵀ), the
    self-stresses): the minimum-norm multipliers with the same constraint forces Jᵀy."""
    if N.shape[1] == 0:
        return y
    Q, _ = np.linalg.qr(N)
    return y - Q @ (Q.T @ y)


def independent_rows(J: np.ndarray, inverse_masses: np.ndarray, policy: RankPolicy = RANK) -> np.ndarray:
    """A maximal set of independent rows of J, in scene order (pivoted QR of Ĵᵀ; a row whose
    pivot is below ``dependent_rtol`` of the largest is implied by the others)."""
    if J.shape[0] == 0:
        return np.zeros(0, dtype=int)
    J = as_dense(J)
    Jhat = row_scale(J, inverse_masses)[:, None] * J * np.sqrt(inverse_masses)[None, :]
    import scipy.linalg as sla

    _, R, order = sla.qr(Jhat.T, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    if diag.size == 0 or diag[0] == 0:
        return np.zeros(0, dtype=int)
    rank = int(np.sum(diag > policy.dependent_rtol * diag[0]))
    return np.sort(order[:rank])


def independent_rows_after(J, first: int, inverse_masses: np.ndarray, policy: RankPolicy = RANK,
                           leading: np.ndarray | None = None) -> np.ndarray:
    """A maximal set of independent rows of J that keeps a maximal independent set of its
    ``first`` rows (``leading``, or found here): the rows after them (velocity rows) join
    only where they are independent of those. Each later row of Ĵ (unit length) is reduced
    by its projection on the span of the leading rows, and the remainders pass a pivoted QR
    with the cut-off ``dependent_rtol`` (of 1, the rows' length)."""
    J = as_dense(J)
    lead = independent_rows(J[:first], inverse_masses, policy) if leading is None else np.asarray(leading)
    Jhat = row_scale(J, inverse_masses)[:, None] * J * np.sqrt(inverse_masses)[None, :]
    rest = Jhat[first:].T
    if lead.size:
        Q, _ = np.linalg.qr(Jhat[lead].T)
        rest = rest - Q @ (Q.T @ rest)
    if rest.shape[1] == 0:
        return np.sort(lead)
    import scipy.linalg as sla

    _, R, order = sla.qr(rest, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    later = order[:int(np.sum(diag > policy.dependent_rtol))] + first
    return np.sort(np.concatenate([lead, later]).astype(int))


def full_row_rank(J, inverse_masses: np.ndarray, policy: RankPolicy = RANK) -> bool | None:
    """True when J shows full row rank by a Cholesky factorization of D A D; None when it
    cannot tell (a small pivot: use ``independent_rows``)."""
    J = np.asarray(J, float)
    s = row_scale(J, inverse_masses)
    try:
        L = np.linalg.cholesky(s[:, None] * schur_matrix(J, inverse_masses) * s[None, :])
    except np.linalg.LinAlgError:
        return None
    d = np.abs(np.diag(L))
    return True if d.size and d.min() > policy.cholesky_rtol * d.max() else None


def tangent_basis(J: np.ndarray, n: int | None = None, policy: RankPolicy = RANK) -> np.ndarray:
    """Orthonormal basis (n, d) of null(J), the admissible virtual displacements (SVD of the
    row-normalized J; singular values below ``dependent_rtol`` of the largest count as 0)."""
    J = np.asarray(J, float)
    n = J.shape[1] if n is None else n
    norms = np.linalg.norm(J, axis=1) if J.shape[0] else np.zeros(0)
    Jn = J[norms > 0] / norms[norms > 0, None]
    if Jn.shape[0] == 0:
        return np.eye(n)
    import scipy.linalg as sla

    return sla.null_space(Jn, rcond=policy.dependent_rtol)
