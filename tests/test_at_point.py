"""The vectorized build's values at one numeric state (manifold/vectorized/at_point.py): the
numbers of the Functions they stand in for at a start, bit for bit."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from test_vectorized import SYSTEMS, _state, rope

from constrained.manifold import manifold, residual
from constrained.manifold.vectorized import at_point
from constrained.manifold.vectorized import build as vb
from constrained.manifold.vectorized import graphs as vg
from constrained.model.cache import structure_cache
from constrained.model.structure import Model, Structure

#: (name of the value, the outputs evaluated, the view's graph of it): as the start's Functions
#: build them (manifold.constraint_values, sparse_jacobian's nonzeros, residual.row_scales).
VALUES = (("f", ("f",), lambda view, X, T: view.constraint(X, T)),
          ("J", ("f", "J"), lambda view, X, T: view.jacobian(X, T)[1].nz[:]),
          ("scale", ("scale",), lambda view, X, T: view.row_scales(X, T)))


def _function_value(model, graph):
    X, T = ca.MX.sym("x", model.n_coordinates), ca.MX.sym("t")
    P = ca.MX.sym("p", len(model.parameter_vector))
    function = ca.Function("value", [X, T, P], [ca.densify(graph(vg.VectorizedView(model, P), X, T))])
    return lambda x, t: np.asarray(function(x, t, model.parameter_vector), float).ravel()


def _states(model, system):
    x, _, t = _state(model, system)
    on_top = np.asarray(system.positions, float).ravel().copy()
    on_top[3:6] = on_top[0:3]  # two particles at one place: a rod's direction 0/0 (NaN)
    far = x.copy()
    far[-3:] = np.inf
    return [(x, t), (np.asarray(system.positions, float).ravel(), 0.0), (on_top, 0.1), (far, 0.2)]


@pytest.mark.parametrize("compiled", [True, False], ids=["C loops", "columns"])
@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_values_at_a_state_are_the_functions_numbers_bit_for_bit(name, compiled, monkeypatch):
    if not compiled:
        monkeypatch.setenv("CONSTRAINED_COMPILE", "0")
    system = SYSTEMS[name]()
    model = Model(system, structure=Structure(system))  # (its own build: with or without the C loops)
    b = vb.vectorized_build(model.structure)
    for key, outputs, graph in VALUES:
        reference = _function_value(model, graph)
        for x, t in _states(model, system):
            with np.errstate(all="ignore"):
                got = at_point.values_at(b, x, None, t, model.parameter_vector, outputs)
            assert got is not None, (key, outputs)
            want = reference(x, t)
            assert got[key].shape == want.shape
            assert np.array_equal(got[key], want, equal_nan=True), (key, x[:6])


def test_on_numbers_replays_a_kernel_as_casadi_evaluates_it():
    a, b = ca.SX.sym("a"), ca.SX.sym("b")
    out = [ca.if_else(a < b, ca.sqrt(a * a + b) / (a - b), ca.fmax(ca.fabs(b), 2 * a)),
           ca.logic_not(a) + (a <= b) + (a == b) - (a != b) + ca.fmin(a, -b) + 1 / b - a ** 2, ca.DM(3.5)]
    kernel = ca.Function("k", [a, b], out)
    rng = np.random.default_rng(4)
    xa = np.r_[rng.standard_normal(40), 0.0, -0.0, np.nan, np.inf, -np.inf, 1.0]
    xb = np.r_[rng.standard_normal(40), 0.0, 1.0, 1.0, np.nan, 2.0, 1.0]
    with np.errstate(all="ignore"):
        got = at_point.on_numbers(kernel, [lambda j: xa, lambda j: xb], xa.size)
    want = [np.asarray(o, float).ravel() for o in kernel.map(xa.size)(xa[None], xb[None])]
    for g, w in zip(got, want, strict=True):
        assert np.array_equal(g[0], w, equal_nan=True)
    with pytest.raises(at_point.NotExact):
        at_point.on_numbers(ca.Function("s", [a], [ca.sin(a)]), [lambda j: xa], xa.size)


def test_a_large_models_first_calls_are_on_numbers_then_its_function():
    system = rope(120, varied=True)  # 360 coordinates: the vectorized build
    model = Model(system, structure=Structure(system))
    assert vg.applies(model)
    cache, prefix = structure_cache(model)
    f, J = manifold.constraint_values(model), manifold.sparse_jacobian(model)
    states = [_state(model, system, seed)[::2] for seed in range(at_point.NUMERIC_CALLS + 2)]
    values = [(f(x, t)[0], np.asarray(J(x, t).nonzeros()), residual.row_scales(model, x, t))
              for x, t in states]
    for key in ("constraint", "jacobian_nonzeros", "row scales"):
        assert cache[(*prefix, "numeric calls", key)] == at_point.NUMERIC_CALLS
        assert (*prefix, "structural", key) in cache  # the Function, after them
    functions = [(_function_value(model, graph)) for _, _, graph in VALUES]
    for (x, t), got in zip(states, values, strict=True):
        for g, function in zip(got, functions, strict=True):
            assert np.array_equal(g, function(x, t))
