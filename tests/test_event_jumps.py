"""A user's event whose value jumps through zero at an impact (docs/hard-cases.md, section 8):
the vertical velocity of a ball bouncing on a floor never passes through zero along the motion
(it flips from −u to +e u at the bounce), yet a user counting bounces with "vy rising" expects
one crossing per bounce. Before session 15 none was recorded and a terminal one never stopped
the run.

Closed form: dropped from h at rest, the ball reaches the floor at t₁ = √(2h/g) with u = g t₁;
bounce k + 1 follows bounce k after 2 eᵏ u / g. Its apexes (vy falling through zero along
the motion) lie half a flight after each bounce."""

from __future__ import annotations

import numpy as np
import pytest

from constrained import Event, System
from constrained.model.constraints import Plane
from constrained.model.effects import Gravity
from constrained.model.system import Particle
from constrained.run.simulate import simulate

G, H, E = 9.81, 1.0, 0.5
TIGHT = {"rtol": 1e-10, "atol": 1e-12}


def ball(vy=0.0, y=H, e=E):
    return System([Particle("b", 1.0, [0, y, 0], [0, vy, 0])],
                  [Plane("b", [0, 1, 0], 0, unilateral=True, restitution=e)], [Gravity([0, -G, 0])])


def vy(t, x, v):
    return v[1]


def bounces(n):
    t1 = np.sqrt(2 * H / G)
    return t1 + np.concatenate([[0.0], np.cumsum(2 * t1 * E ** np.arange(1, n))])


@pytest.mark.parametrize("method", ["dopri", "projection", "baumgarte"])
def test_velocity_event_jumping_through_zero_at_each_bounce(method):
    t1 = np.sqrt(2 * H / G)
    expected = bounces(3)
    traj = simulate(ball(), 2.6 * t1, method=method, events=[Event("up", vy, +1, False)], **TIGHT)
    np.testing.assert_allclose([ev.t for ev in traj.events if ev.kind == "up"], expected, atol=1e-10)
    for ev in traj.events:
        if ev.kind == "up":  # recorded with the state after the jump
            assert ev.v[0, 1] > 0
    both = simulate(ball(), 2.6 * t1, method=method, events=[Event("turn", vy, 0, False)], **TIGHT)
    turns = sorted([*expected, *(expected[:2] + t1 * E ** np.arange(1, 3))])  # bounces and apexes
    np.testing.assert_allclose([ev.t for ev in both.events if ev.kind == "turn"], turns, atol=1e-9)
    # the apexes (vy falling along the motion) are not doubled, a falling event has no bounce
    down = simulate(ball(), 2.6 * t1, method=method, events=[Event("down", vy, -1, False)], **TIGHT)
    np.testing.assert_allclose([ev.t for ev in down.events if ev.kind == "down"], turns[1::2], atol=1e-9)


def test_terminal_velocity_event_stops_after_the_bounce():
    t1 = np.sqrt(2 * H / G)
    traj = simulate(ball(), 3 * t1, events=[Event("up", vy, +1, True)], **TIGHT)
    assert traj.info["stop"] == "terminal event"
    assert traj.t[-1] == pytest.approx(t1, abs=1e-12)
    assert traj.v[-1, 0, 1] == pytest.approx(E * G * t1, rel=1e-9)  # the rebound e u
    assert traj.x[-1, 0, 1] == pytest.approx(0.0, abs=1e-12)
    # with an output grid: the same stop, its state the run's last sample
    grid = np.linspace(0, 3 * t1, 31)
    gridded = simulate(ball(), 3 * t1, t_eval=grid, events=[Event("up", vy, +1, True)], **TIGHT)
    assert gridded.t[-1] == pytest.approx(t1, abs=1e-12) and gridded.v[-1, 0, 1] > 0


def test_plastic_impact_lands_on_zero_and_is_no_crossing():
    """e = 0: vy jumps from −u to zero (give or take round-off): no rising crossing, ever."""
    traj = simulate(ball(e=0.0), 1.0, events=[Event("up", vy, +1, True)], **TIGHT)
    assert [ev.kind for ev in traj.events if ev.kind == "up"] == []
    assert traj.t[-1] == 1.0


def test_a_start_bouncing_at_t0_is_a_crossing_at_t0():
    """A ball on the floor thrown down at 1 m/s bounces at t = 0: vy jumps from −1 to +e."""
    traj = simulate(ball(vy=-1.0, y=0.0), 0.05, events=[Event("up", vy, +1, False)], **TIGHT)
    assert [ev.t for ev in traj.events if ev.kind == "up"] == [0.0]
    stop = simulate(ball(vy=-1.0, y=0.0), 0.05, events=[Event("up", vy, +1, True)], **TIGHT)
    assert stop.info["stop"] == "terminal event" and stop.t[-1] == 0.0
    assert stop.v[-1, 0, 1] == pytest.approx(E, rel=1e-12)
