"""A fixed step that jumps a close encounter (session 15; docs/hard-cases.md, section 16).

A gram released 1 m from a kilogram under V = −1/r (plus a small sideways speed) falls in and
passes the kilogram within a few mm. ``rattle`` at dt = 1 ms steps straight through the
encounter: the run "completed" with its energy gone from −1 J to +92 J, and nothing said so
(the helper's probe of pair forces found it, docs/hard-cases.md section 12). Now the run warns,
naming the time and the change, and says what to do. A resolved orbit (Kepler, e = 0.5, 2,000
steps a period: energy kept to O(h² ω²)) says nothing."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import constrained as C
from constrained.errors import UnresolvedStepWarning


def pair(v_side: float) -> C.System:
    s = C.System(name="gram and kilogram under -1/r")
    s.add_particle("a", 0.001, [1.0, 0.0, 0.0], [0.0, v_side, 0.0])
    s.add_particle("b", 1.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    s.add(C.Central("a", "b", expr="-1/r"), C.Plane(["a", "b"], [0, 0, 1]))
    return s


def test_a_fixed_step_through_a_close_encounter_is_named():
    with pytest.warns(UnresolvedStepWarning, match=r"reduce dt") as caught:
        traj = C.simulate(pair(0.02), 0.1, method="rattle", dt=1e-3)
    info = traj.info["energy_not_conserved"]
    # the fall to the encounter: a radial fall from r0 = 1 m under k = 1 J·m with reduced mass μ
    # reaches r = 0 at t* = (π/2) √(μ r0³ / (2k)) (Kepler's third law for the degenerate ellipse)
    mu = 0.001 * 1.0 / 1.001
    t_star = 0.5 * np.pi * np.sqrt(mu / 2.0)
    assert info["t"] >= t_star - 2e-3  # (the jump is at or after the encounter)
    assert abs(info["change"]) > 10.0
    assert "dt = 0.001 s" in str(caught[0].message)


def test_a_resolved_orbit_says_nothing():
    """Kepler: reduced mass μ, k = 1 J·m, a = 1 m: circular-speed factor chosen for e = 0.5 at
    the apocentre, v = √(k (1 − e) / (μ r_a)) with r_a = a (1 + e); the energy −k/(2a)."""
    mu, k, e = 0.001 * 1.0 / 1.001, 1.0, 0.5
    r_a = 1.0
    a = r_a / (1 + e)
    v = np.sqrt(k * (1 - e) / (mu * r_a))
    period = 2 * np.pi * np.sqrt(mu * a ** 3 / k)
    s = pair(v * 1.0 / 1.001)  # (the gram's speed relative to the centre of mass: the kilogram recoils)
    s.particles[1].velocity = np.array([0.0, -v * 0.001 / 1.001, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnresolvedStepWarning)
        traj = C.simulate(s, period, method="rattle", dt=period / 2000)
    assert "energy_not_conserved" not in traj.info
    np.testing.assert_allclose(traj.energy[0], -k / (2 * a), rtol=1e-6)
    assert np.max(np.abs(traj.energy - traj.energy[0])) < 1e-3 * k / (2 * a)
