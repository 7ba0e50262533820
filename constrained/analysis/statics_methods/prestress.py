"""First-order motions that the constraints' self-stress holds at second order (statics' stability
verdict with redundant constraints).

With redundant rows J has a left null space: self-stresses ω (Jᵀω = 0), multipliers that can be
added to any λ without changing a force. The energy test on null(J) uses the Hessian of
V − λᵀf at one λ (the minimum-norm one), but a self-stress changes it by −Σ ω_k ∇²f_k (its
"stress matrix") unless that vanishes on the tangent space. It vanishes for a rod stated twice
(the two rows' Hessians cancel), not for a net of rods with both diagonals hanging in a plane:
every motion out of the plane keeps the rods' lengths to first order, and the cells' self-stress
(each square with its diagonals is rigid) forbids all of those motions but the real ones, the
folds along the lines between rows. The minimum-norm λ, one stress among all the valid ones,
called that hanging net unstable (ω² = −49 /s²).

For a tangent direction d with dᵀ(Σ ω_k ∇²f_k)d ≠ 0 for some self-stress ω, no curve on the
constraints leaves along d (differentiate ωᵀf = 0 twice along one: ωᵀJ x'' = 0 leaves
dᵀ(Σ ω_k ∇²f_k)d = 0), so such a direction is held at second order by a stress of the right sign and size,
whatever the minimum-norm λ says. Which directions a valid stress holds is a semidefinite
problem this module does not solve: where some stress matrix does not vanish on the tangent
space, a negative eigenvalue at the minimum-norm λ leaves the verdict undecided (None), while a
positive definite Hessian at it still proves a strict minimum (any one valid λ does).
(The real motions of the hanging net, its folds, are not in the common null space of the
stress matrices: a stress across a fold line has dᵀΩd = 0 there but Ωd ≠ 0.)"""

from __future__ import annotations

import numpy as np

from . import large as _large

#: Random combinations of the self-stresses whose stress matrices are tried.
COMBINATIONS = 3
#: A stress matrix's action counts as zero below this fraction of the stress's own scale.
NULL_RTOL = 1e-8


def _self_stresses(model, J, large: bool, rng) -> np.ndarray | None:
    """(C, COMBINATIONS) random combinations of the self-stresses (Jᵀω = 0), or None."""
    if large:
        from scipy.sparse import csr_matrix
        from scipy.sparse.linalg import splu

        J = csr_matrix(J)
        dep = _large.dependent_rows(model, J)
        if len(dep) == 0:
            return None
        ind = np.setdiff1d(np.arange(J.shape[0]), dep)
        Ji, Jd = J[ind], J[dep]
        lu = splu((Ji @ Ji.T).tocsc())
        c = rng.standard_normal((len(dep), COMBINATIONS))
        out = np.zeros((J.shape[0], COMBINATIONS))
        out[dep] = c
        out[ind] = -lu.solve(np.asarray(Ji @ (Jd.T @ c)))
        return out
    import scipy.linalg as sla

    from ...manifold.rank_policy import RANK

    norms = np.linalg.norm(J, axis=1)
    keep = norms > 0
    if not np.any(keep):
        return None
    S = sla.null_space((J[keep] / norms[keep, None]).T, rcond=RANK.dependent_rtol)
    if S.shape[1] == 0:
        return None
    out = np.zeros((J.shape[0], COMBINATIONS))
    out[keep] = (S @ rng.standard_normal((S.shape[1], COMBINATIONS))) / norms[keep, None]
    return out


def tangent_sample(model, J, count: int = COMBINATIONS + 1) -> np.ndarray:
    """(3N, count) orthonormal random directions of the tangent space null(J), J sparse: where no
    basis N of it is built (``modes``' sparse route) they stand in for one in ``stress_matters``.
    A stress matrix that is not zero on the tangent space has a quadratic form that is a nonzero
    polynomial in a random tangent direction's coefficients, so ZᵀΩZ ≠ 0 with probability one.
    The projection z − Jₖᵀ(JₖJₖᵀ)⁻¹Jₖz uses the independent rows Jₖ (the manifold's rank decision)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.linalg import splu

    J = csr_matrix(J)
    Z = np.random.default_rng(20261129).standard_normal((J.shape[1], count))
    Jk = J[np.setdiff1d(np.arange(J.shape[0]), _large.dependent_rows(model, J))]
    if Jk.shape[0]:
        Z = Z - Jk.T @ splu((Jk @ Jk.T).tocsc()).solve(np.asarray(Jk @ Z))
    return np.linalg.qr(Z)[0]


def stress_matters(model, stiffness, x: np.ndarray, J, large: bool, N: np.ndarray) -> bool:
    """Whether some self-stress of the redundant rows of J changes the Hessian of V − λᵀf on the
    tangent space (basis N): its stress matrix Nᵀ(Σ ω_k ∇²f_k)N is not zero. False without
    redundant rows, or when their stress matrices vanish (a rod stated twice).
    ``stiffness(x, λ)``: ∇²(V − λᵀf)."""
    if N.shape[1] == 0:
        return False
    W = _self_stresses(model, J, large, np.random.default_rng(20261128))
    if W is None:
        return False
    K0 = stiffness(x, np.zeros(J.shape[0]))
    for i in range(W.shape[1]):
        Q = N.T @ np.asarray((stiffness(x, W[:, i]) - K0) @ N)
        ref = _large.frobenius(stiffness(x, np.abs(W[:, i])) - K0)
        if np.any(np.abs(Q) > NULL_RTOL * max(ref, 1e-300)):
            return True
    return False
