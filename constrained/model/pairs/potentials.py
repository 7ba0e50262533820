"""A Structure's pair potentials together: which effects are mapped pair kernels, where their
neighbour lists sit in p, and what the Structure's Functions, a run and a diagnosis ask of them
(the energy and forces added to an SX graph's Functions, the lists' data, refreshed and checked).

p is the physical parameters (``n_physical``: the named ones, then the plain numbers), then each
pair potential's neighbour list (``PairTerm.size`` entries at its ``offset``): run data that a
Model fills at its system's positions and the runs refresh as the particles move."""

from __future__ import annotations

import casadi as ca
import numpy as np

from .kernel import PairTerm

#: Fewer pairs than this (about 25 particles) are written out pair by pair in the Structure's
#: one SX graph (``Pairwise.term``): small enough that the SX graph is the faster.
MAPPED_PAIRS_FROM = 300
#: A run rebuilds a neighbour list (and a step loop stops for it) once a particle has moved
#: this share of the skin/2 the list allows: a step taken from there still finds it valid
#: (beyond skin/2 the graph sums every pair: exact, but O(N²)).
REFRESH_SHARE = 0.5
#: An explicit method's step moves no listed particle by more than this share of the margin
#: (1 − REFRESH_SHARE) · skin/2 at its speed at the step's start (``step_limit``; the speed
#: changes within the step: the rest of the margin is for that).
STEP_SHARE = 0.8
#: The Functions that carry the pair potentials, and where: output index -> "force" or "energy".
OUTPUTS = {"dynamics": {0: "force"}, "energy": {0: "energy"}, "potential": {0: "energy"},
           "forces_and_potential": {0: "force", 1: "energy"}}



def _step_margin(term) -> float:
    """How far a listed particle may move in one step (m): STEP_SHARE of the margin a list keeps
    beyond its refresh, (1 − REFRESH_SHARE) · skin/2 (``step_limit``, ``step_held``)."""
    return STEP_SHARE * (1 - REFRESH_SHARE) * term.skin / 2

class PairPotentials:
    """The pair potentials of a system built as mapped kernels (``terms``, from the effects
    ``owners``), their data after the ``n_physical`` physical entries of p (``n_p`` in all)."""

    def __init__(self, system, s, n_coordinates: int):
        self.n_physical = s.p.numel()
        terms, owners = [], []
        for k, effect in enumerate(system.effects):
            spec = effect.pair_spec(s) if hasattr(effect, "pair_spec") else None
            if spec is not None:
                offset = self.n_physical + sum(term.size for term in terms)
                terms.append(PairTerm(spec, s.t, s.p, n_coordinates=n_coordinates, offset=offset,
                                      positions=np.asarray(system.positions, float)))
                owners.append(k)
        self.terms: tuple[PairTerm, ...] = tuple(terms)
        self.owners: tuple[int, ...] = tuple(owners)
        self.n_p = self.n_physical + sum(term.size for term in terms)
        self.n_coordinates = n_coordinates
        self.time_dependent = any(term.time_dependent for term in terms)
        self.parametric = any(ca.depends_on(term.spec.phi, s.p) for term in terms)
        self._values = None

    def with_pairs(self, name: str, rest: ca.Function, *, lists: bool = True,
                   differentiable: bool = False) -> ca.Function:
        """The Function ``name`` (``OUTPUTS``), an MX Function of the full p, with the pair
        potentials' energy and forces added to its outputs: ``rest`` (the SX graph's, of the
        whole p, whose lists it ignores) plus each PairTerm's graph (``lists``: through its
        neighbour list; else every pair, which also evaluates with SX symbols;
        ``differentiable``: the list's mapped kernel, never the fused loop)."""
        inputs = [ca.MX.sym(rest.name_in(i), rest.sparsity_in(i)) for i in range(rest.n_in() - 1)]
        P = ca.MX.sym("p", self.n_p)
        out = rest.call([*inputs, P])
        x, t = inputs[0], inputs[-1]
        energy, force = 0, 0
        kinds = set(OUTPUTS[name].values())
        want = "both" if len(kinds) > 1 else kinds.pop()  # (the list's kernel computes only that)
        for term in self.terms:
            e, f = term.energy_and_forces(x, t, P, self.n_physical, lists=lists, want=want,
                                          differentiable=differentiable)
            energy, force = energy + e, force + f
        for i, kind in OUTPUTS[name].items():
            out[i] = out[i] + (force if kind == "force" else energy)
        return ca.Function(name, [*inputs, P], out, rest.name_in(), rest.name_out())

    def values(self, x, t: float, p) -> list[tuple[float, np.ndarray]]:
        """(V_k, F_k) of each pair potential at (x, t) for p (its physical entries), through
        neighbour lists built at x (no sum over every pair where a cutoff allows less)."""
        if self._values is None:
            X, T, P = ca.MX.sym("x", self.n_coordinates), ca.MX.sym("t"), ca.MX.sym("p", self.n_p)
            out = [e for term in self.terms for e in term.energy_and_forces(X, T, P, self.n_physical)]
            self._values = ca.Function("pair_values", [X, T, P], out)
        p = np.concatenate([np.asarray(p, float)[:self.n_physical], self.data(x)])
        out = self._values(x, t, p)
        out = out if isinstance(out, tuple | list) else [out]
        return [(float(out[2 * k]), np.asarray(out[2 * k + 1], float).ravel())
                for k in range(len(self.terms))]

    def data(self, x) -> np.ndarray:
        """The neighbour lists at positions ``x`` (the entries of p after the physical ones)."""
        return np.concatenate([np.zeros(0), *[term.data(x) for term in self.terms]])

    def stale(self, X, P):
        """MX: 1 when a neighbour list in P is due (a particle moved more than REFRESH_SHARE ·
        skin/2 since it was built), else 0 (0 without one, and for a list beyond its
        capacities, which is never used): step loops stop there for the run to refresh it."""
        stale = ca.MX(0)
        for term in self.terms:
            if term.size:
                gone = ca.logic_and(term.valid_graph(P), ca.logic_not(term.fresh_graph(X, P, REFRESH_SHARE)))
                stale = ca.logic_or(stale, gone)
        return stale

    def step_limit(self, V, P) -> ca.MX | None:
        """MX: the longest step of an explicit method from velocities V (3N) after which no
        listed particle has moved by more than STEP_SHARE of the margin a list keeps beyond its
        refresh, (1 − REFRESH_SHARE) · skin/2, at its present speed: within it the stages of
        the step find their lists valid (beyond, the graph sums every pair: exact, but O(N²)).
        No limit from a list beyond its capacity (not used); None without a list."""
        limits = []
        for term in self.terms:
            if term.size:
                margin = _step_margin(term)
                limits.append(ca.if_else(term.valid_graph(P), margin / ca.fmax(term.fastest_graph(V), 1e-300),
                                         ca.inf))
        if not limits:
            return None
        return limits[0] if len(limits) == 1 else ca.mmin(ca.vertcat(*limits))

    def step_held(self, v, p, h: float, names) -> str | None:
        """Where a neighbour list's ``step_limit`` at velocities ``v`` (3N) is at most the step h
        proposed (a step size collapsed by a skin far below the distance particles move): the words
        naming the effect, its skin, the fastest particle (``names``) and the fix; else None."""
        v = np.asarray(v, float).reshape(-1, 3)
        for term in self.terms:
            if not term.size or p[term.offset] != 1:
                continue
            speeds = np.linalg.norm(v[term.spec.particles], axis=1)
            k = int(np.argmax(speeds))
            margin = _step_margin(term)
            limit = margin / max(float(speeds[k]), 1e-300)
            if limit <= h:  # (a step held by the limit proposes at most MAX_FACTOR times it)
                return (f"the neighbour list of '{term.label}' holds each step to {limit:.3g} s: a step may "
                        f"move a particle by {margin:.3g} m at most (a share of the list's skin, "
                        f"{term.skin:.3g} m), and particle '{names[term.spec.particles[k]]}' moves at "
                        f"{speeds[k]:.3g} m/s; give the effect a 'skin' (and 'cutoff') of the distances "
                        "the particles move")
        return None

    def refreshed(self, p: np.ndarray, x) -> np.ndarray | None:
        """p with the neighbour lists rebuilt at positions ``x`` where a particle has moved more
        than REFRESH_SHARE · skin/2 since they were built, or None when every list is good
        (the graph is exact either way: a stale list is only slower)."""
        stale = [term for term in self.terms
                 if term.size and not term.fresh(x, p[term.offset:term.offset + term.size], REFRESH_SHARE)]
        if not stale:
            return None
        p = np.array(p, dtype=float)
        for term in stale:
            p[term.offset:term.offset + term.size] = term.data(x)
        return p
