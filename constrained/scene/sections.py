"""The sections of a scene that say how to run it and what to check: [simulate] (with the
method, its base and the run's size limits), [outputs], [reduced], [expect] and [[events]].
``RunSections`` validates them; ``build.SceneBuilder`` adds the System's sections."""

from __future__ import annotations

import math

from ..errors import InputError
from ..model import expressions
from ..model.symbols import Symbols
from ..model.system import System
from .expectations import force_names
from .keys import (
    _CONSERVED_KEYS,
    EVENT_KEYS,
    EXPECT_KEYS,
    MAX_SAMPLES,
    MAX_STEPS,
    MAX_TIME,
    OUTPUT_DEFAULTS,
    OUTPUT_FORMATS,
    OUTPUT_PLOTS,
    OUTPUT_QUANTITIES,
    SIMULATE_DEFAULTS,
)
from .validate import Validator, _describe, _is_number, _join, _suggest

#: [expect] formulas (with the particles' names) that parsed before and use no parameter.
_PARSED_FORMULAS: dict = {}


class RunSections(Validator):
    """[simulate], [outputs], [reduced], [expect] and [[events]], validated with Validator's checks."""

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
        from ..run.event_records import CONSTRAINT_KINDS
        from ..run.user_events import DIRECTIONS, FormulaEvent

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
        if s["rest_speed"] is not None:
            s["rest_speed"] = self.number(s["rest_speed"], k + "rest_speed", "a speed in m/s")
            if s["rest_speed"] < 0:
                self.fail(k + "rest_speed", f"must be a speed >= 0 in m/s, got {s['rest_speed']:g}")
        if s["max_steps"] is not None:
            n = s["max_steps"]
            if not isinstance(n, int) or isinstance(n, bool) or n < 1:
                self.fail(k + "max_steps", f"must be a whole number >= 1, got {_describe(n)}")
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
        from ..solvers import METHODS

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
