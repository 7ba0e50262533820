"""Symbols: the CasADi variables of one assembled system, handed to constraints and effects.

Assembly is the only place CasADi symbols are made. A constraint or an effect receives a
Symbols object and returns expressions in ``x`` (3N positions), ``v`` (3N velocities) and
``t``; formula strings are parsed here, with exactly the names the context allows.
"""

from __future__ import annotations

import bisect
import functools
import itertools
import operator
from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ExpressionError, InputError, listed
from . import expressions, parameters
from .lifting import Number

_NUMBER = frozenset((Number,))
_STR = frozenset((str,))
_INDEX = operator.attrgetter("index")


@dataclass(frozen=True)
class Batch:
    """Rows of f (or terms of V) built by one vectorized formula: instance k is the formula
    applied to the particles ``particles[k]`` (n, s) and the plain numbers at the entries
    ``numbers[k]`` (n, q) of p, and it is row (or summand) ``offsets[k]`` of item ``items[k]``
    (a constraint's rows, an effect's term unfolded into its summands). What the mapped build
    (constrained.manifold.vectorized.grouping) would otherwise find by comparing every row
    with candidate kernels; it still checks a sample of the instances."""

    items: np.ndarray
    offsets: np.ndarray
    particles: np.ndarray
    numbers: np.ndarray
    #: The instances themselves as one SX column (in the batch's order) when the item that built
    #: them keeps them (gravity's summands: the mapped build then need not unfold its sum).
    values: ca.SX | None = None

    def shifted(self, items: np.ndarray) -> Batch:
        """This batch with its items renamed ``items[item]`` (an item's place in a longer list)."""
        return Batch(np.asarray(items, np.int64)[self.items], self.offsets, self.particles, self.numbers,
                     self.values)

    def placed(self, first: np.ndarray) -> Batch:
        """This batch with its items replaced by ``first[item]`` (a constraint's first row of f,
        a potential's place among the slot's terms), kept only where that is ≥ 0."""
        items = first[self.items]
        keep = items >= 0
        values = self.values
        if values is not None and not keep.all():
            values = values[np.flatnonzero(keep).tolist()] if keep.any() else None
        return Batch(items[keep], self.offsets[keep], self.particles[keep], self.numbers[keep], values)


class _Pieces:
    """The pieces (``size`` entries each) of an SX column, asked for one by one: the first few
    sliced out, then all at once by one split (a slice costs ≈ 7 µs in CasADi's Python layer, a
    split of 40,000 ≈ 30 ms, and a big chain asks for thousands, a cloth's pins for two). The
    same elements either way."""

    SPLIT_FROM = 32

    def __init__(self, column, size: int = 1):
        self.column, self.size, self.asked, self.pieces = column, size, 0, None

    def __getitem__(self, k: int):
        if self.pieces is None:
            self.asked += 1
            if self.asked <= self.SPLIT_FROM:
                return self.column[self.size * k:self.size * (k + 1)]
            self.pieces = ca.vertsplit(self.column, self.size)
        return self.pieces[k]


class Formula:
    """n scalar expressions built by one vectorized formula (a run of rods, of springs), held
    as its recipe: ``build(chosen)`` makes the SX column of the formula's instances ``chosen``
    (indices, in order; None: all of them) by the same CasADi operations over their inputs, so
    that an instance built alone is the expression that element of the whole column is (the
    same operations on the same symbols). The whole column is built once, when something asks
    for all of its nodes (``column()``: a small model's Functions, the reduced route); the
    first few single instances asked for before that (the mapped build's sample of rows, a
    probe) are built alone (≈ 50 µs each, where a cloth's 20,000 springs take 80 ms), the
    others read from the whole column. A part (``part``) shares its root's recipe and column:
    its column is the root's elements, as a slice of the root's column is."""

    ALONE_UP_TO = 256

    def __init__(self, build, n: int, chosen: np.ndarray | None = None, root: Formula | None = None):
        self._build, self.n, self._chosen = build, int(n), chosen
        self._root = self if root is None else root
        self._column, self._pieces = None, None
        self._alone: dict[int, ca.SX] = {}  # (the root's: instance -> built alone)
        self._asked = 0

    @classmethod
    def of(cls, column: ca.SX) -> Formula:
        """An SX column already built, read as a Formula's."""
        out = cls(None, column.numel())
        out._column = column
        return out

    def numel(self) -> int:
        return self.n

    @property
    def built(self) -> bool:
        """Whether the root's whole column has been built."""
        return self._root._column is not None

    def column(self) -> ca.SX:
        """Every instance as one SX column: the root's column built by ``build(None)``, a
        part's its elements of it."""
        if self._column is None:
            if self._root is self:
                self._column = self._build(None)
            else:
                self._column = self._root.column()[self._chosen.tolist()]
        return self._column

    def part(self, chosen) -> Formula:
        """The instances ``chosen`` (indices into this column, in order) as a Formula."""
        chosen = np.asarray(chosen, np.int64)
        if len(chosen) == self.n and np.array_equal(chosen, np.arange(self.n)):
            return self
        if self._root._build is None:  # (an SX column: sliced, as it always was)
            return Formula.of(self.column()[chosen.tolist()])
        return Formula(self._build, len(chosen), chosen if self._chosen is None else self._chosen[chosen],
                       self._root)

    def elements(self, ks) -> list:
        """``[self[k] for k in ks]``, those not built yet built together by one call of the
        recipe (the same expressions: the operations are elementwise)."""
        root = self._root
        if root._column is not None or self._pieces is not None or root._asked >= self.ALONE_UP_TO:
            return [self[k] for k in ks]
        root._asked += 1
        at = [int(k if self._chosen is None else self._chosen[k]) for k in ks]
        todo = sorted({i for i in at if i not in root._alone})
        if todo:
            root._alone.update(zip(todo, ca.vertsplit(root._build(np.array(todo, np.int64))), strict=True))
        return [root._alone[i] for i in at]

    def __getitem__(self, k: int) -> ca.SX:
        root = self._root
        if root._column is None and self._pieces is None:
            root._asked += 1
            if root._asked <= self.ALONE_UP_TO:
                i = int(k if self._chosen is None else self._chosen[k])
                if i not in root._alone:
                    root._alone[i] = root._build(np.array([i], np.int64))
                return root._alone[i]
        if self._pieces is None:
            self._pieces = _Pieces(self.column())
        return self._pieces[k]


def pair_formula(s: Symbols, ends: np.ndarray, numbers: list[list], formula) -> Formula:
    """``formula(distances, *rows)`` over the particle pairs ``ends`` (n, 2) as a Formula: the
    pairs' distances |x_a − x_b| as one row (1, n), formed as norm_2 forms them (sq of each
    entry, summed, sqrt), column by column, and each list of ``numbers`` (n values) as the row
    ``s.number_column(values).T``; some instances alone: the same over their pairs and values."""
    def build(chosen):
        at, values = (ends, numbers) if chosen is None else (
            ends[chosen], [[column[i] for i in chosen] for column in numbers])
        d = s.particle_columns(at[:, 0]) - s.particle_columns(at[:, 1])
        squares = d * d
        distances = ca.sqrt(squares[0, :] + squares[1, :] + squares[2, :])
        return formula(distances, *[s.number_column(column).T for column in values])
    return Formula(build, len(ends))


class Stacked(Sequence):
    """Expressions in order (rows of f, effects' terms), held as segments: single expressions,
    or columns kept whole — n scalar expressions built by one vectorized formula (a run of
    rods, a plane's rows, a run of springs), ``Formula``s, made into SX nodes only where asked
    for. ``column()`` is the same elements in the same order as a vertcat of them one by one.

    ``probe``: with each single expression an SX whose dependence on a symbol is the
    expression's (the first summand of a sum built by one formula, gravity's), else itself;
    a column's is its first element (the formula is the same for all)."""

    def __init__(self):
        self._segments: list = []  # [single expressions, their probes], or a Formula
        self._starts: list[int] = [0]

    def add(self, expression, probe=None) -> None:
        """Append one expression (``probe``: as in the class docstring)."""
        if not self._segments or not isinstance(self._segments[-1], list):
            self._segments.append([[], []])
            self._starts.append(self._starts[-1])
        self._segments[-1][0].append(expression)
        self._segments[-1][1].append(expression if probe is None else probe)
        self._starts[-1] += 1

    def add_column(self, column: ca.SX | Formula) -> None:
        """Append the n scalar elements of the SX column or Formula ``column`` (built by one
        formula)."""
        n = column.numel()
        if n:
            self._segments.append(column if isinstance(column, Formula) else Formula.of(column))
            self._starts.append(self._starts[-1] + n)

    def __len__(self) -> int:
        return self._starts[-1]

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        k = int(k)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(k)
        j = bisect.bisect_right(self._starts, k) - 1
        segment = self._segments[j]
        return segment[0][k - self._starts[j]] if isinstance(segment, list) else segment[k - self._starts[j]]

    def elements(self, ks) -> list:
        """``[self[k] for k in ks]``: a column's instances not built yet built together."""
        ks = np.asarray(ks, np.int64)
        ks = np.where(ks < 0, ks + len(self), ks)
        segment = np.searchsorted(self._starts, ks, side="right") - 1
        out: list = [None] * len(ks)
        for j in sorted(set(segment.tolist())):  # (np.unique imports numpy.ma: 10 ms)
            at = np.flatnonzero(segment == j)
            if not isinstance(self._segments[j], Formula):
                for i in at.tolist():
                    out[i] = self[int(ks[i])]
                continue
            for i, e in zip(at.tolist(), self._segments[j].elements((ks[at] - self._starts[j]).tolist()),
                            strict=True):
                out[i] = e
        return out

    def segments(self) -> list[tuple[int, object]]:
        """``(first index, segment)``: a list of single expressions, or a Formula."""
        return [(start, segment[0] if isinstance(segment, list) else segment)
                for start, segment in zip(self._starts, self._segments, strict=False)]

    def select(self, keep: np.ndarray) -> Stacked:
        """The expressions where ``keep`` (one bool each), columns kept whole (or their parts)."""
        out = Stacked()
        for start, segment in zip(self._starts, self._segments, strict=False):
            if isinstance(segment, list):
                for k, (e, probe) in enumerate(zip(*segment, strict=True)):
                    if keep[start + k]:
                        out.add(e, probe)
                continue
            kept = keep[start:start + segment.numel()]
            out.add_column(segment if kept.all() else segment.part(np.flatnonzero(kept)))
        return out

    def column(self) -> ca.SX:
        """Every expression as one SX column (a single one that is not SX: as ``ca.SX``)."""
        parts = [e if isinstance(e, ca.SX) else ca.SX(e) for segment in self._segments
                 for e in (segment[0] if isinstance(segment, list) else [segment.column()])]
        return ca.vertcat(*parts) if parts else ca.SX(0, 1)

    def scalars(self) -> bool:
        """Whether every single expression is a scalar (the columns' are)."""
        return all(not isinstance(e, ca.SX) or e.shape == (1, 1) for segment in self._segments
                   if isinstance(segment, list) for e in segment[0])

    @staticmethod
    def may(expressions, symbol: ca.SX) -> bool:
        """``may_depend_on`` of a Stacked; True for a list (it is not known)."""
        return not isinstance(expressions, Stacked) or expressions.may_depend_on(symbol)

    def may_depend_on(self, symbol: ca.SX) -> bool:
        """Whether some expression may depend on ``symbol`` (its probe does): False proves
        that none does, and so that a sum or stack of them does not."""
        probes = [ca.vec(e) for segment in self._segments
                  for e in (segment[1] if isinstance(segment, list) else [segment[0]])
                  if isinstance(e, ca.SX)]
        return bool(probes) and ca.depends_on(ca.vertcat(*probes), symbol)


class Symbols:
    """CasADi SX symbols ``x``, ``v``, ``t`` for a System, plus the scene's parameters.

    By default the parameters and definitions are numbers (``parameters`` maps each name to
    its value) and ``masses`` is the numeric array: expressions come out with the values
    inside. With ``symbolic_parameters`` each parameter is an SX symbol named after it,
    stacked into ``p`` (in the order of ``system.parameters``), each definition an SX
    expression of them, and ``masses`` a list (a float, or an SX expression for a mass given
    by a formula): the Model builds its parametric Functions of ``p`` from these.

    ``numbers``: how many plain numbers the (lifted, constrained.lifting) system holds as
    ``Number`` entries; each is the symbol ``p[len(parameters) + index]``.
    """

    mass_entries: list[int] | None = None
    _offset: int | None = None  # where the Numbers' entries start in p (symbolic parameters)

    def __init__(self, system, *, symbolic_parameters: bool = False, numbers: int = 0):
        self.system = system
        n = system.n_particles
        self.x = ca.SX.sym("x", 3 * n)
        self.v = ca.SX.sym("v", 3 * n)
        self.t = ca.SX.sym("t")
        self._index = {p.name: i for i, p in enumerate(system.particles)}
        self.symbolic_parameters = symbolic_parameters
        if symbolic_parameters:
            self.p, self.parameters = parameters.symbolic(system.parameters, system.definitions)
            hidden = ca.SX.sym("number", numbers)
            self._numbers = _Pieces(hidden)
            offset = self._offset = self.p.numel()
            # (no named parameter: p is the hidden ones, the same symbols; a vertcat copies
            # 69,000 of a cloth's in 10 ms)
            self.p = hidden if self.p.is_empty() and hidden.numel() else ca.vertcat(self.p, hidden)
            lifted = [p.mass for p in system.particles]
            if all(type(m) is Number for m in lifted):  # (a mass given by a formula is not one)
                #: Each particle's entry of p when every mass is a plain number (a Number): then
                #: ``mass_column`` is one gather from p instead of a vertcat of N symbols.
                self.mass_entries = [offset + m.index for m in lifted]
                self._lifted_masses = lifted  # (``masses``: their symbols, when first asked for)
            else:
                self.masses = [
                    expressions.parse(p.formulas["mass"], self.parameters, where=f"{p.where or p.name}.mass")
                    if "mass" in p.formulas else self.number(p.mass)
                    for p in system.particles
                ]
        else:
            self.p = ca.SX(0, 1)
            self._numbers = _Pieces(ca.SX(0, 1))
            self.parameters = system.parameter_values
            self.masses = system.masses
        self._position_names = self._state_names = None

    @functools.cached_property
    def masses(self) -> list:
        """Each particle's mass: the symbols of p of plain numbers (when every mass is one)."""
        return [self._numbers[m.index] for m in self._lifted_masses]

    @functools.cached_property
    def _xp(self) -> _Pieces:
        return _Pieces(self.x, 3)

    @functools.cached_property
    def _vp(self) -> _Pieces:
        return _Pieces(self.v, 3)

    def columns(self, names, where: str):
        """The positions of the particles ``names`` as the columns of a (3, len(names)) SX: one
        gather from x (the same entries as a horzcat of ``position(name)``)."""
        indices = self.indices(names, where)
        X = ca.reshape(self.x, 3, self.x.numel() // 3)
        return X if indices == list(range(X.size2())) else X[:, indices]

    def particle_columns(self, indices: np.ndarray) -> ca.SX:
        """The positions of the particles ``indices`` as the columns of a (3, n) SX: the entries
        of x (those of ``columns``), gathered without reshaping the whole of x."""
        flat = 3 * np.asarray(indices, np.int64)[:, None] + np.arange(3)
        return ca.reshape(self.x[flat.ravel().tolist()], 3, len(flat))

    def number_column(self, values: list):
        """``vertcat(*[number(v) for v in values])``: when all are Numbers, one gather from p."""
        entries = self.number_entries(values) if values else None
        if entries is not None:
            return self.p[entries.tolist()]
        return ca.vertcat(*[self.number(v) for v in values])

    def number_entries(self, values: list) -> np.ndarray | None:
        """The entries of p of ``values`` when all are Numbers (lifted plain numbers), else None."""
        if self._offset is None or not _NUMBER.issuperset(map(type, values)):
            return None
        return np.fromiter(map(_INDEX, values), np.int64, len(values)) + self._offset

    def entries_of(self, values: list) -> np.ndarray | None:
        """For each of ``values`` that is a bare entry of ``p``, its index in p; None when one
        is anything else (a formula, a number)."""
        p = self.p
        symbols = {e.element_hash(): k for k, e in enumerate(ca.vertsplit(p))} if p.numel() else {}
        out = []
        for e in values:
            if not isinstance(e, ca.SX) or not e.is_symbolic() or e.element_hash() not in symbols:
                return None
            out.append(symbols[e.element_hash()])
        return np.array(out, dtype=np.int64)

    def mass_column(self, indices=None):
        """The masses of the particles ``indices`` (all by default) as a column: a DM of
        numbers, or an SX when some are symbols (one CasADi call, not one per particle)."""
        if self.mass_entries is not None:  # (the same elements as the vertcat below)
            entries = self.mass_entries if indices is None else [self.mass_entries[i] for i in indices]
            return self.p[entries] if entries else ca.SX(0, 1)
        masses = self.masses if indices is None else [self.masses[i] for i in indices]
        if not any(isinstance(m, ca.SX) for m in masses):
            return ca.DM(np.asarray(masses, float))
        return ca.vertcat(*[m if isinstance(m, ca.SX) else ca.SX(m) for m in masses])

    def number(self, value):
        """``value``, or the symbol of the hidden parameter when it is a lifted Number."""
        return self._numbers[value.index] if type(value) is Number else value

    @property
    def position_names(self) -> dict:
        """Names a position formula may use: t, parameters, x_NAME, y_NAME, z_NAME (built lazily)."""
        if self._position_names is None:
            self._build_names()
        return self._position_names

    @property
    def state_names(self) -> dict:
        """position_names plus the velocities vx_NAME, vy_NAME, vz_NAME (built lazily)."""
        if self._state_names is None:
            self._build_names()
        return self._state_names

    def _build_names(self) -> None:
        base = {"t": self.t, **self.parameters}
        xs, vs = ca.vertsplit(self.x), ca.vertsplit(self.v)
        position, state = dict(base), dict(base)
        for name, i in self._index.items():
            for k, axis in enumerate("xyz"):
                position[f"{axis}_{name}"] = state[f"{axis}_{name}"] = xs[3 * i + k]
                state[f"v{axis}_{name}"] = vs[3 * i + k]
        self._position_names, self._state_names = position, state

    def indices(self, names: Sequence, where: str) -> list[int]:
        """``[index(name, where) for name in names]``: when all are names of particles, at once."""
        try:
            found = list(map(self._index.get, names, itertools.repeat(-1)))
        except TypeError:  # (an unhashable value: ``index`` says what is wrong)
            found = [-1]
        if -1 in found or not _STR.issuperset(map(type, names)):
            return [self.index(name, where) for name in names]
        return found

    def index(self, name: str, where: str) -> int:
        if not isinstance(name, str) or name not in self._index:
            known = listed(self._index) or "(none)"
            raise InputError(f"names unknown particle {name!r} (particles: {known})", where=where)
        return self._index[name]

    def position(self, name: str, where: str):
        return self._xp[self.index(name, where)]

    def velocity(self, name: str, where: str):
        return self._vp[self.index(name, where)]

    def parse(self, text, where: str, *, velocities: bool = False, extra: dict | None = None):
        """Parse a formula in particle coordinates (and velocities if allowed), t, parameters."""
        if type(text) is Number:
            return self.number(text)
        names = dict(self.state_names if velocities else self.position_names)
        if extra:
            names.update(extra)
        try:
            return expressions.parse(text, names, where=where)
        except ExpressionError:
            if not velocities and isinstance(text, str):
                used = expressions.free_names(text)
                vel = sorted(n for n in used if n in self.state_names and n not in names)
                if vel:
                    raise ExpressionError(
                        f"velocities ({', '.join(vel)}) are not allowed in this formula",
                        where=where,
                    ) from None
            raise

    def parse_field(self, text, where: str, at, *, velocity=None):
        """Parse a field formula in x, y, z, t (and parameters) evaluated at the point ``at``."""
        if type(text) is Number:
            return self.number(text)
        extra = {"x": at[0], "y": at[1], "z": at[2], "t": self.t, **self.parameters}
        if velocity is not None:
            extra.update({"vx": velocity[0], "vy": velocity[1], "vz": velocity[2]})
        return expressions.parse(text, extra, where=where)

    def time_function(self, text, where: str):
        """A formula of t (and parameters) only: moving anchors, plane offsets."""
        if type(text) is Number:
            return self.number(text)
        return expressions.parse(text, {"t": self.t, **self.parameters}, where=where)

    def point(self, entries: Sequence, where: str):
        """A 3-vector whose entries are numbers or formula strings of t."""
        if isinstance(entries, np.ndarray):
            entries = entries.tolist()
        if isinstance(entries, str) or not isinstance(entries, Sequence) or len(entries) != 3:
            raise InputError(
                f"must be a list of 3 entries (numbers or formulas of t), got {entries!r}",
                where=where,
            )
        return ca.vertcat(*[self.time_function(e, f"{where}[{k}]") for k, e in enumerate(entries)])
