"""The KKT acceleration and the projections of ``manifold.graph`` on the vectorized build:
the same formulas (A λ = −γ − J M⁻¹ F, a = M⁻¹ (F + Jᵀ λ); two Newton steps x ← x − M⁻¹ Jᵀ A⁻¹ f,
the second sharing its factorization with the velocity projection), J's products written on
its nonzeros (``build.Jacobian``) and A factorized by CasADi's sparse LDLᵀ."""

from __future__ import annotations

import casadi as ca

from ...model.cache import ParametricView, structure_cache
from ...model.structure import Model
from .build import vectorized_build
from .columns import binary
from .columns import shared_nodes as shared_nodes  # (for step loops: many evaluations, one graph)

#: dopri's step loop in CasADi's virtual machine is built on the vectorized build from this
#: many coordinates (a plain Model, all rows independent). Below, a group's columns are short
#: and the per-node cost of the virtual machine outweighs what the columns save.
VECTORIZED_FROM = 300


def applies(model: Model, rows=None) -> bool:
    """Whether step loops of ``model`` on ``rows`` use the vectorized build: a plain Model (not
    a held row subset) of VECTORIZED_FROM coordinates or more, solving with all its rows, with
    no velocity rows (model/velocity.py) and no mapped pair kernels (model/pairs/: MX of their own)."""
    return (rows is None and getattr(model, "rows", None) is None and model.n_coordinates >= VECTORIZED_FROM
            and getattr(model, "n_position_rows", model.n_constraints) == model.n_constraints
            and not getattr(getattr(model, "structure", None), "pairs", ()))


class VectorizedView(ParametricView):
    """``ParametricView`` whose Functions are the vectorized build's (MX): ``constraint``,
    ``jacobian``, ``velocity_terms``, ``dynamics`` (J a sparse MX matrix), ``energy`` and
    ``row_scales``, for graphs that take the model generically (``manifold.structural_call``)."""

    def __init__(self, model: Model, P):
        super().__init__(model, P)
        self.build = vectorized_build(model.structure)

    def _at(self, X, V, T, outputs: tuple, forces_too: bool = False) -> dict:
        return self.build.evaluate(X, V, T, self.P, outputs, forces_too)

    def constraint(self, X, T):
        return self._at(X, None, T, ("f",))["f"]

    def jacobian(self, X, T):
        out = self._at(X, None, T, ("f", "J"))
        return out["f"], out["J"].matrix()

    def velocity_terms(self, X, T):
        out = self._at(X, None, T, ("J", "f_t"))
        return out["J"].matrix(), out["f_t"]

    def dynamics(self, X, V, T):
        out = self._at(X, V, T, ("J", "gamma"), forces_too=True)
        return out["F"], out["J"].matrix(), out["gamma"]

    def energy(self, X, V, T):
        return self.build.energy(X, V, T, self.P, self.masses)

    def row_scales(self, X, T):
        return self._at(X, None, T, ("scale",))["scale"]


def statics(view: ParametricView) -> tuple:
    """``(m⁻¹, F)``: the inverse masses (3N,) and, when they depend on p alone (gravity, fixed
    loads), the forces (3N,; else None) — what every acceleration of a step shares, computed
    once per step and handed to ``acceleration_graph`` (dopri's step: its accelerations are
    written into its graph)."""
    b = vectorized_build(view._model.structure)
    if b.forces_vary():  # (asked of the SX: an MX graph through C loops has no cheap sparsity)
        return view.inverse_masses, None
    # F reads none of x, v, t, so it is evaluated at zeros: symbols here would be free in the
    # step's graph wherever a call takes them as inputs (the rest's, with no effects at all)
    zeros = ca.MX.zeros(b.n3)
    return view.inverse_masses, b.evaluate(zeros, zeros, ca.MX(0), view.P, (), forces_too=True)["F"]


def acceleration_graph(view: ParametricView, X, V, T, *, minv=None, forces=None):
    """(a, λ) at (X, V, T) with the view's parameters: ``manifold.graph.acceleration_graph``;
    ``minv``, ``forces``: the ``statics`` of the step, when given."""
    b = vectorized_build(view._model.structure)
    out = b.evaluate(X, V, T, view.P, ("J", "gamma"), forces_too=forces is None)
    minv = view.inverse_masses if minv is None else minv
    F, J = out["F"] if forces is None else forces, out["J"]
    if not b.n_rows:
        return minv * F, ca.MX(0, 1)
    lam = J.solve(minv, -out["gamma"] - J.times(binary(ca.OP_MUL, minv, F)))
    return minv * (F + J.transpose_times(lam)), lam


def position_step_graph(view: ParametricView, X, T):
    """(f, dx) with x ← x − dx one mass-weighted Newton step: ``manifold.graph.position_step_graph``."""
    b = vectorized_build(view._model.structure)
    out = b.evaluate(X, None, T, view.P, ("f", "J"))
    minv, J = view.inverse_masses, out["J"]
    if not b.n_rows:
        return ca.MX(0, 1), ca.MX.zeros(b.n3)
    return out["f"], minv * J.transpose_times(J.solve(minv, out["f"]))


def velocity_correction_graph(view: ParametricView, X, V, T):
    """dv with v ← v − dv the nearest velocity with J v + f_t = 0: ``manifold.graph``'s."""
    b = vectorized_build(view._model.structure)
    if not b.n_rows:
        return ca.MX.zeros(b.n3)
    out = b.evaluate(X, None, T, view.P, ("J", "f_t") if b.rheonomic else ("J",))
    minv, J = view.inverse_masses, out["J"]
    c = J.times(V) + out["f_t"] if b.rheonomic else J.times(V)
    return minv * J.transpose_times(J.solve(minv, c))


def projection_graph(view: ParametricView, x, v, t, *, minv=None):
    """(x, v, residual before the last Newton step in metres): ``manifold.graph.projection_graph``."""
    b = vectorized_build(view._model.structure)
    P, minv = view.P, view.inverse_masses if minv is None else minv
    first = b.evaluate(x, None, t, P, ("f", "J"))
    J = first["J"]
    x = x - minv * J.transpose_times(J.solve(minv, first["f"]))
    out = b.evaluate(x, None, t, P, ("f", "J", "f_t", "scale") if b.rheonomic else ("f", "J", "scale"))
    J = out["J"]
    velocity = J.times(v) + out["f_t"] if b.rheonomic else J.times(v)
    sol = J.solve(minv, ca.horzcat(out["f"], velocity))
    residual = ca.mmax(ca.fabs(out["f"]) / out["scale"])
    return x - minv * J.transpose_times(sol[:, 0]), v - minv * J.transpose_times(sol[:, 1]), residual


#: Fixed-point iterations of RATTLE's second half-kick on the vectorized build when the forces
#: depend on v (each gains a factor h/2 |M⁻¹ ∂F/∂v|: 1e-2 for a step that resolves the damping).
KICK_ITERATIONS = 4


def rattle_step_graph(view: ParametricView, x, v, t, lam, h, *, F0=None, iterations: int = 4,
                      velocity_dependent: bool = False):
    """One RATTLE step on the vectorized build (``solvers.rattle``): (x1, v1, λ, |f(x1)| per row,
    F1). With kick = h²/2 M⁻¹ and x1(λ) = x + h v + kick (F0 + J0ᵀ λ), λ is found by
    ``iterations`` simplified Newton steps on f(x1(λ), t + h) = 0,

        λ ← λ − (2/h²) A0⁻¹ f(x1(λ)),   A0 = J0 M⁻¹ J0ᵀ  (J0 = J(x, t)),

    A0 in place of Newton's J(x1) M⁻¹ J0ᵀ, which is not symmetric: the loops' LDLᵀ serves it,
    and the iteration contracts by about |J(x1) − J0| / |J0| ~ h|v| / (a rod's length) a step.
    Then v½ = v + h/2 M⁻¹ (F0 + J0ᵀ λ), x1 = x + h v½, and v1 the mass-weighted nearest velocity
    to v½ + h/2 M⁻¹ F(x1, v½) with J(x1) v1 + f_t = 0 — with ``velocity_dependent`` forces
    then KICK_ITERATIONS times that of v½ + h/2 M⁻¹ F(x1, v1), towards the implicit half-kick
    v1 = v½ + h/2 M⁻¹ (F(x1, v1) + J1ᵀ μ) (second order; ``solvers.rattle.implicit_kick``).
    ``F0``: the forces at (x, t) when carried from the step before (else evaluated here, at
    (x, v, t))."""
    b = vectorized_build(view._model.structure)
    P, minv = view.P, view.inverse_masses
    minv = minv if isinstance(minv, ca.MX) else ca.DM(minv)
    t1 = t + h
    first = b.evaluate(x, v, t, P, ("J",), forces_too=F0 is None)
    J0, F0 = first["J"], first["F"] if F0 is None else F0
    kick = 0.5 * h * h * minv
    base = x + h * v + kick * F0
    solve0 = J0.factorized(minv)  # (one factorization for every iteration)
    for _ in range(iterations):
        f1 = b.evaluate(base + kick * J0.transpose_times(lam), None, t1, P, ("f",))["f"]
        lam = lam - (2 / (h * h)) * solve0(f1)
    v_half = v + 0.5 * h * minv * (F0 + J0.transpose_times(lam))
    x1 = x + h * v_half
    out = b.evaluate(x1, v_half, t1, P, ("f", "J", "f_t") if b.rheonomic else ("f", "J"), forces_too=True)
    J1, F1 = out["J"], out["F"]
    solve1 = J1.factorized(minv)

    def kicked(F):  # the mass-weighted nearest velocity to v½ + h/2 M⁻¹ F with J(x1) v + f_t = 0
        v_pred = v_half + 0.5 * h * minv * F
        c = J1.times(v_pred) + out["f_t"] if b.rheonomic else J1.times(v_pred)
        return v_pred - minv * J1.transpose_times(solve1(c))

    v1 = kicked(F1)
    if velocity_dependent:  # the forces at v_{n+1}: the fixed point, contracting by h/2 |M⁻¹ ∂F/∂v|
        for _ in range(KICK_ITERATIONS):
            F1 = b.evaluate(x1, v1, t1, P, (), forces_too=True)["F"]
            v1 = kicked(F1)
    return x1, v1, lam, out["f"], F1


def _symbols(model: Model):
    n3 = model.n_coordinates
    P = ca.MX.sym("p", len(model.parameter_vector))
    return ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t"), P


#: The manifold's fast paths, in the order ``fast_path_functions`` gives them.
FAST_PATHS = ("acceleration", "newton_step", "velocity_correction")


def fast_path_function(model: Model, name: str) -> ca.Function:
    """One of the manifold's fast paths on the vectorized build (dense outputs, p last), by
    ``name`` in FAST_PATHS: ``acceleration(x, v, t, p) -> (a, λ)``, ``newton_step(x, t, p) ->
    (f, dx)``, ``velocity_correction(x, v, t, p) -> dv``."""
    X, V, T, P = _symbols(model)
    view = ParametricView(model, P)
    d = ca.densify
    if name == "acceleration":
        a, lam = acceleration_graph(view, X, V, T)
        return ca.Function("acceleration", [X, V, T, P], [d(a), d(lam)])
    if name == "newton_step":
        f, dx = position_step_graph(view, X, T)
        return ca.Function("newton_step", [X, T, P], [d(f), d(dx)])
    if name == "velocity_correction":
        return ca.Function("velocity_correction", [X, V, T, P], [d(velocity_correction_graph(view, X, V, T))])
    raise ValueError(f"no fast path {name!r} (choose from {', '.join(FAST_PATHS)})")


def fast_path_functions(model: Model) -> list[ca.Function]:
    """The manifold's fast paths on the vectorized build, in the order of FAST_PATHS."""
    return [fast_path_function(model, name) for name in FAST_PATHS]


#: The quantities ``quantities_function`` can give, in order.
QUANTITY_OUTPUTS = ("multipliers", "check", "constraint_forces", "energy", "constraint_residual",
                    "velocity_residual")


def quantities_function(model: Model, wanted: tuple) -> ca.Function:
    """``(x, v, t, p) -> [...]`` the quantities ``wanted`` (names in QUANTITY_OUTPUTS, in that
    order) at one state: the multipliers λ of the KKT system (sparse LDLᵀ), their ``check``
    r = |J a + γ|∞ / (|γ|∞ + |J M⁻¹ F|∞ + tiny) (``run.quantities``), the constraint forces Jᵀλ,
    the energy, the position and velocity residuals in metres (max_i |f_i| / s_i, |J_i v + f_t,i| / s_i).
    Built once per structure and choice."""
    cache, prefix = structure_cache(model)
    key = (*prefix, "quantities", "vectorized", wanted)
    if key in cache:
        return cache[key]
    X, V, T, P = _symbols(model)
    view = ParametricView(model, P)
    b = vectorized_build(model.structure)
    minv = view.inverse_masses
    kkt = bool({"multipliers", "check", "constraint_forces"} & set(wanted))
    names = ["f", "J", *(["f_t"] if b.rheonomic else []), *(["gamma"] if kkt else []), "scale"]
    out = b.evaluate(X, V, T, P, tuple(names), forces_too=True)
    J, outputs = out["J"], {}
    if kkt:
        F, gamma = out["F"], out["gamma"]
        load = J.times(minv * F)
        lam = J.solve(minv, -gamma - load) if b.n_rows else ca.MX(0, 1)
        a = minv * (F + J.transpose_times(lam))
        scale = ca.mmax(ca.fabs(gamma)) + ca.mmax(ca.fabs(load)) + 1e-300
        outputs["multipliers"] = lam
        outputs["check"] = ca.mmax(ca.fabs(J.times(a) + gamma)) / scale if b.n_rows else ca.MX(0)
        outputs["constraint_forces"] = J.transpose_times(lam)
    if "energy" in wanted:
        outputs["energy"] = b.energy(X, V, T, P, view.masses)
    if "constraint_residual" in wanted:
        outputs["constraint_residual"] = ca.mmax(ca.fabs(out["f"]) / out["scale"]) if b.n_rows else ca.MX(0)
    if "velocity_residual" in wanted:
        velocity = J.times(V) + out["f_t"] if b.rheonomic else J.times(V)
        outputs["velocity_residual"] = ca.mmax(ca.fabs(velocity) / out["scale"]) if b.n_rows else ca.MX(0)
    cache[key] = ca.Function("quantities", [X, V, T, P], [ca.densify(outputs[k]) for k in wanted])
    return cache[key]
