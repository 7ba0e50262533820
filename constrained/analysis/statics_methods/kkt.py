"""The KKT conditions of statics, F(x) + J(x)ᵀλ = 0, f(x, t) = 0, and two ways to solve them:
Newton on the residual (any stationary point near the guess) and IPOPT (a constrained minimum of V).

``newton`` stops at once where the merit ½‖W r‖² is stationary off the solution, BᵀW r = 0 with
B = W ∂r/∂(x, λ): neither its line search nor Levenberg–Marquardt can lower it there. A rope laid
out straight at right angles to gravity is such a point: J M⁻¹F = 0 gives λ = 0, so ∇²ₓL = ∇²V = 0
(gravity is linear) and the rods' gradients have no vertical part; the rows of the vertical
force balance in ∂r/∂(x, λ) vanish while their residual is the weights (statics_methods.descent
takes over from there).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ...model.structure import Model

#: IPOPT's budget (CPU seconds, iterations) after Newton failed: then the failure is reported.
IPOPT_CPU_S, IPOPT_ITERATIONS = 30.0, 500
#: The force balance cannot be met more closely than this many units of round-off of the
#: positions times the stiffness (``force_round_off``).
ROUND_OFF_UNITS = 64.0


def force_round_off(stiffness: np.ndarray, x: np.ndarray, size: float) -> np.ndarray:
    """The force balance's floor per coordinate (N): ``u ε Σ_j |K_ij| (|x_j| + size)``, u =
    ROUND_OFF_UNITS. Positions are known to ε |x_j| (plus ε × the size for the differences
    formed from them), and a stiffness K (N/m) turns that into a force: a 1 kg bob below a
    1e7 N/m spring 1.5 m from the origin balances its weight only to 1e7 × 3e-16 m ≈ 3e-9 N,
    more than 1e-10 of the weight. A tolerance below this floor can never be met."""
    K = np.abs(np.asarray(stiffness, float))
    if K.size == 0:
        return np.zeros(len(x))
    return ROUND_OFF_UNITS * np.finfo(float).eps * (K @ (np.abs(np.asarray(x, float)) + size))


class KKT:
    """CasADi functions of the static problem of one model at a fixed t."""

    def __init__(self, model: Model, t: float):
        n3, C = model.n_coordinates, model.n_constraints
        xs, lam = ca.SX.sym("x", n3), ca.SX.sym("lam", C)
        F, J, _ = model.dynamics(xs, ca.SX.zeros(n3), t)
        f = model.constraint(xs, t)
        g = F + ca.mtimes(J.T, lam)  # force balance = −∇ₓ(V − λᵀf)
        K = -ca.jacobian(g, xs)  # ∇²ₓ(V − λᵀf) for potential forces
        r = ca.vertcat(g, f)
        self.residual = ca.Function("kkt", [xs, lam], [r, ca.jacobian(r, ca.vertcat(xs, lam))])
        self.stiffness = ca.Function("stiffness", [xs, lam], [K])
        self.potential = ca.Function("V", [xs], [model.potential(xs, t)])
        self.objective = model.potential(xs, t)
        self.f = f
        self.xs = xs
        self.n3, self.C = n3, C

    def residual_and_jacobian(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, A = self.residual(z[: self.n3], z[self.n3 :])
        return np.asarray(r, float).ravel(), np.asarray(A, float)


def newton(
    kkt: KKT, z: np.ndarray, w: np.ndarray, max_iter: int, restore=None
) -> tuple[np.ndarray, int, bool]:
    """Newton on the scaled KKT residual W r(z) = 0 with a backtracking line search on
    ½‖W r‖², falling back to Levenberg–Marquardt steps when the Newton step does not descend.
    Steps use least squares (minimum norm) so redundant constraints do no harm. ``restore``
    maps each trial point back onto f = 0 (a second-order correction: without it the
    curvature of the constraints forces tiny steps)."""
    restore = restore or (lambda z: z)
    z = restore(z)
    r, A = kkt.residual_and_jacobian(z)
    merit = 0.5 * float(np.sum((w * r) ** 2))
    polish = 0
    for it in range(1, max_iter + 1):
        if not np.isfinite(merit):
            return z, it, False
        within = bool(np.all(np.abs(w * r) <= 1.0))
        if within:
            polish += 1  # within tolerance: a couple more steps take it to round-off
            if polish > 2:
                return z, it - 1, True
        B = w[:, None] * A
        b = w * r
        if not within and np.linalg.norm(B.T @ b) <= 1e-14 * np.linalg.norm(B) * np.linalg.norm(b):
            return z, it, False  # ∇(½‖Wr‖²) = BᵀWr = 0 off the solution: no step can lower the merit
        dz, *_ = np.linalg.lstsq(B, -b, rcond=1e-14)
        accepted = False
        alpha = 1.0
        while alpha >= 1e-4:
            zn = restore(z + alpha * dz)
            rn, An = kkt.residual_and_jacobian(zn)
            mn = 0.5 * float(np.sum((w * rn) ** 2))
            if np.isfinite(mn) and mn <= (1.0 - 1e-4 * alpha) * merit:
                accepted = True
                break
            alpha *= 0.5
        if not accepted:
            # Levenberg–Marquardt: (BᵀB + μI) dz = −Bᵀb, μ grown until the merit decreases
            BtB, Btb = B.T @ B, B.T @ b
            mu = 1e-6 * max(float(np.max(np.diag(BtB))), 1e-300)
            for _ in range(16):
                dz = np.linalg.solve(BtB + mu * np.eye(len(z)), -Btb)
                zn = restore(z + dz)
                rn, An = kkt.residual_and_jacobian(zn)
                mn = 0.5 * float(np.sum((w * rn) ** 2))
                if np.isfinite(mn) and mn < merit:
                    accepted = True
                    break
                mu *= 10.0
        if not accepted:
            return z, it, bool(np.all(np.abs(w * r) <= 1.0))
        z, r, A, merit = zn, rn, An, mn
    return z, max_iter, bool(np.all(np.abs(w * r) <= 1.0))


def ipopt_minimum(kkt: KKT, x0: np.ndarray) -> np.ndarray | None:
    """A constrained minimum of V near x0 (IPOPT), or None when IPOPT fails."""
    try:
        nlp = {"x": kkt.xs, "f": kkt.objective, "g": kkt.f}
        opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.tol": 1e-12,
                "ipopt.max_cpu_time": IPOPT_CPU_S, "ipopt.max_iter": IPOPT_ITERATIONS}
        solver = ca.nlpsol("statics", "ipopt", nlp, opts)
        sol = solver(x0=x0, lbg=0, ubg=0)
        x = np.asarray(sol["x"], float).ravel()
        return x if np.all(np.isfinite(x)) else None
    except RuntimeError:
        return None
