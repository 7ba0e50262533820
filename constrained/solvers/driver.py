"""THE time loop: every method is a stepper (solvers/base.py) run by ``integrate``.

In the style of diffrax's ``diffeqsolve``: the stepper advances and reports (samples, an
error already controlled, a status) and makes no decisions; this loop decides

- where outputs are taken: at every accepted step (no ``t_eval`` and no default grid of the
  method), at output times the stepper lands on (``Solver.lands``), or from the dense output
  between steps (the stepper's own interpolant, else the Hermite interpolant of the samples,
  solvers/dense.py), each passed through ``Solver.output`` (projecting methods project it);
- events (solvers/events.py): g(t, x, v) at every accepted sample, crossings located to
  round-off; a terminal one ends the run with its state as the last sample;
- when the run stops: Ctrl-C (between calls, each kept short by the stepper), non-finite
  states, the singular-configuration watch at every size and the limit-position check of a
  failed step (solvers/watches.py), the stiffness watch, the step limit;
- progress reporting and the run's statistics (returned in the Solution).
"""

from __future__ import annotations

import bisect

import numpy as np

from .. import interrupt
from ..codegen.fast_call import release_large
from ..manifold import diagnostics
from . import stiffness
from .base import Advance, Event, EventHit, Failure, Solution, Solver, Status
from .events import dense_root, dip, locate
from .stiffness import StiffnessWatch, stiff_stop
from .watches import CollapseWatch, SingularWatch, collapse_stop, past_a_limit

#: A run given no output times keeps its accepted steps, but at most one per this fraction of
#: its span (a run whose steps collapse would otherwise store millions of samples).
STEP_SAMPLES = 20_000
#: ... and, on a large model, at most about this many position values (``step_samples``): a
#: 10,000-particle model keeps about 100 of its steps, evenly in time. Every accepted step of
#: a 1 cm rope of 10,000 links was 600 MB of output and 3 s of post-processing and writing.
STEP_VALUES = 3_000_000
#: The step limit when none is given (accepted plus rejected steps; a fixed-step method gets
#: at least twice the steps its span needs).
DEFAULT_MAX_STEPS = 20_000_000

#: Failures of a step that a limit position passed during it may explain.
STEP_FAILURES = (Status.PROJECTION_FAILED, Status.STEP_SIZE_COLLAPSED, Status.SOLVER_FAILED)


class Stepper(Solver):
    """A Solver run by the driver: ``run`` is ``integrate(self, ...)``."""

    def run(self, x0, v0, t0: float, t_end: float, t_eval=None, events=()) -> Solution:
        return integrate(self, x0, v0, t0, t_end, t_eval=t_eval, events=events)


class _Run:
    """One run's bookkeeping: outputs kept, the last accepted sample, events, watches."""

    def __init__(self, stepper: Solver, x0, v0, t0: float, t_end: float, t_eval, events):
        self.stepper, self.t_end = stepper, t_end
        self.from_caller = t_eval is not None
        grid = np.asarray(t_eval, float) if t_eval is not None else stepper.default_grid(t0, t_end)
        self.every_step = grid is None
        self.min_gap = (t_end - t0) / step_samples(stepper.model.n_coordinates)  # (every_step)
        self.ts, self.xs, self.vs = [], [], []
        if self.every_step or grid[0] <= t0:
            self.keep(t0, x0, v0)
        self.pending = [] if self.every_step else [float(tk) for tk in grid if tk > t0]
        self.last, self.last_a = (t0, x0, v0), None
        self.events = tuple(events)
        # an event exactly zero at the start has no side yet (a pendulum released from rest
        # with the event vx = 0): the run begins on it, which is not a crossing; its side is
        # that of its first nonzero value
        self.g_last = [_side(e.function(t0, x0, v0)) for e in self.events]
        self.rate_last = [_rate(e, t0, x0, v0) for e in self.events]
        self.hits: list[EventHit] = []
        self.singular = SingularWatch(stepper.manifold, stepper.rows, stepper.singular_tol)
        self.collapse = CollapseWatch(t_end) if stepper.adaptive and stepper.dt is None else None
        self.stiffness = StiffnessWatch(stepper.model, x0, t0, t_end, method=stepper.name)
        self.h_rho, self.rho_max = [], 0.0
        self.sampled = stiffness.STIFFNESS_MIN_STEPS // 2

    def keep(self, t: float, x, v) -> None:
        self.ts.append(np.array([t]))
        self.xs.append(np.asarray(x)[None])
        self.vs.append(np.asarray(v)[None])

    def kept_until(self) -> float:
        return float(self.ts[-1][-1]) if self.ts else -np.inf

    def keep_reached(self) -> None:
        """On a stop between two outputs of the method's own grid (or between kept steps),
        keep the state reached."""
        if not self.from_caller and self.last[0] > self.kept_until():
            self.keep(*self.last)

    def thinned(self, t: np.ndarray) -> np.ndarray:
        """Which of the accepted steps at times ``t`` to keep: each one at least ``min_gap``
        after the last kept (the run's end always)."""
        keep = np.zeros(len(t), bool)
        last = self.kept_until()
        for i, tk in enumerate(t):
            if tk - last >= self.min_gap or tk >= self.t_end:
                keep[i], last = True, tk
        return keep

    def keep_last_step(self) -> None:
        """A run that ends between kept steps keeps the state it reached."""
        if self.every_step and self.last[0] > self.kept_until():
            self.keep(*self.last)

    def t_stop(self) -> float:
        return self.pending[0] if self.stepper.lands and self.pending else self.t_end

    def checked(self, adv: Advance, t_stop: float) -> tuple[int, Failure | None]:
        """How many of the advance's samples are good, and the failure it reports, if any."""
        k = len(adv.t)
        if k and not (np.isfinite(adv.x).all() and np.isfinite(adv.v).all()):
            k = int(np.argmin(np.isfinite(adv.x).all(axis=-1) & np.isfinite(adv.v).all(axis=-1)))
            t = float(adv.t[k - 1]) if k else self.last[0]
            return k, Failure(Status.NON_FINITE, f"non-finite state after t = {t:.6g} s; "
                              + diagnostics.nonfinite_cause(self.stepper.model, *self.last[1:], self.last[0]))
        if adv.status is Status.COMPLETED:
            return k, None
        failure = Failure(adv.status, adv.message)
        if adv.status in STEP_FAILURES:
            reached = (float(adv.t[-1]), adv.x[-1], adv.v[-1]) if k else self.last
            limit = past_a_limit(self.stepper, reached, reached[0] + adv.h if adv.h else t_stop)
            if limit:
                failure = Failure(Status.SINGULAR_CONFIGURATION, f"{limit} ({adv.message})")
        return k, failure

    def take(self, adv: Advance, k: int) -> EventHit | None:
        """Record the first k samples of an advance (outputs, events); a terminal hit stops it."""
        stepper = self.stepper
        if k and not self.events and (self.every_step or stepper.lands):  # no dense output needed
            t = adv.t[:k]
            if self.every_step:
                keep = self.thinned(t)
                if keep.any():
                    self.ts.append(t[keep])
                    self.xs.append(adv.x[:k][keep])
                    self.vs.append(adv.v[:k][keep])
            due = bisect.bisect_right(self.pending, t[-1])  # the output times landed on
            if due:
                i = np.searchsorted(t, self.pending[:due])
                del self.pending[:due]
                self.ts.append(t[i])
                self.xs.append(adv.x[i])
                self.vs.append(adv.v[i])
            self.last = (float(t[-1]), adv.x[k - 1], adv.v[k - 1])
            self.last_a = adv.a[k - 1] if adv.a is not None else None
            return None
        for i in range(k):
            sample = (float(adv.t[i]), adv.x[i], adv.v[i])
            a = adv.a[i] if adv.a is not None else None
            dense = None
            if self.events or (not stepper.lands and self.pending):
                dense = (adv.interpolant if adv.interpolant is not None and k == 1 else
                         stepper.between(*self.last, self.last_a, *sample, a))
            hit = self.crossings(sample, dense) if self.events else None
            if not stepper.lands:
                while self.pending and self.pending[0] <= (hit.t if hit else sample[0]):
                    tk = self.pending.pop(0)
                    self.keep(tk, *stepper.output(tk, *dense(tk)))
            if hit is not None:
                self.keep(hit.t, hit.x, hit.v)
                self.last = (hit.t, hit.x, hit.v)
                return hit
            if self.every_step:
                if self.thinned(np.array([sample[0]]))[0]:
                    self.keep(*sample)
            elif stepper.lands and self.pending and sample[0] >= self.pending[0]:
                self.pending.pop(0)
                self.keep(*sample)
            self.last, self.last_a = sample, a
        return None

    def crossings(self, sample, dense) -> EventHit | None:
        """Events crossed since the last sample, located and listed; the first terminal one."""
        g_now = [e.function(*sample) for e in self.events]
        crossed = [j for j, e in enumerate(self.events)
                   if self.g_last[j] is not None and e.crossed(self.g_last[j], g_now[j])
                   and not (e.ignore_round_off and self.round_off_flip(e, self.g_last[j], sample, g_now[j]))]
        ends = {j: sample for j in crossed}
        rate_now = [_rate(e, *sample) for e in self.events]
        for j, e in enumerate(self.events):  # a dip through zero and back within the step
            if (j not in ends and e.rate is not None and dense is not None and self.g_last[j] is not None
                    and self.g_last[j] > 0 and g_now[j] > 0):
                lowest = dip(e, self.last, sample, dense, self.rate_last[j], rate_now[j])
                if lowest is not None:
                    ends[j] = lowest
        g_before = self.g_last
        self.g_last = [g if g != 0 or self.g_last[j] is not None else None for j, g in enumerate(g_now)]
        self.rate_last = rate_now
        found = self.located(ends, g_before, dense)
        stop = next((hit for hit in found if hit.event.terminal), None)
        # every event at the stop's instant is met too (a user's event y = 0 located at a floor's
        # contact, the same root to a few ulps), whichever the sort put first
        self.hits += [hit for hit in found if stop is None or hit.t <= same_instant(stop.t)]
        return stop

    def located(self, ends: dict, g_before: list, dense) -> list[EventHit]:
        """The crossings ``ends`` ({event index: the sample, or a dip's lowest state, after
        it}) located, earliest first. They are refined in the order of their dense-output roots;
        once a terminal one is found at t*, another is refined only if it has crossed by then on
        the method's own state at t* (or its root is t* to round-off): the run stops at t*, and
        the next segment meets the later ones again. (Refining every crossing of a step cost a
        thousand-bead rope on a floor most of its run.)"""
        if len(ends) <= 1:
            return [locate(self.stepper, self.events[j], self.last, end, dense) for j, end in ends.items()]
        roots = {j: dense_root(self.events[j], self.last, end, dense) for j, end in ends.items()}
        found, stop = [], None
        for j in sorted(ends, key=roots.get):
            e = self.events[j]
            if stop is not None and roots[j] > same_instant(stop.t):
                at_stop = e.function(stop.t, stop.x, stop.v)
                if not e.crossed(g_before[j], at_stop):
                    continue
            hit = locate(self.stepper, e, self.last, ends[j], dense, roots[j])
            found.append(hit)
            if e.terminal and (stop is None or hit.t < stop.t):
                stop = hit
        return sorted(found, key=lambda h: h.t)

    def round_off_flip(self, event: Event, g_before: float, sample, g_after: float) -> bool:
        """Whether a sign change of ``event`` lies within the run's resolution: both values no
        larger than the change of g when the state moves by atol (see Event.ignore_round_off)."""
        return all(abs(g) <= event_resolution(event.function, self.stepper.atol, *state)
                   for g, state in ((g_before, self.last), (g_after, sample)))

    def sample_stiffness(self, steps: int, h: float | None, taken: np.ndarray) -> None:
        """h·ρ(∂f/∂y) every STIFFNESS_EVERY accepted steps of an explicit method, with h the
        step it proposes, but no longer than its longest step of the call: ``taken`` (the
        accepted times, from the one before). A step cut short to land on output times is
        held down by them, not by stability (a pendulum at rest on its inverted equilibrium,
        with outputs every 0.01 s, proposed steps of 1.2 s: h·ρ ≈ 3.8, a false "stiff")."""
        if not (self.stepper.explicit and h and steps - self.sampled >= stiffness.STIFFNESS_EVERY):
            return
        if len(taken) > 1:
            h = min(h, float(np.max(np.diff(taken))))
        self.sampled = steps
        y = np.concatenate([self.last[1], self.last[2]])
        rho = stiffness.spectral_radius(self.stepper.derivative, self.last[0], y)
        self.rho_max = max(self.rho_max, rho)
        self.h_rho.append(h * rho)

    def stiffness_verdict(self, stats: dict, failure) -> None:
        """The end-of-run StiffnessWarning of an explicit method (stiffness.stiffness_verdict)."""
        if not self.stepper.explicit or getattr(failure, "status", None) is Status.STIFF:
            return
        what, advice = self.stepper.stiffness_advice()
        e = self.stiffness.fastest()
        if e is not None:
            advice += (f"; the fastest spring, '{e.label}' (effect {e.index}), has period {e.period:.3g} s"
                       + (f": {e.constraint_advice()}" if e.rigid_like else ""))
        d = self.stiffness.dampers[0] if self.stiffness.dampers else None
        if d is not None:
            advice += (f"; the damping '{d.label}' (effect {d.index}) relaxes '{d.particle}' in m/c = "
                       f"{d.period:.3g} s")
        stiffness.stiffness_verdict(stats, self.h_rho, self.rho_max, what=what, advice=advice, stacklevel=6)


#: Two located events this many ulps of t apart are at the same instant (``same_instant``).
SAME_INSTANT_ULPS = 64


def same_instant(t: float) -> float:
    """The latest instant that is still t to round-off: t + SAME_INSTANT_ULPS ulps (two events
    located separately on one root, a contact and a user's event of the same height, agree to
    a few ulps)."""
    return t + SAME_INSTANT_ULPS * np.spacing(abs(t))


def _rate(event: Event, t: float, x, v) -> float:
    """dg/dt of a falling event that has a ``rate`` (see Event), else NaN (never a turn)."""
    return float(event.rate(t, x, v)) if event.rate is not None and event.direction == -1 else np.nan


def step_samples(n_coordinates: int) -> int:
    """How many accepted steps a run given no output times keeps at most (evenly in time):
    STEP_SAMPLES, fewer for a large model (STEP_VALUES position values, at least 50)."""
    return min(STEP_SAMPLES, max(50, STEP_VALUES // max(1, n_coordinates)))


def _default_step_limit(stepper: Solver, t0: float, t_end: float) -> int:
    """DEFAULT_MAX_STEPS, or twice the steps a fixed step ``dt`` needs over the span."""
    dt = getattr(stepper, "dt", None)
    needed = int(np.ceil((t_end - t0) / dt)) if dt else 0
    return max(DEFAULT_MAX_STEPS, 2 * needed)


def event_resolution(g, atol: float, t: float, x, v) -> float:
    """How much g(t, x, v) moves when x, or v, moves by about atol in every component (fixed
    pseudo-random signs and sizes, so that no combination of coordinates cancels)."""
    x, v = np.asarray(x, float), np.asarray(v, float)
    u = atol * np.random.default_rng(20261127).uniform(0.5, 1.5, x.shape) * np.where(
        np.arange(x.size).reshape(x.shape) % 2, -1.0, 1.0)
    g0 = g(t, x, v)
    return max(abs(g(t, x + u, v) - g0), abs(g(t, x, v + u) - g0))


def _side(g: float) -> float | None:
    """g, or None for exactly zero (no side yet)."""
    return None if g == 0 else g


def _interrupted(t: float) -> Failure:
    return Failure(Status.INTERRUPTED, f"{Status.INTERRUPTED.value} at t = {t:.6g} s")


def integrate(stepper: Solver, x0, v0, t0: float, t_end: float, *, t_eval=None,
              events: tuple[Event, ...] = ()) -> Solution:
    """Run ``stepper`` from the consistent (x0, v0, t0) to t_end (see the module's docstring)."""
    x0, v0 = np.asarray(x0, float), np.asarray(v0, float)
    stepper.prepare(t0, t_end, t_eval)
    run = _Run(stepper, x0, v0, t0, t_end, t_eval, events)
    state = stepper.init(x0, v0, t0, t_end)
    run.last_a = stepper.start_acceleration(state)
    release_large()  # (the start's accelerations: their memory serves the steps)
    failure = None
    steps = 0
    max_steps = stepper.max_steps or _default_step_limit(stepper, t0, t_end)
    try:
        while run.last[0] < t_end:
            if stepper.stop_requested():
                failure = _interrupted(run.last[0])
                run.keep_reached()
                break
            verdict = run.stiffness.check(run.last[0], steps, run.last[1])
            if verdict:
                failure = Failure(Status.STIFF, stiff_stop(verdict, run.last[0]))
                break
            t_stop = run.t_stop()
            previous_t = run.last[0]
            adv = stepper.step(state, t_stop)
            state = adv.state
            k, failure = run.checked(adv, t_stop)
            hit = run.take(adv, k)
            steps = int(stepper.stats.get("steps", 0))
            if hit is not None:
                failure = Failure(Status.EVENT, f"the terminal event '{hit.event.name}' at t = {hit.t:.6g} s")
                if stepper.progress is not None:
                    stepper.progress(float(hit.t))
                break
            if failure is None and k and run.last[0] < t_end:  # (a finished run needs no watch)
                reason = run.singular.check(run.last[1], run.last[0])
                failure = Failure(Status.SINGULAR_CONFIGURATION, reason) if reason else None
            if failure is None and k and run.collapse is not None and run.last[0] < t_end:
                h = adv.h if adv.h else (float(adv.t[k - 1]) - previous_t) / k
                reason = run.collapse.check(steps, run.last[0], h)
                if reason:
                    failure = Failure(Status.STEP_SIZE_COLLAPSED, collapse_stop(
                        reason, stepper.diagnose(run.last[1], run.last[2], run.last[0])))
            # (a stepper that takes many steps per call, dopri's chunks, may pass the limit in the
            # call that ends the run: that run is complete, not stopped early)
            if failure is None and steps + int(stepper.stats.get("rejected", 0)) > max_steps \
                    and run.last[0] < t_end:
                failure = Failure(Status.STEP_LIMIT, f"more than max_steps = {max_steps} steps before "
                                  f"t = {t_end:.6g} s (at t = {run.last[0]:.6g} s); raise simulate.max_steps "
                                  "for a longer run")
            if failure is not None:
                run.keep_reached()
                break
            run.sample_stiffness(steps, adv.h, np.concatenate([[previous_t], adv.t[:k]]))
            if stepper.progress is not None and k:
                stepper.progress(float(run.last[0]))
    except KeyboardInterrupt:  # Ctrl-C inside a call into C, or from a progress callback
        interrupt.requested()  # (handled here: seen, so the run's watch() does not raise it again)
        failure = _interrupted(run.last[0])
        run.keep_reached()
    if failure is None or failure.status is Status.COMPLETED:
        run.keep_last_step()
    stepper.finish()
    release_large()  # (the steps': it serves what follows, the quantities along the run)
    stats = stepper.counted()
    run.stiffness_verdict(stats, failure)
    stats["events"] = len(run.hits)
    n = x0.size
    if not run.ts:
        return Solution(np.zeros(0), np.zeros((0, n)), np.zeros((0, n)), stats, failure, run.hits)
    return Solution(np.concatenate(run.ts), np.concatenate(run.xs).reshape(-1, n),
                    np.concatenate(run.vs).reshape(-1, n), stats, failure, run.hits)
