"""The lowest modes of a large conservative model without a dense tangent basis (constrained.modes
with ``count``; beside the large statics, whose sparse helpers it shares).

For a model with more than ``algebra.SPARSE_FROM`` position rows (statics_methods.large), at
rest in no frame, whose forces do not depend on the velocities and whose stiffness
``K₃ = −∂r/∂x`` (3N × 3N, r = F + Jᵀλ at the state's multipliers) is symmetric, the modes
are the generalized eigenproblem on the tangent space ``K₃ φ = ω² M φ``, ``J φ = 0``, written
without a basis of null(J) as the KKT pencil

    [[K₃, Jᵀ], [J, 0]] (φ, μ) = ω² [[M, 0], [0, 0]] (φ, μ)

(J without its dependent rows, which would make the matrix singular). Its finite eigenvalues
are the tangent ones; the others are infinite. ARPACK (``scipy.sparse.linalg.eigsh``) in
shift-invert mode about σ, with one sparse LU of ``[[K₃ − σM, Jᵀ], [J, 0]]``, gives the
``count`` eigenvalues nearest σ. σ lies below the whole spectrum: the tangent Rayleigh quotient
``φᵀK₃φ / φᵀMφ`` is at least the least eigenvalue of ``M^(-1/2) K₃ M^(-1/2)`` on all of R^{3N},
and Gershgorin's discs bound that from below, so the eigenvalues nearest σ are the lowest ones
(a negative ω², an unstable mode, included).

A 1,000-link chain (3,000 coordinates) took 136 s for all its modes by the dense route (SVD of J
for the basis, eigh of K, the shapes); its lowest ten take about 2 s here (docs/modes.md).
"""

from __future__ import annotations

import numpy as np

from ...errors import InputError
from ...model.structure import Model
from . import large as _large
from .kkt import force_round_off

__all__ = ["lowest_modes"]

#: Each computed pair must satisfy the pencil within this fraction of ‖K₃‖ ‖φ‖ (else refused).
RESIDUAL_RTOL = 1e-8


def lowest_modes(model: Model, balance, x: np.ndarray, t: float, count: int, size: float,
                 stationary_rtol: float):
    """(Φ (3N, k), ω² (k,), λ, residual, unbalanced, degrees of freedom, ‖M^(-1/2)K₃M^(-1/2)‖) of
    the ``count`` lowest modes by the KKT pencil (module docstring), Φᵀ M Φ = I; or None when the
    route does not apply (velocity-dependent forces, a non-symmetric K₃, count not below the
    degrees of freedom): then the dense route decides. ``balance``: linearization's CasADi
    Function (y, u, λ) -> (r, ∂r/∂y, ∂r/∂u, J, F) at Ω = 0. InputError when the state is not at
    rest, or when ARPACK fails (naming the fix: fewer modes, or the dense route)."""
    from scipy.sparse import bmat, diags
    from scipy.sparse.linalg import ArpackError, ArpackNoConvergence, LinearOperator, eigsh, splu

    n3 = model.n_coordinates
    F0, J = _large.forces_at_rest(model, x, t)
    lam = _large.multipliers(model, J, F0)
    r, Ry, Ru, _, _ = balance(x, np.zeros(n3), lam)
    r = np.asarray(r, float).ravel()
    Ru = _large.csc(Ru)
    if Ru.nnz and float(np.max(np.abs(Ru.data))) > 0.0:
        return None  # damping, magnetic or gyroscopic forces: the quadratic problem (dense)
    K3 = -_large.csc(Ry)
    kf = _large.frobenius(K3)
    if _large.frobenius(K3 - K3.T) > 1e-10 * max(kf, 1e-300):
        return None
    m = model.masses
    # the state at rest: r / m is the acceleration, tangential since J M⁻¹ r = 0 defines λ
    accel = max(float(np.max(np.abs(F0 / m), initial=0.0)),
                float(np.max(np.abs((J.T @ lam) / m), initial=0.0)), 1e-300)
    a = r / m
    unbalanced = float(np.max(np.abs(a), initial=0.0))
    floor = force_round_off(K3, x, size) / m
    if not np.all(np.abs(a) <= np.maximum(stationary_rtol * accel, floor)):
        raise InputError(f"the state is not at rest: the forces leave a tangential acceleration of "
                         f"{unbalanced:.3g} m/s²; linearize about an equilibrium (leave x out: statics "
                         "finds one)", where="x")
    keep = np.setdiff1d(np.arange(J.shape[0]), _large.dependent_rows(model, J))
    Jk = J[keep]
    dof = n3 - len(keep)
    k = min(int(count), dof)
    if k >= dof - 1 or k < 1:
        return None  # (ARPACK needs k below the dimension; all of them: the dense route)
    d = 1.0 / np.sqrt(m)
    Ks = _large.scaled(K3, d)
    off = np.asarray(abs(Ks).sum(axis=1)).ravel() - np.abs(Ks.diagonal())
    lower = float(np.min(Ks.diagonal() - off))  # Gershgorin: below every eigenvalue of Ks
    knorm = _large.spectral_norm(Ks)
    gap = 1e-6 * max(knorm, 1e-300)
    sigma = min(lower, 0.0) * (1.0 + 1e-3) - gap
    zeros = diags(np.zeros(len(keep)))
    A = bmat([[K3 - sigma * diags(m), Jk.T], [Jk, zeros]], format="csc")
    B = bmat([[diags(m), None], [None, zeros]], format="csc")
    try:
        lu = splu(A)
    except RuntimeError as exc:
        raise InputError(f"the KKT matrix of the modes is singular at the shift σ = {sigma:.3g} 1/s² "
                         f"({exc}); leave count out for the dense route", where="count") from None
    op = LinearOperator(A.shape, matvec=lu.solve, dtype=float)
    v0 = np.concatenate([np.random.default_rng(20261128).standard_normal(n3) * d, np.zeros(len(keep))])
    try:
        w2, V = eigsh(A, k=k, M=B, sigma=sigma, which="LM", OPinv=op, v0=v0,
                      ncv=min(max(2 * k + 1, 20), dof), maxiter=20 * n3)
    except (ArpackNoConvergence, ArpackError) as exc:
        raise InputError(f"the sparse eigensolver (ARPACK) did not converge for the lowest {k} modes "
                         f"({exc}); ask for fewer (count), or leave count out for the dense route",
                         where="count") from None
    order = np.argsort(w2)
    w2, Phi = w2[order], V[:n3, order]
    Phi = Phi / np.sqrt(np.einsum("ij,i,ij->j", Phi, m, Phi))[None, :]  # Φᵀ M Φ = I
    # each pair must solve the pencil: K₃ φ − ω² M φ = −Jᵀμ for some μ (its M⁻¹-projection off
    # range(M⁻¹Jᵀ) vanishes), and J φ = 0
    R = K3 @ Phi - (m[:, None] * Phi) * w2[None, :]
    S = splu((Jk @ diags(1.0 / m) @ Jk.T).tocsc())
    left = R - Jk.T @ S.solve(np.asarray(Jk @ (R / m[:, None])))
    scale_f = RESIDUAL_RTOL * max(kf, 1e-300) * np.linalg.norm(Phi, axis=0)
    bad = bool(np.any(np.linalg.norm(left, axis=0) > scale_f))
    bad = bad or bool(np.any(np.linalg.norm(Jk @ Phi, axis=0) > RESIDUAL_RTOL * np.linalg.norm(Phi, axis=0)
                             * _large.spectral_norm(Jk)))
    if bad or not np.all(np.isfinite(w2)):
        raise InputError("the sparse eigensolver's modes do not satisfy the constrained eigenproblem (the "
                         "shift-invert solve lost accuracy); leave count out for the dense route",
                         where="count")
    return Phi, w2, lam, unbalanced / accel, unbalanced, dof, knorm
