"""Locating events: a sign change of g(t, x, v) between two accepted samples, found on the
dense output and refined to round-off on the method's own solution (restarting the stepper
at the sample before and landing on candidate instants; Illinois' regula falsi on those
exact values)."""

from __future__ import annotations

import numpy as np
from scipy.optimize import brentq

from .base import Event, EventHit, Solver, Status

#: Refinement of an event instant: at most this many landings on candidate instants.
EVENT_REFINEMENTS = 12


def locate(stepper: Solver, event: Event, before, after, dense) -> EventHit:
    """The crossing of ``event`` between the samples ``before`` and ``after`` ((t, x, v)),
    to round-off on the method's own solution when it lands on given times."""
    g = event.function
    ta, xa, va = before
    tb, xb, vb = after
    ga, gb = g(ta, xa, va), g(tb, xb, vb)

    def on_dense(t):
        return g(t, *dense(t))

    try:
        t1 = brentq(on_dense, ta, tb, xtol=1e-15 * max(1.0, abs(tb)), rtol=4e-16)
    except ValueError:  # the interpolant does not change sign: start in the middle
        t1 = ta - ga * (tb - ta) / (gb - ga)
    if not stepper.refines_events:
        x1, v1 = stepper.output(t1, *dense(t1))
        return EventHit(event, float(t1), x1, v1)
    best = (tb, xb, vb) if abs(gb) <= abs(ga) else (ta, xa, va)
    side = 0
    for _ in range(EVENT_REFINEMENTS):
        t1 = min(max(t1, ta), tb)
        if not ta < t1 < tb:
            break
        try:
            x1, v1 = _land(stepper, ta, xa, va, t1)
        except RuntimeError:  # the method cannot land there: the dense output's root stands
            x1, v1 = stepper.output(t1, *dense(t1))
            return EventHit(event, float(t1), x1, v1)
        g1 = g(t1, x1, v1)
        best = (t1, x1, v1)
        if g1 == 0 or tb - ta <= 4e-16 * max(1.0, abs(t1)):
            break
        if (g1 > 0) == (ga > 0):
            ta, xa, va, ga = t1, x1, v1, g1
            gb = gb / 2 if side == -1 else gb  # Illinois: halve the stale end
            side = -1
        else:
            tb, xb, vb, gb = t1, x1, v1, g1
            ga = ga / 2 if side == 1 else ga
            side = 1
        t_new = ta - ga * (tb - ta) / (gb - ga)
        if abs(t_new - t1) <= 2e-16 * max(1.0, abs(t1)):
            break
        t1 = t_new
    return EventHit(event, float(best[0]), np.asarray(best[1]), np.asarray(best[2]))


def _land(stepper: Solver, ta: float, xa, va, t1: float):
    """The method's state at t1, stepping from the accepted sample (ta, xa, va)."""
    state = stepper.init(xa, va, ta, t1)
    while True:
        adv = stepper.step(state, t1)
        state = adv.state
        if adv.status is not Status.COMPLETED:
            raise RuntimeError(adv.message)
        if len(adv.t) and adv.t[-1] >= t1:
            return adv.x[-1], adv.v[-1]
