"""The holonomic constraint library: each constraint yields rows of f(x, t) = 0 (the velocity
constraints, rows a(x, t)·v + b(x, t) = 0, are in model/velocity.py).

Every constraint is a small object with ``rows(symbols) -> list[(expr, label)]``. One
object may give several scalar rows (a pin gives three, a plane one per particle); each
row gets its own multiplier. Residuals are kept in metres where the geometry allows
(distance as |d| - L, planes with a unit normal), so multipliers are forces in newtons.
"""

from __future__ import annotations

import itertools
import math
import operator
from collections.abc import Mapping, Sequence

import casadi as ca
import numpy as np

from ..errors import InputError
from .lifting import Number
from .symbols import Batch, Formula, Stacked, pair_formula


def _fmt(value) -> str:
    if type(value) is Number or type(value) is float:  # (the usual cases, first)
        return f"{value:g}"
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    if isinstance(value, str):
        return value
    if isinstance(value, Sequence):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    return f"{value:g}"


def _as_list(value, where: str, what: str) -> list[str]:
    if isinstance(value, str):
        return [value]
    if not isinstance(value, Sequence) or not value or not all(isinstance(p, str) for p in value):
        raise InputError(f"{what} must be a particle name or a non-empty list of names", where=where)
    return list(value)


def _three(value, where: str, example: str):
    """``value`` when it is a 3-vector (numbers or formula strings), else an InputError at
    construction, not later in the run's build."""
    if value is None or (hasattr(value, "__len__") and not isinstance(value, str) and len(value) == 3):
        return value
    raise InputError(f"must be a vector of 3 entries (numbers or formulas of t), e.g. {example}; "
                     f"got {value!r}", where=where)


class Labelled:
    """A scene item with a readable ``label`` and a ``where`` (scene key) for messages."""

    kind = "item"
    name: str | None = None
    where: str | None = None

    @property
    def label(self) -> str:
        raise NotImplementedError

    def _where(self) -> str:
        return self.where or f"{self.kind} {self.label!r}"

    @classmethod
    def bare(cls, **attributes):
        """An instance holding ``attributes`` (in that order), ``__init__`` not called: the object
        ``__init__`` makes of values already checked (a large scene's items)."""
        item = cls.__new__(cls)
        item.__dict__.update(attributes)
        return item

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.label})"


class Constraint(Labelled):
    """Base class: ``rows(s)`` returns [(CasADi scalar f_k(x, t), label_k), ...].

    One-sided (``unilateral = True``): the constraint holds only one way, and each of its rows
    is switched on and off on its own (constrained.unilateral). ``side`` is the sign that turns
    a row into its gap, g = side · f ≥ 0: −1 for a distance (a string: |d| ≤ length), +1 for
    planes, surfaces and custom formulas (the particle stays where f ≥ 0). ``restitution`` is
    the coefficient e of the impact law when the gap closes (0: the motion along the
    constraint's normal stops; 1: an elastic bounce).
    """

    kind = "constraint"
    #: "position" (rows f(x, t) = 0), or "velocity" (rows a(x, t)·v + b = 0: model/velocity.py).
    level = "position"
    side = 1
    unilateral = False
    restitution = 0.0
    #: Why a type cannot be one-sided (None: it can).
    two_sided_only: str | None = None
    #: Fields whose plain numbers are inputs of the Structure's Functions (constrained.lifting).
    numbers: tuple[str, ...] = ()

    def rows(self, s) -> list[tuple]:
        raise NotImplementedError

    @classmethod
    def batch_rows(cls, items: list, s) -> tuple[list[int], Formula, list[str], Batch | None] | None:
        """The rows of ``items`` (items of this class) that have one row each of one formula,
        built together in a few CasADi calls: ``(plain, column, labels, batch)`` — their
        positions in ``items``, their rows as one column (a Formula: each the expression its
        ``rows`` builds, made into SX nodes when asked for), their labels, and the Batch of
        them (its ``items`` index ``items``; None when their numbers are not all lifted); the
        others are built by ``rows``. None when the class has no such form."""
        return None

    def block_rows(self, s) -> tuple[ca.SX, list[str], Batch] | None:
        """``(column, labels, batch)``: this item's rows as one SX column when ``rows(s)`` builds
        them all by one formula of lifted numbers (the same expressions and labels), with their
        Batch (its ``items`` 0); else None."""
        return None

    def _one_sided(self, unilateral, restitution) -> None:
        """Validate and keep the one-sided settings (every subclass's __init__ calls this)."""
        where = self._where()
        if not isinstance(unilateral, bool):
            raise InputError(f"unilateral must be true or false, got {unilateral!r}",
                             where=f"{where}.unilateral")
        if unilateral and self.two_sided_only:
            raise InputError(f"a {self.two_sided_only}; remove 'unilateral' from it",
                             where=f"{where}.unilateral")
        if isinstance(restitution, str):  # a formula of the parameters: checked for its values
            if not restitution.strip():
                raise InputError("restitution must be a number from 0 to 1 or a formula of the parameters, "
                                 "got an empty string", where=f"{where}.restitution")
        else:
            _check_restitution(restitution, f"{where}.restitution")
        if restitution and not unilateral:
            raise InputError("restitution applies to a one-sided constraint, which can close with an "
                             "impact; add unilateral = true, or remove restitution",
                             where=f"{where}.restitution")
        self.unilateral = unilateral
        self.restitution = restitution if isinstance(restitution, str) else float(restitution)

    def coefficient_of_restitution(self, values: Mapping[str, float]) -> float:
        """e for the parameters' ``values``: the number given, or the formula evaluated (so a
        sweep can vary it); InputError when it is not in [0, 1]."""
        where = f"{self._where()}.restitution"
        e = self.restitution
        if isinstance(e, str):
            from .parameters import evaluate

            e = evaluate(e, values, where)
        return _check_restitution(e, where, formula=self.restitution if isinstance(self.restitution, str)
                                  else None)


def _check_restitution(e, where: str, formula: str | None = None) -> float:
    """A coefficient of restitution as a float in [0, 1], or an InputError saying why not."""
    given = f"{formula!r} = {e!r}" if formula else repr(e)
    if isinstance(e, bool) or not isinstance(e, int | float) or math.isnan(e):
        raise InputError(f"restitution must be a number from 0 (the motion into the constraint stops) "
                         f"to 1 (an elastic bounce) or a formula of the parameters, got {given}", where=where)
    if e < 0:
        raise InputError(f"restitution must be at least 0, got {given}: e < 0 would send the particle on "
                         "into the constraint after the impact (0: the motion into it stops)", where=where)
    if e > 1:
        raise InputError(f"restitution must be at most 1, got {given}: e > 1 would create energy at every "
                         "impact (1: an elastic bounce)", where=where)
    return float(e)


class Distance(Constraint):
    """|x_a − x_b| − length = 0, or |x_a − point(t)| − length = 0 (moving anchor allowed).

    The multiplier is the force along the outward direction: tension = −λ.
    """

    side = -1
    numbers = ("point", "length")

    def __init__(self, a: str, b: str | None = None, *, point=None, length, name=None, where=None,
                 unilateral: bool = False, restitution: float | str = 0.0):
        self.a, self.b, self.point, self.length = a, b, point, length
        self.name, self.where = name, where
        _three(point, f"{where or 'constraint distance'}.point", "point=[0, 0, 0]")
        self._one_sided(unilateral, restitution)
        if (b is None) == (point is None):
            raise InputError("give exactly one of 'b' (a particle) or 'point'", where=self._where())
        if isinstance(length, int | float) and not isinstance(length, bool) and length <= 0:
            other = "'b'" if b is not None else "the point"
            fix = ("a 'pin' constraint holds a particle at a point" if b is None
                   else "merge the two particles into one")
            raise InputError(
                f"must be a positive length in m, got {length!r}: a rod of length {length!r} would hold "
                f"'{a}' on {other}, where the direction of the rod, and so the constraint force, is "
                f"undefined (the constraint's gradient vanishes); {fix}",
                where=f"{self._where()}.length")

    @classmethod
    def between(cls, a: str, b: str, length: float, where: str | None = None) -> Distance:
        """``Distance(a, b, length=length, where=where)`` of values already checked (two different
        particles' names, a finite positive float length), without checking them again: a
        large scene's rods (constrained.scene.plain)."""
        return cls.bare(a=a, b=b, point=None, length=length, name=None, where=where, unilateral=False,
                        restitution=0.0)

    @property
    def label(self) -> str:
        other = self.b if self.b is not None else _fmt(self.point)
        return self.name or f"distance {self.a}–{other} = {_fmt(self.length)} m"

    def rows(self, s):
        where = self._where()
        xa = s.position(self.a, where)
        xb = s.position(self.b, where) if self.b is not None else s.point(self.point, f"{where}.point")
        length = s.time_function(self.length, f"{where}.length")
        return [(ca.norm_2(xa - xb) - length, self.label)]

    @classmethod
    def batch_rows(cls, items: list, s) -> tuple[list[int], Formula, list[str], Batch | None]:
        """|x_a − x_b| − length of rods between two particles with lengths that are plain
        numbers (entries of p, constrained.lifting), as one column (a Formula: built when
        asked for): one CasADi call per operation instead of several per rod (a 10,000-link
        chain)."""
        plain, ends = pair_ends(items, s, ("length",))
        if not plain:
            return plain, Formula.of(ca.SX(0, 1)), [], None
        rods = [items[k] for k in plain]
        lengths = [c.length for c in rods]
        # (``label``, the length's token written as Number.__format__ writes it, without a call)
        labels = [c.name or f"distance {c.a}–{c.b} = ⟦{c.length.index}⟧ m" for c in rods]
        return plain, pair_formula(s, ends, [lengths], lambda d, length: (d - length).T), labels, \
            pair_batch(items, plain, s, [lengths], ends)


def pair_batch(items: list, plain: list[int], s, numbers: list[list], ends: np.ndarray | None = None
               ) -> Batch | None:
    """The Batch of the items ``plain`` of ``items`` (each between particles ``a`` and ``b``,
    one row or term each) whose numbers (``numbers``: one list per field) are all lifted.
    ``ends``: their particles' indices (n, 2), as ``pair_ends`` gives them."""
    entries = [s.number_entries(field) for field in numbers]
    if any(e is None for e in entries):
        return None
    if ends is None:
        index = s._index
        ends = np.array([[index[items[k].a], index[items[k].b]] for k in plain], dtype=np.int64)
    n = len(plain)
    return Batch(np.asarray(plain, np.int64), np.zeros(n, np.int64), ends,
                 np.stack(entries, axis=1) if entries else np.zeros((n, 0), np.int64))


def pair_ends(items: list, s, fields: tuple[str, ...]) -> tuple[list[int], np.ndarray]:
    """For batches of items between two particles (attributes ``a``, ``b``): the positions in
    ``items`` of those joining two particles of ``s`` whose ``fields`` are all plain numbers
    (lifted: entries of p), and their particles' indices (n, 2)."""
    index = s._index
    ends = _between(items, index, fields)
    if ends is not None:
        plain = np.flatnonzero(ends[:, 0] >= 0).tolist()
        ends = ends[plain]
    else:  # (an unhashable end: item by item)
        plain = [k for k, c in enumerate(items) if isinstance(c.a, str) and isinstance(c.b, str)
                 and c.a in index and c.b in index and all(type(getattr(c, f)) is Number for f in fields)]
        ends = np.array([[index[items[k].a], index[items[k].b]] for k in plain], np.int64).reshape(-1, 2)
    return plain, ends


def _between(items: list, index: dict, fields: tuple[str, ...]) -> np.ndarray | None:
    """(n, 2): the particles' indices of each of ``items`` that joins two particles of ``index``
    (its ``a`` and ``b`` strings) and holds Numbers in all its ``fields`` (the rows of the
    others −1), in passes over the whole list; None when an end cannot be looked up."""
    n = len(items)
    ends = [list(map(operator.attrgetter(end), items)) for end in ("a", "b")]
    ok = np.ones(n, bool)
    for column in ends:
        ok &= np.fromiter(map(isinstance, column, itertools.repeat(str)), bool, n)
    for f in fields:
        kinds = map(type, map(operator.attrgetter(f), items))
        ok &= np.fromiter(map(operator.is_, kinds, itertools.repeat(Number)), bool, n)
    try:
        found = np.array([np.fromiter(map(index.get, column, itertools.repeat(-1)), np.int64, n)
                          for column in ends]).T.reshape(n, 2)
    except TypeError:
        return None
    found[~(ok & (found >= 0).all(axis=1))] = -1
    return found


class Pin(Constraint):
    """x_a − point(t) = 0: a fixed position, or a prescribed path when entries depend on t."""

    two_sided_only = ("pin holds a particle at a point and has no side to leave by (a one-sided "
                      "distance to the point of length 0 is not defined either); use a one-sided "
                      "plane or surface through the point")
    numbers = ("point",)

    def __init__(self, a: str, point, *, name=None, where=None, unilateral: bool = False,
                 restitution: float | str = 0.0):
        self.a, self.point, self.name, self.where = a, point, name, where
        self._one_sided(unilateral, restitution)

    @property
    def label(self) -> str:
        return self.name or f"pin {self.a} at {_fmt(self.point)}"

    def rows(self, s):
        where = self._where()
        d = s.position(self.a, where) - s.point(self.point, f"{where}.point")
        return [(d[k], f"{self.label} ({axis})") for k, axis in enumerate("xyz")]


class Plane(Constraint):
    """n(t)·x_i − offset(t) = 0 for each listed particle, scaled by 1/|n| (metres)."""

    numbers = ("normal", "offset")

    def __init__(self, particles, normal, offset=0.0, *, name=None, where=None, unilateral: bool = False,
                 restitution: float | str = 0.0):
        self.particles = _as_list(particles, where or "plane", "'particles'")
        self.normal, self.offset, self.name, self.where = normal, offset, name, where
        self._one_sided(unilateral, restitution)
        if (
            isinstance(normal, Sequence)
            and not isinstance(normal, str)
            and all(isinstance(c, int | float) and c == 0 for c in normal)
        ):
            raise InputError("the normal vector is zero", where=f"{self._where()}.normal")

    @property
    def label(self) -> str:
        return self.name or f"plane n={_fmt(self.normal)}, offset {_fmt(self.offset)}"

    def _column(self, s) -> ca.SX:
        """The rows as one column."""
        where = self._where()
        n = s.point(self.normal, f"{where}.normal")
        offset = s.time_function(self.offset, f"{where}.offset")
        # all rows in a few CasADi calls (one per particle would dominate the build of a chain)
        P = s.columns(self.particles, where)
        return ((ca.mtimes(n.T, P) - offset) / ca.norm_2(n)).T

    def _labels(self) -> list[str]:
        label = self.label
        return [f"{label} [{p}]" for p in self.particles]

    def rows(self, s):
        return list(zip(ca.vertsplit(self._column(s), 1), self._labels(), strict=True))

    def block_rows(self, s) -> tuple[ca.SX, list[str], Batch] | None:
        """The rows n·x_i − offset over the listed particles: one formula, shared numbers."""
        shared = [v for v in (*self.normal, self.offset) if not (isinstance(v, int | float) and v == 0)]
        entries = s.number_entries(shared) if not isinstance(self.normal, str) else None
        if entries is None:  # (a formula of t or of the parameters: no batch)
            return None
        n = len(self.particles)
        particles = np.array(s.indices(self.particles, self._where()), dtype=np.int64)
        return self._column(s), self._labels(), Batch(
            np.zeros(n, np.int64), np.arange(n, dtype=np.int64), particles[:, None],
            np.repeat(entries[None, :], n, axis=0))


class Surface(Constraint):
    """g(x, y, z, t) = 0 for each listed particle; ``expr`` is a formula in x, y, z, t."""

    def __init__(self, particles, expr: str, *, name=None, where=None, unilateral: bool = False,
                 restitution: float | str = 0.0):
        self.particles = _as_list(particles, where or "surface", "'particles'")
        self.expr, self.name, self.where = expr, name, where
        self._one_sided(unilateral, restitution)

    @property
    def label(self) -> str:
        return self.name or f"surface {self.expr} = 0"

    def rows(self, s):
        where, label = self._where(), self.label
        return [
            (s.parse_field(self.expr, f"{where}.expr", s.position(p, where)), f"{label} [{p}]")
            for p in self.particles
        ]


class Curve(Constraint):
    """A curve as the intersection of two surfaces g1 = g2 = 0, for each listed particle."""

    two_sided_only = ("curve is the intersection of two surfaces and has no one side to leave by; "
                      "give the two surfaces as separate one-sided 'surface' constraints")

    def __init__(self, particles, exprs: Sequence[str], *, name=None, where=None, unilateral: bool = False,
                 restitution: float | str = 0.0):
        self.particles = _as_list(particles, where or "curve", "'particles'")
        if isinstance(exprs, str) or len(exprs) != 2:
            raise InputError(
                "a curve needs 'expr' as a list of two surface formulas", where=where or "curve"
            )
        self.exprs, self.name, self.where = list(exprs), name, where
        self._one_sided(unilateral, restitution)

    @property
    def label(self) -> str:
        return self.name or f"curve {self.exprs[0]} = 0, {self.exprs[1]} = 0"

    def rows(self, s):
        where, label = self._where(), self.label
        out = []
        for p in self.particles:
            at = s.position(p, where)
            for k, e in enumerate(self.exprs):
                out.append((s.parse_field(e, f"{where}.expr[{k}]", at), f"{label} [{p}, {k + 1}]"))
        return out


class Custom(Constraint):
    """Any formula in particle coordinates x_NAME, y_NAME, z_NAME and t, equal to zero."""

    def __init__(self, expr: str, *, name=None, where=None, unilateral: bool = False,
                 restitution: float | str = 0.0):
        self.expr, self.name, self.where = expr, name, where
        self._one_sided(unilateral, restitution)

    @property
    def label(self) -> str:
        return self.name or f"{self.expr} = 0"

    def rows(self, s):
        return [(s.parse(self.expr, f"{self._where()}.expr"), self.label)]


#: Runs of at least this many constraints of one class are built together (``batch_rows``).
BATCH_FROM = 64


def constraint_rows(constraints: list, s) -> tuple[list[tuple], list[Batch]]:
    """Each constraint's rows, in order, as pieces ``(first, count, rows)``: ``rows`` a list of
    ``(expression, label)`` of the one constraint ``first`` (``count`` 1), or ``(column,
    labels)`` of ``count`` constraints from ``first`` on (their rows as one SX column: one row
    each, or one constraint's rows built by one formula, ``block_rows``). Runs of BATCH_FROM or
    more constraints of one class go through the class's ``batch_rows`` where it has one (the
    same expressions as ``rows``). And the Batches of rows built by one formula (``items``:
    indices into ``constraints``): a run's, and a constraint's own of BATCH_FROM rows or more."""
    pieces, batches = [], []
    for k, j in class_runs(constraints):
        cls = type(constraints[k])
        built = cls.batch_rows(constraints[k:j], s) if j - k >= BATCH_FROM else None
        plain, column, labels, batch = built if built is not None else ([], None, [], None)
        if batch is not None:
            batches.append(batch.shifted(np.arange(k, j)))
        at = np.zeros(j - k, bool)
        at[plain] = True
        # stretches of consecutive items built together, and the items between them alone
        edges = np.flatnonzero(np.diff(np.concatenate([[False], at, [False]]).astype(np.int8)))
        done, row = k, 0
        for start, stop in [*zip(edges[::2] + k, edges[1::2] + k, strict=True), (j, j)]:
            for i in range(done, start):
                pieces.append(_alone(constraints[i], i, s, batches))
            if stop > start:
                count = stop - start
                pieces.append((start, count, (column.part(np.arange(row, row + count)),
                                              labels[row:row + count])))
            done, row = stop, row + stop - start
    return pieces, batches


def class_runs(items: list) -> list[tuple[int, int]]:
    """``[(start, stop), ...]``: the runs of consecutive items of one class, in order (found in
    one pass over their classes)."""
    kinds = list(map(type, items))
    bounds = [0, *itertools.compress(range(1, len(kinds)), map(operator.is_not, kinds[1:], kinds[:-1])),
              len(kinds)]
    return list(zip(bounds[:-1], bounds[1:], strict=True)) if kinds else []


def stacked_rows(constraints: list, s) -> tuple:
    """``(rows, velocity_rows, labels, owners, first_row, batches)``: the rows of f (a Stacked:
    pieces of ``constraint_rows`` built together kept as columns), the velocity rows
    (model/velocity.py), every row's label (position rows, then velocity rows) and constraint
    (an array), each constraint's first row of f (−1: a velocity constraint), and the Batches
    (``constraint_rows``)."""
    rows, velocity_rows = Stacked(), []
    labels, owners, velocity_labels, velocity_owners = [], [], [], []
    first_row = np.zeros(len(constraints), np.int64)
    pieces, batches = constraint_rows(constraints, s)
    for k, count, built in pieces:
        if isinstance(built, tuple):  # (column, labels) of count constraints, one row each, or of one
            first_row[k:k + count] = len(rows) + (np.arange(count) if count > 1 else 0)
            owners.append(np.arange(k, k + count) if count > 1 else np.full(len(built[1]), k))
            rows.add_column(built[0])
            labels += built[1]
        elif getattr(constraints[k], "level", "position") == "velocity":
            first_row[k] = -1
            velocity_rows += [expr for expr, _ in built]
            velocity_labels += [label for _, label in built]
            velocity_owners += [k] * len(built)
        else:
            first_row[k] = len(rows)
            for expr, _ in built:
                rows.add(expr)
            labels += [label for _, label in built]
            owners.append(np.full(len(built), k))
    owner = np.concatenate([*owners, np.array(velocity_owners, np.int64)]).astype(int)
    return rows, velocity_rows, labels + velocity_labels, owner, first_row, batches


def _alone(c: Constraint, i: int, s, batches: list) -> tuple:
    """The piece of the constraint ``c`` (index ``i``) built by itself: its ``block_rows`` when
    it has BATCH_FROM rows or more of one formula (their Batch added to ``batches``), else its
    ``rows``."""
    block = c.block_rows(s) if len(getattr(c, "particles", ())) >= BATCH_FROM else None
    if block is not None:
        batches.append(block[2].shifted([i]))
        return i, 1, block[:2]
    return i, 1, c.rows(s)


CONSTRAINT_TYPES = {
    "distance": Distance,
    "pin": Pin,
    "plane": Plane,
    "surface": Surface,
    "curve": Curve,
    "custom": Custom,
}
