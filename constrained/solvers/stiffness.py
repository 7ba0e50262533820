"""Stiff elements: springs much stiffer than the motion they carry (``stiff_springs``), Rayleigh
dampers that relax a particle's velocity much faster than the motion (``stiff_dampers``), and
the watch that stops a run held down to either (``StiffnessWatch``, which names the spring and
says to make it a rigid link, or names the damper and says to use an L-stable method)."""

from __future__ import annotations

import itertools
import time
import warnings
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..model.effects import Damping, Spring

#: A spring whose stretch is below this fraction of its length stands for a rigid link.
RIGID_STRETCH = 1e-6


@dataclass
class StiffElement:
    """A spring effect and its oscillation: ω² = k / m_reduced (m_a m_b / (m_a + m_b), or m_a
    for a spring to a point), ``period`` = 2π/ω; ``stretch`` |ℓ − rest| at the state given."""

    index: int
    label: str
    k: float
    reduced_mass: float
    omega: float
    length: float
    rest: float
    stretch: float
    ends: tuple

    @property
    def period(self) -> float:
        return 2 * np.pi / self.omega

    @property
    def rigid_like(self) -> bool:
        return self.stretch <= RIGID_STRETCH * max(self.rest, self.length, 1e-300)

    def constraint_advice(self) -> str:
        a, b = self.ends
        other = f'b = "{b}"' if isinstance(b, str) else f"point = {list(b)}"
        return (f'a spring that stiff stands for a rigid link: replace it by a constraint '
                f'(type = "distance", a = "{a}", {other}, length = {self.rest:g})')


def _plain(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


_NUMBER_TYPES = frozenset((int, float))


def _plain_each(values: list) -> np.ndarray:
    """``_plain`` of each of ``values`` as a mask (ints and floats by their type alone)."""
    if _NUMBER_TYPES.issuperset(map(type, values)):
        return np.ones(len(values), bool)
    return np.fromiter(map(_plain, values), bool, len(values))


def _between_particles(effects: list, springs: list[int], names: dict) -> tuple[list, list, np.ndarray,
                                                                                 np.ndarray]:
    """``(index, springs, ia, ib)`` of the springs (``effects[i]`` for i in ``springs``) whose k and
    rest are plain numbers and whose ends are two particles of ``names`` (name -> index): their
    indices in ``effects``, the springs, and their ends' particle indices; in passes over them all
    (a cloth's 20,000 shear springs)."""
    chosen = [effects[i] for i in springs]
    n = len(chosen)
    ok = _plain_each([e.k for e in chosen]) & _plain_each([e.rest for e in chosen])
    ok &= np.fromiter((isinstance(e.b, str) for e in chosen), bool, n)
    ia = np.full(n, -1, np.int64)
    ia[ok] = np.fromiter(map(names.get, (e.a for e in itertools.compress(chosen, ok)), itertools.repeat(-1)),
                         np.int64, int(ok.sum()))
    ok &= ia >= 0
    ib = np.full(n, -1, np.int64)
    ib[ok] = np.fromiter(map(names.get, (e.b for e in itertools.compress(chosen, ok)), itertools.repeat(-1)),
                         np.int64, int(ok.sum()))
    ok &= ib >= 0
    at = np.flatnonzero(ok).tolist()
    return [springs[j] for j in at], [chosen[j] for j in at], ia[ok], ib[ok]


def stiff_springs(model, x, t: float = 0.0, *, keep=None) -> list[StiffElement]:
    """The scene's springs with their oscillation at the state (x, t), fastest first (springs
    whose stiffness or rest length are not plain numbers at t are evaluated there). ``keep``:
    a test of the period, ``keep(period) -> bool`` that also takes an array of periods: only the
    springs it keeps (springs of plain numbers between two particles are then measured all at
    once, and only those kept are described: a cloth's 20,000 shear springs)."""
    system = model.system
    if not any(isinstance(effect, Spring) for effect in system.effects):
        return []
    x = np.asarray(x, float).reshape(-1, 3)
    masses = system.masses  # (a property that builds the array: once, not per spring)
    found: list[StiffElement] = []
    springs = [index for index, effect in enumerate(system.effects) if isinstance(effect, Spring)]
    others = springs
    if keep is not None:
        names = {name: i for i, name in enumerate(model.particle_names)}
        index, effects, ia, ib = _between_particles(system.effects, springs, names)
        if index:
            k = np.array([float(effect.k) for effect in effects])
            ma, mb = np.asarray(masses, float)[ia], np.asarray(masses, float)[ib]
            with np.errstate(all="ignore"):
                omega = np.sqrt(k / (ma * mb / (ma + mb)))
                kept = np.isfinite(k) & (k > 0) & np.asarray(keep(2 * np.pi / omega), bool)
            for j in np.flatnonzero(kept):
                effect = effects[j]
                found.append(_element(index[j], effect, float(k[j]), float(effect.rest), float(ma[j]),
                                      float(mb[j]), x[int(ia[j])], x[int(ib[j])], effect.b))
            done = set(index)
            others = [i for i in springs if i not in done]
    if others:
        found += _measured(model, others, x, t, masses, keep)
    found.sort(key=lambda e: e.index)  # (in the scene's order, then the fastest first)
    return sorted(found, key=lambda e: -e.omega)


def _element(index: int, effect, k: float, rest: float, ma: float, mb: float, xa, xb, other) -> StiffElement:
    m_red = ma if not np.isfinite(mb) else ma * mb / (ma + mb)
    length = float(np.linalg.norm(xa - xb))
    return StiffElement(index, effect.label, k, m_red, float(np.sqrt(k / m_red)), length, rest,
                        abs(length - rest), (effect.a, other))


def _measured(model, indices: list[int], x: np.ndarray, t: float, masses, keep) -> list[StiffElement]:
    """The springs ``indices`` of the system measured one by one, their formulas evaluated at t."""
    system = model.system
    s = model.symbols

    def at_t(value, where):  # a plain number as it is; a formula evaluated at t
        if _plain(value):
            return float(value)
        return float(np.asarray(ca.Function("c", [s.t], [ca.SX(s.time_function(value, where))])(t),
                                float).ravel()[0])

    found = []
    for index in indices:
        effect = system.effects[index]
        try:
            where = f"effects[{index}]"
            k, rest = at_t(effect.k, where), at_t(effect.rest, where)
            ia = s.index(effect.a, where)
            ma = float(masses[ia])
            if effect.b is not None:
                ib = s.index(effect.b, where)
                mb, xb, other = float(masses[ib]), x[ib], effect.b
            else:
                p = ca.Function("p", [s.t], [s.point(effect.point, where)])
                mb, xb = np.inf, np.asarray(p(t), float).ravel()
                other = tuple(float(c) for c in xb)
        except Exception:  # a diagnosis only: a spring it cannot evaluate is left out
            continue
        if not (np.isfinite(k) and k > 0):
            continue
        element = _element(index, effect, k, rest, ma, mb, x[ia], xb, other)
        if keep is None or keep(element.period):
            found.append(element)
    return found


@dataclass
class StiffDamper:
    """A Rayleigh damping effect and the fastest relaxation it imposes: R = ½ c |v|² on a
    particle of mass m gives m v' = −c v, so v relaxes as e^(−t/τ), τ = m/c (the lightest of
    its particles; for a pair, ½ c |v_a − v_b|², the relative velocity with the reduced mass).
    An explicit step is stable only for h ≲ a few τ."""

    index: int
    label: str
    c: float
    mass: float
    particle: str

    @property
    def period(self) -> float:
        """The relaxation time τ = m / c (s)."""
        return self.mass / self.c


def stiff_dampers(model, t: float = 0.0, *, keep=None) -> list[StiffDamper]:
    """The scene's damping effects with a positive coefficient at t, the fastest (shortest
    τ = m/c) first; ``keep(τ) -> bool``: only those it keeps."""
    system = model.system
    masses = np.asarray(system.masses, float)
    index = {name: i for i, name in enumerate(model.particle_names)}
    found = []
    for k, effect in enumerate(system.effects):
        if not isinstance(effect, Damping):
            continue
        try:
            c = float(effect.coefficient) if _plain(effect.coefficient) else \
                _at_t(model, effect.coefficient, f"effects[{k}].coefficient", t)
            if effect.a is not None:
                ma, mb = masses[index[effect.a]], masses[index[effect.b]]
                mass, who = ma * mb / (ma + mb), f"{effect.a}–{effect.b}"
            else:
                names = effect.particles if effect.particles is not None else list(model.particle_names)
                if not names:
                    continue
                light = min(names, key=lambda n: masses[index[n]])
                mass, who = float(masses[index[light]]), light
        except Exception:  # a diagnosis only: a damper it cannot evaluate is left out
            continue
        if not (np.isfinite(c) and c > 0):
            continue
        element = StiffDamper(k, effect.label, c, float(mass), who)
        if keep is None or keep(element.period):
            found.append(element)
    return sorted(found, key=lambda e: e.period)


def _at_t(model, value, where: str, t: float) -> float:
    """A formula of t and the parameters (a coefficient) evaluated at t."""
    s = model.symbols
    return float(np.asarray(ca.Function("c", [s.t], [ca.SX(s.time_function(value, where))])(t),
                            float).ravel()[0])


def stiff_stop(verdict: str, t: float) -> str:
    """The sentence of a run the watch stopped at t: the fast motion that held its steps down
    (a spring's oscillation, a damper's relaxation), then the watch's ``verdict``."""
    fast = "relaxation" if "relaxes velocities" in verdict else "oscillation"
    return f"the steps follow a fast {fast} at t = {float(t):.6g} s; {verdict}"


class StiffnessWatch:
    """Watches a run for a spring that holds the steps down to its own oscillation.

    The solvers call ``check(t, steps, x)`` after every step or chunk (it costs a clock read).
    From ``AFTER_S`` seconds of wall time on, twice a second: when reaching t_end at the pace
    so far would take more than ``BUDGET_S`` seconds, the run is more than ``MIN_PERIODS``
    periods of the fastest spring long, the steps average less than that period, and the
    spring is barely stretched (a rigid link in disguise), ``check`` returns the diagnosis
    (the run stops with it); likewise for a damper whose relaxation time m/c is MIN_PERIODS
    times shorter than the run and the steps average less than HELD of them (c = 1e8 N·s/m on
    1 kg: dopri crawled through 20 million steps and stopped at max_steps blaming "forces that
    blow up"); otherwise None."""

    AFTER_S = 2.0
    BUDGET_S = 15.0
    #: After AFTER_S, the watch looks again every this many seconds of wall time.
    EVERY_S = 0.5
    MIN_PERIODS = 1e3
    #: Steps averaging less than this many relaxation times m/c are held down by a damper
    #: (an explicit method's stability limit is a few m/c).
    HELD = 10.0

    def __init__(self, model, x0, t0: float, t_end: float, *, method: str):
        self._clock = time.perf_counter
        self.model, self.t0, self.t_end, self.method = model, float(t0), float(t_end), method
        length = self.t_end - self.t0
        self.elements = stiff_springs(model, x0, t0, keep=lambda period: period * self.MIN_PERIODS < length)
        self.dampers = stiff_dampers(model, t0, keep=lambda tau: tau * self.MIN_PERIODS < length)
        self.started = self._clock()
        self.next = self.started + self.AFTER_S

    def check(self, t: float, steps: int, x=None) -> str | None:
        if not self.elements and not self.dampers:
            return None
        now = self._clock()
        if now < self.next:
            return None
        self.next = now + self.EVERY_S
        done = float(t) - self.t0
        projected = np.inf if done <= 0 else (now - self.started) * (self.t_end - self.t0) / done
        return self.verdict(t, steps, x, projected)

    def verdict(self, t: float, steps: int, x, projected: float) -> str | None:
        """The diagnosis of a run at (t, x) after ``steps`` accepted steps whose pace projects
        ``projected`` seconds of wall time to t_end: at least BUDGET_S, and the mean step
        (t − t0)/steps within the period 2π/ω of a barely stretched spring (or HELD relaxation
        times m/c of a damper); else None. The caller keeps the clock (``check``: the run's;
        a batch: each member's share of it, run/variants/watch.py)."""
        if projected < self.BUDGET_S:
            return None
        done = float(t) - self.t0
        element = self.fastest(x, t)
        if element is not None and element.rigid_like and not (steps and done / steps > element.period):
            return self.describe(element, t, steps, projected)
        damper = self.held_damper(t, steps)
        if damper is not None:
            return self.describe_damper(damper, t, steps, projected)
        return None

    def held_damper(self, t: float, steps: int | None) -> StiffDamper | None:
        """The fastest damper when the mean step to t, (t − t0)/steps, is at most HELD of its
        relaxation times m/c (it held the steps down), else None."""
        damper = self.dampers[0] if self.dampers else None
        if damper is None or not steps or not (float(t) - self.t0) / steps <= self.HELD * damper.period:
            return None
        return damper

    def describe_damper(self, damper: StiffDamper, t: float, steps: int | None = None,
                        projected: float | None = None) -> str:
        d, length = damper, self.t_end - self.t0
        pace = self._pace(t, steps, projected, lambda h: f"{h / d.period:.3g} relaxation times")
        return (f"likely cause: stiffness: the damping '{d.label}' (effect {d.index}) has c = {d.c:.3g} "
                f"N·s/m on '{d.particle}' ({d.mass:.3g} kg), so it relaxes velocities in m/c = "
                f"{d.period:.3g} s, "
                f"{length / d.period:.3g} times in the run of {length:g} s{pace}. An explicit method's step "
                "cannot exceed a few m/c: use method = \"rodas\" (L-stable: it steps over the relaxation), "
                "or a smaller coefficient")

    def _pace(self, t: float, steps: int | None, projected: float | None, per) -> str:
        """"; METHOD took N steps to t = … (mean step h, ``per(h)``): about M steps to t_end[, P s
        of wall time]", or "" without ``steps``."""
        if not steps:
            return ""
        length = self.t_end - self.t0
        h = (float(t) - self.t0) / steps
        total = steps * length / max(float(t) - self.t0, 1e-300)
        pace = (f"; {self.method} took {steps} steps to t = {float(t):.3g} s (mean step {h:.3g} s, "
                f"{per(h)}): about {total:.3g} steps to t_end")
        if projected is not None and np.isfinite(projected):
            pace += f", {projected:.0f} s of wall time"
        return pace

    def fastest(self, x=None, t: float | None = None) -> StiffElement | None:
        """The fastest watched spring, re-measured at (x, t) when given."""
        if not self.elements:
            return None
        if x is None:
            return self.elements[0]
        now = stiff_springs(self.model, x, self.t0 if t is None else t)
        return next((e for e in now if e.index == self.elements[0].index), self.elements[0])

    def describe(self, element: StiffElement, t: float, steps: int | None = None,
                 projected: float | None = None) -> str:
        e, length = element, self.t_end - self.t0
        pace = self._pace(t, steps, projected, lambda h: f"{e.period / h:.3g} per period")
        return (f"likely cause: stiffness: the spring '{e.label}' (effect {e.index}) has k = {e.k:.3g} N/m "
                f"on a reduced mass of {e.reduced_mass:.3g} kg, so it oscillates with period "
                f"2π/ω = {e.period:.3g} s (ω = {e.omega:.3g} rad/s), {length / e.period:.3g} periods in "
                f"the run of {length:g} s{pace}. Its stretch is {e.stretch:.2g} m of {e.rest:g} m: "
                f"{e.constraint_advice()}; or, to keep the spring, use a method that steps over the "
                'fast mode (method = "projection" with base = "Radau" or "CVODES_BDF" and a looser rtol)')


# --- an explicit method held down by stability (the end-of-run warning) ------------------------
class StiffnessWarning(UserWarning):
    """An explicit integrator's step is held down by stability, not accuracy: use an implicit base."""


def spectral_radius(rhs, t: float, y: np.ndarray, f0: np.ndarray | None = None, *,
                    iterations: int = 12, seed: int = 0) -> float:
    """Estimate the largest |eigenvalue| of ∂rhs/∂y at (t, y): power iteration on directional
    differences (a diagnostic only; the equations themselves are never differenced)."""
    f0 = rhs(t, y) if f0 is None else f0
    rng = np.random.default_rng(seed)
    w = rng.standard_normal(y.shape)
    w /= np.linalg.norm(w)
    eps = 1e-7 * max(np.linalg.norm(y), 1.0)
    growth = []
    for _ in range(iterations):
        jw = (rhs(t, y + eps * w) - f0) / eps
        nrm = float(np.linalg.norm(jw))
        if not np.isfinite(nrm) or nrm == 0:
            break
        growth.append(nrm)
        w = jw / nrm
    if not growth:
        return 0.0
    # complex pairs make single ratios oscillate: the geometric mean of the last few is robust
    tail = np.array(growth[len(growth) // 2:])
    return float(np.exp(np.mean(np.log(tail))))


#: An explicit run is called stiff when, over at least STIFFNESS_MIN_STEPS steps, the median
#: of h·ρ (sampled every STIFFNESS_EVERY accepted steps) sits near the stability boundary of
#: the explicit method (about 3.3 for DOP853 on the negative real axis, 2.8 for RK45): the
#: step is then held down by stability, not accuracy.
STIFFNESS_EVERY = 50
STIFFNESS_MIN_STEPS = 500
STIFFNESS_H_RHO = 1.0


def stiffness_verdict(stats: dict, h_rho: list, rho_max: float, *, what: str, advice: str,
                      stacklevel: int = 5) -> None:
    """Record h·ρ in ``stats["stiffness"]``; warn (StiffnessWarning) when the explicit
    method's steps were held down by stability over many steps."""
    med = float(np.median(h_rho)) if h_rho else 0.0
    stiff = stats["steps"] >= STIFFNESS_MIN_STEPS and len(h_rho) >= 5 and med >= STIFFNESS_H_RHO
    stats["stiffness"] = {"h_rho_median": med, "rho_max": rho_max, "checks": len(h_rho),
                          "stiff": bool(stiff)}
    if stiff:
        warnings.warn(
            f"the problem looks stiff: {what} took {stats['steps']} steps with h·ρ ≈ {med:.2g} "
            f"(ρ ≈ {rho_max:.3g} /s, the fastest rate of the equations), so its step size is "
            f"limited by stability, not accuracy; {advice}",
            StiffnessWarning,
            stacklevel=stacklevel,
        )
