"""Fast paths of the scene's validation for the shapes a large scene is made of: particles of
plain numbers, rods between two particles, lists of particle names. Each takes a whole
section at once (NumPy over its numbers, C-level passes over its values) and returns None
where any value needs the checks one by one (constrained.scene.build), which then give the
same message as without the fast path: the fast paths accept exactly what those checks
accept, and build the same objects."""

from __future__ import annotations

import itertools
import operator
from itertools import repeat

import numpy as np

from ..errors import InputError
from ..model import expressions
from ..model.constraints import Distance
from ..model.effects import Spring
from ..model.system import Particle

_PARTICLE_KEYS = frozenset(("name", "mass", "position", "velocity"))
_NUMBERS = frozenset((float, int))
_ABSENT = object()
_LIMIT = expressions.MAX_MAGNITUDE


def _vectors(values: list) -> np.ndarray | None:
    """(n, 3) floats of n lists of 3 plain finite numbers (no bool, no string), else None."""
    if set(map(type, values)) != {list} or set(map(len, values)) != {3}:
        return None
    if not _NUMBERS.issuperset(map(type, itertools.chain.from_iterable(values))):
        return None
    try:
        out = np.array(values, float)
    except OverflowError:  # an int beyond a float's range: the checks one by one say so
        return None
    return out if np.isfinite(out).all() else None


def plain_particles(items: list) -> list[Particle] | None:
    """The particles of ``[[particles]]`` tables each of a plain identifier ``name`` (all
    different), a plain number ``mass`` (at least 1/MAX_MAGNITUDE) and lists of 3 plain numbers
    ``position`` and (optional) ``velocity``; None when one is anything else."""
    n = len(items)
    if not n or set(map(type, items)) != {dict}:
        return None
    if not _PARTICLE_KEYS.issuperset(itertools.chain.from_iterable(items)):  # (a dict yields its keys)
        return None
    try:
        names = [item["name"] for item in items]
        masses = [item["mass"] for item in items]
        positions = [item["position"] for item in items]
    except KeyError:
        return None
    if set(map(type, names)) != {str} or not all(map(str.isidentifier, names)) or len(set(names)) != n:
        return None
    if not _NUMBERS.issuperset(map(type, masses)):
        return None
    try:
        mass = np.array(masses, float)
    except OverflowError:
        return None
    if not (np.isfinite(mass).all() and (mass >= 1 / expressions.MAX_MAGNITUDE).all()):
        return None
    position = _vectors(positions)
    if position is None:
        return None
    given = [item.get("velocity", _ABSENT) for item in items]
    velocity = np.zeros((n, 3))
    moving = [k for k, v in enumerate(given) if v is not _ABSENT]
    if moving:
        values = _vectors([given[k] for k in moving])
        if values is None:
            return None
        velocity[moving] = values
    return [Particle.plain(name, m, x, v, f"particles[{k}]") for k, (name, m, x, v)
            in enumerate(zip(names, mass.tolist(), position, velocity, strict=True))]


#: Items between two particles whose other keys are plain numbers: (section, type) -> the
#: numeric keys (required, optional), as constrained.scene.keys lists them.
_PAIR_ITEMS = {("constraints", "distance"): (("length",), ()), ("effects", "spring"): (("k",), ("rest",))}


def plain_pairs(items: list, section: str, names: frozenset, types: dict) -> list:
    """``plain_pair`` of every table of ``items`` (its objects, None where ``item`` is to check the
    table), each kind of item checked all at once: a kind whose tables are all plain (a large
    scene's rods, springs) is built without a check per table; one that is not, table by table."""
    out: list = [None] * len(items)
    if set(map(type, items)) != {dict}:
        return [plain_pair(item, i, section, names, types) for i, item in enumerate(items)]
    kinds = list(map(dict.get, items, repeat("type")))
    for (where, typ), (required, optional) in _PAIR_ITEMS.items():
        if where != section or typ not in types:
            continue
        index = [i for i, kind in enumerate(kinds) if type(kind) is str and kind == typ]
        # the tables with a 'b' all at once; one to a point (a rope's first rod) is not plain
        ends = [i for i in index if "b" in items[i]]
        pairs = [items[i] for i in ends]
        built = _all_plain(pairs, typ, required, optional, names, types[typ], section, ends)
        if built is None:  # some are not plain: which, table by table
            built = [plain_pair(item, i, section, names, types) for i, item in zip(ends, pairs, strict=True)]
        for i, obj in zip(ends, built, strict=True):
            out[i] = obj
    return out


def _all_plain(pairs: list, typ: str, required: tuple, optional: tuple, names: frozenset, cls, section: str,
               index: list) -> list | None:
    """The objects of the tables ``pairs`` of type ``typ`` (at ``index`` in ``section``) when
    every one is plain (what ``plain_pair`` accepts), else None: the checks as passes in C over
    the whole list."""
    if not pairs:
        return []
    keys = frozenset(("type", "a", "b", *required, *optional))
    if not all(map(keys.issuperset, pairs)) or not all(all(map(dict.__contains__, pairs, repeat(k)))
                                                       for k in required):
        return None
    a, b = (list(map(dict.get, pairs, repeat(end))) for end in ("a", "b"))
    if set(map(type, a)) != {str} or set(map(type, b)) != {str} or any(map(operator.eq, a, b)) \
            or not names.issuperset(a) or not names.issuperset(b):
        return None
    numbers = {}
    for k in (*required, *optional):
        values = [v for v in map(dict.get, pairs, repeat(k), repeat(_ABSENT)) if v is not _ABSENT] \
            if k in optional else list(map(dict.get, pairs, repeat(k)))
        if not _NUMBERS.issuperset(map(type, values)) or not all(map(_LIMIT.__ge__, map(abs, values))):
            return None  # (NaN fails the comparison)
        numbers[k] = values
    where = [f"{section}[{i}]" for i in index]
    if typ == "distance" and cls is Distance:  # (a rod: its one check here)
        if min(numbers["length"]) <= 0:
            return None
        return _rods(a, b, list(map(float, numbers["length"])), where)
    if typ == "spring" and cls is Spring:  # (Spring's __init__ checks nothing more)
        rests = list(map(float, map(dict.get, pairs, repeat("rest"), repeat(0.0))))
        return _springs(a, b, list(map(float, numbers["k"])), rests, where)
    try:
        return [cls(end_a, end_b, **{k: float(item[k]) for k in item if k not in ("type", "a", "b")},
                    name=None, where=w) for end_a, end_b, item, w in zip(a, b, pairs, where, strict=True)]
    except InputError:
        return None


def _rods(a: list, b: list, lengths: list, where: list) -> list[Distance]:
    """``Distance.between`` of each ``a, b, length, where`` (the same attributes in the same order),
    each rod's dict made at once (a scene's 20,000 rods: 6 ms instead of 16)."""
    new = Distance.__new__

    def rod(a, b, length, where):
        item = new(Distance)
        item.__dict__ = {"a": a, "b": b, "point": None, "length": length, "name": None, "where": where,
                         "unilateral": False, "restitution": 0.0}
        return item

    return list(map(rod, a, b, lengths, where))


def _springs(a: list, b: list, ks: list, rests: list, where: list) -> list[Spring]:
    """``Spring.between`` of each ``a, b, k, rest, where``, each spring's dict made at once."""
    new = Spring.__new__

    def spring(a, b, k, rest, where):
        item = new(Spring)
        item.__dict__ = {"a": a, "b": b, "point": None, "k": k, "rest": rest, "name": None, "where": where}
        return item

    return list(map(spring, a, b, ks, rests, where))


def plain_pair(item, i: int, section: str, names: frozenset, types: dict):
    """The object of a ``[[constraints]]`` or ``[[effects]]`` table ``{type, a, b, NUMBERS}``
    (a rod, a spring between two different particles, no name, no one-sided keys) whose
    numbers are plain and finite, as ``SceneBuilder.item`` builds it; None for any other table
    or value (``item`` then checks it and says what is wrong)."""
    if type(item) is not dict:
        return None
    typ = item.get("type")
    fields = _PAIR_ITEMS.get((section, typ)) if type(typ) is str else None
    if fields is None or len(item) > 3 + len(fields[0]) + len(fields[1]):
        return None
    required, optional = fields
    a, b = item.get("a"), item.get("b")
    if type(a) is not str or type(b) is not str or a == b or a not in names or b not in names:
        return None
    args = {}
    for k in required:
        if k not in item:
            return None
    for k, v in item.items():
        if k in ("type", "a", "b"):
            continue
        if k not in required and k not in optional:
            return None
        if not ((type(v) is float or type(v) is int) and -_LIMIT <= v <= _LIMIT):  # (NaN fails)
            return None
        args[k] = float(v)
    if typ == "distance" and types[typ] is Distance:  # (a rod: its one check here)
        return Distance.between(a, b, args["length"], f"{section}[{i}]") if args["length"] > 0 else None
    try:
        return types[typ](a, b, **args, name=None, where=f"{section}[{i}]")
    except InputError:
        return None
