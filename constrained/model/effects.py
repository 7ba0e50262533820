"""The effects library: each effect contributes one kind of term to the equations of motion.

An effect returns a term for exactly one of four slots (the Model sums each slot and
assembles only the slots some effect fills):

- ``potential``  V(x, t)                    force −∂V/∂x
- ``generalized_potential`` U(x, v, t)      force −∂U/∂x + d/dt ∂U/∂v   (U linear in v)
- ``dissipation`` Rayleigh R(x, v)          force −∂R/∂v
- ``applied_force`` F(x, v, t) ∈ R^(3N)     added as it is
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import casadi as ca

from ..errors import InputError
from .constraints import Labelled, _as_list, _fmt, _three


class Effect(Labelled):
    """Base class: ``slot`` names the term, ``term(s)`` builds it from Symbols ``s``."""

    kind = "effect"
    slot: str = ""
    #: Fields whose plain numbers are inputs of the Structure's Functions (constrained.lifting).
    numbers: tuple[str, ...] = ()

    def term(self, s):
        raise NotImplementedError


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
        where = self._where()
        g = s.point(self.g, f"{where}.g")
        names = self.particles if self.particles is not None else list(s._index)
        if not names:
            return 0.0
        # V = −Σ m_i g·x_i in a few CasADi calls (one per particle would dominate large builds)
        P = ca.horzcat(*[s.position(p, where) for p in names])
        m = s.mass_column([s.index(p, where) for p in names]).T  # numbers, or SX of p
        return -ca.dot(ca.mtimes(g.T, P), m)


class Spring(Effect):
    """Linear spring: V = ½ k (|x_a − x_b| − rest)², between particles or to a point."""

    slot = "potential"
    numbers = ("point", "k", "rest")

    def __init__(self, a, b=None, *, point=None, k, rest=0.0, name=None, where=None):
        self.a, self.b, self.point, self.k, self.rest = a, b, point, k, rest
        self.name, self.where = name, where

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
    """V = Σ_{i<j} V(r_ij), r_ij = |x_i − x_j|, over every pair of the listed particles (all
    when none are listed): gravitation, Coulomb, Lennard-Jones, the Fekete problem's −log r.
    ``expr`` in r (and t, parameters); parsed once into a function of r, called per pair."""

    slot = "potential"

    def __init__(self, expr: str, particles=None, *, name=None, where=None):
        self.expr, self.name, self.where = expr, name, where
        self.particles = None if particles is None else _as_list(particles, self._where(), "'particles'")

    @property
    def label(self) -> str:
        over = "all particles" if self.particles is None else f"{len(self.particles)} particles"
        return self.name or f"pairwise V(r) = {self.expr} over {over}"

    def term(self, s):
        where = self._where()
        names = self.particles if self.particles is not None else list(s._index)
        if len(set(names)) != len(names):
            raise InputError("'particles' lists a particle twice", where=f"{where}.particles")
        r = ca.SX.sym("r")
        V = s.parse(self.expr, f"{where}.expr", extra={"r": r})
        positions = [s.position(p, where) for p in names]
        pairs = [(i, j) for i in range(len(names)) for j in range(i + 1, len(names))]
        if not pairs:
            return ca.SX(0)
        # V may also use t, coordinates and (symbolic) parameters p
        pair = ca.Function("pair_potential", [r, s.x, s.t, s.p], [V])
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

    @property
    def label(self) -> str:
        on = f"{self.a}–{self.b}" if self.a else ", ".join(self.particles or ["all"])
        return self.name or f"damping c={_fmt(self.coefficient)} N·s/m on {on}"

    def term(self, s):
        where = self._where()
        c = s.time_function(self.coefficient, f"{where}.coefficient")
        if self.a is not None:
            dv = s.velocity(self.a, where) - s.velocity(self.b, where)
            return 0.5 * c * ca.dot(dv, dv)
        names = self.particles if self.particles is not None else list(s._index)
        return 0.5 * c * sum(ca.dot(s.velocity(p, where), s.velocity(p, where)) for p in names)


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


EFFECT_TYPES = {
    "gravity": Gravity,
    "spring": Spring,
    "potential": Potential,
    "central": Central,
    "pairwise": Pairwise,
    "damping": Damping,
    "force": Force,
    "electromagnetic": Electromagnetic,
}


def forces(slots: dict, x, v, t) -> tuple:
    """(F, V, U, ∂U/∂v, active slots) from the effects' terms by slot:

        F = −∂V/∂x − ∂U/∂x + d/dt ∂U/∂v − ∂R/∂v + Σ applied,   V = Σ potentials, U = Σ
        generalized potentials (linear in v: d/dt ∂U/∂v = (∂²U/∂v∂x) v + ∂²U/∂v∂t), R = Σ
        dissipations."""
    active = set()
    F = ca.SX.zeros(x.numel())
    V = U = ca.SX(0)
    dU_dv = ca.SX.zeros(x.numel())
    if slots["potential"]:
        active.add("potential")
        V = sum(slots["potential"], ca.SX(0))
        F -= ca.gradient(V, x)
    if slots["generalized_potential"]:
        active.add("generalized_potential")
        U = sum(slots["generalized_potential"], ca.SX(0))
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
        R = sum(slots["dissipation"], ca.SX(0))
        F -= ca.gradient(R, v)
    if slots["applied_force"]:
        active.add("applied_force")
        for term in slots["applied_force"]:
            F += term
    if ca.depends_on(F, t) or (V.numel() and ca.depends_on(V, t)):
        active.add("time_dependent_forces")
    return F, V, U, dU_dv, active
