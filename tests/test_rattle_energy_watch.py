"""A fixed step that jumps a close encounter (session 15; docs/hard-cases.md, section 16).

A gram released 1 m from a kilogram under V = −1/r (plus a small sideways speed) falls in and
passes the kilogram within a few mm. ``rattle`` at dt = 1 ms steps straight through the
encounter: the run "completed" with its energy gone from −1 J to +92 J, and nothing said so
(the helper's probe of pair forces found it, docs/hard-cases.md section 12). Now the run warns,
naming the time and the change, and says what to do. A resolved orbit (Kepler, e = 0.5, 2,000
steps a period: energy kept to O(h² ω²)) says nothing.

The watch sees every step, not only the output samples (the steps carry h = T + V,
``solvers.rattle.ENERGY_WATCH``): with only the start and the end saved, the encounter is still
named at its time, and so is a pericentre passage whose energy error comes back afterwards
(e = 0.95 at 4,000 steps a period: h off by 9 % at the pericentre, the same to 1e-14 at the
apocentres the samples see)."""

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
    assert info["t"] >= T_STAR - 2e-3  # (the jump is at or after the encounter)
    assert abs(info["change"]) > 10.0
    assert "dt = 0.001 s" in str(caught[0].message)


MU = 0.001 * 1.0 / 1.001  # the pair's reduced mass (kg); k = 1 J·m
#: The fall to the encounter: a radial fall from r0 = 1 m under k = 1 J·m with reduced mass μ
#: reaches r = 0 at t* = (π/2) √(μ r0³ / (2k)) (Kepler's third law for the degenerate ellipse).
T_STAR = 0.5 * np.pi * np.sqrt(MU / 2.0)


def orbit(e: float) -> tuple[C.System, float, float]:
    """Kepler, reduced mass μ, k = 1 J·m, released at the apocentre r_a = 1 m with the speed of
    eccentricity e, v = √(k (1 − e) / (μ r_a)): (system, period 2π √(μ a³ / k), a = r_a / (1 + e));
    its energy is −k / (2a)."""
    k, r_a = 1.0, 1.0
    a = r_a / (1 + e)
    v = np.sqrt(k * (1 - e) / (MU * r_a))
    s = pair(v * 1.0 / 1.001)  # (the gram's speed relative to the centre of mass: the kilogram recoils)
    s.particles[1].velocity = np.array([0.0, -v * 0.001 / 1.001, 0.0])
    return s, 2 * np.pi * np.sqrt(MU * a ** 3 / k), a


def test_a_resolved_orbit_says_nothing():
    s, period, a = orbit(0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnresolvedStepWarning)
        traj = C.simulate(s, period, method="rattle", dt=period / 2000)
    assert "energy_not_conserved" not in traj.info
    np.testing.assert_allclose(traj.energy[0], -1 / (2 * a), rtol=1e-6)
    assert np.max(np.abs(traj.energy - traj.energy[0])) < 1e-3 / (2 * a)


def test_the_encounter_is_named_between_two_samples():
    """Only the start and the end saved (t_eval = [0, 0.1 s]): the steps' own energy names the
    step through the encounter, within two steps of the closed-form fall time t*."""
    with pytest.warns(UnresolvedStepWarning, match=r"reduce dt"):
        traj = C.simulate(pair(0.02), 0.1, method="rattle", dt=1e-3, t_eval=[0.0, 0.1])
    assert list(traj.t) == [0.0, 0.1]
    info = traj.info["energy_not_conserved"]
    assert abs(info["t"] - T_STAR) <= 2e-3 and abs(info["t_change"] - T_STAR) <= 2e-3
    assert abs(info["change"]) > 10.0 and abs(info["step_change"]) > 10.0


def test_an_energy_error_that_comes_back_is_seen_between_the_samples():
    """e = 0.95 at 4,000 steps a period: RATTLE's energy error at the pericentre (where the
    step resolves the orbit worst, h ω ~ (r_a / r_p)^(3/2) times the mean) is 9 % of the energy
    and is gone at the next apocentre. With only the start and the end (two apocentres) saved,
    the run warns and names the pericentre passage, half a period in; the largest change it
    reports is the one of every step's energy computed after the run from the states alone."""
    s, period, a = orbit(0.95)
    dt = period / 4000
    with pytest.warns(UnresolvedStepWarning, match=r"reduce dt"):
        coarse = C.simulate(s, period, method="rattle", dt=dt, t_eval=[0.0, period])
    assert abs(coarse.energy[-1] - coarse.energy[0]) < 1e-10  # (what the samples alone see)
    info = coarse.info["energy_not_conserved"]
    assert abs(info["t_change"] - period / 2) <= 1.01 * dt
    assert abs(info["t"] - period / 2) <= 3.01 * dt
    with pytest.warns(UnresolvedStepWarning):
        every = C.simulate(s, period, method="rattle", dt=dt, t_eval=np.linspace(0.0, period, 4001))
    change = every.energy - every.energy[0]
    k = int(np.argmax(np.abs(change)))
    assert info["change"] == pytest.approx(change[k], rel=1e-9)
    assert abs(info["change"]) > 0.05 / (2 * a)
    assert every.t[k] == pytest.approx(info["t_change"], abs=1e-12)


def test_a_resolved_orbit_on_a_coarse_grid_says_nothing():
    """The e = 0.5 orbit with only its start and end saved: every step's energy within 1e-3 of
    −k/(2a), no warning."""
    s, period, a = orbit(0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnresolvedStepWarning)
        traj = C.simulate(s, period, method="rattle", dt=period / 2000, t_eval=[0.0, period])
    assert "energy_not_conserved" not in traj.info
    assert traj.stats["energy_start"] == pytest.approx(-1 / (2 * a), rel=1e-6)
    assert 0 < abs(traj.stats["energy_change"]) < 1e-3 / (2 * a)


def test_a_chain_at_rest_with_no_forces_says_nothing():
    """A 40-bead chain of 1 cm links at rest, nothing acting on it: h = 0, and the steps'
    round-off (1e-48 J) was "17 × its scale" and warned. The watch's scale has the round-off's
    own floor, the system moving its size at ε a step; the chain stays where it is."""
    s = C.System(name="chain at rest")
    for i in range(40):
        s.add_particle(f"p{i}", 0.01, [0.01 * (i + 1), 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=0.01))
    for i in range(1, 40):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=0.01))
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnresolvedStepWarning)
        traj = C.simulate(s, 0.01, method="rattle", dt=1e-4, t_eval=[0.0, 0.01])
    assert "energy_not_conserved" not in traj.info
    np.testing.assert_allclose(traj.x[-1], traj.x[0], atol=1e-14)


def test_the_watch_can_be_turned_off_and_then_the_same_steps_say_nothing():
    """``energy_watch=False`` (a pair potential's φ not summed every step): the close encounter
    runs the same steps to the same state, bit for bit, without the watch's stats or warning;
    a value that is not true or false is refused."""
    with pytest.warns(UnresolvedStepWarning):
        watched = C.simulate(pair(0.02), 0.1, method="rattle", dt=1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnresolvedStepWarning)
        plain = C.simulate(pair(0.02), 0.1, method="rattle", dt=1e-3, energy_watch=False)
    assert "energy_change" not in plain.stats and "energy_not_conserved" not in plain.info
    np.testing.assert_array_equal(plain.x, watched.x)
    with pytest.raises(C.InputError, match="energy_watch must be true or false"):
        C.simulate(pair(0.02), 0.1, method="rattle", dt=1e-3, energy_watch="no")
