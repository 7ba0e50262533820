"""The hybrid run: smooth segments between events, for one-sided constraints and user events.

Within a segment the held rows (every two-sided row and the active one-sided ones,
``unilateral.ActiveSet``) are integrated as an ordinary constrained run. The segment watches

* each active one-sided row's signed multiplier μ = side · λ (falling through zero: release),
* each inactive one-sided row's gap g = side · f (falling through zero: contact),
* the user's events,

located to round-off on the integrator's dense output (``unilateral.SegmentWatch``: a row
that starts a segment touching — just bounced off, or let go — is watched so that the
transition's round-off is no new event). At a release the row leaves the active set; at a
contact the impact law (``unilateral.impact``) gives the velocity jump, and the row joins the
active set when it then holds (force of the allowed sign) and does not bounce off: a bead
stopped by a plastic impact (e = 0) that the rest of the body then pulls away lifts off.
Every change is an ``EventRecord`` in ``Trajectory.events``.

**Rest rule** (against Zeno chatter: a ball with e < 1 bounces infinitely often in a finite
time): when the rebound speed e·u of an impact is below ``rest_speed`` (default
``REST_SPEED_PER_ATOL × atol`` m/s, the velocities the integrator resolves), the contact
settles: the row joins the active set as if e were 0. A run with more than ``max_events``
events, or segments, stops with a message naming the chattering constraint.

Each segment is a run of the common driver (solvers/driver.py, ``run_segment``) with the
method asked for (``projection``, ``dopri`` or ``baumgarte``; the others refuse, see
``refuse_method``) on the model holding the segment's rows (``constrained.held``): the
driver locates the releases, contacts and user events to round-off. User events on a model
without one-sided constraints go through the driver directly (simulate).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .. import interrupt
from ..errors import InconsistentStateError, InputError, RunInterrupted, SimulationError
from ..manifold.algebra import algebra_for
from ..manifold.manifold import Manifold
from ..model.held import held
from ..model.structure import Model
from ..solvers import METHODS
from ..solvers.base import Failure, Status
from ..solvers.driver import same_instant
from .action_integral import action
from .event_records import EventRecord
from .quantities import constraint_forces_along, trajectory_from
from .trajectory import Trajectory
from .unilateral import (
    MAX_IMPACT_ROUNDS,
    ActiveSet,
    ImpactHistory,
    SegmentWatch,
    check_allowed_side,
    constraint_velocities,
    gaps,
    holding_set,
    impact,
    one_sided,
    scales,
    unloaded_rows,
)
from .user_events import recorded_jumps

#: Default rest speed = this × atol (m/s): rebounds slower than that settle (see the module).
REST_SPEED_PER_ATOL = 1e3
#: Events a run may have before it is stopped as chattering.
MAX_EVENTS = 10_000
#: A Zeno sequence settles when its accumulation point is nearer than this (s; or 1000 ε |t_end|
#: when larger): flights much shorter than that are below what a gap of round-off 1e-16 m (and
#: an event instant of round-off ε |t|) resolves, and all the remaining bounces fit in it.
ZENO_TIME = 1e-6


#: Methods a hybrid run can use: adaptive, with events located to round-off in a segment
#: that may hold no constraint at all (the SUNDIALS methods need constraints, rattle has no
#: adaptive step to land an event).
SEGMENT_METHODS = ("projection", "dopri", "baumgarte")


def refuse_method(method: str, options: dict) -> None:
    """An InputError when ``method`` (with ``options``) cannot run one-sided constraints."""
    if method not in SEGMENT_METHODS:
        raise InputError(
            f"method '{method}' cannot run one-sided constraints: use {', '.join(SEGMENT_METHODS)} "
            "(dopri is the default), which switch the held constraints at each release, "
            "contact and impact")
    if options.get("dt") is not None:
        raise InputError("one-sided constraints need adaptive steps (each event is located "
                         "to round-off inside a step): remove dt")
    base = options.get("base")
    if method == "projection" and base is not None and base.startswith("CVODES"):
        raise InputError(f"base integrator '{base}' cannot run one-sided constraints; "
                         "choose from DOP853, RK45, Radau")


def run_segment(model: Model, rows, x0, v0, t0: float, t_end: float, *, t_eval, events, method: str,
                options: dict):
    """One segment through the common driver: ``method`` on the model holding ``rows``
    (constrained.held), from (x0, v0, t0) to t_end or a terminal event.

    Returns (t, x, v, hits, failure, stats): samples at ``t_eval`` (or at the steps, t0 and
    the end included, when None), every event hit in time order, a failure text or None
    ("interrupted" after Ctrl-C)."""
    sub = held(model, rows)
    stepper = METHODS[method](Manifold.at(sub, x0, t0), **options)
    sol = stepper.run(x0, v0, t0, t_end, t_eval=t_eval, events=events)
    t, x, v = sol.t, sol.x, sol.v
    terminal = next((h for h in sol.events if h.event.terminal), None)
    if terminal is not None and t_eval is not None and len(t) and t[-1] == terminal.t \
            and not np.any(np.asarray(t_eval) == terminal.t):
        t, x, v = t[:-1], x[:-1], v[:-1]  # the driver's last sample: an event, not an output
    failure = None
    if sol.status is Status.INTERRUPTED:
        failure = "interrupted"
    elif sol.status not in (Status.COMPLETED, Status.EVENT):
        failure = sol.failure  # its text, carrying its status (solvers.base.Failure)
    return t, x, v, sol.events, failure, sol.stats


@dataclass
class HybridRun:
    """A hybrid run's samples, its ``segments`` (first sample, end sample, held rows, t0, t1),
    the ``records`` and how it ended."""

    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    segments: list
    records: list
    failure: str | None = None
    stopped_by: str | None = None  # a terminal user event's name
    nfev: int = 0
    steps: int = 0  # accepted steps of every segment's method, summed (not the samples kept)
    #: the start's projection onto the rows held there: largest change of a coordinate (m, m/s)
    start_correction: tuple[float, float] = (0.0, 0.0)


def run(model: Model, x0, v0, t0: float, t_end: float, *, t_eval=None, rtol=1e-8, atol=1e-10,
        method="projection", options=None, user_events=(), rest_speed=None, max_events=MAX_EVENTS, size=1.0,
        max_correction=np.inf) -> HybridRun:
    """Segments between events from a consistent-enough (x0, v0) at t0 to t_end (module doc)."""
    info = one_sided(model)
    rest = REST_SPEED_PER_ATOL * atol if rest_speed is None else float(rest_speed)
    touch = 1e-8 * size
    tol = 1e-13 * size
    records: list[EventRecord] = []
    N = model.n_particles

    def record(t, label, kind, x, v, **extra):
        records.append(EventRecord(float(t), label, kind, x.reshape(N, 3).copy(), v.reshape(N, 3).copy(),
                                   **extra))

    x, v, t = np.asarray(x0, float), np.asarray(v0, float), float(t0)
    # the start: one-sided rows touching (within `touch`) are candidates, as at a contact
    g = gaps(model, x, t) / scales(model, x, t)
    rows = [k for k in range(model.n_constraints) if k not in info.rows or g[k] <= touch]
    x_given, v_given = x, v
    x, _, err = ActiveSet(model, rows, at=(x, t)).project(x, v, t, tol)
    # velocities onto the two-sided rows only: a touching one-sided row's approach is an
    # impact at the start, its separation a lift-off (_transition), not a correction
    one_sided_rows = set(info.rows)  # (sets: thousands of rows)
    two_sided = [k for k in rows if k not in one_sided_rows]
    v = (ActiveSet(model, two_sided, at=(x, t)).manifold.project_velocities(x, v, t) if two_sided
         else np.array(v))
    _check_start(model, x_given, x, t, rows, err, size, max_correction)
    start_correction = (float(np.max(np.abs(x - x_given), initial=0.0)),
                        float(np.max(np.abs(v - v_given), initial=0.0)))
    start_rows = set(rows)
    touching = [k for k in info.rows if k in start_rows]
    touching_set = set(touching)
    rows = [k for k in rows if k not in touching_set]
    history = ImpactHistory(max(ZENO_TIME, 1e3 * np.finfo(float).eps * abs(t_end)))
    before = (x, v)
    active, x, v, rebounding = _transition(model, x, v, t, rows, touching, rest, tol, record, at_start=True,
                                           history=history, touch=touch)
    jumped = recorded_jumps(user_events, t, before, (x, v), atol, records, record)

    T, X, V, segments = [], [], [], []
    grid = None if t_eval is None else np.asarray(t_eval, float)
    stopped_by, failure, nfev, steps = None, None, 0, 0
    if jumped is not None:  # a terminal event crossed by the start's impact: the start is the run
        T, X, V, segments, stopped_by = [t], [x], [v], [(0, 1, active.rows, t, t)], jumped.name
    ended: dict[str, int] = {}  # constraint label -> segments its event ended
    while stopped_by is None:
        watch = SegmentWatch(model, active, list(user_events), t, x, rebounding, touch=touch, round_off=tol)
        if grid is None:
            seg_eval = None
        else:
            first = not T
            seg_eval = grid[(grid >= t) & (grid <= t_end)] if first else grid[(grid > t) & (grid <= t_end)]
        ts, xs, vs, hits, failure, seg_stats = run_segment(
            model, active.rows, x, v, t, t_end, t_eval=seg_eval, events=watch.events, method=method,
            options={"rtol": rtol, "atol": atol, **(options or {})})
        nfev += int(seg_stats.get("nfev", 0))
        steps += int(seg_stats.get("steps", 0))
        if grid is None and T:  # the segment's first sample is the state after the last event
            ts, xs, vs = ts[1:], xs[1:], vs[1:]
        start = len(T)
        for tk, xk, vk in zip(ts, xs, vs, strict=True):
            if T and tk <= T[-1]:  # a segment of zero length (an event at its start): no new sample
                continue
            xk, vk, _ = active.project(xk, vk, tk, tol)
            T.append(float(tk))
            X.append(xk)
            V.append(vk)
        terminal = next((h for h in hits if h.event.terminal), None)
        if terminal is not None:  # a user's stop at the instant of a contact or release: a stop
            terminal = next((h for h in hits if h.event.terminal and watch.kind(h.event)[0] == "user"
                             and h.t <= same_instant(terminal.t)), terminal)
        t_stop = terminal.t if terminal is not None else float(t_end)
        segments.append((start, len(T), active.rows, t, t_stop))
        for h in hits:
            if watch.kind(h.event)[0] == "user" and (not h.event.terminal or h is terminal):
                record(h.t, h.event.name, h.event.name, h.x, h.v)
        if failure or terminal is None:
            break
        t = terminal.t
        x, v, _ = active.project(terminal.x, terminal.v, t, tol)
        kind, row = watch.kind(terminal.event)
        if kind == "user":  # a stop: its state is the run's last sample (output grid or not)
            stopped_by = terminal.event.name
            if not T or T[-1] < t:
                T.append(t)
                X.append(x)
                V.append(v)
                segments[-1] = (*segments[-1][:1], len(T), *segments[-1][2:])
            break
        if interrupt.requested():
            failure = "interrupted"
            break
        held = [k for k in active.rows if k != row]
        if kind == "release":
            record(t, model.constraint_labels[row], "release", x, v)
        closing = [row] if kind == "contact" else []
        closing += _also_closing(model, x, v, t, active.rows, closing, touch)
        before = (x, v)
        active, x, v, rebounding = _transition(model, x, v, t, held, closing, rest, tol, record,
                                               history=history, touch=touch)
        ended[model.constraint_labels[row]] = ended.get(model.constraint_labels[row], 0) + 1
        jumped = recorded_jumps(user_events, t, before, (x, v), atol, records, record)
        if jumped is not None:  # a stop: the state after the jump is the run's last sample
            stopped_by = jumped.name
            if T and T[-1] == t:  # (the segment's last sample is the state before the jump)
                X[-1], V[-1] = x, v
            else:
                T.append(t)
                X.append(x)
                V.append(v)
                segments.append((len(T) - 1, len(T), active.rows, t, t))
            break
        if len(records) > max_events or len(segments) > max_events:
            failure = _chattering(records, ended, max_events, t)
            break
    n3 = model.n_coordinates
    return HybridRun(np.array(T), np.array(X).reshape(-1, n3), np.array(V).reshape(-1, n3), segments,
                     records, failure, stopped_by, nfev, steps, start_correction)


def _chattering(records, ended: dict[str, int], max_events: int, t: float) -> Failure:
    """The stop of a run past its work budget: more than ``max_events`` events recorded, or
    more than ``max_events`` segments (each ends at an event, a transition that records
    nothing included: no loop of segments runs without end), naming the constraint with the
    most of them."""
    counts: dict[str, int] = {}
    for r in records:
        counts[r.constraint] = counts.get(r.constraint, 0) + 1
    what = "events"
    if len(records) <= max_events:
        counts, what = ended, "segments"
    worst = max(counts, key=counts.get)
    return Failure(Status.STEP_LIMIT, f"more than {max_events} {what} by t = {t:.6g} s, {counts[worst]} "
                   f"of them of '{worst}': the constraint chatters (opens and closes ever faster); raise "
                   "rest_speed so that slow rebounds settle, or give restitution = 0")


def _also_closing(model: Model, x, v, t, held, closing, touch) -> list[int]:
    """Other free one-sided rows closing at the same instant (a ball into a corner): touching
    (gap within ``touch``) and approaching."""
    info = one_sided(model)
    s = scales(model, x, t)
    g = gaps(model, x, t) / s
    c = info.side * constraint_velocities(model, x, v, t)
    taken = set(held) | set(closing)  # (a set: thousands of rows)
    return [k for k in info.rows if k not in taken and g[k] <= touch and c[k] < 0]


def _check_start(model: Model, x_given, x, t, rows, err, size, max_correction) -> None:
    """Refuse a start that the held rows cannot reach, or only by moving a particle more than
    ``max_correction × size`` (as ``start.consistent_start`` does for two-sided runs)."""
    moved = float(np.max(np.linalg.norm((x - x_given).reshape(-1, 3), axis=1), initial=0.0))
    f = np.abs(gaps(model, x_given, t)) / scales(model, x_given, t)
    worst = max(rows, key=lambda k: f[k]) if rows else None
    label = model.constraint_labels[worst] if worst is not None else ""
    if not np.isfinite(err) or err > 1e-8 * size:
        raise InconsistentStateError(
            f"the constraints cannot all be satisfied near the initial state: constraint '{label}' "
            f"is violated by {f[worst]:.3g} m at the start and the projection does not reach it; check "
            "that the constraints are compatible (lengths, anchors)")
    if moved > max_correction * size:
        raise InconsistentStateError(
            f"the initial positions are too far from the constraints: constraint '{label}' is violated "
            f"by {f[worst]:.3g} m at t = {t:g}, and the nearest consistent state moves a particle by "
            f"{moved:.3g} m, more than the allowed {max_correction:g} × system size {size:.3g} m. "
            "Correct the positions, or raise simulate.max_initial_correction")


def _transition(model: Model, x, v, t, held, closing, rest, tol, record, at_start=False,
                history: ImpactHistory | None = None, touch: float = 0.0):
    """Rows ``closing`` meet the state at t while ``held`` are held: impacts (with the rest
    rule), then the holding test; returns (the new ActiveSet, x, v, the rows that bounced off
    with their rebound speeds g' > 0 in the row's own units per second).

    The impacts at one instant are resolved **in turn** (Newton's cradle): the rows closing
    take the first impulse, with every held row that carries a load kept rigid; a one-sided row
    that touches without load (free within ``touch``, or held with a force that is zero but for
    round-off, ``unloaded_rows``) takes no impulse then, but takes its own impact, with its own
    restitution, if the jump makes it approach; and so on (``MAX_IMPACT_ROUNDS``)."""
    info = one_sided(model)
    labels = model.constraint_labels
    s = scales(model, x, t)
    c = constraint_velocities(model, x, v, t)
    approach = {k: max(0.0, -info.side[k] * c[k] / s[k]) for k in closing}
    # a start moving away from a touched one-sided row leaves it free
    joining = [k for k in closing if not at_start or info.side[k] * c[k] / s[k] <= rest]
    hit = [k for k in joining if approach[k] > rest]
    bounced: dict[int, float] = {}
    struck: list[int] = []
    if hit:
        unloaded = unloaded_rows(model, held, x, v, t)
        unloaded_set = set(unloaded)
        held = [k for k in held if k not in unloaded_set]
        g = gaps(model, x, t) / s
        held_set = set(held)
        pool = set(closing) | unloaded_set | {k for k in info.rows if k not in held_set and g[k] <= touch}
        settled: set[int] = set()
        c_now = c
        for round_ in range(MAX_IMPACT_ROUNDS + 1):
            speed = {k: -info.side[k] * c_now[k] / s[k] for k in hit}
            v, held, settles = _impact_round(model, x, v, t, held, hit, speed, settled, rest, record,
                                             None if round_ else history, last=round_ == MAX_IMPACT_ROUNDS)
            settled |= settles
            struck += [k for k in hit if k not in struck]
            c_now = constraint_velocities(model, x, v, t)
            held_set = set(held)
            hit = sorted(k for k in pool if k not in held_set and -info.side[k] * c_now[k] / s[k] > rest)
            if not hit or round_ == MAX_IMPACT_ROUNDS:
                break
        joining = [k for k in joining if k not in struck] + sorted(settled)
        bounced = {k: float(info.side[k] * c_now[k]) for k in struck if k not in settled}
        bounced = {k: w for k, w in bounced.items() if w > 0}
        for k in unloaded:  # not struck: held again unless the jump moves it off
            if k not in struck and info.side[k] * c_now[k] / s[k] <= rest:
                held.append(k)
            elif k not in struck:
                record(t, labels[k], "release", x, v, extra={"note": "released by the impact"})
    candidates = sorted(set(held) | set(joining))
    active, dropped = holding_set(model, candidates, x, v, t, tol=0.0)
    for k in joining:
        if k in struck:
            continue
        if k not in dropped and not at_start:  # the start's held rows are in info["segments"]
            away = info.side[k] * c[k] / s[k]
            note = ({"note": f"settles: moving off at {away:.3g} m/s, a flight too short for the run to "
                             "resolve in time"} if away > 0 else {})
            record(t, labels[k], "contact", x, v, extra={"approach_speed": approach[k], **note})
    for k in dropped:
        if k not in joining:
            record(t, labels[k], "release", x, v)
    x, v, _ = active.project(x, v, t, tol)
    return active, x, v, bounced


def _impact_round(model: Model, x, v, t, held, hit, speed, settled, rest, record, history, last: bool):
    """One impact of a transition's sequence: the rows ``hit`` (approach ``speed``, m/s) close
    on (x, v) with ``held`` kept; returns (v after, the rows still held, the rows that settle:
    restitution 0, by the rest rule, having settled before at this instant, or in the
    ``last`` round, which ends a sequence that would not)."""
    info = one_sided(model)
    labels = model.constraint_labels
    e = {k: info.restitution[k] for k in hit}
    notes = {}
    for k in hit:
        note = history.settles(k, t, e[k] * speed[k], rest) if history is not None else None
        if note is None and e[k] * speed[k] <= rest:
            note = f"rebound speed {e[k] * speed[k]:.3g} m/s below the rest speed {rest:.3g} m/s"
        if note is None and last:
            note = f"more than {MAX_IMPACT_ROUNDS} impacts in turn at this instant"
        if note is not None and e[k] > 0 and k not in settled:
            notes[k] = "settles: " + note
    settles = {k for k in hit if k in notes or e[k] == 0 or k in settled}
    result = impact(model, x, v, t, held, hit, {k: (0.0 if k in settles else e[k]) for k in hit})
    for k in result.released:
        record(t, labels[k], "release", x, result.v, extra={"note": "released by the impact"})
    for k in hit:
        record(t, labels[k], "impact", x, result.v, impulse=result.impulse[k],
               energy_lost=result.energy_lost if k == hit[0] else 0.0,
               extra={"approach_speed": speed[k], "restitution": float(e[k]),
                      **({"kinetic_energy_change": result.kinetic_energy_change} if k == hit[0] else {}),
                      **({"note": notes[k]} if k in notes else {})})
    return result.v, [k for k in held if k not in result.released], settles


# ---- the run as simulate returns it --------------------------------------------------------------
def simulate_hybrid(model: Model, system, t_start: float, t_end: float, *, method: str, rtol: float,
                    atol: float, t_eval, wanted, events, max_initial_correction: float, build_time: float,
                    options: dict) -> Trajectory:
    """``simulate`` for a model with one-sided constraints or user events."""
    options = dict(options)
    rest_speed = options.pop("rest_speed", None)
    max_events = options.pop("max_events", MAX_EVENTS)
    refuse_method(method, options)
    options = {k: value for k, value in options.items() if k != "dt"}
    if rest_speed is not None and not (isinstance(rest_speed, int | float) and rest_speed >= 0):
        raise InputError(f"rest_speed must be a speed >= 0 in m/s, got {rest_speed!r}")
    size = system.size()
    x0, v0 = np.asarray(system.positions, float).ravel(), np.asarray(system.velocities, float).ravel()
    check_allowed_side(model, x0, t_start, max_initial_correction * size)
    started = time.perf_counter()
    with interrupt.watch():
        result = run(model, x0, v0, t_start, t_end, t_eval=t_eval, rtol=rtol, atol=atol, method=method,
                     options=options,
                     user_events=events, rest_speed=rest_speed, max_events=max_events, size=size,
                     max_correction=max_initial_correction)
        if not result.failure and interrupt.requested():  # Ctrl-C in the last step: a stop too
            result.failure = "interrupted"
    wall = time.perf_counter() - started
    correction = float(np.max(np.linalg.norm((result.x[0] - x0).reshape(-1, 3), axis=1), initial=0.0)) \
        if len(result.t) else 0.0
    stats = {"nfev": result.nfev, "segments": len(result.segments), "events": len(result.records),
             "steps": result.steps, "wall_time_s": wall, "build_time_s": build_time,
             "method": method}
    traj = trajectory_quantities(model, result, wanted, stats)
    if "action" in wanted and len(traj.t) >= 2:
        traj.action = action(model, traj).cumulative
    reached = float(traj.t[-1]) if len(traj.t) else t_start
    traj.info.update({
        "initial_correction": {"position": correction, "velocity": result.start_correction[1],
                               "projection": result.start_correction[0]},
        "system": system.name, "method": method, "rtol": rtol, "atol": atol,
        "active_terms": sorted(model.active_terms),
        "status": ("interrupted" if result.failure == "interrupted" else
                   "stopped" if result.failure else "completed"),
        "stop": (Status.EVENT.value if result.stopped_by else
                 Status.INTERRUPTED.value if result.failure == "interrupted" else
                 getattr(result.failure, "status", Status.SOLVER_FAILED).value if result.failure
                 else Status.COMPLETED.value),
        "t_end": float(t_end), "t_end_reached": reached,
        "segments": [{"t_start": t0, "t_end": t1, "held": [model.constraint_labels[k] for k in rows],
                      "dof": _dof(model, result, i0, rows)} for i0, _, rows, t0, t1 in result.segments],
    })
    if traj.info["segments"]:  # the report's header: the start's degrees of freedom
        traj.info["degrees_of_freedom"] = traj.info["segments"][0]["dof"]
    if result.stopped_by:
        traj.info["stopped_by_event"] = result.stopped_by
    if result.failure == "interrupted":
        traj.info["message"] = (f"the run was interrupted (Ctrl-C) at t = {reached:.6g} s of t_end = "
                                f"{t_end:g} s; what was computed is kept")
        raise RunInterrupted(traj.info["message"], trajectory=traj)
    if result.failure:
        traj.info["message"] = (f"the run stopped early: {result.failure}; the last good state is at "
                                f"t = {reached:.6g} s")
        raise SimulationError(traj.info["message"], trajectory=traj)
    if result.stopped_by:
        traj.info["message"] = f"the terminal event '{result.stopped_by}' at t = {reached:.6g} s"
    return traj


def _dof(model: Model, result: HybridRun, i0: int, rows) -> int:
    """3N − rank of the held rows' Jacobian at the segment's first sample."""
    if not rows:
        return model.n_coordinates
    k = min(i0, len(result.t) - 1)
    if k < 0:
        return model.n_coordinates - len(rows)
    J = model.jacobian(result.x[k], result.t[k])[1]
    algebra = algebra_for(model.n_constraints)
    if algebra.name == "dense":
        return model.n_coordinates - int(np.linalg.matrix_rank(np.asarray(J, float)[list(rows)]))
    # (a large model: its independent rows by a sparse factorization, no dense J or SVD)
    independent = algebra.independent_rows(algebra.matrix(J)[list(rows)], model.inverse_masses)
    return model.n_coordinates - len(independent)


def trajectory_quantities(model: Model, result: HybridRun, wanted, stats) -> Trajectory:
    """The Trajectory of a hybrid run: the derived quantities on each segment's held rows
    (multipliers 0 on the rows not held; the residual counts a one-sided row not held only
    where it is violated)."""
    per_segment = {"multipliers", "constraint_forces", "constraint_residual", "velocity_residual"}
    traj = trajectory_from(model, result.t, result.x, result.v, set(wanted) - per_segment, stats)
    traj.events = list(result.records)
    n, C = len(result.t), model.n_constraints
    if not n or not (set(wanted) & per_segment):
        return traj
    info = one_sided(model)
    lam = np.zeros((n, C))
    res_x, res_v = np.zeros(n), np.zeros(n)
    for i0, i1, rows, _, _ in result.segments:
        active = ActiveSet(model, rows, at=(result.x[i0], result.t[i0]) if i1 > i0 else None)
        idx = np.array(rows, dtype=int)
        held_rows = set(rows)
        free = np.array([k for k in info.rows if k not in held_rows], dtype=int)
        for i in range(i0, i1):
            x, v, t = result.x[i], result.v[i], result.t[i]
            if "multipliers" in wanted or "constraint_forces" in wanted:
                lam[i] = active.multipliers(x, v, t)
            if "constraint_residual" in wanted or "velocity_residual" in wanted:
                s = scales(model, x, t)
                g = gaps(model, x, t) / s
                res_x[i] = max(np.max(np.abs(g[idx]), initial=0.0), np.max(-g[free], initial=0.0))
                c = constraint_velocities(model, x, v, t) / s
                res_v[i] = np.max(np.abs(c[idx]), initial=0.0)
    if "multipliers" in wanted:
        traj.multipliers = lam
    if "constraint_forces" in wanted:
        traj.constraint_forces = constraint_forces_along(model, result.x, result.t, lam)
    if "constraint_residual" in wanted:
        traj.constraint_residual = res_x
    if "velocity_residual" in wanted:
        traj.velocity_residual = res_v
    return traj
