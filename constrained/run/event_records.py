"""Event records: what a Trajectory keeps of each event of a run and of the smooth segments
between them (``checked_segments``), and the report's lines.

An ``EventRecord`` holds the time, the constraint (or the user event's name), the kind
(``release``, ``contact``, ``impact`` or the user event's name), the state there, and for
impacts the impulse and the kinetic energy lost. The events themselves (``Event``: a
function g(t, x, v) whose crossings the driver locates to round-off) are solvers.base's; the
user's come from constrained.user_events.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

#: The kinds of events the one-sided constraints produce (user events are named by the user).
CONSTRAINT_KINDS = ("release", "contact", "impact")


@dataclass
class EventRecord:
    """One event of a run: ``t``, ``constraint`` (its label, or the user event's name),
    ``kind`` (release / contact / impact / the user event's name), the state ``x``, ``v``
    (N, 3; after the velocity jump for an impact), and for an impact the ``impulse`` (N·s along
    the constraint's normal, per unit of its gradient in metres) and ``energy_lost`` (J, in the
    constraint's frame: ½(1 − e²) m u² with u the approach speed relative to a moving surface;
    the fixed frame's T⁺ − T⁻ is ``extra["kinetic_energy_change"]``)."""

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


def checked_segments(segments, t, labels, where: str, fix: str, t_end: float | None = None) -> list[dict]:
    """The segments of a hybrid run (``Trajectory.info["segments"]``: ``t_start``, ``t_end`` in
    seconds, ``held`` the labels of the rows held there, and ``dof``), as plain dicts, checked
    against the run they describe: times finite, t_start ≤ t_end, in order without overlap and
    within the run (its first sample to its last, or to the ``t_end`` it was asked for, which a
    run that stopped early records), held rows among ``labels`` (unchecked when None). Anything
    else raises InputError naming ``where`` with the entry and key, and ``fix``."""
    def refuse(what: str):
        raise InputError(f"{where}{what}; {fix}")

    if not isinstance(segments, list | tuple):
        refuse(f" is {type(segments).__name__}, not a list of segments {{t_start, t_end, held}}")
    t = np.asarray(t, float)
    first = float(t[0]) if len(t) else 0.0
    last = max(float(t[-1]) if len(t) else 0.0, float(t_end) if t_end is not None else -np.inf)
    slack = 1e-9 * max(last - first, abs(first), abs(last), 1e-300)  # (JSON keeps floats exactly)
    known = None if labels is None else set(labels)
    out, previous_end = [], -np.inf
    for k, seg in enumerate(segments):
        if not isinstance(seg, dict):
            refuse(f"[{k}] is {type(seg).__name__}, not a table {{t_start, t_end, held}}")
        times = []
        for key in ("t_start", "t_end"):
            value = seg.get(key)
            if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
                refuse(f"[{k}]['{key}'] is {value!r}, not a time in seconds")
            times.append(float(value))
        t0, t1 = times
        if t1 < t0:
            refuse(f"[{k}] ends (t_end = {t1:g} s) before it starts (t_start = {t0:g} s)")
        if t0 < first - slack or t1 > last + slack:
            refuse(f"[{k}] spans t = {t0:g} .. {t1:g} s, outside the run ({first:g} .. {last:g} s)")
        if t0 < previous_end - slack:
            refuse(f"[{k}] starts at t = {t0:g} s, before segment {k - 1} ends ({previous_end:g} s)")
        previous_end = t1
        held = seg.get("held", [])
        if not isinstance(held, list | tuple) or not all(isinstance(h, str) for h in held):
            refuse(f"[{k}]['held'] is {held!r}, not a list of constraint labels")
        unknown = [h for h in held if known is not None and h not in known]
        if unknown:
            rows = ", ".join(repr(h) for h in list(labels)[:6]) + (" …" if len(known) > 6 else "")
            refuse(f"[{k}]['held'] names {', '.join(repr(h) for h in unknown)}, not a constraint row "
                   f"(the rows: {rows})")
        dof = seg.get("dof")
        if dof is not None and (isinstance(dof, bool) or not isinstance(dof, int) or dof < 0):
            refuse(f"[{k}]['dof'] is {dof!r}, not a number of degrees of freedom")
        out.append({**seg, "t_start": t0, "t_end": t1, "held": list(held)})
    return out


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
    ended = records and info.get("stop") == "terminal event"
    stopped = info.get("stopped_by_event") or (records[-1].kind if ended else None)
    if stopped:
        lines.append(f"the run ended at the event '{stopped}' (stop = true)")
    return lines
