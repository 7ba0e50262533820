"""The model side's passes over whole lists (a scene's springs built at once, the fingerprint's
runs and columns, ``lift``'s copies run by run, the ends and numbers of rods and springs
looked up at once) give exactly what the item-by-item code they replace gives, on systems
that mix what those passes take with what they leave to the item-by-item code."""

from __future__ import annotations

import copy

import casadi as ca
import numpy as np
import pytest
import structure_reference

import constrained as C
from constrained.errors import InputError
from constrained.model import lifting
from constrained.model.constraints import Distance, pair_ends
from constrained.model.effects import Spring
from constrained.model.symbols import Symbols, pair_formula
from constrained.scene import build as scene_build
from constrained.scene import plain as scene_plain
from constrained.scene.load import SceneError, build_scene


def _mixed_raw(n: int = 90, formula_k: bool = True) -> dict:
    """A rope to a point with rods between particles, some of formula lengths; springs written
    b→a and a→b, of integer rest and of none, one of a formula k (``formula_k``: then every
    spring is built by itself), one to a point, a damper among them; asymmetric masses."""
    particles = [{"name": f"q{i}", "mass": 0.01 * (1 + (i * 7) % 5), "position": [0.1 * (i + 1), 0.0, 0.0]}
                 for i in range(n)]
    rods = [{"type": "distance", "a": "q0", "point": [0.0, 0.0, 0.0], "length": 0.1}]
    rods += [{"type": "distance", "a": f"q{i}", "b": f"q{i + 1}", "length": "L" if i % 17 == 3 else 0.1}
             for i in range(n - 1)]
    springs = [{"type": "spring", "a": f"q{i + 2}", "b": f"q{i}", "k": 40.0 + i, "rest": 0.2}
               if i % 2 else {"type": "spring", "a": f"q{i}", "b": f"q{i + 2}", "k": 30, "rest": 0}
               for i in range(n - 2)]
    springs[11]["k"] = "2*k0" if formula_k else 17
    del springs[12]["rest"]
    springs[20] = {"type": "spring", "a": "q20", "point": [0.0, 1.0, 0.0], "k": 5.0}
    springs.insert(40, {"type": "damping", "coefficient": 0.3, "a": "q3", "b": "q9"})
    springs.append({"type": "gravity", "g": [0.0, -9.81, 0.0]})
    return {"parameters": {"L": 0.1, "k0": 20.0}, "particles": particles, "constraints": rods,
            "effects": springs, "simulate": {"t_end": 0.01}}


def _slow(monkeypatch):
    monkeypatch.setattr(scene_build, "plain_particles", lambda items: None)
    monkeypatch.setattr(scene_build, "plain_pairs", lambda items, *args: [None] * len(items))


def _described(system) -> list:
    return [[(type(c).__name__, list(vars(c).items())) for c in (*system.constraints, *system.effects)],
            [(p.name, p.mass, list(vars(p))) for p in system.particles]]


def _built(raw):
    try:
        return build_scene(copy.deepcopy(raw))
    except SceneError as exc:
        return str(exc)


@pytest.mark.parametrize("formula_k", [False, True])
def test_a_mixed_scene_builds_the_items_and_structure_of_the_checks(monkeypatch, formula_k):
    """Springs built at once (``scene.plain._springs``) are the objects ``Spring(...)`` makes (the same
    attributes in the same order); the Structure of the whole scene has the same labels and
    the same f and V, bit for bit, at a state nobody chose."""
    raw = _mixed_raw(formula_k=formula_k)
    between, original = [], scene_plain._springs
    monkeypatch.setattr(scene_plain, "_springs", lambda a, *args: between.extend(a) or original(a, *args))
    fast = build_scene(copy.deepcopy(raw))
    assert sum(type(e) is Spring for e in fast.system.effects) >= 80
    assert len(between) == (0 if formula_k else 87)  # (one spring of a formula: all built by themselves)
    _slow(monkeypatch)
    slow = build_scene(copy.deepcopy(raw))
    assert _described(fast.system) == _described(slow.system)
    models = [C.assemble(scene.system, reuse=False) for scene in (fast, slow)]
    rng = np.random.default_rng(3)
    x = rng.normal(size=3 * len(raw["particles"]))
    f = [np.asarray(m.structure.function("constraint")(x, 0.0, m.parameter_vector)) for m in models]
    V = [np.asarray(m.structure.function("potential")(x, 0.0, m.parameter_vector)) for m in models]
    assert np.array_equal(*f) and np.array_equal(*V)
    assert models[0].constraint_labels == models[1].constraint_labels


@pytest.mark.parametrize("section, at, key, value", [
    ("effects", 5_000, "k", True),
    ("effects", 5_000, "k", float("nan")),
    ("effects", 5_000, "b", "p5001"),
    ("effects", 5_000, "b", "nobody"),
    ("effects", 5_000, "rest", [1.0]),
    ("constraints", 5_000, "length", 0.0),
    ("constraints", 5_000, "length", "1 +"),
    ("constraints", 5_000, "b", 7),
])
def test_a_bad_item_among_ten_thousand_gets_the_message_of_the_checks(monkeypatch, section, at, key, value):
    """A bad value in the middle of 10,000 springs or rods: the message of the checks one by one,
    naming the item's index and key."""
    n = 10_001
    raw = {"particles": [{"name": f"p{i}", "mass": 1.0, "position": [float(i), 0.0, 0.0]} for i in range(n)],
           "constraints": [{"type": "distance", "a": f"p{i}", "b": f"p{i + 1}", "length": 1.0}
                           for i in range(n - 1)],
           "effects": [{"type": "spring", "a": f"p{i + 1}", "b": f"p{i}", "k": 2.0} for i in range(n - 1)],
           "simulate": {"t_end": 0.01}}
    raw[section][at][key] = value
    fast = _built(raw)
    _slow(monkeypatch)
    slow = _built(raw)
    assert isinstance(fast, str) and fast == slow and f"{section}[{at}]" in fast


def test_one_particle_builds_as_the_checks_build(monkeypatch):
    raw = {"particles": [{"name": "a", "mass": 2.0, "position": [1.0, 0.0, 0.0]}],
           "constraints": [{"type": "distance", "a": "a", "point": [0.0, 0.0, 0.0], "length": 1.0}],
           "effects": [{"type": "spring", "a": "a", "point": [0.0, 1.0, 0.0], "k": 3.0}],
           "simulate": {"t_end": 0.01}}
    fast = build_scene(copy.deepcopy(raw))
    _slow(monkeypatch)
    assert _described(fast.system) == _described(build_scene(copy.deepcopy(raw)).system)


def _pair_distances_one_by_one(items, s, fields):
    """``pair_ends`` and ``pair_formula``'s distances as they were: the items checked and looked
    up one by one."""
    index = s._index
    plain = [k for k, c in enumerate(items) if isinstance(c.a, str) and isinstance(c.b, str)
             and c.a in index and c.b in index and all(type(getattr(c, f)) is lifting.Number for f in fields)]
    if not plain:
        return plain, None
    X = ca.reshape(s.x, 3, s.x.numel() // 3)
    d = X[:, [index[items[k].a] for k in plain]] - X[:, [index[items[k].b] for k in plain]]
    squares = d * d
    return plain, ca.sqrt(squares[0, :] + squares[1, :] + squares[2, :])


class _Name(str):
    """A particle's name of a subclass of str (taken as ``isinstance`` takes it)."""


def test_pair_ends_at_once_are_the_ones_found_one_by_one():
    """Rods to points, rods of formula lengths, an end of a str subclass, an end naming no
    particle: the same items taken, the same ends and the same SX row."""
    system = C.System(parameters={"L": 1.0})
    for i in range(12):
        system.add_particle(f"p{i}", 1.0 + i, [float(i), 0.5 * i, 0.0])
    rods = [C.Distance(f"p{i}", f"p{i + 1}", length=1.0 + 0.1 * i) for i in range(11)]
    rods[2] = C.Distance("p2", point=[0.0, 0.0, 1.0], length=2.0)
    rods[5] = C.Distance("p5", "p6", length="L")
    rods[7] = C.Distance(_Name("p7"), "p8", length=1.5)
    rods[9].b = "ghost"
    system.add(*rods)
    lifted, numbers = lifting.lift(system)
    s = Symbols(lifted, symbolic_parameters=True, numbers=len(numbers))
    plain, ends = pair_ends(lifted.constraints, s, ("length",))
    distances = pair_formula(s, ends, [], lambda d: d.T)
    row = distances.column().T
    reference, reference_row = _pair_distances_one_by_one(lifted.constraints, s, ("length",))
    assert plain == reference == [0, 1, 3, 4, 6, 7, 8, 10]
    rods = lifted.constraints
    assert ends.tolist() == [[s._index[rods[k].a], s._index[rods[k].b]] for k in plain]
    assert str(row) == str(reference_row)
    for k in range(len(plain)):  # (one pair alone: its element of the row)
        assert ca.is_equal(distances[k], row[k], 10)
    none, no_ends = pair_ends(lifted.constraints[2:3], s, ("length",))
    assert none == [] and no_ends.shape == (0, 2)


def test_indices_and_number_entries_at_once_are_the_ones_one_by_one():
    system = C.System()
    for i in range(5):
        system.add_particle(f"p{i}", 1.0, [float(i), 0.0, 0.0])
    lifted, numbers = lifting.lift(system)
    s = Symbols(lifted, symbolic_parameters=True, numbers=len(numbers))
    names = ["p3", "p0", _Name("p4"), "p3"]
    assert s.indices(names, "here") == [s.index(n, "here") for n in names] == [3, 0, 4, 3]
    for bad in (["p1", "nobody"], ["p1", 2], ["p1", ["p2"]]):
        with pytest.raises(InputError) as ours:
            s.indices(bad, "constraints[3]")
        with pytest.raises(InputError) as theirs:
            [s.index(n, "constraints[3]") for n in bad]
        assert str(ours.value) == str(theirs.value)
    masses = [p.mass for p in lifted.particles]
    assert s.number_entries(masses).tolist() == [s._offset + m.index for m in masses]
    assert s.number_entries([*masses[:2], 0.5]) is None and s.number_entries([]).tolist() == []


class _Stored(Distance):
    """A rod whose length is a property (stored elsewhere) in a run of such rods."""

    numbers = ("point", "length")

    @property
    def length(self):
        return self._length

    @length.setter
    def length(self, value):
        self._length = value


class _Fixed(Spring):
    """A spring whose rest length is a class attribute, not one of its own."""

    numbers = ("k", "rest")
    rest = 0.25

    def __init__(self, a, b, k):
        self.a, self.b, self.point, self.k, self.name, self.where = a, b, None, k, None, None


def _lift_one_by_one(system):
    """``lift`` as it was: each particle and item copied by itself."""
    values: list = []
    lifted = copy.copy(system)
    particles = []
    for p in system.particles:
        q = lifting._shallow(p)
        q.mass = lifting.lifted_mass(p, values)
        particles.append(q)
    lifted.particles = particles
    out = []
    for item in (*system.constraints, *system.effects):
        changed = lifting.lifted_fields(item, values)
        out.append(lifting._with_fields(item, changed) if changed else item)
    return particles, out, values


def test_lifting_and_the_fingerprint_run_by_run_are_item_by_item():
    """Runs of rods whose length is a property, springs whose rest is a class attribute, plain
    rods and springs, a plane: ``lift``'s copies (classes, attributes in order) and numbers, and
    the fingerprint's walk, are the item-by-item ones."""
    system = C.System(parameters={"L": 1.0})
    for i in range(8):
        system.add_particle(f"p{i}", "2*L" if i == 4 else 0.5 + i, [float(i), 0.0, 0.1 * i])
    system.add(*[_Stored(f"p{i}", f"p{i + 1}", length=1.0 + i) for i in range(3)],
               *[C.Distance(f"p{i}", f"p{i + 1}", length=0.5) for i in range(3, 6)],
               C.Plane([f"p{i}" for i in range(8)], [0, 0, 1], 0.0),
               *[_Fixed(f"p{i + 1}", f"p{i}", k=2.0 + i) for i in range(4)],
               C.Spring("p0", "p7", k=1.0, rest="L"), C.Damping(0.2, ["p1"]))
    lifted, values = lifting.lift(system)
    particles, items, reference = _lift_one_by_one(system)
    assert values.tolist() == reference
    ours = [*lifted.particles, *lifted.constraints, *lifted.effects]
    for a, b in zip(ours, [*particles, *items], strict=True):
        assert type(a) is type(b) and list(vars(a).items()) == list(vars(b).items())
    assert isinstance(lifted.constraints[0].length, lifting.Number)
    assert "length" not in vars(lifted.constraints[0])
    assert isinstance(lifted.effects[0].rest, lifting.Number) and system.effects[0].rest == 0.25
    walked: list = []
    _, structure_values = structure_reference.structure_data(system, walked)
    _, fast_values, fast_walk = lifting.fingerprint_walk(system)
    assert fast_values == structure_values == reference
    assert fast_walk[0] == walked[0] and fast_walk[1] == walked[1]
    again, _ = lifting.lift(system, fast_walk)
    for a, b in zip([*again.particles, *again.constraints, *again.effects], ours, strict=True):
        assert type(a) is type(b) and list(vars(a).items()) == list(vars(b).items())


@pytest.mark.parametrize("line, value", [
    ("particles", "inf"), ("particles", "nan"), ("particles", "1e101"), ("particles", "-2e200"),
    ("constraints", "1e300"), ("simulate", "1e101"), ("expect", "1e300"), (None, None)])
def test_a_scene_file_walked_once_is_refused_as_the_builders_walk_refuses_it(tmp_path, line, value):
    """``load_scene``'s one walk over the file's values (nesting and numbers at once): a number
    that is not finite or too large is refused with the message the builder's own walk gives
    (``build_scene`` of the same data), naming its key; one in [expect] (which that walk does
    not see) is accepted as before."""
    from constrained import tomlparse
    from constrained.scene.load import load_scene

    text = {"particles": '[[particles]]\nname = "a"\nmass = 1.0\nposition = [1.0, 0.0, {v}]\n',
            "constraints": '[[constraints]]\ntype = "distance"\na = "a"\npoint = [0.0, 0.0, 0.0]\n'
                           'length = 1.0\nname = "rod"\nrestitution = {v}\n',
            "simulate": "[simulate]\nt_end = 0.01\natol = {v}\n",
            "expect": "[expect]\nenergy_drift = {v}\n"}
    source = "".join(part.format(v=value if key == line else "0.5" if key == "particles" else
                                 "0.0" if key == "constraints" else "1e-9" if key == "simulate" else "1.0")
                     for key, part in text.items())
    path = tmp_path / "scene.toml"
    path.write_text(source)
    try:
        loaded = load_scene(path).system.n_particles
    except SceneError as exc:
        loaded = str(exc)
    try:
        built = build_scene(tomlparse.loads(source), path=path).system.n_particles
    except SceneError as exc:
        built = str(exc)
    assert loaded == built
    assert isinstance(loaded, str) == (line not in (None, "expect"))


def _sketch_one_by_one(system) -> dict:
    """``sketch`` as it was written item by item (the reference of the passes)."""
    index = {p.name: k for k, p in enumerate(system.particles)}
    rods, anchors = [], []
    for c in system.constraints:
        kind = type(c).__name__
        a, b, point = getattr(c, "a", None), getattr(c, "b", None), getattr(c, "point", None)
        if kind not in ("Distance", "Pin") or a not in index:
            continue
        if b in index:
            rods.append([index[a], index[b]])
        elif point is not None and kind == "Distance":
            try:
                anchor = [float(v) for v in point]
            except (TypeError, ValueError):
                continue
            length = c.length
            if isinstance(length, str):
                length = system.parameter_values.get(length)
            anchors.append([index[a], anchor, float(length) if isinstance(length, int | float) else None])
    return {"rods": rods, "anchors": anchors}


def test_sketch_in_passes_is_the_sketch_item_by_item():
    """The rods and anchors an animation draws, found in passes over the constraints, are those
    found item by item: rods among pins, planes and rods to points (numbers, a parameter's
    length, a moving point left out), in order."""
    from constrained.model.system import sketch

    s = C.System(parameters={"L": 0.7}, name="sketch")
    for i in range(9):
        s.add_particle(f"p{i}", 1.0 + i, [0.3 * i, 0.1 * (i % 3), 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=0.1), *(C.Distance(f"p{i}", f"p{i + 1}", length=0.3)
                                                          for i in range(4)),
          C.Pin("p8", [2.4, 0.2, 0.0]), C.Distance("p5", point=[1.0, 0, 0], length="L"),
          C.Distance("p6", point=["cos(t)", 0, 0], length=0.5), C.Plane(["p7", "p8"], [0, 0, 1]),
          C.Distance("p8", "p2", length=0.9), C.Spring("p1", "p3", k=2.0))
    found = sketch(s)
    assert found == _sketch_one_by_one(s)
    assert found["rods"][-1] == [8, 2] and [a[0] for a in found["anchors"]] == [0, 5]
    bare = C.System([C.Particle("a", 1.0, [0, 0, 0])], [C.Pin("a", [0, 0, 0])])  # a pin alone: no rod
    assert sketch(bare) == _sketch_one_by_one(bare) == {"rods": [], "anchors": []}


def test_a_system_made_at_once_is_the_system_added_one_by_one():
    """``System(particles, constraints, effects)`` takes plain particles and the items in passes:
    the same lists, in order, as adding them one by one, and the same refusals (a duplicate
    name, an object that is no item), formulas still evaluated."""
    particles = [C.Particle(f"q{i}", 1.0 + i, [0.1 * i, 0, 0]) for i in range(5)]
    items = [C.Distance("q0", "q1", length=0.1), C.Gravity([0, 0, -9.81]), C.Pin("q2", [0.2, 0, 0]),
             C.Spring("q3", "q4", k=3.0), C.Plane(["q1"], [0, 0, 1])]
    at_once = C.System(particles, items[::2], items[1::2])
    one_by_one = C.System()
    for p in particles:
        one_by_one.add_particle(p)
    one_by_one.add(*items[::2], *items[1::2])
    assert at_once.particles == one_by_one.particles and at_once.particles is not particles
    assert at_once.constraints == one_by_one.constraints == [items[0], items[2], items[4]]
    assert at_once.effects == one_by_one.effects == [items[1], items[3]]
    at_once.add_particle("q5", 2.0, [1, 0, 0])
    with pytest.raises(InputError, match="duplicate particle name 'q5'"):
        at_once.add_particle("q5", 2.0, [1, 0, 0])
    with pytest.raises(InputError, match="duplicate particle name 'q1'"):
        C.System([*particles, C.Particle("q1", 1.0, [0, 0, 0])])
    with pytest.raises(InputError, match="expected a Constraint or an Effect, got 3"):
        C.System(particles, [items[0], 3])
    formula = C.System([C.Particle("r", "2*m", [0, 0, 0])], parameters={"m": 1.5})
    assert formula.particles[0].mass == 3.0


def test_short_rods_found_in_passes_are_those_found_one_by_one():
    """``unresolved_rods`` reads floats in one pass and any other length (an int, a formula) as
    before: the same rods found, with the same lengths."""
    from constrained.model.regularity import unresolved_rods

    s = C.System(name="short", parameters={"L": 1.0})
    for i in range(6):
        s.add_particle(f"p{i}", 1.0, [1e3 * i, 0, 0])
    s.add(C.Distance("p0", "p1", length=1e-11), C.Distance("p1", "p2", length=2),
          C.Distance("p2", "p3", length="L"), C.Distance("p3", point=[1e4, 0, 0], length=5e-10),
          C.Distance("p4", "p5", length=1e-30))
    found = [(i, length) for i, _, length, _ in unresolved_rods(s)]
    assert found == [(0, 1e-11), (3, 5e-10), (4, 1e-30)]
    s.constraints[1].length = 3e-300  # (an int among them before: now floats alone)
    assert [(i, length) for i, _, length, _ in unresolved_rods(s)] == [(0, 1e-11), (1, 3e-300), (3, 5e-10),
                                                                      (4, 1e-30)]
