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

import casadi as ca
import numpy as np

from ...model.cache import built_once
from ...model.structure import Structure, forces
from ..mapped import _row_terms, mapped_build
from .columns import Summation, on_columns, take

#: The outputs of a row kernel, in order ("J" is d entries, the others one each).
ROW_OUTPUTS = ("f", "J", "f_t", "gamma", "scale")


@dataclass
class Jacobian:
    """J at one state as streams (MX columns) over the build's index data."""

    build: VectorizedBuild
    streams: list

    def times(self, y):
        """J y (C,) for a column y (3N,)."""
        b = self.build
        return b.by_rows([J * take(y, c) for J, c in zip(self.streams, b.cols, strict=True)])

    def transpose_times(self, lam):
        """Jᵀ λ (3N,) for a column λ (C,)."""
        b = self.build
        return b.by_cols([J * take(lam, r) for J, r in zip(self.streams, b.rows, strict=True)])

    def gram(self, inverse_masses):
        """A = J M⁻¹ Jᵀ (C, C), sparse, for the inverse masses per coordinate (3N,)."""
        b = self.build
        minv = inverse_masses
        if not isinstance(minv, ca.MX):
            minv = ca.DM(np.asarray(minv, float))
        weighted = [J * take(minv, c) for J, c in zip(self.streams, b.cols, strict=True)]
        products = [J * G for J, G in zip(self.streams, weighted, strict=True)]
        for s1, p1, s2, p2 in b.pairs:
            products.append(take(self.streams[s1], p1) * take(weighted[s2], p2))
        return ca.MX(b.gram_sparsity, b.by_gram([products[k] for k in b.gram_sources]))

    def matrix(self):
        """J as a sparse MX matrix (C, 3N): for generic products; the methods above are cheaper."""
        b = self.build
        return ca.MX(b.jacobian_sparsity, b.by_nonzero(self.streams)) if b.n_rows else ca.MX(0, b.n3)


class VectorizedBuild:
    """The index data of a structure's vectorized evaluation (``vectorized_build``)."""

    def __init__(self, structure: Structure):
        mb = mapped_build(structure)
        e = mb.e
        self.mapped, self.e = mb, e
        self.n3, self.n_rows = structure.n_coordinates, structure.n_constraints
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
        rows = [np.repeat(g.place[None], g.index.shape[0], axis=0) for g in mb.rows]
        self.rows = [row for g_rows in rows for row in g_rows] + [mb.rest_place[np.asarray(r, np.int64)]]
        self.cols = [col for g in mb.rows for col in g.index] + [np.asarray(c, np.int64)]
        lengths = [len(k) for k in self.rows]
        self.by_rows = Summation(lengths, self.rows, self.n_rows)
        self.by_cols = Summation(lengths, self.cols, self.n3)
        # values per row (f, γ, f_t, scales): each group's instances, then the rest, to scene order
        self.places = [g.place for g in mb.rows] + [mb.rest_place]
        self.by_place = Summation([len(p) for p in self.places], self.places, self.n_rows)
        self.by_force = Summation([g.index.shape[1] for g in mb.terms for _ in g.index],
                                  [col for g in mb.terms for col in g.index], self.n3)
        self._gram_pattern(lengths)
        self._jacobian_pattern(lengths)
        self._kernels: dict = {}
        _, V_rest, U, dU_dv, _ = forces(mb.rest_slots, e.x, e.v, e.t)
        self.rest["E"] = V_rest + U - ca.dot(e.v, dU_dv)

    # --- A = J M⁻¹ Jᵀ: which products, summed where --------------------------------------------
    def _gram_pattern(self, lengths: list[int]) -> None:
        sid = np.repeat(np.arange(len(lengths)), lengths)
        pos = np.concatenate([np.arange(k) for k in lengths]) if lengths else np.zeros(0, np.int64)
        row, col = np.concatenate(self.rows), np.concatenate(self.cols)
        order = np.lexsort((pos, sid, col))
        sid, pos, row, col = sid[order], pos[order], row[order], col[order]
        first, second = [], []  # off-diagonal pairs of entries (indices into the sorted entries)
        for d in range(1, int(np.bincount(col).max(initial=1))):
            same = np.flatnonzero(col[:-d] == col[d:])
            first.append(same)
            second.append(same + d)
        first = np.concatenate(first) if first else np.zeros(0, np.int64)
        second = np.concatenate(second) if second else np.zeros(0, np.int64)
        n = self.n_rows
        a_rows = np.concatenate([row, row[first], row[second]])
        a_cols = np.concatenate([row, row[second], row[first]])
        key = np.unique(a_cols * n + a_rows)  # compressed-column order
        self.gram_sparsity = ca.Sparsity.triplet(n, n, (key % n).tolist(), (key // n).tolist())

        def entry(r, c):
            return np.searchsorted(key, c * n + r)

        # sources: the diagonal products (one per stream), then the pairs grouped by streams
        sources, targets = [], []
        for s, rows in enumerate(self.rows):
            sources.append(s)
            targets.append(entry(rows, rows))
        self.pairs = []
        pair_key = sid[first] * len(lengths) + sid[second]
        for k in np.unique(pair_key):
            members = np.flatnonzero(pair_key == k)
            i1, i2 = first[members], second[members]
            self.pairs.append((int(sid[i1[0]]), pos[i1], int(sid[i2[0]]), pos[i2]))
            product = len(lengths) + len(self.pairs) - 1
            sources += [product, product]
            targets += [entry(row[i1], row[i2]), entry(row[i2], row[i1])]
        self.gram_sources = sources
        self.by_gram = Summation([len(t) for t in targets], targets, len(key))

    def _jacobian_pattern(self, lengths: list[int]) -> None:
        """J's sparsity (C, 3N) and where each stream's entries go in its nonzeros."""
        n = self.n_rows
        key = [c * n + r for r, c in zip(self.rows, self.cols, strict=True)]
        every = np.unique(np.concatenate(key)) if key else np.zeros(0, np.int64)
        self.jacobian_sparsity = ca.Sparsity.triplet(n, self.n3, (every % max(n, 1)).tolist(),
                                                     (every // max(n, 1)).tolist())
        self.by_nonzero = Summation(lengths, [np.searchsorted(every, k) for k in key], len(every))

    # --- evaluation at one state ------------------------------------------------------------
    def _kernel(self, g, outputs: tuple) -> ca.Function:
        key = (id(g), outputs)
        if key not in self._kernels:
            e, xl = self.e, g.xl
            vl = ca.SX.sym("vl", xl.numel())
            terms = _row_terms(g.local, xl, vl, e.t, lambda i: g.parts[i])
            out = [ca.densify(ca.vec(terms[k])) for k in outputs]
            self._kernels[key] = ca.Function("kernel", [xl, vl, g.c, e.t, e.p], out, {"cse": True})
        return self._kernels[key]

    def _gradient_kernel(self, g) -> ca.Function:
        key = (id(g), "gradient")
        if key not in self._kernels:
            e, xl = self.e, g.xl
            gradient = ca.densify(ca.gradient(g.local, xl))
            vl = ca.SX.sym("vl", xl.numel())
            self._kernels[key] = ca.Function("gradient", [xl, vl, g.c, e.t, e.p], [gradient], {"cse": True})
        return self._kernels[key]

    def _rest_function(self, outputs: tuple) -> ca.Function:
        if outputs not in self._rest_functions:
            e = self.e
            self._rest_functions[outputs] = ca.Function(
                "rest", [e.x, e.v, e.t, e.p], [self.rest[k] for k in outputs], {"cse": True})
        return self._rest_functions[outputs]

    def _columns(self, g, kernel, X, V, T, P) -> list:
        n = g.index.shape[1]
        values = ca.vertcat(P, ca.DM(g.constants)) if g.constants.size else P
        # gathers made when the kernel reads them (each input element is read once)
        inputs = [lambda j: take(X, g.index[j]), lambda j: take(V, g.index[j]),
                  lambda j: take(values, g.sources[j]), [T], lambda j: P[j]]
        return on_columns(kernel, inputs, n)

    def evaluate(self, X, V, T, P, outputs: tuple, forces_too: bool = False) -> dict:
        """The ``outputs`` (names in ROW_OUTPUTS; "J" a ``Jacobian``) at (X, V, T) with the
        parameters P, MX columns; ``forces_too``: also "F" (3N,)."""
        mb = self.mapped
        rows = {k: [] for k in outputs}
        for g in mb.rows:
            out = self._columns(g, self._kernel(g, outputs), X, V, T, P)
            for k, values in zip(outputs, out, strict=True):
                rows[k] += values if k == "J" else values
        rest_outputs = (*outputs, "F") if forces_too and (self.rest_forces or not mb.terms) else outputs
        rest = self._rest_function(rest_outputs)(X, V if V is not None else ca.MX.zeros(self.n3), T, P)
        rest = rest if isinstance(rest, list | tuple) else [rest]
        result = {}
        if forces_too and "F" not in rest_outputs:
            rest_outputs, rest = (*rest_outputs, "F"), [*rest, None]
        for k, value in zip(rest_outputs, rest, strict=True):
            if k == "J":
                result["J"] = Jacobian(self, rows["J"] + [value])
            elif k == "F":
                gradients = [col for g in mb.terms
                             for col in self._columns(g, self._gradient_kernel(g), X, V, T, P)[0]]
                if not gradients:
                    result["F"] = value
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
            e, xl = self.e, g.xl
            vl = ca.SX.sym("vl", xl.numel())
            self._kernels[key] = ca.Function("value", [xl, vl, g.c, e.t, e.p], [g.local], {"cse": True})
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
