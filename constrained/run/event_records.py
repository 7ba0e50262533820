"""Event records: what a Trajectory keeps of each event of a run, and the report's lines.

An ``EventRecord`` holds the time, the constraint (or the user event's name), the kind
(``release``, ``contact``, ``impact`` or the user event's name), the state there, and for
impacts the impulse and the kinetic energy lost. The events themselves (``Event``: a
function g(t, x, v) whose crossings the driver locates to round-off) are solvers.base's; the
user's come from constrained.user_events.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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
