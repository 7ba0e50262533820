"""Velocity constraints on scenes nobody in this repository chose (session 15).

Each test checks a closed form derived here: the Chaplygin sleigh started aligned, at rest,
with a 10⁶ mass ratio and under `rodas`; a ball rolling on a level floor (v = ω × R n); a
no-slip particle held against the tangential pull; redundant velocity rows (minimum-norm
split); a start that violates the runner (mass-weighted projection); a row whose
coefficient vanishes mid-run (diagnosed, the force Aᵀμ finite); degenerate knife edges
(refused naming the particles); the modes' reduced-route cross-check on the motions the
runner allows. docs/hard-cases.md, section 11.
"""

from __future__ import annotations

import itertools
import math
import warnings

import numpy as np
import pytest
from test_nonholonomic import SCENE, G, sleigh, sleigh_closed_form, sleigh_state

import constrained as C
from constrained.cli.main import main
from constrained.manifold.constraint_report import SingularConfigurationWarning


# --- the sleigh where its closed form degenerates -------------------------------------------------
def test_a_sleigh_started_aligned_runs_straight_and_one_at_rest_stays():
    """ω0 = 0: M v' = M a ω² = 0 and I ω' = 0, so v = v0 for ever, the runner carries no force
    (μ = M v ω I_C / I = 0); backwards (v0 < 0) the same. At rest nothing moves at all."""
    t = np.linspace(0.0, 3.0, 31)
    for v0 in (0.3, -0.3):
        tr = C.simulate(sleigh(v0=v0, w0=0.0), 3.0, rtol=1e-10, atol=1e-12, t_eval=t)
        omega, speed, heading = sleigh_state(tr)
        assert np.max(np.abs(omega)) < 1e-12 and np.max(np.abs(heading)) < 1e-12
        np.testing.assert_allclose(speed, v0, atol=1e-12)
        np.testing.assert_allclose(tr.x[:, 0, 0], v0 * t, atol=1e-11)
        assert np.max(np.abs(tr.multipliers[:, -1])) < 1e-10
    rest = C.simulate(sleigh(v0=0.0, w0=0.0), 3.0, t_eval=t)
    assert np.max(np.abs(rest.x - rest.x[0])) == 0.0 and np.max(np.abs(rest.multipliers)) == 0.0


@pytest.mark.parametrize("mP, mF", [(1000.0, 0.001), (0.001, 1000.0)])
def test_sleigh_with_a_million_to_one_mass_ratio_follows_the_closed_form(mP, mF):
    t = np.linspace(0.0, 3.0, 31)
    tr = C.simulate(sleigh(mP=mP, mF=mF), 3.0, rtol=1e-10, atol=1e-12, t_eval=t)
    omega, speed, heading = sleigh_state(tr)
    omega_ref, speed_ref, heading_ref = sleigh_closed_form(t, mP=mP, mF=mF)
    np.testing.assert_allclose(omega, omega_ref, atol=1e-8)
    np.testing.assert_allclose(speed, speed_ref, atol=1e-8)
    np.testing.assert_allclose(heading, heading_ref, atol=1e-8)
    assert np.ptp(tr.energy) <= 1e-9 * tr.energy[0]


def test_rodas_follows_the_sleigh_and_rattles_refusal_names_it():
    t = np.linspace(0.0, 4.0, 41)
    tr = C.simulate(sleigh(), 4.0, method="rodas", rtol=1e-10, atol=1e-12, t_eval=t)
    omega, speed, heading = sleigh_state(tr)
    omega_ref, speed_ref, heading_ref = sleigh_closed_form(t)
    np.testing.assert_allclose(omega, omega_ref, atol=1e-9)
    np.testing.assert_allclose(heading, heading_ref, atol=1e-9)
    assert np.ptp(tr.energy) <= 1e-9 * tr.energy[0] and np.max(tr.velocity_residual) < 1e-12
    with pytest.raises(C.InputError, match="rattle' cannot take velocity constraints.*rodas"):
        C.simulate(sleigh(), 1.0, method="rattle", dt=1e-3)


@pytest.mark.parametrize("method", ["rodas", "baumgarte", "pantelides"])
def test_a_belt_does_the_work_minus_mu_b_under_more_methods(method):
    """vx = U sin Ωt on a particle under gravity along y: x = x0 + U (1 − cos Ωt)/Ω, the force
    m U Ω cos Ωt, and E(t) − E(0) = ∫ −μ b dt = m U² sin²(Ωt)/2 (the kinetic energy along x)."""
    m, U, W = 1.7, 0.8, 3.0
    system = C.System([C.Particle("p", m, [0.2, 0, 0], [0, 0.5, 0])], [C.Velocity("vx_p - U*sin(W*t)")],
                      [C.Gravity([0, -G, 0])], parameters={"U": U, "W": W})
    t = np.linspace(0.0, 2.0, 41)
    tr = C.simulate(system, 2.0, method=method, rtol=1e-10, atol=1e-12, t_eval=t)
    tol = 1e-6 if method != "rodas" else 1e-8
    np.testing.assert_allclose(tr.x[:, 0, 0], 0.2 + U * (1 - np.cos(W * t)) / W, atol=tol)
    np.testing.assert_allclose(tr.multipliers[:, 0], m * U * W * np.cos(W * t), atol=1e3 * tol)
    np.testing.assert_allclose(tr.energy - tr.energy[0], 0.5 * m * (U * np.sin(W * t)) ** 2, atol=1e2 * tol)


# --- starts that break the runner -----------------------------------------------------------------
def test_a_start_across_the_runner_is_projected_by_the_least_kinetic_change_and_reported():
    """P moves 0.2 m/s across its blade (along y). The least mass-weighted change that satisfies
    the runner (v_P·ŷ = 0) and the rod ((v_F − v_P)·x̂ = 0) takes exactly that 0.2 m/s off P
    alone (the rod's multiplier is 0: κ (1/m_P + 1/m_F) = 0)."""
    system = sleigh()
    v = system.velocities.copy()
    v[0, 1] = 0.2
    moved = system.with_state(system.positions, v)
    with pytest.warns(C.InitialStateWarning, match="velocities changed by 0.2 m/s"):
        tr = C.simulate(moved, 1.0, rtol=1e-10, atol=1e-12, t_eval=[0.0, 1.0])
    np.testing.assert_allclose(tr.v[0], sleigh().velocities, atol=1e-14)
    assert tr.info["initial_correction"]["velocity"] == pytest.approx(0.2, rel=1e-12)


# --- rolling ------------------------------------------------------------------------------------------
def ball_on_floor(R=0.25, d=0.2, mc=0.7, mv=0.4, speed=0.6, spin=1.1, normal_length=1.0):
    """The tetrahedron ball of test_nonholonomic on the level floor z = 0, rolling along x with
    ω = n × v / R plus a spin about n; no gravity: nothing but the constraints acts."""
    n = np.array([0.0, 0.0, 1.0])
    corners = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) * d / math.sqrt(3)
    vc = np.array([speed, 0.0, 0.0])
    omega = np.cross(n, vc) / R + spin * n
    names = ["c", "v1", "v2", "v3", "v4"]
    X = np.vstack([R * n, R * n + corners])
    V = np.vstack([vc, vc + np.cross(omega, corners)])
    particles = [C.Particle(k, m, x, v) for k, m, x, v in zip(names, [mc] + [mv] * 4, X, V, strict=True)]
    rods = [C.Distance(a, b, length=float(np.linalg.norm(X[i] - X[j])))
            for (i, a), (j, b) in itertools.combinations(enumerate(names), 2)]
    return C.System(particles, [*rods, C.Plane(["c"], [0, 0, 1], R),
                                C.Rolling("c", normal=[0, 0, normal_length], radius=R, a="v1", b="v2")])


@pytest.mark.parametrize("normal_length", [1.0, 7.5])
def test_a_ball_rolling_on_a_level_floor_keeps_v_equal_omega_cross_R(normal_length):
    """No force along the floor: v_c stays, and the contact point's velocity v_c + ω × (−R n)
    stays 0, so ω's part in the floor is n × v_c / R; the spin about n stays. The normal's
    length does not matter (it is normalized)."""
    R, speed, spin = 0.25, 0.6, 1.1
    t = np.linspace(0.0, 2.0, 21)
    tr = C.simulate(ball_on_floor(R=R, speed=speed, spin=spin, normal_length=normal_length), 2.0,
                    rtol=1e-10, atol=1e-12, t_eval=t)
    np.testing.assert_allclose(tr.v[:, 0], np.tile([speed, 0.0, 0.0], (len(t), 1)), atol=1e-10)
    for k in range(len(t)):  # ω from the body: v_i − v_c = ω × r_i (least squares over the corners)
        r, u = tr.x[k, 1:] - tr.x[k, 0], tr.v[k, 1:] - tr.v[k, 0]
        skew = np.concatenate([np.array([[0, ri[2], -ri[1]], [-ri[2], 0, ri[0]], [ri[1], -ri[0], 0]])
                               for ri in r])
        omega = np.linalg.lstsq(skew, u.ravel(), rcond=None)[0]
        np.testing.assert_allclose(omega, [0.0, speed / R, spin], atol=1e-9)
    assert np.ptp(tr.energy) < 1e-10 and np.max(np.abs(tr.multipliers[:, -2:])) < 1e-9


def test_a_no_slip_particle_is_held_where_it_stands_by_the_tangential_force():
    """radius 0: the particle has no velocity along its plane, so it cannot move there at all;
    its in-plane start velocity is removed (reported) and friction μ₁t₁ + μ₂t₂ carries the
    tangential weight m (g − (g·n̂)n̂), whatever the normal's length."""
    m, g = 0.3, np.array([1.0, 2.0, -9.81])
    system = C.System([C.Particle("p", m, [0.1, 0.2, 0], [0.3, 0.2, 0])],
                      [C.Plane("p", [0, 0, 1]), C.Rolling("p", normal=[0, 0, 2])], [C.Gravity(list(g))])
    with pytest.warns(C.InitialStateWarning, match="velocities changed by 0.361 m/s"):
        tr = C.simulate(system, 1.0, rtol=1e-10, atol=1e-12, t_eval=[0.0, 0.5, 1.0])
    np.testing.assert_allclose(tr.x[:, 0], np.tile([0.1, 0.2, 0.0], (3, 1)), atol=1e-13)
    np.testing.assert_allclose(tr.constraint_forces[:, 0], np.tile(-m * g, (3, 1)), atol=1e-12)


# --- redundant velocity rows: the minimum-norm split ------------------------------------------------
@pytest.mark.parametrize("method", ["dopri", "projection", "rodas", "idas", "ggl", "baumgarte", "pantelides"])
def test_a_velocity_row_repeating_a_planes_derivative_shares_its_load(method):
    """z = 0 and v_z = 0 on one particle under gravity: both rows have the gradient ẑ, so the
    least |(λ, μ)| with λ + μ = m g is λ = μ = m g / 2."""
    m = 2.0
    system = C.System([C.Particle("p", m, [0, 0, 0], [1, 0, 0])],
                      [C.Plane("p", [0, 0, 1]), C.Velocity("vz_p")], [C.Gravity([0, 0, -G])])
    tr = C.simulate(system, 1.0, method=method, t_eval=[0.0, 0.5, 1.0])
    np.testing.assert_allclose(tr.multipliers, m * G / 2, rtol=1e-9)
    np.testing.assert_allclose(tr.x[:, 0, 0], [0.0, 0.5, 1.0], atol=1e-9)


def test_a_velocity_row_given_twice_at_two_scales_splits_by_its_gradients():
    """v_z = 0 and 2 v_z = 0: μ₁ + 2 μ₂ = m g with the least |μ| is μ ∝ (1, 2): m g (1, 2)/5."""
    m = 2.0
    system = C.System([C.Particle("p", m, [0, 0, 0], [1, 0, 0])],
                      [C.Velocity("vz_p"), C.Velocity("2*vz_p")], [C.Gravity([0, 0, -G])])
    tr = C.simulate(system, 1.0, t_eval=[0.0, 1.0])
    np.testing.assert_allclose(tr.multipliers, np.tile(m * G * np.array([1, 2]) / 5, (2, 1)), rtol=1e-9)
    assert np.max(np.abs(tr.x[:, 0, 2])) < 1e-12


# --- a row whose coefficient vanishes mid-run -----------------------------------------------------------
def vanishing_row() -> C.System:
    """y·v_x = 0 on a particle moving along y through y = 0 at 1 m/s, pulled along x by 1 N:
    while y ≠ 0, v_x = 0 and the force is y μ = −1 N (μ = −1/y: a pole at t = 1 s)."""
    return C.System([C.Particle("p", 1.0, [0, -1, 0], [0, 1, 0])],
                    [C.Plane("p", [0, 0, 1]), C.Velocity("y_p*vx_p")], [C.Gravity([1, 0, 0])])


def test_a_velocity_row_whose_coefficient_vanishes_is_named_and_its_force_stays_finite():
    t = np.linspace(0.0, 2.0, 5)  # t = 1 s lands on the pole
    with pytest.warns(SingularConfigurationWarning, match=r"'y_p\*vx_p = 0' at t = 1 s .*pole"):
        tr = C.simulate(vanishing_row(), 2.0, rtol=1e-10, atol=1e-12, t_eval=t)
    lost = tr.info["velocity_rows_lost_rank"]
    assert [row["row"] for row in lost] == ["y_p*vx_p = 0"] and lost[0]["t"] == 1.0
    np.testing.assert_allclose(tr.x[:, 0, 1], -1.0 + t, atol=1e-12)
    assert np.max(np.abs(tr.x[:, 0, 0])) < 1e-9  # x does not move: v_x = 0 on both sides
    away = np.abs(tr.x[:, 0, 1]) > 0.1
    np.testing.assert_allclose(tr.constraint_forces[away, 0], np.tile([-1.0, 0, 0], (away.sum(), 1)),
                               atol=1e-9)
    np.testing.assert_allclose(tr.multipliers[away, 1], -1.0 / tr.x[away, 0, 1], rtol=1e-8)
    # a grid that does not come near the pole says nothing (the multipliers there are moderate)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SingularConfigurationWarning)
        far = C.simulate(vanishing_row(), 2.0, t_eval=np.linspace(0.0, 2.0, 4))
    assert "velocity_rows_lost_rank" not in far.info


def test_a_run_stopped_at_a_vanishing_velocity_row_names_it():
    with pytest.raises(C.SimulationError, match=r"lose rank along the run: 'y_p\*vx_p = 0'"), \
            pytest.warns(SingularConfigurationWarning):
        C.simulate(vanishing_row(), 2.0, method="rodas", t_eval=np.linspace(0.0, 2.0, 5))


# --- knife edges without a direction ------------------------------------------------------------------
def blade(across=None, along=None, normal=None, B=(1.0, 0.0, 0.0)):
    return C.System([C.Particle("P", 1, [0, 0, 0], [1, 0, 0]), C.Particle("A", 1, [1, 0, 0]),
                     C.Particle("B", 1, list(B))],
                    [C.KnifeEdge("P", across=across, along=along, normal=normal)])


@pytest.mark.parametrize("system, words", [
    (blade(across=["A", "B"]), r"'A' and 'B' that give the blade's direction \('across'\) are at the same"),
    (blade(along=["A", "B"], normal=[0, 0, 1]), r"'A' and 'B' that give the blade's direction \('along'\)"),
    (blade(along=["A", "B"], normal=[0, 0, 1], B=(1.0, 0.0, 0.5)), "is parallel to the plane's normal"),
])
def test_a_knife_edge_without_a_direction_is_refused_naming_why(system, words):
    with pytest.raises(C.InconsistentStateError, match=words):
        C.simulate(system, 1.0)


def test_a_knife_edge_with_a_zero_normal_is_refused_naming_the_key():
    with pytest.raises(C.InputError, match=r"normal: the normal vector is zero"):
        C.KnifeEdge("P", along=["A", "B"], normal=[0, 0, 0])


def test_a_scene_whose_blade_particles_coincide_exits_2_naming_them(tmp_path, capsys):
    path = tmp_path / "blade.toml"
    scene = SCENE.format(item='type = "knife_edge"\nparticle = "p"\nacross = ["q", "r"]')
    scene = scene.replace("[[constraints]]\ntype = \"knife_edge\"",
                          "[[particles]]\nname = \"r\"\nmass = 1.0\nposition = [1, 0, 0]\n\n"
                          "[[constraints]]\ntype = \"knife_edge\"")
    path.write_text(scene)
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "constraints[1]" in err and "'q' and 'r' that give the blade's direction" in err, err


# --- modes: the reduced route on the motions the runner allows ---------------------------------------
def test_the_modes_reduced_cross_check_restricts_to_the_runners_motions(capsys, tmp_path):
    """A double pendulum whose lower bob rides a runner along the lower rod: one mode,
    ω² = g (m_p + m_q)/(m_p l1) + g m_q/(m_p l2). The reduced route in (a, b) has two
    coordinates; restricted to Ã q̇ = 0 it has the same one root pair (it said DISAGREE, inf)."""
    mp, mq, l1, l2 = 1.0, 2.0, 1.0, 0.7
    system = C.System([C.Particle("p", mp, [0, -l1, 0]), C.Particle("q", mq, [0, -l1 - l2, 0])],
                      [C.Distance("p", point=[0, 0, 0], length=l1), C.Distance("p", "q", length=l2),
                       C.Plane(["p", "q"], [0, 0, 1]), C.KnifeEdge("q", along=["p", "q"], normal=[0, 0, 1])],
                      [C.Gravity([0, -G, 0])])
    reduced = C.ReducedModel(system, ["a", "b"], {
        "p": ["l1*sin(a)", "-l1*cos(a)", "0"],
        "q": ["l1*sin(a) + l2*sin(b)", "-l1*cos(a) - l2*cos(b)", "0"]}, parameters={"l1": l1, "l2": l2})
    found = C.modes(system)
    check = found.cross_check(reduced)
    expected = math.sqrt(G * (mp + mq) / (mp * l1) + G * mq / (mp * l2))
    np.testing.assert_allclose(np.abs(check.reduced), expected, rtol=1e-9)
    assert check.difference < 1e-9
    assert main(["modes", "scenarios/chaplygin_sleigh.toml", "--out", str(tmp_path)]) == 0
    assert "the roots s agree" in capsys.readouterr().out
