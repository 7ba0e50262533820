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
    F = F_rest − S · vec([∇V_g(X_g)]_g)    (S: the 0/1 matrix scattering local gradients),
    W = W_rest + Σ_g Σ_k V_g(X_g[:, k])   (``forces_and_potential``: h − ½ vᵀMv with F).

The rest (rows and summands of small groups, the other force slots) is one SX graph built as
the Structure builds it (``model.forces``). J's sparsity, the permutations back to scene
order and S are data of the generated code, not code: its size does not grow with N.
The numbers are those of the Structure's Functions up to the order of floating-point sums
(tests/test_mapped.py).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..model.cache import ParametricView, built_once, structure_cache
from ..model.structure import Model, Structure, forces
from ..model.symbols import Stacked
from .graph import acceleration_graph
from .vectorized.columns import sorted_unique
from .vectorized.grouping import MAX_KINDS, MIN_GROUP, Group, grouped, lifted, summands  # noqa: F401

#: dopri's compiled step loop is built on the mapped Functions from this many coordinates
#: (a plain Model, not a held row subset). Below, the unrolled SX graph compiles in a second
#: or two and runs faster (a 16-link chain's loop: 0.70 against 0.81 ms); from about 48 links
#: a chain runs as fast mapped, from about 100 faster. An all-pairs potential runs slower
#: mapped (about 1.6x: gathers and scatters), but the unrolled graph of its N²/2 terms takes
#: the C compiler minutes (docs/performance.md, "Compile time").
MAPPED_FROM = 150
#: The Functions the mapped build provides (the others are the Structure's).
NAMES = ("constraint", "jacobian", "velocity_terms", "dynamics", "forces_and_potential", "row_scales")
#: Their constraint outputs and whether they take the velocities.
_OUTPUTS = {"constraint": (("f",), False), "jacobian": (("f", "J"), False),
            "velocity_terms": (("J", "f_t"), False), "dynamics": (("J", "gamma"), True),
            "forces_and_potential": ((), True), "row_scales": (("scale",), False)}


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
        row_batches = [(b.items + b.offsets, b.particles, b.numbers) for b in e.row_batches]
        self.rows, rest_rows = grouped(e.rows, e.x, e.t, e.p, symbols, row_batches)
        self.rest_place = np.array(rest_rows, dtype=np.int64)
        terms, counts = _split(e.slots["potential"], e.term_batches)
        term_batches = _summand_batches(e.term_batches, counts)
        self.terms, rest_terms = grouped(terms, e.x, e.t, e.p, symbols, term_batches)
        self.rest_slots = {**e.slots, "potential": [terms[k] for k in rest_terms]}
        self._functions: dict[str, ca.Function] = {}

    @property
    def mapped_instances(self) -> int:
        """How many rows and potential terms the kernels evaluate."""
        return sum(g.index.shape[1] for g in (*self.rows, *self.terms))

    # --- the SX pieces: one kernel per group, the rest -------------------------------------
    def _rest(self, outputs: tuple, with_v: bool, with_forces: bool,
              with_potential: bool = False) -> ca.Function:
        e = self.e
        f = ca.vertcat(*[e.rows[k] for k in self.rest_place]) if len(self.rest_place) else ca.SX(0, 1)
        terms = _row_terms(f, e.x, e.v, e.t, lambda i: i // 3)
        terms["J"] = ca.vertcat(*terms["J"].nonzeros()) if terms["J"].nnz() else ca.SX(0, 1)
        out = [terms[k] for k in outputs]
        if with_forces:
            F, V, U, dU_dv, _ = forces(self.rest_slots, e.x, e.v, e.t)
            out += [ca.sparsify(F), *([V + U - ca.dot(e.v, dU_dv)] if with_potential else [])]
        inputs = [e.x, e.v, e.t, e.p] if with_v else [e.x, e.t, e.p]
        return ca.Function("rest", inputs, out)

    def _kernel(self, g: Group, outputs: tuple, with_v: bool, name: str) -> ca.Function:
        e, xl = self.e, g.xl
        vl = ca.SX.sym("vl", xl.numel())
        terms = _row_terms(g.local, xl, vl, e.t, lambda i: g.parts[i])
        out = [ca.densify(terms[k].T if k == "J" else terms[k]) for k in outputs]
        inputs = [xl, vl, g.c, e.t, self._p(g)] if with_v else [xl, g.c, e.t, self._p(g)]
        kernel = ca.Function(f"{name}_kernel", inputs, out)
        shared = [len(inputs) - 2, len(inputs) - 1]  # t and p: the same for every instance
        return kernel.map(f"{name}_map", "serial", g.index.shape[1], shared, [])

    def _p(self, g: Group) -> ca.SX:
        """The kernel's input p: the Structure's, or an empty one when every entry of p the
        kernel reads was lifted into its data (the usual case: the map then passes no p)."""
        return self.e.p if ca.depends_on(g.local, self.e.p) else ca.SX.sym("p", 0)

    def _p_argument(self, g: Group, P):
        return P if ca.depends_on(g.local, self.e.p) else ca.MX(0, 1)

    def _potential_kernel(self, g: Group, name: str, with_value: bool = False) -> ca.Function:
        """The group's ∇V_k (and V_k: ``with_value``) mapped over its instances."""
        e = self.e
        gradient = ca.densify(ca.gradient(g.local, g.xl))
        inputs = [g.xl, g.c, e.t, self._p(g)]
        kernel = (ca.Function(f"{name}_kernel", inputs, [gradient, g.local], {"cse": True}) if with_value
                  else ca.Function(f"{name}_kernel", inputs, [gradient]))
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
        X, V, T = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
        structure = self.structure
        P_full = ca.MX.sym("p", structure.n_p)  # the physical p, then the pairs' neighbour lists
        P = P_full[:structure.n_physical] if structure.n_p != structure.n_physical else P_full
        dynamics = name in ("dynamics", "forces_and_potential")
        potential = name == "forces_and_potential"  # (F, W = h − ½ vᵀMv: V, and U's part)
        rest = self._rest(outputs, with_v, dynamics, potential)(*([X, V, T, P] if with_v else [X, T, P]))
        rest = rest if isinstance(rest, list | tuple) else [rest]
        pieces = {k: [rest[i]] for i, k in enumerate(outputs)}
        for j, g in enumerate(self.rows if outputs else ()):
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
            W = rest[-1] if potential else None
            F = rest[-2] if potential else rest[-1]
            gradients = []
            for j, g in enumerate(self.terms):
                out = self._potential_kernel(g, f"potential_{'value_' * potential}{j}", potential)(
                    _gather(X, g.index), g.data(P), T, self._p_argument(g, P))
                gradients.append(ca.vec(out[0] if potential else out))
                W = W + ca.sum2(out[1]) if potential else W
            if gradients:
                F = F - ca.mtimes(self._scatter(), ca.vertcat(*gradients))
            for term in structure.pairs:  # each pair potential: its own mapped kernel
                e, f = term.energy_and_forces(X, T, P_full, structure.n_physical,
                                              want="both" if potential else "force")
                F, W = F + f, (W + e if potential else W)
            outs, out_names = [ca.densify(F), *outs], ["F", *out_names]
            if potential:
                outs, out_names = [*outs, W], [*out_names, "W"]
        inputs, in_names = (([X, V, T, P_full], ["x", "v", "t", "p"]) if with_v
                            else ([X, T, P_full], ["x", "t", "p"]))
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


def _split(terms, batches) -> tuple[Stacked, np.ndarray]:
    """The summands (``summands``) of every term in order, as one Stacked, and how many each
    term has. A term whose summands a Batch holds (``values``: gravity's) takes them from it
    instead of unfolding its sum; the terms of a Batch with one summand each (a run of springs)
    are taken whole when its first one is (they are one formula: the same top operation), a
    column of them (``Stacked``) as it is."""
    held = {int(b.items[0]): b.values for b in batches
            if b.values is not None and len(b.items) and np.all(b.items == b.items[0])
            and np.array_equal(b.offsets, np.arange(len(b.items))) and b.values.numel() == len(b.items)}
    whole = np.zeros(len(terms), bool)
    for b in batches:
        if len(b.items) and not b.offsets.any() and len(sorted_unique(b.items)) == len(b.items):
            first = terms[b.items[0]]
            whole[b.items] = len(parts := summands(first)) == 1 and parts[0] is first
    out, counts = Stacked(), np.ones(len(terms), np.int64)
    for start, segment in (terms.segments() if isinstance(terms, Stacked) else [(0, list(terms))]):
        if not isinstance(segment, list):  # a column of terms built by one formula (a Formula)
            if whole[start:start + segment.numel()].all():
                out.add_column(segment)  # (as it is: made into SX nodes only where asked for)
                continue
            segment = ca.vertsplit(segment.column())
        for k, term in enumerate(segment, start):
            if k in held:
                out.add_column(held[k])
                counts[k] = held[k].numel()
            elif whole[k]:
                out.add(term)
            else:
                parts = summands(term)
                counts[k] = len(parts)
                for part in parts:
                    out.add(part)
    return out, counts


def _summand_batches(batches, counts: np.ndarray) -> list[tuple]:
    """The term Batches (``items``: a potential's place in its slot, ``offsets``: its summand)
    as (positions among the summands flattened, particles, entries of p), ``counts`` the number
    of summands of each term; a batch whose summands are not where it says (a term that did not
    unfold as built) is dropped."""
    start = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else counts
    out = []
    for b in batches:
        if len(b.items) and np.all(b.offsets < counts[b.items]) and np.all(
                np.bincount(b.items, minlength=len(counts))[b.items] == counts[b.items]):
            out.append((start[b.items] + b.offsets, b.particles, b.numbers))
    return out


def _gather(X, index: np.ndarray) -> ca.MX:
    """The columns x[I_k] of ``index`` (d, n) as a (d, n) matrix."""
    return ca.reshape(X[index.ravel(order="F").tolist()], index.shape[0], index.shape[1])


def mapped_build(structure: Structure) -> MappedBuild:
    """The structure's MappedBuild, built once and kept beside it."""
    return built_once(structure, "mapped build", lambda: MappedBuild(structure))


def applies(model: Model) -> bool:
    """Whether step loops of ``model`` use the mapped build: a plain Model (not a held row
    subset) of MAPPED_FROM coordinates or more, without velocity rows (built only as the
    Structure builds them)."""
    return (getattr(model, "rows", None) is None and model.n_coordinates >= MAPPED_FROM
            and model.n_position_rows == model.n_constraints)


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
