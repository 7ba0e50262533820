"""The descent's trust-region step on a large model (statics_methods.descent), without a dense
basis of the tangent space: the subproblem solved on a Krylov space (GLTR).

In the mass-weighted coordinates u = D x of the descent, with A = Jₖ D⁻¹ (the independent rows,
the manifold's rank decision) and the projection onto the tangent space null(A)

    P v = v − Aᵀ (A Aᵀ)⁻¹ A v        (one sparse LU of A Aᵀ per iterate, applied twice: the
                                      second pass removes what the first left of range(Aᵀ)),

the step minimizes gᵀp + ½ pᵀHp over tangent p with ‖p‖ ≤ Δ, where g = P D⁻¹∇V and H v =
P D⁻¹ ∇²ₓ(V − λᵀf) D⁻¹ v (λ = (A Aᵀ)⁻¹ A D⁻¹∇V, the least-squares multipliers). Lanczos from g
makes H tridiagonal on a growing Krylov space, where the dense route's exact solver
(trust_region.py: negative curvature, the hard case) gives the step; the space stops growing
when the step's residual is small (``_lanczos_step``). Steihaug's truncated conjugate gradients,
tried first, stop at the first direction of zero curvature — from a flat start that is every
step, and a 300-link rope released horizontal ran out of its 2,000 iterations; on Krylov spaces
it hangs in 154 (the dense route: 148), the 30 × 30 net in 27 (26): 2.9 s and 6.5 s of CPU,
against 14.6 s and 144–220 s on the dense route's QR of J per iteration.
"""

from __future__ import annotations

import numpy as np

from ... import interrupt
from . import large as _large
from .trust_region import trust_region_step

#: The Krylov space stops growing when the step's residual is below CG_RTOL × ‖g‖ for a step
#: inside the region (Newton's), LANCZOS_RTOL × ‖g‖ for one on its boundary; it holds at most
#: LANCZOS_VECTORS vectors (then the best step on it is taken).
CG_RTOL, LANCZOS_RTOL, LANCZOS_VECTORS = 1e-12, 0.1, 400


def sparse_rows(J, rows: int):
    """The first ``rows`` rows (the position rows) of a CasADi DM as SciPy CSR."""
    return _large.csc(J).tocsr()[:rows]


def _lanczos_step(hessian, g: np.ndarray, radius: float, newton_rtol: float) -> tuple[np.ndarray, bool]:
    """The trust-region step on the Krylov space of H from g (GLTR, Gould, Lucidi, Roma & Toint):
    Lanczos vectors Q_k (fully reorthogonalized) make H tridiagonal, T_k = Q_kᵀ H Q_k, and the
    subproblem min ‖g‖e₁ᵀy + ½ yᵀT_k y, ‖y‖ ≤ Δ is solved exactly (trust_region.trust_region_step,
    negative curvature and the hard case included); p = Q_k y. The space grows until H Q_k y + g,
    of norm β_{k+1}|y_k|, is below LANCZOS_RTOL (a step inside the region: ``newton_rtol``)
    × ‖g‖, or H has no new direction."""
    n, norm_g = len(g), float(np.linalg.norm(g))
    most = min(LANCZOS_VECTORS, n)
    Q = np.zeros((n, most))
    alphas, betas = np.zeros(most), np.zeros(most)
    Q[:, 0] = g / norm_g
    for k in range(most):
        if k % 64 == 63 and interrupt.requested():
            raise KeyboardInterrupt
        w = hessian(Q[:, k])
        alphas[k] = float(Q[:, k] @ w)
        for _ in range(2):  # (full reorthogonalization, twice: the vectors stay orthonormal)
            w = w - Q[:, :k + 1] @ (Q[:, :k + 1].T @ w)
        beta = float(np.linalg.norm(w))
        last = beta <= 1e-14 * norm_g or k + 1 == most
        if not (last or (k + 1) & k == 0 or (k + 1) % 32 == 0):  # (solved at 1, 2, 4, … 32, 64, 96, …)
            betas[k + 1] = beta
            Q[:, k + 1] = w / beta
            continue
        T = np.diag(alphas[:k + 1]) + np.diag(betas[1:k + 1], 1) + np.diag(betas[1:k + 1], -1)
        e1 = np.zeros(k + 1)
        e1[0] = norm_g
        y, newton = trust_region_step(e1, T, radius)
        residual = beta * abs(float(y[-1]))
        if residual <= (newton_rtol if newton else LANCZOS_RTOL) * norm_g or last:
            return Q[:, :k + 1] @ y, newton
        betas[k + 1] = beta
        Q[:, k + 1] = w / beta
    return np.zeros_like(g), False  # (most = 0: no tangent space)


def sparse_step(model, kkt, x: np.ndarray, F: np.ndarray, J, d: np.ndarray, radius: float,
                force_scale: float, force_rtol: float):
    """(dx, whether it is the interior Newton step, the predicted decrease of V, the step's length
    ‖p‖ in u = D x) of one step (module text), or None when no tangential force exceeds
    ``force_rtol`` × ``force_scale`` (N)."""
    from scipy.sparse import diags
    from scipy.sparse.linalg import splu

    keep = np.setdiff1d(np.arange(J.shape[0]), _large.dependent_rows(model, J))
    A = (J[keep] @ diags(1.0 / d)).tocsr()
    normal = splu((A @ A.T).tocsc()) if A.shape[0] else None

    def project(v: np.ndarray) -> np.ndarray:
        for _ in range(2):
            if normal is not None:
                v = v - A.T @ normal.solve(A @ v)
        return v

    grad = -F / d  # D⁻¹∇V
    g = project(grad)
    force = float(np.max(np.abs(g) * d, initial=0.0))  # (the tangential force, back in newtons)
    if force <= force_rtol * force_scale:
        return None
    multipliers = np.zeros(model.n_constraints)
    if normal is not None:
        multipliers[keep] = normal.solve(A @ grad)
    K = _large.stiffness(kkt.stiffness, x, multipliers)
    Ks = _large.scaled(0.5 * (K + K.T), 1.0 / d)

    def hessian(v: np.ndarray) -> np.ndarray:
        return project(Ks @ v)

    # an inexact Newton step far from the minimum, an exact one near it (the forcing term falls
    # with the tangential force: superlinear convergence without hundreds of vectors early on)
    newton_rtol = min(max(CG_RTOL, force / force_scale), LANCZOS_RTOL)
    p, newton = _lanczos_step(hessian, g, radius, newton_rtol)
    predicted = -(float(g @ p) + 0.5 * float(p @ hessian(p)))
    return p / d, newton, predicted, float(np.linalg.norm(p))
