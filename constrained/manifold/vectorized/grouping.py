"""Repeated rows and terms found (issue 16, 28): every constraint row and every summand of the
potential cut out with the coordinates it depends on, its numbers lifted out as data
(``lifted``), and the instances with the same operations gathered into one ``Group`` — the
kernel that the mapped build (``manifold.mapped``: CasADi ``map`` in compiled step loops) and
the vectorized build (``vectorized.build``: whole columns in the virtual machine) evaluate.

Rows of one shape (as many local coordinates, the same particles, as many entries of p read)
are compared with a candidate kernel all at once at two random points — every row's value
there from one Function of all the rows, the kernel's from ``map`` on the rows' own coordinates
and numbers (``_same_at_points``; where a row reads velocities, the kernel applied to the rows
in SX instead, ``_same``): a row is the kernel's instance when the values agree to the last
bit at both (the same operations in the same order always do; two different formulas never
do, barring a coincidence of measure zero — and a row that computes the same function another
way would be that function anyway) — so the work per row is a few array operations, linear
whatever the expressions' sharing; only rows that fit none of MAX_KINDS candidates are cut
out one by one.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .columns import sorted_unique, unique_rows
from .rest import MAX_PLACED, Positions, Rows

#: A repeated row or potential term becomes a mapped kernel from this many instances; fewer
#: stay in the one SX graph of the rest.
MIN_GROUP = 8


@dataclass
class Group:
    """Instances of one local function: ``local`` (SX in ``xl``, ``c``, t, p), ``index`` (d, n)
    the coordinates of each instance, ``sources`` (k, n) where each instance's value of ``c``
    comes from: an index into [p; ``constants``], ``place`` (n,) each instance's row
    (constraints), ``parts`` the particle of each local coordinate (0, 1, … in order of
    appearance)."""

    local: ca.SX
    xl: ca.SX
    c: ca.SX
    index: np.ndarray
    sources: np.ndarray
    constants: np.ndarray
    place: np.ndarray
    parts: tuple

    def data(self, P) -> ca.MX:
        """C_g (k, n): the instances' values of ``c`` from p (an MX) and the constants."""
        k, n = self.sources.shape
        if k == 0:
            return ca.MX(0, n)
        values = ca.vertcat(P, ca.DM(self.constants)) if self.constants.size else P
        return ca.reshape(values[self.sources.ravel(order="F").tolist()], k, n)


def summands(term) -> list:
    """The terms e_k of ``term`` = Σ ± e_k (sums, differences and negations unfolded)."""
    add, sub, neg = ca.OP_ADD, ca.OP_SUB, ca.OP_NEG
    out, stack = [], [(term if isinstance(term, ca.SX) else ca.SX(term), False)]
    while stack:
        e, negative = stack.pop()
        op = e.op()  # (one call per node: gravity's sum has 10,000 terms)
        if op == add:
            stack += [(e.dep(1), negative), (e.dep(0), negative)]
        elif op == sub:
            stack += [(e.dep(1), not negative), (e.dep(0), negative)]
        elif op == neg:
            stack.append((e.dep(0), not negative))
        else:
            out.append(-e if negative else e)
    return out


def lifted(function: ca.Function, c: ca.SX, parameters: int | None = None) -> tuple[ca.SX, list] | None:
    """The scalar output of the SX ``function`` with its k-th numeric constant, or k-th read
    of an entry of its input number ``parameters`` (p), replaced by ``c[k]`` (the same
    operations otherwise), and what each c[k] stands for: ``("c", value)`` or ``("p", j)``;
    None when ``c`` is too short or an operation cannot be rebuilt (a call)."""
    inputs = [function.sx_in(i) for i in range(function.n_in())]
    work: dict[int, ca.SX] = {}
    values: list[tuple] = []
    out = None
    for k in range(function.n_instructions()):
        op, args = function.instruction_id(k), function.instruction_input(k)
        res = function.instruction_output(k)
        if op == ca.OP_INPUT and args[0] == parameters:
            if len(values) == c.numel():
                return None
            work[res[0]] = c[len(values)]
            values.append(("p", int(args[1])))
        elif op == ca.OP_INPUT:
            work[res[0]] = inputs[args[0]][args[1]]
        elif op == ca.OP_OUTPUT:
            out = work[args[0]]
        elif op == ca.OP_CONST:
            if len(values) == c.numel():
                return None
            work[res[0]] = c[len(values)]
            values.append(("c", function.instruction_constant(k)))
        elif len(args) == 1 and op != ca.OP_CALL:
            work[res[0]] = ca.SX.unary(op, work[args[0]])
        elif len(args) == 2 and op != ca.OP_CALL:
            work[res[0]] = ca.SX.binary(op, work[args[0]], work[args[1]])
        else:
            return None
    return (out if out is not None else ca.SX(0)), values


#: Numbers lifted out of one row or term at most (more: the instance keeps its numbers).
MAX_CONSTANTS = 16


#: A bucket of rows with the same shape (local coordinates, particles, entries of p read) tries
#: this many different local functions by whole-bucket comparison; the rows left are cut out
#: one by one.
MAX_KINDS = 8
#: The points (x, t, p drawn from this seed) at which a candidate kernel's instances and the
#: rows are compared.
PROBE_SEED = 20_280


@dataclass
class _Kind:
    """One local function: ``expr`` in ``xl``, ``cs``, t (and p when it keeps its own entries of p:
    ``used``, else None), with ``numbers`` what each entry of cs stands for in the instance it
    was cut from: ("p", position in that instance's reads of p) or ("c", constant)."""

    key: tuple
    expr: ca.SX
    xl: ca.SX
    cs: ca.SX
    numbers: list
    used: tuple | None


def _kind(e, x, t, p, index, used, symbols: dict, c) -> _Kind | None:
    """The local function of the scalar ``e`` reading x[index] and p[used] (None: it depends on
    more, e.g. velocities)."""
    xl = symbols.setdefault(("xl", len(index)), ca.SX.sym("xl", len(index)))
    pl = symbols.setdefault(("pl", len(used)), ca.SX.sym("pl", len(used)))
    try:
        e_local = ca.substitute([e], [x[index.tolist()], p[used.tolist()]], [xl, pl])[0]
        local = ca.Function("kernel", [xl, t, pl], [e_local])
    except RuntimeError:  # it depends on more than x_l, t and p (velocities)
        return None
    parts = tuple(first_parts(index.tolist()))
    lift = lifted(local, c, parameters=2)
    if lift is None:  # the instance keeps its own entries of p
        expr = ca.substitute(local.sx_out(0), pl, p[used.tolist()])
        return _Kind((parts, tuple(used.tolist()), local.serialize()), expr, xl, ca.SX(0, 1), [],
                     tuple(used.tolist()))
    cs = symbols.setdefault(("c", len(lift[1])), ca.SX.sym("c", len(lift[1])))
    expr = ca.substitute(lift[0], c[:len(lift[1])], cs)
    key = (parts, ca.Function("kernel", [xl, cs, t], [expr]).serialize())
    return _Kind(key, expr, xl, cs, list(lift[1]), None)


def _numbers(kind: _Kind, reads: np.ndarray) -> list:
    """The numbers of instances whose reads of p are ``reads`` (n_p, n): per entry of cs
    ("p", indices into p (n,)) or ("c", value)."""
    return [("p", reads[value]) if what == "p" else ("c", value) for what, value in kind.numbers]


def _instances(kind: _Kind, p, reads: np.ndarray) -> tuple[list, ca.SX]:
    """``_numbers`` of the instances, and cs as SX (k, n)."""
    n = reads.shape[1]
    numbers = _numbers(kind, reads)
    if not numbers:
        return numbers, ca.SX(0, n)
    rows = [ca.reshape(p[value.tolist()], 1, n) if what == "p" else ca.SX(ca.DM.ones(1, n) * value)
            for what, value in numbers]
    return numbers, ca.vertcat(*rows)


def _reading_its_own(kind: _Kind, reads: np.ndarray, n: int) -> np.ndarray:
    """Which of n rows can be ``kind``: where it has its own entries of p, only the rows that
    read exactly those (``reads`` (n_p, n))."""
    same = np.ones(n, bool)
    if kind.used is not None and reads.size:
        same &= np.all(reads == np.asarray(kind.used)[:, None], axis=0)
    return same


def _same(kind: _Kind, exprs: list, ks: np.ndarray, index: np.ndarray, reads: np.ndarray,
          x, t, p) -> np.ndarray:
    """Which rows ``ks`` (coordinates ``index`` (d, n), reads of p ``reads`` (n_p, n)) are ``kind``
    applied to their own coordinates and numbers: the kernel applied to all of them at once
    and compared with the rows node by node."""
    same = _reading_its_own(kind, reads, len(ks))
    if not same.any():
        return same
    ks, index, reads = ks[same], index[:, same], reads[:, same]
    n = len(ks)
    X = ca.reshape(x[index.ravel(order="F").tolist()], index.shape[0], n)
    if kind.used is None:
        _, C = _instances(kind, p, reads)
        applied = ca.Function("kernel", [kind.xl, kind.cs, t], [kind.expr]).map(n)(X, C, t)
    else:
        applied = ca.Function("kernel", [kind.xl, t, p], [kind.expr]).map(n)(X, t, p)
    applied = ca.vec(applied)
    original = ca.vertcat(*(exprs.elements(ks) if hasattr(exprs, "elements") else [exprs[k] for k in ks]))
    # a Function of the entries of x and p the rows should read, not of the whole vectors (a
    # cloth's 30,000 + 69,000 symbols: 4 ms to build, and as much to convert each point)
    x_at = sorted_unique(index)
    p_at = sorted_unique(np.concatenate([reads.ravel(), np.asarray(kind.used or (), np.int64)]))
    try:
        both = ca.Function("probe", [x[x_at.tolist()], t, p[p_at.tolist()]], [applied, original])
    except RuntimeError:  # some row reads more than those, t and p (velocities): none is taken here
        return np.zeros_like(same)
    equal = np.ones(n, bool)
    for x0, t0, p0 in _probe_points(x, t, p):
        with np.errstate(all="ignore"):
            a, b = (np.asarray(o, float).ravel() for o in both(x0[x_at], t0, p0[p_at]))
        equal &= (a == b) & np.isfinite(a)  # (a value that is not finite proves nothing)
    out = np.zeros_like(same)
    out[np.flatnonzero(same)[equal]] = True
    return out


def _probe_points(x, t, p) -> list[tuple]:
    """The two points (x, t, p) at which candidate kernels and rows are compared (PROBE_SEED)."""
    return _points(x.numel(), p.numel())


@functools.lru_cache(maxsize=4)
def _points(n_x: int, n_p: int) -> list[tuple]:
    """``_probe_points`` for these sizes, drawn once (read only)."""
    rng = np.random.default_rng(PROBE_SEED)
    points = [(rng.uniform(0.5, 1.5, n_x), rng.uniform(0.1, 1.0), rng.uniform(0.5, 1.5, n_p))
              for _ in range(2)]
    for x0, _, p0 in points:
        x0.setflags(write=False)
        p0.setflags(write=False)
    return points


def _rows_function(stacked, x, t, p) -> Rows | None:
    """The rows ``stacked`` (one column) as ``Rows``; None when a row reads more than x, t and
    p (velocities): then each bucket's rows are compared by ``_same``."""
    read = ca.symvar(stacked)
    at = Positions(x, None, t, p).of(read) if len(read) <= MAX_PLACED else None
    x_at, _, p_at = at if at is not None else (np.arange(x.numel()), None, np.arange(p.numel()))
    try:
        return Rows(ca.Function("rows", [x[x_at.tolist()], t, p[p_at.tolist()]], [stacked]), x_at, p_at)
    except RuntimeError:
        return None


def _row_values(rows: Rows | None, x, t, p) -> list[np.ndarray] | None:
    """Every row at each probe point, from the Function of them all (``_rows_function``; None:
    None)."""
    if rows is None:
        return None
    with np.errstate(all="ignore"):
        return [np.asarray(rows.at(*point), float).ravel() for point in _probe_points(x, t, p)]


def _same_at_points(kind: _Kind, values: list[np.ndarray], ks: np.ndarray, index: np.ndarray,
                    reads: np.ndarray, x, t, p) -> np.ndarray:
    """``_same`` with the rows' values known at the probe points (``_row_values``): the kernel
    evaluated on the rows' own coordinates and numbers at those points, in numbers, and compared
    with them (the same operations on the same numbers: what ``_same`` compares, without
    writing the kernel out for every row in SX)."""
    same = _reading_its_own(kind, reads, len(ks))
    if not same.any():
        return same
    ks, index, reads = ks[same], index[:, same], reads[:, same]
    n = len(ks)
    if kind.used is None:
        kernel = ca.Function("kernel", [kind.xl, kind.cs, t], [kind.expr]).map(n)
    else:
        kernel = ca.Function("kernel", [kind.xl, t, p], [kind.expr]).map(n)
    numbers = [("p", reads[value]) if what == "p" else ("c", value) for what, value in kind.numbers]
    equal = np.ones(n, bool)
    for (x0, t0, p0), value in zip(_probe_points(x, t, p), values, strict=True):
        X = x0[index]  # (d, n): each row's coordinates as a column
        with np.errstate(all="ignore"):
            if kind.used is None:
                C = np.array([p0[v] if what == "p" else np.full(n, float(v)) for what, v in numbers]
                             ).reshape(len(numbers), n)
                a = np.asarray(kernel(X, C, t0), float).ravel()
            else:
                a = np.asarray(kernel(X, t0, p0), float).ravel()
        b = value[ks]
        equal &= (a == b) & np.isfinite(a)  # (a value that is not finite proves nothing)
    out = np.zeros_like(same)
    out[np.flatnonzero(same)[equal]] = True
    return out


def _buckets(colind: np.ndarray, row: np.ndarray, read_colind: np.ndarray) -> list[np.ndarray]:
    """Rows with the same shape: as many local coordinates, the same particle of each (numbered
    in order of appearance), as many entries of p read. In order of their first row."""
    counts, reads = np.diff(colind), np.diff(read_colind)
    out = []
    for d in sorted_unique(counts):
        ks = np.flatnonzero(counts == d)
        if d == 0:
            out.append(ks)
            continue
        particle = row[colind[ks][:, None] + np.arange(d)] // 3  # (n, d)
        first = np.argmax(particle[:, :, None] == particle[:, None, :], axis=2)  # first equal position
        if d * np.log2(max(d, 2)) + np.log2(int(reads[ks].max(initial=0)) + 2) < 62:
            # one integer per row: the reads, then the positions in base d (a 1-D unique is fast)
            key = reads[ks].astype(np.int64)
            for j in range(d):
                key = key * d + first[:, j]
            _, inverse = np.unique(key, return_inverse=True)
        else:
            _, inverse = np.unique(np.concatenate([first, reads[ks][:, None]], axis=1), axis=0,
                                   return_inverse=True)
        inverse = inverse.ravel()
        order = np.argsort(inverse, kind="stable")
        bounds = np.searchsorted(inverse[order], np.arange(int(inverse.max()) + 2))
        out += [ks[order[bounds[u]:bounds[u + 1]]] for u in range(len(bounds) - 1)]
    return sorted(out, key=lambda ks: ks[0])


def grouped(exprs: list, x, t, p, symbols: dict, batches=()) -> tuple[list[Group], list[int]]:
    """Groups (MIN_GROUP instances or more) of the scalar ``exprs`` by local function, their
    numbers lifted out as per-instance data, and the indices of the others (the rest).
    ``symbols``: (name, size) -> the local symbol of that size. ``batches``: (positions in
    ``exprs``, particles (n, s), entries of p (n, q)) of instances built by one formula
    (``model.symbols.Batch``), grouped from those arrays (``batched``).

    Rows of one shape (``_buckets``) are tried against the local function of their first row
    all at once (``_same``); only rows that match none of MAX_KINDS functions are cut out one
    by one, so the work per row is a few array operations."""
    if not exprs:
        return [], []
    found: dict[tuple, list] = {}
    c = ca.SX.sym("c", MAX_CONSTANTS)
    claimed = batched(exprs, batches, x, t, p, symbols, c, found)
    if claimed.any():
        others = np.flatnonzero(~claimed)
        rest = _discovered([exprs[k] for k in others], x, t, p, symbols, c, found, others)
    else:
        rest = _discovered(exprs, x, t, p, symbols, c, found, None)
    return _groups(found, rest, p)


def batched(exprs: list, batches, x, t, p, symbols: dict, c, found: dict) -> np.ndarray:
    """Group the instances of ``batches`` (positions, particles, entries of p) into ``found``
    (kind key -> [kind, chunks]) without comparing every row: the first instance's local
    function (``_kind``) and its coordinates and reads of p expressed through the batch's
    particles and entries, applied to every instance by array operations; instances whose
    coordinates or reads would not come in the same (ascending) order are left to discovery,
    and so is a whole batch where a sample of its instances is not that function applied to
    them (``_same``). Which of ``exprs`` were grouped here."""
    claimed = np.zeros(len(exprs), bool)
    for positions, particles, numbers in batches:
        positions = np.asarray(positions, np.int64)
        if len(positions) < MIN_GROUP or claimed[positions].any():
            continue
        first = exprs[positions[0]]
        index0, reads0 = _read_by(first, x, t, p, particles[0], numbers[0])
        # each local coordinate as (the batch's particle slot, the component); each read as a slot
        slot = [np.flatnonzero(particles[0] == i // 3) for i in index0]
        which = [np.flatnonzero(numbers[0] == r) for r in reads0]
        if not len(index0) or any(len(s) != 1 for s in (*slot, *which)):
            continue
        index = (3 * particles[:, [s[0] for s in slot]] + index0 % 3).T  # (d, n)
        reads = numbers[:, [w[0] for w in which]].T  # (n_p, n)
        ordered = np.all(np.diff(index, axis=0) > 0, axis=0) & np.all(np.diff(reads, axis=0) > 0, axis=0)
        kind = _kind(first, x, t, p, index[:, 0], reads[:, 0], symbols, c) if ordered[0] else None
        if kind is None or np.count_nonzero(ordered) < MIN_GROUP:
            continue
        members = np.flatnonzero(ordered)
        sample = _spread(members)
        if not _same(kind, exprs, positions[sample], index[:, sample], reads[:, sample], x, t, p).all():
            continue
        # instances whose coordinates come in another order (a spring from b to a): the kernel
        # on their ascending coordinates, where a sample of each order shows it is the row (the
        # formula is then symmetric under that exchange: discovery would find them the same)
        others = np.flatnonzero(~ordered)
        if len(others):
            order = np.concatenate([np.argsort(index[:, others], axis=0),
                                    np.argsort(reads[:, others], axis=0)])
            index[:, others] = np.sort(index[:, others], axis=0)
            reads[:, others] = np.sort(reads[:, others], axis=0)
            distinct = np.all(np.diff(index[:, others], axis=0) > 0, axis=0) & np.all(
                np.diff(reads[:, others], axis=0) > 0, axis=0)
            others, order = others[distinct], order[:, distinct]
        if len(others):
            _, pattern = unique_rows(order.T)  # (np.unique(order, axis=1): 10 ms on a cloth's springs)
            for u in range(int(pattern.max()) + 1):
                these = others[pattern.ravel() == u]
                sample = _spread(these)
                if _same(kind, exprs, positions[sample], index[:, sample], reads[:, sample], x, t, p).all():
                    members = np.concatenate([members, these])
            members = np.sort(members)
        numbers_of = _numbers(kind, reads[:, members])
        found.setdefault(kind.key, [kind, []])[1].append(
            (positions[members], index[:, members], (len(members), numbers_of)))
        claimed[positions[members]] = True
    return claimed


def _read_by(first, x, t, p, particles: np.ndarray, numbers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The positions in x and in p (ascending) that the scalar ``first`` reads: looked for among
    the coordinates of ``particles`` and the entries ``numbers`` of p (its batch's), where every
    symbol it reads is among those and t (a Jacobian's pattern costs CasADi time in proportion
    to the vector: 2-4 ms for a cloth's 30,000 coordinates and 69,000 entries of p), else in
    the whole vectors."""
    xs = sorted_unique(3 * np.asarray(particles, np.int64)[:, None] + np.arange(3))
    ps = sorted_unique(np.asarray(numbers, np.int64))
    xs, ps = xs[(xs >= 0) & (xs < x.numel())], ps[(ps >= 0) & (ps < p.numel())]
    index0 = xs[np.array(ca.jacobian_sparsity(first, x[xs.tolist()]).get_col(), np.int64)] if len(xs) else xs
    reads0 = ps[np.array(ca.jacobian_sparsity(first, p[ps.tolist()]).get_col(), np.int64)] if len(ps) else ps
    if len(ca.symvar(first)) == len(index0) + len(reads0) + ca.depends_on(first, t):
        return index0, reads0
    index0 = np.array(ca.jacobian_sparsity(first, x).get_col(), np.int64)
    return index0, np.array(ca.jacobian_sparsity(first, p).get_col(), np.int64) if p.numel() else index0[:0]


#: Instances of a batch checked against its rows (spread evenly, the first and last among them).
BATCH_SAMPLE = 8


def _spread(ids: np.ndarray) -> np.ndarray:
    """BATCH_SAMPLE of ``ids`` (all when fewer), spread evenly from the first to the last."""
    return ids[sorted_unique(np.linspace(0, len(ids) - 1, BATCH_SAMPLE).round().astype(np.int64))]


def _discovered(exprs: list, x, t, p, symbols: dict, c, found: dict, places) -> list[int]:
    """Group ``exprs`` by comparing them with candidate kernels (into ``found``, their
    positions ``places[k]``; None: k) and return the positions of the rest."""
    if not exprs:
        return []
    place = (lambda ks: ks) if places is None else (lambda ks: places[ks])
    stacked = exprs.column() if hasattr(exprs, "column") else ca.vertcat(*exprs)  # (model.symbols.Stacked)
    if stacked.numel() != len(exprs) or not stacked.is_column():  # (one check, not one per row)
        raise ValueError("the rows and terms of the mapped build are scalars")
    rows = _rows_function(stacked, x, t, p)

    def transposed(pattern):
        return np.array(pattern.T.colind(), np.int64), np.array(pattern.T.row(), np.int64)
    colind, row = transposed(ca.jacobian_sparsity(stacked, x)) if rows is None else rows.reads(0)
    # the entries of p each row reads: a row's kernel takes those alone (pl), so that its work
    # does not grow with the length of p (one number per rod of a 10,000-link chain)
    if p.numel():
        read_colind, read_row = (transposed(ca.jacobian_sparsity(stacked, p)) if rows is None
                                 else rows.reads(2))
    else:
        read_colind, read_row = np.zeros(len(exprs) + 1, np.int64), np.zeros(0, np.int64)
    values = _row_values(rows, x, t, p)  # (None: each bucket compared in SX)
    rest = []

    def gathered(ks, colind, row, width):  # (width, len(ks)): each row's entries as a column
        if not width:
            return np.zeros((0, len(ks)), np.int64)
        return row[colind[ks][None, :] + np.arange(width)[:, None]]

    for ks in _buckets(colind, row, read_colind):
        d, n_p = int(colind[ks[0] + 1] - colind[ks[0]]), int(read_colind[ks[0] + 1] - read_colind[ks[0]])
        if d == 0:
            rest += place(ks).tolist()
            continue
        index, reads = gathered(ks, colind, row, d), gathered(ks, read_colind, read_row, n_p)
        left = np.ones(len(ks), bool)
        for _ in range(MAX_KINDS):
            if not left.any():
                break
            first = int(np.argmax(left))
            kind = _kind(exprs[ks[first]], x, t, p, index[:, first], reads[:, first], symbols, c)
            if kind is None:
                rest.append(int(place(ks[first])))
                left[first] = False
                continue
            todo = np.flatnonzero(left)
            same = (_same(kind, exprs, ks[todo], index[:, todo], reads[:, todo], x, t, p) if values is None
                    else _same_at_points(kind, values, ks[todo], index[:, todo], reads[:, todo], x, t, p))
            same[0] = True  # (the row it was cut from, whatever the comparison says)
            members = todo[same]
            numbers = _numbers(kind, reads[:, members])
            chunk = (place(ks[members]), index[:, members], (len(members), numbers))
            found.setdefault(kind.key, [kind, []])[1].append(chunk)
            left[members] = False
        for i in np.flatnonzero(left):  # one by one
            kind = _kind(exprs[ks[i]], x, t, p, index[:, i], reads[:, i], symbols, c)
            if kind is None:
                rest.append(int(place(ks[i])))
                continue
            numbers = _numbers(kind, reads[:, [i]])
            found.setdefault(kind.key, [kind, []])[1].append((place(ks[[i]]), index[:, [i]], (1, numbers)))
    return rest


def _groups(found: dict, rest: list, p) -> tuple[list[Group], list[int]]:
    """The Groups of ``found`` (kind key -> [kind, chunks of instances]) with MIN_GROUP
    instances or more, sorted by their first row, and the rest (sorted)."""
    groups = []
    for kind, chunks in found.values():
        place = np.concatenate([k for k, _, _ in chunks])
        if len(place) < MIN_GROUP:
            rest += place.tolist()
            continue
        order = np.argsort(place, kind="stable")  # instances in the order of their rows
        index = np.concatenate([i for _, i, _ in chunks], axis=1)[:, order]
        sources, constants = _sources([numbers for _, _, numbers in chunks], p.numel())
        groups.append(Group(kind.expr, kind.xl, kind.cs, index, sources[:, order], constants, place[order],
                             kind.key[0]))
    groups.sort(key=lambda g: g.place[0])
    return groups, sorted(rest)


def first_parts(index) -> list[int]:
    """The particle of each local coordinate, numbered 0, 1, … in order of appearance."""
    first: dict[int, int] = {}
    return [first.setdefault(i // 3, len(first)) for i in index]


def _sources(chunks: list, n_p: int) -> tuple[np.ndarray, np.ndarray]:
    """``(sources, constants)`` of a group from its chunks of instances, each ``(n, numbers)``
    with ``numbers`` a list over the lifted values of ("p", indices into p (n,)) or ("c",
    value): for each lifted value (k) of each instance its index into [p (n_p entries);
    constants], and the constants (each distinct value once)."""
    constants: dict[float, int] = {}
    blocks = []
    for n, numbers in chunks:
        rows = [np.asarray(value, np.int64) if what == "p"
                else np.full(n, n_p + constants.setdefault(float(value), len(constants)), np.int64)
                for what, value in numbers]
        blocks.append(np.stack(rows) if rows else np.zeros((0, n), np.int64))
    return np.concatenate(blocks, axis=1), np.array(list(constants), dtype=float)
