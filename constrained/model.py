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

from .errors import InputError
from .symbols import Symbols


class FastCall:
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
    """An assembled system: CasADi Functions in (x, v, t). Immutable once built: runs keep
    their counters and redundancy in their own ``Manifold`` (constrained.manifold), which
    also holds the KKT solve.

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
        self.masses.flags.writeable = self.inverse_masses.flags.writeable = False
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
        #: The system's data the numeric side needs, copied so the Model does not change.
        self.particle_names = tuple(p.name for p in system.particles)

    # --- batch evaluation along a trajectory ----------------------------------------------
    def evaluate(self, function: ca.Function, *columns: np.ndarray) -> list[np.ndarray]:
        """Evaluate ``function`` at many points at once (CasADi ``map``); columns are (T, k)."""
        n = columns[0].shape[0]
        mapped = function.map(n)
        args = [np.atleast_2d(np.asarray(c, float).reshape(n, -1)).T for c in columns]
        out = mapped(*args)
        out = out if isinstance(out, tuple) else (out,)
        return [np.asarray(o) for o in out]

    def __repr__(self) -> str:
        return (
            f"Model({self.n_particles} particles, {self.n_constraints} constraint rows, "
            f"active: {', '.join(sorted(self.active_terms)) or 'none'})"
        )


def assemble(system) -> Model:
    """Build the Model of a System (the only step that makes CasADi symbols)."""
    return Model(system)
