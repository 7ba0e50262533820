"""Each constraint and effect type against closed-form physics or an equivalent formulation."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import planar_pendulum

import constrained as C

G = 9.81


def spherical_pendulum(constraint) -> C.System:
    s = C.System()
    s.add_particle("bob", 2.0, [0.6, 0.0, -0.8], [0.0, 1.5, 0.0])
    s.add(constraint, C.Gravity([0, 0, -G]))
    return s


def test_surface_and_distance_give_the_same_motion_and_forces():
    t = np.linspace(0, 3, 61)
    by_distance = C.simulate(spherical_pendulum(C.Distance("bob", point=[0, 0, 0], length=1.0)), 3.0,
                             rtol=1e-11, atol=1e-12, t_eval=t)
    by_surface = C.simulate(spherical_pendulum(C.Surface("bob", "x**2 + y**2 + z**2 - 1")), 3.0,
                            rtol=1e-11, atol=1e-12, t_eval=t)
    np.testing.assert_allclose(by_surface.x, by_distance.x, atol=1e-8)
    # f = |x|² − 1 has gradient 2x: the multiplier halves, the force is the same
    np.testing.assert_allclose(by_surface.constraint_forces, by_distance.constraint_forces, atol=1e-7)
    np.testing.assert_allclose(by_surface.multipliers[:, 0], by_distance.multipliers[:, 0] / 2, rtol=1e-7)
    # angular momentum about the vertical axis is conserved (gravity and rod give no z-torque)
    Lz = 2.0 * np.cross(by_surface.x[:, 0], by_surface.v[:, 0])[:, 2]
    np.testing.assert_allclose(Lz, Lz[0], rtol=1e-9)


def test_bead_on_a_horizontal_circle_feels_centripetal_and_supporting_force():
    m, R, speed = 0.3, 2.0, 1.7
    s = C.System()
    s.add_particle("bead", m, [R, 0, 0], [0, speed, 0])
    s.add(C.Curve("bead", ["x**2 + y**2 - 4", "z"]), C.Gravity([0, 0, -G]))
    assert C.degrees_of_freedom(s) == 1
    t = np.linspace(0, 5, 51)
    tr = C.simulate(s, 5.0, rtol=1e-11, atol=1e-12, t_eval=t)
    w = speed / R
    np.testing.assert_allclose(tr.x[:, 0, 0], R * np.cos(w * t), atol=1e-8)
    np.testing.assert_allclose(tr.x[:, 0, 1], R * np.sin(w * t), atol=1e-8)
    expected = np.stack([-m * speed**2 / R * np.cos(w * t), -m * speed**2 / R * np.sin(w * t),
                         np.full_like(t, m * G)], axis=1)
    np.testing.assert_allclose(tr.constraint_forces[:, 0], expected, atol=1e-8)


def test_custom_constraint_reproduces_the_pendulum():
    t = np.linspace(0, 2, 21)
    ref = C.simulate(planar_pendulum(0.9), 2.0, rtol=1e-11, atol=1e-12, t_eval=t)
    s = C.System()
    s.add_particle("bob", 1.0, ref.x[0, 0])
    s.add(C.Custom("sqrt(x_bob**2 + y_bob**2 + z_bob**2) - 1"), C.Custom("z_bob"), C.Gravity([0, -G, 0]))
    tr = C.simulate(s, 2.0, rtol=1e-11, atol=1e-12, t_eval=t)
    np.testing.assert_allclose(tr.x, ref.x, atol=1e-9)
    np.testing.assert_allclose(tr.constraint_forces, ref.constraint_forces, atol=1e-8)


def test_pin_on_a_prescribed_path_needs_exactly_the_force_of_that_motion():
    m = 1.5
    s = C.System()
    s.add_particle("p", m, [1, 0, 0], [0, 2, 0])
    s.add(C.Pin("p", ["cos(2*t)", "sin(2*t)", "0.1*t**2"]), C.Gravity([0, 0, -G]))
    assert C.degrees_of_freedom(s) == 0
    t = np.linspace(0, 2, 21)
    tr = C.simulate(s, 2.0, rtol=1e-10, atol=1e-12, t_eval=t)
    np.testing.assert_allclose(tr.x[:, 0], np.stack([np.cos(2 * t), np.sin(2 * t), 0.1 * t**2], 1),
                               atol=1e-12)
    accel = np.stack([-4 * np.cos(2 * t), -4 * np.sin(2 * t), np.full_like(t, 0.2)], 1)
    np.testing.assert_allclose(tr.constraint_forces[:, 0], m * accel - m * np.array([0, 0, -G]), atol=1e-9)


def test_moving_plane_lifts_a_resting_particle():
    m = 0.4
    s = C.System()
    s.add_particle("p", m, [0.3, -0.2, 0.0], [0.5, 0, 0.25])
    s.add(C.Plane("p", ["0", "0", "2"], "0.5*t"), C.Gravity([0, 0, -G]))  # plane z = t/4
    tr = C.simulate(s, 1.0, rtol=1e-10, atol=1e-12, t_eval=np.linspace(0, 1, 11))
    np.testing.assert_allclose(tr.x[:, 0, 2], tr.t / 4, atol=1e-12)
    np.testing.assert_allclose(tr.x[:, 0, 0], 0.3 + 0.5 * tr.t, atol=1e-10)
    np.testing.assert_allclose(tr.constraint_forces[:, 0], np.tile([0, 0, m * G], (11, 1)), atol=1e-9)


def test_kepler_orbit_period_from_the_semi_major_axis():
    mu, m = 4.0, 1.0
    r0, v0 = 1.0, 1.6  # below escape speed sqrt(2 mu / r0) ≈ 2.83
    s = C.System()
    s.add_particle("planet", m, [r0, 0, 0], [0, v0, 0])
    s.add(C.Central("planet", point=[0, 0, 0], expr=f"-{mu * m}/r"))
    energy = 0.5 * v0**2 - mu / r0
    a = -mu / (2 * energy)
    period = 2 * np.pi * np.sqrt(a**3 / mu)
    tr = C.simulate(s, period, rtol=1e-12, atol=1e-13, t_eval=[0, period / 2, period])
    np.testing.assert_allclose(tr.x[-1, 0], tr.x[0, 0], atol=1e-8)
    # at half a period the planet is at apoapsis 2a − r0 on the far side
    np.testing.assert_allclose(tr.x[1, 0], [-(2 * a - r0), 0, 0], atol=1e-8)
    L = np.cross(tr.x[:, 0], tr.v[:, 0])[:, 2]
    np.testing.assert_allclose(L, r0 * v0, rtol=1e-10)


def test_applied_force_formula_equals_rayleigh_damping():
    def system(effect):
        s = C.System()
        s.add_particle("p", 2.0, [1, 0, 0], [0, 1, 0.5])
        s.add(C.Spring("p", point=[0, 0, 0], k=3.0), effect)
        return s

    t = np.linspace(0, 4, 41)
    a = C.simulate(system(C.Damping(0.7, ["p"])), 4.0, rtol=1e-11, atol=1e-12, t_eval=t)
    b = C.simulate(system(C.Force("p", ["-0.7*vx_p", "-0.7*vy_p", "-0.7*vz_p"])), 4.0,
                   rtol=1e-11, atol=1e-12, t_eval=t)
    np.testing.assert_allclose(a.x, b.x, atol=1e-10)
    # energy decays at the rate of the dissipation: dE/dt = −c |v|²
    power = -0.7 * np.sum(a.v[:, 0] ** 2, axis=1)
    dE = np.gradient(a.energy, t)
    np.testing.assert_allclose(dE[2:-2], power[2:-2], atol=2e-3)


def test_pairwise_damping_keeps_momentum_and_kills_relative_motion():
    s = C.System()
    s.add_particle("a", 1.0, [0, 0, 0], [1.0, 0.2, 0])
    s.add_particle("b", 3.0, [1.5, 0, 0], [0, 0, 0])
    s.add(C.Spring("a", "b", k=5.0, rest=1.0), C.Damping(2.0, a="a", b="b"))
    tr = C.simulate(s, 20.0, rtol=1e-10, atol=1e-12, t_eval=np.linspace(0, 20, 11))
    p = tr.v[:, 0] * 1.0 + tr.v[:, 1] * 3.0
    np.testing.assert_allclose(p - p[0], 0, atol=1e-10)
    rel = tr.v[-1, 0] - tr.v[-1, 1]
    assert np.linalg.norm(rel) < 1e-3 * np.linalg.norm(tr.v[0, 0] - tr.v[0, 1])


def test_gravity_on_listed_particles_only():
    s = C.System()
    s.add_particle("heavy", 1.0, [0, 0, 0])
    s.add_particle("floating", 1.0, [1, 0, 0])
    s.add(C.Gravity([0, 0, -G], particles=["heavy"]))
    tr = C.simulate(s, 1.0, t_eval=[0, 1], rtol=1e-10)
    np.testing.assert_allclose(tr.x[-1, 0], [0, 0, -G / 2], atol=1e-9)
    np.testing.assert_allclose(tr.x[-1, 1], [1, 0, 0], atol=1e-12)


def test_unknown_particle_in_a_constraint_is_named():
    s = planar_pendulum(0.1)
    s.add(C.Distance("bob", "ghost", length=1.0))
    with pytest.raises(C.InputError, match="unknown particle 'ghost'"):
        C.assemble(s)


def test_velocity_dependent_generalized_potential_must_be_linear():
    s = C.System()
    s.add_particle("p", 1.0, [0, 0, 0], [1, 0, 0])
    s.add(C.Electromagnetic({"p": 1.0}, phi="0", A=["x", "0", "0"]))
    assert "generalized_potential" in C.assemble(s).active_terms
