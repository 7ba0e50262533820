"""The vectorized build's Functions on the entries they read (``vectorized.rest``) and its kept
gathers (``columns.take``): the same numbers as the Functions of the whole x, v and p and as a
gather by a Python list, bit for bit, on a rope whose rest has a custom row, a spring, damping
(forces of v), a moving anchor (rows of t) and entries of p."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from test_vectorized import rope

from constrained.manifold.vectorized import build as vb
from constrained.manifold.vectorized import columns
from constrained.manifold.vectorized.rest import Positions
from constrained.model.structure import Structure

OUTPUTS = [("f",), ("J", "gamma"), ("f", "J", "f_t", "scale"), ("F", "E"), ("E",), ("gamma", "F")]


@pytest.fixture(scope="module")
def build():
    system = rope(40, varied=True, moving=True)
    extras = rope(40, varied=True, extras=True)
    kept = [e for e in extras.effects if type(e).__name__ in ("Spring", "Damping")]
    system.add(*extras.constraints[-1:], *kept)  # a custom row, a spring, damping
    return vb.VectorizedBuild(Structure(system))


@pytest.mark.parametrize("outputs", OUTPUTS, ids="-".join)
def test_the_rest_on_the_entries_it_reads_gives_the_whole_vectors_numbers(build, outputs):
    e, rng = build.e, np.random.default_rng(3)
    x, v, p = (rng.uniform(-1, 1, n) for n in (build.n3, build.n3, e.p.numel()))
    t = 0.37
    rest = build._rest_function(outputs)
    whole = ca.Function("whole", [e.x, e.v, e.t, e.p], [build.rest[k] for k in outputs])
    expected = [np.asarray(o, float) for o in whole.call([x, v, t, p])]
    got = [np.asarray(o, float) for o in rest.function.call(list(rest.arguments(x, v, t, p)))]
    assert all(np.array_equal(a, b) for a, b in zip(expected, got, strict=True))
    # through an MX graph, as the step loops call it
    X, V, T = ca.MX.sym("x", build.n3), ca.MX.sym("v", build.n3), ca.MX.sym("t")
    P = ca.MX.sym("p", e.p.numel())
    out = rest(X, V, T, P)
    graph = ca.Function("graph", [X, V, T, P], list(out) if isinstance(out, list | tuple) else [out])
    assert all(np.array_equal(a, np.asarray(b, float)) for a, b in zip(expected, graph.call([x, v, t, p]),
                                                                        strict=True))
    assert len(rest.x_at) < build.n3 and len(rest.p_at) < e.p.numel()  # (what it is for)


def test_the_rows_rest_reads_velocities_and_time_where_they_do(build):
    rest = build._rest_function(("F",))
    assert len(rest.v_at)  # the damping
    assert not len(build._rest_function(("f",)).v_at)


def test_a_symbol_of_none_of_x_v_p_has_no_position(build):
    e = build.e
    places = Positions(e.x, e.v, e.t, e.p)
    assert places.of([ca.SX.sym("elsewhere")]) is None
    assert [a.tolist() for a in places.of([e.x[4], e.v[2], e.t, e.p[1], e.x[1]])] == [[1, 4], [2], [1]]
    assert Positions(e.x, None, e.t, e.p).of([e.v[2]]) is None  # (rows of velocities: none)


@pytest.mark.parametrize("index", [np.array([5, 3, 3, 0] * 40), np.arange(2, 200, 3), np.arange(300),
                                   np.random.default_rng(1).integers(0, 300, 1000), np.array([7])],
                         ids=["repeats", "progression", "whole", "random", "one"])
def test_a_kept_gather_is_the_gather_by_a_list(index):
    column = ca.MX.sym("c", 300)
    values = np.random.default_rng(2).normal(size=300)
    got = ca.Function("got", [column], [columns.take(column, index)])(values)
    again = columns.take(column, index.copy())  # (its plan kept: found by content)
    assert columns._plan(index) is columns._plan(index.copy())
    expected = ca.Function("expected", [column], [column[index.tolist()]])(values)
    assert np.array_equal(np.asarray(got), np.asarray(expected))
    assert np.array_equal(np.asarray(ca.Function("again", [column], [again])(values)), np.asarray(expected))
    if index.size == 300 and np.array_equal(index, np.arange(300)):
        assert columns.take(column, index) is column
