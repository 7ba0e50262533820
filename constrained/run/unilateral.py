"""One-sided constraints: the active set, the release test and the impact law.

A one-sided row keeps its **gap** ``g = side · f ≥ 0`` (``Constraint.side``: −1 for a distance,
a string with |d| ≤ length; +1 for planes, surfaces and custom formulas, where the particle
stays on the side f ≥ 0). It can only push along ∇g: with ``M a = F + Jᵀλ`` its force is
``λ ∇f = (side · λ) ∇g``, so the **allowed sign** is ``μ = side · λ ≥ 0``:

=========================  =========  ================================
constraint                 side       holding when
=========================  =========  ================================
distance (string, rope)    −1         λ ≤ 0 (tension −λ ≥ 0)
plane, surface, custom     +1         λ ≥ 0 (the push along ∇f)
=========================  =========  ================================

While a row is **active** it is held as an equality; it is **released** when μ would turn
negative. An inactive row **closes** when its gap falls to zero; the impact law then gives
the velocity jump. The time loop that switches between these is constrained.hybrid; this
module holds the per-state numerics and the event functions a segment watches
(``SegmentWatch``). Linear systems go through ``manifold.schur_solve``.

Impact law (mass-weighted, Newton's restitution on each closing row c, the active rows a
kept): with c = J v + f_t the constraint velocities, find the impulse P over the rows a ∪ c
with ``v⁺ = v⁻ + M⁻¹ Jᵀ P`` and ``c⁺_a = 0``, ``c⁺_c = −e c⁻_c``, i.e.

    (J M⁻¹ Jᵀ) P = c⁺ − c⁻

— the minimum kinetic-energy change that stops (e = 0) or reverses (e > 0) the approach, so
momentum in every direction the constraints do not touch is kept.

The energy an impact dissipates is measured in the frame of the constraint (a moving wall's):
with ΔT = T⁺ − T⁻ the change in the fixed frame and A = J M⁻¹ Jᵀ,

    E_lost = −ΔT − f_tᵀ P = −½ Pᵀ (c⁺ + c⁻) ≥ 0   (e ≤ 1),

which for one row is ½ (1 − e²) m_eff u², u the approach speed relative to the surface and
m_eff = 1/A (a particle on a plane: its mass). In a frame moving with the surface (J w + f_t = 0)
it is exactly the kinetic energy lost there. ΔT itself is kept too: a moving wall does work,
so in the fixed frame an impact may even add kinetic energy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..manifold import residual
from ..manifold.algebra import SPARSE_FROM, algebra_for
from ..manifold.manifold import Manifold, constraint_values
from ..model.cache import built_once
from ..model.held import held
from ..model.structure import Model
from ..solvers.base import Event


@dataclass(frozen=True)
class OneSided:
    """The one-sided rows of a model: ``rows`` (indices), and per model row ``side`` (±1; +1 for
    two-sided rows, unused there) and ``restitution`` (0 for two-sided rows)."""

    rows: tuple[int, ...]
    side: np.ndarray
    restitution: np.ndarray

    @property
    def bilateral(self) -> tuple[int, ...]:
        one_sided_rows = set(self.rows)  # (a set: thousands of rows)
        return tuple(k for k in range(len(self.side)) if k not in one_sided_rows)


def one_sided(model: Model) -> OneSided:
    """Which rows of ``model`` are one-sided, their sides and coefficients of restitution."""
    def build():
        constraints = model.system.constraints
        owner = model.constraint_owner
        rows = tuple(int(k) for k in range(model.n_constraints) if constraints[owner[k]].unilateral)
        side = np.array([float(constraints[owner[k]].side) for k in range(model.n_constraints)])
        values = model.system.parameter_values  # (restitution may be a formula of them)
        e = np.array([constraints[owner[k]].coefficient_of_restitution(values) if k in rows else 0.0
                      for k in range(model.n_constraints)], float)
        return OneSided(rows, side, e)

    return built_once(model, "one_sided", build)


def has_one_sided(model: Model) -> bool:
    return bool(one_sided(model).rows)


# --- evaluation on a row subset ------------------------------------------------------------------
class ActiveSet:
    """The rows held during one segment of a run (every two-sided row and the active one-sided
    ones): the manifold of the model holding them (``held``, ``Manifold``: the one KKT solve
    and projection), with its multipliers spread over every model row."""

    def __init__(self, model: Model, rows, at: tuple | None = None):
        self.model = model
        self.rows = tuple(sorted(int(k) for k in rows))
        self._index = np.array(self.rows, dtype=int)
        kept = held(model, self.rows)
        # dependent held rows (a two-sided plane and a one-sided one that coincide) solved as
        # such, decided at ``at`` = (x, t): else the solve met a singular matrix (CasADi's
        # "LDL factorization has zeros in D" on stderr) before it fell back. Dense decisions only
        # (up to SPARSE_FROM rows): a large active set keeps the fallback
        dependent = at is not None and 0 < kept.n_constraints <= SPARSE_FROM
        self.manifold = Manifold.at(kept, *at) if dependent else Manifold(kept)

    @property
    def nfev(self) -> int:
        return self.manifold.counters.nfev

    def accelerations(self, x, v, t) -> tuple[np.ndarray, np.ndarray]:
        """(a, λ over the held rows), the minimum-norm multipliers where they are dependent."""
        return self.manifold.accelerations(x, v, t)

    def multipliers(self, x, v, t) -> np.ndarray:
        """λ over every model row: the active rows' multipliers, 0 on the others."""
        out = np.zeros(self.model.n_constraints)
        out[self._index] = self.accelerations(x, v, t)[1]
        return out

    def project(self, x, v, t, tol: float, max_iter: int = 20) -> tuple[np.ndarray, np.ndarray, float]:
        """The mass-weighted nearest (x, v) on the active rows (the manifold's Newton, then its
        velocity solve); returns (x, v, max |f_active| left)."""
        x, v = np.array(x, float), np.array(v, float)
        if not self.rows:
            return x, v, 0.0
        position = self.manifold.project_positions(x, t, tol=tol, max_iter=max_iter)
        return position.x, self.manifold.project_velocities(position.x, v, t), float(position.residual)


def gaps(model: Model, x, t) -> np.ndarray:
    """g = side · f over every row (only the one-sided rows' values mean a gap)."""
    return one_sided(model).side * constraint_values(model)(x, t)[0]


def _velocity_terms(model: Model, x, t):
    """(J, f_t) at (x, t): J in the model's linear algebra (``algebra_for``: SciPy CSR for a
    large model, where a dense J of a 3,000-bead rope on a floor is 0.6 GB at every event)."""
    J, f_t = model.velocity_terms(x, t)
    return algebra_for(model.n_constraints).matrix(J), np.asarray(f_t, float).ravel()


def constraint_velocities(model: Model, x, v, t) -> np.ndarray:
    """c = J v + f_t over every row (the rate of f along the motion)."""
    J, f_t = _velocity_terms(model, x, t)
    return J @ np.asarray(v, float) + f_t


def scales(model: Model, x, t) -> np.ndarray:
    """Row scales (constrained.residual): |f|/s is a distance in metres, |c|/s a speed in m/s."""
    s = residual.row_scales(model, x, t)
    return np.where(np.isfinite(s) & (s > 0), s, 1.0)


def wrong_sign(model: Model, active: ActiveSet, x, v, t, tol: float) -> list[int]:
    """The active one-sided rows whose force has the forbidden sign (μ = side·λ < −tol, in N
    per unit of the row's scale), most negative first."""
    info = one_sided(model)
    lam = active.multipliers(x, v, t)
    mu = info.side * lam * scales(model, x, t)
    held_rows = set(active.rows)
    bad = [k for k in info.rows if k in held_rows and mu[k] < -tol]
    return sorted(bad, key=lambda k: mu[k])


def holding_set(model: Model, rows, x, v, t, tol: float) -> tuple[ActiveSet, list[int]]:
    """Drop, one at a time, the one-sided row pulling (pushing) the wrong way hardest, until
    every held one-sided row has the allowed sign; returns (active set, dropped rows)."""
    active = ActiveSet(model, rows, at=(x, t))
    dropped = []
    while True:
        bad = wrong_sign(model, active, x, v, t, tol)
        if not bad:
            return active, dropped
        dropped.append(bad[0])
        active = ActiveSet(model, [k for k in active.rows if k != bad[0]], at=(x, t))


# --- the impact law ----------------------------------------------------------------------------------
#: A held row's impulse of the forbidden sign releases it only beyond this fraction of the
#: impact's largest impulse: a bead resting on a floor next to one landing (the link between
#: them along the floor) takes an impulse that is zero but for round-off (~1e-14 of the
#: landing's), which must not lift it off.
IMPULSE_ROUND_OFF = 1e-10


@dataclass(frozen=True)
class Impact:
    """The outcome of an impact: the new velocity ``v``, the impulse on each closing row
    (``impulse``: row -> N·s along the row's unit normal, ≥ 0 in the allowed direction),
    ``energy_lost`` (J, ≥ 0 for e ≤ 1: in the frame of the constraint, ½(1 − e²) m u² for one
    particle meeting a surface at relative speed u), ``released`` (active one-sided rows the
    impulse would have had to pull on, which leave instead) and ``kinetic_energy_change`` (the
    fixed frame's T⁺ − T⁻)."""

    v: np.ndarray
    impulse: dict
    energy_lost: float
    released: tuple[int, ...]
    #: T⁺ − T⁻ in the fixed frame (J): −energy_lost on a fixed constraint; on a moving one it
    #: also holds the work of the constraint's motion.
    kinetic_energy_change: float = 0.0


def impact(model: Model, x, v, t, active_rows, closing, restitution: dict) -> Impact:
    """The velocity jump when the rows ``closing`` close at (x, t) with approach velocity,
    keeping the rows ``active_rows`` held: (J M⁻¹ Jᵀ) P = c⁺ − c⁻ over both (see the module).
    ``restitution``: row -> e. A held one-sided row whose impulse comes out with the forbidden
    sign (beyond ``IMPULSE_ROUND_OFF`` of the largest) is released and the jump recomputed
    without it."""
    info = one_sided(model)
    x, v = np.asarray(x, float), np.asarray(v, float)
    J, f_t = _velocity_terms(model, x, t)
    c = J @ v + f_t
    algebra = algebra_for(model.n_constraints)
    s = scales(model, x, t)
    closing_set, one_sided_rows = set(closing), set(info.rows)  # (sets: thousands of rows)
    held = [k for k in active_rows if k not in closing_set]
    released = []
    while True:
        rows = np.array(sorted(held) + sorted(closing), dtype=int)
        held_set = set(held)
        target = np.zeros(len(rows))
        for i, k in enumerate(rows):
            if k in closing_set:
                target[i] = -restitution.get(k, 0.0) * c[k]
        P = algebra.schur_solve(J[rows], model.inverse_masses, target - c[rows])
        pulls = info.side[rows] * P * s[rows]  # N·s along each row's normal (allowed: ≥ 0)
        round_off = IMPULSE_ROUND_OFF * np.max(np.abs(pulls), initial=0.0)
        wrong = [(pulls[i], k) for i, k in enumerate(rows)
                 if k in held_set and k in one_sided_rows and pulls[i] < -round_off]
        if not wrong:
            break
        worst = min(wrong)[1]
        held.remove(worst)
        released.append(worst)
    v_new = v + model.inverse_masses * (J[rows].T @ P)
    change = float(model.kinetic(v_new)) - float(model.kinetic(v))
    lost = max(0.0, -change - float(f_t[rows] @ P))  # in the constraint's frame (see the module)
    impulse = {int(k): float(info.side[k] * P[i] * s[k]) for i, k in enumerate(rows) if k in closing_set}
    return Impact(v_new, impulse, lost, tuple(released), change)


#: A Zeno sequence: the last impact intervals' ratios agree to this fraction.
ZENO_RATIO_SPREAD = 0.05


class ImpactHistory:
    """Each one-sided row's impact instants, for the Zeno test of the rest rule: a row whose
    last impacts follow each other at intervals shrinking by a steady ratio r < 1 (a ball
    bouncing with e = r) would bounce infinitely often before the accumulation point
    t∞ = t + Δ r / (1 − r). It settles when t∞ is closer than ``zeno_time``: the remaining
    bounces (infinitely many, all within zeno_time) are replaced by one plastic impact, which
    loses the same energy, the rebound's ½ m_eff (e u)²."""

    def __init__(self, zeno_time: float):
        self.zeno_time = zeno_time
        self.times: dict[int, list[float]] = {}

    def settles(self, k: int, t: float, rebound: float, rest: float) -> str | None:
        times = self.times.setdefault(k, [])
        times.append(t)
        if len(times) < 4:
            return None
        d1, d2, d3 = np.diff(times[-4:])
        if not (d1 > 0 and d2 > 0 and d3 > 0):
            return None
        r1, r2 = d2 / d1, d3 / d2
        if not (r2 < 1 and abs(r1 - r2) <= ZENO_RATIO_SPREAD * r2):
            return None
        remaining = d3 * r2 / (1 - r2)
        if rebound > rest and remaining > self.zeno_time:
            return None
        if rebound <= rest:
            return (f"rebound speed {rebound:.3g} m/s below the rest speed {rest:.3g} m/s "
                    f"({len(times)} impacts; accumulation point t∞ ≈ {t + remaining:.9g} s)")
        return (f"Zeno sequence of {len(times)} impacts: the accumulation point t∞ ≈ {t + remaining:.9g} s "
                f"is within {self.zeno_time:.3g} s")


#: A held one-sided row carries no load when its force is within this fraction of the largest
#: held force (``unloaded_rows``): beads of a Newton's cradle hanging side by side touch with a
#: force of ±1e-17 N beside rod tensions of 1 N.
LOAD_ROUND_OFF = 1e-9
#: Impacts resolved in turn at one instant (hybrid._transition) before the rest are plastic.
MAX_IMPACT_ROUNDS = 1000


def unloaded_rows(model: Model, held, x, v, t) -> list[int]:
    """The held one-sided rows that carry no load at (x, v, t): |λ s| ≤ LOAD_ROUND_OFF × the
    largest |λ s| of the held rows (s the row scales; all of them when every force is 0).
    At an impact such a row is a touching contact, not a rigid one: whether round-off left it
    held must not decide whether a cradle's beads move as one block (bead 1 of 3 bouncing
    back at −u/3) or pass the impact on (bead 3 leaving at u)."""
    info = one_sided(model)
    one_sided_rows = set(info.rows)
    rows = [k for k in held if k in one_sided_rows]
    if not rows:
        return []
    force = np.abs(ActiveSet(model, held, at=(x, t)).multipliers(x, v, t) * scales(model, x, t))
    largest = np.max(force[list(held)], initial=0.0)
    return [k for k in rows if force[k] <= LOAD_ROUND_OFF * largest]


# --- the start -----------------------------------------------------------------------------------
def check_allowed_side(model: Model, x, t, limit: float) -> None:
    """Refuse a start on the forbidden side of a one-sided row by more than ``limit`` metres."""
    info = one_sided(model)
    g = gaps(model, x, t) / scales(model, x, t)
    for k in info.rows:
        if g[k] < -limit:
            what = ("the string is stretched beyond its length" if info.side[k] < 0 else
                    "the particle is on the forbidden side (where the constraint function is negative)")
            raise InputError(
                f"one-sided constraint '{model.constraint_labels[k]}' is violated by {-g[k]:.3g} m at "
                f"t = {t:g} s: {what}; move the particle to the allowed side or onto the constraint "
                "(a one-sided constraint keeps side · f ≥ 0; see docs/scene-format.md, "
                "\"One-sided constraints\")")


def start_report(model: Model, x, t: float, size: float, max_correction: float) -> str:
    """``constrained check``'s line on the one-sided rows at the start: each touching or open
    (with its gap), or the refusal a run would give."""
    x = np.asarray(x, float).ravel()
    try:
        check_allowed_side(model, x, t, max_correction * size)
    except InputError as exc:
        return f"projection: FAILS, run would refuse this start: {exc}"
    info = one_sided(model)
    g = gaps(model, x, t) / scales(model, x, t)
    parts = []
    for k in info.rows:
        state = ("touching (held while its force has the allowed sign)" if g[k] <= 1e-8 * size
                 else f"open (gap {g[k]:.3g} m)")
        parts.append(f"{model.constraint_labels[k]} {state}")
    return ("one-sided constraints at the start: " + "; ".join(parts)
            + " (the two-sided ones are projected on)")


# --- what a segment watches ------------------------------------------------------------------------

class SegmentWatch:
    """The events one segment of a hybrid run (constrained.run.hybrid) watches: each active
    one-sided row's signed multiplier μ = side · λ (falling through zero: a release), each
    free one-sided row's gap g = side · f (falling through zero: a contact), and the user's
    events; the multipliers memoized (the driver evaluates every event function at the same
    point).

    A free row's gap is watched in one of three forms, so that a segment never ends on the
    round-off of the transition that started it:

    * a row that has just bounced off at speed w > 0: g(t) / (t − t0) → w (``_deflated_gap``);
    * a row that starts the segment touching without bouncing (let go by the holding test, or
      released by an impact): g(t) − min(g0, 0) + ρ, ρ the position round-off (``_lifting_gap``);
    * any other row: g itself, its round-off at the start read as open (``_open_at_start``).
    """

    def __init__(self, model: Model, active: ActiveSet, user: list[Event], t0: float, x0,
                 rebounding: dict[int, float] | None = None, *, touch: float = 0.0, round_off: float = 0.0):
        info = one_sided(model)
        self.model, self.active, self._memo, self.t0 = model, active, (None, None), t0
        self._gap_memo, self._rate_memo = (None, None), (None, None)
        self._kinds: dict[int, tuple] = {}
        self.rebounding = rebounding or {}
        s = scales(model, x0, t0)
        g0 = gaps(model, x0, t0)
        held_rows = set(active.rows)  # (sets: thousands of rows, a segment each)
        #: free rows that start the segment touching (|g0| within ``touch``, m: a row found
        #: deeper is a landing the last segment missed, watched as g itself): each one's gap
        #: at the start and the position round-off ρ (``round_off``, m) in the row's units
        self.lifting = {k: (float(g0[k]), round_off * s[k]) for k in info.rows
                        if k not in held_rows and k not in self.rebounding and abs(g0[k]) <= touch * s[k]}
        #: rows that have just bounced off: each one's gap at the start (a round-off, possibly
        #: below zero: a bounce at a corner, the start projected onto the other wall only)
        self._rebound_start = {k: float(g0[k]) for k in self.rebounding}
        self.events: list[Event] = []
        self.meaning: list[tuple[str, int | None]] = []
        for k in info.rows:
            label = model.constraint_labels[k]
            if k in held_rows:
                self.events.append(Event(f"release {label}", self._mu(k), -1, True))
                self.meaning.append(("release", k))
            else:
                # (a rebounding row's deflated gap has the sign of g − min(g0, 0) after t0, so
                # the rate's root, the minimum of g, shows its dip too: a bead bouncing off a
                # ball, falling back through it and out within one step)
                self.events.append(Event(f"contact {label}", self._gap(k), -1, True, rate=self._rate(k)))
                self.meaning.append(("contact", k))
        for e in user:
            self.events.append(e)
            self.meaning.append(("user", None))

    def _multipliers(self, t, x, v):
        if not self._same_state(self._memo[0], t, x, v):
            self._memo = ((t, x, v), self.active.multipliers(x, v, t))
        return self._memo[1]

    @staticmethod
    def _same_state(key, t, x, v=None) -> bool:
        """Whether (t, x, v) is the state ``key`` was made at: the same arrays (the driver calls
        every event function with one sample's), else equal ones. (A key of the arrays' bytes
        cost a 24 KB copy per event function and call: a thousand rows on a floor.)"""
        if key is None or key[0] != t:
            return False
        return all(a is b or (a is not None and b is not None and np.array_equal(a, b))
                   for a, b in ((key[1], x), (key[2], v)))

    def _gaps(self, t, x) -> np.ndarray:
        """Every row's gap at (t, x), one evaluation for all of the rows' events."""
        if not self._same_state(self._gap_memo[0], t, x):
            self._gap_memo = ((t, x, None), gaps(self.model, x, t))
        return self._gap_memo[1]

    def _rate(self, k):
        """dg/dt = side · (J v + f_t) of row k (``Event.rate``: a dip through the floor and
        back within one step is found at its turn), one evaluation for all rows."""
        side = one_sided(self.model).side[k]

        def rate(t, x, v):
            if not self._same_state(self._rate_memo[0], t, x, v):
                self._rate_memo = ((t, x, v), constraint_velocities(self.model, x, v, t))
            return side * self._rate_memo[1][k]

        return rate

    def _open_at_start(self, value: float, t: float) -> float:
        """At the segment's first instant a watched quantity is on its allowed side (the
        transition made it so): its round-off is read as positive. Otherwise a rebound whose
        whole flight fits in one step (a parabola is integrated exactly, in very long steps)
        would show no sign change between the step's ends, and the landing would be missed."""
        return max(abs(value), 1e-300) if t == self.t0 else value

    def _mu(self, k):
        side = one_sided(self.model).side[k]
        return lambda t, x, v: self._open_at_start(side * self._multipliers(t, x, v)[k], t)

    def _gap(self, k):
        if k in self.rebounding:
            return self._deflated_gap(k, self.rebounding[k])
        if k in self.lifting:
            return self._lifting_gap(k, *self.lifting[k])
        return lambda t, x, v: self._open_at_start(self._gaps(t, x)[k], t)

    def _lifting_gap(self, k, g0: float, rho: float):
        """The gap of a free row that starts the segment touching (a contact the holding test
        let go, a row released by an impact), as it opens from its start g0 (a round-off,
        possibly below zero) with a margin of the position round-off ρ:

            ĝ(t) = g(t) − min(g0, 0) + ρ.

        Such a row leaves tangentially — g(t) − g0 = w (t − t0) + ½ g̈ (t − t0)² + … with w ≈ 0
        — so g itself has a double zero at t0, and its round-off (a start 1e-16 m below zero,
        or the dense output's) reads as a landing a moment after t0: a transition that changes
        nothing, repeated without end. ĝ > 0 there; the row lands where its gap falls ρ below
        where it started (ρ ~ 1e-13 m, the projections' tolerance)."""
        below = min(g0, 0.0)
        return lambda t, x, v: self._gaps(t, x)[k] - below + rho

    def _deflated_gap(self, k, speed: float):
        """The gap of a row that has just bounced off, divided by the time since: g(t) =
        w (t − t0) − ½ |g̈| (t − t0)² + … vanishes at the impact instant t0 itself, where its
        round-off (~1e-16 m) would read as a crossing a moment after t0 for a short flight;
        g(t)/(t − t0) → w (the rebound speed, > 0) at t0 instead, and changes sign only where
        the flight ends. The start's own round-off below zero, g0 < 0, is taken out first,

            ĝ(t) = (g(t) − min(g0, 0)) / (t − t0),

        else a ball bouncing off one wall of a sharp wedge at its apex (the start projected
        onto the other wall only, g0 = −5e-14 m) reads ĝ → −∞ just after t0: a landing at t0
        itself, a segment of zero length."""
        t0 = self.t0
        below = min(self._rebound_start[k], 0.0)

        def deflated(t, x, v):
            return speed if t <= t0 else (self._gaps(t, x)[k] - below) / (t - t0)

        return deflated

    def kind(self, event: Event) -> tuple[str, int | None]:
        if len(self._kinds) != len(self.events):  # (by identity: index() compared dataclasses)
            self._kinds = {id(e): m for e, m in zip(self.events, self.meaning, strict=True)}
        found = self._kinds.get(id(event))
        return found if found is not None else self.meaning[self.events.index(event)]
