"""The vectorized build's values at one numeric state (manifold/vectorized/at_point.py): the
numbers of the Functions they stand in for at a start, bit for bit."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from test_batched_groups import _cloth
from test_vectorized import SYSTEMS, _state, rope

import constrained as C
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


def _spring_systems() -> dict:
    """Potentials the kernels hold (springs as groups), with formulas of t and p among plain
    numbers, uneven and parametric masses, and a rope with no effect at all."""
    cloth = _cloth(7, formulas=True)
    springy = rope(110, varied=True, moving=True)
    springy.parameters = {**(springy.parameters or {}), "k2": 3.5}
    for i in range(0, 106, 3):  # rest lengths: a formula of t every other spring, k a parameter
        springy.add(C.Spring(f"p{i}", f"p{i + 3}", k="k2" if i % 2 else 2.0,
                             rest="0.02 + 0.001*t*t" if i % 6 == 0 else 0.02 + 0.001 * i))
    bare = C.System(name="no effects")
    for i in range(120):
        bare.add_particle(f"b{i}", 0.01 * (1 + (i % 4)), [0.01 * i, 0.0, 0.0], [0.0, 0.1 * i, 0.0])
    for i in range(1, 120):
        bare.add(C.Distance(f"b{i - 1}", f"b{i}", length=0.01))
    return {"cloth with springs": lambda: cloth, "rope with springs": lambda: springy,
            "no effects": lambda: bare}


@pytest.mark.parametrize("compiled", [True, False], ids=["C loops", "columns"])
@pytest.mark.parametrize("name", sorted(SYSTEMS) + ["cloth with springs", "rope with springs", "no effects"])
def test_forces_and_energy_at_a_state_are_the_functions_numbers_bit_for_bit(name, compiled, monkeypatch):
    """``forces_and_energy_at`` (the start checks of finite forces and energy, on numbers) gives
    F and the energy of ``manifold.forces_and_energy``'s Function bit for bit, at moving states,
    with particles on top of each other and at infinity (NaN and inf where the Function has them)."""
    if not compiled:
        monkeypatch.setenv("CONSTRAINED_COMPILE", "0")
    system = {**SYSTEMS, **_spring_systems()}[name]()
    model = Model(system, structure=Structure(system))  # (large or not: the vectorized build)
    b = vb.vectorized_build(model.structure)
    X, V, T = ca.MX.sym("x", model.n_coordinates), ca.MX.sym("v", model.n_coordinates), ca.MX.sym("t")
    P = ca.MX.sym("p", len(model.parameter_vector))
    view = vg.VectorizedView(model, P)
    function = ca.Function("fe", [X, V, T, P], [ca.densify(view.dynamics(X, V, T)[0]), view.energy(X, V, T)])
    rng = np.random.default_rng(3)
    for x, t in _states(model, system):
        v = 0.2 * rng.standard_normal(model.n_coordinates)
        with np.errstate(all="ignore"):
            got = at_point.forces_and_energy_at(b, x, v, t, model.parameter_vector, model.masses)
        F, E = (np.asarray(o, float).ravel() for o in function(x, v, t, model.parameter_vector))
        assert got is not None
        assert np.array_equal(got[0], F, equal_nan=True), x[:6]
        assert np.array_equal([got[1]], E, equal_nan=True), (got[1], E)


def test_the_start_checks_of_forces_are_on_numbers_then_one_function():
    """``manifold.forces_and_energy`` of a large model: its first NUMERIC_CALLS calls on numbers
    (no Function built), then the Function, built once; every call gives the Function's numbers,
    and ``potential_forces_finite`` sees a force that is not finite."""
    system = _spring_systems()["rope with springs"]()
    model = Model(system, structure=Structure(system))
    cache, prefix = structure_cache(model)
    values = manifold.forces_and_energy(model)
    rng = np.random.default_rng(8)
    states = [(*_state(model, system, seed)[:2], 0.1 * seed) for seed in range(at_point.NUMERIC_CALLS + 2)]
    got = [values(x, v, t) for x, v, t in states]
    assert cache[(*prefix, "numeric calls", "forces_and_energy")] == at_point.NUMERIC_CALLS
    function = cache[(*prefix, "structural", "forces_and_energy")]
    for (x, v, t), (F, E) in zip(states, got, strict=True):
        want = function(x, v, t, model.parameter_vector)
        assert np.array_equal(F, want[0]) and np.array_equal(E, want[1])
    fresh = Model(system, structure=Structure(system))
    x0, v0 = (np.asarray(a, float).ravel() for a in (system.positions, system.velocities))
    assert manifold.potential_forces_finite(fresh)(x0, v0 + rng.standard_normal(v0.size), 0.0)
    x0[7] = np.inf
    assert not manifold.potential_forces_finite(fresh)(x0, v0, 0.0)
    assert (*structure_cache(fresh)[1], "structural", "forces_and_energy") not in structure_cache(fresh)[0]


def test_a_potential_outside_the_exact_operations_is_left_to_the_function():
    """A spring whose stiffness is a formula with sin(t): its energy is not replayed on numbers
    (libraries round sin differently), so the Function is built and gives the values."""
    system = rope(110)
    system.add(*(C.Spring(f"p{i}", f"p{i + 4}", k="2 + sin(t)", rest=0.03) for i in range(0, 100, 2)))
    model = Model(system, structure=Structure(system))
    x, v, t = _state(model, system)
    b = vb.vectorized_build(model.structure)
    assert at_point.forces_and_energy_at(b, x, v, t, model.parameter_vector, model.masses) is None
    F, E = manifold.forces_and_energy(model)(x, v, t)
    cache, prefix = structure_cache(model)
    assert (*prefix, "structural", "forces_and_energy") in cache
    F_model = np.asarray(model.dynamics(x, v, t)[0], float).ravel()
    np.testing.assert_allclose(F, F_model, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(E, float(model.energy(x, v, t)), rtol=1e-12)


def test_a_kept_jacobian_reads_as_the_plain_dm_of_its_numbers():
    """``sparse_jacobian``'s J (at_point.JacobianAt) gives the nonzeros and compressed columns a
    plain DM of the same numbers gives, read-only, and the same full-rank verdict (its pivots)."""
    from constrained.manifold import sparse

    for system in (rope(120, varied=True), _cloth(12, formulas=True)):
        model = Model(system, structure=Structure(system))
        assert vg.applies(model)
        x, _, t = _state(model, system, 3)
        J = manifold.sparse_jacobian(model)(x, t)
        assert isinstance(J, at_point.JacobianAt)
        plain = ca.DM(J.sparsity(), list(ca.DM.nonzeros(J)))
        assert type(plain) is ca.DM
        assert np.array_equal(J.nonzeros(), np.asarray(plain.nonzeros(), float))
        assert not J.nonzeros().flags.writeable
        for kept, want in zip(J.compressed_columns(), plain.sparsity().get_ccs(), strict=True):
            assert np.array_equal(kept, np.asarray(want, np.int64))
        assert np.array_equal(np.asarray(J.full()), np.asarray(plain.full()))
        for masses in (model.inverse_masses, model.inverse_masses[::-1].copy()):
            assert (sparse.clearly_full_row_rank(J, masses)
                    == sparse.clearly_full_row_rank(plain, masses))
