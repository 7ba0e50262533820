"""The effects library: each effect contributes one kind of term to the equations of motion.

An effect returns a term for exactly one of four slots (the Model sums each slot and
assembles only the slots some effect fills):

- ``potential``  V(x, t)                    force −∂V/∂x
- ``generalized_potential`` U(x, v, t)      force −∂U/∂x + d/dt ∂U/∂v   (U linear in v)
- ``dissipation`` Rayleigh R(x, v)          force −∂R/∂v
- ``applied_force`` F(x, v, t) ∈ R^(3N)     added as it is
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence

import casadi as ca
import numpy as np

from ..codegen.interval import where_negative
from ..errors import InputError
from . import constraints, expressions
from .constraints import BATCH_FROM, Distance, Labelled, _as_list, _fmt, _three, pair_batch, pair_ends
from .symbols import Batch, Formula, Stacked, pair_formula


class Effect(Labelled):
    """Base class: ``slot`` names the term, ``term(s)`` builds it from Symbols ``s``."""

    kind = "effect"
    slot: str = ""
    #: Fields whose plain numbers are inputs of the Structure's Functions (constrained.lifting).
    numbers: tuple[str, ...] = ()

    def term(self, s):
        raise NotImplementedError

    @classmethod
    def batch_terms(cls, items: list, s) -> tuple[list[int], Formula, Batch | None] | None:
        """``(plain, column, batch)``: the positions in ``items`` of those with a term of one
        formula, those terms (each what ``term`` builds) as one column built together (a
        Formula: made into SX nodes when asked for), and their Batch (None: numbers not all
        lifted); None when the class has no such form."""
        return None

    def term_and_batch(self, s) -> tuple:
        """``(term(s), the Batch of its summands when it builds them all by one formula)``."""
        return self.term(s), None


def _other_end(s, b, point, where):
    if (b is None) == (point is None):
        raise InputError("give exactly one of 'b' (a particle) or 'point'", where=where)
    return s.position(b, where) if b is not None else s.point(point, f"{where}.point")


class Gravity(Effect):
    """Uniform field: force m_i g on each particle; V = −Σ m_i g·x_i."""

    slot = "potential"
    numbers = ("g",)

    def __init__(self, g, particles=None, *, name=None, where=None):
        self.g, self.name, self.where, self.particles = g, name, where, None
        _three(g, f"{self.where or 'effect gravity'}.g", "Gravity([0, -9.81, 0]) for g = 9.81 m/s² along −y")
        self.particles = None if particles is None else _as_list(particles, self._where(), "'particles'")

    @property
    def label(self) -> str:
        return self.name or f"gravity g={_fmt(self.g)} m/s²"

    def term(self, s):
        return self.term_and_batch(s, batch=False)[0]

    def term_and_batch(self, s, batch: bool = True) -> tuple:
        """V = −Σ m_i g·x_i, and (``batch``, plain masses and g) the Batch of its summands
        −m_i g·x_i, one per particle, holding them (``values``: the mapped build takes them
        instead of unfolding the sum)."""
        where = self._where()
        g = s.point(self.g, f"{where}.g")
        names = self.particles if self.particles is not None else list(s._index)
        if not names:
            return 0.0, None
        # in a few CasADi calls (one per particle would dominate large builds): −dot(gᵀP, m)
        particles = s.indices(names, where)
        products = ca.mtimes(g.T, s.columns(names, where)).T * s.mass_column(particles)
        term = -ca.sum1(products)
        entries = s.number_entries([v for v in self.g if not (isinstance(v, int | float) and v == 0)])
        if not batch or entries is None or not len(entries) or s.mass_entries is None:
            return term, None
        # (g not all zero, masses symbols of p: each product g·x_i m_i a product of symbols, so
        # the sum unfolds into exactly the summands −(g·x_i m_i))
        particles = np.array(particles, dtype=np.int64)
        masses = np.asarray(s.mass_entries, np.int64)[particles]
        n = len(names)
        return term, Batch(np.zeros(n, np.int64), np.arange(n, dtype=np.int64), particles[:, None],
                           np.concatenate([np.repeat(entries[None, :], n, axis=0), masses[:, None]], axis=1),
                           -products)


class Spring(Effect):
    """Linear spring: V = ½ k (|x_a − x_b| − rest)², between particles or to a point."""

    slot = "potential"
    numbers = ("point", "k", "rest")

    def __init__(self, a, b=None, *, point=None, k, rest=0.0, name=None, where=None):
        self.a, self.b, self.point, self.k, self.rest = a, b, point, k, rest
        self.name, self.where = name, where

    @classmethod
    def between(cls, a: str, b: str, k: float, rest: float, where: str | None = None) -> Spring:
        """``Spring(a, b, k=k, rest=rest, where=where)`` of checked values (two particles' names,
        finite floats), its attributes set at once: a large scene's springs (scene.plain)."""
        return cls.bare(a=a, b=b, point=None, k=k, rest=rest, name=None, where=where)

    @property
    def label(self) -> str:
        other = self.b if self.b is not None else _fmt(self.point)
        return self.name or f"spring {self.a}–{other} (k={_fmt(self.k)} N/m)"

    def term(self, s):
        where = self._where()
        d = s.position(self.a, where) - _other_end(s, self.b, self.point, where)
        k = s.time_function(self.k, f"{where}.k")
        rest = s.time_function(self.rest, f"{where}.rest")
        if isinstance(self.rest, int | float) and self.rest == 0:
            return 0.5 * k * ca.dot(d, d)  # smooth at d = 0
        return 0.5 * k * (ca.sqrt(ca.dot(d, d)) - rest) ** 2

    @classmethod
    def batch_terms(cls, items: list, s) -> tuple[list[int], Formula, Batch | None]:
        """The terms of springs between two particles whose k and rest are plain numbers
        (entries of p, constrained.lifting) as one column: one CasADi call per operation
        instead of several per spring (a cloth's shear springs)."""
        plain, ends = pair_ends(items, s, ("k", "rest"))
        if not plain:
            return plain, Formula.of(ca.SX(0, 1)), None
        springs = [items[j] for j in plain]
        ks, rests = [e.k for e in springs], [e.rest for e in springs]
        return plain, pair_formula(s, ends, [ks, rests], lambda d, k, rest: (0.5 * k * (d - rest) ** 2).T), \
            pair_batch(items, plain, s, [ks, rests], ends)


class Potential(Effect):
    """A potential energy V(particle coordinates, t) from a formula string."""

    slot = "potential"

    def __init__(self, expr: str, *, name=None, where=None):
        self.expr, self.name, self.where = expr, name, where

    @property
    def label(self) -> str:
        return self.name or f"potential {self.expr}"

    def term(self, s):
        return s.parse(self.expr, f"{self._where()}.expr")


class Central(Effect):
    """A central potential V(r), r = |x_a − x_b| or |x_a − point|; ``expr`` in r (and t)."""

    slot = "potential"
    numbers = ("point",)

    def __init__(self, a, b=None, *, point=None, expr: str, name=None, where=None):
        self.a, self.b, self.point, self.expr = a, b, point, expr
        self.name, self.where = name, where

    @property
    def label(self) -> str:
        other = self.b if self.b is not None else _fmt(self.point)
        return self.name or f"central V(r) = {self.expr} about {other}"

    def term(self, s):
        where = self._where()
        d = s.position(self.a, where) - _other_end(s, self.b, self.point, where)
        r = ca.sqrt(ca.dot(d, d))
        return s.parse(self.expr, f"{where}.expr", extra={"r": r})


class Pairwise(Effect):
    """V = Σ_{i<j} φ(r_ij), r_ij = |x_i − x_j|, over every pair of the listed particles (all
    when none are listed): gravitation, Coulomb, Lennard-Jones, soft repulsion, the Fekete
    problem's −log r. ``expr`` in r (and t, parameters), parsed once.

    ``cutoff`` (m): only pairs closer than r_c count, through the shifted
    φ_c(r) = φ(r) − φ(r_c) − (r − r_c) φ'(r_c) − ½ (r − r_c)² φ''(r_c) (0 beyond r_c: energy,
    force and its derivative continuous, so the energy is conserved and error-controlled
    steps cross r_c smoothly), found by a neighbour list kept ``skin`` beyond r_c (default
    0.1 r_c), valid while no particle has moved more than skin/2 and rebuilt by runs at skin/4.
    ``exclude_bonded``: leave out the pairs joined by a distance constraint.

    From model.pairs.MAPPED_PAIRS_FROM pairs the Structure builds φ once as a mapped kernel
    (constrained.model.pairs, ``pair_spec``); fewer are written out pair by pair (``term``)."""

    slot = "potential"

    def __init__(self, expr: str, particles=None, *, cutoff=None, skin=None, exclude_bonded: bool = False,
                 name=None, where=None):
        self.expr, self.name, self.where = expr, name, where
        self.particles = self.cutoff = None  # (the label, in messages, reads them)
        self.particles = None if particles is None else _as_list(particles, self._where(), "'particles'")
        for key, value in (("cutoff", cutoff), ("skin", skin)):
            if value is not None and not (isinstance(value, int | float) and not isinstance(value, bool)
                                          and math.isfinite(value) and value > 0):
                raise InputError(f"'{key}' must be a positive length in m (a plain number), got {value!r}",
                                 where=f"{self._where()}.{key}")
        if skin is not None and cutoff is None:
            raise InputError("'skin' is the neighbour list's margin beyond 'cutoff': give a cutoff too",
                             where=f"{self._where()}.skin")
        if not isinstance(exclude_bonded, bool):
            raise InputError(f"'exclude_bonded' must be true or false, got {exclude_bonded!r}",
                             where=f"{self._where()}.exclude_bonded")
        self.cutoff = None if cutoff is None else float(cutoff)
        self.skin = None if cutoff is None else float(skin if skin is not None else 0.1 * cutoff)
        self.exclude_bonded = exclude_bonded

    @property
    def label(self) -> str:
        over = "all particles" if self.particles is None else f"{len(self.particles)} particles"
        cut = f", cutoff {_fmt(self.cutoff)} m" if self.cutoff is not None else ""
        return self.name or f"pairwise V(r) = {self.expr} over {over}{cut}"

    def closest_pair(self, system, x) -> tuple[str, str, float] | None:
        """(a, b, |x_a − x_b|) of the closest two of the effect's particles at positions ``x``
        (3N): where φ(r) is most likely singular (two particles on one point). None for fewer
        than two particles."""
        names = [q.name for q in system.particles]
        index = {name: k for k, name in enumerate(names)}
        rows = np.array([index[p] for p in (self.particles or names) if p in index], dtype=np.int64)
        if len(rows) < 2:
            return None
        from scipy.spatial import cKDTree

        points = np.asarray(x, float).reshape(-1, 3)[rows]
        distance, neighbour = cKDTree(points).query(points, k=2)
        i = int(np.argmin(distance[:, 1]))
        a, b = sorted((int(rows[i]), int(rows[int(neighbour[i, 1])])))
        return names[a], names[b], float(distance[i, 1])

    def _parsed(self, s):
        """(names, r, φ(r)) of the effect, its particles checked."""
        where = self._where()
        names = self.particles if self.particles is not None else list(s._index)
        if len(set(names)) != len(names):
            raise InputError("'particles' lists a particle twice", where=f"{where}.particles")
        for p in names:
            s.index(p, where)
        r = ca.SX.sym("r")
        return names, r, ca.SX(s.parse(self.expr, f"{where}.expr", extra={"r": r}))

    def _excluded(self, s, names) -> np.ndarray:
        """(E, 2) positions in ``names`` of the pairs joined by a distance constraint."""
        if not self.exclude_bonded:
            return np.zeros((0, 2), dtype=np.int64)
        place = {p: k for k, p in enumerate(names)}
        pairs = {tuple(sorted((place[c.a], place[c.b]))) for c in s.system.constraints
                 if isinstance(c, Distance) and c.b is not None and c.a in place and c.b in place}
        return np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2)

    def pair_spec(self, s):
        """The effect as one mapped kernel (constrained.model.pairs.PairSpec), or None where it
        is written out pair by pair: fewer than MAPPED_PAIRS_FROM pairs, or a φ that reads
        particle coordinates besides r."""
        from .pairs import MAPPED_PAIRS_FROM, PairSpec

        names, r, phi = self._parsed(s)
        if len(names) * (len(names) - 1) // 2 < MAPPED_PAIRS_FROM or ca.depends_on(phi, s.x):
            return None
        indices = np.array([s.index(p, self._where()) for p in names], dtype=np.int64)
        return PairSpec(self.label, r, phi, indices, self.cutoff, self.skin or 0.0, self._excluded(s, names))

    def term(self, s):
        """V written out pair by pair (the shifted φ_c with a cutoff; excluded pairs left
        out): one SX graph of n(n−1)/2 terms."""
        from .pairs import effective

        where = self._where()
        names, r, phi = self._parsed(s)
        positions = [s.position(p, where) for p in names]
        excluded = {tuple(e) for e in self._excluded(s, names).tolist()}
        pairs = [(i, j) for i in range(len(names)) for j in range(i + 1, len(names))
                 if (i, j) not in excluded]
        if not pairs:
            return ca.SX(0)
        # φ may also use t, coordinates and (symbolic) parameters p
        pair = ca.Function("pair_potential", [r, s.x, s.t, s.p], [effective(phi, r, self.cutoff)])
        return sum((pair(ca.norm_2(positions[i] - positions[j]), s.x, s.t, s.p) for i, j in pairs),
                   ca.SX(0))


class Damping(Effect):
    """Rayleigh dissipation R = ½ c Σ|v_i|² (listed particles), or ½ c |v_a − v_b|² (a pair)."""

    slot = "dissipation"
    numbers = ("coefficient",)

    def __init__(self, coefficient, particles=None, *, a=None, b=None, name=None, where=None):
        self.coefficient, self.a, self.b, self.name, self.where = coefficient, a, b, name, where
        self.particles = None
        if (a is None) != (b is None):
            raise InputError("pairwise damping needs both 'a' and 'b'", where=self._where())
        if a is not None and particles is not None:
            raise InputError("give either 'particles' or the pair 'a', 'b', not both", where=self._where())
        self.particles = None if particles is None else _as_list(particles, self._where(), "'particles'")
        if isinstance(coefficient, int | float) and not isinstance(coefficient, bool) and not (
                math.isfinite(coefficient) and coefficient >= 0):
            why = ("a Rayleigh function R = ½ c |v|² with c < 0 is not dissipation but an energy source "
                   "(the force −c v pushes along v); for a driven particle write the force itself (type = "
                   "\"force\", expr = [\"g*vx_p\", \"g*vy_p\", \"g*vz_p\"])" if coefficient < 0
                   else "give a finite number")
            raise InputError(f"the damping coefficient must be a finite number ≥ 0 N·s/m, got "
                             f"{coefficient!r}: {why}", where=f"{self._where()}.coefficient")

    @property
    def label(self) -> str:
        on = f"{self.a}–{self.b}" if self.a else ", ".join(self.particles or ["all"])
        return self.name or f"damping c={_fmt(self.coefficient)} N·s/m on {on}"

    def negative_coefficient(self, values: Mapping[str, float], t0: float,
                             t_end: float) -> tuple[float, float] | None:
        """(t, c(t)), the lowest found, where a coefficient given by a formula of t is negative or
        not finite anywhere on [t0, t_end], however briefly (for the parameters' and definitions'
        ``values``, name -> number, as ``System.parameter_values``; bounded over every instant in
        interval arithmetic, not sampled: ``codegen.interval.where_negative``), else None. A plain
        number is checked when the effect is made, a formula only once its parameters have values
        (a fit without bounds, ``--set``, a member of ``simulate_many``)."""
        if not isinstance(self.coefficient, str):
            return None
        t = ca.SX.sym("t")  # (as Symbols.time_function parses it)
        c = expressions.parse(self.coefficient, {"t": t, **values}, where=f"{self._where()}.coefficient")
        return where_negative(ca.Function("c", [t], [c]), t0, t_end)

    def refusal(self, values: Mapping[str, float], t0: float, t_end: float) -> InputError | None:
        """The InputError refusing this coefficient for these ``values`` when it is negative or
        not finite somewhere on [t0, t_end] (``negative_coefficient``), naming the key, the lowest
        value and its time; else None. ``simulate`` raises it; ``simulate_many`` gives its text
        to the member it refuses (run/variants/refusals.py): one sentence for both."""
        bad = self.negative_coefficient(values, t0, t_end)
        if bad is None:
            return None
        lowest = " (its lowest over the run)" if math.isfinite(bad[1]) else ""
        return InputError(
            f"the damping coefficient {self.coefficient!r} is {bad[1]:g} N·s/m at t = {bad[0]:g} "
            f"s{lowest} for these parameter values: a Rayleigh function R = ½ c |v|² with c < 0 is not "
            "dissipation but an energy source (the force −c v pushes along v); give parameter values "
            "that keep it ≥ 0 (a fit: bounds), or write a driving force itself (type = \"force\")",
            where=f"{self._where()}.coefficient")

    def term(self, s):
        where = self._where()
        c = s.time_function(self.coefficient, f"{where}.coefficient")
        if self.a is not None:
            dv = s.velocity(self.a, where) - s.velocity(self.b, where)
            return 0.5 * c * ca.dot(dv, dv)
        names = self.particles if self.particles is not None else list(s._index)
        return 0.5 * c * sum(ca.dot(s.velocity(p, where), s.velocity(p, where)) for p in names)


def damping_formulas(effects) -> list[Damping]:
    """The dampers among ``effects`` whose coefficient is a formula (checked by ``Damping.refusal``
    once the parameters have values)."""
    return [e for e in effects if isinstance(e, Damping) and isinstance(e.coefficient, str)]


class Force(Effect):
    """An applied force F(particle coordinates, velocities, t) on one particle (3 formulas)."""

    slot = "applied_force"
    numbers = ("expr",)

    def __init__(self, particle: str, expr: Sequence, *, name=None, where=None):
        self.particle, self.expr, self.name, self.where = particle, expr, name, where
        if isinstance(expr, str) or not isinstance(expr, Sequence) or len(expr) != 3:
            raise InputError(
                f"'expr' must be a list of 3 formulas (Fx, Fy, Fz), got {expr!r}", where=self._where()
            )

    @property
    def label(self) -> str:
        return self.name or f"force on {self.particle}"

    def term(self, s):
        where = self._where()
        i = s.index(self.particle, where)
        F = ca.SX.zeros(s.x.shape[0])
        for k in range(3):
            F[3 * i + k] = s.parse(self.expr[k], f"{where}.expr[{k}]", velocities=True)
        return F


class Electromagnetic(Effect):
    """Generalized potential U = Σ q_i (φ(x_i, t) − v_i·A(x_i, t)), SI units.

    Gives the Lorentz force q (E + v × B) with E = −∇φ − ∂A/∂t, B = ∇ × A.
    """

    slot = "generalized_potential"
    numbers = ("charges", "phi", "A")

    def __init__(self, charges: Mapping[str, float], phi="0", A=("0", "0", "0"), *, name=None, where=None):
        self.charges, self.phi, self.A, self.name, self.where = dict(charges), phi, A, name, where
        if not self.charges:
            raise InputError("'charges' must name at least one particle", where=self._where())
        if isinstance(A, str) or not isinstance(A, Sequence) or len(A) != 3:
            raise InputError(f"'A' must be a list of 3 formulas, got {A!r}", where=self._where())

    @property
    def label(self) -> str:
        return self.name or "electromagnetic field"

    def term(self, s):
        where = self._where()
        U = 0.0
        for pname, q in self.charges.items():
            x, v = s.position(pname, where), s.velocity(pname, where)
            q = s.time_function(q, f"{where}.charges.{pname}")
            phi = s.parse_field(self.phi, f"{where}.phi", x)
            A = ca.vertcat(*[s.parse_field(a, f"{where}.A[{k}]", x) for k, a in enumerate(self.A)])
            U = U + q * (phi - ca.dot(v, A))
        return U


def effect_terms(effects: list, s, skip=()) -> tuple[Stacked, list[Batch]]:
    """Each effect's ``term(s)`` in order (``ca.SX(0)`` for the indices in ``skip``), a Stacked:
    runs of BATCH_FROM or more of one class through its ``batch_terms``, kept as SX columns (the
    same expressions). And the Batches of terms built by one formula (``items``: indices into
    ``effects``)."""
    out, batches = Stacked(), []
    for k, j in constraints.class_runs(effects):
        cls = type(effects[k])
        kept = [i for i in range(k, j) if i not in skip] if skip else list(range(k, j))
        built = cls.batch_terms(effects[k:j] if not skip else [effects[i] for i in kept], s) \
            if len(kept) >= BATCH_FROM else None
        plain, column, batch = built if built is not None else ([], None, None)
        if batch is not None:
            batches.append(batch.shifted(kept))
        together = np.zeros(j - k, bool)  # (each of the run's effects: built in the column)
        together[np.asarray(kept, np.int64)[plain] - k] = True
        i, row = k, 0
        while i < j:
            if together[i - k]:  # a stretch built together
                stop = i + int(np.argmin(np.append(together[i - k:], False)))
                out.add_column(column.part(np.arange(row, row + stop - i)))
                i, row = stop, row + stop - i
                continue
            term, own = (ca.SX(0), None) if i in skip else effects[i].term_and_batch(s)
            if own is not None and len(own.items) >= BATCH_FROM:
                batches.append(own.shifted([i]))
            out.add(term, None if own is None else own.values[0])  # (its summands' formula's dependence)
            i += 1
    return out, batches


def _total(terms: list):
    """``sum(terms, ca.SX(0))`` of scalar terms as one CasADi sum: the same expression (t₁ + t₂ + …
    in order), not one Python addition per term (2.6 s for a cloth's 40,000 springs)."""
    if isinstance(terms, Stacked) and len(terms) >= 2 and terms.scalars():  # (its columns kept whole)
        return ca.sum1(terms.column())
    terms = [term if isinstance(term, ca.SX) else ca.SX(term) for term in terms]
    if len(terms) < 2 or any(term.shape != (1, 1) for term in terms):
        return sum(terms, ca.SX(0))
    return ca.sum1(ca.vertcat(*terms))


def forces(slots: dict, x, v, t, *, deferred: bool = False) -> tuple:
    """(F, V, U, ∂U/∂v, active slots) from the effects' terms by slot:

        F = −∂V/∂x − ∂U/∂x + d/dt ∂U/∂v − ∂R/∂v + Σ applied,   V = Σ potentials, U = Σ
        generalized potentials (linear in v: d/dt ∂U/∂v = (∂²U/∂v∂x) v + ∂²U/∂v∂t), R = Σ
        dissipations.

    ``deferred``: F and V as functions of no arguments that build them when first called
    (the same expressions). With potentials alone, F = −∂V/∂x is then not differentiated here
    (a large model's runs use the vectorized build's forces: 0.2 s for a cloth's 40,000
    springs), nor V summed (its columns of terms are made into SX nodes only then:
    ``symbols.Formula``), and whether it depends on t is V's answer (∂V/∂x reads t only where
    V does)."""
    if deferred and not any(slots[k] for k in ("generalized_potential", "dissipation", "applied_force")):
        V = functools.cache(lambda: _total(slots["potential"]) if slots["potential"] else ca.SX(0))
        active = {"potential"} if slots["potential"] else set()
        # (none of a Stacked's terms of t: nor is V; else V is asked, a sum may cancel)
        if slots["potential"] and Stacked.may(slots["potential"], t) and ca.depends_on(V(), t):
            active.add("time_dependent_forces")
        zero = (ca.SX.zeros(x.numel()), ca.SX(0), ca.SX.zeros(x.numel()))
        return functools.cache(lambda: zero[0] - ca.gradient(V(), x) if slots["potential"] else zero[0]), \
            V, zero[1], zero[2], active
    if deferred:
        F, V, *rest = forces(slots, x, v, t)
        return (lambda: F), (lambda: V), *rest
    active = set()
    F = ca.SX.zeros(x.numel())
    V = U = ca.SX(0)
    dU_dv = ca.SX.zeros(x.numel())
    if slots["potential"]:
        active.add("potential")
        V = _total(slots["potential"])
        F -= ca.gradient(V, x)
    if slots["generalized_potential"]:
        active.add("generalized_potential")
        U = _total(slots["generalized_potential"])
        dU_dv = ca.gradient(U, v)
        if ca.depends_on(dU_dv, v):
            raise InputError(
                "a generalized potential must be linear in the velocities "
                "(U = U0(x, t) + v·W(x, t)); this one is not"
            )
        # Q = −∂U/∂x + d/dt ∂U/∂v, with d/dt ∂U/∂v = (∂²U/∂v∂x) v + ∂²U/∂v∂t
        F += -ca.gradient(U, x) + ca.jtimes(dU_dv, x, v) + ca.jacobian(dU_dv, t)
    if slots["dissipation"]:
        active.add("dissipation")
        R = _total(slots["dissipation"])
        F -= ca.gradient(R, v)
    if slots["applied_force"]:
        active.add("applied_force")
        for term in slots["applied_force"]:
            F += term
    if ca.depends_on(F, t) or (V.numel() and ca.depends_on(V, t)):
        active.add("time_dependent_forces")
    return F, V, U, dU_dv, active


EFFECT_TYPES = {"gravity": Gravity, "spring": Spring, "potential": Potential, "central": Central,
                "pairwise": Pairwise, "damping": Damping, "force": Force, "electromagnetic": Electromagnetic}
