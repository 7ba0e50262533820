"""Rows and terms kept as SX columns (``model.symbols.Stacked``): a run of rods, a plane's rows,
a run of springs are held as the column their vectorized formula builds, and gravity's Batch
holds its summands, so that nothing is split into 10,000s of expressions to be joined again.
The Structure's f and V must be the expressions built item by item (the same SX, in the same
order), its labels, owners and flags (rheonomic, time-dependent forces, forces of v) those of
the whole f and V, and the mapped build's groups those that unfolding V finds — on systems
chosen to break them: gravity of a parameter formula, two gravities and a field, rods with
formula lengths and a rod to a fixed point among plain ones, springs written b→a, a rod whose
length is a formula of t, damping among springs, one particle."""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np
import pytest
from test_batched_groups import _same_groups

import constrained as C
from constrained.manifold.mapped import MappedBuild
from constrained.manifold.vectorized.grouping import summands
from constrained.model import lifting
from constrained.model.constraints import BATCH_FROM
from constrained.model.structure import Structure
from constrained.model.symbols import Stacked, Symbols

N = 2 * BATCH_FROM + 40  # (a run of springs on either side of a damper: each batched)


def _chain(n: int = N, *, g=(0.3, -9.81, 0.0), field: bool = False, formulas: bool = False,
           of_t: bool = False, springs: bool = False, damping: bool = False) -> C.System:
    """A chain of uneven masses: a rod to a fixed point at its middle, every seventh rod's length
    a formula (``formulas``; ``of_t``: one of t), springs along every other pair, some written
    from the far end (``springs``), a plane over all, gravity ``g``; ``field``: a second gravity
    on some particles and a potential formula; ``damping``: a damper among the springs."""
    s = C.System(name="chain", parameters={"L": 0.01, "gy": -9.0, "w": 2.0})
    for i in range(n):
        s.add_particle(f"p{i}", 0.01 * (1 + 0.5 * np.cos(i)), [0.01 * (i + 1), 0.002 * np.sin(i), 0.0])
    for i in range(1, n):
        length = 0.01 * (1 + 0.01 * np.sin(i))
        if formulas and i % 7 == 0:
            length = "L*(1 + 0.01*sin(w*t))" if of_t and i == 14 else "L"
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=length) if i % 3 else
              C.Distance(f"p{i}", f"p{i - 1}", length=length))
        if i == n // 2:
            s.add(C.Distance(f"p{i}", point=[0.0, 0.1, 0.0], length=0.2))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1], 0.0))
    if springs:
        for i in range(n - 2):
            a, b = (f"p{i}", f"p{i + 2}") if i % 4 else (f"p{i + 2}", f"p{i}")
            s.add(C.Spring(a, b, k=1.0 + 0.01 * i, rest=0.02))
            if damping and i == n // 2:
                s.add(C.Damping(0.3, a=a, b=b))
    s.add(C.Gravity(list(g)))
    if field:
        s.add(C.Gravity([0.0, 0.0, 2.5], particles=[f"p{i}" for i in range(0, n, 3)]),
              C.Potential("0.5*y_p3"))
    return s


SYSTEMS = {
    "chain": lambda: _chain(),
    "gravity of a parameter": lambda: _chain(g=(0.0, "gy", 0.0)),
    "gravity of t": lambda: _chain(g=(0.0, "-9.81*(1 + 0.1*sin(w*t))", 0.0)),
    "two gravities and a field": lambda: _chain(field=True),
    "formula lengths": lambda: _chain(formulas=True, springs=True),
    "a length of t": lambda: _chain(formulas=True, of_t=True),
    "springs both ways": lambda: _chain(springs=True),
    "damping among springs": lambda: _chain(springs=True, damping=True),
    "one particle": lambda: _one(),
}


def _one() -> C.System:
    s = C.System(name="one")
    s.add_particle("a", 0.2, [0.1, 0.0, 0.0])
    s.add(C.Distance("a", point=[0, 0, 0], length=0.1), C.Gravity([0, -9.81, 0]))
    return s


def _serialized(inputs, output) -> str:
    return ca.Function("f", inputs, [output]).serialize()


def _one_by_one(system: C.System) -> tuple:
    """f, V, the labels and owners of the rows, built item by item (``rows``, ``term``; gravity
    as −dot(gᵀP, m)) from Symbols of the lifted system."""
    lifted, numbers = lifting.lift(system)
    s = Symbols(lifted, symbolic_parameters=True, numbers=len(numbers))
    rows, labels, owners = [], [], []
    for k, c in enumerate(lifted.constraints):
        for expr, label in c.rows(s):
            rows.append(expr), labels.append(label), owners.append(k)
    terms = []
    for e in lifted.effects:
        if isinstance(e, C.Gravity):
            names = e.particles or [p.name for p in lifted.particles]
            m = s.mass_column([s.index(p, "g") for p in names]).T
            terms.append(-ca.dot(ca.mtimes(s.point(e.g, "g").T, s.columns(names, "g")), m))
        elif e.slot == "potential":
            terms.append(e.term(s))
    V = ca.sum1(ca.vertcat(*terms)) if len(terms) > 1 else terms[0]
    return s, ca.vertcat(*rows), V, labels, owners


@pytest.mark.parametrize("name", SYSTEMS)
def test_f_and_v_are_the_expressions_built_one_by_one(name):
    system = SYSTEMS[name]()
    structure = Structure(system)
    e = structure.expressions
    s, f, V, labels, owners = _one_by_one(system)
    assert _serialized([e.x, e.t, e.p], e.rows.column()) == _serialized([s.x, s.t, s.p], f)
    assert [e.rows[k].__repr__() for k in range(len(e.rows))] == [r.__repr__() for r in ca.vertsplit(f)]
    V_structure = structure.function("potential").call([e.x, e.t, e.p])[0]
    assert _serialized([e.x, e.t, e.p], V_structure) == _serialized([s.x, s.t, s.p], V)
    if name != "one particle":  # (kept whole: rods, the plane, springs)
        assert sum(not isinstance(segment, list) for _, segment in e.rows.segments()) >= 3
        assert ("springs" not in name) or any(not isinstance(segment, list)
                                              for _, segment in e.slots["potential"].segments())
    assert structure.constraint_labels == labels
    assert structure.constraint_owner.tolist() == owners
    # the flags are the whole expressions' answers
    assert structure.rheonomic == bool(ca.depends_on(f, s.t))
    assert ("time_dependent_forces" in structure.active_terms) == bool(
        ca.depends_on(V, s.t) or ca.depends_on(structure.function("dynamics").call(
            [e.x, e.v, e.t, e.p])[0], e.t))
    F = structure.function("dynamics").call([e.x, e.v, e.t, e.p])[0]
    assert structure.forces_depend_on_velocity == bool(ca.depends_on(F, e.v))


def test_the_flags_follow_the_formulas_of_t_and_v():
    """(That the cases above exercise both answers.)"""
    assert Structure(SYSTEMS["a length of t"]()).rheonomic
    assert not Structure(SYSTEMS["formula lengths"]()).rheonomic
    assert "time_dependent_forces" in Structure(SYSTEMS["gravity of t"]()).active_terms
    assert "time_dependent_forces" not in Structure(SYSTEMS["chain"]()).active_terms
    assert Structure(SYSTEMS["damping among springs"]()).forces_depend_on_velocity
    assert not Structure(SYSTEMS["springs both ways"]()).forces_depend_on_velocity


@pytest.mark.parametrize("name", SYSTEMS)
def test_summands_held_by_a_batch_are_those_unfolding_finds(name):
    """The mapped build with gravity's summands taken from its Batch, and with them unfolded
    from V (the Batches without ``values``, the potential slot as a plain list): the same
    groups, rest and Functions' values."""
    structure = Structure(SYSTEMS[name]())
    e = structure.expressions
    held = MappedBuild(structure)
    assert not any(b.values is not None for b in e.row_batches)
    plain = dataclasses.replace(
        e, slots={**e.slots, "potential": list(e.slots["potential"])},
        term_batches=tuple(dataclasses.replace(b, values=None) for b in e.term_batches))
    structure.expressions = plain
    unfolded = MappedBuild(structure)
    _same_groups(held.rows, unfolded.rows, e.t)
    _same_groups(held.terms, unfolded.terms, e.t)
    assert np.array_equal(held.rest_place, unfolded.rest_place)
    rest = [held.rest_slots["potential"], unfolded.rest_slots["potential"]]
    assert [repr(r) for r in rest[0]] == [repr(r) for r in rest[1]]
    x = np.asarray(structure_positions := np.linspace(0.01, 0.02, e.x.numel()))
    v, p = np.cos(structure_positions), np.linspace(0.5, 1.5, e.p.numel())
    for name_ in ("dynamics", "forces_and_potential"):
        a = held.function(name_)(x, v, 0.3, p)
        b = unfolded.function(name_)(x, v, 0.3, p)
        for u, w in zip(a, b, strict=True):
            assert np.array_equal(np.asarray(u), np.asarray(w))


def test_gravitys_summands_are_the_unfolded_ones():
    """Gravity's Batch ``values``: exactly ``summands`` of its term, in order, for plain masses
    and g of one or several nonzero entries, over some particles; none for g all zero or g a
    formula (the sum is then unfolded as before)."""
    system = _chain(n=BATCH_FROM + 3)
    lifted, numbers = lifting.lift(system)
    s = Symbols(lifted, symbolic_parameters=True, numbers=len(numbers))
    names = [p.name for p in lifted.particles]
    for g, particles, batched in (([0.0, -9.81, 0.0], None, True), ([0.3, -9.81, 2.0], names[::2], True),
                                  ([0.0, 0.0, 0.0], None, False), ([0.0, "gy", 0.0], None, False)):
        gravity, _ = lifting.lift(C.System(particles=list(system.particles), effects=[
            C.Gravity(g, particles)], parameters={"gy": -9.0}))
        term, batch = gravity.effects[0].term_and_batch(s)
        assert (batch is not None) == batched
        if batch is not None:
            walked = summands(term)
            assert len(walked) == batch.values.numel() == len(batch.items)
            for a, b in zip(walked, ca.vertsplit(batch.values), strict=True):
                assert _serialized([s.x, s.p], a) == _serialized([s.x, s.p], b)


def test_a_stacked_column_reads_as_the_list_of_its_expressions():
    x = ca.SX.sym("x", 80)
    stacked, listed = Stacked(), []
    for k in range(3):
        stacked.add(x[k] * 2), listed.append(x[k] * 2)
    column = ca.sin(x[3:73])
    stacked.add_column(column), listed.extend(ca.vertsplit(column))
    stacked.add(x[75]), listed.append(x[75])
    stacked.add_column(x[76:78] + 1), listed.extend(ca.vertsplit(x[76:78] + 1))
    assert len(stacked) == len(listed) == 76
    assert [repr(stacked[k]) for k in range(76)] == [repr(e) for e in listed]
    assert repr(stacked[-1]) == repr(listed[-1])
    with pytest.raises(IndexError):
        stacked[76]
    assert _serialized([x], stacked.column()) == _serialized([x], ca.vertcat(*listed))
    keep = np.arange(76) % 3 != 1
    kept = stacked.select(keep)
    assert [repr(e) for e in kept] == [repr(e) for e, k in zip(listed, keep, strict=True) if k]
    t = ca.SX.sym("t")
    assert not stacked.may_depend_on(t)
    stacked.add(x[0] * t)
    assert stacked.may_depend_on(t) and not stacked.select(np.r_[keep, False]).may_depend_on(t)


# --- columns held as their recipe (``symbols.Formula``) -----------------------------------------

def _formulas(stacked: Stacked) -> list:
    return [segment for _, segment in stacked.segments() if not isinstance(segment, list)]


def _eager(monkeypatch) -> None:
    """Formulas as columns were before: every element asked for read from the whole column."""
    from constrained.model import symbols
    monkeypatch.setattr(symbols.Formula, "ALONE_UP_TO", 0)


FUNCTIONS = ("constraint", "jacobian", "velocity_terms", "dynamics", "energy", "potential",
             "forces_and_potential", "kinetic")


@pytest.mark.parametrize("name", SYSTEMS)
def test_the_functions_of_held_columns_are_those_of_whole_columns(name, monkeypatch):
    """The Structure's Functions with its columns held as recipes — the mapped build having
    first asked for single rows and terms built alone, before anything asked for a whole
    column — are those of columns built whole at once (read element by element from them, as
    before): the same serialization, and the same values at random states."""
    lazy = Structure(SYSTEMS[name]())
    lazy_mapped = MappedBuild(lazy)  # (single rows and terms built alone, before any whole column)
    held = _formulas(lazy.expressions.rows) + _formulas(lazy.expressions.slots["potential"])
    assert name == "one particle" or held
    with monkeypatch.context() as m:
        _eager(m)
        whole = Structure(SYSTEMS[name]())
        eager_mapped = MappedBuild(whole)
    e, rng = lazy.expressions, np.random.default_rng(7)
    for function in FUNCTIONS:
        a, b = lazy.function(function), whole.function(function)
        assert a.serialize() == b.serialize(), function
        args = [rng.uniform(0.5, 1.5, a.size_in(i)) for i in range(a.n_in())]
        for u, w in zip(a.call(args), b.call(args), strict=True):
            assert np.array_equal(np.asarray(u), np.asarray(w), equal_nan=True), function
    t_b = whole.expressions.t
    _same_groups(lazy_mapped.rows, eager_mapped.rows, e.t, t_b)
    _same_groups(lazy_mapped.terms, eager_mapped.terms, e.t, t_b)
    assert np.array_equal(lazy_mapped.rest_place, eager_mapped.rest_place)


def test_an_instance_built_alone_is_its_element_of_the_whole_column():
    """Each rod's row, each spring's term (some written b→a) and those of a part (``part``,
    ``select``): built alone, before the column, the same expression as its element of the
    column built later; past ALONE_UP_TO asked, read from the whole column."""
    structure = Structure(_chain(springs=True))
    e = structure.expressions
    formulas = _formulas(e.rows) + _formulas(e.slots["potential"])
    assert formulas and not any(f.built for f in formulas if f._root._build is not None)
    for f in formulas:
        part = f.part(np.arange(1, f.numel(), 3))
        alone = [f[k] for k in range(f.numel())[:20]] + [part[k] for k in range(part.numel())[:10]]
        column, part_column = f.column(), part.column()
        assert f.built and part.built
        for k, expr in enumerate(alone[:20]):  # (is_equal takes a + b for b + a: repr does not)
            assert ca.is_equal(expr, column[k], 100) and repr(expr) == repr(column[k])
        for k, expr in enumerate(alone[20:]):
            assert repr(expr) == repr(part_column[k]) == repr(column[1 + 3 * k])
        assert all(f[k] is not None and repr(f[k]) == repr(column[k]) for k in range(f.numel()))
    stacked = Structure(_chain(springs=True)).expressions.slots["potential"]  # (springs, gravity)
    ks = [len(stacked) - 1, 3, 0, 5, 3, 40, -1]
    together = stacked.elements(ks)  # (the sample of the mapped build: built by one call)
    assert [repr(e) for e in together] == [repr(stacked[k]) for k in ks]
    whole = stacked.column()
    assert [repr(e) for e in together] == [repr(whole[k]) for k in ks]
    fresh = _formulas(Structure(_chain(springs=True)).expressions.rows)[0]
    asked = [fresh[k % fresh.numel()] for k in range(fresh.ALONE_UP_TO + 1)]
    assert fresh.built and len(asked) == fresh.ALONE_UP_TO + 1  # (asked for often: built whole)


def _cloth(n: int) -> C.System:
    """An n × n cloth: rods along rows and columns, shear springs both ways, two pins, gravity."""
    s = C.System(name="cloth")
    for i in range(n):
        for j in range(n):
            s.add_particle(f"p{i}_{j}", 0.01 * (1 + 0.1 * ((i + 2 * j) % 5)), [0.01 * j, 0.0, 0.01 * i])
    for i in range(n):
        for j in range(n):
            if j + 1 < n:
                s.add(C.Distance(f"p{i}_{j}", f"p{i}_{j + 1}", length=0.01))
            if i + 1 < n:
                s.add(C.Distance(f"p{i}_{j}", f"p{i + 1}_{j}", length=0.01))
    for i in range(n - 1):
        for j in range(n - 1):
            s.add(C.Spring(f"p{i}_{j}", f"p{i + 1}_{j + 1}", k=5.0, rest=0.0141),
                  C.Spring(f"p{i + 1}_{j}", f"p{i}_{j + 1}", k=5.0, rest=0.0141))
    s.add(C.Pin("p0_0", [0.0, 0.0, 0.0]), C.Pin(f"p0_{n - 1}", [0.01 * (n - 1), 0.0, 0.0]))
    s.add(C.Gravity([0.0, 0.0, -9.81]))
    return s


def test_a_large_models_vectorized_build_leaves_the_columns_unbuilt(monkeypatch):
    """On a cloth run on the vectorized build the rods' rows and the springs' terms are never
    made into whole columns (only a sample of single instances), and the groups are those found
    with the columns built whole."""
    from constrained.manifold.vectorized.build import vectorized_build
    system = _cloth(20)
    structure = Structure(system)
    vectorized_build(structure)
    e = structure.expressions
    formulas = [f for f in _formulas(e.rows) + _formulas(e.slots["potential"]) if f._root._build is not None]
    assert len(formulas) >= 2 and not any(f.built for f in formulas)
    assert sum(f.numel() for f in formulas) >= 2 * 19 * 20 + 2 * 19 * 19 - 2
    with monkeypatch.context() as m:
        _eager(m)
        eager = MappedBuild(Structure(_cloth(20)))
    lazy = MappedBuild(structure)
    _same_groups(lazy.rows, eager.rows, e.t, eager.e.t)
    _same_groups(lazy.terms, eager.terms, e.t, eager.e.t)
    assert not any(f.built for f in formulas)
