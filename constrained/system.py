"""System and Particle: the plain description of what is simulated (no CasADi here)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError


def as_vector3(value, *, where: str, what: str = "vector") -> np.ndarray:
    """A finite 3-vector of floats, or an InputError saying what is wrong with ``value``."""
    if isinstance(value, str) or not isinstance(value, Sequence | np.ndarray):
        raise InputError(f"{what} must be a list of 3 numbers, got {value!r}", where=where)
    if len(value) != 3:
        raise InputError(f"{what} must have 3 entries (x, y, z), got {len(value)}", where=where)
    out = np.empty(3)
    for i, entry in enumerate(value):
        if isinstance(entry, bool) or not isinstance(entry, int | float | np.number):
            raise InputError(f"{what} entry {i} must be a number, got {entry!r}", where=where)
        if not math.isfinite(entry):
            raise InputError(f"{what} entry {i} is not finite ({entry!r})", where=where)
        out[i] = float(entry)
    return out


@dataclass
class Particle:
    """A point mass: ``name``, ``mass`` in kg, ``position`` in m, ``velocity`` in m/s."""

    name: str
    mass: float
    position: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    where: str | None = None

    def __post_init__(self):
        where = self.where or f"particle '{self.name}'"
        if not isinstance(self.name, str) or not self.name.isidentifier():
            raise InputError(
                f"particle name {self.name!r} must be a plain identifier "
                "(letters, digits, underscore; not starting with a digit)",
                where=where,
            )
        if isinstance(self.mass, bool) or not isinstance(self.mass, int | float | np.number):
            raise InputError(f"mass must be a number in kg, got {self.mass!r}", where=where)
        if not math.isfinite(self.mass) or self.mass <= 0:
            raise InputError(f"mass must be a finite positive number, got {self.mass!r}", where=where)
        self.mass = float(self.mass)
        self.position = as_vector3(self.position, where=where, what="position")
        self.velocity = as_vector3(self.velocity, where=where, what="velocity")


class System:
    """Particles, holonomic constraints and effects, with named ``parameters``.

    Always three coordinates per particle; motion in a plane is a constraint.
    """

    def __init__(
        self,
        particles: Iterable[Particle] = (),
        constraints: Iterable = (),
        effects: Iterable = (),
        parameters: dict[str, float] | None = None,
        name: str = "",
    ):
        self.name = name
        self.particles: list[Particle] = []
        self.constraints: list = []
        self.effects: list = []
        self.parameters: dict[str, float] = {}
        #: User events of a scene's [[events]] (constrained.events.FormulaEvent), watched by
        #: every run of this system besides the ``events=`` given to simulate.
        self.events: list = []
        for p in particles:
            self.add_particle(p)
        for key, value in (parameters or {}).items():
            self.set_parameter(key, value)
        self.add(*constraints, *effects)

    # --- building -------------------------------------------------------------------------
    def add_particle(self, particle_or_name, mass=None, position=None, velocity=(0.0, 0.0, 0.0)):
        """Add a Particle (or build one from name, mass, position, velocity); returns it."""
        if isinstance(particle_or_name, Particle):
            p = particle_or_name
        else:
            p = Particle(particle_or_name, mass, position, velocity)
        if any(q.name == p.name for q in self.particles):
            raise InputError(f"duplicate particle name '{p.name}'", where=p.where or "particles")
        self.particles.append(p)
        return p

    def add(self, *items):
        """Add constraints and effects (objects from constrained.constraints / .effects)."""
        from .constraints import Constraint
        from .effects import Effect

        for item in items:
            if isinstance(item, Constraint):
                self.constraints.append(item)
            elif isinstance(item, Effect):
                self.effects.append(item)
            else:
                raise InputError(f"expected a Constraint or an Effect, got {item!r}")
        return self

    def set_parameter(self, key: str, value: float):
        if not isinstance(key, str) or not key.isidentifier():
            raise InputError(f"parameter name {key!r} must be a plain identifier", where="parameters")
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise InputError(f"parameter must be a finite number, got {value!r}", where=f"parameters.{key}")
        self.parameters[key] = float(value)

    # --- reading ---------------------------------------------------------------------------
    @property
    def n_particles(self) -> int:
        return len(self.particles)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.particles]

    @property
    def masses(self) -> np.ndarray:
        return np.array([p.mass for p in self.particles])

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) initial positions."""
        return np.array([p.position for p in self.particles]).reshape(-1, 3)

    @property
    def velocities(self) -> np.ndarray:
        """(N, 3) initial velocities."""
        return np.array([p.velocity for p in self.particles]).reshape(-1, 3)

    def index(self, name: str, *, where: str | None = None) -> int:
        for i, p in enumerate(self.particles):
            if p.name == name:
                return i
        known = ", ".join(self.names) or "(none)"
        raise InputError(f"unknown particle '{name}' (particles: {known})", where=where)

    def with_state(self, x: np.ndarray, v: np.ndarray | None = None) -> System:
        """A copy with positions (N, 3) and velocities replaced."""
        x = np.asarray(x, float).reshape(-1, 3)
        v = self.velocities if v is None else np.asarray(v, float).reshape(-1, 3)
        particles = [
            Particle(p.name, p.mass, x[i], v[i], p.where) for i, p in enumerate(self.particles)
        ]
        copy = System(particles, self.constraints, self.effects, self.parameters, self.name)
        copy.events = list(self.events)
        return copy

    def size(self) -> float:
        """A length scale: the largest of |x_i| and |x_i - x_j| at the start (1 m if all zero)."""
        x = self.positions
        if len(x) == 0:
            return 1.0
        spread = float(np.max(np.ptp(x, axis=0))) if len(x) > 1 else 0.0
        scale = max(float(np.max(np.linalg.norm(x, axis=1))), spread)
        return scale if scale > 0 else 1.0

    def __repr__(self) -> str:
        return (
            f"System({self.name!r}: {self.n_particles} particles, "
            f"{len(self.constraints)} constraints, {len(self.effects)} effects)"
        )


def sketch(system) -> dict:
    """What an animation draws of the constraints, as plain lists (stored in a trajectory's
    ``info["sketch"]`` so that ``constrained plot`` draws it without the scene file):
    ``rods`` — particle index pairs held at a distance; ``anchors`` — ``[index, point, length]``
    for a distance to a fixed point (a rod to a pivot; ``length`` a number, or a parameter's
    value, else None);
    moving points and formula-valued anchors are left out."""
    names = [p.name for p in system.particles]
    index = {n: k for k, n in enumerate(names)}
    rods, anchors = [], []
    for c in getattr(system, "constraints", ()):
        kind = type(c).__name__
        a, b, point = getattr(c, "a", None), getattr(c, "b", None), getattr(c, "point", None)
        if kind not in ("Distance", "Pin") or a not in index:
            continue
        if b in index:
            rods.append([index[a], index[b]])
        elif point is not None and kind == "Distance":
            try:
                anchor = [float(v) for v in point]
            except (TypeError, ValueError):  # a moving anchor (formula of t): not drawn
                continue
            length = getattr(c, "length", None)
            if isinstance(length, str):  # a parameter's name; other formulas are not evaluated here
                length = getattr(system, "parameters", {}).get(length.strip())
            anchors.append([index[a], anchor, float(length) if isinstance(length, int | float) else None])
    return {"rods": rods, "anchors": anchors}
