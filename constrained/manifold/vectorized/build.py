"""The vectorized build: the groups of ``constrained.manifold.mapped`` (each repeated row or
potential term one SX kernel, with index and number data) evaluated as whole columns, and the
products with J the KKT solve needs written on J's nonzeros by index data.

J is held as *streams*: for group g and local coordinate j the column J_gj (n_g, 1) of
∂φ_g/∂x_l[j] over the group's instances, at rows ``place_g`` and columns ``index_g[j]``;
the rows the kernels do not cover (the rest) give one more stream, their nonzeros. Then

    (J y)_r   = Σ over the entries (r, c) of J_rc y_c            (Summation by rows)
    (Jᵀ λ)_c  = Σ over the entries (r, c) of J_rc λ_r            (Summation by columns)
    A = J M⁻¹ Jᵀ:  A_rs = Σ over the coordinates c of J_rc J_sc / m_c,

the last from the products of every pair of entries in one column (the diagonal from each
entry with itself; each off-diagonal product once, summed into A_rs and A_sr), grouped by the
pair of streams they come from, so that a chain's thousands of products are a few column
operations. The numbers are those of the mapped and unrolled builds up to the order of
floating-point sums (tests/test_vectorized.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np

from ...model.cache import built_once
from ...model.structure import Structure, forces
from ..mapped import _row_terms, mapped_build
from .columns import Summation, binary, on_columns, shared, sorted_unique, take
from .fused import fused_groups
from .products import compiled_products
from .rest import Positions, RestFunction, rest_function
from .sums import summation_loop

#: The outputs of a row kernel, in order ("J" is d entries, the others one each).
ROW_OUTPUTS = ("f", "J", "f_t", "gamma", "scale")
#: What an acceleration reads of the rows.
DYNAMICS = ("J", "gamma")


@dataclass
class Jacobian:
    """J at one state as streams (MX columns) over the build's index data."""

    build: VectorizedBuild
    streams: list

    def _products(self):
        """The build's products in C (``products``) when they apply to these streams, else None."""
        loops = self.build.products()
        if loops is None or any(J.nnz() != J.numel() for J in self.streams):
            return None
        return loops

    def times(self, y):
        """J y (C,) for a column y (3N,)."""
        b, loops = self.build, self._products()
        if loops is not None:
            return shared(("J y", *map(hash, self.streams), hash(y)), lambda: loops.times(self.streams, y),
                          *self.streams, y)
        return b.by_rows([_times(J, take(y, c)) for J, c in zip(self.streams, b.cols, strict=True)])

    def transpose_times(self, lam):
        """Jᵀ λ (3N,) for a column λ (C,)."""
        b, loops = self.build, self._products()
        if loops is not None:
            return shared(("J' y", *map(hash, self.streams), hash(lam)),
                          lambda: loops.transpose_times(self.streams, lam), *self.streams, lam)
        return b.by_cols([_times(J, take(lam, r)) for J, r in zip(self.streams, b.rows, strict=True)])

    def gram(self, inverse_masses):
        """A = J M⁻¹ Jᵀ (C, C), sparse, for the inverse masses per coordinate (3N,)."""
        return self.build.gram(self.streams, _column(inverse_masses))

    def solve(self, inverse_masses, B):
        """Λ with (J M⁻¹ Jᵀ) Λ = B (C, k) by CasADi's sparse LDLᵀ. Rows with one coordinate
        each (``VectorizedBuild``'s ``single``: a plane along an axis, a pin's) are eliminated
        first: with S those rows, c_s their coordinates, j_s their entries, R the others,

            Σ_{c ∉ {c_s}} J_rc J_r'c / m_c · Λ_R = B_R − Σ_s J_{r c_s} B_s / j_s,
            Λ_s = (m_{c_s} B_s / j_s − Σ_r J_{r c_s} Λ_r) / j_s,

        the Schur complement of the diagonal block of S: the same Λ, from a system of R's
        rows alone (a chain in a plane: half the rows, and A's couplings through z gone)."""
        b, minv = self.build, _column(inverse_masses)
        loops = self._products()
        if loops is not None and B.shape[1] in (1, 2):
            return loops.solve(self.streams, minv, B)
        if b.single is None:
            return ca.solve(self.gram(minv), B, "ldl")
        e = b.single
        J = self.streams
        j = e.by_single([take(J[s], p) for s, p, _ in e.entries])
        columns = ca.horzsplit(B)
        reduced = []
        for Bi in columns:
            y = take(Bi, e.rows) / j
            coupled = e.by_coupled_rows([_times(take(J[s], p), take(y, q)) for s, p, _, q in e.coupling])
            reduced.append(take(Bi, e.others) - coupled)
        if len(e.others):
            lam = ca.solve(e.gram(J, minv), ca.horzcat(*reduced), "ldl")
        else:
            lam = ca.MX(0, len(columns))
        out = []
        for i, Bi in enumerate(columns):
            w = e.by_coupled_cols([_times(take(J[s], p), take(lam[:, i], r)) for s, p, r, _ in e.coupling])
            lam_s = (take(Bi, e.rows) / _times(take(minv, e.cols), j) - w) / j
            out.append(e.by_split([lam[:, i], lam_s]))
        return ca.horzcat(*out)

    def factorized(self, inverse_masses):
        """``solve`` for many right-hand sides with one factorization of J M⁻¹ Jᵀ (the loops'
        ``factor``, then a substitution per solve), as a function B -> Λ; ``solve`` itself
        where the loops do not apply."""
        loops, minv = self._products(), _column(inverse_masses)
        if loops is None:
            return lambda B: self.solve(minv, B)
        factors = loops.factor(self.streams, minv)
        return lambda B: loops.solve(self.streams, minv, B, factors) if B.shape[1] in (1, 2) \
            else self.solve(minv, B)

    def matrix(self):
        """J as a sparse MX matrix (C, 3N): for generic products; the methods above are cheaper."""
        b = self.build
        return ca.MX(b.jacobian_sparsity, b.by_nonzero(self.streams)) if b.n_rows else ca.MX(0, b.n3)


def _times(a, b):
    """a ∘ b, one node for the same operands within ``columns.shared_nodes``."""
    return binary(ca.OP_MUL, a, b)


def _column(values):
    """Inverse masses as a column usable in MX products (an MX as it is)."""
    return values if isinstance(values, ca.MX) else ca.DM(np.asarray(values, float))


class _Gram:
    """Index data of A = J M⁻¹ Jᵀ restricted to some rows (``label``: row -> its index in A,
    −1 to leave out) and to the coordinates not ``dropped`` (3N,): the products of every pair
    of kept entries in one column — the diagonal from each entry with itself, each
    off-diagonal product once, summed into A_rs and A_sr — grouped by the pair of streams
    they come from."""

    def __init__(self, rows: list, cols: list, label: np.ndarray, n: int, dropped: np.ndarray):
        kept = [np.flatnonzero((label[r] >= 0) & ~dropped[c]) for r, c in zip(rows, cols, strict=True)]
        none = [np.zeros(0, np.int64)]
        sid = np.concatenate([np.full(len(k), s) for s, k in enumerate(kept)] or none)
        pos = np.concatenate(kept or none)
        row = np.concatenate([label[r[k]] for r, k in zip(rows, kept, strict=True)] or none)
        col = np.concatenate([c[k] for c, k in zip(cols, kept, strict=True)] or none)
        order = np.lexsort((pos, sid, col))
        sid, pos, row, col = sid[order], pos[order], row[order], col[order]
        first, second = [], []  # off-diagonal pairs of entries (indices into the sorted entries)
        for d in range(1, int(np.bincount(col).max(initial=1))):
            same = np.flatnonzero(col[:-d] == col[d:])
            first.append(same)
            second.append(same + d)
        first = np.concatenate(first) if first else np.zeros(0, np.int64)
        second = np.concatenate(second) if second else np.zeros(0, np.int64)
        key = sorted_unique(np.concatenate([row * n + row, row[second] * n + row[first],
                                            row[first] * n + row[second]]))  # compressed-column order
        self.sparsity = ca.Sparsity.triplet(n, n, (key % max(n, 1)).tolist(), (key // max(n, 1)).tolist())

        def entry(r, c):
            return np.searchsorted(key, c * n + r)

        # the diagonal products (one per stream), then the pairs grouped by streams
        self.diagonal = [(s, k) for s, k in enumerate(kept) if len(k)]
        targets = [entry(label[rows[s][k]], label[rows[s][k]]) for s, k in self.diagonal]
        self.sources = list(range(len(self.diagonal)))
        self.pairs = []
        pair_key = sid[first] * len(rows) + sid[second]
        for k in sorted_unique(pair_key):
            members = np.flatnonzero(pair_key == k)
            i1, i2 = first[members], second[members]
            self.pairs.append((int(sid[i1[0]]), pos[i1], int(sid[i2[0]]), pos[i2]))
            product = len(self.diagonal) + len(self.pairs) - 1
            self.sources += [product, product]
            targets += [entry(row[i1], row[i2]), entry(row[i2], row[i1])]
        self.by_gram = Summation([len(t) for t in targets], targets, len(key))
        #: Where each product goes in A's nonzeros: the diagonal's, then two per pair.
        self.targets = targets
        self.cols = cols

    def __call__(self, streams: list, minv):
        weighted = {}  # J_s ∘ m⁻¹ at its coordinates, for the streams used

        def g(s):
            if s not in weighted:
                weighted[s] = _times(streams[s], take(minv, self.cols[s]))
            return weighted[s]

        products = [_times(take(streams[s], k), take(g(s), k)) for s, k in self.diagonal]
        products += [_times(take(streams[s1], p1), take(g(s2), p2)) for s1, p1, s2, p2 in self.pairs]
        return ca.MX(self.sparsity, self.by_gram([products[k] for k in self.sources]))


class _Elimination:
    """Rows with one coordinate each, at distinct coordinates (``Jacobian.solve``): ``rows``
    (S, scene order), their ``cols``, ``others`` (R); ``entries`` (stream, positions, index in
    S) of S's entries; ``coupling`` (stream, positions, index in R, index in S) of R's entries at
    S's coordinates; the reduced ``gram`` over R and the other coordinates."""

    def __init__(self, rows: list, cols: list, n_rows: int, n3: int):
        count = np.bincount(np.concatenate(rows), minlength=n_rows) if rows else np.zeros(n_rows, np.int64)
        single = np.zeros(n_rows, bool)
        single[count == 1] = True
        at = np.full(n_rows, -1, np.int64)  # each single row's coordinate
        for r, c in zip(rows, cols, strict=True):
            one = single[r]
            at[r[one]] = c[one]
        taken = np.bincount(at[single], minlength=n3)  # two single rows on one coordinate: kept whole
        single &= (at >= 0) & (taken[np.maximum(at, 0)] == 1)
        self.rows, self.others = np.flatnonzero(single), np.flatnonzero(~single)
        self.cols = at[self.rows]
        in_s = np.full(n_rows, -1, np.int64)
        in_s[self.rows] = np.arange(len(self.rows))
        in_r = np.full(n_rows, -1, np.int64)
        in_r[self.others] = np.arange(len(self.others))
        s_at = np.full(n3, -1, np.int64)
        s_at[self.cols] = np.arange(len(self.rows))
        self.entries, self.coupling = [], []
        for s, (r, c) in enumerate(zip(rows, cols, strict=True)):
            mine = np.flatnonzero(in_s[r] >= 0)
            if len(mine):
                self.entries.append((s, mine, in_s[r[mine]]))
            cross = np.flatnonzero((in_r[r] >= 0) & (s_at[c] >= 0))
            if len(cross):
                self.coupling.append((s, cross, in_r[r[cross]], s_at[c[cross]]))
        n_s, n_r = len(self.rows), len(self.others)
        self.by_single = Summation([len(p) for _, p, _ in self.entries], [q for _, _, q in self.entries], n_s)
        lengths = [len(p) for _, p, _, _ in self.coupling]
        self.by_coupled_rows = Summation(lengths, [r for _, _, r, _ in self.coupling], n_r)
        self.by_coupled_cols = Summation(lengths, [q for _, _, _, q in self.coupling], n_s)
        self.by_split = Summation([n_r, n_s], [self.others, self.rows], n_rows)
        self._gram_of = (rows, cols, in_r, n_r, n3)

    @cached_property
    def gram(self) -> _Gram:
        """The index data of the reduced A (over R and the coordinates not S's), built when first
        asked for: a start whose C loops are in the compile cache needs none (0.1 s of a
        100 x 100 cloth's start)."""
        rows, cols, in_r, n_r, n3 = self._gram_of
        dropped = np.zeros(n3, bool)
        dropped[self.cols] = True
        return _Gram(rows, cols, in_r, n_r, dropped)


class VectorizedBuild:
    """The index data of a structure's vectorized evaluation (``vectorized_build``)."""

    def __init__(self, structure: Structure):
        mb = mapped_build(structure)
        e = mb.e
        self.mapped, self.e = mb, e
        self.n3, self.n_rows = structure.n_coordinates, structure.n_position_rows  # (no velocity rows)
        self.rheonomic = structure.rheonomic
        # the rest: one SX Function of (x, v, t, p), its J's nonzeros one stream
        f_rest = ca.vertcat(*[e.rows[k] for k in mb.rest_place]) if len(mb.rest_place) else ca.SX(0, 1)
        terms = _row_terms(f_rest, e.x, e.v, e.t, lambda i: i // 3)
        r, c = terms["J"].sparsity().get_triplet()
        rest_J = ca.vertcat(*terms["J"].nonzeros()) if terms["J"].nnz() else ca.SX(0, 1)
        F_rest = forces(mb.rest_slots, e.x, e.v, e.t)[0]
        #: Whether the rest has forces (else F is the potential terms' alone).
        self.rest_forces = F_rest.nnz() > 0 and not F_rest.is_zero()
        F_rest = ca.densify(F_rest)
        self.rest = {k: terms[k] for k in ("f", "f_t", "gamma", "scale")}
        self.rest["J"], self.rest["F"] = rest_J, F_rest
        self._rest_functions: dict = {}
        self._positions = Positions(e.x, e.v, e.t, e.p)
        rows = [np.repeat(g.place[None], g.index.shape[0], axis=0) for g in mb.rows]
        self.rows = [row for g_rows in rows for row in g_rows] + [mb.rest_place[np.asarray(r, np.int64)]]
        self.cols = [col for g in mb.rows for col in g.index] + [np.asarray(c, np.int64)]
        lengths = [len(k) for k in self.rows]
        # values per row (f, γ, f_t, scales): each group's instances, then the rest, to scene order
        self.places = [g.place for g in mb.rows] + [mb.rest_place]
        self.by_place = Summation([len(p) for p in self.places], self.places, self.n_rows)
        self.by_force = Summation([g.index.shape[1] for g in mb.terms for _ in g.index],
                                  [col for g in mb.terms for col in g.index], self.n3)
        #: Rows with one coordinate each, eliminated in ``Jacobian.solve`` (None: there are none).
        self.single = _Elimination(self.rows, self.cols, self.n_rows, self.n3) if self.n_rows else None
        if self.single is not None and not len(self.single.rows):
            self.single = None
        self._jacobian_pattern(lengths)
        self._kernels: dict = {}
        self._no_p = ca.SX.sym("p", 0)  # (a kernel's p when it reads none: ``_group_function``)
        self._fused: dict | None = None
        self._products = None
        self._force_sum = None
        _, V_rest, U, dU_dv, _ = forces(mb.rest_slots, e.x, e.v, e.t)
        self.rest["E"] = V_rest + U - ca.dot(e.v, dU_dv)

    @cached_property
    def by_rows(self) -> Summation:
        """J y's sums by rows, built when first asked for: where J's products are C loops
        (``products``) nothing asks (0.01 s of a 100 x 100 cloth's build)."""
        return Summation([len(k) for k in self.rows], self.rows, self.n_rows)

    @cached_property
    def by_cols(self) -> Summation:
        """Jᵀ λ's sums by coordinates, built when first asked for (as ``by_rows``)."""
        return Summation([len(k) for k in self.rows], self.cols, self.n3)

    @cached_property
    def gram(self) -> _Gram:
        """The index data of A = J M⁻¹ Jᵀ over every row, built when first asked for: where rows
        are eliminated (``single``) the solves use the reduced one, ``_Elimination.gram``
        (building this one too took 0.1 s of a 10,000-particle rope's start)."""
        return _Gram(self.rows, self.cols, np.arange(self.n_rows), self.n_rows, np.zeros(self.n3, bool))

    def _jacobian_pattern(self, lengths: list[int]) -> None:
        """J's sparsity (C, 3N) and where each stream's entries go in its nonzeros."""
        n = self.n_rows
        key = [c * n + r for r, c in zip(self.rows, self.cols, strict=True)]
        every = sorted_unique(np.concatenate(key)) if key else np.zeros(0, np.int64)
        # (compressed columns from the sorted keys: CasADi's triplet constructor sorts them again)
        colind = np.concatenate([[0], np.cumsum(np.bincount(every // max(n, 1), minlength=self.n3))])
        row = every % max(n, 1)
        self.jacobian_sparsity = ca.Sparsity(n, self.n3, colind.tolist(), row.tolist())
        self.jacobian_columns = (colind.astype(np.int64), row.astype(np.int64))  # (its get_ccs)
        self.by_nonzero = Summation(lengths, [np.searchsorted(every, k) for k in key], len(every))

    # --- evaluation at one state ------------------------------------------------------------
    def _kernel(self, g, outputs: tuple) -> ca.Function:
        key = (id(g), outputs)
        if key not in self._kernels:
            e, xl = self.e, g.xl
            vl = ca.SX.sym("vl", xl.numel())
            terms = _row_terms(g.local, xl, vl, e.t, lambda i: g.parts[i])
            # γ = ∂c/∂x v (+ ∂c/∂t), c = J v + f_t: by forward differentiation twice (a rod's
            # kernel: 48 operations where the product with the Jacobian row gives 61)
            c = ca.jtimes(g.local, xl, vl) + terms["f_t"]
            terms["gamma"] = ca.jtimes(c, xl, vl) + (ca.jacobian(c, e.t) if ca.depends_on(c, e.t) else 0)
            out = [ca.densify(ca.vec(terms[k])) for k in outputs]
            self._kernels[key] = self._group_function("kernel", g, vl, out)
        return self._kernels[key]

    def _group_function(self, name: str, g, vl, outputs: list) -> ca.Function:
        """A group's SX kernel of (x_l, v_l, c, t, p) with ``outputs``, p the Structure's where they
        read an entry of it, else an empty one: the same instructions, where a Function of p's
        10⁴-10⁵ symbols (a cloth's rest lengths) costs 2 ms to build, a dozen times a start."""
        e = self.e
        own = {s.element_hash() for part in (g.xl, vl, g.c, e.t) for s in part.nonzeros()}
        read = ca.symvar(ca.veccat(*outputs)) if outputs else []
        p = e.p if any(s.element_hash() not in own for s in read) else self._no_p
        return ca.Function(name, [g.xl, vl, g.c, e.t, p], outputs, {"cse": True})

    def _gradient_kernel(self, g) -> ca.Function:
        key = (id(g), "gradient")
        if key not in self._kernels:
            xl = g.xl
            gradient = ca.densify(ca.gradient(g.local, xl))
            vl = ca.SX.sym("vl", xl.numel())
            self._kernels[key] = self._group_function("gradient", g, vl, [gradient])
        return self._kernels[key]

    def _rest_function(self, outputs: tuple) -> RestFunction:
        """The rest's ``outputs`` (names in ``rest``) on the entries of x, v, p they read."""
        if outputs not in self._rest_functions:
            self._rest_functions[outputs] = rest_function(self.e, [self.rest[k] for k in outputs],
                                                          self._positions)
        return self._rest_functions[outputs]

    def products(self):
        """J's products in C (``products.CompiledProducts``), built once; None without compiled code."""
        if self._products is None:
            self._products = (compiled_products(self) if self.n_rows else None) or False
        return self._products or None

    def force_sum(self):
        """F of the potential terms from their gradient columns (the streams of ``by_force``)
        as one C loop (``sums``): −Σ, or Σ where the rest has forces (F = rest − Σ); built once;
        None without compiled code, or where ``by_force`` is a matrix product."""
        if self._force_sum is None:
            terms = self.mapped.terms
            self._force_sum = self.by_force.matrix is None and summation_loop(
                [g.index.shape[1] for g in terms for _ in g.index], [col for g in terms for col in g.index],
                self.n3, negated=not self.rest_forces) or False
        return self._force_sum or None

    def _loops(self) -> dict:
        """The C loops of the groups (``fused``): (id(group), ROW_OUTPUTS, DYNAMICS or "gradient")
        -> FusedGroup, for the groups the whitelist covers; empty without compiled code."""
        if self._fused is None:
            mb = self.mapped
            # each row group twice: every output, and an acceleration's J and γ alone (a
            # loop computes what it has, and a rod's row scale is a second square root)
            keys = ([(id(g), ROW_OUTPUTS) for g in mb.rows] + [(id(g), DYNAMICS) for g in mb.rows]
                    + [(id(g), "gradient") for g in mb.terms])
            groups = [*mb.rows, *mb.rows, *mb.terms]
            kernels = [*(self._kernel(g, ROW_OUTPUTS) for g in mb.rows),
                       *(self._kernel(g, DYNAMICS) for g in mb.rows),
                       *(self._gradient_kernel(g) for g in mb.terms)]
            loops = fused_groups(groups, kernels, self.n3, self.e.p.numel()) if groups else []
            self._fused = {k: f for k, f in zip(keys, loops, strict=True) if f is not None}
        return self._fused

    def _fused_call(self, g, outputs, X, V, T, P, wanted: ca.Function) -> list | None:
        """Every scalar output of g's C loop for ``outputs`` (ROW_OUTPUTS, DYNAMICS or
        "gradient") at (X, V, T, P), or None (no loop for g); ``wanted``: the kernel of the
        outputs the caller takes from them."""
        loop = self._loops().get((id(g), outputs))
        if loop is None:
            return None
        if V is None and not self._reads(wanted, 1):
            # (v = 0 as an input is a constant, whose call costs CasADi 10-20 ms on a 100 x 100
            # cloth; the outputs taken do not read v, and those that do are left unused)
            V = X
        key = ("loop", id(g), outputs, hash(X), None if V is None else hash(V), hash(T), hash(P))
        return shared(key, lambda: loop(X, V, T, P), X, V, T, P, g)

    def _reads(self, kernel: ca.Function, i: int) -> bool:
        """Whether ``kernel``'s outputs depend on its input i."""
        key = (id(kernel), "reads", i)
        if key not in self._kernels:
            out = ca.vertcat(*[ca.vec(o) for o in kernel.call(kernel.sx_in())])
            self._kernels[key] = bool(ca.depends_on(out, kernel.sx_in(i)))
        return self._kernels[key]

    def _moves(self, g, kernel: ca.Function) -> bool:
        """Whether ``kernel``'s outputs change with the state (else columns: computed once per
        step within ``shared_nodes``, a plane's row of J)."""
        key = (id(g), id(kernel), "moves")
        if key not in self._kernels:
            xl, vl = kernel.sx_in(0), kernel.sx_in(1)
            out = ca.vertcat(*[ca.vec(o) for o in kernel.call(kernel.sx_in())])
            self._kernels[key] = bool(ca.depends_on(out, ca.vertcat(xl, vl)))
        return self._kernels[key]

    def forces_vary(self) -> bool:
        """Whether F changes with x, v or t (else it depends on p alone), from the SX."""
        e = self.e
        # (the state's 60,000 symbols of a 100 x 100 cloth gathered only for a rest with forces: 8 ms)
        if self.rest_forces and ca.depends_on(self.rest["F"], ca.vertcat(e.x, e.v, e.t)):
            return True
        for g in self.mapped.terms:
            kernel = self._gradient_kernel(g)
            inputs = kernel.sx_in()
            if ca.depends_on(kernel.call(inputs)[0], ca.vertcat(inputs[0], inputs[1], inputs[3])):
                return True
        return False

    def _row_columns(self, g, outputs: tuple, X, V, T, P) -> list:
        """The ``outputs`` of g's rows, for each a list of MX columns (J: one per coordinate)."""
        kernel = self._kernel(g, outputs)
        variant = DYNAMICS if set(outputs) <= set(DYNAMICS) else ROW_OUTPUTS
        scalars = self._fused_call(g, variant, X, V, T, P, kernel) if self._moves(g, kernel) else None
        if scalars is None:
            return self._columns(g, kernel, X, V, T, P)
        full = self._kernel(g, variant)
        start = np.concatenate([[0], np.cumsum([full.nnz_out(i) for i in range(full.n_out())])])
        return [scalars[start[variant.index(k)]:start[variant.index(k) + 1]] for k in outputs]

    def _gradient_columns(self, g, X, V, T, P) -> list:
        """The gradient of g's terms, one MX column per local coordinate."""
        kernel = self._gradient_kernel(g)
        scalars = self._fused_call(g, "gradient", X, V, T, P, kernel) if self._moves(g, kernel) else None
        return self._columns(g, kernel, X, V, T, P)[0] if scalars is None else list(scalars)

    def _columns(self, g, kernel, X, V, T, P) -> list:
        n = g.index.shape[1]
        values = (shared(("values", id(g), hash(P)), lambda: ca.vertcat(P, ca.DM(g.constants)), g, P)
                  if g.constants.size else P)
        # gathers made when the kernel reads them (each input element is read once)
        inputs = [lambda j: take(X, g.index[j]), lambda j: take(V, g.index[j]),
                  lambda j: take(values, g.sources[j]), [T],
                  lambda j: shared(("p", hash(P), j), lambda: P[j], P)]
        return on_columns(kernel, inputs, n)

    def evaluate(self, X, V, T, P, outputs: tuple, forces_too: bool = False) -> dict:
        """The ``outputs`` (names in ROW_OUTPUTS; "J" a ``Jacobian``) at (X, V, T) with the
        parameters P, MX columns; ``forces_too``: also "F" (3N,)."""
        mb = self.mapped
        rows = {k: [] for k in outputs}
        for g in mb.rows:
            out = self._row_columns(g, outputs, X, V, T, P)
            for k, values in zip(outputs, out, strict=True):
                rows[k] += values
        rest_outputs = (*outputs, "F") if forces_too and (self.rest_forces or not mb.terms) else outputs
        rest = []
        if rest_outputs:
            rest = self._rest_function(rest_outputs)(X, V, T, P)
            rest = rest if isinstance(rest, list | tuple) else [rest]
        result = {}
        if forces_too and "F" not in rest_outputs:
            rest_outputs, rest = (*rest_outputs, "F"), [*rest, None]
        for k, value in zip(rest_outputs, rest, strict=True):
            if k == "J":
                result["J"] = Jacobian(self, rows["J"] + [value])
            elif k == "F":
                gradients = [col for g in mb.terms for col in self._gradient_columns(g, X, V, T, P)]
                loop = self.force_sum() if all(c.nnz() == c.numel() for c in gradients) else None
                if not gradients:
                    result["F"] = value
                elif loop is not None:  # the same sums in one C loop, negated there without a rest
                    summed = shared(("forces", *map(hash, gradients)), lambda f=loop, g=gradients: f(*g),
                                    *gradients)
                    result["F"] = value - summed if self.rest_forces else summed
                elif self.rest_forces:
                    result["F"] = value - self.by_force(gradients)
                else:  # every force a potential term's: no dense zeros to subtract from
                    result["F"] = -self.by_force(gradients)
            else:
                result[k] = self.by_place(rows[k] + [value])
        return result


    def _value_kernel(self, g) -> ca.Function:
        key = (id(g), "value")
        if key not in self._kernels:
            xl = g.xl
            vl = ca.SX.sym("vl", xl.numel())
            self._kernels[key] = self._group_function("value", g, vl, [g.local])
        return self._kernels[key]

    def energy(self, X, V, T, P, masses):
        """The energy function h = T + V + U − v·∂U/∂v (the Structure's ``energy``), MX scalar."""
        total = 0.5 * ca.dot(masses * V, V) + self._rest_function(("E",))(X, V, T, P)
        for g in self.mapped.terms:
            total = total + ca.sum1(self._columns(g, self._value_kernel(g), X, V, T, P)[0][0])
        return total


def vectorized_build(structure: Structure) -> VectorizedBuild:
    """The structure's VectorizedBuild, built once and kept beside it."""
    return built_once(structure, "vectorized build", lambda: VectorizedBuild(structure))
