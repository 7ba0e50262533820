"""Pair potentials V = Σ_{i<j} φ(r_ij) as ONE mapped kernel, built once whatever the number of
pairs (issue 28), and their neighbour lists.

φ is parsed once into an SX function of r (and t, the parameters p). The effect's particles
are cut into blocks of ``BLOCK``; a *tile* is the interaction of two blocks, its BLOCK² pairs
written out once as an SX kernel giving the tile's energy and the force on each particle,

    f_i = −φ'(r_ij) (x_i − x_j) / r_ij,    f_j = −f_i,

and the graph applies that kernel with CasADi ``map`` (a loop in the generated code), so the
graph, the generated C and its compile time do not grow with the pairs. Padding places of a
block are masked: their pairs count zero.

All pairs (no cutoff): an outer map over blocks a (in groups of GROUP, which bounds the
copies CasADi's map makes of its shared inputs) of an inner map over all blocks b, the kernel
chosen per tile by a conditional: b < a nothing, b = a the pairs i < j inside the block,
b > a the whole tile, the reactions on b summed by the outer map. No index data: exact,
O(N²) work, O(N) memory.

Cutoff r_c (shifted force, smoothed to second order): the pair term is

    φ_c(r) = φ(r) − φ(r_c) − (r − r_c) φ'(r_c) − ½ (r − r_c)² φ''(r_c)   for r < r_c,   0 beyond,

continuous at r_c in energy, force and the force's derivative, so a run conserves the energy
it reports (that of φ_c), and an error-controlled method crosses r_c without losing order
(with the usual shifted force, φ'' jumps there: DOP853 on a small gas rejected every other
step). Only pairs within r_c count, found outside the graph (``neighbours.pair_rows``): every
pair (i, j), i < j, within r_c + skin (SciPy's cKDTree), held by i in *rows* of ROW neighbours
(a particle with more has several rows, its last padded), the rows padded to a capacity in
whole groups of GROUP_ROWS. That list is *data* (``PairTerm.data``, appended to the
Structure's p: every Function, the compiled step loops included, takes it as an input, and
none is rebuilt when it changes): the graph gathers the positions of each row's particle and
of its neighbours by the indices it holds, maps a kernel of GROUP_ROWS rows (GROUP_ROWS · ROW
pairs written out once) over the groups — a group of empty rows skipped by a conditional —
and adds the forces back by the transposed gathers (CasADi's AD of them). A pair's work is
then that of the pair alone (~40 operations), not of the 8 × 8 tile of two neighbouring blocks
the list held before (most of whose pairs were beyond the cutoff: ~8x the work at N =
10,000). The kernel computes only what its Function uses: the forces for ``dynamics``, the
energy for ``energy`` and ``potential``. The list is valid while no particle has moved more
than skin/2 since it was built (the positions then, ``x_ref``, are in the data): every pair
closer than r_c now was closer than r_c + skin then. The graph checks that itself and takes
the all-pairs branch when it does not hold (a short-circuit conditional), so a stale list
costs time, never accuracy; runs refresh it at half that distance, so the steps taken from a
fresh list stay within it (``PairTerm.fresh``, ``PairPotentials.refreshed``,
``REFRESH_SHARE``).

Where a C compiler is at hand, the forces through the list (what a step evaluates) are not
this mapped graph but one fused C loop over the same rows (``fused``: gather, pair and
scatter-add in one pass, ~3x cheaper at 10,000 particles); the energy, and every Function
without a compiler, take the mapped kernel. Both sum the same pairs.

Excluded pairs (``exclude_bonded``: joined by a distance constraint) are never summed: the
neighbour list leaves them out, and the all-pairs tiles mask them like padding (each particle's
excluded partners are an input of its block's tiles, K per particle, K the most any has).
Subtracting them after the sums, as this did before, lost the other pairs to round-off where a
bond is short inside the repulsion (docs/hard-cases.md, section 12).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ...codegen.fast_call import FastCall
from . import cells, fused, neighbours
from .neighbours import GROUP_ROWS, ROW

#: Particles per block of the all-pairs sum: a tile is BLOCK² pairs written out once (64 pairs,
#: ~1.7k operations); larger tiles amortize the map's call more.
BLOCK = 8
#: Blocks a of the all-pairs sum per call of its outer map (whose shared inputs CasADi copies
#: once per block: GROUP copies of the positions at a time).
GROUP = 32
#: Capacity of a neighbour list: this factor times the pairs of the first list (plus a chunk);
#: a list that needs more is not used (all pairs are summed instead).
CAPACITY_FACTOR = 1.25
#: Whether the listed forces run as one fused C loop where a C compiler allows
#: (``fused.fused_forces``); False: the mapped kernel always (tests compare the two).
FUSED = True
#: Whether a list's rows are built by the cell list in C where a C compiler allows
#: (``cells``); False: by SciPy's tree and NumPy always (tests compare the two).
CELLS = True


@dataclass(frozen=True)
class PairSpec:
    """What a ``pairwise`` effect declares: ``phi`` (SX in the symbol ``r``, and t, p), its
    ``particles`` (indices into the system's), ``cutoff`` (None: every pair) and ``skin``
    (metres), ``excluded`` pairs (E, 2) as positions in ``particles``, and its ``label``."""

    label: str
    r: ca.SX
    phi: ca.SX
    particles: np.ndarray
    cutoff: float | None
    skin: float
    excluded: np.ndarray


def effective(phi: ca.SX, r: ca.SX, cutoff: float | None) -> ca.SX:
    """φ itself, or with a cutoff the shifted φ_c (see the module's docstring)."""
    if cutoff is None:
        return phi
    rc = ca.SX(cutoff)
    at_cut = ca.substitute(phi, r, rc)
    d1 = ca.jacobian(phi, r)
    slope, curvature = ca.substitute(d1, r, rc), ca.substitute(ca.jacobian(d1, r), r, rc)
    return ca.if_else(r < rc, phi - at_cut - (r - rc) * slope - 0.5 * (r - rc) ** 2 * curvature, 0)


def _pair(phi: ca.SX, r: ca.SX, t, p) -> ca.Function:
    """(x_i, x_j, t, p) -> (φ(r_ij), f_i = −∂φ/∂x_i)."""
    xi, xj = ca.SX.sym("xi", 3), ca.SX.sym("xj", 3)
    d = xi - xj
    rij = ca.sqrt(ca.dot(d, d))
    v = ca.substitute(phi, r, rij)
    dphi = ca.substitute(ca.jacobian(phi, r), r, rij)
    # (one division for the three components: a tile's cost is mostly its divisions)
    return ca.Function("pair", [xi, xj, t, p], [v, (-dphi / rij) * d])


def _tiles(pair: ca.Function, t, p, excluded: int = 0) -> dict[str, ca.Function]:
    """The tile kernels (x_a, x_b, m_a, m_b, t, p) -> (V, F_a, F_b) (3B, 3B, B, B: coordinates
    and 0/1 masks): ``full`` every pair of the two blocks, ``diag`` the pairs i < j of block a
    alone (x_b, m_b unused, F_b = 0), ``zero`` nothing; the conditional ``tile(case, …)``
    picks one (0 zero, 1 diag, 2 full). ``excluded`` K > 0: two more inputs after m_b, e_a
    (B·K: each particle of block a, its excluded partners, −1 where none) and b (block b's
    number: its slot j is particle b·B + j); a pair (i, j) with b·B + j among i's partners
    counts nothing, like padding (not computed and subtracted: see ``neighbours.without``)."""
    B, K = BLOCK, excluded
    xa, xb, ma, mb = ca.SX.sym("xa", 3 * B), ca.SX.sym("xb", 3 * B), ca.SX.sym("ma", B), ca.SX.sym("mb", B)
    ea, b = ca.SX.sym("ea", B * K), ca.SX.sym("b")
    inputs = [xa, xb, ma, mb, *([ea, b] if K else []), t, p]
    zero3 = ca.SX.zeros(3)

    def masked(i, j, other, mother):
        v, f = pair(xa[3 * i:3 * i + 3], other[3 * j:3 * j + 3], t, p)
        w = ma[i] * mother[j] > 0  # padding places count nothing (even a NaN of theirs)
        for k in range(K):  # nor excluded pairs (in the diagonal tile b = a)
            w = ca.logic_and(w, ea[K * i + k] != b * B + j)
        return ca.if_else(w, v, 0), ca.if_else(w, f, zero3)

    V, Fa, Fb = ca.SX(0), [zero3] * B, [zero3] * B
    Vd, Fd = ca.SX(0), [zero3] * B
    for i in range(B):
        for j in range(B):
            v, f = masked(i, j, xb, mb)
            V, Fa[i], Fb[j] = V + v, Fa[i] + f, Fb[j] - f
            if j > i:
                v, f = masked(i, j, xa, ma)
                Vd, Fd[i], Fd[j] = Vd + v, Fd[i] + f, Fd[j] - f
    zero = ca.SX.zeros(3 * B)
    full = ca.Function("tile_full", inputs, [V, ca.vertcat(*Fa), ca.vertcat(*Fb)], {"cse": True})
    diag = ca.Function("tile_diag", inputs, [Vd, ca.vertcat(*Fd), zero], {"cse": True})
    nothing = ca.Function("tile_zero", inputs, [ca.SX(0), zero, zero])
    return ca.Function.conditional("tile", [nothing, diag], full)


def _partners(excluded: np.ndarray, n: int) -> np.ndarray:
    """(n, K): row i the partners of particle i in the ``excluded`` pairs (E, 2), in both
    directions, −1 after them; K the most any particle has (0 without exclusions)."""
    ends = np.concatenate([excluded, excluded[:, ::-1]]) if len(excluded) else np.zeros((0, 2), np.int64)
    counts = np.bincount(ends[:, 0], minlength=n)
    out = -np.ones((n, int(counts.max(initial=0))))
    ends = ends[np.lexsort((ends[:, 1], ends[:, 0]))]
    place = np.arange(len(ends)) - np.concatenate([[0], np.cumsum(counts)[:-1]])[ends[:, 0]]
    out[ends[:, 0], place] = ends[:, 1]
    return out


def _case(a, b):
    """The tile of blocks a, b: 1 (the same block: its pairs i < j), else 2 (every pair)."""
    return ca.if_else(b == a, 1, 2)


class PairTerm:
    """One ``pairwise`` effect in a Structure: its kernels (built once), its graph
    (``energy_and_forces``) and, with a cutoff, its neighbour list: ``size`` entries of p from
    ``offset`` on (``data``, ``fresh``)."""

    def __init__(self, spec: PairSpec, t: ca.SX, p: ca.SX, *, n_coordinates: int, offset: int,
                 positions: np.ndarray):
        self.spec, self.label = spec, spec.label
        self.n = len(spec.particles)
        self.n_blocks = -(-self.n // BLOCK)
        self.n_coordinates = n_coordinates
        self.cutoff, self.skin = spec.cutoff, spec.skin
        phi = effective(spec.phi, spec.r, spec.cutoff)
        self.time_dependent = bool(ca.depends_on(phi, t))
        # the kernels take only the entries of p that φ reads (the maps copy their shared
        # inputs once per call: all of p, thousands of plain numbers, would swamp the pairs)
        self._p_used = sorted(set(ca.jacobian_sparsity(phi, p).get_col())) if p.numel() else []
        q = ca.SX.sym("q", len(self._p_used))
        phi = ca.substitute(phi, p[self._p_used], q) if self._p_used else phi
        self._pair = _pair(phi, spec.r, t, q)
        self._phi_c, self._t, self._q = phi, t, q  # (φ_c of spec.r, t and q)
        # each particle's excluded partners (e_a of the tiles: K columns, −1 where none)
        self._partners = _partners(spec.excluded, self.n_blocks * BLOCK)
        self._tile = _tiles(self._pair, t, q, self._partners.shape[1])
        self._coordinates = (3 * spec.particles[:, None] + np.arange(3)).ravel()
        self._functions = None
        self._cell_rows = None  # (the cell list's FastCall, or False: NumPy's route)
        mask = np.zeros(self.n_blocks * BLOCK)
        mask[:self.n] = 1.0
        self._mask = ca.DM(mask.reshape(self.n_blocks, BLOCK).T)
        self.offset = offset
        #: Capacity of the neighbour list: rows of ROW pairs (whole groups of GROUP_ROWS).
        self.capacity = 0
        if self.cutoff is not None:  # room for the rows the start needs, and more
            i = neighbours.without(*neighbours.pairs_within(self._listed(positions), self.reach), self.n,
                                   spec.excluded)[0]
            self.capacity = neighbours.capacity_for(neighbours.rows_needed(i, self.n), CAPACITY_FACTOR,
                                                    self.n)
        #: Entries of p this term's data takes (its neighbour list; 0 without a cutoff).
        self.size = 0 if self.cutoff is None else 1 + 3 * self.n + (1 + ROW) * self.capacity

    @property
    def reach(self) -> float:
        """r_c + skin: the distance within which the neighbour list holds the pairs."""
        return self.cutoff + self.skin

    # --- the data: a neighbour list, outside the graph ------------------------------------
    def _listed(self, x) -> np.ndarray:
        """The effect's particles' positions (n, 3) from positions (N, 3) or a flat 3N x."""
        return np.asarray(x, float).reshape(-1, 3)[self.spec.particles]

    def data(self, x) -> np.ndarray:
        """The neighbour list at positions ``x`` ((N, 3) or flat 3N), as the entries of p it
        takes: [valid (1, or 0 for a list beyond the capacity: the graph then sums every
        pair), x_ref (3n), I (capacity), J (ROW·capacity): the pairs within r_c + skin in rows
        (``neighbours.pair_rows``: row k holds the pairs (I_k, J_{ROW·k + s})), placeholders n
        and n + 1 where empty]. All finite (a run checks its state is)."""
        if self.cutoff is None:
            return np.zeros(0)
        y = self._listed(x)
        found = self._rows(y)
        valid = found is not None
        ref = y.ravel() if valid else np.zeros(3 * self.n)
        if not valid:
            found = np.full(self.capacity, float(self.n)), np.full(ROW * self.capacity, float(self.n + 1))
        return np.concatenate([[float(valid)], ref, *found])

    def _rows(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``neighbours.pair_rows`` of the points y (n, 3): by the cell list in C when it can
        be had (compiled on the first call), else by SciPy and NumPy."""
        if self._cell_rows is None:
            function = (cells.rows_function(self.n, self.capacity, self.reach, self.cutoff,
                                            self.spec.excluded) if CELLS else None)
            self._cell_rows = FastCall(function) if function is not None else False
        if self._cell_rows is False:
            return neighbours.pair_rows(y, self.reach, self.capacity, self.spec.excluded)
        out = self._cell_rows(y.ravel())[0]
        if out[0] != 1:
            return None
        return out[1:1 + self.capacity], out[1 + self.capacity:]

    def fresh(self, x, data, share: float = 1.0) -> bool:
        """Whether ``data`` still holds every pair within the cutoff at positions ``x`` (no
        particle moved more than skin/2 since it was built; always, without a cutoff);
        ``share`` < 1: more than share · skin/2 counts as moved (a run refreshes its list
        at half of that, so that a step taken from there still finds it valid)."""
        if self.cutoff is None:
            return True
        moved = self._listed(x) - np.asarray(data[1:1 + 3 * self.n]).reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            limit = (share * self.skin / 2) ** 2
            within = np.max(np.einsum("ij,ij->i", moved, moved), initial=0.0) <= limit
        return bool(data[0] == 1 and within)

    # --- the graph -----------------------------------------------------------------------
    def energy_and_forces(self, X: ca.MX, T, P: ca.MX, n_physical: int, *, lists: bool = True,
                          want: str = "both", differentiable: bool = False) -> tuple[ca.MX, ca.MX]:
        """(V, F) as MX of the positions X (3N), t and the full p (the physical parameters are
        its first ``n_physical`` entries, this term's data at ``offset``): F = −∂V/∂x (3N).
        ``lists`` False: every pair, whatever the data (no neighbour list: the graph then
        also evaluates with SX symbols, written out). ``want`` "force" or "energy": the
        neighbour list's kernel computes that one alone (the other output is then not the
        term's: 0 through the list)."""
        Pp = P[self._p_used] if self._p_used else ca.MX(0, 1)  # (the entries φ reads)
        Xl = X[self._coordinates.tolist()]
        every, listed = self._sums(want, differentiable)
        if self.cutoff is None or not lists:
            V, F = every(Xl, T, Pp)
        else:  # every pair only when the list is stale; of each, only the outputs asked for
            data = P[self.offset:self.offset + self.size]
            used = {"force": [1], "energy": [0]}.get(want, [0, 1])
            through_list, through_all = listed(Xl, T, Pp, data), every(Xl, T, Pp)
            both = ca.if_else(self.fresh_graph(X, P), ca.vertcat(*[through_list[k] for k in used]),
                              ca.vertcat(*[through_all[k] for k in used]), True)
            V = both[0] if 0 in used else ca.MX(0)
            F = both[1 if 0 in used else 0:] if 1 in used else ca.MX.zeros(3 * self.n, 1)
        if np.array_equal(self._coordinates, np.arange(self.n_coordinates)):
            return V, F
        scatter = ca.DM(ca.Sparsity.triplet(self.n_coordinates, 3 * self.n, self._coordinates.tolist(),
                                            list(range(3 * self.n))), 1.0)
        return V, ca.mtimes(scatter, F)

    def _sums(self, want: str = "both",
              differentiable: bool = False) -> tuple[ca.Function, ca.Function | None]:
        """(every, listed): the pair sums as Functions, built once and called by every Function
        of the Structure that holds them: ``every(x_l, t, p_φ) -> (V, F)`` over every pair and
        (a cutoff) ``listed(x_l, t, p_φ, data) -> (V, F)`` through the neighbour list, which
        computes only what ``want`` asks ("both", "force": V = 0, "energy": F = 0): the forces
        (and with them the energy: "both") by the fused C loop where it can be had and
        derivatives are not asked for (``differentiable``)."""
        if self._functions is None:
            Xl, T, Pp = ca.MX.sym("x", 3 * self.n), ca.MX.sym("t"), ca.MX.sym("p", len(self._p_used))
            self._functions = {"every": ca.Function("pairs_every", [Xl, T, Pp],
                                                    list(self._all_pairs(Xl, T, Pp)))}
        every = self._functions["every"]
        if self.cutoff is None:
            return every, None
        if want in ("force", "both") and not differentiable:
            if "fused" not in self._functions:
                self._functions["fused"] = self._fused()
            if self._functions["fused"] is not None:
                return every, self._functions["fused"]
        if want not in self._functions:
            self._functions[want] = self._mapped(want)
        return every, self._functions[want]

    def _mapped(self, want: str) -> ca.Function:
        """The listed sum as the mapped graph (``_listed_pairs``)."""
        Xl, T, Pp = ca.MX.sym("x", 3 * self.n), ca.MX.sym("t"), ca.MX.sym("p", len(self._p_used))
        data = ca.MX.sym("data", self.size)
        return ca.Function(f"pairs_listed_{want}", [Xl, T, Pp, data],
                           list(self._listed_pairs(Xl, T, Pp, data, want)))

    def _fused(self) -> ca.Function | None:
        """The listed forces as one C loop (``fused.fused_forces``), or None where that cannot
        be had (the mapped kernel then): g(r) = −φ_c'(r)/r is what the loop evaluates."""
        if not FUSED:
            return None
        r = self.spec.r
        return fused.fused_forces("pairs_fused_force", r, self._t, self._q, -ca.jacobian(self._phi_c, r) / r,
                                  self._phi_c, n=self.n, size=self.size, capacity=self.capacity,
                                  cutoff=self.cutoff)

    def fresh_graph(self, X, P, share: float = 1.0):
        """MX: whether the neighbour list in P holds at positions X (``fresh``; false for a
        list beyond the capacities)."""
        ref = P[self.offset + 1:self.offset + 1 + 3 * self.n]
        moved = ca.reshape(X[self._coordinates.tolist()] - ref, 3, self.n)
        within = ca.sum1(moved * moved) <= (share * self.skin / 2) ** 2
        return ca.logic_and(P[self.offset] == 1, ca.sum2(ca.logic_not(within)) == 0)

    def fastest_graph(self, V):
        """MX: the largest speed among the term's particles at velocities V (3N)."""
        return ca.sqrt(ca.mmax(ca.sum1(ca.reshape(V[self._coordinates.tolist()], 3, self.n) ** 2)))

    def valid_graph(self, P):
        """MX: whether the data in P is a list (not one beyond the capacities)."""
        return P[self.offset] == 1

    def _symbols(self, n_p: int):
        B = BLOCK
        return (ca.MX.sym("xa", 3 * B), ca.MX.sym("ma", B), ca.MX.sym("a"), ca.MX.sym("xb", 3 * B),
                ca.MX.sym("mb", B), ca.MX.sym("b"), ca.MX.sym("t"), ca.MX.sym("p", n_p))

    def _all_pairs(self, Xl, T, Pp) -> tuple[ca.MX, ca.MX]:
        """Every pair: outer map over blocks a, inner over blocks b (see the module)."""
        B, nb, K = BLOCK, self.n_blocks, self._partners.shape[1]
        xa, ma, a, xb, mb, b, t, p = self._symbols(Pp.numel())
        ea = [ca.MX.sym("ea", B * K)] if K else []  # (block a's excluded partners: see _tiles)
        case = ca.if_else(b < a, 0, _case(a, b))
        inner = ca.Function("pairs_inner", [xa, ma, a, *ea, xb, mb, b, t, p],
                            self._tile(case, xa, xb, ma, mb, *ea, *([b] if K else []), t, p))
        e = len(ea)
        inner = inner.map("pairs_row", "serial", nb, [0, 1, 2, *([3] if K else []), 6 + e, 7 + e], [0, 1])
        XB, MB, IB = ca.MX.sym("XB", 3 * B, nb), ca.MX.sym("MB", B, nb), ca.MX.sym("IB", 1, nb)
        outer = ca.Function("pairs_outer", [xa, ma, a, *ea, XB, MB, IB, t, p],
                            inner(xa, ma, a, *ea, XB, MB, IB, t, p))
        pad = nb * B - self.n
        Xb = ca.reshape(ca.vertcat(Xl, ca.MX.zeros(3 * pad)) if pad else Xl, 3 * B, nb)
        index = ca.DM(np.arange(nb, dtype=float)).T
        EA = ca.DM(self._partners.reshape(nb, B * K).T) if K else None
        V, FA, FB, groups = 0, [], 0, {}
        for start in range(0, nb, GROUP):
            k = min(GROUP, nb - start)
            part = slice(start, start + k)
            if k not in groups:  # (one map per size: at most two)
                groups[k] = outer.map(f"pairs_group_{k}", "serial", k, [3 + e + s for s in range(5)], [0, 2])
            group = groups[k]
            own = [Xb[:, part], self._mask[:, part], index[:, part], *([EA[:, part]] if K else [])]
            Vg, FAg, FBg = group(*own, Xb, self._mask, index, T, Pp)
            V, FB = V + Vg, FB + FBg
            FA.append(FAg)
        return V, (ca.vec(ca.horzcat(*FA)) + ca.vec(FB))[:3 * self.n]

    def _listed_pairs(self, Xl, T, Pp, data, want: str = "both") -> tuple[ca.MX, ca.MX]:
        """The neighbour list's rows: the positions of each row's particle and of its ROW
        neighbours gathered by index, a kernel of GROUP_ROWS rows mapped over the groups (a
        group of empty rows skipped), the forces added back by the transposed gathers
        (CasADi's AD of them). The placeholders n and n + 1 are two points 4 r_c apart and at
        least that far from every particle: a pair with one of them counts exactly nothing."""
        n, rows, G = self.n, self.capacity, GROUP_ROWS
        start = 1 + 3 * n  # after valid and x_ref
        # (column vectors of indices and (3, k) positions, laid out as the map's calls take
        # them: no reshaped copies, and few distinct large shapes, which the compile cache's
        # key serializes one by one)
        I, J = data[start:start + rows], data[start + rows:start + rows + ROW * rows]
        far = ca.mmax(Xl) + 4 * self.cutoff
        spare = ca.vertcat(ca.horzcat(far, far + 4 * self.cutoff), ca.repmat(far, 2, 2))
        Xd = ca.horzcat(ca.reshape(Xl, 3, n), spare)
        XI, XJ = Xd[:, I], Xd[:, J]  # (3, rows), (3, ROW·rows)
        used = (I[list(range(0, rows, G))] < n).T  # (the empty rows are last: a group is all empty)
        groups = self._group(want).map("pairs_groups", "serial", rows // G, [3, 4], [0])
        if want == "energy":
            return groups(used, XI, XJ, T, Pp)[0], ca.MX.zeros(3 * n, 1)
        V, FI, FJ = groups(used, XI, XJ, T, Pp)
        Y = ca.MX.sym("Y", 3, n + 2)
        GI, GJ = ca.MX.sym("GI", 3, rows), ca.MX.sym("GJ", 3, ROW * rows)
        SI, SJ = ca.MX.sym("SI", rows), ca.MX.sym("SJ", ROW * rows)
        back = ca.Function("pairs_reactions", [Y, SI, GI, SJ, GJ],
                           [ca.gradient(ca.dot(Y[:, SI], GI) + ca.dot(Y[:, SJ], GJ), Y)])
        return V, ca.vec(back(Xd, I, FI, J, FJ)[:, :n])

    def _group(self, want: str = "both") -> ca.Function:
        """The listed kernel: (used, X_I, X_J, t, p_φ) -> (V, F_I, F_J) for GROUP_ROWS rows, the
        rows' particles x_i (3, GROUP_ROWS) and their ROW neighbours each x_j (3, ROW·GROUP_ROWS),
        the forces on each; nothing when ``used`` is 0 (a group of empty rows). ``want``
        "force": V = 0 (not computed); "energy": V alone."""
        G = GROUP_ROWS
        XI, XJ = ca.SX.sym("xi", 3, G), ca.SX.sym("xj", 3, ROW * G)
        t, q = ca.SX.sym("t"), ca.SX.sym("q", len(self._p_used))
        V, FI, FJ = ca.SX(0), [], []
        for g in range(G):
            fi = ca.SX.zeros(3)
            for s in range(ROW):
                v, f = self._pair(XI[:, g], XJ[:, ROW * g + s], t, q)
                V, fi, FJ = V + v, fi + f, [*FJ, -f]
            FI.append(fi)
        inputs = [XI, XJ, t, q]
        outputs = [ca.SX(0) if want == "force" else V, ca.horzcat(*FI), ca.horzcat(*FJ)]
        zeros = [ca.SX(0), ca.SX.zeros(3, G), ca.SX.zeros(3, ROW * G)]
        if want == "energy":
            outputs, zeros = outputs[:1], zeros[:1]
        full = ca.Function("pairs_group", inputs, outputs, {"cse": True})
        nothing = ca.Function("pairs_none", inputs, zeros)
        return ca.Function.conditional("pairs_rows", [nothing], full)
