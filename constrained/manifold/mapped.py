"""The mapped build: repeated constraint rows and potential terms as ONE CasADi kernel each,
applied with ``Function.map`` over index columns, so that generated code holds each kind once.

A chain's rods are one formula |x_a − x_b| − L applied to many pairs of particles; gravity is
one term −m g·x_i per particle; an all-pairs potential one V(r_ij) per pair. The Structure
writes every instance out in one SX graph, so its generated C code — and the C compiler's
time, which grows faster than the length of a function — grows with N. Here every row f_k
of the constraints and every summand V_k of V = Σ_k V_k is cut out of the Structure's
expressions (``Structure.expressions``) with the coordinates it depends on, I_k (ascending),
as a local function of x_l = x[I_k], and its numbers are lifted out (``lifted``: the k-th
constant or entry of p it reads becomes c_k), giving φ_k(x_l, c, t). Instances whose lifted
functions are the same (the same operations: equal serializations, and the same split of x_l
into particles) form a group g, whatever their numbers (rods of different lengths, particles
of different masses: entries of p, constrained.lifting); a group of MIN_GROUP instances or
more becomes one SX kernel evaluated by ``map`` on the columns X_g = [x[I_1], …, x[I_n]] (a
gather: index data) and C_g = [c_1, …, c_n], gathered from [p; the constants] (index data):

    f[r_k] = φ_g(x_l, c_k, t, p),   J[r_k, I_k] = ∂φ_g/∂x_l,      f_t[r_k] = ∂φ_g/∂t,
    γ[r_k] = ∂w/∂x_l · v_l + ∂w/∂t  with  w = J_l v_l + f_t,
    s[r_k] = max over the row's particles q of |∂φ_g/∂x_q|    (the row scale, as manifold's),
    F = F_rest − S · vec([∇V_g(X_g)]_g)    (S: the 0/1 matrix scattering local gradients).

The rest (rows and summands of small groups, the other force slots) is one SX graph built as
the Structure builds it (``model.forces``). J's sparsity, the permutations back to scene
order and S are data of the generated code, not code: its size does not grow with N.
The numbers are those of the Structure's Functions up to the order of floating-point sums
(tests/test_mapped.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..model.cache import ParametricView, built_once, structure_cache
from ..model.structure import Model, Structure, forces
from .graph import acceleration_graph

#: A repeated row or potential term becomes a mapped kernel from this many instances; fewer
#: stay in the one SX graph of the rest.
MIN_GROUP = 8
#: dopri's compiled step loop is built on the mapped Functions from this many coordinates
#: (a plain Model, not a held row subset). Below, the unrolled SX graph compiles in a second
#: or two and runs faster (a 16-link chain's loop: 0.70 against 0.81 ms); from about 48 links
#: a chain runs as fast mapped, from about 100 faster. An all-pairs potential runs slower
#: mapped (about 1.6x: gathers and scatters), but the unrolled graph of its N²/2 terms takes
#: the C compiler minutes (docs/performance.md, "Compile time").
MAPPED_FROM = 150
#: The Functions the mapped build provides (the others are the Structure's).
NAMES = ("constraint", "jacobian", "velocity_terms", "dynamics", "row_scales")
#: Their constraint outputs and whether they take the velocities.
_OUTPUTS = {"constraint": (("f",), False), "jacobian": (("f", "J"), False),
            "velocity_terms": (("J", "f_t"), False), "dynamics": (("J", "gamma"), True),
            "row_scales": (("scale",), False)}


@dataclass
class _Group:
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
    out, stack = [], [(ca.SX(term), False)]
    while stack:
        e, negative = stack.pop()
        if e.is_op(ca.OP_ADD):
            stack += [(e.dep(1), negative), (e.dep(0), negative)]
        elif e.is_op(ca.OP_SUB):
            stack += [(e.dep(1), not negative), (e.dep(0), negative)]
        elif e.is_op(ca.OP_NEG):
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
#: How deep two expressions are compared node by node (``casadi.is_equal``).
EQUAL_DEPTH = 64


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


def _instances(kind: _Kind, p, reads: np.ndarray) -> tuple[list, ca.SX]:
    """The numbers of instances whose reads of p are ``reads`` (n_p, n): per entry of cs
    ("p", indices into p (n,)) or ("c", value); and cs as SX (k, n)."""
    n = reads.shape[1]
    numbers = [("p", reads[value]) if what == "p" else ("c", value) for what, value in kind.numbers]
    if not numbers:
        return numbers, ca.SX(0, n)
    rows = [ca.reshape(p[value.tolist()], 1, n) if what == "p" else ca.SX(ca.DM.ones(1, n) * value)
            for what, value in numbers]
    return numbers, ca.vertcat(*rows)


def _same(kind: _Kind, exprs: list, ks: np.ndarray, index: np.ndarray, reads: np.ndarray,
          x, t, p) -> np.ndarray:
    """Which rows ``ks`` (coordinates ``index`` (d, n), reads of p ``reads`` (n_p, n)) are ``kind``
    applied to their own coordinates and numbers: the kernel applied to all of them at once
    and compared with the rows node by node."""
    same = np.ones(len(ks), bool)
    if kind.used is not None:  # its own entries of p: only rows reading exactly those
        same &= np.all(reads == np.asarray(kind.used)[:, None], axis=0) if reads.size else same
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
    original = ca.vertcat(*[exprs[k] for k in ks])
    if ca.is_equal(applied, original, EQUAL_DEPTH):
        return same
    equal = np.array([ca.is_equal(applied[i], original[i], EQUAL_DEPTH) for i in range(n)])
    out = np.zeros_like(same)
    out[np.flatnonzero(same)[equal]] = True
    return out


def _buckets(colind: np.ndarray, row: np.ndarray, read_colind: np.ndarray) -> list[np.ndarray]:
    """Rows with the same shape: as many local coordinates, the same particle of each (numbered
    in order of appearance), as many entries of p read. In order of their first row."""
    counts, reads = np.diff(colind), np.diff(read_colind)
    out = []
    for d in np.unique(counts):
        ks = np.flatnonzero(counts == d)
        if d == 0:
            out.append(ks)
            continue
        particle = row[colind[ks][:, None] + np.arange(d)] // 3  # (n, d)
        first = np.argmax(particle[:, :, None] == particle[:, None, :], axis=2)  # first equal position
        key = np.concatenate([first, reads[ks][:, None]], axis=1)
        _, inverse = np.unique(key, axis=0, return_inverse=True)
        out += [ks[inverse.ravel() == u] for u in range(int(inverse.max()) + 1)]
    return sorted(out, key=lambda ks: ks[0])


def _grouped(exprs: list, x, t, p, symbols: dict) -> tuple[list[_Group], list[int]]:
    """Groups (MIN_GROUP instances or more) of the scalar ``exprs`` by local function, their
    numbers lifted out as per-instance data, and the indices of the others (the rest).
    ``symbols``: (name, size) -> the local symbol of that size.

    Rows of one shape (``_buckets``) are tried against the local function of their first row
    all at once (``_same``); only rows that match none of MAX_KINDS functions are cut out one
    by one, so the work per row is a few array operations."""
    if not exprs:
        return [], []
    if any(e.numel() != 1 for e in exprs):
        raise ValueError("the rows and terms of the mapped build are scalars")
    stacked = ca.vertcat(*exprs)
    pattern = ca.jacobian_sparsity(stacked, x).T
    colind, row = np.array(pattern.colind(), np.int64), np.array(pattern.row(), np.int64)
    # the entries of p each row reads: a row's kernel takes those alone (pl), so that its work
    # does not grow with the length of p (one number per rod of a 10,000-link chain)
    if p.numel():
        reads = ca.jacobian_sparsity(stacked, p).T
        read_colind, read_row = np.array(reads.colind(), np.int64), np.array(reads.row(), np.int64)
    else:
        read_colind, read_row = np.zeros(len(exprs) + 1, np.int64), np.zeros(0, np.int64)
    c = ca.SX.sym("c", MAX_CONSTANTS)
    found: dict[tuple, list] = {}
    rest = []

    def gathered(ks, colind, row, width):  # (width, len(ks)): each row's entries as a column
        if not width:
            return np.zeros((0, len(ks)), np.int64)
        return row[colind[ks][None, :] + np.arange(width)[:, None]]

    for ks in _buckets(colind, row, read_colind):
        d, n_p = int(colind[ks[0] + 1] - colind[ks[0]]), int(read_colind[ks[0] + 1] - read_colind[ks[0]])
        if d == 0:
            rest += ks.tolist()
            continue
        index, reads = gathered(ks, colind, row, d), gathered(ks, read_colind, read_row, n_p)
        left = np.ones(len(ks), bool)
        for _ in range(MAX_KINDS):
            if not left.any():
                break
            first = int(np.argmax(left))
            kind = _kind(exprs[ks[first]], x, t, p, index[:, first], reads[:, first], symbols, c)
            if kind is None:
                rest.append(int(ks[first]))
                left[first] = False
                continue
            todo = np.flatnonzero(left)
            same = _same(kind, exprs, ks[todo], index[:, todo], reads[:, todo], x, t, p)
            same[0] = True  # (the row it was cut from, whatever the comparison says)
            members = todo[same]
            numbers, _ = _instances(kind, p, reads[:, members])
            chunk = (ks[members], index[:, members], (len(members), numbers))
            found.setdefault(kind.key, [kind, []])[1].append(chunk)
            left[members] = False
        for i in np.flatnonzero(left):  # one by one
            kind = _kind(exprs[ks[i]], x, t, p, index[:, i], reads[:, i], symbols, c)
            if kind is None:
                rest.append(int(ks[i]))
                continue
            numbers, _ = _instances(kind, p, reads[:, [i]])
            found.setdefault(kind.key, [kind, []])[1].append((ks[[i]], index[:, [i]], (1, numbers)))
    groups = []
    for kind, chunks in found.values():
        place = np.concatenate([k for k, _, _ in chunks])
        if len(place) < MIN_GROUP:
            rest += place.tolist()
            continue
        order = np.argsort(place, kind="stable")  # instances in the order of their rows
        index = np.concatenate([i for _, i, _ in chunks], axis=1)[:, order]
        sources, constants = _sources([numbers for _, _, numbers in chunks], p.numel())
        groups.append(_Group(kind.expr, kind.xl, kind.cs, index, sources[:, order], constants, place[order],
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


def _row_scale(J_row, parts) -> ca.SX:
    """max over the row's particles q of |J_q| (1 when it vanishes): ``row_scales_expr`` of
    one row whose entries ``J_row`` belong to the particles ``parts``."""
    norms = ca.SX(0)
    for q in sorted(set(parts)):
        block = ca.vertcat(*[J_row[k] for k, pk in enumerate(parts) if pk == q])
        norm = ca.sqrt(ca.sum1(block * block))
        norms = norm if q == min(parts) else ca.fmax(norms, norm)
    return ca.if_else(norms > 0, norms, 1.0)


def _row_terms(f, x, v, t, particle=None) -> dict:
    """f, J = ∂f/∂x, f_t, γ and (given ``particle``: coordinate -> particle) the row scales
    of the rows ``f``, as the Structure forms them."""
    J = ca.jacobian(f, x)
    rheonomic = ca.depends_on(f, t)
    f_t = ca.jacobian(f, t) if rheonomic else ca.SX(f.numel(), 1)
    c = ca.mtimes(J, v) + f_t
    gamma = ca.jtimes(c, x, v) + (ca.jacobian(c, t) if rheonomic else 0)
    out = {"f": f, "J": J, "f_t": f_t, "gamma": gamma}
    if particle is not None:
        scales = [_row_scale(J[k, :].nonzeros(), [particle(c) for c in J[k, :].sparsity().get_col()])
                  for k in range(f.numel())]
        out["scale"] = ca.vertcat(*scales) if scales else ca.SX(0, 1)
    return out


class MappedBuild:
    """The mapped Functions of a Structure (``function(name)``, names in ``NAMES``, with the
    signatures of the Structure's and ``row_scales(x, t, p) -> s``), built once per structure
    (``mapped_build``)."""

    def __init__(self, structure: Structure):
        e = structure.expressions
        self.structure, self.e = structure, e
        self.n3, self.n_rows = structure.n_coordinates, structure.n_constraints
        symbols: dict[int, ca.SX] = {}
        self.rows, rest_rows = _grouped(e.rows, e.x, e.t, e.p, symbols)
        self.rest_place = np.array(rest_rows, dtype=np.int64)
        terms = [s for term in e.slots["potential"] for s in summands(term)]
        self.terms, rest_terms = _grouped(terms, e.x, e.t, e.p, symbols)
        self.rest_slots = {**e.slots, "potential": [terms[k] for k in rest_terms]}
        self._functions: dict[str, ca.Function] = {}

    @property
    def mapped_instances(self) -> int:
        """How many rows and potential terms the kernels evaluate."""
        return sum(g.index.shape[1] for g in (*self.rows, *self.terms))

    # --- the SX pieces: one kernel per group, the rest -------------------------------------
    def _rest(self, outputs: tuple, with_v: bool, with_forces: bool) -> ca.Function:
        e = self.e
        f = ca.vertcat(*[e.rows[k] for k in self.rest_place]) if len(self.rest_place) else ca.SX(0, 1)
        terms = _row_terms(f, e.x, e.v, e.t, lambda i: i // 3)
        terms["J"] = ca.vertcat(*terms["J"].nonzeros()) if terms["J"].nnz() else ca.SX(0, 1)
        out = [terms[k] for k in outputs]
        if with_forces:
            out.append(ca.sparsify(forces(self.rest_slots, e.x, e.v, e.t)[0]))
        inputs = [e.x, e.v, e.t, e.p] if with_v else [e.x, e.t, e.p]
        return ca.Function("rest", inputs, out)

    def _kernel(self, g: _Group, outputs: tuple, with_v: bool, name: str) -> ca.Function:
        e, xl = self.e, g.xl
        vl = ca.SX.sym("vl", xl.numel())
        terms = _row_terms(g.local, xl, vl, e.t, lambda i: g.parts[i])
        out = [ca.densify(terms[k].T if k == "J" else terms[k]) for k in outputs]
        inputs = [xl, vl, g.c, e.t, self._p(g)] if with_v else [xl, g.c, e.t, self._p(g)]
        kernel = ca.Function(f"{name}_kernel", inputs, out)
        shared = [len(inputs) - 2, len(inputs) - 1]  # t and p: the same for every instance
        return kernel.map(f"{name}_map", "serial", g.index.shape[1], shared, [])

    def _p(self, g: _Group) -> ca.SX:
        """The kernel's input p: the Structure's, or an empty one when every entry of p the
        kernel reads was lifted into its data (the usual case: the map then passes no p)."""
        return self.e.p if ca.depends_on(g.local, self.e.p) else ca.SX.sym("p", 0)

    def _p_argument(self, g: _Group, P):
        return P if ca.depends_on(g.local, self.e.p) else ca.MX(0, 1)

    def _potential_kernel(self, g: _Group, name: str) -> ca.Function:
        e = self.e
        gradient = ca.densify(ca.gradient(g.local, g.xl))
        kernel = ca.Function(f"{name}_kernel", [g.xl, g.c, e.t, self._p(g)], [gradient])
        return kernel.map(f"{name}_map", "serial", g.index.shape[1], [2, 3], [])

    # --- the assembled MX Functions --------------------------------------------------------
    def function(self, name: str) -> ca.Function:
        """The mapped Function ``name`` (``NAMES``): the Structure's inputs, then p."""
        if name not in self._functions:
            self._functions[name] = self._build(name)
        return self._functions[name]

    def _build(self, name: str) -> ca.Function:
        outputs, with_v = _OUTPUTS[name]
        n3 = self.n3
        X, V, T, P = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t"), ca.MX.sym("p", self.e.p.numel())
        dynamics = name == "dynamics"
        rest = self._rest(outputs, with_v, dynamics)(*([X, V, T, P] if with_v else [X, T, P]))
        rest = rest if isinstance(rest, list | tuple) else [rest]
        pieces = {k: [rest[i]] for i, k in enumerate(outputs)}
        for j, g in enumerate(self.rows):
            velocities = [_gather(V, g.index)] if with_v else []
            gather = [_gather(X, g.index), *velocities, g.data(P), T, self._p_argument(g, P)]
            out = self._kernel(g, outputs, with_v, f"{name}_{j}")(*gather)
            for k, o in zip(outputs, out if isinstance(out, list | tuple) else [out], strict=True):
                pieces[k].append(ca.vec(o))
        result = {k: self._rows(pieces[k]) for k in outputs if k != "J"}
        if "J" in outputs:
            result["J"] = self._jacobian(ca.vertcat(*pieces["J"]))
        names = {"f": "f", "J": "J", "f_t": "f_t", "gamma": "gamma", "scale": "s"}
        outs, out_names = [result[k] for k in outputs], [names[k] for k in outputs]
        if name == "velocity_terms" and not self.structure.rheonomic:
            outs[1] = ca.MX(self.n_rows, 1)  # structurally zero, as the Structure's
        if dynamics:
            gradients = [ca.vec(self._potential_kernel(g, f"potential_{j}")(
                _gather(X, g.index), g.data(P), T, self._p_argument(g, P))) for j, g in enumerate(self.terms)]
            F = rest[-1]
            if gradients:
                F = F - ca.mtimes(self._scatter(), ca.vertcat(*gradients))
            outs, out_names = [ca.densify(F), *outs], ["F", *out_names]
        inputs, in_names = ([X, V, T, P], ["x", "v", "t", "p"]) if with_v else ([X, T, P], ["x", "t", "p"])
        return ca.Function(name, inputs, outs, in_names, out_names)

    def _rows(self, pieces: list) -> ca.MX:
        """Values of the rest's rows then each group's, put back in scene order (dense)."""
        if not self.n_rows:
            return ca.MX(0, 1)
        place = np.concatenate([self.rest_place, *[g.place for g in self.rows]])
        values = ca.vertcat(*[ca.densify(p) for p in pieces])
        order = np.argsort(place, kind="stable")
        return values if np.array_equal(order, np.arange(len(order))) else values[order.tolist()]

    def _jacobian(self, nonzeros) -> ca.MX:
        """J (C, 3N) from the rest's nonzeros and the groups' local gradients (column-major)."""
        sparsity, order = self._jacobian_pattern()
        return ca.MX(sparsity, nonzeros[order.tolist()]) if sparsity.nnz() else ca.MX(self.n_rows, self.n3)

    def _jacobian_pattern(self):
        if not hasattr(self, "_pattern"):
            e = self.e
            f = ca.vertcat(*[e.rows[k] for k in self.rest_place]) if len(self.rest_place) else ca.SX(0, 1)
            r, c = ca.jacobian(f, e.x).sparsity().get_triplet()
            rows = [self.rest_place[np.asarray(r, dtype=np.int64)]]
            cols = [np.asarray(c, dtype=np.int64)]
            for g in self.rows:
                d = g.index.shape[0]
                rows.append(np.repeat(g.place, d))
                cols.append(g.index.ravel(order="F"))
            rows, cols = np.concatenate(rows), np.concatenate(cols)
            order = np.lexsort((rows, cols))  # compressed-column order
            sparsity = ca.Sparsity.triplet(self.n_rows, self.n3, rows[order].tolist(), cols[order].tolist())
            self._pattern = (sparsity, order)
        return self._pattern

    def _scatter(self) -> ca.DM:
        """S: column j of the stacked local gradients onto its coordinate (3N, Σ d·n)."""
        cols = np.concatenate([g.index.ravel(order="F") for g in self.terms])
        sparsity = ca.Sparsity.triplet(self.n3, len(cols), cols.tolist(), list(range(len(cols))))
        return ca.DM(sparsity, 1.0)


def _gather(X, index: np.ndarray) -> ca.MX:
    """The columns x[I_k] of ``index`` (d, n) as a (d, n) matrix."""
    return ca.reshape(X[index.ravel(order="F").tolist()], index.shape[0], index.shape[1])


def mapped_build(structure: Structure) -> MappedBuild:
    """The structure's MappedBuild, built once and kept beside it."""
    return built_once(structure, "mapped build", lambda: MappedBuild(structure))


def applies(model: Model) -> bool:
    """Whether step loops of ``model`` use the mapped build: a plain Model (not a held row
    subset) of MAPPED_FROM coordinates or more."""
    return getattr(model, "rows", None) is None and model.n_coordinates >= MAPPED_FROM


class MappedView(ParametricView):
    """``ParametricView`` on the mapped Functions (``NAMES``; the others are the Structure's),
    with ``row_scales(x, t)`` for ``projection_graph``'s residual."""

    def __init__(self, model: Model, P):
        super().__init__(model, P)
        self._mapped = mapped_build(model.structure)

    def _call(self, name: str, *args):
        if name in NAMES:
            return self._mapped.function(name)(*args, self.P)
        return super()._call(name, *args)

    def row_scales(self, X, T):
        return self._call("row_scales", X, T)


def acceleration_function(model: Model, rows=None) -> ca.Function:
    """``(x, v, t, p) -> (a, λ_rows)`` on the mapped Functions (sparse LDLᵀ of J M⁻¹ Jᵀ,
    ``manifold.acceleration_graph``), built once per structure and row set."""
    cache, prefix = structure_cache(model)
    key = (*prefix, "acceleration", rows, "mapped")
    if key not in cache:
        n3 = model.n_coordinates
        X, V, T = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
        P = ca.MX.sym("p", len(model.parameter_vector))
        a, lam = acceleration_graph(MappedView(model, P), X, V, T, rows=rows, linsol="ldl")
        cache[key] = ca.Function("acceleration", [X, V, T, P], [a, lam])
    return cache[key]
