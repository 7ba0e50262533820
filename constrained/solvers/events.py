"""Locating events: a sign change of g(t, x, v) between two accepted samples, found on the
dense output. Methods whose dense output is their own solution between steps (SciPy's
interpolants) take its root (brentq, to round-off); the others refine it on their own
solution: one step of the method from the accepted sample before to each candidate instant
(a smooth function of the instant), secant steps from the dense root on those values,
kept inside the bracket (bisection where a secant step would leave it)."""

from __future__ import annotations

import numpy as np

from .. import interrupt
from .base import Event, EventHit, Solver, Status

#: Refinement of an event instant: at most this many landings on candidate instants.
EVENT_REFINEMENTS = 12
#: Steps one landing on a candidate instant may take (it normally takes one or two): the
#: work budget that keeps event location finite whatever the method does near the instant.
LANDING_STEPS = 200
#: brentq's smallest relative tolerance (4 machine epsilons).
BRENTQ_RTOL = 4 * np.finfo(float).eps


def dense_root(event: Event, before, after, dense, ga: float | None = None, gb: float | None = None) -> float:
    """The crossing of ``event`` between the samples ``before`` and ``after`` on the dense
    output (brentq, to round-off), or a secant guess where the interpolant shows no sign change:
    the first estimate, which ``locate`` refines on the method's own solution."""
    g = event.function
    ta, tb = before[0], after[0]
    ga = g(*before) if ga is None else ga
    gb = g(*after) if gb is None else gb

    def on_dense(t):
        return g(t, *dense(t))

    from scipy.optimize import brentq  # (0.1 s of imports: only when an event is met)

    try:
        return brentq(on_dense, ta, tb, xtol=1e-15 * max(1.0, abs(tb)), rtol=BRENTQ_RTOL)
    except ValueError:  # the interpolant does not change sign: a secant guess
        return ta - ga * (tb - ta) / (gb - ga) if gb != ga else 0.5 * (ta + tb)


def locate(stepper: Solver, event: Event, before, after, dense, root: float | None = None) -> EventHit:
    """The crossing of ``event`` between the samples ``before`` and ``after`` ((t, x, v)),
    to round-off on the method's own solution when it lands on given times; ``root``: its
    ``dense_root`` when already found."""
    g = event.function
    ta, xa, va = before
    tb, xb, vb = after
    ga, gb = g(ta, xa, va), g(tb, xb, vb)
    t1 = dense_root(event, before, after, dense, ga, gb) if root is None else root
    if not stepper.refines_events:
        x1, v1 = stepper.output(t1, *dense(t1))
        return EventHit(event, float(t1), x1, v1)
    origin = before
    after_positive = gb > 0  # the side the crossing goes to (g before may be ~0: a gap just opened)
    best = None
    previous = None
    for _ in range(EVENT_REFINEMENTS):
        try:
            # always one step from the accepted sample before: g is then a smooth function
            # of t1, whose root the secant steps find to round-off from the dense root
            x1, v1 = _land(stepper, *origin, t1)
        except RuntimeError:  # the method cannot land there: the dense output's root stands
            x1, v1 = stepper.output(t1, *dense(t1))
            return EventHit(event, float(t1), x1, v1)
        g1 = g(t1, x1, v1)
        if best is None or abs(g1) < abs(best[3]):
            best = (t1, x1, v1, g1)
        if g1 == 0:
            break
        if (g1 > 0) == after_positive:  # keep the crossing bracketed
            tb = t1
        else:
            ta = t1
        if previous is None or previous[1] == g1:
            # a second point close by for the first secant
            t_new = t1 - max(1e-9 * (tb - ta), 8 * np.finfo(float).eps * max(1.0, abs(t1)))
            t_new = t_new if ta < t_new < tb else t1 + (t1 - t_new)
        else:
            t_new = t1 - g1 * (t1 - previous[0]) / (g1 - previous[1])
        if not ta < t_new < tb:
            t_new = 0.5 * (ta + tb)
        if abs(t_new - t1) <= 4 * np.finfo(float).eps * max(1.0, abs(t1)):
            break
        previous, t1 = (t1, g1), t_new
    return EventHit(event, float(best[0]), np.asarray(best[1]), np.asarray(best[2]))


def dip(event: Event, before, after, dense, rate_before: float, rate_after: float):
    """The state (t, x, v) at the minimum of a falling ``event``'s g between two samples where
    g is positive at both, when g turns around between them (``event.rate`` < 0 before, > 0
    after) and that minimum is below zero: the crossing then lies between ``before`` and it;
    else None. The minimum is the rate's root on the dense output (brentq)."""
    if event.rate is None or not (rate_before < 0 < rate_after):
        return None
    from scipy.optimize import brentq

    ta, tb = before[0], after[0]
    try:
        t_min = brentq(lambda t: event.rate(t, *dense(t)), ta, tb, xtol=1e-15 * max(1.0, abs(tb)),
                       rtol=BRENTQ_RTOL)
    except ValueError:  # the interpolant's rate does not change sign: no turn to look at
        return None
    x, v = dense(t_min)
    if not event.function(t_min, x, v) < 0:
        return None
    return (float(t_min), np.asarray(x), np.asarray(v))


def _land(stepper: Solver, ta: float, xa, va, t1: float):
    """The method's state at t1, stepping from the accepted sample (ta, xa, va): a
    RuntimeError when it cannot (a failed step, more than LANDING_STEPS calls without
    reaching t1, or Ctrl-C), after which the dense output's state stands."""
    if not t1 > ta:
        return np.asarray(xa), np.asarray(va)
    state = stepper.init(xa, va, ta, t1, first_step=t1 - ta)
    for _ in range(LANDING_STEPS):
        if interrupt.requested():
            raise RuntimeError("interrupted")
        adv = stepper.step(state, t1)
        state = adv.state
        if adv.status is not Status.COMPLETED:
            raise RuntimeError(adv.message)
        if len(adv.t) and adv.t[-1] >= t1:
            return adv.x[-1], adv.v[-1]
    raise RuntimeError(f"no landing at t = {t1:.17g} s within {LANDING_STEPS} steps")
