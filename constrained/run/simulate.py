"""simulate: System -> consistent start -> solver -> Trajectory."""

from __future__ import annotations

import difflib
import functools
import inspect
import math
import time
import warnings
from collections.abc import Iterable

import numpy as np

from .. import interrupt
from ..errors import InitialStateWarning, InputError, RunInterrupted, SimulationError, UnresolvedStepWarning
from ..manifold import diagnostics
from ..manifold.constraint_report import SingularConfigurationWarning
from ..manifold.manifold import forces_and_energy
from ..model import velocity
from ..model.effects import damping_formulas
from ..model.structure import Model, assemble
from ..model.system import length_scale, require_system
from ..solvers import DEFAULT_METHOD, METHODS
from ..solvers.base import Event, Status
from ..solvers.stiffness import StiffnessWatch
from ..threads import one_blas_thread
from . import hybrid
from .action_integral import action
from .event_records import EventRecord
from .quantities import OUTPUT_NAMES, trajectory_from
from .start import consistent_start, consistent_state  # noqa: F401  (consistent_state: public name)
from .trajectory import QUANTITIES, Trajectory
from .unilateral import has_one_sided
from .user_events import user_events


def simulate(
    system,
    t_end: float,
    *,
    method: str = DEFAULT_METHOD,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    dt: float | None = None,
    t_eval: Iterable[float] | None = None,
    t_start: float = 0.0,
    outputs: Iterable[str] | None = None,
    max_initial_correction: float = 1e-3,
    model: Model | None = None,
    parameters: dict[str, float] | None = None,
    events: Iterable[Event] = (),
    **options,
) -> Trajectory:
    """Simulate ``system`` from ``t_start`` to ``t_end`` and return a Trajectory.

    ``method`` picks the solver (see ``constrained.solvers.METHODS``); ``outputs`` limits the
    derived quantities computed (default: all). The initial state is projected onto the
    constraints first; the correction is in ``trajectory.info["initial_correction"]``.
    ``parameters`` (name -> value) replaces some of the system's parameters for this run:
    the ``model`` (passed in, or assembled once) is reused for them without rebuilding, and
    the initial state is the system's for those values (``Model.with_parameters``).
    ``events`` are ``Event(name, g(t, x, v), direction, terminal)`` (or plain callables, as for
    solve_ivp; the scene's [[events]] are added): their zero crossings are located to round-off
    and recorded in ``trajectory.events``; a terminal one ends the run there (``info["stop"]``
    is then "terminal event"). A system with one-sided constraints runs in segments between
    releases, contacts and impacts (constrained.hybrid).
    """
    require_system(system, "simulate")
    if method not in METHODS:
        close = difflib.get_close_matches(str(method), sorted(METHODS), n=1)
        raise InputError(f"unknown method {method!r} (choose from {', '.join(sorted(METHODS))})"
                         + (f"; did you mean '{close[0]}'?" if close else ""))
    if options:
        _check_keywords(method, options)
    for key, value in (("t_end", t_end), ("t_start", t_start)):
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise InputError(f"{key} must be a finite number of seconds, got {value!r}")
    if t_end <= t_start:
        raise InputError(f"t_end ({t_end:g} s) must be later than t_start ({t_start:g} s)")
    if not (isinstance(max_initial_correction, int | float) and max_initial_correction >= 0):
        raise InputError(f"max_initial_correction must be >= 0, got {max_initial_correction!r}")
    try:
        wanted = OUTPUT_NAMES if outputs is None else set(outputs)
        if isinstance(outputs, str) or not all(isinstance(name, str) for name in wanted):
            raise TypeError
    except TypeError:
        raise InputError(f"outputs must be a list of names (of {', '.join(sorted(OUTPUT_NAMES))}), "
                         f"got {outputs!r:.80}") from None
    unknown = wanted - OUTPUT_NAMES
    if unknown:
        raise InputError(
            f"unknown output(s) {', '.join(sorted(unknown))} (known: {', '.join(sorted(OUTPUT_NAMES))})"
        )
    if t_eval is not None:
        try:
            t_eval = np.asarray(list(t_eval), dtype=float).ravel()
        except (TypeError, ValueError):
            raise InputError(f"t_eval must be a list of times in seconds, got {t_eval!r:.80}") from None
        if t_eval.size == 0 or not np.all(np.isfinite(t_eval)):
            raise InputError("t_eval must be a non-empty list of finite times")
        if np.any(np.diff(t_eval) <= 0):
            raise InputError("t_eval must be strictly increasing")
        if t_eval[0] < t_start or t_eval[-1] > t_end:
            raise InputError(f"t_eval must lie within [t_start, t_end] = [{t_start:g}, {t_end:g}]")
    if system.n_particles == 0:
        raise InputError("the system has no particles")

    started = time.perf_counter()
    model = (model or assemble(system)).with_parameters(parameters)
    system = system.with_parameters(parameters)  # its initial state for these values
    build_time = time.perf_counter() - started
    events = user_events(system, events)
    refuse_negative_damping(model, system, float(t_start), float(t_end))
    if has_one_sided(model):
        traj = hybrid.simulate_hybrid(
            model, system, float(t_start), float(t_end), method=method, rtol=rtol, atol=atol, t_eval=t_eval,
            wanted=wanted, events=events, max_initial_correction=max_initial_correction,
            build_time=build_time, options={"dt": dt, **options})
        start = traj.info["initial_correction"]  # the projection at the start (not an impact there)
        _warn_if_corrected({"position": start["projection"], "velocity": start["velocity"]},
                           system.velocities, system.size())
        return traj
    # what only contacts use means nothing without one-sided constraints
    options = {k: v for k, v in options.items() if k not in ("rest_speed", "max_events")}
    start = consistent_start(
        model, system.positions, system.velocities, t_start,
        max_correction=max_initial_correction, size=system.size(),
    )
    x0, v0, correction = start.x, start.v, start.correction
    _warn_if_corrected(correction, system.velocities, system.size())
    _refuse_nonfinite_start(model, x0, v0, float(t_start))
    started = time.perf_counter()
    solver = METHODS[method](start.manifold, rtol=rtol, atol=atol, dt=dt, **options)
    setup_time = time.perf_counter() - started
    with one_blas_thread():  # see constrained.threads
        started = time.perf_counter()
        # Ctrl-C becomes a request the solver honours after its current step or chunk
        with interrupt.watch():
            solution = solver.run(x0, v0, float(t_start), float(t_end), t_eval, events=events)
            # Ctrl-C in the run's last step (or while its step loop was compiled) stops it too
            interrupted = solution.status is Status.INTERRUPTED or interrupt.requested()
        wall = time.perf_counter() - started
        stats = {**solution.stats, "wall_time_s": wall, "build_time_s": build_time,
                 "setup_time_s": setup_time, "method": method}
        ended_by_event = solution.status is Status.EVENT
        skipped = []
        try:
            traj = trajectory_from(model, solution.t, solution.x, solution.v, wanted, stats)
        except KeyboardInterrupt:
            if not interrupted:
                raise
            # a second Ctrl-C while the stopped run's quantities are computed: keep t, x, v
            skipped, wanted = sorted(wanted & set(QUANTITIES)), set()
            traj = trajectory_from(model, solution.t, solution.x, solution.v, wanted, stats)
        if "action" in wanted and len(traj.t) >= 2:
            traj.action = action(model, traj).cumulative
    reached = float(traj.t[-1]) if len(traj.t) else float(t_start)
    traj.info.update(
        {
            "initial_correction": correction,
            "system": system.name,
            "method": method,
            "rtol": rtol,
            "atol": atol,
            "active_terms": sorted(model.active_terms),
            "status": "interrupted" if interrupted else ("stopped" if solution.failure and not ended_by_event
                                                         else "completed"),
            # solvers.base.Status: how the run ended
            "stop": Status.INTERRUPTED.value if interrupted else solution.status.value,
            "t_end": float(t_end),
            "t_end_reached": reached,
            "events": [{"t": hit.t, "name": hit.event.name, "x": hit.x, "v": hit.v}
                       for hit in solution.events],
        }
    )
    if not start.manifold.redundant:  # independent rows at the start: rank C, as constraint_report says
        traj.info["degrees_of_freedom"] = model.n_coordinates - model.n_position_rows  # configuration
        if model.n_position_rows < model.n_constraints:
            traj.info["velocity_degrees_of_freedom"] = model.n_coordinates - model.n_constraints
    vanished = velocity.vanishing_rows(model, traj.t, traj.x, (x0, float(t_start))) if not interrupted else []
    if vanished:  # a row a(x)·v + b whose a(x) passed through 0: μ has a pole there
        traj.info["velocity_rows_lost_rank"] = vanished
        warnings.warn(SingularConfigurationWarning(velocity.describe_vanishing(vanished)), stacklevel=2)
    unresolved = None if interrupted else _unresolved_energy(model, traj)
    if unresolved:
        traj.info["energy_not_conserved"] = unresolved
        warnings.warn(UnresolvedStepWarning(unresolved["message"]), stacklevel=2)
    traj.events = [EventRecord(hit.t, hit.event.name, hit.event.name, np.reshape(hit.x, (-1, 3)),
                               np.reshape(hit.v, (-1, 3))) for hit in solution.events]
    if interrupted:
        note = (f" (a second Ctrl-C: the derived quantities {', '.join(skipped)} were not computed)"
                if skipped else "")
        if skipped:
            traj.info["quantities_skipped"] = skipped
        traj.info["message"] = (f"the run was interrupted (Ctrl-C) at t = {reached:.6g} s of t_end = "
                                f"{t_end:g} s; what was computed is kept{note}")
        raise RunInterrupted(traj.info["message"], trajectory=traj)
    if ended_by_event:  # which event, when (Trajectory.message)
        traj.info["message"] = str(solution.failure)
    failure = None if ended_by_event else solution.failure
    bad = None if failure else _first_nonfinite(model, traj, wanted)
    if bad is not None:
        what, k = bad
        state = (traj.x[k].ravel(), traj.v[k].ravel(), float(traj.t[k]))
        kept = traj.head(k)
        message = f"non-finite {what} at t = {traj.t[k]:.6g} s; {diagnostics.nonfinite_cause(model, *state)}"
        kept.info.update(status="stopped", stop=Status.NON_FINITE.value, message=message,
                         t_end_reached=float(kept.t[-1]) if k else float(t_start))
        raise SimulationError(message, trajectory=kept)
    if failure:
        last_state = (traj.x[-1].ravel(), traj.v[-1].ravel(), float(traj.t[-1])) if len(traj.t) else None
        cause = ("" if "likely cause" in failure else
                 _stiff_spring_cause(model, traj, x0, float(t_start), float(t_end), stats) or
                 (f" ({diagnostics.likely_cause(model, *last_state)})" if last_state else
                  " (likely cause: a singular configuration, stiffness, or forces that blow up)"))
        last = f"t = {traj.t[-1]:.6g} s" if len(traj.t) else "the start"
        traj.info["message"] = f"the run stopped early: {failure}; the last good state is at {last}{cause}"
        if vanished:
            traj.info["message"] += f"; {velocity.describe_vanishing(vanished)}"
        raise SimulationError(traj.info["message"], trajectory=traj)
    return traj


def _warn_if_corrected(correction: dict, v0, size: float) -> None:
    """An InitialStateWarning when the start was changed beyond round-off (as ``constrained run``
    prints it): the user's velocity had components the constraints forbid, or the positions
    were off the constraints (within max_initial_correction)."""
    speed = max(1.0, float(np.max(np.abs(np.asarray(v0, float)), initial=0.0)))
    dx, dv = correction["position"], correction["velocity"]
    changed = []
    if dx > 1e-9 * size:
        worst = (f" (the worst violation was {correction['max_residual_before']:.3g} m, of "
                 f"'{correction['worst_constraint']}')" if "worst_constraint" in correction else "")
        changed.append(f"positions moved by {dx:.3g} m{worst}")
    if dv > 1e-9 * speed:
        changed.append(f"velocities changed by {dv:.3g} m/s (their components along the constrained "
                       "directions removed)")
    if changed:
        warnings.warn(InitialStateWarning("the initial state was made consistent with the constraints: "
                                          + "; ".join(changed) + " (trajectory.info['initial_correction'])"),
                      stacklevel=3)


#: Keywords every run takes besides simulate's own and its method's OPTIONS (the solvers' common
#: ones, and a run with one-sided constraints' own).
COMMON_KEYWORDS = ("compiled", "progress", "rest_speed", "max_events")


@functools.cache
def _own_keywords() -> tuple[str, ...]:
    return tuple(name for name in inspect.signature(simulate).parameters if name not in ("system", "options"))


#: A fixed-step run of a conservative system warns when its energy changed by more than this
#: fraction of the motion's energy scale (``_unresolved_energy``). RATTLE's energy error at a
#: step that resolves the motion is O(h² ω²): well under it.
UNRESOLVED_ENERGY = 0.05


def _unresolved_energy(model: Model, traj) -> dict | None:
    """For a ``rattle`` run whose steps watched the energy h = T + V (a system that conserves
    it: ``solvers.rattle.conserves_energy``), at every step and not only at the output samples
    (``stats``: the largest h − h₀ and the largest one-step change, with their times): where
    max |h − h₀| exceeds UNRESOLVED_ENERGY × the scale max(|h₀|, T₀, |V₀|, the median T over the
    samples, M (ε size / dt)² the round-off's), the step that changed h most (the one that did not
    resolve the motion), the change and the words; else None. A gram falling onto a kilogram
    under V = −1/r "completed" at dt = 1 ms with its energy gone from −1 J to +92 J: the steps
    jumped the close encounter."""
    stats = traj.stats
    if "energy_change" not in stats or not len(traj.t):
        return None
    h0, change = float(stats["energy_start"]), float(stats["energy_change"])
    v = np.asarray(traj.v, float).reshape(len(traj.t), -1)
    T = 0.5 * (v * v) @ model.masses
    if not (np.isfinite(h0) and np.isfinite(change) and np.all(np.isfinite(T))):
        return None
    dt = stats.get("dt")
    # round-off's own energy: the system moving its size at ε a step (a chain at rest with no
    # forces has h = 0, and the projections' round-off of 1e-48 J was "17 × its scale")
    x = np.asarray(traj.x, float)
    size = float(length_scale(x[0])) if x.size else 1.0
    noise = float(np.sum(model.masses) / 3) * (np.finfo(float).eps * size / dt) ** 2 if dt else 0.0
    scale = max(abs(h0), T[0], abs(h0 - T[0]), float(np.median(T)), noise)
    if not scale > 0 or abs(change) <= UNRESOLVED_ENERGY * scale:
        return None
    t_step, step_change = float(stats["energy_step_change_t"]), float(stats["energy_step_change"])
    step = f"the fixed step dt = {dt:.3g} s" if dt else "the fixed step"
    t_change = float(stats["energy_change_t"])
    return {"t": t_step, "step_change": step_change, "change": change, "t_change": t_change, "scale": scale,
            "message": (
                f"the energy, which this system conserves, changed by {change:.3g} J (from {h0:.6g} J; "
                f"the most at t = {t_change:.6g} s), {abs(change) / scale:.3g} of its scale {scale:.3g} J, "
                f"and by {step_change:.3g} J in the one step to t = {t_step:.6g} s: {step} did not resolve "
                "the motion there (a close encounter or a collision); reduce dt, or use an adaptive method "
                "(dopri), which follows such an encounter or names the collapse")}


def _check_keywords(method: str, options: dict) -> None:
    """Refuse a keyword no run takes, with the one meant (did you mean 'rtol'?) or the methods
    that take it; keywords some run takes are checked by the method itself."""
    takes = {*_own_keywords(), *COMMON_KEYWORDS, *METHODS[method].OPTIONS}
    for key in sorted(set(options) - takes):
        elsewhere = sorted(m for m, cls in METHODS.items() if key in cls.OPTIONS)
        if elsewhere:
            raise InputError(f"method '{method}' does not take the option {key!r}; "
                             f"{', '.join(elsewhere)} take{'s' if len(elsewhere) == 1 else ''} it")
        close = difflib.get_close_matches(key, sorted(takes), n=1)
        raise InputError(f"simulate() got an unknown keyword {key!r}"
                         + (f"; did you mean '{close[0]}'?" if close else
                            f" (it takes {', '.join(sorted(takes))})"))


def _stiff_spring_cause(model: Model, traj: Trajectory, x0, t0: float, t_end: float, stats: dict) -> str:
    """'; likely cause: stiffness: ...' when a barely stretched spring far faster than the run,
    or a damper whose relaxation time m/c held the steps down, explains a stop the solver could
    not name (diagnostics.StiffnessWatch), else ''."""
    try:
        watch = StiffnessWatch(model, x0, t0, t_end, method=stats.get("method", ""))
        t = float(traj.t[-1]) if len(traj.t) else t0
        element = watch.fastest()  # as at the start: an unstable step stretches it later
        steps = int(stats.get("steps", 0) or 0)
        if element is None or not element.rigid_like:
            damper = watch.held_damper(t, steps)
            return f"; {watch.describe_damper(damper, t, steps)}" if damper is not None else ""
        dt = stats.get("dt")
        limit = (f"; the fixed step dt = {dt:.3g} s is beyond its stability limit 2/ω = "
                 f"{2 / element.omega:.3g} s" if dt and dt * element.omega > 2 else "")
        return f"; {watch.describe(element, t, int(stats.get('steps', 0) or 0))}{limit}"
    except Exception:  # a diagnosis must never hide the stop itself
        return ""


def refuse_negative_damping(model: Model, system, t0: float, t_end: float) -> None:
    """Refuse a Rayleigh coefficient (a formula of t and the parameters) that is negative or not
    finite at any instant of [t0, t_end], however briefly (``Damping.refusal``: bounded, not
    sampled): R = ½ c |v|² with c < 0 is an energy source. (simulate_many refuses such a member
    with the same sentence: run/variants/refusals.py.)"""
    dampers = damping_formulas(system.effects)
    values = model.system.parameter_values if dampers else {}
    for effect in dampers:
        error = effect.refusal(values, t0, t_end)
        if error is not None:
            raise error


def _refuse_nonfinite_start(model: Model, x0, v0, t0: float) -> None:
    """Stop before stepping when the forces (or the energy) are not finite at the start."""
    F, E = forces_and_energy(model)(x0, v0, t0)
    E = float(E[0])
    if np.all(np.isfinite(F)) and np.isfinite(E):
        return
    what = "forces" if not np.all(np.isfinite(F)) else f"energy ({E:g} J)"
    start = trajectory_from(model, [t0], np.asarray(x0)[None], np.asarray(v0)[None], set())
    start.info.update(status="stopped", t_end_reached=t0)
    raise SimulationError(f"non-finite {what} at the initial state (t = {t0:g} s); "
                          f"{diagnostics.nonfinite_cause(model, x0, v0, t0)}", trajectory=start)


def _first_nonfinite(model: Model, traj: Trajectory, wanted):
    """(name, index) of the first sample where a state or a computed quantity is not finite
    (the energy is checked at the last sample even when not asked for), or None."""
    n = len(traj.t)
    if n == 0:
        return None
    first = None
    for name in ("x", "v", *QUANTITIES):
        values = getattr(traj, name)
        if values is None or name == "action":
            continue
        ok = np.all(np.isfinite(values.reshape(n, -1)), axis=1)
        if not ok.all():
            k = int(np.argmin(ok))
            if first is None or k < first[1]:
                first = ({"x": "positions", "v": "velocities"}.get(name, name.replace("_", " ")), k)
    if first is None and "energy" not in wanted:
        E = forces_and_energy(model)(traj.x[-1].ravel(), traj.v[-1].ravel(), traj.t[-1])[1]
        if not np.all(np.isfinite(E)):  # then find the first sample where it is not
            E = model.evaluate(model.energy, traj.x.reshape(n, -1), traj.v.reshape(n, -1), traj.t)[0]
            first = ("energy", int(np.argmin(np.isfinite(np.asarray(E).ravel()))))
    return first
