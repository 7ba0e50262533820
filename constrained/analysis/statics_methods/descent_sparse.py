"""The descent's trust-region step on a large model (statics_methods.descent), without a dense
basis of the tangent space: projected conjugate gradients with Steihaug's stopping rules.

In the mass-weighted coordinates u = D x of the descent, with A = Jₖ D⁻¹ (the independent rows,
the manifold's rank decision) and the projection onto the tangent space null(A)

    P v = v − Aᵀ (A Aᵀ)⁻¹ A v        (one sparse LU of A Aᵀ per iterate, applied twice: the
                                      second pass removes what the first left of range(Aᵀ)),

the step minimizes gᵀp + ½ pᵀHp over tangent p with ‖p‖ ≤ Δ, where g = P D⁻¹∇V and H v =
P D⁻¹ ∇²ₓ(V − λᵀf) D⁻¹ v (λ = (A Aᵀ)⁻¹ A D⁻¹∇V, the least-squares multipliers). Conjugate
gradients from p = 0 (Steihaug; Gould, Hribar & Nocedal for the projection): a direction of
zero or negative curvature, or an iterate leaving the region, ends the step on the boundary
(from a flat start H = 0 and the first step follows −g: the particles fall); a residual below
CG_RTOL × ‖g‖ ends it inside as the Newton step. The dense route's 2,700 × 1,800 QR per
iteration (a 30 × 30 net: 2.4–5 s each) becomes a few hundred sparse products.
"""

from __future__ import annotations

import numpy as np

from ... import interrupt
from . import large as _large

#: Conjugate gradients stop inside the region (a Newton step) when the projected residual is
#: below this fraction of the projected gradient; after at most CG_ITERATIONS products.
CG_RTOL, CG_ITERATIONS = 1e-12, 5000


def sparse_rows(J, rows: int):
    """The first ``rows`` rows (the position rows) of a CasADi DM as SciPy CSR."""
    return _large.csc(J).tocsr()[:rows]


def _to_boundary(p: np.ndarray, direction: np.ndarray, radius: float) -> np.ndarray:
    """p + τ·direction with τ ≥ 0 and ‖p + τ·direction‖ = radius (‖p‖ ≤ radius)."""
    a, b, c = float(direction @ direction), float(p @ direction), float(p @ p) - radius**2
    if a == 0.0:
        return p
    tau = (-b + np.sqrt(max(b * b - a * c, 0.0))) / a
    return p + tau * direction


def sparse_step(model, kkt, x: np.ndarray, F: np.ndarray, J, d: np.ndarray, radius: float,
                force_floor: float):
    """(dx, whether it is the interior Newton step, the predicted decrease of V) of one step
    (module text), or None when no tangential force exceeds ``force_floor`` (N)."""
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
    if np.max(np.abs(g) * d, initial=0.0) <= force_floor:
        return None  # (the tangential force, back in newtons)
    multipliers = np.zeros(model.n_constraints)
    if normal is not None:
        multipliers[keep] = normal.solve(A @ grad)
    K = _large.stiffness(kkt.stiffness, x, multipliers)
    Ks = _large.scaled(0.5 * (K + K.T), 1.0 / d)

    def hessian(v: np.ndarray) -> np.ndarray:
        return project(Ks @ v)

    p, r = np.zeros_like(g), g.copy()
    direction, rr = -r, float(r @ r)
    stop = CG_RTOL**2 * rr
    newton = False
    for k in range(CG_ITERATIONS):
        if k % 64 == 63 and interrupt.requested():
            raise KeyboardInterrupt
        Hd = hessian(direction)
        curvature = float(direction @ Hd)
        if curvature <= 0.0:
            p = _to_boundary(p, direction, radius)
            break
        alpha = rr / curvature
        if np.linalg.norm(p + alpha * direction) >= radius:
            p = _to_boundary(p, direction, radius)
            break
        p = p + alpha * direction
        r = project(r + alpha * Hd)
        rr_next = float(r @ r)
        if rr_next <= stop:
            newton = True
            break
        direction, rr = -r + (rr_next / rr) * direction, rr_next
    predicted = -(float(g @ p) + 0.5 * float(p @ hessian(p)))
    return p / d, newton, predicted
