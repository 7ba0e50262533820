"""The fast paths of a scene's validation (constrained.scene.plain) build exactly what the checks
one by one build, and leave every value they do not accept to those checks (the same message)."""

from __future__ import annotations

import copy
import datetime
import random

import numpy as np
import pytest

from constrained.model import expressions
from constrained.scene import build as scene_build
from constrained.scene import validate
from constrained.scene.load import MAX_NESTING, SceneError, build_scene, refuse_deep_nesting


def _raw(n: int = 5) -> dict:
    particles = [{"name": f"p{i}", "mass": 0.5 + i, "position": [1.0 + i, 0, -1.5 * i]} for i in range(n)]
    particles[1]["velocity"] = [0.0, 2, 0.25]
    constraints = [{"type": "distance", "a": "p0", "point": [0.0, 0.0, 0.0], "length": 1.0}]
    constraints += [{"type": "distance", "a": f"p{i}", "b": f"p{i + 1}", "length": 1 + 0.5 * i}
                    for i in range(n - 1)]
    constraints.append({"type": "plane", "particles": [f"p{i}" for i in range(n)], "normal": [0, 0, 1]})
    effects = [{"type": "gravity", "g": [0.0, -9.81, 0.0]},
               {"type": "spring", "a": "p0", "b": "p2", "k": 3, "rest": 0.5},
               {"type": "spring", "a": "p1", "b": "p3", "k": 2.5}]
    return {"particles": particles, "constraints": constraints, "effects": effects,
            "simulate": {"t_end": 1.0}}


def _slow(monkeypatch):
    monkeypatch.setattr(scene_build, "plain_particles", lambda items: None)
    monkeypatch.setattr(scene_build, "plain_pairs", lambda items, *args: [None] * len(items))


def _build(raw):
    try:
        return build_scene(copy.deepcopy(raw))
    except SceneError as exc:
        return str(exc)


def _described(scene) -> list:
    system = scene.system
    particles = [(p.name, type(p.mass), p.mass, p.position.tolist(), p.velocity.tolist(), p.where,
                  p.formulas, list(vars(p))) for p in system.particles]
    items = [(type(c).__name__, list(vars(c).items())) for c in (*system.constraints, *system.effects)]
    return [particles, items]


def test_the_fast_paths_build_what_the_checks_build(monkeypatch):
    raw = _raw()
    fast = _described(build_scene(copy.deepcopy(raw)))
    _slow(monkeypatch)
    assert fast == _described(build_scene(copy.deepcopy(raw)))


def _bad(raw, path, value):
    raw = copy.deepcopy(raw)
    *keys, last = path
    target = raw
    for k in keys:
        target = target[k]
    if value is KeyError:
        del target[last]
    else:
        target[last] = value
    return raw


@pytest.mark.parametrize("path, value", [
    (("particles", 2, "mass"), True),
    (("particles", 2, "mass"), 0),
    (("particles", 2, "mass"), -1.0),
    (("particles", 2, "mass"), 1e-101),
    (("particles", 2, "mass"), "m"),
    (("particles", 2, "mass"), KeyError),
    (("particles", 2, "name"), "p1"),
    (("particles", 2, "name"), "2p"),
    (("particles", 2, "name"), 7),
    (("particles", 2, "position"), [0.0, 1.0]),
    (("particles", 2, "position"), [0.0, True, 1.0]),
    (("particles", 2, "position"), [0.0, "1.0", 1.0]),
    (("particles", 2, "position"), (0.0, 1.0, 1.0)),
    (("particles", 2, "position"), [0.0, float("nan"), 1.0]),
    (("particles", 2, "velocity"), None),
    (("particles", 2, "velocity"), [0.0, 1.0, 2.0, 3.0]),
    (("particles", 2, "colour"), "red"),
    (("constraints", 2, "length"), 0.0),
    (("constraints", 2, "length"), -1),
    (("constraints", 2, "length"), float("inf")),
    (("constraints", 2, "length"), False),
    (("constraints", 2, "b"), "p1"),
    (("constraints", 2, "b"), "nobody"),
    (("constraints", 2, "b"), 3),
    (("constraints", 2, "name"), ""),
    (("constraints", 2, "point"), [0.0, 0.0, 0.0]),
    (("constraints", 2, "unilateral"), "yes"),
    (("constraints", 5, "particles"), ["p0", "p1", "p0"]),
    (("constraints", 5, "particles"), ["p0", "p9"]),
    (("constraints", 5, "particles"), ["p0", 1]),
    (("effects", 1, "k"), "k"),
    (("effects", 1, "k"), float("nan")),
    (("effects", 1, "b"), "p0"),
    (("effects", 1, "rest"), KeyError),
    (("effects", 2, "damping"), 1.0),
])
def test_what_the_fast_paths_leave_the_checks_say_as_before(monkeypatch, path, value):
    raw = _bad(_raw(), path, value)
    fast = _build(raw)
    _slow(monkeypatch)
    slow = _build(raw)
    assert (fast if isinstance(fast, str) else _described(fast)) == \
        (slow if isinstance(slow, str) else _described(slow))


def test_the_fast_paths_keep_the_structure_fingerprint(monkeypatch):
    from constrained.model.structure import structure_fingerprint

    fast = structure_fingerprint(build_scene(_raw()).system)
    _slow(monkeypatch)
    assert fast == structure_fingerprint(build_scene(_raw()).system)


def test_plain_particles_share_no_arrays():
    system = build_scene(_raw()).system
    system.particles[0].position[0] = 9.0
    assert system.particles[1].position[0] == 2.0 and np.all(system.particles[1].velocity == [0, 2, 0.25])


def test_a_scene_read_without_its_equations_draws_the_same_page(tmp_path, capsys):
    """``load_scene(path, equations=False)`` (``view`` and ``plot`` with --scene): the same
    System — particles, constraints, effects — without a Structure built or the start checked,
    and the viewer's page from it is the page from the fully loaded scene, byte for byte. A
    scene with a bad formula is read so (its formulas are not parsed: ``check`` and ``run``
    refuse it), while its layout is still checked."""
    from pathlib import Path

    from constrained.cli.main import main
    from constrained.model.structure import Structure
    from constrained.scene.load import load_scene

    root = Path(__file__).resolve().parents[1]
    path = root / "scenarios" / "four_bar_linkage.toml"
    out = tmp_path / "run"
    assert main(["run", str(path), "--out", str(out), "--quiet", "--set", "simulate.t_end=0.2"]) == 0
    built = Structure.builds
    light = load_scene(path, ["simulate.t_end=0.3"], equations=False)
    assert Structure.builds == built and light.structure is None and light.loaded_model() is None
    full = load_scene(path, ["simulate.t_end=0.3"])
    assert [p.name for p in light.system.particles] == [p.name for p in full.system.particles]
    np.testing.assert_array_equal(light.system.positions, full.system.positions)
    assert [c.label for c in light.system.constraints] == [c.label for c in full.system.constraints]
    assert [e.label for e in light.system.effects] == [e.label for e in full.system.effects]
    from constrained.output.viewer import view_command

    pages = [view_command(out, scene=scene, out=tmp_path / f"{name}.html")
             for name, scene in (("light", light), ("full", full))]
    assert pages[0].read_bytes() == pages[1].read_bytes()
    bad = tmp_path / "bad.toml"
    potential = '[[effects]]\ntype = "potential"\nexpr = "x_B +* 2"\n'
    bad.write_text(path.read_text().replace("[simulate]", potential + "[simulate]"))
    assert load_scene(bad, equations=False).system.n_particles == full.system.n_particles
    with pytest.raises(SceneError, match="cannot read formula"):
        load_scene(bad)
    bad.write_text(bad.read_text().replace('a = "B"', 'a = "Z"', 1))
    with pytest.raises(SceneError, match="names unknown particle 'Z'"):
        load_scene(bad, equations=False)


def _random_raw(rng: random.Random) -> dict:
    """A small scene of rods, springs and other items, some tables plain, some with a value the
    checks refuse or take by the slow path (a name, a point, an int, a formula, NaN, a bool...)."""
    n = rng.randint(1, 5)
    raw = _raw(n) if n > 1 else {"particles": [{"name": "p0", "mass": 2.0, "position": [0.0, 1, 2]}],
                                 "constraints": [], "effects": [], "simulate": {"t_end": 1.0}}
    names = [f"p{i}" for i in range(n)]
    odd = [0, 3, -1, 1e101, float("nan"), True, "2*l", None, [1.0], 7, 2.5e-3]
    for section, typ, number in (("constraints", "distance", "length"), ("effects", "spring", "k")):
        for _ in range(rng.randint(0, 6)):
            a, b = rng.sample(names, 2) if n > 1 else ("p0", "p0")
            item = {"type": typ, "a": a, "b": b, number: rng.choice([rng.uniform(0.1, 2), 1, 2])}
            if typ == "spring" and rng.random() < .5:
                item["rest"] = rng.choice([0.5, 1, 0])
            if rng.random() < .08:
                key = rng.choice([number, "a", "b", "rest", "name", "point", "unilateral", "type"])
                item[key] = rng.choice([*odd, rng.choice(names), "spring", "distance", [0.0, 0.0, 1.0]])
            raw[section].insert(rng.randint(0, len(raw[section])), item)
    raw["parameters"] = {"l": 1.5}
    return raw


def test_random_item_mixes_build_what_the_checks_build(monkeypatch):
    """plain_pairs, over sections of rods and springs among other items, some not plain: the
    same objects or the same first refusal as the checks one by one."""
    rng = random.Random(17)
    raws = [_random_raw(rng) for _ in range(150)]
    fast = [_build(raw) for raw in raws]
    _slow(monkeypatch)
    slow = [_build(raw) for raw in raws]
    assert sum(isinstance(f, str) for f in fast) > 20 and sum(not isinstance(f, str) for f in fast) > 20
    for f, s in zip(fast, slow, strict=True):
        assert (f if isinstance(f, str) else _described(f)) == (s if isinstance(s, str) else _described(s))


class _Table(dict):
    pass


def _random_nest(rng: random.Random, depth: int):
    r = rng.random()
    if depth > 0 and r < .35:
        return {f"k{i}": _random_nest(rng, depth - 1) for i in range(rng.randint(0, 3))}
    if depth > 0 and r < .55:
        return [_random_nest(rng, depth - 1) for _ in range(rng.randint(0, 3))]
    if depth > 0 and r < .58:
        return _Table(x=_random_nest(rng, depth - 1))
    return rng.choice([1.0, -3, "s", True, 1e100, -1e100, 1e101, 10**101, -(10**200), float("inf"),
                       float("nan"), np.float64(2.0), np.float64(1e300), None, (1e200,),
                       datetime.date(2000, 1, 1)])


def _moderate(value) -> bool:
    if isinstance(value, int | float) and not isinstance(value, bool):
        return abs(value) <= expressions.MAX_MAGNITUDE
    if isinstance(value, dict):
        return all(map(_moderate, value.values()))
    return all(map(_moderate, value)) if isinstance(value, list) else True


def _depth(value) -> int:
    inner = value.values() if isinstance(value, dict) else value if isinstance(value, list) else None
    return 0 if inner is None else 1 + max(map(_depth, inner), default=0)


def test_the_walks_over_a_scene_see_every_number_and_level():
    """validate._all_moderate (finite_everywhere's quick walk) and load.refuse_deep_nesting, one
    level at a time split by type, against recursive walks: numbers of every kind (bool is none,
    NumPy floats are), dict subclasses, nesting at MAX_NESTING and one beyond."""
    rng = random.Random(5)
    values = [_random_nest(rng, rng.randint(0, 6)) for _ in range(3000)]
    assert 0.2 < np.mean([_moderate(v) for v in values]) < 0.8
    for value in values:
        assert validate._all_moderate(value) == _moderate(value), value
    for depth in (1, 2, MAX_NESTING - 1, MAX_NESTING, MAX_NESTING + 1, 200):
        for leaf in ([], {}, 1.0, "x"):
            raw = leaf
            for k in range(depth - 1):
                raw = {"a": raw, "b": 0.5} if k % 3 == 0 else [0.5, raw] if k % 3 == 1 else _Table(b=raw)
            raw = {"a": raw}
            deep = _depth(raw) > MAX_NESTING
            try:
                refuse_deep_nesting(raw, "f.toml")
            except SceneError as exc:
                assert deep and "nested too deeply" in str(exc)
            else:
                assert not deep, depth


@pytest.mark.parametrize("section", ["particles", "constraints", "effects"])
def test_an_entry_that_is_not_a_table_is_named(section):
    """array_of_tables takes a list of dicts at once; any other entry is still named."""
    raw = _raw()
    raw[section].insert(2, [1.0])
    message = _build(raw)
    assert f"{section}[2]" in message and f"must be a table (one [[{section}]] entry), got a list [1.0]" \
        in message, message


def test_rods_and_springs_to_a_point_among_plain_ones_build_what_the_checks_build(monkeypatch):
    """A rod or spring to a fixed point (no 'b': built by the checks) among plain ones (built
    all at once, plain_pairs): the same objects in the same order, or the same first refusal,
    as the checks one by one; the plain ones still come from the fast path."""
    from constrained.scene import plain

    rng = random.Random(29)
    raws = []
    for _ in range(80):
        raw = _random_raw(rng)
        names = [p["name"] for p in raw["particles"]]
        for section, typ, number in (("constraints", "distance", "length"), ("effects", "spring", "k")):
            for _ in range(rng.randint(1, 2)):
                item = {"type": typ, "a": rng.choice(names), "point": [0.0, 0.1, 0.0],
                        number: rng.choice([0.5, 2])}
                if rng.random() < .05:  # (now and then one the checks refuse)
                    item[rng.choice(["point", number])] = rng.choice([[1, 2], -1.0])
                raw[section].insert(rng.randint(0, len(raw[section])), item)
        raws.append(raw)
    all_at_once = []
    original = plain._all_plain
    monkeypatch.setattr(plain, "_all_plain", lambda pairs, *args: all_at_once.append(
        result := original(pairs, *args)) or result)
    fast = [_build(raw) for raw in raws]
    assert sum(r is not None and len(r) > 0 for r in all_at_once) > 20
    monkeypatch.undo()
    _slow(monkeypatch)
    slow = [_build(raw) for raw in raws]
    assert sum(isinstance(f, str) for f in fast) > 10 and sum(not isinstance(f, str) for f in fast) > 10
    for f, s in zip(fast, slow, strict=True):
        assert (f if isinstance(f, str) else _described(f)) == (s if isinstance(s, str) else _described(s))
