"""A gap that dips through zero and comes back within one step (session 14).

Events are found by a sign change of g between two accepted samples. A bead that dips below a
floor and is back above it by the end of the step shows none: on a 200-bead rope of 1 cm links
falling onto a perfectly inelastic floor, bead 14 ended a segment 35 µm below the floor, above
it at both ends of its 4 ms step. A falling event may now carry its rate dg/dt (the one-sided
rows' gaps do: side · (J v + f_t)); where g is positive at both samples but the rate turns from
negative to positive, the minimum is found on the dense output and, below zero, is a crossing.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_rope_rests_on_floor import FLOOR, T_END, _rope_over_a_floor

import constrained as C
from constrained.solvers.base import Event

Y0, VY0, G_UP = 0.001, -0.2, 9.81


def _ball_under_an_upward_field() -> C.System:
    """A ball 1 mm above y = 0 moving down at 0.2 m/s in a field pushing up at 9.81 m/s²: it
    dips 1.04 mm below y = 0 between t = 5.8 ms and 34.9 ms and comes back up."""
    s = C.System(name="ball dipping")
    s.add_particle("b", 1.0, [0.0, Y0, 0.0], [0.0, VY0, 0.0])
    s.add(C.Gravity([0, G_UP, 0]), C.Plane("b", [0, 0, 1], 0.0))
    return s


FIRST_ROOT = (-VY0 - np.sqrt(VY0**2 - 2 * G_UP * Y0)) / G_UP  # Y0 + VY0 t + ½ G t² = 0


def _floor(rate: bool) -> Event:
    return Event("y = 0", lambda t, x, v: x[1], -1, True, rate=(lambda t, x, v: v[1]) if rate else None)


def test_a_dip_inside_one_step_is_found_at_its_first_root():
    # RATTLE's step of 50 ms holds the whole dip: y > 0 at both of its ends
    hit = C.simulate(_ball_under_an_upward_field(), 0.2, method="rattle", dt=0.05, events=[_floor(True)])
    assert hit.t[-1] == pytest.approx(FIRST_ROOT, rel=1e-12, abs=1e-15)
    assert abs(hit.x[-1, 0, 1]) < 1e-14
    # what the rate is for: without it the step's ends show no sign change, and the run passes
    missed = C.simulate(_ball_under_an_upward_field(), 0.2, method="rattle", dt=0.05, events=[_floor(False)])
    assert missed.t[-1] == pytest.approx(0.2)


def test_a_rate_that_does_not_turn_is_no_dip():
    s = C.System(name="ball rising")
    s.add_particle("b", 1.0, [0.0, Y0, 0.0], [0.0, 0.2, 0.0])
    s.add(C.Gravity([0, G_UP, 0]), C.Plane("b", [0, 0, 1], 0.0))
    tr = C.simulate(s, 0.2, method="rattle", dt=0.05, events=[_floor(True)])
    assert tr.t[-1] == pytest.approx(0.2) and np.min(tr.x[:, 0, 1]) > 0


def test_no_bead_of_a_long_rope_passes_through_an_inelastic_floor():
    n = 200
    tr = C.simulate(_rope_over_a_floor(n), T_END, method="dopri", rtol=1e-6, atol=1e-6, compiled=False)
    assert tr.info["status"] == "completed"
    y = tr.x.reshape(len(tr.t), n, 3)[:, :, 1]
    assert y.min() >= FLOOR - 1e-9  # 35 µm below before
    assert np.max(tr.constraint_residual) < 1e-9


def test_crossings_after_the_first_stop_are_not_refined(monkeypatch):
    """Thirty beads 1 µm apart in height fall onto a floor: every step that reaches it crosses
    thirty gaps. Only the first impact ends the segment; refining all thirty each time (about
    4 landings of a step each) cost a thousand-bead rope on a floor most of its run. A crossing
    is refined only when it happened by the first stop's instant."""
    from constrained.solvers import driver

    calls = []
    original = driver.locate
    monkeypatch.setattr(driver, "locate", lambda *a: calls.append(a[1].name) or original(*a))
    n, h = 30, 0.1
    s = C.System(name="beads over a floor")
    for i in range(n):
        s.add_particle(f"b{i}", 0.01, [0.05 * i, h + 1e-6 * i, 0.0], [0.0, 0.0, 0.0])
    beads = [f"b{i}" for i in range(n)]
    s.add(C.Plane(beads, [0, 1, 0], 0.0, unilateral=True, restitution=0.5), C.Gravity([0, -9.81, 0]))
    t_land = np.sqrt(2 * h / 9.81)
    tr = C.simulate(s, t_land * 1.01, rtol=1e-8, atol=1e-10, compiled=False)
    impacts = sorted(r.t for r in tr.events if r.kind == "impact")
    assert len(impacts) == n
    expected = np.sqrt(2 * (h + 1e-6 * np.arange(n)) / 9.81)
    np.testing.assert_allclose(impacts, expected, rtol=0, atol=1e-12)  # each at its own instant
    assert len(calls) <= 3 * n  # (refining every crossing of every step: n²/2 = 450)
