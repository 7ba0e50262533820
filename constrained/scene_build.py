"""Scene validation: every section of a scene's TOML data checked and turned into what the
Scene holds (the System with its particles, constraints, effects and parameters, the run
settings, outputs, [reduced], [expect], [[events]]). ``SceneBuilder(raw, path).build()``
gives the Scene's fields; constrained.scene makes the Scene."""

from __future__ import annotations

import copy
import functools
import math

import numpy as np

from . import expressions
from .constraints import CONSTRAINT_TYPES
from .effects import EFFECT_TYPES
from .errors import InputError
from .expectations import force_names
from .model import kept_structure
from .parameters import RESERVED_NAMES
from .regularity import undefined_items
from .scene_keys import (
    _CONSERVED_KEYS,
    CONSTRAINT_KEYS,
    EFFECT_KEYS,
    EVENT_KEYS,
    EXPECT_KEYS,
    MAX_SAMPLES,
    MAX_STEPS,
    MAX_TIME,
    ONE_SIDED_KEYS,
    OUTPUT_DEFAULTS,
    OUTPUT_FORMATS,
    OUTPUT_PLOTS,
    OUTPUT_QUANTITIES,
    SIMULATE_DEFAULTS,
    TOP_LEVEL_TABLES,
)
from .scene_validate import Validator, _describe, _is_number, _join, _name_or_value, _suggest
from .symbols import Symbols
from .system import Particle, System


def _why_singular(obj, system: System, t0: float) -> str:
    """The likely reason an item is undefined at the start: two ends at one place."""
    a, b, point = (getattr(obj, k, None) for k in ("a", "b", "point"))
    if not isinstance(a, str):
        return "; move the particles away from the singular point (e.g. r = 0 in a formula)"
    names = [p.name for p in system.particles]
    pos = np.asarray(system.positions, float).reshape(-1, 3)
    here = pos[names.index(a)] if a in names else None
    if isinstance(b, str) and b in names and here is not None and np.allclose(here, pos[names.index(b)]):
        return (f": particles '{a}' and '{b}' start at the same position, where the direction "
                "between them is undefined; move one of them")
    if point is not None and here is not None:
        return (f": particle '{a}' starts on the point {list(point)}, where the direction from "
                "the point is undefined; move the particle (to the rod's length from the point)")
    return "; move the particles away from the singular point"


#: [expect] formulas (with the particles' names) that parsed before and use no parameter.
_PARSED_FORMULAS: dict = {}


class SceneBuilder(Validator):
    """Validates a scene's sections in turn (``build``) with the checks of Validator."""

    # sections ---------------------------------------------------------------------------
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
        for k in TOP_LEVEL_TABLES:
            if k in self.raw and k != "expect":
                self.finite_everywhere(self.raw[k], k)

        name, description = self.scene_section()
        particles = self.particles()
        parameters = self.parameters()
        definitions = self.definitions(parameters)
        constraints = [
            self.item(i, item, "constraints") for i, item in enumerate(self.array_of_tables("constraints"))
        ]
        effects = [self.item(i, item, "effects") for i, item in enumerate(self.array_of_tables("effects"))]
        try:
            system = System(particles, constraints, effects, parameters, name, definitions)
        except InputError as exc:
            self.fail(exc.where, exc.reason)
        structure = self.structure(system)
        system.events = self.events_section(system)
        settings = self.simulate()
        if "reduced" not in self.raw:  # with [reduced], crosscheck starts from the mapped state
            self.regular_start(system, settings["t_start"], structure)
        outputs = self.outputs()
        reduced = self.reduced({**parameters, **definitions})
        expect = self.raw.get("expect")
        expectations = None if expect is None else self.expect_section(expect, system)
        return dict(
            path=self.path,
            name=name,
            system=system,
            settings=settings,
            outputs=outputs,
            reduced=reduced,
            raw=self.raw,
            expect=None if expect is None else copy.deepcopy(expect),
            description=description,
            expectations=expectations,
            units=dict(self.raw.get("scene", {}).get("units", {})),
        )

    def expect_section(self, table: dict, system: System) -> list[dict]:
        """Validate [expect]; returns one normalized check per entry (formulas parsed once here)."""
        self.keys(table, "expect", EXPECT_KEYS, what="[expect]")
        symbols: list[Symbols] = []  # made when a formula is parsed
        out: list[dict] = []

        def formula(text, key: str):
            if _is_number(text):
                return self.number(text, key)
            if not isinstance(text, str) or not text.strip():
                self.fail(key, f"must be a number or a formula string, got {_describe(text)}")
            # a formula of coordinates, velocities, forces and t alone parses the same for
            # every scene with these particles: checked once (parameters' values could matter)
            names = (text, tuple(system.names))
            if names in _PARSED_FORMULAS:
                return text
            if not symbols:
                symbols.append(Symbols(system))
            s = symbols[0]
            try:
                s.parse(text, key, velocities=True, extra=force_names(s))
            except InputError as exc:
                self.fail(key, exc.reason)
            if not expressions.free_names(text) & (set(system.parameters) | set(system.definitions)):
                _PARSED_FORMULAS[names] = None
                while len(_PARSED_FORMULAS) > 256:
                    _PARSED_FORMULAS.pop(next(iter(_PARSED_FORMULAS)))
            return text

        def tolerance(value, key: str) -> float:
            tol = self.number(value, key, "a tolerance (a number >= 0)")
            if tol < 0:
                self.fail(key, f"must be a tolerance >= 0, got {value!r}")
            return tol

        def pairs(name: str, what: str):
            sub = self.table(table[name], f"expect.{name}", f"a table formula -> {what}")
            for lhs, value in sub.items():
                key = _join(f"expect.{name}", lhs)
                formula(lhs, key)
                if not isinstance(value, list) or len(value) != 2:
                    got = f"{len(value)} entries" if isinstance(value, list) else _describe(value)
                    self.fail(key, f"must be a list {what}, got {got}")
                yield lhs, value, key

        for name in EXPECT_KEYS:
            if name not in table:
                continue
            key = f"expect.{name}"
            if name in ("energy_drift", "constraint_residual", "velocity_residual"):
                out.append({"kind": name, "key": key, "tol": tolerance(table[name], key)})
            elif name in ("final", "closed_form", "period"):
                for lhs, (value, tol), k in pairs(name, "[value or formula, tolerance]"):
                    out.append({"kind": name, "key": k, "lhs": lhs, "rhs": formula(value, _join(k, 0)),
                                "tol": tolerance(tol, _join(k, 1))})
            elif name in ("bounds", "reaches"):
                for lhs, (lo, hi), k in pairs(name, "[lowest, highest]"):
                    lo_, hi_ = (self.number(v, _join(k, i)) if not (_is_number(v) and math.isinf(v))
                                else float(v) for i, v in enumerate((lo, hi)))
                    if lo_ > hi_:
                        self.fail(k, f"lowest ({lo_:g}) is above highest ({hi_:g})")
                    out.append({"kind": name, "key": k, "lhs": lhs, "lo": lo_, "hi": hi_})
            else:  # conserved
                sub = self.table(table[name], key, "a table name -> {axis, point, translation, tol}")
                for label, entry in sub.items():
                    k = _join(key, label)
                    self.table(entry, k, "a table {axis = [..], point = [..], tol = ..} or "
                               "{translation = [..], tol = ..}")
                    self.keys(entry, k, _CONSERVED_KEYS, ("tol",), what="a conserved quantity")
                    if "axis" not in entry and "translation" not in entry:
                        self.fail(k, "give 'axis' (and optionally 'point') for a rotation, or "
                                  "'translation', the symmetry whose Noether charge is conserved")
                    if "point" in entry and "axis" not in entry:
                        self.fail(_join(k, "point"), "'point' needs 'axis' (the rotation axis)")
                    vec = {v: self.numbers3(entry[v], _join(k, v)) for v in ("axis", "point", "translation")
                           if v in entry}
                    for v in ("axis", "translation"):
                        if v in vec and not any(vec[v]):
                            self.fail(_join(k, v), "must not be the zero vector")
                    out.append({"kind": name, "key": k, "label": label,
                                "rotation": (vec["axis"], vec.get("point", [0.0, 0.0, 0.0]))
                                if "axis" in vec else None,
                                "translation": vec.get("translation"),
                                "tol": tolerance(entry["tol"], _join(k, "tol"))})
        return out

    def events_section(self, system: System) -> list:
        """[[events]]: name, a formula crossing zero, direction, stop (constrained.events)."""
        from .events import CONSTRAINT_KINDS
        from .user_events import DIRECTIONS, FormulaEvent

        entries = self.array_of_tables("events")
        s = Symbols(system) if entries else None
        out, seen = [], {}
        for i, item in enumerate(entries):
            key = _join("events", i)
            self.keys(item, key, EVENT_KEYS[0] + EVENT_KEYS[1], EVENT_KEYS[0], what="an event")
            name = self.string(item["name"], f"{key}.name", "an event name")
            if name in seen or name in CONSTRAINT_KINDS:
                taken = f"also events[{seen[name]}]" if name in seen else "a constraint event kind"
                self.fail(f"{key}.name", f"the event name '{name}' is taken ({taken}); give each event "
                          "its own name")
            seen[name] = i
            expr = self.string(item["expr"], f"{key}.expr", "a formula string (zero at the event)")
            try:
                s.parse(expr, f"{key}.expr", velocities=True)
            except InputError as exc:
                self.fail(exc.where or f"{key}.expr", exc.reason)
            direction = item.get("direction", "both")
            if direction not in DIRECTIONS and direction not in (-1, 0, 1) or isinstance(direction, bool):
                self.fail(f"{key}.direction", f"must be \"rising\" (the formula crossing zero upward), "
                          f"\"falling\" or \"both\", got {_describe(direction)}")
            stop = item.get("stop", False)
            if not isinstance(stop, bool):
                self.fail(f"{key}.stop", "must be true (the run ends at the event) or false, "
                          f"got {_describe(stop)}")
            out.append(FormulaEvent(name, str(expr), DIRECTIONS.get(direction, direction), stop, where=key))
        return out

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

    def parameters(self) -> dict[str, float]:
        table = self.raw.get("parameters", {})
        reserved = self.reserved_for_formulas()
        out = {}
        for k, v in table.items():
            key = _join("parameters", k)
            self.identifier(k, key, "a parameter name")
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
        reserved = self.reserved_for_formulas()
        for k, v in table.items():
            key = _join("definitions", k)
            self.identifier(k, key, "a definition name")
            if k in reserved or k in parameters:
                what = "a parameter" if k in parameters else "it already means something in formulas"
                self.fail(key, f"the definition name '{k}' is taken ({what})")
            self.formula(v, key)
        return dict(table)

    def item(self, i: int, item: dict, section: str):
        """One [[constraints]] or [[effects]] entry -> the library object."""
        key = _join(section, i)
        kind = "constraint" if section == "constraints" else "effect"
        types = CONSTRAINT_TYPES if section == "constraints" else EFFECT_TYPES
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
        if k == "restitution":
            return self.number(v, key, "a coefficient of restitution from 0 to 1")
        if k in ("a", "b", "particle"):
            return self.particle(v, key)
        if k == "particles":
            return self.particle_list(v, key)
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
        structure, numbers = structure if structure is not None else self.structure(system)
        for section, i, obj in undefined_items(system, t0, structure=structure, numbers=numbers)[:1]:
            what = "constraint" if section == "constraints" else "effect"
            self.fail(_join(section, i), f"this {what} ({obj.label}) is undefined at the initial state "
                      f"(t = {t0:g} s): its value or its gradient is not finite there"
                      f"{_why_singular(obj, system, t0)}")

    def simulate(self) -> dict:
        table = self.raw.get("simulate", {})
        self.keys(table, "simulate", SIMULATE_DEFAULTS, what="[simulate]")
        s = dict(SIMULATE_DEFAULTS)
        s.update(table)
        k = "simulate."
        if s["t_end"] is not None:
            s["t_end"] = self.positive(s["t_end"], k + "t_end", "a finite positive time (s)")
        s["t_start"] = self.number(s["t_start"], k + "t_start", "a time in s")
        if s["t_end"] is not None and s["t_end"] <= s["t_start"]:
            self.fail(k + "t_end", f"must be later than t_start = {s['t_start']:g}, got {s['t_end']:g}")
        s["method"] = self.string(s["method"], k + "method", "a method name")
        s["base"] = self.string(s["base"], k + "base", "an integrator name")
        self.method_and_base(s["method"], s["base"], "base" in table)
        s["rtol"] = self.number(s["rtol"], k + "rtol")
        if not 0 < s["rtol"] < 1:
            self.fail(k + "rtol", f"must be between 0 and 1 (exclusive), got {s['rtol']:g}")
        s["atol"] = self.number(s["atol"], k + "atol")
        if not 0 < s["atol"] < 1:
            self.fail(k + "atol", f"must be between 0 and 1 (exclusive), got {s['atol']:g}")
        for name in ("dt", "output_dt"):
            if s[name] is not None:
                s[name] = self.positive(s[name], k + name, "a finite positive time step (s)")
        if s["samples"] is not None:
            n = s["samples"]
            if not isinstance(n, int) or isinstance(n, bool) or n < 2:
                self.fail(k + "samples", f"must be a whole number >= 2, got {_describe(n)}")
        if s["samples"] is not None and s["output_dt"] is not None:
            self.fail(k + "samples", "give either 'samples' or 'output_dt', not both")
        self.run_size(s)
        mic = self.number(s["max_initial_correction"], k + "max_initial_correction")
        if mic < 0:
            self.fail(k + "max_initial_correction", f"must be zero or positive, got {mic!r}")
        s["max_initial_correction"] = mic
        if s["compiled"] not in (True, False, "auto"):
            self.fail(k + "compiled", f'must be true, false or "auto", got {_describe(s["compiled"])}')
        if s["method"] == "reduced" and "reduced" not in self.raw:
            self.fail(k + "method", "method 'reduced' needs the scene's [reduced] section "
                      "(coordinates, initial, rates, map)")
        return s

    def run_size(self, s: dict) -> None:
        """Times a step can resolve, and a bounded number of output samples and fixed steps."""
        k = "simulate."
        for name in ("t_start", "t_end"):
            if s[name] is not None and abs(s[name]) > MAX_TIME:
                self.fail(k + name, f"{s[name]:g} s is beyond {MAX_TIME:g} s: at such times a float "
                          "cannot resolve a time step; shift the clock (t_start = 0)")
        if s["samples"] is not None and s["samples"] > MAX_SAMPLES:
            self.fail(k + "samples", f"{s['samples']} output samples is more than the {MAX_SAMPLES} "
                      "accepted; ask for fewer")
        if s["t_end"] is None:
            return
        span = s["t_end"] - s["t_start"]
        if s["output_dt"] is not None and span / s["output_dt"] > MAX_SAMPLES:
            self.fail(k + "output_dt", f"{s['output_dt']:g} s over {span:g} s gives more than the "
                      f"{MAX_SAMPLES} output samples accepted; use a larger output_dt")
        if s["dt"] is not None and span / s["dt"] > MAX_STEPS:
            self.fail(k + "dt", f"{s['dt']:g} s over {span:g} s is more than {MAX_STEPS:g} steps; "
                      "use a larger dt")

    def method_and_base(self, method: str, base: str, base_given: bool) -> None:
        """``method`` must be a registered solver; ``base`` one its solver accepts."""
        from .solvers import METHODS

        if method not in METHODS:
            self.fail(
                "simulate.method",
                f"unknown method '{method}' (known methods: {', '.join(sorted(METHODS))})"
                f"{_suggest(method, METHODS)}",
            )
        cls = METHODS[method]
        if "base" not in cls.OPTIONS:
            if base_given:
                self.fail("simulate.base", f"method '{method}' does not take a base integrator")
            return
        bases = cls.BASES
        if bases and base not in bases:
            others = [m for m, c in METHODS.items() if base in c.BASES]
            hint = (f"; '{base}' is a base of method {', '.join(others)}: add method = "
                    f"\"{others[0]}\"" if others else _suggest(base, bases))
            self.fail(
                "simulate.base",
                f"unknown base integrator '{base}' for method '{method}' "
                f"(known: {', '.join(bases)}){hint}",
            )

    def outputs(self) -> dict:
        table = self.raw.get("outputs", {})
        self.keys(table, "outputs", OUTPUT_DEFAULTS, what="[outputs]")
        out = {k: list(v) for k, v in OUTPUT_DEFAULTS.items()}
        allowed = {
            "quantities": OUTPUT_QUANTITIES,
            "plots": OUTPUT_PLOTS,
            "formats": OUTPUT_FORMATS,
        }
        for k, v in table.items():
            out[k] = self.string_list(v, f"outputs.{k}", allowed[k], k)
        return out

    def reduced(self, parameters: dict) -> dict | None:
        if "reduced" not in self.raw:
            return None
        table = self.raw["reduced"]
        self.keys(
            table,
            "reduced",
            ("coordinates", "initial", "rates", "map"),
            ("coordinates", "initial", "map"),
            what="[reduced]",
        )
        coords = table["coordinates"]
        if not isinstance(coords, list) or not coords:
            self.fail("reduced.coordinates", f"must be a non-empty list of names, got {_describe(coords)}")
        taken = self.reserved_for_formulas() | set(parameters)
        for i, c in enumerate(coords):
            key = _join("reduced.coordinates", i)
            self.identifier(c, key, "a coordinate name")
            if c in coords[:i]:
                self.fail(key, f"coordinate '{c}' is listed twice")
            if c in taken:
                what = "a parameter" if c in parameters else "a name formulas already use"
                self.fail(key, f"the coordinate name '{c}' is taken ({what})")

        def values(name: str, complete: bool) -> dict[str, float]:
            tab = self.table(table.get(name, {}), f"reduced.{name}", "a table coordinate -> number")
            for k in tab:
                if k not in coords:
                    self.fail(
                        _join(f"reduced.{name}", k),
                        f"'{k}' is not a coordinate (coordinates: {', '.join(coords)}){_suggest(k, coords)}",
                    )
            if complete:
                for c in coords:
                    if c not in tab:
                        self.fail(_join(f"reduced.{name}", c), f"missing the initial value of '{c}'")
            return {c: self.number(tab.get(c, 0.0), _join(f"reduced.{name}", c)) for c in coords}

        initial = values("initial", True)
        rates = values("rates", False)
        mapping = self.table(table["map"], "reduced.map", "a table particle name -> [x, y, z] formulas")
        out_map = {}
        for k, v in mapping.items():
            key = _join("reduced.map", k)
            if k not in self.names:
                self.fail(key, f"names unknown particle '{k}' (particles: {', '.join(self.names)})")
            out_map[k] = self.formulas(v, key, 3, "formulas (x, y, z) in the coordinates")
        for p in self.names:
            if p not in out_map:
                self.fail(
                    _join("reduced.map", p),
                    f"particle '{p}' is not mapped; every particle needs x, y, z",
                )
        return {
            "coordinates": list(coords),
            "initial": initial,
            "rates": rates,
            "map": {p: out_map[p] for p in self.names},
        }
