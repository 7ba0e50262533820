"""Constraint residuals in metres, whatever the scale a constraint's formula is written in.

A surface ``1e8 * (x**2 + y**2 + z**2 - 1) = 0`` is the same sphere as the unscaled formula,
but |f| is 1e8 times larger for the same miss, and ``1e-8 * (...)`` makes a particle 1e-8 m
off the surface look like |f| = 1e-16. Residuals and tolerances are therefore measured per
row as |f_i| / s_i with the row scale

    s_i = max over particles p of |∂f_i/∂x_p|      (N/A rows with zero gradient: s_i = 1)

— for a row that moves one particle (surface, pin, plane) |f_i|/s_i is, to first order, that
particle's distance from the constraint in metres; for a distance constraint between two
particles it is the error of the length. Velocity residuals |J_i v + f_t,i| / s_i are in m/s.
A velocity row a·v + b (model/velocity.py) has the scale max_p |a_p|: its residual is in m/s
too. ``row_scales`` gives every row's scale (those of f first).

The projections themselves are untouched (mass-weighted, in manifold/model): only the
tolerances handed to them and the residuals reported are converted here.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..codegen.fast_call import FastCall
from ..model.cache import ParametricView, structure_cache
from .graph import row_scales_expr
from .vectorized import at_point
from .vectorized import graphs as vectorized

_CACHE_KEY = "residual_in_metres"


def functions(model) -> dict[str, ca.Function]:
    """``scales(x, t, p) -> s`` (C,; a FunctionBuffer call), ``position(x, t, p) -> max_i
    |f_i|/s_i`` (m) and ``velocity(x, v, t, p) -> max_i |J_i v + f_t,i|/s_i`` (m/s), with the
    parameters p as their last input: built once per structure (``structure_cache``)."""
    cache, prefix = structure_cache(model)
    key = (*prefix, _CACHE_KEY)
    if key not in cache:
        cache[key] = _build(model)
    return cache[key]


class _Residuals(dict):
    """``functions``' dictionary of a large model: "scales" now, "position" and "velocity" when
    first asked for (a run's start and steps need only the scales; its residuals along the
    trajectory come from the vectorized build's quantities)."""

    def __init__(self, scales: FastCall, build):
        super().__init__(scales=scales)
        self._build = build

    def __missing__(self, key: str):
        if key not in ("position", "velocity"):
            raise KeyError(key)
        self.update(self._build())
        return self[key]


def _build(model) -> dict:
    n3 = model.n_coordinates
    # a large model: MX on the vectorized build (an SX graph of every row would be built)
    large = vectorized.applies(model)
    kind = ca.MX if large else ca.SX
    x, v, t = kind.sym("x", n3), kind.sym("v", n3), kind.sym("t")
    p = kind.sym("p", len(model.parameter_vector))
    view = vectorized.VectorizedView(model, p) if large else ParametricView(model, p)

    def scales(s) -> FastCall:
        return FastCall(ca.Function("row_scales", [x, t, p], [ca.densify(s)]))

    def residuals(s) -> dict:  # (s None: the scales of J, returned too)
        f, J = view.jacobian(x, t)
        G, f_t = view.velocity_terms(x, t)  # every row (those of f first, then velocity rows)
        J = G if model.n_position_rows < model.n_constraints else J  # (else the same J: one graph)
        out = {}
        if s is None:
            s = row_scales_expr(J, model.n_particles)
            out["scales"] = scales(s)
        C_f = model.n_position_rows
        position = ca.mmax(ca.fabs(f) / s[:C_f]) if C_f else kind(0)
        velocity = ca.mmax(ca.fabs(ca.mtimes(J, v) + f_t) / s) if model.n_constraints else kind(0)
        return {**out, "position": ca.Function("residual_m", [x, t, p], [position]),
                "velocity": ca.Function("velocity_residual_m", [x, v, t, p], [velocity])}

    if not large:
        return residuals(None)
    s = view.row_scales(x, t)
    return _Residuals(scales(s), lambda: residuals(s))


def _parameters(model, n: int) -> np.ndarray:
    """The model's parameter values, one row per sample (for ``Model.evaluate``)."""
    return np.tile(model.parameter_vector, (n, 1))


def row_scales(model, x, t: float = 0.0) -> np.ndarray:
    """s_i (see the module) at (x, t), shape (C,): the rows of f, then the velocity rows."""
    if model.n_constraints == 0:
        return np.zeros(0)
    if vectorized.applies(model):  # a start's call: on numbers, the Function when a run asks often
        cache, prefix = structure_cache(model)
        return at_point.numeric_first(model, "row scales", ("scale",),
                                      lambda: _scales_call(model, cache, prefix))(x, t)[0]
    return functions(model)["scales"](np.asarray(x, float).ravel(), t, model.parameter_vector)[0]


def _scales_call(model, cache: dict, prefix: tuple):
    """(x, t) -> [s] through the structure's "scales" Function (``functions``), noted as built
    for ``at_point.numeric_first`` (its key "row scales")."""
    scales = functions(model)["scales"]
    cache[(*prefix, "structural", "row scales")] = scales
    return lambda x, t: scales(np.asarray(x, float).ravel(), t, model.parameter_vector)


def smallest_scale(model, x, t: float = 0.0) -> float:
    """min_i s_i over the rows of f at (x, t): a tolerance of ``tol`` metres on every row is
    |f| ≤ tol × this."""
    s = row_scales(model, x, t)[:model.n_position_rows]
    return float(np.min(s)) if s.size else 1.0


def position_residual(model, x, t: float = 0.0) -> float:
    """max_i |f_i(x, t)| / s_i in metres at one state."""
    if model.n_position_rows == 0:
        return 0.0
    value = functions(model)["position"](np.asarray(x, float).ravel(), t, model.parameter_vector)
    return float(np.asarray(value).ravel()[0])


def position_residual_along(model, X: np.ndarray, t: np.ndarray) -> np.ndarray:
    """max_i |f_i| / s_i (m) at each sample: X (T, 3N), t (T,)."""
    n = len(t)
    if model.n_position_rows == 0 or n == 0:
        return np.zeros(n)
    position = functions(model)["position"]
    return np.asarray(model.evaluate(position, X, t, _parameters(model, n))[0], float).ravel()


def velocity_residual_along(model, X: np.ndarray, V: np.ndarray, t: np.ndarray) -> np.ndarray:
    """max_i |J_i v + f_t,i| / s_i (m/s) at each sample."""
    n = len(t)
    if model.n_constraints == 0 or n == 0:
        return np.zeros(n)
    velocity = functions(model)["velocity"]
    return np.asarray(model.evaluate(velocity, X, V, t, _parameters(model, n))[0], float).ravel()
