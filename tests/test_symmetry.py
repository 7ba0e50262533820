"""Noether charges of declared symmetries, and invariances of Lagrange's equations:
point transformations, adding a total time derivative, gauge transformations."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from conftest import double_pendulum

import constrained as C
from constrained.analysis.symmetry import (
    charge_drift,
    euler_lagrange,
    is_symmetry,
    is_symmetry_reduced,
    noether_charge,
    noether_charge_reduced,
    with_total_derivative,
)

TIGHT = {"rtol": 1e-11, "atol": 1e-12}
ORIGIN = [0.0, 0.0, 0.0]
TH0, VY0 = 0.8, 1.5  # spherical pendulum start: polar angle from −z, tangential speed along y


def spherical_pendulum() -> C.System:
    """Unit rod to the origin, gravity along −z, started tangentially (a conical-ish orbit)."""
    s = C.System(name="spherical pendulum")
    s.add_particle("bob", 1.0, [np.sin(TH0), 0.0, -np.cos(TH0)], [0.0, VY0, 0.0])
    s.add(C.Distance("bob", point=ORIGIN, length=1.0), C.Gravity([0.0, 0.0, -9.81]))
    return s


@pytest.fixture(scope="module")
def pendulum_run():
    system = spherical_pendulum()
    model = C.assemble(system)
    traj = C.simulate(system, 5.0, model=model, t_eval=np.linspace(0, 5, 201), **TIGHT)
    return model, traj


# --- Cartesian route ---------------------------------------------------------------------------


def test_spherical_pendulum_rotation_about_z_conserved_about_x_not(pendulum_run):
    model, traj = pendulum_run
    about_z = ([0, 0, 1], ORIGIN)
    report = is_symmetry(model, rotation=about_z)
    assert report.holds, report.message
    Lz = noether_charge(model, traj, rotation=about_z)
    x, v = traj.x[:, 0], traj.v[:, 0]
    assert np.allclose(Lz, x[:, 0] * v[:, 1] - x[:, 1] * v[:, 0], rtol=0, atol=1e-14)  # m (r × v)_z
    assert Lz[0] == pytest.approx(np.sin(TH0) * VY0, rel=1e-12)
    assert charge_drift(Lz) < 1e-9

    about_x = ([2, 0, 0], ORIGIN)  # the axis is normalized
    report = is_symmetry(model, rotation=about_x)
    assert not report.holds
    assert len(report.breaking) == 1 and report.breaking[0].startswith("potential 'gravity")
    assert "gravity" in report.message and "not a symmetry" in report.message
    assert not any(b.startswith("constraint") for b in report.breaking)  # the rod is round
    Lx = noether_charge(model, traj, rotation=about_x)
    assert np.allclose(Lx, x[:, 1] * v[:, 2] - x[:, 2] * v[:, 1], atol=1e-14)
    assert charge_drift(Lx) > 0.3  # order 1


def test_spherical_pendulum_rotation_about_an_offset_axis_is_broken_by_the_rod():
    report = is_symmetry(spherical_pendulum(), rotation=([0, 0, 1], [0.5, 0.0, 0.0]))
    assert not report.holds
    assert report.breaking == [next(k for k in report.changes if k.startswith("constraint 0"))]


def tetrahedron() -> C.System:
    s = C.System(name="free tetrahedron")
    pts = np.array([[1.0, 0.0, 0.0], [-0.5, 0.8, 0.1], [-0.4, -0.9, 0.0], [0.1, 0.05, 1.2]])
    vel = np.array([[0.3, 1.0, -0.2], [-0.5, 0.2, 0.4], [0.7, -0.3, 0.1], [0.2, 1.5, -0.9]])
    masses = [1.0, 2.0, 1.5, 0.7]
    names = ["a", "b", "c", "d"]
    for n, m, p, v in zip(names, masses, pts, vel, strict=True):
        s.add_particle(n, m, p, v)
    for i in range(4):
        for j in range(i + 1, 4):
            s.add(C.Distance(names[i], names[j], length=float(np.linalg.norm(pts[i] - pts[j]))))
    return s


def test_free_rigid_body_momentum_and_angular_momentum():
    system = tetrahedron()
    model = C.assemble(system)
    traj = C.simulate(system, 4.0, model=model, t_eval=np.linspace(0, 4, 161), **TIGHT)
    m = system.masses[None, :, None]
    P = np.sum(m * traj.v, axis=1)
    Lang = np.sum(np.cross(traj.x, m * traj.v), axis=1)
    assert np.max(traj.constraint_residual) < 1e-10
    for k, e in enumerate(np.eye(3)):
        assert is_symmetry(model, translation=e).holds
        assert is_symmetry(model, rotation=(e, ORIGIN)).holds
        Pk = noether_charge(model, traj, translation=e)
        Lk = noether_charge(model, traj, rotation=(e, ORIGIN))
        assert np.allclose(Pk, P[:, k], atol=1e-13) and np.allclose(Lk, Lang[:, k], atol=1e-13)
        assert charge_drift(Pk) < 1e-9, (k, charge_drift(Pk))
        assert charge_drift(Lk) < 1e-9, (k, charge_drift(Lk))
    # the body does rotate: the individual particles' angular momenta change by order 1
    La = np.cross(traj.x[:, 0], system.masses[0] * traj.v[:, 0])[:, 2]
    assert charge_drift(La) > 0.1


B0, CHARGE, MASS = 2.0, 0.5, 1.3
A_SYMMETRIC = [f"-{B0}*y/2", f"{B0}*x/2", "0"]


def charged_particle(phi="0", A=A_SYMMETRIC, x0=(1.0, 0.4, 0.0), v0=(0.2, 0.9, 0.1)) -> C.System:
    s = C.System(name="charge in B")
    s.add_particle("e", MASS, list(x0), list(v0))
    s.add(C.Electromagnetic({"e": CHARGE}, phi=phi, A=A))
    return s


def test_charge_in_uniform_B_canonical_angular_momentum():
    system = charged_particle()
    model = C.assemble(system)
    traj = C.simulate(system, 6.0, model=model, t_eval=np.linspace(0, 6, 241), **TIGHT)
    about_z = ([0, 0, 1], ORIGIN)
    assert is_symmetry(model, rotation=about_z).holds
    x, y = traj.x[:, 0, 0], traj.x[:, 0, 1]
    vx, vy = traj.v[:, 0, 0], traj.v[:, 0, 1]
    kinetic = MASS * (x * vy - y * vx)
    canonical = kinetic + CHARGE * (x * (B0 * x / 2) - y * (-B0 * y / 2))
    Q = noether_charge(model, traj, rotation=about_z)
    assert np.allclose(Q, canonical, atol=1e-13)
    assert charge_drift(Q) < 1e-9
    assert charge_drift(kinetic) > 0.1  # the orbit is not centred on the axis
    # rotation about x is broken by the field (a generalized potential), named as such
    report = is_symmetry(model, rotation=([1, 0, 0], ORIGIN))
    assert not report.holds and report.breaking[0].startswith("generalized potential")


def test_damping_breaks_the_symmetry_and_the_charge_decays():
    system = spherical_pendulum()
    system.add(C.Damping(0.3))
    report = is_symmetry(system, rotation=([0, 0, 1], ORIGIN))
    assert not report.holds and any(b.startswith("dissipation") for b in report.breaking)
    traj = C.simulate(system, 2.0, t_eval=np.linspace(0, 2, 21), **TIGHT)
    Lz = noether_charge(system, traj, rotation=([0, 0, 1], ORIGIN))
    assert Lz[-1] < 0.7 * Lz[0]


def test_declaring_nothing_is_an_input_error():
    with pytest.raises(C.InputError, match="declare a symmetry"):
        is_symmetry(spherical_pendulum())
    with pytest.raises(C.InputError, match="rotation axis"):
        is_symmetry(spherical_pendulum(), rotation=([0, 0, 0], ORIGIN))


def test_charge_drift():
    assert charge_drift([2.0, 2.0, 1.0]) == pytest.approx(0.5)
    assert charge_drift([]) == 0.0


# --- reduced route ---------------------------------------------------------------------------


def spherical_reduced() -> C.ReducedModel:
    phi_dot0 = VY0 / np.sin(TH0)  # ẏ = sin θ cos φ φ̇ at φ = 0
    return C.ReducedModel(
        spherical_pendulum(), ["th", "ph"],
        {"bob": ["sin(th)*cos(ph)", "sin(th)*sin(ph)", "-cos(th)"]},
        initial={"th": TH0, "ph": 0.0}, rates={"th": 0.0, "ph": phi_dot0},
    )


def test_reduced_spherical_pendulum_charge_equals_cartesian(pendulum_run):
    model, cart = pendulum_run
    rm = spherical_reduced()
    assert is_symmetry_reduced(rm, ["0", "1"]).holds
    shift_th = is_symmetry_reduced(rm, ["1", "0"])
    assert not shift_th.holds and "V" in shift_th.breaking
    red = rm.solve(5.0, t_eval=cart.t, outputs=(), **TIGHT)
    Q = noether_charge_reduced(rm, red, ["0", "1"])
    assert charge_drift(Q) < 1e-9
    Qc = noether_charge(model, cart, rotation=([0, 0, 1], ORIGIN))
    assert np.max(np.abs(Q - Qc)) < 1e-8
    # the same from explicit arrays; p_φ = m sin²θ φ̇
    q, qd = red.info["q"], red.info["q_dot"]
    Q2 = noether_charge_reduced(rm, (q, qd, red.t), [0, 1])
    assert np.allclose(Q2, np.sin(q[:, 0]) ** 2 * qd[:, 1], atol=1e-14)


# --- invariances ---------------------------------------------------------------------------------


def test_point_transformation_absolute_and_relative_angles_agree():
    th1, th2 = 0.3, -0.2
    system = double_pendulum(th1, th2)
    absolute = C.ReducedModel(
        system, ["th1", "th2"],
        {"p1": ["sin(th1)", "-cos(th1)", "0"], "p2": ["sin(th1) + sin(th2)", "-cos(th1) - cos(th2)", "0"]},
        initial={"th1": th1, "th2": th2},
    )
    relative = C.ReducedModel(
        system, ["al", "be"],
        {"p1": ["sin(al)", "-cos(al)", "0"],
         "p2": ["sin(al) + sin(al + be)", "-cos(al) - cos(al + be)", "0"]},
        initial={"al": th1, "be": th2 - th1},
    )
    grid = np.linspace(0, 5, 251)
    a = absolute.solve(5.0, t_eval=grid, outputs=(), **TIGHT)
    b = relative.solve(5.0, t_eval=grid, outputs=(), **TIGHT)
    assert np.max(np.abs(a.x - b.x)) < 1e-8
    assert np.max(np.abs(a.x[-1] - a.x[0])) > 0.1  # it moved
    # the Lagrangians agree as functions under the substitution (a scalar under point maps)
    rng = np.random.default_rng(3)
    for _ in range(10):
        al, be, ald, bed = rng.uniform(-2, 2, 4)
        La = float(absolute.lagrangian([al, al + be], [ald, ald + bed], 0.0))
        Lb = float(relative.lagrangian([al, be], [ald, bed], 0.0))
        assert La == pytest.approx(Lb, rel=1e-13, abs=1e-13)


def test_adding_a_total_time_derivative_leaves_the_equations_unchanged():
    rm = spherical_reduced()
    L = rm.lagrangian
    Lt = with_total_derivative(rm, "sin(th)*ph*t + 0.3*th**2*cos(ph) + t**3*ph")
    E, Et = euler_lagrange(L, 2), euler_lagrange(Lt, 2)
    rng = np.random.default_rng(7)
    worst, moved = 0.0, 0.0
    for _ in range(30):
        q, qd, qdd = rng.uniform(0.2, 1.4, 2), rng.normal(size=2), rng.normal(size=2)
        t = rng.uniform(0, 3)
        worst = max(worst, float(np.max(np.abs(np.asarray(E(q, qd, qdd, t) - Et(q, qd, qdd, t))))))
        moved = max(moved, abs(float(Lt(q, qd, t)) - float(L(q, qd, t))))
        # E(L) is the ReducedModel's own Lagrange residual M q̈ − rhs
        assert np.allclose(np.asarray(E(q, qd, qdd, t)), np.asarray(rm.lagrange_residual(q, qd, qdd, t)),
                           atol=1e-12)
    assert worst < 1e-10
    assert moved > 0.1  # the Lagrangians themselves differ
    # a term that is not a total derivative does change the equations
    q, qd = ca.SX.sym("q", 2), ca.SX.sym("qd", 2)
    t = ca.SX.sym("t")
    bad = ca.Function("L_bad", [q, qd, t], [L(q, qd, t) + q[0] ** 2 * qd[1] ** 2])
    x = ([0.7, 0.2], [0.3, -0.4], [0.1, 0.2], 0.5)
    assert float(ca.norm_inf(euler_lagrange(bad, 2)(*x) - E(*x))) > 1e-3


def test_gauge_transformation_leaves_the_motion_unchanged():
    # λ = 0.3 x y t + 0.1 z²:  ∇λ = (0.3 y t, 0.3 x t, 0.2 z),  ∂λ/∂t = 0.3 x y
    phi = "-0.2*x"  # a weak uniform E = 0.2 x̂ besides the uniform B along z
    phi_gauged = "-0.2*x - 0.3*x*y"
    A_gauged = [f"-{B0}*y/2 + 0.3*y*t", f"{B0}*x/2 + 0.3*x*t", "0.2*z"]
    kw = {"x0": (1.0, 0.4, 0.3), "v0": (0.2, 0.9, 0.4)}
    one, two = charged_particle(phi, **kw), charged_particle(phi_gauged, A_gauged, **kw)
    grid = np.linspace(0, 4, 161)
    a = C.simulate(one, 4.0, t_eval=grid, **TIGHT)
    b = C.simulate(two, 4.0, t_eval=grid, **TIGHT)
    assert np.max(np.abs(a.x - b.x)) < 1e-9 and np.max(np.abs(a.v - b.v)) < 1e-9
    assert np.max(np.abs(a.x[-1] - a.x[0])) > 0.5  # it moved (and drifted in E × B)
    # canonical momenta differ by q ∇λ: the x component by q · 0.3 y t
    px_a = noether_charge(one, a, translation=[1, 0, 0])
    px_b = noether_charge(two, b, translation=[1, 0, 0])
    assert np.allclose(px_b - px_a, CHARGE * 0.3 * a.x[:, 0, 1] * a.t, atol=1e-9)
    assert np.max(np.abs(px_b - px_a)) > 0.1
    # the energy function h = T + qφ is gauge dependent too: differs by −q ∂λ/∂t
    assert np.allclose(b.energy - a.energy, -CHARGE * 0.3 * a.x[:, 0, 0] * a.x[:, 0, 1], atol=1e-9)
