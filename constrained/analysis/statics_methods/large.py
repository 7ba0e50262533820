"""The statics of a large model (more than ``algebra.SPARSE_FROM`` constraint rows and no
velocity rows): J and the stiffness K as SciPy sparse matrices, the multipliers by the
sparse Schur solve, spectral norms by ARPACK, and one dense null-space basis for the
stability verdict where the small model's route takes three.

A catenary of 1,000 links of 1 cm (5,000 unknowns, under the statics' limit of 6,000) took
138 s with every matrix dense: 68 s forming J M⁻¹ Jᵀ densely for the multipliers after each
Newton step, 21 s converting CasADi matrices to dense arrays, three SVDs of J for tangent
bases (21 s) and two of K for its norm (20 s)."""

from __future__ import annotations

import numpy as np

from ...manifold.algebra import SPARSE, SPARSE_FROM
from ...manifold.sparse_rank import as_scipy
from ...model.structure import Model


def is_large(model: Model) -> bool:
    """Whether the statics of ``model`` take this module's sparse route."""
    return model.n_constraints > SPARSE_FROM and model.n_constraints == model.n_position_rows


def forces_at_rest(model: Model, x: np.ndarray, t: float):
    """F(x, v = 0, t) (3N,) and J (C, 3N) as SciPy CSR."""
    F, J, _ = model.dynamics(x, np.zeros_like(x), t)
    return np.asarray(F, float).ravel(), as_scipy(J)


def multipliers(model: Model, J, F: np.ndarray) -> np.ndarray:
    """λ of (J M⁻¹ Jᵀ) λ = −J M⁻¹ F (every particle at rest: a = 0), minimum-norm for
    redundant rows, refined on the force balance (``LinearAlgebra.multipliers`` with γ = 0)."""
    if J.shape[0] == 0:
        return np.zeros(0)
    return SPARSE.multipliers(J, model.inverse_masses, F, np.zeros(J.shape[0]), full_rank=False)


def dependent_rows(model: Model, J) -> np.ndarray:
    """The rows of J that depend on the others (``independent_rows``' complement, the
    manifold's rank decision), in order."""
    independent = SPARSE.independent_rows(J, model.inverse_masses)
    return np.setdiff1d(np.arange(J.shape[0]), independent).astype(np.int64)


def csc(dm):
    """A CasADi DM as SciPy CSC, straight from its compressed columns."""
    from scipy.sparse import csc_matrix

    colind, row = dm.sparsity().get_ccs()
    return csc_matrix((np.array(dm.nonzeros(), float), row, colind), shape=dm.shape)


def dense(dm) -> np.ndarray:
    """A CasADi DM as a dense array through its compressed columns (np.asarray walks every entry of
    a sparse DM: 0.54 s for a 1,800 × 2,700 Jacobian, against 0.03 s)."""
    if not hasattr(dm, "sparsity") or dm.nnz() == dm.numel():  # (an array, or a dense DM)
        return np.asarray(dm, float)
    # each nonzero assigned, not added to a zero (SciPy's toarray: 0.0 + −0.0 is +0.0), so the
    # array is np.asarray's, bit for bit: a −0.0 of J (x_a − x_b of equal coordinates, negated)
    # kept, whose sign the dense route's QR and eigh read (equilibria moved by 1e-14 without it)
    colind, row = dm.sparsity().get_ccs()
    out = np.zeros(dm.shape)
    out[row, np.repeat(np.arange(dm.shape[1]), np.diff(colind))] = dm.nonzeros()
    return out


def stiffness(function, x: np.ndarray, lam: np.ndarray):
    """K = ∇²ₓ(V − λᵀf) from the CasADi ``function`` (x, λ) -> K, as SciPy CSC."""
    return csc(function(x, lam))


#: ``spectral_norm``'s accuracy (of σ; ARPACK works on AᵀA) and its budget of ARPACK restarts.
SPECTRAL_NORM_RTOL, SPECTRAL_NORM_RESTARTS = 1e-6, 500


def spectral_norm(A) -> float:
    """‖A‖₂ (the largest singular value), dense or sparse (ARPACK, a few products)."""
    if isinstance(A, np.ndarray):
        return float(np.linalg.norm(A, 2)) if A.size else 0.0
    if A.nnz == 0:
        return 0.0
    from scipy.sparse.linalg import svds

    try:  # (tol: σ² to 1e-12 relative; without it a cluster of nearly equal top singular values — a
        # hanging net's identical columns — kept ARPACK going for 270,000 iterations, 50 s)
        return float(svds(A.astype(float), k=1, return_singular_vectors=False, random_state=20261128,
                          tol=SPECTRAL_NORM_RTOL, maxiter=SPECTRAL_NORM_RESTARTS)[0])
    except Exception:  # ARPACK did not converge: the Frobenius norm bounds it from above
        return float(np.linalg.norm(A.data))


def frobenius(A) -> float:
    """‖A‖_F, dense or sparse."""
    return float(np.linalg.norm(A)) if isinstance(A, np.ndarray) else float(np.linalg.norm(A.tocsr().data))


def scaled(K, r: np.ndarray):
    """diag(r) K diag(r), dense or sparse."""
    if isinstance(K, np.ndarray):
        return r[:, None] * K * r[None, :]
    from scipy.sparse import diags

    return (diags(r) @ K @ diags(r)).tocsc()


def weighted_basis(N: np.ndarray, r: np.ndarray) -> np.ndarray:
    """An orthonormal basis of null(J diag(r)) from one of null(J), ``N``: null(J R) = R⁻¹ null(J),
    orthonormalized (QR) instead of a second SVD of J."""
    if N.shape[1] == 0:
        return N
    Q, _ = np.linalg.qr(N / r[:, None])
    return Q
