"""Issue 30: velocity constraints a(x, t)·v + b(x, t) = 0 with their multipliers.

Closed forms: the Chaplygin sleigh (turning rate, speed, heading, energy), a skate on an
inclined plane (its cycloid-like path), a ball rolling down a slope (acceleration, spin),
a prescribed velocity that does work (the energy balance ∫ (Aᵀμ)·v dt); the reduced route
(Lagrange–d'Alembert) against the Cartesian one; statics, the DOF counts and refusals.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.integrate import simpson

import constrained as C
from constrained.cli.main import main

G = 9.81


# --- the systems -------------------------------------------------------------------------------
def sleigh(mP=1.0, mF=2.3, L=0.8, v0=0.3, w0=1.5, method_form="along") -> C.System:
    """Two particles: the rear P on a knife edge along the body P→F, on the plane z = 0."""
    xP, xF = np.zeros(3), np.array([L, 0.0, 0.0])
    vP = np.array([v0, 0.0, 0.0])
    vF = vP + np.cross([0.0, 0.0, w0], xF - xP)
    blade = (C.KnifeEdge("P", along=["P", "F"], normal=[0, 0, 1]) if method_form == "along"
             else C.Velocity("-vx_P*(y_F - y_P) + vy_P*(x_F - x_P)", name="runner"))
    return C.System([C.Particle("P", mP, xP, vP), C.Particle("F", mF, xF, vF)],
                    [C.Distance("P", "F", length=L), C.Plane(["P", "F"], [0, 0, 1]), blade])


def sleigh_closed_form(t, mP=1.0, mF=2.3, L=0.8, v0=0.3, w0=1.5):
    """(turning rate, speed of P along the blade, heading) of the Chaplygin sleigh:
    M v' = M a ω², I ω' = −M a v ω with I about P, so v = V tanh(k t + c0),
    ω = √(M/I) V sech(k t + c0), θ = √(I/M)/a (gd(k t + c0) − gd(c0))."""
    M = mP + mF
    a = mF * L / M
    I = mF * L**2  # about P
    E = 0.5 * M * v0**2 + 0.5 * I * w0**2
    V = math.sqrt(2 * E / M)
    c0, k = math.atanh(v0 / V), a * M * V / I
    s = k * t + c0
    return (np.sqrt(M / I) * V / np.cosh(s), V * np.tanh(s),
            np.sqrt(I / M) / a * (np.arctan(np.sinh(s)) - np.arctan(np.sinh(c0))))


def sleigh_state(tr, L=0.8):
    d, dv = tr.x[:, 1] - tr.x[:, 0], tr.v[:, 1] - tr.v[:, 0]
    omega = (d[:, 0] * dv[:, 1] - d[:, 1] * dv[:, 0]) / L**2
    speed = np.sum(tr.v[:, 0] * d, axis=1) / L
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    return omega, speed, heading


def skate(alpha=0.35, omega=2.0, m0=0.9, m1=0.35, r=0.15, heading=0.0):
    """A skate on a plane through the origin tilted by ``alpha``: the blade particle P (at
    the centre of mass) and A, B at P ∓ r·(blade), the blade turned ``heading`` from the
    downhill direction, spinning at ``omega`` about the normal, at rest otherwise."""
    n = np.array([-math.sin(alpha), 0.0, math.cos(alpha)])
    g_t = np.array([0.0, 0.0, -G]) - (-G * n[2]) * n
    down = g_t / np.linalg.norm(g_t)
    side = np.cross(n, down)
    d = math.cos(heading) * down + math.sin(heading) * side
    P, A, B = np.zeros(3), -r * d, r * d
    spin = omega * n
    particles = [C.Particle("P", m0, P), C.Particle("A", m1, A, np.cross(spin, A)),
                 C.Particle("B", m1, B, np.cross(spin, B))]
    constraints = [C.Plane(["P", "A", "B"], list(n)), C.Distance("A", "B", length=2 * r)]
    constraints += [C.Custom(f"{c}_P - ({c}_A + {c}_B)/2") for c in "xyz"]  # z: redundant with the planes
    constraints.append(C.KnifeEdge("P", along=["A", "B"], normal=list(n)))
    return C.System(particles, constraints, [C.Gravity([0, 0, -G])]), down, side, float(np.linalg.norm(g_t))


# --- the Chaplygin sleigh ------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["dopri", "projection", "baumgarte", "idas", "ggl", "pantelides"])
def test_chaplygin_sleigh_follows_its_closed_form_with_every_method(method):
    t = np.linspace(0.0, 6.0, 121)
    tr = C.simulate(sleigh(), 6.0, method=method, rtol=1e-10, atol=1e-12, t_eval=t)
    omega, speed, heading = sleigh_state(tr)
    omega_ref, speed_ref, heading_ref = sleigh_closed_form(t)
    tol = 1e-6 if method == "baumgarte" else 1e-8  # Baumgarte's feedback leaves a small drift
    np.testing.assert_allclose(omega, omega_ref, atol=tol)
    np.testing.assert_allclose(speed, speed_ref, atol=tol)
    np.testing.assert_allclose(heading, heading_ref, atol=tol)
    # the blade does no work: the energy stays (b = 0)
    assert np.ptp(tr.energy) <= 1e-8 * tr.energy[0]
    assert tr.multipliers.shape == (len(t), 4)  # 3 rows of f, then the blade's μ
    assert (tr.info["degrees_of_freedom"], tr.info["velocity_degrees_of_freedom"]) == (3, 2)


def test_sleigh_ends_in_straight_line_motion_at_the_speed_its_energy_allows():
    mP, mF, L = 0.6, 1.7, 1.1
    t = np.linspace(0.0, 30.0, 31)
    tr = C.simulate(sleigh(mP, mF, L, v0=-0.2, w0=-2.0), 30.0, rtol=1e-10, atol=1e-12, t_eval=t)
    omega, speed, _ = sleigh_state(tr, L)
    E = tr.energy[0]
    assert abs(omega[-1]) < 1e-6 * abs(omega[0])
    # all the energy ends up in the translation: |v| → √(2E/M), forward (towards F)
    assert speed[-1] == pytest.approx(math.sqrt(2 * E / (mP + mF)), rel=1e-9)


def test_a_formula_velocity_constraint_gives_the_knife_edge_motion():
    t = np.linspace(0.0, 3.0, 31)
    a = C.simulate(sleigh(), 3.0, rtol=1e-10, atol=1e-12, t_eval=t)
    b = C.simulate(sleigh(method_form="formula"), 3.0, rtol=1e-10, atol=1e-12, t_eval=t)
    np.testing.assert_allclose(a.x, b.x, atol=1e-10)
    # the formula's row is the knife edge's times |P→F| = L: its multiplier is μ / L
    np.testing.assert_allclose(b.constraint_forces, a.constraint_forces, atol=1e-8)


# --- a skate on an inclined plane ------------------------------------------------------------------
def test_skate_on_an_incline_follows_the_cycloid_like_closed_form():
    omega = 2.0
    system, down, side, g_t = skate(omega=omega)
    t = np.linspace(0.0, 2 * math.pi / omega, 201)
    tr = C.simulate(system, t[-1], rtol=1e-10, atol=1e-12, t_eval=t)
    P = tr.x[:, 0]
    # from rest with the blade downhill: φ = ω t, u = (g_t/ω) sin ω t along the blade
    np.testing.assert_allclose(P @ down, g_t / (2 * omega**2) * np.sin(omega * t) ** 2, atol=1e-9)
    np.testing.assert_allclose(P @ side, g_t / (2 * omega) * (t - np.sin(2 * omega * t) / (2 * omega)),
                               atol=1e-9)
    # it never goes further down than g_t/(2ω²), and is back on its level after each half turn
    assert np.max(P @ down) == pytest.approx(g_t / (2 * omega**2), rel=1e-6)
    assert np.ptp(tr.energy) < 1e-9
    report = C.constraint_report(system)
    assert (report.degrees_of_freedom, report.velocity_degrees_of_freedom) == (3, 2)
    assert report.redundant  # the midpoint's z row is implied by the planes


# --- a ball rolling down a slope ---------------------------------------------------------------------
def rolling_ball(alpha=0.35, R=0.3, d=0.2, mc=0.7, mv=0.4, spin=1.3, seed=3):
    """A ball of radius R: a centre particle and a regular tetrahedron of four particles at
    distance d (isotropic inertia I = 8/3 mv d²), all ten distances held, rolling without
    slipping on a plane tilted by alpha, started sideways with a spin about the normal."""
    n = np.array([-math.sin(alpha), 0.0, math.cos(alpha)])
    rotation, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    corners = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) * d / math.sqrt(3) @ rotation.T
    g_t = np.array([0.0, 0.0, -G]) - (-G * n[2]) * n
    vc = 0.7 * np.cross(n, g_t) / np.linalg.norm(g_t)
    omega = np.cross(n, vc) / R + spin * n  # rolling, plus a spin about the normal
    names = ["c", "v1", "v2", "v3", "v4"]
    X = np.vstack([R * n, R * n + corners])
    V = np.vstack([vc, vc + np.cross(omega, corners)])
    masses = [mc] + [mv] * 4
    particles = [C.Particle(k, m, x, v) for k, m, x, v in zip(names, masses, X, V, strict=True)]
    rods = [C.Distance(a, b, length=float(np.linalg.norm(X[i] - X[j])))
            for (i, a), (j, b) in itertools.combinations(enumerate(names), 2)]
    system = C.System(particles, [*rods, C.Plane(["c"], list(n), R),
                                  C.Rolling("c", normal=list(n), radius=R, a="v1", b="v2")],
                      [C.Gravity([0, 0, -G])])
    M, I = mc + 4 * mv, 8 / 3 * mv * d**2
    return system, n, g_t / (1 + I / (M * R**2)), np.array(masses)


def test_ball_rolls_down_with_the_reduced_acceleration_and_keeps_its_spin():
    system, n, acceleration, masses = rolling_ball()
    t = np.linspace(0.0, 2.0, 101)
    tr = C.simulate(system, 2.0, method="projection", rtol=1e-10, atol=1e-12, t_eval=t)
    c0, v0 = tr.x[0, 0], tr.v[0, 0]
    # the centre moves in the reduced field g_t / (1 + I/(M R²)), whatever the spin
    np.testing.assert_allclose(tr.x[:, 0], c0 + np.outer(t, v0) + 0.5 * np.outer(t**2, acceleration),
                               atol=1e-9)
    # friction acts in the plane through the contact point: the spin about n stays
    rel, relv = tr.x - tr.x[:, :1], tr.v - tr.v[:, :1]
    spin = np.sum(masses[None, :, None] * np.cross(rel, relv), axis=1) @ n
    assert np.ptp(spin) < 1e-9 * abs(spin[0]) + 1e-12
    assert np.ptp(tr.energy) < 1e-8 * abs(tr.energy).max()  # rolling without slipping does no work
    # the contact point's velocity (body point under the centre) is zero along the plane
    assert np.max(tr.velocity_residual) < 1e-12
    report = C.constraint_report(system)
    assert (report.degrees_of_freedom, report.velocity_degrees_of_freedom) == (5, 3)


# --- a velocity constraint that does work -------------------------------------------------------------
def test_prescribed_velocity_does_work_and_the_energy_balance_holds():
    """vx = U sin(Ω t) (b = −U sin Ω t): no f at all (a velocity-only system); the force
    m U Ω cos Ω t that keeps it does the work that changes the energy."""
    m, U, W = 1.7, 0.8, 3.0
    system = C.System([C.Particle("p", m, [0.2, 0, 0], [0, 0.5, 0])], [C.Velocity("vx_p - U*sin(W*t)")],
                      [C.Gravity([0, -G, 0])], parameters={"U": U, "W": W})
    t = np.linspace(0.0, 3.0, 3001)
    for method in ("dopri", "projection", "ggl"):
        tr = C.simulate(system, 3.0, method=method, rtol=1e-10, atol=1e-12, t_eval=t)
        np.testing.assert_allclose(tr.x[:, 0, 0], 0.2 + U * (1 - np.cos(W * t)) / W, atol=1e-8)
        np.testing.assert_allclose(tr.multipliers[:, 0], m * U * W * np.cos(W * t), atol=1e-8)
        power = np.sum(tr.constraint_forces[:, 0] * tr.v[:, 0], axis=1)
        work = simpson(power, x=t)
        assert abs(work) > 0.05  # it does work …
        rel = 1e-6 if method == "ggl" else 1e-8  # IDAS's BDF is the least accurate here
        assert tr.energy[-1] - tr.energy[0] == pytest.approx(work, rel=rel)  # … all of it


def test_sleigh_pushed_sideways_by_a_prescribed_slip_gains_what_the_blade_gives():
    """The runner slips sideways at a prescribed s(t): a(x)·v + b(t) = 0, not integrable.
    No other force acts, so dE/dt is the blade's power −μ·b."""
    system = sleigh()
    system.constraints[-1] = C.Velocity("(-vx_P*(y_F - y_P) + vy_P*(x_F - x_P))/0.8 - 0.4*sin(2*t)",
                                        name="slipping runner")
    t = np.linspace(0.0, 4.0, 4001)
    tr = C.simulate(system, 4.0, rtol=1e-11, atol=1e-12, t_eval=t)
    power = np.sum(tr.constraint_forces * tr.v, axis=(1, 2))
    energy = tr.energy - tr.energy[0]
    gained = np.array([simpson(power[:k + 1], x=t[:k + 1]) for k in range(100, len(t), 500)])
    np.testing.assert_allclose(energy[100::500], gained, atol=1e-8 * np.max(np.abs(energy)))
    assert np.max(np.abs(energy)) > 0.01
    # and the power is −μ·b along the run
    b = -0.4 * np.sin(2 * t)
    np.testing.assert_allclose(power, -tr.multipliers[:, -1] * b, atol=1e-9)


# --- the reduced route: Lagrange–d'Alembert in generalized coordinates -------------------------------
def test_cross_check_of_the_sleigh_scene_with_lagrange_dalembert():
    scene = C.load_scene("scenarios/chaplygin_sleigh.toml")
    check = C.cross_check(scene, t_end=4.0)
    assert check.max_position_difference < 1e-7
    assert check.max_velocity_difference < 1e-7
    assert check.max_constraint_force_difference < 1e-6
    assert check.reduced_model.jacobi_integral_conserved()  # the blade does no work


def test_reduced_method_runs_the_lagrange_dalembert_equations():
    scene = C.load_scene("scenarios/chaplygin_sleigh.toml")
    rm = C.ReducedModel.from_scene(scene)
    t = np.linspace(0.0, 2.0, 21)
    a = C.simulate(scene.system, 2.0, rtol=1e-11, atol=1e-12, t_eval=t)
    b = C.simulate(scene.system, 2.0, method="reduced", reduced_model=rm, rtol=1e-11, atol=1e-12, t_eval=t)
    np.testing.assert_allclose(a.x, b.x, atol=1e-8)
    # the multiplier in q is the Cartesian one (the same force: Ãᵀμ = (∂x/∂q)ᵀ Aᵀμ)
    mu_q = float(np.asarray(rm.velocity_multipliers(rm.initial, rm.rates, 0.0)).ravel()[0])
    assert mu_q == pytest.approx(a.multipliers[0, -1], rel=1e-9)


def test_reduced_rates_off_the_constraint_are_brought_onto_it():
    scene = C.load_scene("scenarios/chaplygin_sleigh.toml", ["reduced.rates.Y=0.3"])
    rm = C.ReducedModel.from_scene(scene)
    A = np.array([-math.sin(0.0), math.cos(0.0), 0.0])  # -X' sin th + Y' cos th = 0
    assert abs(A @ rm.rates) < 1e-12
    check = C.cross_check(scene, t_end=1.0)
    assert check.max_position_difference < 1e-7


def test_a_working_velocity_row_is_named_as_why_the_jacobi_integral_changes(tmp_path):
    """L = T − V with no explicit t and no damping: only the belt's b(t) ≠ 0 changes h = T + V
    (here h is the energy: the map is scleronomic), at the rate −μ·b. The cross-check's line
    must name that cause, not only 'L depends on t or non-conservative forces act'."""
    path = tmp_path / "belt.toml"
    path.write_text("""
[[particles]]
name = "p"
mass = 0.07
position = [0.2, 0.1, 0.0]
[[constraints]]
type = "plane"
particles = ["p"]
normal = [0.0, 0.0, 1.0]
[[constraints]]
type = "velocity"
expr = "vx_p + y_p*vy_p - 0.4*sin(2*t)"
[[effects]]
type = "spring"
a = "p"
point = [0.0, 0.0, 0.0]
k = 3.0
rest = 0.0
[simulate]
t_end = 1.0
rtol = 1e-11
atol = 1e-13
[reduced]
coordinates = ["X", "Y"]
initial = { X = 0.2, Y = 0.1 }
map = { p = ["X", "Y", "0"] }
""")
    check = C.cross_check(C.load_scene(path), t_end=1.0)
    assert not check.reduced_model.jacobi_integral_conserved()
    h = check.jacobi_integral
    assert np.max(np.abs(h - h[0])) > 1e-3   # the belt does work
    assert "a velocity constraint does work" in check.jacobi_integral_line()


def test_hand_derived_sleigh_equations_check_with_multipliers():
    scene = C.load_scene("scenarios/chaplygin_sleigh.toml")
    # I th'' = −M a u th', u = X' cos th + Y' sin th (speed of P along the axis); μ eliminated
    M, a, I = 2.0, 0.5, 1.25
    good = f"{I}*th_ddot + {M * a}*(X_dot*cos(th) + Y_dot*sin(th))*th_dot = 0"
    checks = C.check_equations(scene, [good, "th_ddot = 0"])
    assert checks[0].ok and not checks[1].ok
    text = C.describe(scene)
    assert "velocity constraint 1 (multiplier mu1)" in text and "mu1" in text.split("equation for X:")[1]


# --- statics and virtual work -------------------------------------------------------------------------
def test_skate_across_a_slope_is_held_by_its_blade():
    system, down, side, g_t = skate(heading=1.2)  # turned part way: Newton turns it across
    eq = C.equilibrium(system)
    blade = eq.x[2] - eq.x[1]
    assert abs(blade @ down) < 1e-9  # across the slope
    mass = 0.9 + 2 * 0.35
    assert abs(eq.multipliers[-1]) == pytest.approx(mass * g_t, rel=1e-9)  # the blade holds the weight
    assert "hold the system at rest" in eq.velocity_constraints
    assert eq.stable is None  # the energy method does not decide it
    assert eq.virtual_work_residual < 1e-9  # d'Alembert's virtual displacements (A δx = 0)
    assert C.virtual_work(system, eq.x) < 1e-9


def test_skate_pointing_downhill_has_no_equilibrium_and_statics_says_so():
    # along its blade nothing holds the skate: it slides, so there is no rest here; the
    # IPOPT fallback minimizes V on the holonomic rows alone, runs downhill without bound and
    # ends where a distance's gradient is 0/0: that must not crash the search (LinAlgError)
    system, down, _, g_t = skate(heading=0.0)
    with pytest.raises(C.InputError, match="no static equilibrium found"):
        C.equilibrium(system)
    tr = C.simulate(system, 0.5, rtol=1e-10, atol=1e-12, t_eval=[0.0, 0.5])
    assert (tr.x[-1, 0] - tr.x[0, 0]) @ down > 0.1 * g_t * 0.5**2  # it does slide downhill


def test_velocity_constraints_carry_no_force_at_a_holonomic_equilibrium():
    eq = C.equilibrium(sleigh())
    assert eq.multipliers[-1] == 0.0
    assert "no force at this equilibrium" in eq.velocity_constraints
    # a double pendulum whose lower bob rides a runner along the lower rod, hanging straight
    # down: gravity pulls along the runner, so only the rods hold it (a strict minimum of V)
    system = C.System([C.Particle("p", 1.0, [0, -1.0, 0]), C.Particle("q", 2.0, [0, -1.7, 0])],
                      [C.Distance("p", point=[0, 0, 0], length=1.0), C.Distance("p", "q", length=0.7),
                       C.Plane(["p", "q"], [0, 0, 1]), C.KnifeEdge("q", along=["p", "q"], normal=[0, 0, 1])],
                      [C.Gravity([0, -G, 0])])
    eq = C.equilibrium(system)
    assert abs(eq.multipliers[-1]) < 1e-12 and eq.stable is True
    assert -eq.multipliers[0] == pytest.approx(3.0 * G)  # tension −λ: the upper rod carries both weights
    # turned aside, the runner holds the lower bob where the rods alone would not: another
    # equilibrium of the family, found by Newton from there
    moved = system.with_state(np.array([[0.6, -0.8, 0], [0.6 + 0.7 * 0.6, -0.8 - 0.7 * 0.8, 0]]),
                              np.zeros((2, 3)))
    held = C.equilibrium(moved)
    assert "hold the system" in held.velocity_constraints and held.virtual_work_residual < 1e-9


def test_statics_refuses_a_velocity_constraint_that_forbids_rest(capsys, tmp_path):
    system = C.System([C.Particle("p", 1.0, [0, 0, 0])], [C.Velocity("vx_p - 0.5")])
    with pytest.raises(C.InputError, match="does not allow rest"):
        C.equilibrium(system)


# --- what the model says: DOF, rows, refusals -----------------------------------------------------------
def test_dof_counts_configuration_and_velocities_and_names_a_redundant_velocity_row():
    system = sleigh()
    system.add(C.Velocity("vx_P*(y_F - y_P) - vy_P*(x_F - x_P)", name="the same runner again"))
    report = C.constraint_report(system)
    assert C.degrees_of_freedom(system) == report.degrees_of_freedom == 3
    assert report.velocity_degrees_of_freedom == 2
    assert report.redundant == ["the same runner again"]
    t = np.linspace(0.0, 2.0, 21)
    tr = C.simulate(system, 2.0, rtol=1e-10, atol=1e-12, t_eval=t)
    omega, _, _ = sleigh_state(tr)
    np.testing.assert_allclose(omega, sleigh_closed_form(t)[0], atol=1e-8)
    # two rows of one force share it: the least |μ| giving that force is μ ∝ the rows'
    # gradients, 1 (the knife edge, ê·v) and −0.8 (the formula, −L ê·v)
    np.testing.assert_allclose(tr.multipliers[:, -1], -0.8 * tr.multipliers[:, -2], atol=1e-9)


@pytest.mark.parametrize("expr, words", [
    ("vx_p**2 - 1", "not linear in the velocities"),
    ("vx_p*vy_p", "not linear in the velocities"),
    ("x_p - 1", "involves no velocity"),
    # derivative 0 in v, yet not a(x, t)·v + b: the step functions must not pass as linear
    ("sign(vx_p) - 0.5", "not linear in the velocities"),
    ("floor(vx_p)", "not linear in the velocities"),
    ("vy_p + ceil(vx_p)*x_p", "not linear in the velocities"),
])
def test_a_velocity_formula_must_be_linear_in_the_velocities(expr, words):
    system = C.System([C.Particle("p", 1.0, [0, 0, 0], [1, 0, 0])], [C.Velocity(expr)])
    with pytest.raises(C.InputError, match=words):
        C.simulate(system, 1.0)


def test_rattle_refuses_velocity_constraints_with_a_reason():
    with pytest.raises(C.InputError, match="rattle' cannot take velocity constraints: .*no f"):
        C.simulate(sleigh(), 1.0, method="rattle", dt=1e-3)


def test_the_action_principle_is_refused_for_velocity_constraints():
    tr = C.simulate(sleigh(), 1.0, t_eval=np.linspace(0, 1, 11))
    with pytest.raises(C.InputError, match="d'Alembert's principle"):
        C.stationarity(sleigh(), tr)


def test_one_sided_and_velocity_constraints_together_are_refused():
    system = sleigh()
    system.add(C.Plane(["F"], [0, 1, 0], -5.0, unilateral=True))
    with pytest.raises(C.InputError, match="one-sided constraints and velocity constraints"):
        C.simulate(system, 1.0)


SCENE = """\
[[particles]]
name = "p"
mass = 1.0
position = [0, 0, 0]
velocity = [1, 0, 0]

[[particles]]
name = "q"
mass = 1.0
position = [1, 0, 0]

[[constraints]]
type = "distance"
a = "p"
b = "q"
length = 1.0

[[constraints]]
{item}

[simulate]
t_end = 1.0
"""


@pytest.mark.parametrize("item, key, words", [
    ('type = "velocity"\nexpr = "vx_p*vx_p"', "constraints[1].expr", "not linear in the velocities"),
    ('type = "knife_edge"\nparticle = "p"\nacross = ["p", "q"]\nalong = ["p", "q"]', "constraints[1]",
     "exactly one of 'across'"),
    ('type = "knife_edge"\nparticle = "p"\nalong = ["p", "q"]', "constraints[1]", "needs the 'normal'"),
    ('type = "knife_edge"\nparticle = "p"\nacross = ["p"]', "constraints[1].across", "two particle names"),
    ('type = "rolling"\nparticle = "p"\nnormal = [0, 0, 1]\nradius = 0.2', "constraints[1]", "'a' and 'b'"),
    ('type = "rolling"\nparticle = "p"\nnormal = [0, 0, "t"]', "constraints[1].normal", "three numbers"),
    ('type = "velocity"\nexpr = "vx_p"\nunilateral = true', "constraints[1].unilateral", "no gap"),
])
def test_bad_velocity_constraints_in_a_scene_exit_2_naming_the_key(item, key, words, tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(SCENE.format(item=item))
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert key in err and words in err, err


def test_check_prints_the_velocity_rows_and_both_counts(capsys):
    assert main(["check", "scenarios/chaplygin_sleigh.toml"]) == 0
    out = capsys.readouterr().out
    assert "velocity constraints (1 row" in out
    assert "velocity degrees of freedom 2 (configuration: 3)" in out


def test_no_slip_particle_is_a_pivot_reached_at_the_velocity_level():
    """radius 0: the particle itself does not slide on the plane. Integrable (its in-plane
    position stays), so a pendulum hung from a no-slip particle swings as from a pin."""
    L = 0.9
    particles = [C.Particle("o", 5.0, [0, 0, 0]),
                 C.Particle("b", 1.0, [L * math.sin(0.6), -L * math.cos(0.6), 0])]
    base = [C.Distance("o", "b", length=L), C.Plane(["b"], [0, 0, 1])]
    pinned = C.System(particles, [*base, C.Pin("o", [0, 0, 0])], [C.Gravity([0, -G, 0])])
    rolling = C.System(particles, [*base, C.Plane(["o"], [0, 0, 1]), C.Plane(["o"], [0, 1, 0]),
                                   C.Rolling("o", normal=[0, 1, 0])], [C.Gravity([0, -G, 0])])
    t = np.linspace(0.0, 3.0, 31)
    a = C.simulate(pinned, 3.0, rtol=1e-10, atol=1e-12, t_eval=t)
    b = C.simulate(rolling, 3.0, rtol=1e-10, atol=1e-12, t_eval=t)
    np.testing.assert_allclose(b.x, a.x, atol=1e-9)
    # the same force holds the pivot: the rows differ, the sum Jᵀλ does not
    np.testing.assert_allclose(b.constraint_forces, a.constraint_forces, atol=1e-7)


def test_rows_of_f_come_first_whatever_the_scene_order():
    system = sleigh()
    blade = system.constraints.pop()
    system.constraints.insert(0, blade)  # the knife edge listed first
    tr = C.simulate(system, 1.0, rtol=1e-10, atol=1e-12, t_eval=[0.0, 0.5, 1.0])
    assert tr.constraint_labels[-1] == blade.label  # its multiplier is the last column
    ref = C.simulate(sleigh(), 1.0, rtol=1e-10, atol=1e-12, t_eval=[0.0, 0.5, 1.0])
    np.testing.assert_allclose(tr.multipliers, ref.multipliers, atol=1e-10)


def test_the_sleigh_scene_runs_other_parameter_values_on_the_same_structure():
    from constrained.model.structure import Structure

    scene = C.load_scene("scenarios/chaplygin_sleigh.toml")
    scene.run(["simulate.t_end=1"])
    builds = Structure.builds
    result = scene.run(["simulate.t_end=2", "parameters.W0=3.0", "parameters.mS=0.8"])
    assert result.ok, result.report()
    assert Structure.builds == builds


def test_noether_charges_of_a_sleigh_are_those_its_runner_allows():
    """Translations and rotations leave L and every row unchanged, but d/dt(p·ξ) = μ·(A ξ):
    the runner pushes across, so neither momentum nor angular momentum is conserved, and
    is_symmetry names the runner; the energy is the integral that survives (b = 0)."""
    system = sleigh()
    for kind in ({"translation": [1, 0, 0]}, {"rotation": ([0, 0, 1], [0, 0, 0])}):
        report = C.is_symmetry(system, **kind)
        assert not report.holds
        assert report.breaking == ["constraint 2 (knife edge P (blade P→F, normal (0, 0, 1)))"]
    # the same translation without the runner is a symmetry
    free = C.System(system.particles, system.constraints[:2])
    assert C.is_symmetry(free, translation=[1, 0, 0]).holds
    tr = C.simulate(system, 3.0, rtol=1e-10, atol=1e-12, t_eval=np.linspace(0, 3, 31))
    momentum = np.sum(np.array([1.0, 2.3])[None, :, None] * tr.v, axis=1)
    assert np.ptp(momentum[:, 0]) > 0.01
    assert np.ptp(tr.energy) < 1e-9


def test_cyclic_coordinates_of_the_sleigh_are_not_conserved_where_the_runner_acts():
    scene = C.load_scene("scenarios/chaplygin_sleigh.toml")
    found = C.conservation(scene)
    # X and Y are absent from L, but the runner acts on both: their momenta are not conserved
    assert set(found.structurally_cyclic) == {"X", "Y"}
    assert found.cyclic == []
    assert found.jacobi_integral_conserved  # the runner does no work


@pytest.mark.slow
def test_sleigh_viewer_page_works_in_chromium(tmp_path):
    from test_viewer import CHROMIUM, IN_CI, selftest

    if CHROMIUM is None:
        if IN_CI:
            pytest.fail("chromium is not installed: the viewer tests need it in CI")
        pytest.skip("no chromium on this machine (the viewer's browser tests run in CI)")
    assert main(["run", "scenarios/chaplygin_sleigh.toml", "--out", str(tmp_path), "--set",
                 "simulate.t_end=2", "--set", 'outputs.plots=["viewer"]', "--quiet"]) == 0
    report = selftest(CHROMIUM, tmp_path / "viewer.html")
    assert report["errors"] == [], report
    assert report["particles"] == 3 and report["constraints"] == 5  # plane, three rods, the runner (listed)
    assert report["start"]["ink"] > 1000 and report["slider_changes_picture"]
    assert report["multiplier_choice_changes_panel"] and report["forces_toggle_changes_picture"]


def test_a_turning_constraint_with_b_zero_does_no_work():
    """v · e(t) = 0 with e(t) = (cos Ωt, sin Ωt, 0): rheonomic, but b = 0, so its force does no
    work (power −μ·b): the speed stays V and the particle runs round a circle of radius V/Ω."""
    m, V, W = 0.013, 0.04, 2.5  # grams and centimetres
    system = C.System([C.Particle("p", m, [0.01, 0.02, 0], [0, V, 0])],
                      [C.Plane("p", [0, 0, 1]), C.Velocity(f"vx_p*cos({W}*t) + vy_p*sin({W}*t)")])
    t = np.linspace(0.0, 4.0, 81)
    for method in ("dopri", "idas"):
        tr = C.simulate(system, 4.0, method=method, rtol=1e-10, atol=1e-13, t_eval=t)
        np.testing.assert_allclose(tr.x[:, 0, 0], 0.01 + V / W * (np.cos(W * t) - 1), atol=1e-10)
        np.testing.assert_allclose(tr.x[:, 0, 1], 0.02 + V / W * np.sin(W * t), atol=1e-10)
        np.testing.assert_allclose(np.linalg.norm(tr.v[:, 0], axis=1), V, rtol=1e-8)
        # the force is the centripetal m V Ω, across the velocity
        np.testing.assert_allclose(np.abs(tr.multipliers[:, -1]), m * V * W, rtol=1e-6)


def test_gram_and_centimetre_sleigh_follows_the_closed_form():
    scale = dict(mP=0.002, mF=0.0035, L=0.012, v0=0.003, w0=0.4)
    t = np.linspace(0.0, 5.0, 51)
    tr = C.simulate(sleigh(**scale), 5.0, rtol=1e-10, atol=1e-14, t_eval=t)
    omega, speed, heading = sleigh_state(tr, scale["L"])
    omega_ref, speed_ref, heading_ref = sleigh_closed_form(t, **scale)
    np.testing.assert_allclose(omega, omega_ref, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(speed, speed_ref, rtol=1e-7, atol=1e-11)
    np.testing.assert_allclose(heading, heading_ref, atol=1e-8)


def test_simulate_many_runs_velocity_constraints_in_one_mapped_loop():
    system = C.System([C.Particle("p", 1.0, [0.2, 0, 0], [0, 0.5, 0])], [C.Velocity("vx_p - U*sin(W*t)")],
                      [C.Gravity([0, -G, 0])], parameters={"U": 0.8, "W": 3.0})
    U = np.array([0.1, 0.5, 0.8])
    t = np.linspace(0.0, 1.0, 11)
    many = C.simulate_many(system, 1.0, {"U": U}, t_eval=t, rtol=1e-10, atol=1e-12)
    assert all(s == "completed" for s in many.status)
    np.testing.assert_allclose(many.x[:, :, 0, 0], 0.2 + np.outer(U, 1 - np.cos(3.0 * t)) / 3.0, atol=1e-9)


def test_an_event_on_the_sleighs_heading_lands_at_the_closed_form_instant():
    """θ(t) = √(I/M)/a (gd(k t + c0) − gd(c0)) reaches 1 rad at t = (gd⁻¹(gd(c0) + a √(M/I)) − c0)/k,
    gd⁻¹(y) = asinh(tan y)."""
    scene = C.load_scene("scenarios/chaplygin_sleigh.toml")
    M, a, I, v0, W0 = 2.0, 0.5, 1.25, 0.5, 2.0
    V = math.sqrt((M * v0**2 + I * W0**2) / M)
    k, c0 = a * M * V / I, math.atanh(v0 / V)
    expected = (math.asinh(math.tan(math.atan(math.sinh(c0)) + a * math.sqrt(M / I))) - c0) / k

    def heading(t, x, v):
        return math.atan2((x[4] + x[7]) / 2 - x[1], (x[3] + x[6]) / 2 - x[0]) - 1.0

    for method in ("dopri", "projection"):
        tr = C.simulate(scene.system, 8.0, method=method, rtol=1e-10, atol=1e-12,
                        events=[C.Event("turned 1 rad", heading, direction=1)])
        assert tr.info["stop"] == "terminal event"
        assert tr.t[-1] == pytest.approx(expected, abs=1e-9)


def test_normal_modes_keep_to_the_motions_the_runner_allows():
    """A double pendulum hanging down whose lower bob q rides a runner along the lower rod:
    to first order q cannot move sideways, so one mode is left, the upper bob swinging with
    ω² = g (m_p + m_q)/(m_p l1) + g m_q/(m_p l2) (the potential's curvature over m_p alone)."""
    mp, mq, l1, l2 = 1.0, 2.0, 1.0, 0.7
    system = C.System([C.Particle("p", mp, [0, -l1, 0]), C.Particle("q", mq, [0, -l1 - l2, 0])],
                      [C.Distance("p", point=[0, 0, 0], length=l1), C.Distance("p", "q", length=l2),
                       C.Plane(["p", "q"], [0, 0, 1]), C.KnifeEdge("q", along=["p", "q"], normal=[0, 0, 1])],
                      [C.Gravity([0, -G, 0])])
    expected = math.sqrt(G * (mp + mq) / (mp * l1) + G * mq / (mp * l2))
    for found in (C.modes(system), C.modes(system, x=system.positions, refine=True)):
        assert found.degrees_of_freedom == 1
        assert found.frequencies[0] == pytest.approx(expected, rel=1e-9)
