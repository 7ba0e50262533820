"""Plain numbers are inputs too (constrained.lifting): a mass, length, spring constant, field
strength … written as a number, in a scene or a constructor, is an entry of p, so systems that
differ only in such numbers share one Structure (counted: ``Structure.builds``) and one
compiled step loop (counted: compilations), and give what the numbers written in as constants
give (``Structure(system, lift=False)``), to round-off."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import structure_reference

import constrained as C
from constrained.codegen import compiled
from constrained.errors import InputError
from constrained.model import expressions, lifting
from constrained.model.structure import Model, Structure, assemble

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"
BASE = dict(m=1.3, k=40.0, rest=0.3, c=0.2, q=0.7, length=0.9, offset=0.05, g=9.81, F=0.4,
            anchor=0.5)


def plain(**changes) -> C.System:
    """Two particles held by a rod to a point and a plane, with gravity, a spring to a point,
    damping, a charge in a field and an applied force: every number a plain number."""
    v = {**BASE, **changes}
    s = C.System(name="plain numbers")
    s.add_particle("a", v["m"], [v["anchor"] + v["length"], 0.0, v["offset"]], [0.0, 0.3, 0.0])
    s.add_particle("b", 1.0, [0.0, -1.0, v["offset"]])
    s.add(C.Distance("a", point=[v["anchor"], 0.0, 0.0], length=v["length"]),
          C.Plane(["a", "b"], [0, 0, 1], v["offset"]),
          C.Gravity([0.0, -v["g"], 0.0]),
          C.Spring("b", point=[0.0, v["anchor"], 0.0], k=v["k"], rest=v["rest"]),
          C.Damping(v["c"]),
          C.Electromagnetic({"a": v["q"]}, phi="-1.5*x", A=["0", "0.75*x", "0"]),
          C.Force("b", [v["F"], 0.0, 0.0]))
    return s


def constants(system) -> Model:
    """The reference: the numbers as constants inside the expressions (nothing lifted)."""
    return Model(system, structure=Structure(system, lift=False), numbers=np.zeros(0))


FUNCTIONS = {"constraint": "xt", "jacobian": "xt", "velocity_terms": "xt", "dynamics": "xvt",
             "energy": "xvt", "potential": "xt", "kinetic": "v"}


def assert_same(a: Model, b: Model) -> None:
    rng = np.random.default_rng(7)
    for _ in range(3):
        args = {"x": rng.standard_normal(a.n_coordinates), "v": rng.standard_normal(a.n_coordinates),
                "t": rng.uniform(0, 2)}
        for name, takes in FUNCTIONS.items():
            for oa, ob in zip(getattr(a, name).call([args[k] for k in takes]),
                              getattr(b, name).call([args[k] for k in takes]), strict=True):
                np.testing.assert_allclose(np.asarray(oa), np.asarray(ob), rtol=1e-13, atol=1e-13,
                                           err_msg=name)
    np.testing.assert_array_equal(a.masses, b.masses)


@pytest.mark.parametrize("change", [dict(m=2.1), dict(k=7.5), dict(rest=0.45), dict(c=1.1), dict(q=-0.2),
                                    dict(length=1.4), dict(offset=-0.3), dict(g=1.62), dict(F=-3.0),
                                    dict(anchor=-0.25), dict(m=0.4, length=2.0, g=3.7, k=0.5)])
def test_a_new_plain_number_shares_the_structure_and_equals_the_constants(change):
    base = assemble(plain())
    before = Structure.builds
    other = assemble(plain(**change))
    assert other.structure is base.structure and Structure.builds == before
    assert not np.array_equal(other.numbers, base.numbers)
    assert_same(other, constants(plain(**change)))
    assert other.constraint_labels == constants(plain(**change)).constraint_labels  # the values


def test_the_labels_read_the_numbers_as_written():
    labels = assemble(plain(length=0.75, anchor=0.5)).constraint_labels
    assert labels[0] == "distance a–(0.5, 0, 0) = 0.75 m"
    assert expressions.fill("k=⟦1⟧ N/m", np.array([3.0, 40.5])) == "k=40.5 N/m"


def test_zeros_stay_constants_so_sparsity_and_formulas_keep_their_shape():
    structure, reference = Structure(plain()), Structure(plain(), lift=False)
    for name in ("jacobian", "dynamics"):
        a, b = structure.function(name), reference.function(name)
        for i in range(a.n_out()):
            assert a.sparsity_out(i) == b.sparsity_out(i), name
    # a zero that becomes a number is another structure (a spring of rest length 0 is smooth at 0)
    base = assemble(plain())
    assert assemble(plain(rest=0.0)).structure is not base.structure
    assert assemble(plain(anchor=0.0)).structure is not base.structure


def test_the_plain_numbers_are_the_tail_of_p_in_walk_order():
    model = assemble(plain())
    v = BASE
    # masses, rod (point x, length), plane (normal z, offset), gravity y, spring (point y, k, rest),
    # damping, charge, force x
    assert model.numbers.tolist() == [v["m"], 1.0, v["anchor"], v["length"], 1.0, v["offset"], -v["g"],
                                      v["anchor"], v["k"], v["rest"], v["c"], v["q"], v["F"]]
    np.testing.assert_array_equal(model.parameter_vector, model.numbers)  # no named parameters
    assert model.parameters == {}


def test_a_system_of_another_structure_is_refused():
    base = assemble(plain())
    other = plain()
    other.add(C.Spring("a", "b", k=3.0))
    with pytest.raises(InputError, match="not a system of this structure"):
        Model(other, structure=base.structure)


def test_a_scene_read_with_a_new_number_shares_the_structure_and_runs_as_the_constants():
    path = SCENARIOS / "double_pendulum.toml"
    first = assemble(C.load_scene(path).system)
    before = Structure.builds
    sets = ["particles.p1.mass=1.7", "constraints[1].length=1.0", "effects[0].g=[0, -3.7, 0]"]
    scene = C.load_scene(path, sets)
    model = assemble(scene.system)
    assert model.structure is first.structure and Structure.builds == before
    kw = dict(method="dopri", rtol=1e-10, atol=1e-12, t_eval=[0.0, 1.0], outputs=["multipliers"])
    run = C.simulate(scene.system, 1.0, model=model, **kw)
    reference = C.simulate(scene.system, 1.0, model=constants(scene.system), compiled=False, **kw)
    np.testing.assert_allclose(run.x, reference.x, rtol=0, atol=1e-11)
    np.testing.assert_allclose(run.multipliers, reference.multipliers, rtol=1e-9, atol=1e-10)


@pytest.mark.skipif(compiled.compiler() is None, reason="no C compiler on this machine")
def test_new_plain_numbers_do_not_compile_again(tmp_path, monkeypatch):
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    builds = []
    original = compiled._build
    monkeypatch.setattr(compiled, "_build", lambda *a, **k: builds.append(1) or original(*a, **k))
    kw = dict(method="dopri", rtol=1e-9, atol=1e-11, t_eval=[0.0, 0.5], outputs=set(), compiled=True)
    system = plain(k=11.0)  # a structure of its own (a number no other test uses)
    system.add(C.Spring("a", "b", k=0.123))
    C.simulate(system, 0.5, **kw)
    assert len(builds) == 1
    for change in (dict(m=0.6, k=30.0), dict(length=1.2, g=4.0, c=0.05)):
        other = plain(**change)
        other.add(C.Spring("a", "b", k=0.321))
        run = C.simulate(other, 0.5, **kw)
        assert run.stats["evaluation"] == "compiled"
        reference = C.simulate(other, 0.5, **{**kw, "compiled": False}, model=constants(other))
        np.testing.assert_allclose(run.x[-1], reference.x[-1], rtol=0, atol=1e-10)
    assert len(builds) == 1, "a new plain number compiled the step loop again"


def test_constrained_run_uses_the_structure_built_while_loading(monkeypatch):
    """``Scene.loaded_model`` (what ``constrained run`` passes to ``run``): the Model of the
    Structure built at load, so the run neither fingerprints nor builds again, and runs as
    ``run()`` does; a scene whose system was replaced gets None."""
    import dataclasses

    from constrained.model import structure as structure_module

    scene = C.load_scene(Path(__file__).parents[1] / "scenarios" / "double_pendulum.toml")
    walks = []
    original = structure_module._fingerprint
    monkeypatch.setattr(structure_module, "_fingerprint", lambda s: walks.append(s) or original(s))
    before = Structure.builds
    loaded = scene.loaded_model()
    assert loaded.structure is scene.structure[1]
    fast = scene.run(model=loaded).trajectory
    assert walks == [] and Structure.builds == before
    plain_run = scene.run().trajectory
    assert len(walks) == 1 and Structure.builds == before
    assert np.array_equal(fast.t, plain_run.t) and np.array_equal(fast.x, plain_run.x)
    replaced = dataclasses.replace(scene, system=scene.system.copy())
    assert replaced.loaded_model() is None


def test_springs_built_in_a_batch_equal_springs_built_one_by_one(monkeypatch):
    """``Spring.batch_terms`` (runs of BATCH_FROM springs or more: a cloth's shear springs) gives
    the energy and forces of each spring's own ``term``, at a random state, for a mix of
    springs between particles (batched), to a point, with rest 0 and with k a formula
    (built one by one)."""
    from constrained.model import effects

    rng = np.random.default_rng(3)
    s = C.System(name="net", parameters={"kk": 2.0})
    n = 40
    for i in range(n):
        s.add_particle(f"p{i}", 0.01 + 0.001 * i, rng.normal(size=3) * 0.1)
    for i in range(n - 1):
        for j in (i + 1, min(i + 3, n - 1)):
            s.add(C.Spring(f"p{i}", f"p{j}", k=1.0 + 0.1 * i, rest=0.02 + 0.001 * j))
    s.add(C.Spring("p0", point=[0, 0, 0.1], k=3.0, rest=0.05), C.Spring("p1", "p5", k="kk", rest=0.0),
          C.Spring("p2", "p6", k="kk", rest=0.03))
    assert sum(isinstance(e, C.Spring) for e in s.effects) >= effects.BATCH_FROM
    built = []
    original = C.Spring.batch_terms.__func__
    monkeypatch.setattr(C.Spring, "batch_terms", classmethod(
        lambda cls, items, sym: built.append(len(items)) or original(cls, items, sym)))
    batched = Model(s, structure=Structure(s))
    assert built
    monkeypatch.setattr(effects, "BATCH_FROM", 10**9)
    single = Model(s, structure=Structure(s))
    x, v = rng.normal(size=3 * n) * 0.1, rng.normal(size=3 * n)
    assert float(batched.energy(x, v, 0.0)) == pytest.approx(float(single.energy(x, v, 0.0)), rel=1e-13)
    Fb = np.asarray(batched.dynamics(x, v, 0.0)[0]).ravel()
    Fs = np.asarray(single.dynamics(x, v, 0.0)[0]).ravel()
    assert np.allclose(Fb, Fs, rtol=1e-12, atol=1e-12 * np.abs(Fs).max())


def test_labels_are_filled_in_one_pass_as_one_by_one():
    values = np.array([0.01, 2.5, 1e-7, 0.01, -3.0])
    texts = ["rod ⟦0⟧ m", "⟦1⟧ and ⟦3⟧", "no number", "", "x⟦2⟧⟦4⟧", "a\0b ⟦1⟧"]
    for some in (texts[:5], texts, []):
        assert expressions.fill_all(some, values) == [expressions.fill(t, values) for t in some]


def test_a_run_of_rods_is_labelled_as_each_rod_labels_itself(monkeypatch):
    """The labels of rods built together (``Distance.batch_rows``, their tokens written without
    Number.__format__) are each rod's own ``label`` in the lifted system: named rods, unequal
    lengths, equal ones, rods to a point and a length given by a formula among them."""
    from constrained.model import constraints

    s = C.System(name="rods")
    s.parameters["L"] = 0.4
    for i in range(90):
        s.add_particle(f"q{i}", 1.0 + i % 3, [0.1 * i, 0.02 * (i % 5), 0.0])
    for i in range(89):
        length = "L" if i == 40 else (0.25 if i % 7 == 0 else 0.1 + 0.001 * i)
        s.add(C.Distance(f"q{i}", f"q{i + 1}", length=length, name="named" if i == 13 else None))
    s.add(C.Distance("q0", point=[0.0, 0.0, 1.0], length=1.0))
    for i in range(70):
        s.add(C.Distance(f"q{i}", f"q{i + 2}", length=0.2 + 1e-4 * i))
    structure = Structure(s)
    lifted, _ = lifting.lift(s)
    expected = [c.label for c in lifted.constraints]
    assert structure.constraint_labels == expected
    assert any("⟦" in label for label in expected)
    monkeypatch.setattr(constraints, "BATCH_FROM", 10**9)  # each rod by itself
    assert Structure(s).constraint_labels == expected


def test_plain_data_of_flat_tables_and_lists_as_one_by_one():
    for value in ([1, 2.5, "a", None, True], ("a", 1), {"a": 1, "b": None, "c": False},
                  {"a": [1, 2], "b": lifting.Number(3)}, [[1, "x"], {"k": 0.5}]):
        assert lifting.plain_data(value) == _plain_data_one_by_one(value)


def _plain_data_one_by_one(value):
    if isinstance(value, list | tuple):
        return [_plain_data_one_by_one(v) for v in value]
    if isinstance(value, dict):
        return ["mapping", [[_plain_data_one_by_one(k), _plain_data_one_by_one(v)] for k, v in value.items()]]
    if isinstance(value, lifting.Number):
        return ["number", value.index]
    return value


def test_fingerprints_tell_apart_what_runs_of_items_hold():
    from constrained.model.structure import structure_fingerprint

    def system(*items):
        s = C.System([C.Particle("p1", 1.0, [1, 0, 0]), C.Particle("p2", 2.0, [0, 1, 0]),
                      C.Particle("p3", 1.0, [0, 0, 1])])
        return s.add(*items)

    def rod(a="p1", b="p2", length=1.0, **kw):
        return C.Distance(a, b, length=length, **kw)

    same = structure_fingerprint(system(rod(), rod("p2", "p3"), C.Spring("p1", "p3", k=2.0)))
    assert same == structure_fingerprint(system(rod(length=3.0), rod("p2", "p3", length=0.5),
                                                C.Spring("p1", "p3", k=7.0)))
    others = [system(rod("p2", "p3"), rod(), C.Spring("p1", "p3", k=2.0)),
              system(rod(), rod("p3", "p2"), C.Spring("p1", "p3", k=2.0)),
              system(rod(), C.Pin("p3", [0, 0, 1.0]), C.Spring("p1", "p3", k=2.0)),
              system(rod(), rod("p2", "p3", name="second"), C.Spring("p1", "p3", k=2.0)),
              system(rod(), rod("p2", "p3"), C.Spring("p1", "p3", k=2.0, rest=0.5)),
              system(rod(), rod("p2", "p3"), C.Spring("p1", point=[0, 0, 1.0], k=2.0)),
              system(rod(), rod("p2", "p3"))]
    prints = {structure_fingerprint(s) for s in others}
    assert len(prints) == len(others) and same not in prints


def test_models_of_one_structure_label_rows_with_their_own_numbers():
    def rope(length):
        s = C.System([C.Particle("a", 1.0, [length, 0, 0])])
        return s.add(C.Distance("a", point=[0, 0, 0], length=length))

    first = assemble(rope(1.5))
    second = assemble(rope(2.5))
    assert first.structure is second.structure
    for _ in range(2):
        assert first.constraint_labels == ["distance a–(0, 0, 0) = 1.5 m"]
        assert second.constraint_labels == ["distance a–(0, 0, 0) = 2.5 m"]
    first.constraint_labels.append("changed")
    assert Model(rope(1.5), structure=first.structure).constraint_labels == \
        ["distance a–(0, 0, 0) = 1.5 m"]


def _chain_of_items(n: int = 1000) -> C.System:
    """About 2,000 items in runs: rods (the first and one in the middle to a point, one of a
    formula length), springs (some of rest 0, one of a formula k), a plane, gravity."""
    s = C.System(name="chain", parameters={"k": 3.0, "L": 0.02})
    for i in range(n):
        s.add_particle(f"p{i}", 0.01 * (1 + i % 3), [0.01 * (i + 1), 0.0, 0.0])
    rods = [C.Distance(f"p{i - 1}", f"p{i}", length=0.01) for i in range(1, n)]
    rods[n // 2] = C.Distance(f"p{n // 2 + 1}", point=[0.0, 0.5, 0.0], length=0.3)
    rods[n // 3] = C.Distance(f"p{n // 3}", f"p{n // 3 + 1}", length="L")
    springs = [C.Spring(f"p{i}", f"p{i + 2}", k=2.0, rest=0.0 if i % 7 else 0.02) for i in range(n - 2)]
    springs[n // 4] = C.Spring(f"p{n // 4}", f"p{n // 4 + 2}", k="2*k", rest=0.02)
    return s.add(C.Distance("p0", point=[0, 0, 0], length=0.01), *rods, C.Plane(list(s.names), [0, 0, 1]),
                 *springs, C.Gravity([0, -9.81, 0]))


def _changed(change) -> C.System:
    system = _chain_of_items()
    change(system)
    return system


class _Rod(C.Distance):
    """A rod of another class (the same attributes)."""


def _retyped(system, k: int) -> None:
    rod = system.constraints[k]
    system.constraints[k] = _Rod.__new__(_Rod)
    system.constraints[k].__dict__.update(vars(rod))


#: Changes of what a Structure is built from (a particle, a class, a formula, a zero).
_OTHER_STRUCTURES = {
    "a rod's particle": lambda s: setattr(s.constraints[20], "b", "p30"),
    "a rod to a point's particle": lambda s: setattr(s.constraints[0], "a", "p1"),
    "a rod's class": lambda s: _retyped(s, 700),
    "a length's formula": lambda s: setattr(s.constraints[334], "length", "2*L"),
    "a spring's formula": lambda s: setattr(s.effects[250], "k", "3*k"),
    "a number made a formula": lambda s: setattr(s.effects[10], "k", "k"),
    "a zero rest made nonzero": lambda s: setattr(s.effects[1], "rest", 0.5),
    "a nonzero rest made zero": lambda s: setattr(s.effects[7], "rest", 0.0),
    "a zero moved to the spring before": lambda s: (setattr(s.effects[0], "rest", 0.0),
                                                    setattr(s.effects[1], "rest", 0.02)),
    "a length made zero": lambda s: setattr(s.constraints[40], "length", 0.0),
    "a point's zero made nonzero": lambda s: s.constraints[501].point.__setitem__(0, 0.25),
    "a rod's name": lambda s: setattr(s.constraints[60], "name", "rod 60"),
    "a rod made one-sided": lambda s: setattr(s.constraints[61], "unilateral", True),
    "an int zero for a float zero": lambda s: setattr(s.effects[3], "rest", 0),
    "a mass made a formula": lambda s: s.particles[5].formulas.__setitem__("mass", "k"),
    "a parameter's name": lambda s: s.parameters.__setitem__("extra", 1.0),
    "a particle's name": lambda s: setattr(s.particles[4], "name", "q4"),
    "a restitution's zero made -0": lambda s: setattr(s.constraints[62], "restitution", -0.0),
    "a rod's place": lambda s: setattr(s.constraints[63], "where", "constraints[64]"),
}

#: Changes of plain nonzero numbers alone (the same Structure, other values of p).
_SAME_STRUCTURE = {
    "a length": lambda s: setattr(s.constraints[20], "length", 0.013),
    "a point's nonzero entry": lambda s: s.constraints[501].point.__setitem__(1, 0.7),
    "a spring's k": lambda s: setattr(s.effects[100], "k", 5.0),
    "an int for a float": lambda s: setattr(s.effects[101], "k", 2),
    "a mass": lambda s: setattr(s.particles[3], "mass", 0.5),
    "a parameter's value": lambda s: s.parameters.__setitem__("k", 4.0),
}


def _old_fingerprint(system) -> str:
    """The fingerprint as the JSON of ``structure_data`` hashed (the reference)."""
    import hashlib
    import json

    return hashlib.sha256(json.dumps(structure_reference.structure_data(system)[0]).encode()).hexdigest()


@pytest.mark.parametrize("change", list(_OTHER_STRUCTURES), ids=list(_OTHER_STRUCTURES))
def test_a_change_of_structure_changes_the_fingerprint(change):
    """The column-by-column fingerprint of a 2,000-item chain tells apart every change of what a
    Structure is built from, as the item-by-item data does."""
    from constrained.model.structure import structure_fingerprint

    base, other = _chain_of_items(), _changed(_OTHER_STRUCTURES[change])
    assert len(base.constraints) + len(base.effects) >= 2000
    assert structure_fingerprint(other) != structure_fingerprint(base)
    assert _old_fingerprint(other) != _old_fingerprint(base)


@pytest.mark.parametrize("change", list(_SAME_STRUCTURE), ids=list(_SAME_STRUCTURE))
def test_new_plain_numbers_keep_the_fingerprint_and_walk_as_item_by_item(change):
    """A new nonzero plain number keeps the fingerprint; the walk (numbers, lifted masses and
    fields) is the item-by-item walk's, whose order p follows."""
    from constrained.model.structure import structure_fingerprint

    base, other = _chain_of_items(), _changed(_SAME_STRUCTURE[change])
    assert structure_fingerprint(other) == structure_fingerprint(base)
    for system in (base, other):
        walked: list = []
        _, values = structure_reference.structure_data(system, walked)
        _, fast_values, fast_walk = lifting.fingerprint_walk(system)
        assert fast_values == values and np.array_equal(lifting.numbers(system), values)
        assert fast_walk[0] == walked[0] and fast_walk[1] == walked[1] and list(fast_walk[2]) == walked[2]
        assert [type(v) for fields in fast_walk[1] for v in fields.values()] == [
            type(v) for fields in walked[1] for v in fields.values()]


class _PointDefault(C.Distance):
    """A rod whose ``point`` is the class's (never in the instance's dict)."""

    point = None

    def __init__(self, a, b, length):
        self.a, self.b, self.length, self.name, self.where = a, b, length, None, None


class _LengthProperty(C.Distance):
    """A rod whose ``length`` is a data descriptor (its copy cannot be made from its dict)."""

    length = property(lambda self: self.__dict__["_length"], lambda self, v: self.__dict__.update(_length=v))


def test_lifting_by_columns_copies_what_lifting_item_by_item_copies():
    """``lift`` with the fingerprint walk's columns (fields left as they are, runs cut where the
    walk describes item by item, classes whose copy is not their dict) gives the copy that
    ``lift`` without the walk gives: the same attributes, in the same order, of the same types."""
    s = C.System(name="columns")
    for i in range(7):
        s.add_particle(f"p{i}", [1.0, 2, 0.5][i % 3], [0.1 * i, 0.02 * (i % 2), 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=0.1), *(C.Distance(f"p{i}", f"p{i + 1}", length=0.1 + i)
                                                          for i in range(3)))
    s.add(C.Distance("p3", point=[0.3, 0.0, 0.0], length=2), C.Distance("p3", "p4", length=1))
    s.add(*(_PointDefault(f"p{i}", f"p{i + 1}", 0.5) for i in range(4, 6)),
          _LengthProperty("p0", "p6", length=3.0))
    s.add(*(C.Spring(f"p{i}", f"p{i + 2}", k=10.0 * i, rest=[0.0, 0.2][i % 2]) for i in range(5)),
          C.Gravity([0, -9.81, 0]))
    _, values, walked = lifting.fingerprint_walk(s)
    reused, numbers = lifting.lift(s, walked)
    anew, reference = lifting.lift(s)
    assert np.array_equal(numbers, reference) and numbers.tolist() == values
    for ours, theirs in zip((*reused.particles, *reused.constraints, *reused.effects),
                            (*anew.particles, *anew.constraints, *anew.effects), strict=True):
        assert type(ours) is type(theirs) and list(vars(ours).items()) == list(vars(theirs).items())
        assert [type(v) for v in vars(ours).values()] == [type(v) for v in vars(theirs).values()]
    assert "point" in vars(reused.constraints[6])
    assert reused.constraints[8].length == anew.constraints[8].length


def test_columns_described_at_once_tell_apart_what_their_json_tells_apart():
    """A column of strings, of one bool or None repeated, of floats is described in one pass;
    two columns get one description exactly when their JSON (``plain_data``) is the same: NUL
    inside a name, -0.0 against 0.0, an int among floats, how many times a value repeats."""
    import json

    columns = [["a", "b"], ["a\0b"], ["a\0", "b"], ["a", "\0b"], ["a", "b", ""], [""], ["null"], [None],
               [None, None], [True, True], [True, 1], [False, True], [0.0, 0.5], [-0.0, 0.5], [0, 0.5],
               [0.5], [float("inf")], [float("nan")], [], [[1.0, 2.0]], [(1.0, 2.0)], [{"x": 1.0}]]
    described = [lifting._column_text("column", list(c)) for c in columns]
    reference = [json.dumps(lifting.plain_data(c)) if "nan" not in repr(c) else repr(c) for c in columns]
    for i, j in itertools.combinations(range(len(columns)), 2):
        assert (described[i] == described[j]) == (reference[i] == reference[j]), (columns[i], columns[j])
    assert described[1][0] == "column" and described[0][0] == "column 2 strings"  # (NUL: the JSON)
    assert lifting._column_text("c", [0.5, 0.25]) == lifting._column_text("c", [0.5, 0.25])
