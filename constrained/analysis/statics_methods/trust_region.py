"""The trust-region subproblem min gᵀp + ½ pᵀHp over ‖p‖ ≤ radius, solved exactly on a small dense H
(the statics' descent: on a dense basis of the tangent space, or on a Krylov space of it)."""

from __future__ import annotations

import numpy as np


def trust_region_step(g: np.ndarray, H: np.ndarray, radius: float) -> tuple[np.ndarray, bool]:
    """argmin gᵀp + ½ pᵀHp over ‖p‖ ≤ radius (H symmetric) and whether it is the interior Newton
    step −H⁻¹g (H ≻ 0). On the boundary p(μ) = −(H + μI)⁻¹g, ‖p(μ)‖ = radius, μ > −λ_min found
    by bisection on the eigenvalues; in the "hard case" (g ⟂ the lowest eigenvector) the
    eigenvector completes p to the boundary."""
    curv, Q = np.linalg.eigh(H)
    gq = Q.T @ g
    if curv[0] > 0:
        p = -Q @ (gq / curv)
        if np.linalg.norm(p) <= radius:
            return p, True
    scale = max(float(np.max(np.abs(curv))), float(np.linalg.norm(g)) / radius, 1e-300)
    low = max(0.0, -float(curv[0])) + 1e-12 * scale

    def length(mu: float) -> float:
        return float(np.linalg.norm(gq / (curv + mu)))

    if length(low) <= radius:  # hard case: add the direction of least curvature
        p = -Q @ (gq / (curv + low))
        return p + np.sqrt(max(radius**2 - float(p @ p), 0.0)) * Q[:, 0], False
    high = low + float(np.linalg.norm(g)) / radius + scale
    for _ in range(200):  # ‖p(μ)‖ decreases with μ: bisect (geometrically while the range is wide)
        mid = np.sqrt(low * high) if high > 4 * low else 0.5 * (low + high)
        low, high = (mid, high) if length(mid) > radius else (low, mid)
        if high - low <= 1e-12 * high:
            break
    return -Q @ (gq / (curv + high)), False
