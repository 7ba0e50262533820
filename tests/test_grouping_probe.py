"""The grouping's numeric probe (constrained.manifold.vectorized.grouping): a candidate kernel is
compared with a bucket's rows in numbers — the rows' values at the probe points computed once
for them all (``_row_values``), the kernel evaluated on the rows' own coordinates and numbers —
instead of writing the kernel out for every row in SX (``_same``). Both must find the same groups
with the same data, on friendly and unfriendly systems: uneven masses and lengths, springs of
zero rest length among others, rows a kernel cannot take, values that are not finite at the
probe points, rows that read velocities (then every bucket is compared in SX)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import constrained as C
from constrained.manifold.vectorized import grouping
from constrained.model.structure import Structure


def _rope(n: int, *, varied: bool, zero_rest: bool = False, extras: bool = False) -> C.System:
    s = C.System(name="rope")
    lengths = [0.01 * (1 + 0.3 * np.sin(i) * varied) for i in range(n)]
    masses = [0.01 * (1 + 0.5 * np.cos(i) * varied) for i in range(n)]
    at = np.cumsum(np.c_[lengths, np.zeros(n), np.zeros(n)], axis=0)
    for i in range(n):
        s.add_particle(f"p{i}", masses[i], at[i])
    s.add(C.Distance("p0", point=[0, 0, 0], length=lengths[0]))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=lengths[i]))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1], 0.0), C.Gravity([0, -9.81, 0]))
    if zero_rest:  # springs of zero rest length (another formula) among ones of a rest length
        s.add(*[C.Spring(f"p{i}", f"p{i + 2}", k=0.1 * (1 + i % 2), rest=0.0 if i % 3 else 0.02)
                for i in range(n - 2)])
    if extras:
        s.add(C.Spring("p1", f"p{n - 1}", k=0.5, rest=0.02), C.Damping(0.01, ["p2", "p3"]),
              C.Custom(f"x_p{n // 2} - y_p{n // 2} - 0.1"),
              C.Custom(f"log(x_p{n // 3} - 100) - 1"),  # not finite at the probe points
              C.Potential("0.001*sqrt(y_p2 - 50)"))  # nor this term
    return s


def _cloth(k: int) -> C.System:
    s = C.System(name="cloth")
    for i in range(k):
        for j in range(k):
            s.add_particle(f"q{i}_{j}", 1.5e-5 * (1 + 0.1 * ((i + j) % 3)), [0.01 * i, 0.01 * j, 0.0])
    for i in range(k):
        for j in range(k):
            for di, dj in ((1, 0), (0, 1)):
                if i + di < k and j + dj < k:
                    s.add(C.Distance(f"q{i}_{j}", f"q{i + di}_{j + dj}", length=0.01))
    for i in range(k - 1):
        for j in range(k - 1):
            s.add(C.Spring(f"q{i}_{j}", f"q{i + 1}_{j + 1}", k=0.5, rest=0.01 * 2 ** 0.5))
            s.add(C.Spring(f"q{i + 1}_{j}", f"q{i}_{j + 1}", k=0.25, rest=0.01 * 2 ** 0.5))
    s.add(C.Pin("q0_0", [0, 0, 0.0]), C.Gravity([0, 0, -9.81]))
    return s


SYSTEMS = {
    "rope": lambda: _rope(40, varied=False),
    "uneven rope": lambda: _rope(40, varied=True),
    "springs of zero rest length": lambda: _rope(40, varied=True, zero_rest=True),
    "extras": lambda: _rope(40, varied=True, extras=True),
    "cloth": lambda: _cloth(7),
}


def _groups(exprs: list, e) -> tuple:
    groups, rest = grouping.grouped(exprs, e.x, e.t, e.p, {})
    return [(g.place.tolist(), g.index.tolist(), g.sources.tolist(), g.constants.tolist(), g.parts,
             str(g.local)) for g in groups], rest


def _both(exprs: list, e, monkeypatch) -> tuple:
    numeric = _groups(exprs, e)
    with monkeypatch.context() as m:
        m.setattr(grouping, "_row_values", lambda *a: None)  # every bucket compared in SX
        symbolic = _groups(exprs, e)
    return numeric, symbolic


@pytest.mark.parametrize("name", SYSTEMS)
def test_the_numeric_probe_finds_the_groups_the_symbolic_one_finds(name, monkeypatch):
    e = Structure(SYSTEMS[name]()).expressions
    terms = [s for term in e.slots["potential"] for s in grouping.summands(term)]
    for exprs in (e.rows, terms):
        numeric, symbolic = _both(exprs, e, monkeypatch)
        assert numeric == symbolic
        stacked = ca.vertcat(*exprs)  # the Function's sparsity is the expressions'
        function = grouping._rows_function(stacked, e.x, e.t, e.p)
        for k, symbol in ((0, e.x), (2, e.p)):  # (on the entries the rows read: in the whole vector's places)
            expected = ca.jacobian_sparsity(stacked, symbol).T
            colind, row = function.reads(k)
            assert colind.tolist() == expected.colind() and row.tolist() == expected.row()
    groups, _ = _groups(e.rows, e)
    assert groups and max(len(g[0]) for g in groups) >= 39  # (the rods are one group)


def test_rows_of_other_functions_in_one_bucket_are_told_apart(monkeypatch):
    """Rows of one shape whose operations differ (a square, a sine, a rod's length) split into
    their kinds; rows not finite at the probe points (a logarithm's) match no candidate and are
    cut out one by one (their equal serializations then make one group)."""
    x, t, p = ca.SX.sym("x", 60), ca.SX.sym("t"), ca.SX.sym("p", 3)
    rows = []
    for i in range(0, 60, 3):
        a, b = x[i], x[i + 1]
        rows += [a * a - b, ca.sin(a) - b, ca.sqrt(a * a + b * b) - p[i % 3], ca.log(a - 50) + b]
    numeric = grouping.grouped(rows, x, t, p, {})
    with monkeypatch.context() as m:
        m.setattr(grouping, "_row_values", lambda *a: None)
        symbolic = grouping.grouped(rows, x, t, p, {})
    assert [g.place.tolist() for g in numeric[0]] == [g.place.tolist() for g in symbolic[0]]
    assert numeric[1] == symbolic[1]
    assert sorted(g.place.tolist() for g in numeric[0]) == [list(range(k, 80, 4)) for k in range(4)]
    assert numeric[1] == []


def test_rows_that_read_velocities_are_compared_in_sx():
    """A row of x and v cannot be evaluated from x, t and p: no values for the probe (the
    buckets are compared in SX, where such rows are left to the rest)."""
    x, v, t, p = ca.SX.sym("x", 30), ca.SX.sym("v", 30), ca.SX.sym("t"), ca.SX.sym("p", 1)
    rows = [x[i] * x[i] - p[0] for i in range(30)] + [x[0] * v[0]]
    function = grouping._rows_function(ca.vertcat(*rows), x, t, p)
    assert function is None and grouping._row_values(function, x, t, p) is None
    groups, rest = grouping.grouped(rows, x, t, p, {})
    assert [g.place.tolist() for g in groups] == [list(range(30))] and rest == [30]
