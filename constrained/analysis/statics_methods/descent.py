"""A minimum of the potential V on the constraints f(x, t) = 0 by a trust-region Newton method.

The statics call it when Newton on the KKT conditions fails from the guess, for instance from a
rope laid out straight and horizontal: there the least-squares multipliers are 0 (the rods are at
right angles to gravity), ∇²ₓ(V − λᵀf) = ∇²V = 0, and the linearized force balance cannot lift
the weights at all (statics_methods.kkt). IPOPT from the same point takes a step of g/δ ≈ 1,000 m
(its Hessian regularization δ = 1e-4 against a 0.1 N weight), off the constraints, and does not
come back within its budget.

Every iterate stays on the constraints (a step is projected back, mass-weighted), so V itself is
the merit function. In the mass-weighted coordinates u = D x, D = diag √(m/m̄) (m̄ the mean mass,
so ‖δu‖² = Σ m_i |δx_i|² / m̄ measures a displacement by its kinetic-energy metric), with Z an
orthonormal basis of the tangent space null(J D⁻¹), the step p solves

    min  gᵀp + ½ pᵀHp   subject to ‖p‖ ≤ Δ,
    g = Zᵀ D⁻¹ ∇V,   H = Zᵀ D⁻¹ ∇²ₓ(V − λᵀf) D⁻¹ Z,   λ: least squares of D⁻¹(Jᵀλ − ∇V) = 0,

(V's Riemannian gradient and Hessian on the constraint manifold), exactly, by the eigenvalues of H:
p = −(H + μI)⁻¹ g with μ ≥ max(0, −λ_min(H)) such that ‖p‖ = Δ, or μ = 0 inside the region when
H ≻ 0 (a Newton step). Where H is zero or indefinite the step follows −g (the particles fall) or
a direction of negative curvature (a saddle is left). The ratio ρ of the actual to the predicted
decrease of V decides: ρ > 0.1 takes the step; ρ < ¼, or a projection that fails, sets
Δ = ‖p‖/4; ρ > ¾ on the boundary doubles Δ (up to the system's size).

The work is bounded: DESCENT_ITERATIONS iterations, DESCENT_CPU_S seconds of CPU, and a descent
that carries a particle farther than FAR_SIZES system sizes from the guess stops (V has no
minimum near it: unbounded below, or falling away forever). Ctrl-C is honoured between iterations.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ... import interrupt
from ...manifold import residual
from ...manifold.manifold import Manifold
from ...manifold.rank_policy import RANK
from ...model.structure import Model
from .descent_sparse import sparse_rows, sparse_step
from .kkt import KKT
from .large import dense, is_large
from .trust_region import trust_region_step

#: The descent's budget: iterations, CPU seconds (all threads), and how far (in system sizes) a
#: particle may move from the guess before V is judged to have no minimum near it.
DESCENT_ITERATIONS, DESCENT_CPU_S, FAR_SIZES = 2000, 300.0, 20.0
#: Hand over to Newton on the KKT conditions when the Newton step moves no particle by more
#: than STEP_RTOL × size, or the tangential force is below FORCE_RTOL × the force scale.
STEP_RTOL, FORCE_RTOL = 1e-10, 1e-10


@dataclass
class Descent:
    """Where the descent stopped: ``x`` (3N,), ``iterations``, ``reason`` one of ``"minimum"``
    (handed to Newton), ``"far"`` (V has no minimum near the guess), ``"budget"``, ``"stalled"``
    (the trust region collapsed), ``"non-finite"`` or ``"off the constraints"`` (x0 is not on them)."""

    x: np.ndarray
    iterations: int
    reason: str

    def explanation(self) -> str:
        """The reason in words, for the statics' failure message."""
        return {
            "minimum": "a descent of V on the constraints stopped at a point Newton could not complete",
            "far": f"V kept decreasing over more than {FAR_SIZES:g} system sizes from the guess "
                   "(no minimum near it: is V bounded below?)",
            "budget": "a descent of V on the constraints ran out of its budget "
                      f"({DESCENT_ITERATIONS} iterations or {DESCENT_CPU_S:g} s of CPU)",
            "stalled": "a descent of V on the constraints stalled (its trust region collapsed)",
            "non-finite": "a descent of V on the constraints met non-finite forces",
            "off the constraints": "the guess could not be projected onto the constraints to descend from",
        }[self.reason]


def _tangent_frame(Jd: np.ndarray, grad: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal basis Z of null(Jd) and the least-squares λ of Jdᵀλ = grad, both from one
    pivoted QR of the row-normalized Jdᵀ (rows dependent within RANK.dependent_rtol are dropped)."""
    if Jd.shape[0] == 0:
        return np.eye(n), np.zeros(0)
    norms = np.linalg.norm(Jd, axis=1)
    norms = np.where(norms > 0, norms, 1.0)
    Q, R, piv = sla.qr((Jd / norms[:, None]).T, pivoting=True, check_finite=False)
    diag = np.abs(np.diag(R))
    rank = int(np.sum(diag > RANK.dependent_rtol * max(float(diag[0]) if diag.size else 0.0, 1e-300)))
    lam = np.zeros(Jd.shape[0])
    if rank:
        lam[piv[:rank]] = sla.solve_triangular(R[:rank, :rank], Q[:, :rank].T @ grad, check_finite=False)
    return Q[:, rank:], lam / norms


def _dense_step(model: Model, kkt: KKT, x, F, Jp, d, radius: float, force_scale: float, force_rtol: float):
    """(dx, whether it is the interior Newton step, the predicted decrease of V, the step's length
    ‖p‖ in u = D x) of one trust-region step on a dense basis of the tangent space (the module's
    text), or None when no tangential force exceeds ``force_rtol`` × ``force_scale`` (N)."""
    n3 = len(x)
    Z, lam = _tangent_frame(Jp / d[None, :], -F / d, n3)
    g = -Z.T @ (F / d)
    if np.max(np.abs(Z @ g) * d, initial=0.0) <= force_rtol * force_scale:
        return None  # (the tangential force, back in newtons)
    multipliers = np.zeros(model.n_constraints)
    multipliers[:Jp.shape[0]] = lam
    K = dense(kkt.stiffness(x, multipliers))
    H = Z.T @ ((0.5 * (K + K.T) / np.outer(d, d)) @ Z)
    p, newton = trust_region_step(g, 0.5 * (H + H.T), radius)
    # (‖p‖ of the subspace's coordinates: ‖Z p‖ up to rounding, which the radius's next value
    # would carry into every later iteration)
    return (Z @ p) / d, newton, -(float(g @ p) + 0.5 * float(p @ H @ p)), float(np.linalg.norm(p))


def minimize_on_constraints(model: Model, kkt: KKT, manifold: Manifold, x0: np.ndarray, t: float,
                            size: float, force_scale: float) -> Descent:
    """Descend V from x0 (on the constraints) to a constrained minimum; see the module's text."""
    started = time.process_time()
    n3, rows = model.n_coordinates, model.n_position_rows
    masses = 1.0 / model.inverse_masses
    d = np.sqrt(masses / np.mean(masses))  # u = d x
    x, V = x0, float(kkt.potential(x0))
    if not residual.position_residual(model, x0, t) <= 1e-10 * size:
        return Descent(x0, 0, "off the constraints")  # (IPOPT may start off them; this method may not)
    radius, max_radius = 0.1 * size, size
    large = is_large(model)  # (no dense basis of the tangent space: descent_sparse)
    for it in range(DESCENT_ITERATIONS):
        if interrupt.requested():
            raise KeyboardInterrupt
        if time.process_time() - started > DESCENT_CPU_S:
            return Descent(x, it, "budget")
        F, J, _ = model.dynamics(x, np.zeros(n3), t)
        F = np.asarray(F, float).ravel()
        J = sparse_rows(J, rows) if large else dense(J).reshape(-1, n3)[:rows]
        if not (np.isfinite(V) and np.all(np.isfinite(F)) and np.all(np.isfinite(J.data if large else J))):
            return Descent(x, it, "non-finite")
        step = sparse_step if large else _dense_step
        found = step(model, kkt, x, F, J, d, radius, force_scale, FORCE_RTOL)
        if found is None:
            return Descent(x, it, "minimum")  # (the tangential force below FORCE_RTOL × the force scale)
        dx, newton, predicted, length = found
        if newton and np.max(np.abs(dx)) <= STEP_RTOL * size:
            return Descent(x, it, "minimum")
        if predicted <= 1e-15 * (abs(V) + force_scale * size):
            return Descent(x, it, "minimum")  # below V's round-off: Newton finishes
        with np.errstate(all="ignore"):
            trial = manifold.project_positions(x + dx, t, tol=1e-14 * size, max_iter=12)
        onto = np.isfinite(trial.residual) and trial.residual <= 1e-10 * size and np.all(np.isfinite(trial.x))
        V_trial = float(kkt.potential(trial.x)) if onto else np.inf
        rho = (V - V_trial) / predicted if np.isfinite(V_trial) else -np.inf
        if rho > 0.1:
            x, V = trial.x, V_trial
            if np.max(np.abs(x - x0)) > FAR_SIZES * size:
                return Descent(x, it + 1, "far")
        if rho < 0.25:
            radius = 0.25 * length  # (‖p‖ in u = D x)
            if radius <= 1e-14 * size:
                return Descent(x, it + 1, "stalled")
        elif rho > 0.75 and not newton:
            radius = min(2.0 * radius, max_radius)
    return Descent(x, DESCENT_ITERATIONS, "budget")
