"""Assembly: System -> Model, the CasADi functions every solver and analysis uses.

Equations (DESIGN.md): ``M x'' = F(x, x', t) + Jᵀ λ`` with ``f(x, t) = 0``. Differentiating
the constraints twice gives ``J x'' + γ = 0``, ``γ = d/dt(J v + f_t) − J x''``, which CasADi
forms by AD as ``γ = ∂c/∂x · v + ∂c/∂t`` for ``c = J v + f_t``. Only the terms the system
needs are built: ``active_terms`` lists them.
"""

from __future__ import annotations

import threading

import casadi as ca
import numpy as np
import scipy.linalg as sla

from .errors import InputError
from .symbols import Symbols

#: Relative size below which a pivot of J M⁻¹ Jᵀ counts as zero (redundant constraints).
RANK_RTOL = 1e-10


class _FastCall:
    """Call a CasADi Function through its FunctionBuffer: preallocated NumPy arrays in and
    out, no DM conversion (≈ 0.2 µs of call overhead instead of ≈ 30 µs plus ``.full()``).

    Inputs and outputs must be dense (the fast paths densify theirs). Returns copies, so
    the results outlive the next call. The buffers are per thread.
    """

    def __init__(self, function: ca.Function):
        self.function = function
        self._local = threading.local()

    def _state(self):
        state = getattr(self._local, "state", None)
        if state is None:
            f = self.function
            buf, evaluate = f.buffer()
            args = [np.zeros(f.nnz_in(i)) for i in range(f.n_in())]
            res = [np.zeros(f.nnz_out(i)) for i in range(f.n_out())]
            for i, a in enumerate(args):
                buf.set_arg(i, memoryview(a))
            for i, r in enumerate(res):
                buf.set_res(i, memoryview(r))
            state = self._local.state = (buf, evaluate, args, res)
        return state

    def __call__(self, *inputs) -> list[np.ndarray]:
        buf, evaluate, args, res = self._state()
        for a, value in zip(args, inputs, strict=True):
            a[:] = value
        evaluate()
        if buf.ret():  # an evaluation error: let the ordinary call raise it
            out = self.function(*inputs)
            out = out if isinstance(out, tuple) else (out,)
            return [np.asarray(o, float).ravel() for o in out]
        return [r.copy() for r in res]


class Model:
    """An assembled system: CasADi Functions in (x, v, t) plus the numeric KKT solve.

    Functions (all with flat 3N vectors):
      ``constraint(x, t) -> f``                (C,)
      ``jacobian(x, t) -> (f, J)``              J = ∂f/∂x, (C, 3N)
      ``velocity_terms(x, t) -> (J, f_t)``
      ``dynamics(x, v, t) -> (F, J, γ)``        what the acceleration-level KKT needs
      ``energy(x, v, t) -> h``                 h = T + V + U − v·∂U/∂v (the energy function)
      ``kinetic(v) -> T``
    """

    def __init__(self, system):
        self.system = system
        s = Symbols(system)
        self.symbols = s
        x, v, t = s.x, s.v, s.t
        n3 = 3 * system.n_particles
        self.n_particles = system.n_particles
        self.n_coordinates = n3
        self.masses = np.repeat(system.masses, 3)
        self.inverse_masses = 1.0 / self.masses
        active = set()

        rows, labels, owners = [], [], []
        for k, constraint in enumerate(system.constraints):
            for expr, label in constraint.rows(s):
                rows.append(expr)
                labels.append(label)
                owners.append(k)
        self.constraint_labels: list[str] = labels
        self.constraint_owner = np.array(owners, dtype=int)
        self.n_constraints = len(rows)
        f = ca.vertcat(*rows) if rows else ca.SX(0, 1)
        J = ca.jacobian(f, x)
        self.rheonomic = bool(rows) and ca.depends_on(f, t)
        if rows:
            active.add("constraints")
        if self.rheonomic:
            active.add("rheonomic")
            f_t = ca.jacobian(f, t)
            c = ca.mtimes(J, v) + f_t
            gamma = ca.jtimes(c, x, v) + ca.jacobian(c, t)
        else:
            f_t = ca.SX(self.n_constraints, 1)  # structurally zero: no f_t terms
            c = ca.mtimes(J, v)
            gamma = ca.jtimes(c, x, v)

        slots = {"potential": [], "generalized_potential": [], "dissipation": [], "applied_force": []}
        for effect in system.effects:
            slots[effect.slot].append(effect.term(s))
        F = ca.SX.zeros(n3)
        V = U = ca.SX(0)
        dU_dv = ca.SX.zeros(n3)
        if slots["potential"]:
            active.add("potential")
            V = sum(slots["potential"], ca.SX(0))
            F -= ca.gradient(V, x)
        if slots["generalized_potential"]:
            active.add("generalized_potential")
            U = sum(slots["generalized_potential"], ca.SX(0))
            dU_dv = ca.gradient(U, v)
            if ca.depends_on(dU_dv, v):
                raise InputError(
                    "a generalized potential must be linear in the velocities "
                    "(U = U0(x, t) + v·W(x, t)); this one is not"
                )
            # Q = −∂U/∂x + d/dt ∂U/∂v, with d/dt ∂U/∂v = (∂²U/∂v∂x) v + ∂²U/∂v∂t
            F += -ca.gradient(U, x) + ca.jtimes(dU_dv, x, v) + ca.jacobian(dU_dv, t)
        if slots["dissipation"]:
            active.add("dissipation")
            R = sum(slots["dissipation"], ca.SX(0))
            F -= ca.gradient(R, v)
        if slots["applied_force"]:
            active.add("applied_force")
            for term in slots["applied_force"]:
                F += term
        if ca.depends_on(F, t) or (V.numel() and ca.depends_on(V, t)):
            active.add("time_dependent_forces")
        self.active_terms = frozenset(active)

        T = 0.5 * ca.dot(ca.DM(self.masses) * v, v)
        energy = T + V + U - ca.dot(v, dU_dv)
        self.constraint = ca.Function("constraint", [x, t], [f], ["x", "t"], ["f"])
        self.jacobian = ca.Function("jacobian", [x, t], [f, J], ["x", "t"], ["f", "J"])
        self.velocity_terms = ca.Function("velocity_terms", [x, t], [J, f_t], ["x", "t"], ["J", "f_t"])
        self.dynamics = ca.Function(
            "dynamics", [x, v, t], [F, J, gamma], ["x", "v", "t"], ["F", "J", "gamma"]
        )
        self.energy = ca.Function("energy", [x, v, t], [energy], ["x", "v", "t"], ["E"])
        self.potential = ca.Function("potential", [x, t], [V], ["x", "t"], ["V"])
        self.kinetic = ca.Function("kinetic", [v], [T], ["v"], ["T"])
        self.counters = {"nfev": 0, "njev": 0, "nlu": 0}
        #: Set when J has dependent rows: every solve then takes the minimum-norm path.
        self.redundant = False
        #: "virtual machine" (CasADi's) or "compiled" (see ``compile``).
        self.evaluation = "virtual machine"
        #: What solvers build once per model and reuse across runs (e.g. dopri's step loop).
        self.solver_cache: dict = {}
        self._build_fast_paths()

    def _build_fast_paths(self) -> None:
        """One CasADi call per numeric operation, the KKT solve inside it (sparse LDLᵀ of the
        SPD J M⁻¹ Jᵀ for the acceleration, ≈ 18 % faster than QR on a chain; sparse QR for the
        projections).

        Valid while J has full row rank; results that come out non-finite, or a model
        flagged ``redundant``, fall back to the NumPy minimum-norm path.
        """
        n3, C = self.n_coordinates, self.n_constraints
        X, Vv, T = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
        minv = ca.DM(self.inverse_masses)
        F, J, gamma = self.dynamics(X, Vv, T)
        if C:
            A = ca.mtimes(ca.mtimes(J, ca.diag(minv)), J.T)
            lam = ca.solve(A, -gamma - ca.mtimes(J, minv * F), "ldl")
            acc = minv * (F + ca.mtimes(J.T, lam))
            f, Jx = self.jacobian(X, T)
            Ax = ca.mtimes(ca.mtimes(Jx, ca.diag(minv)), Jx.T)
            dx = minv * ca.mtimes(Jx.T, ca.solve(Ax, f, "qr"))
            Jv, f_t = self.velocity_terms(X, T)
            dv = minv * ca.mtimes(Jv.T, ca.solve(Ax, ca.mtimes(Jv, Vv) + f_t, "qr"))
        else:
            lam, acc = ca.MX(0, 1), minv * F
            f, dx, dv = ca.MX(0, 1), ca.MX.zeros(n3), ca.MX.zeros(n3)
        # Dense outputs: the FunctionBuffer calls (_FastCall) read them as flat arrays.
        d = ca.densify
        self._acceleration = ca.Function("acceleration", [X, Vv, T], [d(acc), d(lam)])
        #: The acceleration as a differentiable CasADi graph (for CasADi integrators).
        self.acceleration_graph = self._acceleration
        self._newton_step = ca.Function("newton_step", [X, T], [d(f), d(dx)])
        self._velocity_correction = ca.Function("velocity_correction", [X, Vv, T], [d(dv)])
        self._make_fast_calls()

    def symbolic_acceleration(self) -> ca.Function:
        """The acceleration ``(x, v, t) -> (a, λ)`` as one SX expression, the KKT solve written
        out symbolically: fastest for small models (a few constraints), where it can be
        expanded into a larger SX graph; its size grows with the cube of the constraint count."""
        cached = self.solver_cache.get("symbolic_acceleration")
        if cached is None:
            n3 = self.n_coordinates
            X, Vv, T = ca.SX.sym("x", n3), ca.SX.sym("v", n3), ca.SX.sym("t")
            minv = ca.DM(self.inverse_masses)
            F, J, gamma = self.dynamics(X, Vv, T)
            if self.n_constraints:
                A = ca.mtimes(ca.mtimes(J, ca.diag(minv)), J.T)
                lam = ca.solve(A, -gamma - ca.mtimes(J, minv * F))
                acc = minv * (F + ca.mtimes(J.T, lam))
            else:
                lam, acc = ca.SX(0, 1), minv * F
            cached = ca.Function("acceleration_sx", [X, Vv, T], [acc, lam])
            self.solver_cache["symbolic_acceleration"] = cached
        return cached

    def _make_fast_calls(self) -> None:
        self._fast_acceleration = _FastCall(self._acceleration)
        self._fast_newton_step = _FastCall(self._newton_step)
        self._fast_velocity_correction = _FastCall(self._velocity_correction)

    def compile(self) -> bool:
        """Replace the per-call fast paths by compiled machine code (constrained.compiled).

        Returns True when they now run compiled; False (virtual machine kept) otherwise.
        """
        from . import compiled

        if self.evaluation == "compiled":
            return True
        funcs = [compiled.compile_function(f) for f in
                 (self._acceleration, self._newton_step, self._velocity_correction)]
        if any(f.class_name() != "External" for f in funcs):
            return False
        # CasADi integrators differentiate the right-hand side; compiled code has no
        # derivatives, so they keep the virtual-machine acceleration (``acceleration_graph``).
        self.acceleration_graph = self._acceleration
        self._acceleration, self._newton_step, self._velocity_correction = funcs
        self._make_fast_calls()
        self.evaluation = "compiled"
        return True

    # --- the KKT system ----------------------------------------------------------------------
    def schur_solve(self, J: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Solve (J M⁻¹ Jᵀ) y = b; minimum-norm least squares when J is rank deficient."""
        if J.shape[0] == 0:
            return np.zeros(0)
        A = (J * self.inverse_masses) @ J.T
        self.counters["nlu"] += 1
        if not self.redundant:
            # Symmetric diagonal scaling first: with masses 1e12 apart the rows of A differ by
            # as much, and the unscaled pivot test would take a heavy row for a dependent one.
            diag = np.diag(A)
            s = 1.0 / np.sqrt(np.where(diag > 0, diag, 1.0))
            try:
                L, lower = sla.cho_factor(s[:, None] * A * s[None, :], lower=True, check_finite=False)
                d = np.abs(np.diag(L))
                if d.min() > np.sqrt(RANK_RTOL) * d.max():
                    return s * sla.cho_solve((L, lower), s * b, check_finite=False)
            except (np.linalg.LinAlgError, ValueError):
                pass
        # Redundant or singular: minimum-norm solution, small singular values cut off.
        U_, sv, Vt = np.linalg.svd(A)
        keep = sv > RANK_RTOL * sv[0] if sv.size and sv[0] > 0 else np.zeros_like(sv, bool)
        return Vt[keep].T @ ((U_[:, keep].T @ b) / sv[keep])

    def accelerations(self, x: np.ndarray, v: np.ndarray, t: float):
        """Accelerations and multipliers from M a = F + Jᵀλ, J a = −γ (flat vectors):
        (J M⁻¹ Jᵀ) λ = −γ − J M⁻¹ F, a = M⁻¹ (F + Jᵀλ)."""
        self.counters["nfev"] += 1
        if not self.redundant:
            a, lam = self._fast_acceleration(x, v, t)
            self.counters["nlu"] += 1
            if np.all(np.isfinite(a)) and np.all(np.isfinite(lam)):
                return a, lam
        F, J, gamma = self.dynamics(x, v, t)
        F, J, gamma = F.full().ravel(), J.full(), gamma.full().ravel()
        if self.n_constraints == 0:
            return self.inverse_masses * F, np.zeros(0)
        lam = self.schur_solve(J, -gamma - J @ (self.inverse_masses * F))
        return self.inverse_masses * (F + J.T @ lam), lam

    # --- projections onto the constraint manifolds --------------------------------------------
    def project_positions(self, x: np.ndarray, t: float, tol: float, max_iter: int = 12):
        """Nearest point (mass-weighted) with f(x, t) = 0, by Newton:
        x ← x − M⁻¹Jᵀ (J M⁻¹ Jᵀ)⁻¹ f. Returns (x, max|f|, iterations)."""
        x = np.array(x, dtype=float)
        if self.n_constraints == 0:
            return x, 0.0, 0
        best = np.inf
        err = np.inf
        for it in range(max_iter + 1):
            self.counters["njev"] += 1
            if self.redundant:
                f, J = self.jacobian(x, t)
                f, J = f.full().ravel(), J.full()
                dx = None
            else:
                f, dx = self._fast_newton_step(x, t)
            err = float(np.max(np.abs(f)))
            if not np.isfinite(err) or err <= tol or it == max_iter or (err > 0.5 * best and it > 2):
                return x, err, it
            best = min(best, err)
            if dx is None or not np.all(np.isfinite(dx)):
                if dx is not None:
                    J = self.jacobian(x, t)[1].full()
                dx = self.inverse_masses * (J.T @ self.schur_solve(J, f))
            x = x - dx
        return x, err, max_iter

    def project_velocities(self, x: np.ndarray, v: np.ndarray, t: float):
        """Nearest velocity (mass-weighted) with J v + f_t = 0 (one linear solve)."""
        if self.n_constraints == 0:
            return np.array(v, dtype=float)
        self.counters["njev"] += 1
        if not self.redundant:
            (dv,) = self._fast_velocity_correction(x, v, t)
            if np.all(np.isfinite(dv)):
                return v - dv
        J, f_t = self.velocity_terms(x, t)
        J = J.full()
        c = J @ v + f_t.full().ravel()
        return v - self.inverse_masses * (J.T @ self.schur_solve(J, c))

    # --- batch evaluation along a trajectory ----------------------------------------------
    def evaluate(self, function: ca.Function, *columns: np.ndarray) -> list[np.ndarray]:
        """Evaluate ``function`` at many points at once (CasADi ``map``); columns are (T, k)."""
        n = columns[0].shape[0]
        mapped = function.map(n)
        args = [np.atleast_2d(np.asarray(c, float).reshape(n, -1)).T for c in columns]
        out = mapped(*args)
        out = out if isinstance(out, tuple) else (out,)
        return [np.asarray(o) for o in out]

    def multipliers_along(self, X: np.ndarray, V: np.ndarray, t: np.ndarray) -> np.ndarray:
        """λ at each sample (T, C), from the KKT system at (x, v, t)."""
        n = len(t)
        if self.n_constraints == 0:
            return np.zeros((n, 0))
        F, Jcat, gamma = self.evaluate(self.dynamics, X, V, t)
        C, n3 = self.n_constraints, self.n_coordinates
        J = Jcat.reshape(C, n, n3).transpose(1, 0, 2) if n > 0 else np.zeros((0, C, n3))
        lam = np.empty((n, C))
        for k in range(n):
            Fk = F[:, k]
            lam[k] = self.schur_solve(J[k], -gamma[:, k] - J[k] @ (self.inverse_masses * Fk))
        return lam

    def constraint_forces_along(self, X: np.ndarray, t: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """(Jᵀλ)_i for each particle, (T, N, 3)."""
        n = len(t)
        if self.n_constraints == 0:
            return np.zeros((n, self.n_particles, 3))
        _, Jcat = self.evaluate(self.jacobian, X, t)
        J = Jcat.reshape(self.n_constraints, n, self.n_coordinates).transpose(1, 0, 2)
        return np.einsum("kci,kc->ki", J, lam).reshape(n, self.n_particles, 3)

    def __repr__(self) -> str:
        return (
            f"Model({self.n_particles} particles, {self.n_constraints} constraint rows, "
            f"active: {', '.join(sorted(self.active_terms)) or 'none'})"
        )


def assemble(system) -> Model:
    """Build the Model of a System (the only step that makes CasADi symbols)."""
    return Model(system)
