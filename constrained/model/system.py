"""System and Particle: the plain description of what is simulated (no CasADi here)."""

from __future__ import annotations

import copy
import itertools
import math
import operator
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError, listed


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


def _formula_or_number(entry, *, where: str, what: str):
    """A number (as float, finite) or a non-empty formula string, kept as it is."""
    if isinstance(entry, str):
        if not entry.strip():
            raise InputError(f"{what} is an empty formula", where=where)
        return entry
    if isinstance(entry, bool) or not isinstance(entry, int | float | np.number):
        raise InputError(f"{what} must be a number or a formula string, got {entry!r}", where=where)
    if not math.isfinite(entry):
        raise InputError(f"{what} is not finite ({entry!r})", where=where)
    return float(entry)


def _vector3_or_formulas(value, *, where: str, what: str):
    """A finite 3-vector, or (when an entry is a formula string) the list of its 3 entries."""
    if isinstance(value, Sequence) and not isinstance(value, str) and any(isinstance(e, str) for e in value):
        if len(value) != 3:
            raise InputError(f"{what} must have 3 entries (x, y, z), got {len(value)}", where=where)
        return [_formula_or_number(e, where=where, what=f"{what} entry {i}") for i, e in enumerate(value)]
    return as_vector3(value, where=where, what=what)


@dataclass
class Particle:
    """A point mass: ``name``, ``mass`` in kg, ``position`` in m, ``velocity`` in m/s.

    ``mass`` may be a formula string and ``position``/``velocity`` entries may be formula
    strings, in the parameters and definitions of the System the particle belongs to
    (``mass="m1"``, ``position=["l1*sin(th1)", "-l1*cos(th1)", 0]``). The formulas are kept in
    ``formulas`` (key -> the given value); the System evaluates them into the numeric
    ``mass``, ``position``, ``velocity`` for its parameters' values (NaN until then).
    """

    name: str
    mass: float
    position: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    where: str | None = None
    formulas: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        where = self.where or f"particle '{self.name}'"
        if not isinstance(self.name, str) or not self.name.isidentifier():
            raise InputError(
                f"particle name {self.name!r} must be a plain identifier "
                "(letters, digits, underscore; not starting with a digit)",
                where=where,
            )
        self.formulas = dict(self.formulas)
        if isinstance(self.mass, str):
            self.formulas["mass"] = _formula_or_number(self.mass, where=f"{where}.mass", what="mass")
            self.mass = math.nan
        elif "mass" not in self.formulas:
            self.mass = _check_mass(self.mass, where)
        for key in ("position", "velocity"):
            value = _vector3_or_formulas(getattr(self, key), where=where, what=key)
            if isinstance(value, list):
                self.formulas[key] = value
                value = np.full(3, math.nan)
            setattr(self, key, value)

    @classmethod
    def plain(cls, name: str, mass: float, position: np.ndarray, velocity: np.ndarray,
              where: str | None = None) -> Particle:
        """The Particle ``Particle(name, mass, position, velocity, where=where)`` makes of values
        already checked (a plain identifier, a finite positive float mass, finite float arrays of
        3), without checking them again: a large scene's particles (constrained.scene.plain)."""
        particle = cls.__new__(cls)
        particle.__dict__.update(name=name, mass=mass, position=position, velocity=velocity, where=where,
                                 formulas={})
        return particle

    def copy(self) -> Particle:
        """An independent copy (its arrays and formulas copied too)."""
        other = copy.copy(self)
        other.position, other.velocity = self.position.copy(), self.velocity.copy()
        other.formulas = {k: list(v) if isinstance(v, list) else v for k, v in self.formulas.items()}
        return other

    def spec(self) -> tuple:
        """``(name, mass, position, velocity)`` as given: formulas where formulas were given."""
        f = self.formulas
        return (self.name, f.get("mass", self.mass), f.get("position", self.position),
                f.get("velocity", self.velocity))

    def resolve(self, values: Mapping[str, float]) -> None:
        """Evaluate the formulas (mass, position and velocity entries) for these parameter and
        definition ``values``; a mass must come out finite and positive."""
        from .parameters import evaluate

        where = self.where or f"particle '{self.name}'"
        if "mass" in self.formulas:
            self.mass = _check_mass(evaluate(self.formulas["mass"], values, f"{where}.mass"), where,
                                    formula=self.formulas["mass"])
        for key in ("position", "velocity"):
            if key in self.formulas:
                setattr(self, key, np.array([evaluate(e, values, f"{where}.{key}[{i}]")
                                             for i, e in enumerate(self.formulas[key])]))


def _check_mass(mass, where: str, formula=None) -> float:
    given = f" (the formula {formula!r})" if isinstance(formula, str) else ""
    if isinstance(mass, bool) or not isinstance(mass, int | float | np.number):
        raise InputError(f"mass must be a number in kg or a formula string, got {mass!r}", where=where)
    if not math.isfinite(mass) or mass <= 0:
        raise InputError(f"mass must be a finite positive number, got {mass!r}{given}; "
                         "give a positive mass (or parameter values that make it positive)",
                         where=f"{where}.mass" if formula is not None else where)
    return float(mass)



def length_scale(x: np.ndarray) -> np.ndarray:
    """The largest of |x_i| and the spread of the x_i along an axis (max over axes of
    max_i x_i − min_i x_i), 1 m where both are 0: x (..., n, 3), one value per leading index
    (``System.size``; a batch of starts, ``run.variants``)."""
    x = np.asarray(x, float)
    scale = np.maximum(np.max(np.linalg.norm(x, axis=-1), axis=-1), np.max(np.ptp(x, axis=-2), axis=-1))
    return np.where(scale > 0, scale, 1.0)

class System:
    """Particles, holonomic constraints and effects, with named ``parameters`` (numbers) and
    ``definitions`` (formulas in parameters and other definitions).

    Always three coordinates per particle; motion in a plane is a constraint. Example, a
    pendulum of 1 m in the plane z = 0, built in Python instead of a scene file::

        import constrained as C

        system = C.System(
            [C.Particle("bob", mass=1.0, position=[1.0, 0.0, 0.0])],
            [C.Distance("bob", point=[0, 0, 0], length=1.0), C.Plane("bob", normal=[0, 0, 1])],
            [C.Gravity([0, -9.81, 0])],
        )
        traj = C.simulate(system, 2.0)        # default method dopri, rtol 1e-8
        print(traj.multipliers[-1, 0])        # the rod's multiplier at t = 2 s, in N (tension = −λ)

    In Jupyter a System shows as a table of its particles, constraints, effects, parameters.
    """

    def __init__(
        self,
        particles: Iterable[Particle] = (),
        constraints: Iterable = (),
        effects: Iterable = (),
        parameters: dict[str, float] | None = None,
        name: str = "",
        definitions: dict[str, object] | None = None,
    ):
        self.name = name
        self.particles: list[Particle] = []
        self.constraints: list = []
        self.effects: list = []
        self.parameters: dict[str, float] = {}
        self.definitions: dict[str, object] = {}
        self._values: dict[str, float] | None = None
        #: User events of a scene's [[events]] (constrained.events.FormulaEvent), watched by
        #: every run of this system besides the ``events=`` given to simulate.
        self.events: list = []
        for key, value in (parameters or {}).items():
            self.set_parameter(key, value)
        for key, formula in (definitions or {}).items():
            self.define(key, formula)
        particles = list(particles)
        names = list(map(operator.attrgetter("name"), particles)) \
            if all(map(isinstance, particles, itertools.repeat(Particle))) else None
        if names is not None and len(set(names)) == len(names) \
                and not any(map(operator.attrgetter("formulas"), particles)):
            # (what add_particle does one by one, at once: distinct names, nothing to resolve)
            self.particles = particles
            self._names = (self.particles, len(particles), set(names))
        else:
            for p in particles:
                self.add_particle(p)
        self.add(*constraints, *effects)

    # --- building -------------------------------------------------------------------------
    def add_particle(self, particle_or_name, mass=None, position=None, velocity=(0.0, 0.0, 0.0)):
        """Add a Particle (or build one from name, mass, position, velocity); returns it.
        Its formulas, if any, are evaluated with the system's parameters."""
        if isinstance(particle_or_name, Particle):
            p = particle_or_name
        else:
            p = Particle(particle_or_name, mass, position, velocity)
        names = self._particle_names()
        if p.name in names:
            raise InputError(f"duplicate particle name '{p.name}'", where=p.where or "particles")
        if p.formulas:
            p.resolve(self.parameter_values)
        self.particles.append(p)
        names.add(p.name)
        self._names = (self.particles, len(self.particles), names)
        return p

    def _particle_names(self) -> set[str]:
        """The particles' names as a set, kept while ``particles`` is the same list of the same
        length (O(1) per added particle instead of a scan: a chain of 10,000 adds them in turn)."""
        cache = self.__dict__.get("_names")
        if cache is None or cache[0] is not self.particles or cache[1] != len(self.particles):
            cache = (self.particles, len(self.particles), {q.name for q in self.particles})
        self._names = cache
        return cache[2]

    def add(self, *items):
        """Add constraints and effects (objects from constrained.constraints / .effects)."""
        from .constraints import Constraint
        from .effects import Effect

        kinds = {cls: issubclass(cls, Constraint) or (False if issubclass(cls, Effect) else None)
                 for cls in set(map(type, items))}
        if None not in kinds.values():  # (every class a constraint's or an effect's: in one pass each)
            constraint = list(map(kinds.__getitem__, map(type, items)))
            self.constraints += itertools.compress(items, constraint)
            self.effects += itertools.compress(items, map(operator.not_, constraint))
            return self
        for item in items:
            if isinstance(item, Constraint):
                self.constraints.append(item)
            elif isinstance(item, Effect):
                self.effects.append(item)
            else:
                raise InputError(f"expected a Constraint or an Effect, got {item!r}")
        return self

    def set_parameter(self, key: str, value: float):
        """Set (or add) a parameter; formulas of the particles are evaluated again."""
        from .parameters import check_name, check_value

        if key not in self.parameters:
            check_name(key, f"parameters.{key}", taken=self.definitions)
        self.parameters[key] = check_value(key, value)
        self._changed()

    def define(self, key: str, formula):
        """Add a definition: a named formula in parameters and other definitions (or a number)."""
        from .parameters import check_name, order

        check_name(key, f"definitions.{key}", taken=self.parameters, what="definition")
        if isinstance(formula, str) and not formula.strip() or not isinstance(formula, str | int | float) \
                or isinstance(formula, bool):
            raise InputError(f"a definition must be a formula string or a number, got {formula!r}",
                             where=f"definitions.{key}")
        definitions = {**self.definitions, key: formula}
        order(definitions)  # refuse a cycle now
        self.definitions = definitions
        self._changed()

    def _changed(self) -> None:
        self._values = None
        if any(p.formulas for p in self.particles):
            values = self.parameter_values
            for p in self.particles:
                if p.formulas:
                    p.resolve(values)

    def copy(self) -> System:
        """A copy sharing nothing that changes: particles, lists and tables copied
        (constraints and effects are descriptions, shared)."""
        new = copy.copy(self)
        new.parameters, new.definitions = dict(self.parameters), dict(self.definitions)
        new.constraints, new.effects = list(self.constraints), list(self.effects)
        new.events = list(getattr(self, "events", []))
        new.particles = [p.copy() for p in self.particles]
        new._values = None if self._values is None else dict(self._values)
        return new

    def with_parameters(self, parameters: Mapping[str, float] | None = None) -> System:
        """A copy with these parameters' values changed (names must be parameters of the
        system); particles' formulas (masses, initial positions, velocities) are evaluated
        again. Constraints and effects are shared: they are descriptions, not numbers."""
        from .parameters import check_value

        if not parameters:
            return self
        check_parameter_names(parameters, self.parameters, self.definitions)
        new = copy.copy(self)  # the particles' names were checked when they were added
        new.parameters = {**self.parameters, **{k: check_value(k, v) for k, v in parameters.items()}}
        new.definitions, new._values = dict(self.definitions), None
        new.constraints, new.effects = list(self.constraints), list(self.effects)
        new.particles = [p.copy() for p in self.particles]
        if any(p.formulas for p in new.particles):
            values = new.parameter_values
            for p in new.particles:
                if p.formulas:
                    p.resolve(values)
        return new

    # --- reading ---------------------------------------------------------------------------
    @property
    def n_particles(self) -> int:
        return len(self.particles)

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.particles]

    @property
    def parameter_values(self) -> dict[str, float]:
        """Every parameter and definition as a number (definitions evaluated)."""
        if self._values is None:
            from .parameters import values

            self._values = values(self.parameters, self.definitions)
        return dict(self._values)

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
        known = listed(self.names) or "(none)"
        raise InputError(f"unknown particle '{name}' (particles: {known})", where=where)

    def with_state(self, x: np.ndarray, v: np.ndarray | None = None) -> System:
        """A copy with positions (N, 3) and velocities replaced."""
        x = np.asarray(x, float).reshape(-1, 3)
        v = self.velocities if v is None else np.asarray(v, float).reshape(-1, 3)
        particles = [  # a mass given by a formula stays one; the state is as given
            Particle(p.name, p.formulas.get("mass", p.mass), x[i], v[i], p.where)
            for i, p in enumerate(self.particles)
        ]
        copy = System(particles, self.constraints, self.effects, self.parameters, self.name,
                      self.definitions)
        copy.events = list(self.events)
        return copy

    def size(self) -> float:
        """A length scale: the largest of |x_i| and |x_i - x_j| at the start (1 m if all zero)."""
        x = self.positions
        return float(length_scale(x)) if len(x) else 1.0

    def _repr_html_(self) -> str:
        """Jupyter: one table of what the system holds."""
        from .. import notebook

        return notebook.table(repr(self), self.summary())

    def summary(self) -> list[tuple[str, str]]:
        """``(what, value)`` rows: particles (mass, start), constraints, effects, parameters."""
        rows = []
        for p in self.particles[:20]:
            mass = p.formulas.get("mass", p.mass)
            mass = f"{mass:g} kg" if isinstance(mass, float) else f"{mass} = {p.mass:g} kg"
            rows.append((f"particle {p.name}", f"{mass}, at {_vec(p.position)} m, "
                                               f"moving {_vec(p.velocity)} m/s"))
        if self.n_particles > 20:
            rows.append(("particles", f"… {self.n_particles - 20} more ({self.n_particles} in all)"))
        for what, items in (("constraint", self.constraints), ("effect", self.effects)):
            rows += [(what, item.label) for item in items[:20]]
            if len(items) > 20:
                rows.append((f"{what}s", f"… {len(items) - 20} more ({len(items)} in all)"))
        if self.parameters:
            rows.append(("parameters", ", ".join(f"{k} = {v:g}" for k, v in self.parameters.items())))
        if self.definitions:
            rows.append(("definitions", ", ".join(f"{k} = {v}" for k, v in self.definitions.items())))
        return rows

    def __repr__(self) -> str:
        return (
            f"System({self.name!r}: {self.n_particles} particles, "
            f"{len(self.constraints)} constraints, {len(self.effects)} effects)"
        )


def _vec(value) -> str:
    return "(" + ", ".join(f"{float(c):.4g}" for c in np.asarray(value, dtype=float).ravel()) + ")"


def check_parameter_names(given: Mapping, parameters: Mapping, definitions: Mapping = ()) -> None:
    """Refuse (InputError) a name in ``given`` that is not one of ``parameters``."""
    for key in given:
        if key in parameters:
            continue
        known = ", ".join(parameters) or "(none: the system has no parameters)"
        hint = (f"; '{key}' is a definition (a formula of the parameters): set the parameters it "
                "uses instead" if key in definitions else "")
        raise InputError(f"unknown parameter {key!r} (parameters: {known}){hint}",
                         where=f"parameters.{key}")


def sketch(system) -> dict:
    """What an animation draws of the constraints, as plain lists (stored in a trajectory's
    ``info["sketch"]`` so that ``constrained plot`` draws it without the scene file):
    ``rods`` — particle index pairs held at a distance; ``anchors`` — ``[index, point, length]``
    for a distance to a fixed point (a rod to a pivot; ``length`` a number, or the value of a
    formula of the parameters, else None);
    moving points and formula-valued anchors are left out."""
    names = [p.name for p in system.particles]
    index = {n: k for k, n in enumerate(names)}
    constraints = list(getattr(system, "constraints", ()))
    kinds = {cls: cls.__name__ for cls in set(map(type, constraints))}
    drawn = [c for c, kind in zip(constraints, map(kinds.__getitem__, map(type, constraints)), strict=True)
             if kind == "Distance" or kind == "Pin"]
    try:  # (a cloth's 19,800 rods between particles: their ends looked up in passes)
        ends = [list(map(index.get, map(getattr, drawn, itertools.repeat(end), itertools.repeat(None))))
                for end in ("a", "b")]
    except TypeError:  # (an unhashable end: each found as below)
        ends = [[index[c.a] if getattr(c, "a", None) in index else None for c in drawn]]
        ends.append([index[c.b] if k is not None and getattr(c, "b", None) in index else None
                     for c, k in zip(drawn, ends[0], strict=True)])
    rods = [[a, b] for a, b in zip(*ends, strict=True) if a is not None and b is not None]
    anchors = []
    for k in itertools.compress(range(len(drawn)), map(operator.is_, ends[1], itertools.repeat(None))):
        c, a, point = drawn[k], ends[0][k], getattr(drawn[k], "point", None)
        if a is not None and point is not None and type(c).__name__ == "Distance":
            try:
                anchor = [float(v) for v in point]
            except (TypeError, ValueError):  # a moving anchor (formula of t): not drawn
                continue
            length = getattr(c, "length", None)
            if isinstance(length, str):  # a formula of the parameters (one of t is not drawn)
                from .parameters import evaluate

                try:
                    length = evaluate(length, getattr(system, "parameter_values", {}), "length")
                except InputError:
                    length = None
            anchors.append([a, anchor, float(length) if isinstance(length, int | float) else None])
    return {"rods": rods, "anchors": anchors}


def require_system(system, who: str) -> None:
    """Refuse anything but a System as the first argument of ``who`` (a Scene too: it names
    what to pass instead)."""
    if isinstance(system, System):
        return
    if hasattr(system, "system") and isinstance(getattr(system, "system", None), System):
        raise InputError(f"{who}() takes a System; this is a {type(system).__name__}: pass its .system "
                         f"({who}(scene.system, ...)), or run the scene with its own settings: scene.run()")
    raise InputError(f"{who}() takes a System (constrained.System, or load_scene(file).system) as its "
                     f"first argument, got {type(system).__name__} {system!r:.60}")
