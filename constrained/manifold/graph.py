"""The manifold's solves as CasADi graphs: the KKT accelerations, the Newton and velocity
projection steps and the scaled Schur solve, for step loops built inside CasADi (dopri,
rattle, the fast paths of ``manifold.Manifold``) — the same formulas as ``dense``/``sparse``,
symbolic (SX) or with CasADi's sparse LDLᵀ/QR (MX)."""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..model.structure import Model
from .sparse_rows import row_max


def _casadi(values):
    """Numbers as a DM; a CasADi expression (masses that are formulas of p) as it is."""
    return values if isinstance(values, ca.SX | ca.MX) else ca.DM(values)


def _select(expr, rows):
    return expr if rows is None else expr[list(rows), :]


def position_rows(model, rows):
    """The rows of f among ``rows`` (all of them when None): the position rows come first,
    the velocity rows (no f) after them. None when that is every row of f."""
    C_f = model.n_position_rows
    if rows is None:
        return None if C_f == model.n_constraints else tuple(range(C_f))
    return tuple(k for k in rows if k < C_f)


def symbolic_spd_solve(A, rhs):
    """y with A y = rhs for a symmetric positive definite A, the sparse LDLᵀ factorization
    (AMD ordering, no pivoting: stable for SPD) written out as operations: about 0.6× the
    operations of the symbolic QR in an acceleration (216 against 336 for the double
    pendulum). SX arguments give SX; MX arguments call an SX Function of A's sparsity (it is
    inlined where the graph is expanded)."""
    if isinstance(A, ca.SX):
        D, Lt, p = ca.ldl(A)
        return ca.ldl_solve(rhs, D, Lt, p)
    key = (A.sparsity().serialize(), rhs.shape)
    solve = _SPD_SOLVES.get(key)
    if solve is None:
        As, bs = ca.SX.sym("A", A.sparsity()), ca.SX.sym("b", *rhs.shape)
        D, Lt, p = ca.ldl(As)
        solve = _SPD_SOLVES[key] = ca.Function("spd_solve", [As, bs], [ca.ldl_solve(bs, D, Lt, p)])
    return solve(A, rhs)


#: The SX solves of symbolic_spd_solve for MX graphs, by sparsity and right-hand side shape.
_SPD_SOLVES: dict = {}


def schur_solve_graph(J_left, J_right, inverse_masses, rhs, linsol: str | None = "qr"):
    """y with (J_left M⁻¹ J_rightᵀ) y = rhs, as a CasADi expression (J_left = J_right: the
    Schur complement; RATTLE's Newton step takes J at two states). ``linsol``: a CasADi
    linear solver plugin for MX graphs, None for SX (solved symbolically).

    Numeric linear solvers are scaled like the NumPy solve, D_l A D_r z = D_l rhs, y = D_r z,
    with D = diag(J M⁻¹ Jᵀ)^(-1/2) of each side: CasADi's sparse QR takes pivots below an
    absolute 1e-12 or so for zero, and h² M⁻¹ of a heavy particle is far below that. Symbolic
    solves (SX, "symbolicqr": the factorization written out) and the sparse LDLᵀ (no pivoting,
    so invariant to a symmetric diagonal scaling) are not scaled: there it would only add
    operations to every step of a compiled loop."""
    minv = _casadi(inverse_masses)
    if linsol in (None, "symbolicqr", "ldl"):  # no absolute pivot threshold: unscaled
        A = ca.mtimes(ca.mtimes(J_left, ca.diag(minv)), J_right.T)
        if linsol == "ldl":
            return ca.solve(A, rhs, linsol)
        if J_left is not J_right:  # not symmetric (RATTLE's two states): a symbolic QR
            return ca.solve(A, rhs) if linsol is None else ca.solve(A, rhs, linsol)
        return symbolic_spd_solve(A, rhs)

    def scale(J):
        return 1.0 / ca.sqrt(ca.mtimes(J * J, minv))

    # CasADi's sparse QR forms Householder norms without guarding against underflow: an entry
    # of J near 1e-160 (a coordinate that Newton leaves at 1e-160 instead of 0) squares to a
    # subnormal number and the factorization returns NaN. Such entries are zero in every
    # physical sense; they are flushed (RATTLE at small steps met them on the four-bar).
    J_left, J_right = _flush_underflow(J_left), _flush_underflow(J_right)
    d_left, d_right = scale(J_left), scale(J_right)
    # diagonal matrices (sparse) keep the scaling O(nnz): an outer product d_l d_rᵀ would be C × C
    Dl, Dr = ca.diag(d_left), ca.diag(d_right)
    A = ca.mtimes(ca.mtimes(ca.mtimes(Dl, J_left), ca.diag(minv)), ca.mtimes(Dr, J_right).T)
    b = ca.mtimes(Dl, rhs)
    z = ca.solve(A, b) if linsol is None else ca.solve(A, b, linsol)
    return ca.mtimes(Dr, z)


#: |entries| of J below this are taken as 0 in a numeric QR (their squares would underflow).
UNDERFLOW = 1e-150


def _flush_underflow(J):
    """J with its entries below UNDERFLOW set to 0, its sparsity kept: done on the vector of
    its nonzeros (elementwise operations on a large sparse MX matrix are slow to build)."""
    if isinstance(J, ca.SX | ca.DM):
        return J * (ca.fabs(J) >= UNDERFLOW)
    nz = ca.vec(J.nz[:])
    return ca.MX(J.sparsity(), nz * (ca.fabs(nz) >= UNDERFLOW))


def acceleration_graph(model: Model, X, V, T, *, rows=None, linsol: str = "ldl", feedback=None):
    """(a, λ) of the KKT system as CasADi expressions in (X, V, T): A λ = −γ − J M⁻¹ F,
    a = M⁻¹ (F + Jᵀ λ), over ``rows`` (all by default; λ holds those rows only).

    ``feedback = (α, β)`` imposes Baumgarte's J a + γ + 2α (J v + f_t) + β² f = 0 instead
    (a velocity row, having no f, takes 2α (A v + b) alone)."""
    minv = _casadi(model.inverse_masses)
    F, J, gamma = model.dynamics(X, V, T)
    if not model.n_constraints:
        return minv * F, (ca.SX if isinstance(X, ca.SX) else ca.MX)(0, 1)
    if feedback is not None:
        alpha, beta = feedback
        _, f_t = model.velocity_terms(X, T)
        f = model.constraint(X, T)
        f = ca.vertcat(f, type(f)(model.n_constraints - f.numel(), 1))  # velocity rows: no f
        gamma = gamma + 2 * alpha * (ca.mtimes(J, V) + f_t) + beta**2 * f
    J, gamma = _select(J, rows), _select(gamma, rows)
    lam = schur_solve_graph(J, J, model.inverse_masses, -gamma - ca.mtimes(J, minv * F), linsol)
    return minv * (F + ca.mtimes(J.T, lam)), lam


def position_step_graph(model: Model, X, T, *, rows=None, linsol: str = "qr"):
    """(f, dx): one mass-weighted Newton step toward f = 0 is x ← x − dx, dx = M⁻¹Jᵀ A⁻¹ f;
    f is over all rows of f (the residual), the step over those among ``rows`` (velocity rows
    have no position level)."""
    f, J = model.jacobian(X, T)
    rows = position_rows(model, rows)
    fs, Js = _select(f, rows), _select(J, rows)
    minv = _casadi(model.inverse_masses)
    if Js.shape[0] == 0:  # velocity rows only: nothing to project at the position level
        return f, type(X)(X.numel(), 1)
    return f, minv * ca.mtimes(Js.T, schur_solve_graph(Js, Js, model.inverse_masses, fs, linsol))


def velocity_correction_graph(model: Model, X, V, T, *, rows=None, linsol: str = "qr"):
    """dv with v ← v − dv the mass-weighted nearest velocity satisfying J v + f_t = 0 (and
    A v + b = 0: ``velocity_terms`` holds every row of the velocity level)."""
    J, f_t = model.velocity_terms(X, T)
    J, f_t = _select(J, rows), _select(f_t, rows)
    minv = _casadi(model.inverse_masses)
    c = ca.mtimes(J, V) + f_t
    return minv * ca.mtimes(J.T, schur_solve_graph(J, J, model.inverse_masses, c, linsol))


def no_velocity_correction(model: Model, v) -> bool:
    """Whether v − dv (``velocity_correction_graph``'s dv) is v itself, bit for bit, with no
    solve: every component of v is +0.0 and no term moves the constraints (no f_t, no velocity
    rows' b), so J v + f_t = 0 holds, dv = M⁻¹ Jᵀ A⁻¹ 0 is ±0 and v − dv is +0.0. A start at
    rest then needs no velocity correction (its Function: 40 ms on a 100 x 100 cloth)."""
    v = np.asarray(v, float)
    moving = getattr(model, "rheonomic", True) or getattr(model, "n_position_rows", -1) != model.n_constraints
    return not moving and not np.any(v) and not np.any(np.signbit(v))


def row_scales_expr(J, n_particles: int):
    """s_i = max_p |∂f_i/∂x_p| as a column (C,) of J's type (SX or MX), 1 where a row's gradient
    vanishes. O(nnz J) operations (constrained.sparse_rows): the squared per-particle norms
    Q = (J∘J) B, with B (3N × N) summing each particle's three columns, then each row's
    largest √Q_ip over its stored entries."""
    C = J.shape[0]
    if C == 0:
        return ca.SX(0, 1)
    B = ca.DM(ca.Sparsity.triplet(3 * n_particles, n_particles, list(range(3 * n_particles)),
                                  [k // 3 for k in range(3 * n_particles)]), 1.0)
    norms = row_max(ca.sqrt(ca.mtimes(J * J, B)))
    return ca.if_else(norms > 0, norms, 1.0)


def projection_graph(model: Model, x, v, t, *, rows=None, linsol: str = "qr"):
    """Two Newton steps onto f = 0, the second sharing its factorization with the velocity
    projection: (x, v, residual before the last step, in metres: max_i |f_i| / s_i with the row
    scales of ``row_scales_expr``, or the view's ``row_scales``). The step loops (dopri) use it.
    With velocity rows the positions are projected over J, the velocities over [J; A]."""
    minv = _casadi(model.inverse_masses)
    _, dx = position_step_graph(model, x, t, rows=rows, linsol=linsol)
    x = x - dx
    f, J = model.jacobian(x, t)
    s = model.row_scales(x, t) if hasattr(model, "row_scales") else row_scales_expr(J, model.n_particles)
    residual = ca.mmax(abs(f) / s) if f.numel() else type(x).zeros(1, 1)
    if model.n_position_rows < model.n_constraints:  # velocity rows: a solve of each level
        _, dx = position_step_graph(model, x, t, rows=rows, linsol=linsol)
        x = x - dx
        return x, v - velocity_correction_graph(model, x, v, t, rows=rows, linsol=linsol), residual
    _, f_t = model.velocity_terms(x, t)
    fs, Js, f_ts = _select(f, rows), _select(J, rows), _select(f_t, rows)
    sol = schur_solve_graph(Js, Js, model.inverse_masses, ca.horzcat(fs, ca.mtimes(Js, v) + f_ts), linsol)
    return x - minv * ca.mtimes(Js.T, sol[:, 0]), v - minv * ca.mtimes(Js.T, sol[:, 1]), residual
