"""Events: user conditions watched during a run, and the records of what happened when.

A user event is a function ``g(t, x, v)`` (x and v flat, 3N) whose zero crossings are
located to round-off during a run, in the habits of ``scipy.integrate.solve_ivp``:
``direction`` +1 keeps only rising crossings (g from − to +), −1 only falling ones, 0 both;
``terminal`` ends the run at the crossing. ``Event`` carries the same fields as the driver's
event hook; a plain callable with optional ``terminal`` / ``direction`` attributes is
accepted too (solve_ivp's defaults then: not terminal, both directions). In a scene, an
``[[events]]`` entry gives a formula in particle coordinates, velocities, t and parameters.

An ``EventRecord`` is what a Trajectory keeps of one event: the time, the constraint (or the
user event's name), the kind (``release``, ``contact``, ``impact`` or the user event's name),
the state there, and for impacts the impulse and the kinetic energy lost.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError

#: The kinds of events the one-sided constraints produce (user events are named by the user).
CONSTRAINT_KINDS = ("release", "contact", "impact")

#: Direction words of a scene's [[events]] entry.
DIRECTIONS = {"rising": 1, "falling": -1, "both": 0}


@dataclass(frozen=True)
class Event:
    """A condition g(t, x, v) = 0 to stop at or to record (fields as the driver's Event)."""

    name: str
    function: Callable[[float, np.ndarray, np.ndarray], float]
    direction: int = 0
    terminal: bool = True

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"an event needs a name (a non-empty string), got {self.name!r}")
        if self.name in CONSTRAINT_KINDS:
            raise InputError(f"the event name {self.name!r} is the name of a constraint event kind "
                             f"({', '.join(CONSTRAINT_KINDS)}); choose another name")
        if self.direction not in (-1, 0, 1) or isinstance(self.direction, bool):
            raise InputError(f"event {self.name!r}: direction must be +1 (rising), -1 (falling) or 0 "
                             f"(both), got {self.direction!r}")
        if not callable(self.function):
            raise InputError(f"event {self.name!r}: function must be callable as g(t, x, v)")
        if not isinstance(self.terminal, bool):
            raise InputError(f"event {self.name!r}: terminal must be true or false, got {self.terminal!r}")


def as_events(events) -> list[Event]:
    """``simulate(events=...)``: one Event or callable, or a list of them, as Events. A plain
    callable takes solve_ivp's defaults (``terminal`` False, ``direction`` 0) unless it
    carries those attributes; its name is its ``__name__``."""
    if events is None:
        return []
    if isinstance(events, Event) or callable(events):
        events = [events]
    if not isinstance(events, Iterable) or isinstance(events, str):
        raise InputError(f"events must be an Event, a callable g(t, x, v) or a list of them, got {events!r}")
    out = []
    for k, e in enumerate(events):
        if isinstance(e, Event):
            out.append(e)
        elif callable(e):
            terminal = getattr(e, "terminal", False)
            direction = getattr(e, "direction", 0)
            # solve_ivp's terminal may be a count; here: stop at the first crossing or never
            out.append(Event(getattr(e, "__name__", None) or f"event {k}", e,
                             int(np.sign(direction)), bool(terminal)))
        else:
            raise InputError(f"events[{k}] must be an Event or a callable g(t, x, v), got {e!r}")
    names = [e.name for e in out]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"two events share the name(s) {', '.join(twice)}: give each its own name, "
                         "the records tell them apart by it")
    return out


@dataclass(frozen=True)
class FormulaEvent:
    """A scene's ``[[events]]`` entry: ``expr`` (a formula in particle coordinates, velocities,
    t and parameters) crossing zero, ``direction`` (+1, −1, 0), ``stop`` (terminal)."""

    name: str
    expr: str
    direction: int = 0
    stop: bool = False
    where: str | None = None

    def event(self, symbols) -> Event:
        """The Event of this formula for a system's Symbols (parsed into CasADi, never eval)."""
        import casadi as ca  # here: a Trajectory (which imports this module) stays light to load

        g = symbols.parse(self.expr, f"{self.where or 'events'}.expr", velocities=True)
        function = ca.Function(f"event_{self.name}", [symbols.t, symbols.x, symbols.v], [g])

        def value(t, x, v, _f=function):
            return float(_f(t, x, v))

        return Event(self.name, value, self.direction, self.stop)


@dataclass
class EventRecord:
    """One event of a run: ``t``, ``constraint`` (its label, or the user event's name),
    ``kind`` (release / contact / impact / the user event's name), the state ``x``, ``v``
    (N, 3; after the velocity jump for an impact), and for an impact the ``impulse`` (N·s along
    the constraint's normal, per unit of its gradient in metres) and ``energy_lost`` (J)."""

    t: float
    constraint: str
    kind: str
    x: np.ndarray
    v: np.ndarray
    impulse: float = 0.0
    energy_lost: float = 0.0
    extra: dict = field(default_factory=dict)

    def describe(self) -> str:
        what = self.kind if self.kind in CONSTRAINT_KINDS else f"event '{self.kind}'"
        text = f"t = {self.t:.10g} s: {what}"
        if self.kind in CONSTRAINT_KINDS:
            text += f" of '{self.constraint}'"
        if self.kind == "impact":
            text += f", impulse {self.impulse:.4g} N·s, kinetic energy lost {self.energy_lost:.4g} J"
        note = self.extra.get("note")
        return text + (f" ({note})" if note else "")


def records_to_arrays(records: list[EventRecord], n_particles: int) -> tuple[dict, list]:
    """(arrays for an .npz, JSON-able meta) of a list of records; inverse: ``records_from``."""
    shape = (len(records), n_particles, 3)
    arrays = {
        "event_t": np.array([r.t for r in records], float),
        "event_x": np.array([np.asarray(r.x, float) for r in records]).reshape(shape),
        "event_v": np.array([np.asarray(r.v, float) for r in records]).reshape(shape),
        "event_impulse": np.array([r.impulse for r in records], float),
        "event_energy_lost": np.array([r.energy_lost for r in records], float),
    }
    meta = [{"constraint": r.constraint, "kind": r.kind, "extra": r.extra} for r in records]
    return arrays, meta


def records_from(arrays: dict, meta: list) -> list[EventRecord]:
    """The records saved by ``records_to_arrays`` (an empty list when the file has none)."""
    if "event_t" not in arrays:
        return []
    return [EventRecord(float(arrays["event_t"][k]), m["constraint"], m["kind"], arrays["event_x"][k],
                        arrays["event_v"][k], float(arrays["event_impulse"][k]),
                        float(arrays["event_energy_lost"][k]), dict(m.get("extra", {})))
            for k, m in enumerate(meta)]


#: Events listed one by one in a run's report (the rest are counted).
REPORT_EVENTS = 20


def report_lines(info: dict, records: list[EventRecord]) -> list[str]:
    """The report's lines on a hybrid run: the held constraints' degrees of freedom over time,
    the events, the energy lost in impacts and a stop at a user event ([] for other runs)."""
    lines = []
    spans = []  # (dof, t_start, t_end), consecutive segments of equal dof merged
    for s in info.get("segments") or []:
        if spans and spans[-1][0] == s["dof"]:
            spans[-1][2] = s["t_end"]
        else:
            spans.append([s["dof"], s["t_start"], s["t_end"]])
    if len(spans) > 1:
        text = [f"{d} (t = {a:.6g} .. {b:.6g} s)" for d, a, b in spans[:8]]
        more = f" … ({len(spans) - 8} more changes)" if len(spans) > 8 else ""
        lines.append("degrees of freedom change as one-sided constraints release and hold: "
                     + " → ".join(text) + more)
    if records:
        lines.append(f"events ({len(records)}):")
        lines += [f"  {r.describe()}" for r in records[:REPORT_EVENTS]]
        if len(records) > REPORT_EVENTS:
            lines.append(f"  … and {len(records) - REPORT_EVENTS} more (trajectory.npz: event_t, "
                         "event_x, event_v, event_impulse, event_energy_lost)")
        impacts = [r for r in records if r.kind == "impact"]
        if impacts:
            lost = sum(r.energy_lost for r in impacts)
            lines.append(f"kinetic energy lost in {len(impacts)} impact(s): {lost:.6g} J")
    if info.get("stopped_by_event"):
        lines.append(f"the run ended at the event '{info['stopped_by_event']}' (stop = true)")
    return lines
