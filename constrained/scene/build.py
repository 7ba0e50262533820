"""Scene validation: every section of a scene's TOML data checked and turned into what the
Scene holds (the System with its particles, constraints, effects and parameters, the run
settings, outputs, [reduced], [expect], [[events]]). ``SceneBuilder(raw, path).build()``
gives the Scene's fields; constrained.scene makes the Scene."""

from __future__ import annotations

import copy
import functools

import numpy as np

from ..errors import InputError
from ..manifold.manifold import constraint_values, potential_forces_finite, sparse_jacobian
from ..manifold.vectorized import graphs as vectorized
from ..model import expressions
from ..model.constraints import CONSTRAINT_TYPES
from ..model.effects import EFFECT_TYPES
from ..model.parameters import RESERVED_NAMES, check_name
from ..model.regularity import undefined_items, unresolved_reason, unresolved_rods
from ..model.structure import Model, kept_structure
from ..model.symbols import Symbols
from ..model.system import Particle, System
from ..model.velocity import VELOCITY_TYPES
from .keys import (
    CONSTRAINT_KEYS,
    EFFECT_KEYS,
    ONE_SIDED_KEYS,
    TOP_LEVEL_TABLES,
)
from .plain import plain_pairs, plain_particles
from .sections import RunSections
from .validate import _describe, _join, _name_or_value, _suggest


def _why_singular(obj, system: System, t0: float) -> str:
    """The likely reason an item is undefined at the start: two ends at one place."""
    if hasattr(obj, "why_undefined"):  # the item knows (a knife edge's blade direction)
        why = obj.why_undefined([p.name for p in system.particles], system.positions, t0)
        if why:
            return f": {why}"
    a, b, point = (getattr(obj, k, None) for k in ("a", "b", "point"))
    closest = obj.closest_pair(system, system.positions) if hasattr(obj, "closest_pair") else None
    if closest is not None:
        a, b, d = closest
        where = "at the same position" if d == 0 else f"{d:.3g} m apart"
        return (f": its closest pair, particles '{a}' and '{b}', start {where}, where V(r) is singular "
                "(e.g. r = 0 in the formula); move one of them")
    if not isinstance(a, str):
        return "; move the particles away from the singular point (e.g. r = 0 in a formula)"
    names = [p.name for p in system.particles]
    pos = np.asarray(system.positions, float).reshape(-1, 3)
    here = pos[names.index(a)] if a in names else None
    if isinstance(b, str) and b in names and here is not None and np.allclose(here, pos[names.index(b)]):
        return (f": particles '{a}' and '{b}' start at the same position, where the direction "
                "between them is undefined; move one of them")
    largest = float(np.max(np.abs(pos), initial=0.0))
    if largest > 1e100:  # (a formula's value: e.g. a length parameter of 1e300 as a position)
        return (f": the start has coordinates of {largest:.3g} m, whose squares overflow; use units "
                "(or parameter values) that keep the numbers moderate")
    try:
        anchor = np.asarray(point, float) if point is not None else None
    except (TypeError, ValueError):  # a moving point (formulas): its place at t0 is not known here
        anchor = np.full(3, np.nan)
    if anchor is not None and here is not None and (not np.all(np.isfinite(anchor))
                                                    or np.allclose(here, anchor, rtol=0, atol=1e-12)):
        return (f": particle '{a}' starts on the point {list(point)}, where the direction from "
                "the point is undefined; move the particle (to the rod's length from the point)")
    return "; move the particles away from the singular point"


class SceneBuilder(RunSections):
    """Validates a scene's sections in turn (``build``) with the checks of Validator."""

    # sections ---------------------------------------------------------------------------
    #: False: the System without its equations (no Structure, no start checks): enough to draw
    #: the scene (``load_scene(..., equations=False)``).
    equations = True
    #: True: every number of the raw data is known to be finite and moderate (load_scene's walk).
    numbers_checked = False

    def build(self) -> dict:
        """Validate every section and build the System: the fields of the Scene."""
        for k in self.raw:
            if k not in TOP_LEVEL_TABLES:
                self.fail(
                    k,
                    f"unknown top-level table '{k}' (allowed: {', '.join(TOP_LEVEL_TABLES)})"
                    f"{_suggest(k, TOP_LEVEL_TABLES)}",
                )
        for k in ("scene", "parameters", "definitions", "simulate", "outputs", "reduced", "expect"):
            if k in self.raw:
                self.table(self.raw[k], k, f"a table [{k}]")
        for k in TOP_LEVEL_TABLES if not self.numbers_checked else ():
            if k in self.raw and k != "expect":
                self.finite_everywhere(self.raw[k], k)

        name, description = self.scene_section()
        particles = self.particles()
        parameters = self.parameters()
        definitions = self.definitions(parameters)
        constraints, effects = self.items("constraints"), self.items("effects")
        try:
            system = System(particles, constraints, effects, parameters, name, definitions)
            for c in system.constraints:  # a formula's value in [0, 1] (sweeps check theirs per run)
                if c.unilateral:
                    c.coefficient_of_restitution(system.parameter_values)
        except InputError as exc:
            self.fail(exc.where, exc.reason)
        structure = self.structure(system) if self.equations else None
        system.events = self.events_section(system)
        settings = self.simulate()
        if "reduced" not in self.raw and self.equations:  # with [reduced], crosscheck starts from
            self.regular_start(system, settings["t_start"], structure)  # the mapped state
        outputs = self.outputs()
        reduced = self.reduced({**parameters, **definitions})
        expect = self.raw.get("expect")
        expectations = None if expect is None else self.expect_section(expect, system)
        return dict(
            path=self.path,
            name=name,
            system=system,
            settings=settings,
            given_settings=frozenset(self.raw.get("simulate", {})),
            outputs=outputs,
            reduced=reduced,
            raw=self.raw,
            expect=None if expect is None else copy.deepcopy(expect),
            description=description,
            expectations=expectations,
            units=dict(self.raw.get("scene", {}).get("units", {})),
            structure=None if structure is None else (system, *structure),
        )

    def scene_section(self) -> tuple[str, str]:
        table = self.raw.get("scene", {})
        self.keys(table, "scene", ("name", "description", "units"), what="[scene]")
        units = table.get("units", {})
        if not isinstance(units, dict) or not all(isinstance(v, str) for v in units.values()):
            self.fail("scene.units", "must be a table of unit strings, e.g. units = { a = \"m\", "
                      f"nu = \"rad/s\" }}, got {_describe(units)}")
        default = self.path.stem if self.path is not None else "scene"
        name = self.string(table["name"], "scene.name") if "name" in table else default
        description = table.get("description", "")
        if not isinstance(description, str):
            self.fail("scene.description", f"must be a string, got {_describe(description)}")
        return name, description

    def particles(self) -> list[Particle]:
        items = self.array_of_tables("particles")
        if not items:
            self.fail("particles", "the scene has no particles; add at least one [[particles]] table")
        fast = plain_particles(items)  # all plain numbers (a large scene): checked at once
        if fast is not None:
            self.names = [p.name for p in fast]
            return fast
        out = []
        seen: dict[str, int] = {}
        for i, item in enumerate(items):
            key = _join("particles", i)
            self.keys(
                item,
                key,
                ("name", "mass", "position", "velocity"),
                ("name", "mass", "position"),
                what="a particle",
            )
            name = self.identifier(item["name"], f"{key}.name", "a particle name")
            if name in seen:
                self.fail(
                    f"{key}.name",
                    f"duplicate particle name '{name}' (also particles[{seen[name]}])",
                )
            seen[name] = i
            mass = item["mass"]
            if isinstance(mass, str):  # a formula of the parameters, evaluated by the System
                mass = self.formula(mass, f"{key}.mass")
            elif self.positive(mass, f"{key}.mass", "a finite positive number (kg) or a formula "
                               "of the parameters") < 1 / expressions.MAX_MAGNITUDE:
                self.fail(f"{key}.mass", f"the mass {mass!r} kg is too small (below "
                          f"{1 / expressions.MAX_MAGNITUDE:g}): 1/m overflows in the equations of motion; "
                          "use units that keep the numbers moderate")
            position = self.formulas(item["position"], f"{key}.position", 3,
                                     "numbers or formulas of the parameters (x, y, z)")
            velocity = self.formulas(item.get("velocity", [0.0, 0.0, 0.0]), f"{key}.velocity", 3,
                                     "numbers or formulas of the parameters (x, y, z)")
            try:
                out.append(Particle(name, mass, position, velocity, where=key))
            except InputError as exc:
                self.fail(exc.where or key, exc.reason)
        self.names = list(seen)
        return out

    def numbers3(self, value, key: str) -> list[float]:
        if not isinstance(value, list) or len(value) != 3:
            got = f"{len(value)} entries" if isinstance(value, list) else _describe(value)
            self.fail(key, f"must be a list of 3 numbers (x, y, z), got {got}")
        return [self.number(v, _join(key, i)) for i, v in enumerate(value)]

    def reserved_for_formulas(self) -> set[str]:
        names = set(RESERVED_NAMES)
        for p in self.names:
            for axis in "xyz":
                names |= {f"{axis}_{p}", f"v{axis}_{p}"}
        return names

    def name_for_formulas(self, name: str, key: str, what: str) -> None:
        """Refuse a name no formula could use (a keyword of the syntax, e, a function), saying why."""
        try:
            check_name(name, key, what=what)
        except InputError as exc:
            self.fail(key, exc.reason)

    def parameters(self) -> dict[str, float]:
        table = self.raw.get("parameters", {})
        reserved = self.reserved_for_formulas() if table else ()
        out = {}
        for k, v in table.items():
            key = _join("parameters", k)
            self.identifier(k, key, "a parameter name")
            self.name_for_formulas(k, key, "parameter")
            if k in reserved:
                self.fail(
                    key,
                    f"the parameter name '{k}' is taken (it already means something in formulas)",
                )
            out[k] = self.number(v, key, "a number")
        return out

    def definitions(self, parameters: dict) -> dict:
        """[definitions]: name -> a formula in parameters and other definitions (or a number)."""
        table = self.raw.get("definitions", {})
        reserved = self.reserved_for_formulas() if table else ()
        for k, v in table.items():
            key = _join("definitions", k)
            self.identifier(k, key, "a definition name")
            self.name_for_formulas(k, key, "definition")
            if k in reserved or k in parameters:
                what = "a parameter" if k in parameters else "it already means something in formulas"
                self.fail(key, f"the definition name '{k}' is taken ({what})")
            self.formula(v, key)
        return dict(table)

    def items(self, section: str) -> list:
        """The objects of the ``[[constraints]]`` or ``[[effects]]`` tables, in order (a rod or a
        spring of plain numbers by the fast path, constrained.scene.plain; any other by ``item``)."""
        items = self.array_of_tables(section)
        types = {**CONSTRAINT_TYPES, **VELOCITY_TYPES} if section == "constraints" else EFFECT_TYPES
        plain = plain_pairs(items, section, self.name_set(), types)
        return [obj if obj is not None else self.item(i, item, section)
                for i, (item, obj) in enumerate(zip(items, plain, strict=True))]

    def item(self, i: int, item: dict, section: str):
        """One [[constraints]] or [[effects]] entry -> the library object."""
        key = _join(section, i)
        kind = "constraint" if section == "constraints" else "effect"
        types = {**CONSTRAINT_TYPES, **VELOCITY_TYPES} if section == "constraints" else EFFECT_TYPES
        schema = CONSTRAINT_KEYS if section == "constraints" else EFFECT_KEYS
        if "type" not in item:
            self.fail(
                f"{key}.type",
                f"missing required key 'type' (known {kind} types: {', '.join(types)})",
            )
        typ = item["type"]
        if not isinstance(typ, str) or typ not in types:
            self.fail(
                f"{key}.type",
                f"unknown {kind} type {_name_or_value(typ)} (known types: {', '.join(types)})"
                f"{_suggest(typ, types)}",
            )
        if typ not in schema:
            self.fail(f"{key}.type", f"the {kind} type '{typ}' cannot be used from scene files yet")
        required, optional = schema[typ]
        if kind == "constraint":
            optional = (*optional, *ONE_SIDED_KEYS)
        self.keys(item, key, ("type", "name", *required, *optional), required, what=f"a {typ} {kind}")
        name = self.string(item["name"], f"{key}.name", "a name") if "name" in item else None
        args = {k: self.value(typ, k, v, f"{key}.{k}") for k, v in item.items() if k not in ("type", "name")}
        self.pairing(typ, args, key)
        cls = types[typ]
        try:
            return self.construct(cls, typ, args, name=name, where=key)
        except InputError as exc:
            self.fail(exc.where or key, exc.reason)

    def value(self, typ: str, k: str, v, key: str):
        if k == "unilateral":
            if not isinstance(v, bool):
                self.fail(key, f"must be true (a one-sided constraint) or false, got {_describe(v)}")
            return v
        if k == "restitution":  # a number, or a formula of the parameters (swept like any)
            if isinstance(v, str):
                return self.formula(v, key)
            return self.number(v, key, "a coefficient of restitution from 0 to 1, or a formula of the "
                               "parameters")
        if k in ("cutoff", "skin"):
            return self.positive(v, key, "a positive length in m (a plain number)")
        if k == "exclude_bonded":
            if not isinstance(v, bool):
                self.fail(key, f"must be true (leave out pairs joined by a distance constraint) or false, "
                          f"got {_describe(v)}")
            return v
        if k in ("a", "b", "particle"):
            return self.particle(v, key)
        if k == "particles":
            return self.particle_list(v, key)
        if k in ("across", "along"):  # a knife edge's direction: two particles
            pair = self.particle_list(v, key)
            if len(pair) != 2:
                self.fail(key, f"must be a list of two particle names (the direction from the first to "
                               f"the second), got {len(pair)}")
            return pair
        if k in ("point", "normal", "g", "A"):
            return self.vector(v, key)
        if k == "expr":
            if typ == "curve":
                return self.formulas(v, key, 2, "surface formulas")
            if typ == "force":
                return self.formulas(v, key, 3, "force formulas (Fx, Fy, Fz)")
            return self.formula(v, key)
        if k == "charges":
            self.table(v, key, "a table particle name -> charge")
            if not v:
                self.fail(key, "must name at least one particle")
            return {
                self.particle(name, _join(key, name)): self.formula(q, _join(key, name))
                for name, q in v.items()
            }
        return self.formula(v, key)  # length, offset, k, rest, coefficient, phi

    def pairing(self, typ: str, args: dict, key: str) -> None:
        if typ in ("distance", "spring", "central"):
            if ("b" in args) == ("point" in args):
                self.fail(key, "give exactly one of 'b' (a particle) or 'point'")
        if typ == "damping":
            if ("a" in args) != ("b" in args):
                self.fail(key, "pairwise damping needs both 'a' and 'b'")
            if "a" in args and "particles" in args:
                self.fail(key, "give either 'particles' or the pair 'a', 'b', not both")
        if "a" in args and args.get("b") == args["a"]:
            self.fail(f"{key}.b", f"'a' and 'b' name the same particle '{args['a']}'")

    @staticmethod
    def construct(cls, typ: str, args: dict, *, name, where):
        a = dict(args)
        sides = {k: a.pop(k) for k in ONE_SIDED_KEYS if k in a}
        if sides:  # one-sided keys go to every constraint type
            return SceneBuilder.construct(functools.partial(cls, **sides), typ, a, name=name, where=where)
        if typ == "curve":
            return cls(a.pop("particles"), exprs=a.pop("expr"), name=name, where=where)
        if typ == "pin":
            return cls(a.pop("a"), a.pop("point"), name=name, where=where)
        if typ == "plane":
            return cls(a.pop("particles"), a.pop("normal"), a.pop("offset", 0.0), name=name, where=where)
        if typ == "surface":
            return cls(a.pop("particles"), a.pop("expr"), name=name, where=where)
        if typ in ("distance", "spring", "central"):
            return cls(a.pop("a"), a.pop("b", None), **a, name=name, where=where)
        if typ == "gravity":
            return cls(a.pop("g"), a.pop("particles", None), name=name, where=where)
        if typ == "damping":
            return cls(a.pop("coefficient"), a.pop("particles", None), **a, name=name, where=where)
        if typ == "force":
            return cls(a.pop("particle"), a.pop("expr"), name=name, where=where)
        if typ == "electromagnetic":
            return cls(a.pop("charges"), **a, name=name, where=where)
        return cls(**a, name=name, where=where)  # custom, potential: expr

    def structure(self, system: System) -> tuple:
        """The system's Structure and plain numbers (``model.kept_structure``: built here, or
        the one kept from an equal scene read before, and kept for the run), which parses and
        differentiates every formula: a bad one is reported at load time, with its item's key
        (``check_formulas`` finds the item when the Structure's error does not name one)."""
        try:
            return kept_structure(system)
        except (InputError, RuntimeError, TypeError, ValueError, ZeroDivisionError) as exc:
            self.check_formulas(system)
            if isinstance(exc, InputError):
                self.fail(exc.where or "effects", exc.reason)
            self.fail("constraints", f"the equations cannot be built: {exc}")

    def check_formulas(self, system: System) -> tuple[Symbols, dict]:
        """Parse every formula now (cheap), so a bad one is reported at load time; returns the
        Symbols and the built rows and terms, {(section, index): value}, for ``regular_start``."""
        s = Symbols(system)
        built = {}
        for section, items, call in (
            ("constraints", system.constraints, lambda c: c.rows(s)),
            ("effects", system.effects, lambda e: e.term(s)),
        ):
            for i, obj in enumerate(items):
                key = _join(section, i)
                try:
                    built[section, i] = call(obj)
                except InputError as exc:
                    self.fail(exc.where or key, exc.reason)
                except (RuntimeError, TypeError, ZeroDivisionError) as exc:
                    self.fail(key, f"cannot be built: {exc}")
        return s, built

    def regular_start(self, system: System, t0: float, structure: tuple | None = None) -> None:
        """Every constraint row, its gradient, and every effect's term and gradients must be
        finite at the initial state: a rod whose particle sits on its anchor, or a 1/r potential
        at r = 0, is refused here with the item's key instead of failing inside a solver
        (constrained.regularity: one sparse evaluation for the whole system, of a Function
        built once per structure). ``structure``: ``(Structure, numbers)`` of the system."""
        for i, rod, length, smallest in unresolved_rods(system)[:1]:
            self.fail(f"{_join('constraints', i)}.length", unresolved_reason(rod, length, smallest))
        structure, numbers = structure if structure is not None else self.structure(system)
        jacobian, effects_finite = None, False
        model = Model(system, structure=structure, numbers=numbers)
        if vectorized.applies(model):  # large: the run's vectorized build, not an SX Jacobian
            f, J = constraint_values(model), sparse_jacobian(model)
            jacobian = lambda x, t: (f(x, t)[0], J(x, t))  # noqa: E731
            # potentials alone: one evaluation of F and V says whether every effect is finite
            # (a term and its gradient per effect in SX: 0.4 s for a cloth's 19,602 springs)
            if structure.active_terms <= {"constraints", "rheonomic", "potential", "time_dependent_forces"}:
                effects_finite = potential_forces_finite(model)(system.positions, system.velocities, t0)
        undefined = undefined_items(system, t0, model=model, jacobian=jacobian,
                                    effects_finite=effects_finite)
        for section, i, obj in undefined[:1]:
            what = "constraint" if section == "constraints" else "effect"
            self.fail(_join(section, i), f"this {what} ({obj.label}) is undefined at the initial state "
                      f"(t = {t0:g} s): its value or its gradient is not finite there"
                      f"{_why_singular(obj, system, t0)}")

