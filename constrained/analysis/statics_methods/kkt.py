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

from ... import interrupt
from ...model.structure import Model

#: IPOPT's budget (CPU seconds, iterations) after Newton failed: then the failure is reported.
IPOPT_CPU_S, IPOPT_ITERATIONS = 30.0, 500
#: KKT systems of more unknowns (coordinates and multipliers) than this are solved with sparse
#: matrices: a 300-link catenary took 48 s in dense conversions and least squares (1,496
#: unknowns), a 1,000-link one did not finish in 10 minutes.
SPARSE_KKT_FROM = 600
#: The force balance cannot be met more closely than this many units of round-off of the
#: positions times the stiffness (``force_round_off``).
ROUND_OFF_UNITS = 64.0


def force_round_off(stiffness: np.ndarray, x: np.ndarray, size: float) -> np.ndarray:
    """The force balance's floor per coordinate (N): ``u ε Σ_j |K_ij| (|x_j| + size)``, u =
    ROUND_OFF_UNITS. Positions are known to ε |x_j| (plus ε × the size for the differences
    formed from them), and a stiffness K (N/m) turns that into a force: a 1 kg bob below a
    1e7 N/m spring 1.5 m from the origin balances its weight only to 1e7 × 3e-16 m ≈ 3e-9 N,
    more than 1e-10 of the weight. A tolerance below this floor can never be met."""
    K = abs(stiffness) if hasattr(stiffness, "tocsr") else np.abs(np.asarray(stiffness, float))
    if K.shape[0] * K.shape[1] == 0:
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
        jacobian = ca.jacobian(r, ca.vertcat(xs, lam))
        self.residual = ca.Function("kkt", [xs, lam], [r, jacobian])
        self.values = ca.Function("kkt_r", [xs, lam], [r])
        #: Solved with sparse matrices (``newton``): more unknowns than SPARSE_KKT_FROM.
        self.sparse = n3 + C > SPARSE_KKT_FROM
        #: Unknowns (indices into z = (x, λ)) of the dependent rows' multipliers, set by the
        #: caller: where the KKT matrix is singular for them, the sparse step holds them (and
        #: their rows of f) out, and ``restore`` splits the load minimum-norm after the step.
        self.dependent = np.zeros(0, dtype=np.int64)
        self._ccs = jacobian.sparsity().get_ccs() if self.sparse else None
        self.stiffness = ca.Function("stiffness", [xs, lam], [K])
        self.potential = ca.Function("V", [xs], [model.potential(xs, t)])
        self.objective = model.potential(xs, t)
        self.f = f
        self.xs = xs
        self.n3, self.C = n3, C

    def residual_and_jacobian(self, z: np.ndarray):
        """(r, ∂r/∂(x, λ)) at z = (x, λ): the matrix dense, or SciPy CSC when ``sparse``."""
        r, A = self.residual(z[: self.n3], z[self.n3 :])
        r = np.asarray(r, float).ravel()
        if not self.sparse:
            return r, np.asarray(A, float)
        from scipy.sparse import csc_matrix

        colind, row = self._ccs
        return r, csc_matrix((np.array(A.nonzeros(), float), row, colind), shape=(len(z), len(z)))

    def residual_only(self, z: np.ndarray) -> np.ndarray:
        """r at z (a trial point of the line search needs no Jacobian)."""
        return np.asarray(self.values(z[: self.n3], z[self.n3 :]), float).ravel()


def newton(
    kkt: KKT, z: np.ndarray, w: np.ndarray, max_iter: int, restore=None
) -> tuple[np.ndarray, int, bool]:
    """Newton on the scaled KKT residual W r(z) = 0 with a backtracking line search on
    ½‖W r‖², falling back to Levenberg–Marquardt steps when the Newton step does not descend.
    Steps use least squares (minimum norm) so redundant constraints do no harm. ``restore``
    maps each trial point back onto f = 0 (a second-order correction: without it the
    curvature of the constraints forces tiny steps)."""
    restore = restore or (lambda z: z)
    # (a caller's own KKT may give the residual with its Jacobian only, dense, no dependent rows)
    values = getattr(kkt, "residual_only", None) or (lambda z: kkt.residual_and_jacobian(z)[0])
    dependent = getattr(kkt, "dependent", np.zeros(0, dtype=np.int64))
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
        if interrupt.requested():
            raise KeyboardInterrupt
        B = _scaled_rows(w, A)
        b = w * r
        if not within and np.linalg.norm(B.T @ b) <= 1e-14 * _norm(B) * np.linalg.norm(b):
            return z, it, False  # ∇(½‖Wr‖²) = BᵀWr = 0 off the solution: no step can lower the merit
        dz = _least_squares_step(B, -b, dependent)
        accepted = False
        alpha = 1.0
        while alpha >= 1e-4:
            zn = restore(z + alpha * dz)
            mn = 0.5 * float(np.sum((w * values(zn)) ** 2))
            if np.isfinite(mn) and mn <= (1.0 - 1e-4 * alpha) * merit:
                accepted = True
                break
            alpha *= 0.5
        if not accepted:
            # Levenberg–Marquardt: (BᵀB + μI) dz = −Bᵀb, μ grown until the merit decreases
            BtB, Btb = B.T @ B, B.T @ b
            mu = 1e-6 * max(float(np.max(BtB.diagonal())), 1e-300)
            for _ in range(16):
                dz = _shifted_solve(BtB, mu, -Btb)
                zn = restore(z + dz)
                mn = 0.5 * float(np.sum((w * values(zn)) ** 2))
                if np.isfinite(mn) and mn < merit:
                    accepted = True
                    break
                mu *= 10.0
        if not accepted:
            return z, it, bool(np.all(np.abs(w * r) <= 1.0))
        z, merit = zn, mn
        r, A = kkt.residual_and_jacobian(z)
    return z, max_iter, bool(np.all(np.abs(w * r) <= 1.0))


def _scaled_rows(w: np.ndarray, A):
    """W A (rows scaled by w), dense or sparse as A."""
    if isinstance(A, np.ndarray):
        return w[:, None] * A
    from scipy.sparse import diags

    return (diags(w) @ A).tocsc()


def _norm(B) -> float:
    """‖B‖ (Frobenius), dense or sparse."""
    return float(np.linalg.norm(B)) if isinstance(B, np.ndarray) else float(np.linalg.norm(B.data))


def _least_squares_step(B, rhs: np.ndarray, dependent: np.ndarray) -> np.ndarray:
    """The minimum-norm least-squares solution of B dz = rhs (redundant constraints make B
    singular). Dense: LAPACK's (rcond 1e-14). Sparse: B's LU where B is regular (then the
    same dz); else the LU of B without the ``dependent`` rows' multipliers and rows of f
    (those multipliers held, the step otherwise the same); else LSMR (minimum norm from a zero
    start; slow: thousands of products with B)."""
    if isinstance(B, np.ndarray):
        return np.linalg.lstsq(B, rhs, rcond=1e-14)[0]
    from scipy.sparse.linalg import lsmr

    dz = _lu_solve(B, rhs)
    if dz is None and dependent.size:
        keep = np.setdiff1d(np.arange(B.shape[0]), dependent)
        kept = _lu_solve(B[keep][:, keep].tocsc(), rhs[keep])
        if kept is not None:
            dz = np.zeros(B.shape[1])
            dz[keep] = kept
    if dz is not None:
        return dz
    return lsmr(B, rhs, atol=1e-14, btol=1e-14, maxiter=10 * B.shape[1])[0]


def _lu_solve(B, rhs: np.ndarray) -> np.ndarray | None:
    """B⁻¹ rhs by SuperLU, or None where B is singular (a zero pivot, or a solution that does not
    solve: not finite, or its residual above 1e-10 of rhs)."""
    from scipy.sparse.linalg import splu

    try:
        with np.errstate(all="ignore"):
            dz = splu(B).solve(rhs)
    except RuntimeError:  # exactly singular
        return None
    ok = np.all(np.isfinite(dz)) and np.linalg.norm(B @ dz - rhs) <= 1e-10 * np.linalg.norm(rhs)
    return dz if ok else None


def _shifted_solve(BtB, mu: float, rhs: np.ndarray) -> np.ndarray:
    """(BᵀB + μ I)⁻¹ rhs, dense or sparse."""
    if isinstance(BtB, np.ndarray):
        return np.linalg.solve(BtB + mu * np.eye(len(rhs)), rhs)
    from scipy.sparse import identity
    from scipy.sparse.linalg import spsolve

    return spsolve((BtB + mu * identity(len(rhs), format="csc")).tocsc(), rhs)


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
