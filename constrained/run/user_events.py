"""User events: a scene's ``[[events]]`` formulas and ``simulate(events=...)``, as the
driver's ``Event`` (solvers.base).

An event is a function ``g(t, x, v)`` (x and v flat, 3N) whose zero crossings are located to
round-off during a run, in the habits of ``scipy.integrate.solve_ivp``: ``direction`` +1
keeps only rising crossings (g from − to +), −1 only falling ones, 0 both; ``terminal`` ends
the run at the crossing. Besides ``Event`` objects, ``simulate`` takes plain callables with
optional ``terminal`` / ``direction`` attributes (solve_ivp's defaults then: not terminal,
both directions).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..solvers.base import Event
from ..solvers.driver import event_resolution, same_instant
from .event_records import CONSTRAINT_KINDS

#: Direction words of a scene's [[events]] entry.
DIRECTIONS = {"rising": 1, "falling": -1, "both": 0}


def as_events(events) -> list[Event]:
    """``simulate(events=...)``: one Event or callable, or a list of them, as Events; a plain
    callable is named by its ``__name__``."""
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
            # solve_ivp's terminal may be a count; here: stop at the first crossing or never
            out.append(Event(getattr(e, "__name__", None) or f"event {k}", e,
                             int(np.sign(getattr(e, "direction", 0))), bool(getattr(e, "terminal", False))))
        else:
            raise InputError(f"events[{k}] must be an Event or a callable g(t, x, v), got {e!r}")
    return out


def user_events(system, events) -> list[Event]:
    """The scene's [[events]] (``system.events``) and the ``events=`` given to simulate, with
    names that tell them apart and from the constraint event kinds."""
    out = []
    formulas = getattr(system, "events", ()) or ()
    if formulas:
        from ..model.symbols import Symbols

        symbols = Symbols(system)
        out = [f.event(symbols) for f in formulas]
    out += as_events(events)
    names = [e.name for e in out]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"two events share the name(s) {', '.join(twice)}: give each its own name, "
                         "the records tell them apart by it")
    taken = sorted(set(names) & set(CONSTRAINT_KINDS))
    if taken:
        raise InputError(f"the event name(s) {', '.join(taken)} are the kinds of constraint events "
                         f"({', '.join(CONSTRAINT_KINDS)}); choose other names")
    return [dataclasses.replace(e, ignore_round_off=True) for e in out]


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
        import casadi as ca

        g = symbols.parse(self.expr, f"{self.where or 'events'}.expr", velocities=True)
        # (not named after the event: CasADi allows only identifiers, an event may be "half way")
        function = ca.Function("user_event", [symbols.t, symbols.x, symbols.v], [g])

        def value(t, x, v, _f=function):
            return float(_f(t, x, v))

        return Event(self.name, value, self.direction, self.stop)


def jumped_through_zero(events, t: float, before: tuple, after: tuple, atol: float) -> list[Event]:
    """The ``events`` whose value jumps through zero at t, where the state jumps from
    ``before`` = (x, v) to ``after`` (an impact: the velocities change at once), in their
    direction: g(t, before) < −r and g(t, after) > r is a rising crossing, the reverse a
    falling one. r is the run's resolution (``driver.event_resolution``) for events that ignore
    round-off, else 0: a plastic impact lands vy on zero, give or take round-off, and that is
    no crossing. The velocity of a ball bouncing off a floor is such an event: it never passes
    through zero along the motion, yet its sign changes at the bounce."""
    out = []
    for e in events:
        g0, g1 = float(e.function(t, *before)), float(e.function(t, *after))
        if not (np.isfinite(g0) and np.isfinite(g1)):
            continue
        r = max(event_resolution(e.function, atol, t, *state) for state in (before, after)) \
            if e.ignore_round_off else 0.0
        rising, falling = g0 < -r and g1 > r, g0 > r and g1 < -r
        if (rising and e.direction >= 0) or (falling and e.direction <= 0):
            out.append(e)
    return out


def recorded_jumps(user_events, t: float, before: tuple, after: tuple, atol: float, records: list, record):
    """The user's events that the state's jump at t (an impact) takes through zero
    (``jumped_through_zero``: vy of a bouncing ball) recorded, unless a crossing of the same
    event was recorded at this instant already; returns the first terminal one, or None."""
    stop = None
    for e in jumped_through_zero(user_events, t, before, after, atol):
        if any(r.kind == e.name and -same_instant(-t) <= r.t <= same_instant(t) for r in records):
            continue
        record(t, e.name, e.name, *after)
        if e.terminal and stop is None:
            stop = e
    return stop
