"""``rodas``: a linearly implicit (Rosenbrock) method on the index-1 DAE, for stiff systems.

Fine discretizations are stiff: a taut rope of 1 cm links carries transverse waves of
thousands of radians per second, and an explicit method (``dopri``) has to resolve them,
whatever the accuracy asked. RODAS (solvers/tableaus/rodas4.py: order 4, L-stable, stiffly
accurate, Hairer and Wanner's) takes steps set by accuracy. It integrates the semi-explicit
index-1 DAE in y = (x, v, λ) with the independent constraint rows (``Solver.rows``):

    x' = v,    v' = a = M⁻¹ (F(x, v, t) + J(x)ᵀ λ),    0 = g = J a + γ(x, v, t),

(the acceleration-level constraint, algebraic in λ: ∂g/∂λ = J M⁻¹ Jᵀ), mass matrix
diag(I, I, 0). Each step factors W = diag(I, I, 0)/(γh) − ∂(v, a, g)/∂(x, v, λ) once (CasADi
differentiates, sparse) and solves it six times. The x block is eliminated first
(U_x = γh (r_x + U_v)), so the sparse LU (SciPy's SuperLU) is of the matrix

    K = [[I/(γh) − a_v − γh a_x,  −a_λ],
         [−(g_v + γh g_x),         −g_λ]]      (3N + C square, banded for a chain: O(N)).

Error control on x and v (the scaled RMS of the embedded estimate, SciPy's norm; the
controller's exponent 1/4); after each accepted step the state is projected onto f = 0 and
J v + f_t = 0 like dopri's and λ is made consistent with it (the KKT solve), so the next step
starts on the manifold. Output times end a step each, or (more than LANDED_OUTPUTS of them)
come from the driver's Hermite dense output, projected.

Where to use it: stiff systems — fine ropes and cloth, stiff springs — at moderate accuracy
(rtol 1e-3 … 1e-8); each step costs a Jacobian and a sparse LU, so on non-stiff problems
dopri's cheap steps win. docs/methods.md compares.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..codegen.fast_call import FastCall
from ..manifold import residual
from ..manifold.algebra import REFINE_ABOVE, algebra_for
from ..manifold.manifold import acceleration_function, dynamics_values
from ..model.cache import ParametricView, structure_cache
from .base import DRIVER_OPTIONS, Advance, Status
from .driver import Stepper
from .tableaus.rodas4 import RODAS4

SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 1 / 6, 5.0
#: The step-size controller's exponent −1/(q + 1), q = 3 the embedded estimate's order.
EXPONENT = -1 / (RODAS4.error_order + 1)
#: Attempts one ``step`` call may make (rejections included) before it reports a collapse.
MAX_ATTEMPTS = 60
#: As dopri: up to this many output times each end a step; more come from the dense output.
LANDED_OUTPUTS = 16
#: Projection residual (× system size) before the last Newton step that stops the run.
PROJECTION_FAIL = 1e-6
#: The error test's floor, in units of the accelerations' round-off (``round_off_acceleration``).
ROUND_OFF_FACTOR = 8.0


@dataclass(frozen=True)
class _State:
    t: float
    x: np.ndarray
    v: np.ndarray
    lam: np.ndarray  # the independent rows' multipliers, consistent with (x, v)
    a: np.ndarray
    h: float
    p: np.ndarray  # the model's p (its neighbour lists refreshed as the particles move)
    rejected: bool = False


class _Functions:
    """The DAE's right-hand side and Jacobian as CasADi Functions of (x, v, λ, t, p), built once
    per structure and row set: ``rhs -> (a, g)``; ``jacobian -> (k1, k2, d, ∂(a, g)/∂t)``, the
    nonzeros of the reduced matrix's parts on one pattern, K(γh) = k0/(γh) + k1 + γh k2 with
    k0 = diag(I, 0), k1 = −∂(a, g)/∂(v, λ), k2 = −[∂(a, g)/∂x, 0], and d = ∂(a, g)/∂x's own
    nonzeros (for the right-hand sides); the patterns (compressed columns) kept for SciPy."""

    def __init__(self, model, rows):
        n3 = model.n_coordinates
        kind = ca.MX if getattr(model.structure, "pairs", ()) else ca.SX
        X, V, T = kind.sym("x", n3), kind.sym("v", n3), kind.sym("t")
        P = kind.sym("p", len(model.parameter_vector))
        view = ParametricView(model, P, differentiable=True)  # (∂F/∂x below)
        F, J, gamma = view.dynamics(X, V, T)
        if rows is not None:
            J, gamma = J[list(rows), :], gamma[list(rows)]
        c = J.shape[0]
        L = kind.sym("lam", c)
        minv = view.inverse_masses
        minv = minv if isinstance(minv, ca.SX | ca.MX) else ca.DM(minv)
        a = minv * (F + ca.mtimes(J.T, L))
        g = ca.mtimes(J, a) + gamma
        z = ca.vertcat(a, g)
        d_x, d_vl = ca.jacobian(z, X), ca.jacobian(z, ca.vertcat(V, L))
        size = n3 + c
        eye = ca.DM(ca.Sparsity.diag(n3, n3), 1.0)
        eye = ca.diagcat(eye, ca.DM(c, c)) if c else eye
        shifted = ca.horzcat(d_x, kind(size, c)) if c else d_x
        pattern = eye.sparsity().unite(d_vl.sparsity()).unite(shifted.sparsity())
        self.k0 = np.asarray(ca.DM(ca.project(eye, pattern)).nonzeros())
        parts = [ca.project(-d_vl, pattern), ca.project(-shifted, pattern), d_x]
        nonzeros = [ca.densify(e.nz[:]) if e.nnz() else kind(0, 1) for e in parts]
        self.pattern, self.coupling = pattern, d_x.sparsity()
        self.rhs = FastCall(ca.Function("rodas_rhs", [X, V, L, T, P], [ca.densify(a), ca.densify(g)]))
        self.jacobian = FastCall(ca.Function("rodas_jacobian", [X, V, L, T, P],
                                             [*nonzeros, ca.densify(ca.jacobian(z, T))]))
        self.consistent = FastCall(acceleration_function(model, rows, parametric=True))
        # ε M⁻¹ (|F| + |J|ᵀ|λ|): what round-off leaves in a (``Rodas.round_off_acceleration``)
        spread = minv * (ca.fabs(F) + (ca.mtimes(ca.fabs(J).T, ca.fabs(L)) if c else 0))
        self.round_off = FastCall(ca.Function("rodas_round_off", [X, V, L, T, P],
                                              [np.finfo(float).eps * ca.densify(spread)]))
        self.n3, self.n_rows = n3, c


def _functions(model, rows) -> _Functions:
    cache, prefix = structure_cache(model)
    key = (*prefix, "rodas", rows)
    if key not in cache:
        cache[key] = _Functions(model, rows)
    return cache[key]


class Rodas(Stepper):
    name = "rodas"
    order = RODAS4.order
    OPTIONS = DRIVER_OPTIONS
    explicit = False

    def __init__(self, manifold, *, rtol=1e-8, atol=1e-10, dt=None, **options):
        super().__init__(manifold, rtol=rtol, atol=atol, dt=dt, **options)
        self.tableau = RODAS4
        self._f = _functions(self.model, self.manifold.rows)
        self._scale = self._smallest_scale = None
        self.stats.update(rejected=0, tableau=RODAS4.name)

    # --- the driver's contract -------------------------------------------------------------
    def prepare(self, t0, t_end, t_eval) -> None:
        self.lands = t_eval is None or len(t_eval) <= LANDED_OUTPUTS

    def init(self, x0, v0, t0, t_end, first_step=None):
        if self._scale is None:
            self._scale = max(1.0, float(np.max(np.abs(x0), initial=0.0)))
        p = self._refreshed(self.model.parameter_vector, x0)
        a0, lam0 = self._consistent(x0, v0, t0, p)
        h = first_step if first_step else self._initial_step(x0, v0, a0, lam0, t0, t_end, p)
        return _State(float(t0), np.asarray(x0, float), np.asarray(v0, float), lam0, a0, float(h), p)

    def start_acceleration(self, state):
        return state.a

    def step(self, state: _State, t_stop: float) -> Advance:
        n = self.model.n_coordinates
        t, h = state.t, state.h
        rejected = state.rejected
        p = self._refreshed(state.p, state.x)
        jac = self._jacobian(state, p)
        noise = self.round_off_acceleration(state, p)
        for _ in range(MAX_ATTEMPTS):
            if self.stop_requested():
                return Advance.empty(state, n)
            last = h >= t_stop - t
            hh = t_stop - t if last else h
            try:
                x1, v1, lam1, err = self._attempt(state, hh, jac, p, noise)
            except (RuntimeError, ValueError, ZeroDivisionError):  # a singular W: a smaller step
                x1 = err = None
            self.stats["nlu"] += 1
            if err is not None and np.isfinite(err) and err <= 1.0:
                t1 = t_stop if last else t + hh
                grow = MAX_FACTOR if err == 0 else min(MAX_FACTOR, SAFETY * err ** EXPONENT)
                h_next = hh * (min(1.0, grow) if rejected else grow)
                if last:  # a step clipped to an output time keeps the proposal it had
                    h_next = max(h, h_next)
                return self._accepted(state, t1, x1, v1, lam1, h_next, p)
            shrink = MIN_FACTOR if err is None or not np.isfinite(err) else \
                max(MIN_FACTOR, SAFETY * err ** EXPONENT)
            h = hh * min(shrink, 0.9)
            rejected = True
            self.stats["rejected"] += 1
            if h < 1e-14 * max(1.0, abs(t)):
                break
        return Advance.empty(
            _State(t, state.x, state.v, state.lam, state.a, h, p, True), n, Status.STEP_SIZE_COLLAPSED,
            f"the step size collapsed at t = {t:.6g} s (h = {h:.3g} s); "
            + self.diagnose(state.x, state.v, t))

    def output(self, t, x, v):
        """A dense-output sample, projected onto both manifolds as a step's end is."""
        projected = self._project(x, v, t)
        if projected is None:
            return np.full_like(x, np.nan), np.full_like(v, np.nan)
        return projected

    def finish(self) -> None:
        self.stats["projections"] = max(self.stats["projections"], self.stats["steps"])

    def stiffness_advice(self) -> tuple[str, str]:  # (an implicit method: never asked)
        return "method rodas", "loosen rtol"

    # --- one step ---------------------------------------------------------------------------
    def _jacobian(self, state: _State, p):
        """The parts of K (k1, k2: nonzeros on its pattern), ∂(a, g)/∂x as a SciPy matrix, and
        ∂(a, g)/∂t, at the step's start."""
        from scipy.sparse import csc_matrix

        f = self._f
        self.stats["njev"] += 1
        k1, k2, d_x, dt = f.jacobian(state.x, state.v, state.lam, state.t, p)
        colind, row = f.coupling.get_ccs()
        coupling = csc_matrix((d_x, row, colind), shape=f.coupling.shape)
        return k1, k2, coupling, dt

    def round_off_acceleration(self, state: _State, p) -> np.ndarray:
        """ROUND_OFF_FACTOR ε M⁻¹ (|F| + |J|ᵀ|λ|) (3N,): how far round-off leaves each
        acceleration, a floor under the error test's scales (h² of it for x, h for v). A 1 mg
        bead between two 1 t beads on rods carries tensions of 2e4 N that cancel on it: its
        acceleration is known to 4e-6 m/s², and at atol 1e-11 the error test resolved that
        noise: 101,128 steps for one second of the chain hanging at rest (dopri: 10)."""
        return ROUND_OFF_FACTOR * np.asarray(self._f.round_off(state.x, state.v, state.lam, state.t, p)[0],
                                             float).ravel()

    def _attempt(self, state: _State, h: float, jac, p, noise: np.ndarray | float = 0.0):
        """One RODAS step of size h: (x1, v1, λ1, scaled error); ``noise``: the round-off of
        the accelerations (``round_off_acceleration``)."""
        from scipy.sparse import csc_matrix
        from scipy.sparse.linalg import splu

        k1, k2, coupling, dt = jac
        tab, f = self.tableau, self._f
        n, c = f.n3, f.n_rows
        beta = tab.gamma * h
        colind, row = f.pattern.get_ccs()
        lu = splu(csc_matrix((f.k0 / beta + k1 + beta * k2, row, colind), shape=f.pattern.shape))
        timed = bool(np.any(dt))
        x, v, lam = state.x, state.v, state.lam
        U = []  # (U_x, U_v, U_λ) per stage
        for i in range(tab.stages):
            if i == 0:
                xi, vi, li, ai, gi = x, v, lam, state.a, np.zeros(c)
            else:
                xi = x + sum(tab.A[i, j] * U[j][0] for j in range(i))
                vi = v + sum(tab.A[i, j] * U[j][1] for j in range(i))
                li = lam + sum(tab.A[i, j] * U[j][2] for j in range(i))
                ai, gi = f.rhs(xi, vi, li, state.t + tab.alpha[i] * h, p)
                self.stats["nfev"] += 1
            r_x = vi + sum(tab.C[i, j] * U[j][0] for j in range(i)) / h
            r = np.concatenate([ai + sum(tab.C[i, j] * U[j][1] for j in range(i)) / h, gi])
            if timed and tab.d[i]:
                r = r + h * tab.d[i] * dt
            sol = lu.solve(r + beta * (coupling @ r_x))
            u_v, u_l = sol[:n], sol[n:]
            U.append((beta * (r_x + u_v), u_v, u_l))
        x1 = x + sum(tab.A[5, j] * U[j][0] for j in range(5)) + U[5][0]
        v1 = v + sum(tab.A[5, j] * U[j][1] for j in range(5)) + U[5][1]
        lam1 = lam + sum(tab.A[5, j] * U[j][2] for j in range(5)) + U[5][2]
        scale_x = self.atol + self.rtol * np.maximum(np.abs(x), np.abs(x1)) + h * h * noise
        scale_v = self.atol + self.rtol * np.maximum(np.abs(v), np.abs(v1)) + h * noise
        err = np.sqrt((np.sum((U[5][0] / scale_x) ** 2) + np.sum((U[5][1] / scale_v) ** 2)) / (2 * n))
        return x1, v1, lam1, float(err)

    def _accepted(self, state: _State, t1, x1, v1, lam1, h_next, p) -> Advance:
        n = self.model.n_coordinates
        projected = self._project(x1, v1, t1) if self.model.n_constraints else (x1, v1)
        if projected is None:
            return Advance.empty(state, n, Status.PROJECTION_FAILED,
                                 f"the state could not be kept on the constraints near t = {t1:.6g} s: "
                                 "reduce rtol")
        x1, v1 = projected
        p = self._refreshed(p, x1)
        a1, lam1 = self._consistent(x1, v1, t1, p)
        self.stats["steps"] += 1
        new = _State(float(t1), x1, v1, lam1, a1, float(h_next), p)
        return Advance(new, np.array([t1]), x1[None], v1[None], a1[None], h=float(h_next))

    # --- helpers ----------------------------------------------------------------------------
    def _consistent(self, x, v, t, p):
        """(a, λ over the independent rows) from the KKT system at (x, v, t); where they leave
        J a + γ off by more than REFINE_ABOVE (of |a|, at least 1 m/s²), λ refined on the equations of motion
        (``LinearAlgebra.multipliers``): a 1 mg bead between 1 t beads gave λ off by 9.4e-4 N,
        a start the steps corrected, so the error test saw h × 1e-6 m/s² at rest (70,000 steps
        for a second of a chain hanging still)."""
        self.stats["nfev"] += 1
        a, lam = self._f.consistent(x, v, t, p)
        if not len(lam):
            return a, lam
        _, g = self._f.rhs(x, v, lam, t, p)
        g = np.asarray(g, float).ravel()
        if np.max(np.abs(g)) > REFINE_ABOVE * max(float(np.max(np.abs(a))), 1.0):
            F, J, gamma = dynamics_values(self.model)(x, v, t)
            algebra = algebra_for(len(lam))
            J = algebra.matrix(J[list(self.rows), :] if len(self.rows) < J.shape[0] else J)
            lam = algebra.multipliers(J, self.model.inverse_masses, F, gamma[self.rows], start=lam,
                                      full_rank=True)
            a = self.model.inverse_masses * (F + J.T @ lam)
        return a, lam

    def _refreshed(self, p, x):
        structure = self.model.structure
        if not getattr(structure, "pairs", ()):
            return p
        fresh = structure.pair_potentials.refreshed(p, x)
        return p if fresh is None else fresh

    def _project(self, x, v, t):
        m = self.manifold
        if not self.model.n_constraints:
            return x, v
        if self._smallest_scale is None:
            self._smallest_scale = residual.smallest_scale(self.model, x, t)
        scale = (self._scale or 1.0) * self._smallest_scale
        projected = m.project_positions(x, t, tol=1e-14 * scale)
        if not projected.residual <= PROJECTION_FAIL * scale:  # NaN too
            return None
        m.counters.projections += 1
        return projected.x, m.project_velocities(projected.x, v, t)

    def _initial_step(self, x0, v0, a0, lam0, t0, t_end, p) -> float:
        """Hairer's starting step (as SciPy's select_initial_step) for order 4."""
        if self.dt is not None:
            return min(float(self.dt), t_end - t0)
        y0, f0 = np.concatenate([x0, v0]), np.concatenate([v0, a0])
        scale = self.atol + np.abs(y0) * self.rtol
        d0, d1 = np.linalg.norm(y0 / scale), np.linalg.norm(f0 / scale)
        h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
        h0 = min(h0, t_end - t0)
        a1, _ = self._consistent(x0 + h0 * v0, v0 + h0 * a0, t0 + h0, p)
        d2 = np.linalg.norm((np.concatenate([v0 + h0 * a0, a1]) - f0) / scale) / h0
        h1 = max(1e-6, h0 * 1e-3) if max(d1, d2) <= 1e-15 else (0.01 / max(d1, d2)) ** (1 / (self.order + 1))
        return min(100 * h0, h1, t_end - t0)

