"""The KKT acceleration and the projections of ``manifold.graph`` on the vectorized build:
the same formulas (A λ = −γ − J M⁻¹ F, a = M⁻¹ (F + Jᵀ λ); two Newton steps x ← x − M⁻¹ Jᵀ A⁻¹ f,
the second sharing its factorization with the velocity projection), J's products written on
its nonzeros (``build.Jacobian``) and A factorized by CasADi's sparse LDLᵀ."""

from __future__ import annotations

import casadi as ca

from ...model.cache import ParametricView, structure_cache
from ...model.structure import Model
from .build import vectorized_build

#: dopri's step loop in CasADi's virtual machine is built on the vectorized build from this
#: many coordinates (a plain Model, all rows independent). Below, a group's columns are short
#: and the per-node cost of the virtual machine outweighs what the columns save.
VECTORIZED_FROM = 300


def applies(model: Model, rows=None) -> bool:
    """Whether step loops of ``model`` on ``rows`` use the vectorized build: a plain Model (not
    a held row subset) of VECTORIZED_FROM coordinates or more, solving with all its rows."""
    return rows is None and getattr(model, "rows", None) is None and model.n_coordinates >= VECTORIZED_FROM


def acceleration_graph(view: ParametricView, X, V, T):
    """(a, λ) at (X, V, T) with the view's parameters: ``manifold.graph.acceleration_graph``."""
    b = vectorized_build(view._model.structure)
    out = b.evaluate(X, V, T, view.P, ("J", "gamma"), forces_too=True)
    minv, F, J = view.inverse_masses, out["F"], out["J"]
    if not b.n_rows:
        return minv * F, ca.MX(0, 1)
    lam = ca.solve(J.gram(minv), -out["gamma"] - J.times(minv * F), "ldl")
    return minv * (F + J.transpose_times(lam)), lam


def projection_graph(view: ParametricView, x, v, t):
    """(x, v, residual before the last Newton step in metres): ``manifold.graph.projection_graph``."""
    b = vectorized_build(view._model.structure)
    P, minv = view.P, view.inverse_masses
    first = b.evaluate(x, None, t, P, ("f", "J"))
    J = first["J"]
    x = x - minv * J.transpose_times(ca.solve(J.gram(minv), first["f"], "ldl"))
    out = b.evaluate(x, None, t, P, ("f", "J", "f_t", "scale") if b.rheonomic else ("f", "J", "scale"))
    J = out["J"]
    velocity = J.times(v) + out["f_t"] if b.rheonomic else J.times(v)
    sol = ca.solve(J.gram(minv), ca.horzcat(out["f"], velocity), "ldl")
    residual = ca.mmax(ca.fabs(out["f"]) / out["scale"])
    return x - minv * J.transpose_times(sol[:, 0]), v - minv * J.transpose_times(sol[:, 1]), residual


def acceleration_function(model: Model) -> ca.Function:
    """``(x, v, t, p) -> (a, λ)`` on the vectorized build, built once per structure."""
    cache, prefix = structure_cache(model)
    key = (*prefix, "acceleration", "vectorized")
    if key not in cache:
        n3 = model.n_coordinates
        X, V, T = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
        P = ca.MX.sym("p", len(model.parameter_vector))
        a, lam = acceleration_graph(ParametricView(model, P), X, V, T)
        cache[key] = ca.Function("acceleration", [X, V, T, P], [a, lam])
    return cache[key]
