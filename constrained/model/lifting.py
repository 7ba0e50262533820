"""Plain numbers as hidden parameters: what lets a new mass or length reuse the Structure.

A scene's or a constructor's plain numbers (a particle's ``mass = 1.0``, a rod's
``length = 0.8``, a spring's ``k``, gravity's ``g`` entries, …) are not constants of the
CasADi expressions. Each nonzero number in a field an item declares numeric (its class's
``numbers``: ``Distance.numbers == ("point", "length")``) becomes an entry of the parameter
vector after the named parameters,

    p = [named parameters (System.parameters, in order); plain numbers (in walk order)],

so two systems that differ only in such numbers have the same Structure (the same
fingerprint, the same Functions, the same compiled step loops) and differ in p alone.
Zeros stay constants: they decide sparsity (a plane's normal [0, 0, 1], a pivot at the
origin) and sometimes the formula (a spring of rest length 0 is smooth at zero length).
Numbers written inside formula strings (``"0.5*k*x**2"``) are part of the formula, hence
of the structure.

The walk order is the same for every reader: particles' masses (numbers, not formulas) in
order, then each constraint and each effect in order, its declared fields in the order
declared, vector and mapping entries in order.
"""

from __future__ import annotations

import bisect
import collections
import copy
import copyreg
import hashlib
import itertools
import json
import math
import operator
from collections.abc import Mapping

import numpy as np


class Number:
    """A plain number of the scene in the Structure's build: the hidden parameter
    ``p[offset + index]`` (``offset`` the number of named parameters). Formats as a token
    that ``expressions.fill`` replaces by the value, so labels read as the scene wrote them."""

    __slots__ = ("index",)

    def __init__(self, index: int):
        self.index = index

    def __format__(self, spec: str) -> str:
        return f"⟦{self.index}⟧"

    __str__ = __repr__ = lambda self: format(self)

    def __eq__(self, other) -> bool:
        return isinstance(other, Number) and other.index == self.index

    def __hash__(self) -> int:
        return hash(("Number", self.index))


def _is_number(value) -> bool:
    kind = type(value)
    if kind is float or kind is int:  # the common case, without the ABC check of np.number
        return value != 0 and math.isfinite(value)
    if value is None or kind is str:
        return False
    return (not isinstance(value, bool) and isinstance(value, int | float | np.number)
            and math.isfinite(value) and value != 0)


def _entries(value, out: list | None):
    """``value`` with each nonzero plain number replaced by a Number (appending its value
    to ``out``), or, when ``out`` is None, only the values (list of floats, in order)."""
    if type(value) is float and value != 0 and math.isfinite(value):
        out.append(value)
        return Number(len(out) - 1)
    if value is None or type(value) is str:  # (before the ABC checks below: a spring's point)
        return value
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, list | tuple):
        return [_entries(v, out) for v in value]
    if isinstance(value, Mapping):
        return {k: _entries(v, out) for k, v in value.items()}
    if _is_number(value):
        out.append(float(value))
        return Number(len(out) - 1)
    return value


def fields(item) -> tuple[str, ...]:
    """The fields of a constraint or an effect whose plain numbers are hidden parameters."""
    return getattr(type(item), "numbers", ())


def lifted_mass(particle, values: list):
    """The particle's mass as the Structure reads it: a Number (its value appended to
    ``values``), or as it is when a formula gives it. The one walk rule for masses."""
    return particle.mass if "mass" in particle.formulas else _entries(particle.mass, values)


def lifted_fields(item, values: list) -> dict:
    """``{field: value}`` of the item's numeric fields, in declared order, their nonzero plain
    numbers as Numbers (appended to ``values``). The one walk rule for items."""
    return {name: _entries(getattr(item, name), values) for name in fields(item)}


def _plain_copier(cls) -> bool:
    """Whether ``copy.copy`` of an instance of ``cls`` is a new instance with its ``__dict__``
    copied (no copy or pickle hooks, no slots): then ``_shallow`` does that directly."""
    plain = _PLAIN_COPY.get(cls)
    if plain is None:
        plain = _PLAIN_COPY[cls] = (
            cls.__reduce_ex__ is object.__reduce_ex__ and cls.__reduce__ is object.__reduce__
            and cls.__getstate__ is object.__getstate__ and cls.__new__ is object.__new__
            and not any(hasattr(cls, name) for name in ("__copy__", "__setstate__", "__getnewargs__",
                                                        "__getnewargs_ex__", "__slots__"))
            and cls not in copyreg.dispatch_table and "__dict__" in dir(cls))
    return plain


_PLAIN_COPY: dict = {}


def _shallow(obj):
    """``copy.copy(obj)``, a few times faster for a plain object (10,000 particles)."""
    cls = type(obj)
    if not _plain_copier(cls):
        return copy.copy(obj)
    new = object.__new__(cls)
    new.__dict__.update(obj.__dict__)
    return new


def _with_fields(item, changed: dict):
    """A shallow copy of ``item`` with the attributes ``changed`` set (``setattr`` one by one):
    for a plain class, whose setting is storing in ``__dict__``, the copy's dict made at once."""
    special = _set_specially(type(item))
    if special is not None and special.isdisjoint(changed):
        new = object.__new__(type(item))
        attributes = new.__dict__
        attributes.update(item.__dict__)
        attributes.update(changed)
        return new
    new = _shallow(item)
    for name, value in changed.items():
        setattr(new, name, value)
    return new


def _set_specially(cls) -> set | None:
    """The attribute names that ``setattr`` on an instance of ``cls`` does not store in its
    ``__dict__`` (data descriptors); None when ``cls`` is not plain (its own copy or setattr)."""
    if cls not in _SET_SPECIALLY:
        plain = _plain_copier(cls) and cls.__setattr__ is object.__setattr__
        _SET_SPECIALLY[cls] = None if not plain else {
            k for c in cls.__mro__ for k, v in vars(c).items() if hasattr(type(v), "__set__")}
    return _SET_SPECIALLY[cls]


_SET_SPECIALLY: dict = {}


def _copies(run: list, names, changes: list | None, columns: list | None = None) -> list | None:
    """``[_with_fields(item, changed) for item, changed in zip(run, changes)]`` for items of one
    class, each changed in the attributes ``names``: for a plain class, in passes over the
    whole run (a large system's particles or rods). ``columns`` instead: a list of new values
    per name (None: unchanged), and None back for a class that is not plain."""
    cls = type(run[0])
    special = _set_specially(cls)
    if special is None or not special.isdisjoint(names):
        if changes is None:
            return None
        return list(map(_with_fields, run, changes))
    attributes = list(map(dict, map(vars, run)))
    if changes is not None:
        _consume(map(dict.update, attributes, changes))
    else:  # (a column None: the items' own values, left as they are)
        for name, column in zip(names, columns, strict=True):
            if column is not None:
                _consume(map(dict.__setitem__, attributes, itertools.repeat(name), column))
    copies = list(map(object.__new__, itertools.repeat(cls, len(run))))
    _consume(map(setattr, copies, itertools.repeat("__dict__"), attributes))
    return copies


def _consume(calls) -> None:
    """Run the calls of the iterator ``calls`` (a ``map`` of methods returning None)."""
    collections.deque(calls, maxlen=0)


class Changes:
    """Each item's lifted fields (``{field: value}``), in walk order, held as segments: runs of
    items described column by column (their fields' values as one list per field) and lists of
    dicts. ``lift`` sets a run's columns in passes, without a dict per item."""

    def __init__(self, dicts: list = ()):
        self._starts: list[int] = [0]
        self._segments: list[tuple] = []  # (names, columns, kept) or (None, dicts, ())
        self.add_columns(None, list(dicts), len(dicts))  # (items described one by one: their dicts)

    def add_columns(self, names: tuple | None, columns: list, n: int, kept: tuple = ()) -> Changes:
        """Append ``n`` items whose field ``names[f]`` holds ``columns[f][k]`` (names None: their
        dicts, ``columns``); ``kept``: the fields whose values are the items' own (left by ``lift``)."""
        if n:
            self._segments.append((names if names is None else tuple(names), columns, frozenset(kept)))
            self._starts.append(self._starts[-1] + n)
        return self

    def __len__(self) -> int:
        return self._starts[-1]

    def __iter__(self):
        return iter(self.dicts(0, len(self)))

    def __eq__(self, other) -> bool:  # (a walk item by item, tests/structure_reference.py)
        return list(self) == list(other) if isinstance(other, Changes | list | tuple) else NotImplemented

    def dicts(self, a: int, b: int) -> list[dict]:
        """The fields of items a to b (excluded), a dict each."""
        out: list[dict] = []
        k = bisect.bisect_right(self._starts, a) - 1
        while a < b:
            start, stop = self._starts[k], self._starts[k + 1]
            names, held, _ = self._segments[k]
            lo, hi = a - start, min(b, stop) - start
            if names is None:
                out += held[lo:hi]
            else:
                rows = zip(*(column[lo:hi] for column in held), strict=True) if names else ((),) * (hi - lo)
                out += map(dict, map(zip, itertools.repeat(names), rows))
            a, k = min(b, stop), k + 1
        return out

    def breaks(self, a: int, b: int) -> list[int]:
        """The starts of segments strictly between a and b."""
        return self._starts[bisect.bisect_right(self._starts, a):bisect.bisect_left(self._starts, b)]

    def columns(self, a: int, b: int, names: tuple) -> list | None:
        """The columns of items a to b (excluded) when they lie in one segment described column
        by column with the fields ``names`` (None for a field whose values are the items' own),
        else None."""
        if a >= b:
            return None
        k = bisect.bisect_right(self._starts, a) - 1
        start, stop = self._starts[k], self._starts[k + 1]
        held_names, held, kept = self._segments[k]
        if b > stop or held_names != tuple(names):
            return None
        whole = a == start and b == stop
        return [None if name in kept else column if whole else column[a - start:b - start]
                for name, column in zip(names, held, strict=True)]


def lift(system, walked: tuple | None = None) -> tuple[object, np.ndarray]:
    """``(lifted, values)``: a shallow copy of ``system`` whose particles' numeric masses and
    items' numeric fields hold Numbers instead of their nonzero numbers, and those numbers
    in order. Only the Structure's build reads the lifted copy (its particles have no state).
    ``walked``: ``fingerprint_walk``'s walk of this system (its lifted masses, each item's lifted
    fields, the values), used instead of walking it again."""
    values: list[float] = []
    lifted = copy.copy(system)
    particles, constraints, effects = list(system.particles), list(system.constraints), list(system.effects)
    if walked is None:
        walked = ([lifted_mass(p, values) for p in particles],
                  [lifted_fields(item, values) for item in (*constraints, *effects)], values)
    masses, changes = walked[0], walked[1] if isinstance(walked[1], Changes) else Changes(walked[1])
    by_mass = Changes().add_columns(("mass",), [masses], len(masses))
    lifted.particles = _lifted_copies(particles, by_mass, 0, lambda p: ("mass",))
    lifted.constraints = _lifted_copies(constraints, changes, 0, fields)
    lifted.effects = _lifted_copies(effects, changes, len(constraints), fields)
    return lifted, np.array(walked[2], float)


def _lifted_copies(sequence: list, changes: Changes, offset: int, names_of) -> list:
    """``sequence`` with each item whose class has numeric fields (``names_of(item)``) replaced by
    its copy with the attributes of ``changes`` at ``offset + k`` (each item's fields) set: runs
    of one class at once (``_copies``)."""
    if not sequence:
        return []
    kinds = list(map(type, sequence))
    changed = itertools.compress(range(1, len(kinds)), map(operator.is_not, kinds[1:], kinds[:-1]))
    segments = (k - offset for k in changes.breaks(offset, offset + len(kinds)))
    bounds = sorted({0, *changed, *segments, len(kinds)})
    out = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):  # (runs of one class in one segment)
        names = names_of(sequence[a])
        if not names:
            out += sequence[a:b]
            continue
        columns = changes.columns(offset + a, offset + b, names)
        copies = _copies(sequence[a:b], names, None, columns) if columns is not None else None
        out += copies if copies is not None else _copies(sequence[a:b], names,
                                                         changes.dicts(offset + a, offset + b))
    return out


def numbers(system) -> np.ndarray:
    """The values ``lift`` takes out of ``system``, in the same order, without copying."""
    values: list[float] = []
    for p in system.particles:
        lifted_mass(p, values)
    for item in (*system.constraints, *system.effects):
        lifted_fields(item, values)
    return np.array(values, float)


def fingerprint_walk(system) -> tuple[str, list[float], tuple]:
    """``(digest, values, walked)``: the sha256 hex digest of everything a Structure is built
    from (particle names and masses — Numbers, or their formulas —, each constraint and effect —
    its class and every attribute —, the parameter names in order and the definitions; equal
    digests for equal data; tests/structure_reference.py holds the same description item by
    item), the plain numbers ``numbers(system)`` gives and the walk
    for ``lift``, without a JSON object per item: a run of items of one class and one set of
    attributes whose numeric fields all hold scalars (a chain's rods, a cloth's springs) is
    described column by column (which of its numeric entries are Numbers as a mask, the rest
    and every other attribute as one JSON list each). NotPlain (or TypeError, ValueError) when
    an item holds a value that cannot be described exactly."""
    digest = hashlib.sha256()

    def add(tag: str, text: str | bytes) -> None:  # (tagged and length-framed: no two readings)
        data = text.encode() if isinstance(text, str) else text
        digest.update(f"{tag}:{len(data)}:".encode())
        digest.update(data)

    values: list[float] = []
    particles = system.particles
    masses = [p.mass for p in particles]
    if set(map(type, masses)) == {float} and not any("mass" in p.formulas for p in particles) \
            and np.all(np.isfinite(masses)) and np.all(np.asarray(masses) != 0):
        values += masses
        lifted_masses = [Number(k) for k in range(len(particles))]
    else:
        lifted_masses = [lifted_mass(p, values) for p in particles]
    if all(type(m) is Number for m in lifted_masses):  # (their indices: 0, 1, …, in order)
        add(*_column_text("named masses", [p.name for p in particles]))
    else:
        described = [[p.name, ["formula", p.formulas["mass"]] if "mass" in p.formulas else plain_data(m)]
                     for p, m in zip(particles, lifted_masses, strict=True)]
        add("masses", json.dumps(described))
    items = (*system.constraints, *system.effects)
    item_fields = Changes()
    attributes = list(map(vars, items))
    for k, j in _runs(items, attributes):
        cls, keys = type(items[k]), tuple(attributes[k])
        names = fields(items[k])
        other = tuple(key for key in keys if key not in names)
        add("run", json.dumps([cls.__module__, cls.__qualname__, list(names), list(other)]))
        _described_run(items[k:j], attributes[k:j], names, other, values, item_fields, add)
    add("parameters", json.dumps([list(system.parameters), plain_data(system.definitions)]))
    walked = (lifted_masses, item_fields, values)
    return digest.hexdigest(), values, walked


#: Types of the values of a numeric field that a run's columns describe (the rest: item by item).
_SCALARS = frozenset((float, int, str, type(None)))
_FLOAT, _INT_FLOAT = frozenset((float,)), frozenset((float, int))


def _runs(items: tuple, attributes: list) -> list[tuple[int, int]]:
    """``[(start, stop), ...]``: the runs of consecutive items of one class and one tuple of
    attribute names (``attributes``: each item's ``vars``), in order."""
    n = len(items)
    if n < 2:
        return [(0, n)] if n else []
    kinds, keys = list(map(type, items)), list(map(tuple, attributes))
    breaks = itertools.compress(range(1, n), map(operator.or_, map(operator.is_not, kinds[1:], kinds[:-1]),
                                                 map(operator.ne, keys[1:], keys[:-1])))
    bounds = [0, *breaks, n]
    return list(zip(bounds[:-1], bounds[1:], strict=True))


def _stored(cls, name: str, attributes: dict) -> bool:
    """Whether ``getattr`` of an instance of ``cls`` whose ``vars`` are ``attributes`` gives
    ``attributes[name]`` (no data descriptor of the class, no ``__getattribute__`` of its own)."""
    descriptor = type(getattr(cls, name, None))
    return name in attributes and cls.__getattribute__ is object.__getattribute__ \
        and not (hasattr(descriptor, "__set__") or hasattr(descriptor, "__delete__"))


def _described_run(run: tuple, attributes: list, names: tuple, other: tuple, values: list,
                   item_fields: Changes, add) -> None:
    """Describe a run of items of one class and attributes (``add``; ``attributes``: their
    ``vars``), append its lifted fields to ``item_fields`` and its plain numbers to ``values``
    (in walk order: item by item, each item's numeric fields in declared order). Items whose
    numeric fields hold scalars alone are described column by column, the others (a list, a
    mapping …) item by item."""
    n = len(run)
    stored = [_stored(type(run[0]), name, attributes[0]) for name in names]
    columns = [list(map(operator.itemgetter(name), attributes)) if held
               else [getattr(item, name) for item in run] for name, held in zip(names, stored, strict=True)]
    kinds = [set(map(type, column)) for column in columns]
    scalar = np.ones(n, bool)
    for column, column_kinds in zip(columns, kinds, strict=True):
        if not _SCALARS.issuperset(column_kinds):
            scalar &= np.fromiter((type(v) in _SCALARS for v in column), bool, n)
    bounds = [0, *(np.flatnonzero(np.diff(scalar)) + 1).tolist(), n]
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if not scalar[a]:  # (a rod to a point in a chain of rods between particles)
            lifted = [{name: _entries(getattr(item, name), values) for name in names} for item in run[a:b]]
            item_fields.add_columns(None, lifted, len(lifted))
            add("items", json.dumps([[_plain_value(v) for v in fields.values()] for fields in lifted]))
            continue
        lifted_at = np.zeros((b - a, len(names)), bool)  # which entries are Numbers (_entries' rule)
        numbers = np.zeros((b - a, len(names)))
        segment = [column[a:b] for column in columns]
        for f, column in enumerate(segment):
            column_kinds = kinds[f] if b - a == n else set(map(type, column))
            if column_kinds == _FLOAT:
                numbers[:, f] = column
            elif not column_kinds.isdisjoint(_INT_FLOAT):  # (else no number, all 0: a spring's point None)
                numbers[:, f] = [v if type(v) is float or type(v) is int else 0.0 for v in column]
            lifted_at[:, f] = (numbers[:, f] != 0) & np.isfinite(numbers[:, f])
        index = np.cumsum(lifted_at.ravel()).reshape(lifted_at.shape) - 1 + len(values)
        values += numbers[lifted_at].tolist()
        lifted_columns, kept = [], []
        for f, column in enumerate(segment):
            at = lifted_at[:, f]
            add("numbers at", at.tobytes())
            add(*_column_text("numbers left", list(itertools.compress(column, ~at))))
            if at.all():
                lifted_columns.append(list(map(Number, index[:, f].tolist())))
                continue
            if not at.any() and stored[f]:  # (no Number: the values in the items' dicts)
                lifted_columns.append(column)
                kept.append(names[f])
                continue
            lifted = list(column)
            for i, number in zip(np.flatnonzero(at).tolist(), index[at, f].tolist(), strict=True):
                lifted[i] = Number(number)
            lifted_columns.append(lifted)
        item_fields.add_columns(names, lifted_columns, b - a, tuple(kept))
    for key in other:
        add(*_column_text("column", list(map(operator.itemgetter(key), attributes))))


def _column_text(tag: str, column: list) -> tuple[str, str | bytes]:
    """``(tag, text)`` that describe ``column`` exactly (``plain_data`` of each value), the usual
    columns in one pass (strings joined by NUL, one bool or None n times, floats' bytes), else as
    JSON: the tag says which, and n (no two readings)."""
    n, kinds = len(column), set(map(type, column))
    kind = type(column[0]) if len(kinds) == 1 and n else None
    if kind is str and (joined := "\0".join(column)).count("\0") == n - 1:  # (no NUL of their own)
        return f"{tag} {n} strings", joined
    if (kind is bool or kind is type(None)) and column.count(column[0]) == n:
        return f"{tag} {n} times", json.dumps(column[0])
    if kind is float:
        return f"{tag} {n} floats", np.array(column, float).tobytes()
    return tag, json.dumps(column if _ATOMS.issuperset(kinds) else [plain_data(v) for v in column])


def _plain_value(value):
    """``plain_data(value)``, the usual kinds first."""
    kind = type(value)
    if kind is str or kind is float or kind is int or kind is bool or value is None:
        return value
    return ["number", value.index] if kind is Number else plain_data(value)


class NotPlain(Exception):
    """A value structure_fingerprint cannot describe exactly."""


#: Types ``plain_data`` gives back as they are.
_ATOMS = frozenset((float, str, int, bool, type(None)))
_NUMBERED = _ATOMS | {Number}


def plain_data(value):
    """``value`` as JSON-able data that determines it exactly (floats by their repr)."""
    kind = type(value)
    if kind is float or kind is str or kind is int or value is None:
        return value
    if kind is list or kind is tuple:
        if _ATOMS.issuperset(map(type, value)):  # (what the loop below gives, at once)
            return list(value)
        return [plain_data(v) for v in value]
    if kind is dict:
        if _ATOMS.issuperset(map(type, value)):  # (plain keys; values plain or Numbers: at once)
            kinds = set(map(type, value.values()))
            if kinds <= _ATOMS:
                return ["mapping", [[k, v] for k, v in value.items()]]
            if kinds <= _NUMBERED:
                return ["mapping", [[k, ["number", v.index] if type(v) is Number else v]
                                    for k, v in value.items()]]
        return ["mapping", [[plain_data(k), plain_data(v)] for k, v in value.items()]]
    if kind is Number:
        return ["number", value.index]
    if isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return ["ndarray", value.dtype.str, list(value.shape), value.tolist()]
    if isinstance(value, list | tuple):
        return [plain_data(v) for v in value]
    if isinstance(value, Mapping):
        return ["mapping", [[plain_data(k), plain_data(v)] for k, v in value.items()]]
    raise NotPlain(type(value).__name__)
