"""Issue 2 acceptance: the core pipeline against closed-form physics and conservation laws."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from conftest import DP_ENERGY, DP_REF_T2, double_pendulum, planar_pendulum
from scipy.integrate import simpson

import constrained as C
from constrained.manifold.constraint_report import SingularConfigurationWarning
from constrained.manifold.dense import schur_solve


def test_simple_pendulum_tension_follows_closed_form():
    m, l, g = 1.3, 0.8, 9.81
    s = planar_pendulum(1.2, 0.5, m=m, l=l, g=g)
    assert C.degrees_of_freedom(s) == 1
    tr = C.simulate(s, 3.0, rtol=1e-10, atol=1e-12, t_eval=np.linspace(0, 3, 301))
    x, v = tr.x[:, 0], tr.v[:, 0]
    cos_theta = -x[:, 1] / l
    expected = m * g * cos_theta + m * np.sum(v**2, axis=1) / l
    tension = -tr.multipliers[:, 0]  # λ is the force along the outward direction
    np.testing.assert_allclose(tension, expected, rtol=1e-6)
    # the force on the bob is the tension along the rod, pointing to the pivot
    np.testing.assert_allclose(tr.constraint_forces[:, 0, :2],
                               -(tension / l)[:, None] * x[:, :2],
                               atol=1e-6 * m * g)


def test_small_amplitude_period_is_two_pi_root_l_over_g():
    l, g = 2.0, 9.81
    s = planar_pendulum(0.01, m=0.5, l=l, g=g)
    period = 2 * np.pi * np.sqrt(l / g)
    t = np.linspace(0, 5 * period, 4001)
    tr = C.simulate(s, t[-1], rtol=1e-11, atol=1e-13, t_eval=t)
    xs = tr.x[:, 0, 0]
    k = np.nonzero((xs[:-1] < 0) & (xs[1:] >= 0))[0]  # upward zero crossings
    crossings = t[k] - xs[k] * (t[k + 1] - t[k]) / (xs[k + 1] - xs[k])
    measured = np.mean(np.diff(crossings))
    assert len(crossings) >= 4
    assert abs(measured / period - 1) < 1e-4


def test_spring_of_the_theory_text_is_a_harmonic_oscillator():
    m, k, A, delta = 0.7, 5.0, 0.3, 0.4
    w = np.sqrt(k / m)
    s = C.System()
    s.add_particle("m", m, [A * np.cos(-delta), 0, 0], [A * w * np.sin(delta), 0, 0])
    s.add(C.Spring("m", point=[0, 0, 0], k=k), C.Plane("m", [0, 1, 0]), C.Plane("m", [0, 0, 1]))
    assert C.degrees_of_freedom(s) == 1
    t = np.linspace(0, 6, 601)
    tr = C.simulate(s, 6.0, rtol=1e-11, atol=1e-12, t_eval=t)
    np.testing.assert_allclose(tr.x[:, 0, 0], A * np.cos(w * t - delta), atol=1e-7)
    np.testing.assert_allclose(tr.x[:, 0, 1:], 0, atol=1e-12)


def rigid_body(points, masses, pairs) -> C.System:
    s = C.System(name="rigid body")
    for i, (p, mass) in enumerate(zip(points, masses, strict=True)):
        s.add_particle(f"p{i}", mass, p)
    for i, j in pairs:
        s.add(C.Distance(f"p{i}", f"p{j}", length=float(np.linalg.norm(points[i] - points[j]))))
    return s


def test_rigid_tetrahedron_has_six_degrees_of_freedom():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0.5, 0.9, 0], [0.4, 0.3, 0.8]], float)
    s = rigid_body(pts, [1, 2, 3, 4], itertools.combinations(range(4), 2))
    report = C.constraint_report(s)
    assert report.degrees_of_freedom == 6 and not report.redundant and not report.singular
    assert C.degrees_of_freedom(s) == 6


def test_coplanar_tetrahedron_is_reported_singular():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1.2, 0]], float)
    s = rigid_body(pts, [1, 1, 1, 1], itertools.combinations(range(4), 2))
    with pytest.warns(SingularConfigurationWarning, match="overstates"):
        assert C.degrees_of_freedom(s) == 7
    report = C.constraint_report(s)
    assert report.singular and report.generic_degrees_of_freedom == 6


def spinning_cube():
    pts = np.array(list(itertools.product([-0.5, 0.5], repeat=3)), float)
    masses = np.array([1.0, 2.0, 1.5, 1.0, 0.5, 1.0, 3.0, 1.0])
    s = rigid_body(pts, masses, itertools.combinations(range(8), 2))
    com = masses @ pts / masses.sum()
    omega = np.array([0.3, 4.0, 1.0])
    vel = np.cross(omega, pts - com) + np.array([0.2, 1.0, 0.0])
    for p, v in zip(s.particles, vel, strict=True):
        p.velocity = v
    s.add(C.Gravity([0, 0, -9.81]))
    return s, masses


def test_cube_with_all_28_distances_is_rigid_and_redundant():
    s, _ = spinning_cube()
    report = C.constraint_report(s)
    assert report.n_constraints == 28 and report.rank == 18
    assert report.degrees_of_freedom == 6 and not report.singular
    assert len(report.redundant) == 10  # 28 rows, 18 independent


def test_spinning_cube_keeps_its_shape_and_angular_momentum():
    s, masses = spinning_cube()
    tr = C.simulate(s, 2.0, rtol=1e-10, atol=1e-12, t_eval=np.linspace(0, 2, 101))
    x0 = s.positions
    for i, j in itertools.combinations(range(8), 2):
        d = np.linalg.norm(tr.x[:, i] - tr.x[:, j], axis=1)
        np.testing.assert_allclose(d, np.linalg.norm(x0[i] - x0[j]), atol=1e-9)
    com = np.einsum("n,tnk->tk", masses, tr.x) / masses.sum()
    vcom = np.einsum("n,tnk->tk", masses, tr.v) / masses.sum()
    L = np.einsum("n,tnk->tk", masses, np.cross(tr.x - com[:, None], tr.v - vcom[:, None]))
    assert np.max(np.linalg.norm(L - L[0], axis=1)) <= 1e-8 * np.linalg.norm(L[0])
    # free fall of the centre of mass
    np.testing.assert_allclose(com[:, 2] - com[0, 2],
                               vcom[0, 2] * tr.t - 0.5 * 9.81 * tr.t**2, atol=1e-8)
    # redundant set: minimum-norm multipliers, and constraint forces sum to zero (internal)
    np.testing.assert_allclose(tr.constraint_forces.sum(axis=1), 0, atol=1e-8)


def test_double_pendulum_matches_reference_and_conserves_energy():
    tr = C.simulate(double_pendulum(), 2.0, rtol=1e-12, atol=1e-12, t_eval=[0.0, 1.0, 2.0])
    assert np.max(np.abs(tr.x[-1, :, :2] - DP_REF_T2)) <= 1e-9
    tr = C.simulate(double_pendulum(), 10.0, rtol=1e-10, atol=1e-10)
    assert np.max(np.abs(tr.energy / DP_ENERGY - 1)) <= 1e-8
    assert np.max(tr.constraint_residual) <= 1e-10
    assert np.max(tr.velocity_residual) <= 1e-10
    # scleronomic constraints do no work
    power = np.einsum("tnk,tnk->t", tr.constraint_forces, tr.v)
    assert np.max(np.abs(power)) <= 1e-8


def test_driven_pivot_constraint_forces_do_work_and_balance_energy():
    a, w = 0.2, 3.0
    s = C.System(name="driven pivot")
    s.add_particle("bob", 1.0, [np.sin(0.5), -np.cos(0.5), 0.0])
    s.add(C.Distance("bob", point=[f"{a}*sin({w}*t)", "0", "0"], length=1.0),
          C.Plane("bob", [0, 0, 1]), C.Gravity([0, -9.81, 0]))
    model = C.assemble(s)
    assert "rheonomic" in model.active_terms
    t = np.linspace(0, 4, 4001)
    tr = C.simulate(s, 4.0, rtol=1e-11, atol=1e-12, t_eval=t)
    # the start: the anchor moves at a·w, and the bob's velocity is projected to match
    assert tr.info["initial_correction"]["velocity"] > 0.1 * a * w
    power = np.einsum("tnk,tnk->t", tr.constraint_forces, tr.v)
    assert np.max(np.abs(power)) > 0.1  # a moving constraint does work
    work = np.array([simpson(power[: k + 1], x=t[: k + 1]) if k > 1 else 0.0
                     for k in range(0, len(t), 400)])
    np.testing.assert_allclose(tr.energy[::400] - tr.energy[0], work, atol=1e-6)
    assert np.max(tr.constraint_residual) <= 1e-10


def charged_particle(B0=2.0, E0=0.0, q=1.5, m=0.5, v0=(1.0, 0.0, 0.3)):
    s = C.System(name="charged particle")
    s.add_particle("ion", m, [0, 0, 0], v0)
    s.add(C.Electromagnetic({"ion": q}, phi=f"-{E0}*y", A=[f"-{B0}*y/2", f"{B0}*x/2", "0"]))
    return s


def test_cyclotron_frequency_and_radius():
    B0, q, m, v = 2.0, 1.5, 0.5, 1.0
    w = q * B0 / m
    r = m * v / (q * B0)
    t = np.linspace(0, 3, 301)
    tr = C.simulate(charged_particle(B0, 0.0, q, m, (v, 0, 0.3)), 3.0, rtol=1e-12, atol=1e-13, t_eval=t)
    x = tr.x[:, 0]
    # v × B with B along +z turns a +x velocity towards −y: centre at (0, −r)
    np.testing.assert_allclose(x[:, 0], r * np.sin(w * t), atol=1e-8 * r)
    np.testing.assert_allclose(x[:, 1], -r * (1 - np.cos(w * t)), atol=1e-8 * r)
    np.testing.assert_allclose(x[:, 2], 0.3 * t, atol=1e-10)
    radius = np.hypot(x[:, 0], x[:, 1] + r)
    assert np.max(np.abs(radius / r - 1)) <= 1e-8
    # the magnetic force does no work: energy (T + qφ) constant
    assert np.max(np.abs(tr.energy / tr.energy[0] - 1)) <= 1e-10


def test_e_cross_b_drift():
    B0, E0, q, m = 2.0, 0.8, 1.5, 0.5
    period = 2 * np.pi * m / (q * B0)
    tr = C.simulate(charged_particle(B0, E0, q, m, (0, 0, 0)), 3 * period, rtol=1e-12, atol=1e-13,
                    t_eval=[0, period, 2 * period, 3 * period])
    # from rest, a cycloid: after each cyclotron period the particle has moved (E/B)·T along E × B
    drift = (tr.x[1:, 0] - tr.x[:-1, 0]) / period
    np.testing.assert_allclose(drift[:, 0], E0 / B0, rtol=1e-8)
    np.testing.assert_allclose(drift[:, 1:], 0, atol=1e-8 * E0 / B0)


def test_damped_hanging_spring_matches_closed_form():
    m, k, b, g = 1.0, 4.0, 0.6, 9.81  # x measured downward: m x'' + b x' + k x = m g
    s = C.System()
    s.add_particle("m", m, [0, 0, 0])
    s.add(C.Spring("m", point=[0, 0, 0], k=k), C.Damping(b, "m"), C.Gravity([g, 0, 0]),
          C.Plane("m", [0, 1, 0]), C.Plane("m", [0, 0, 1]))
    model = C.assemble(s)
    assert "dissipation" in model.active_terms
    t = np.linspace(0, 5, 101)
    tr = C.simulate(s, 5.0, rtol=1e-11, atol=1e-12, t_eval=t, model=model)
    xe = m * g / k
    wd = np.sqrt(k / m - (b / (2 * m)) ** 2)
    decay = np.exp(-b * t / (2 * m))
    expected = -xe * decay * (np.cos(wd * t) + b / (2 * m * wd) * np.sin(wd * t)) + xe
    np.testing.assert_allclose(tr.x[:, 0, 0], expected, atol=1e-8)
    assert np.all(np.diff(tr.energy) <= 1e-12)  # damping only removes energy


def test_model_assembles_only_the_terms_a_scene_names():
    dp = C.assemble(double_pendulum())
    assert dp.active_terms == frozenset({"constraints", "potential"})
    assert not dp.rheonomic
    # scleronomic: the time-derivative terms are structurally zero (never evaluated)
    assert dp.velocity_terms.sparsity_out(1).nnz() == 0
    free = C.System()
    free.add_particle("p", 1.0, [0, 0, 0], [1, 0, 0])
    free_model = C.assemble(free)
    assert free_model.active_terms == frozenset()
    tr = C.simulate(free, 1.0, t_eval=[0, 1])
    np.testing.assert_allclose(tr.x[-1, 0], [1, 0, 0], atol=1e-12)


def test_inconsistent_start_is_projected_and_reported():
    s = planar_pendulum(0.7)
    s.particles[0].position = s.particles[0].position * (1 + 1e-4)
    tr = C.simulate(s, 0.1, t_eval=[0, 0.1])
    corr = tr.info["initial_correction"]
    assert 0.5e-4 < corr["position"] < 2e-4
    assert abs(np.linalg.norm(tr.x[0, 0]) - 1) < 1e-13


def test_start_far_from_the_constraints_is_refused_with_the_constraint_named():
    s = planar_pendulum(0.7)
    s.particles[0].position = s.particles[0].position * 1.5
    with pytest.raises(C.InconsistentStateError, match=r"distance bob–\(0, 0, 0\) = 1 m.*violated by 0.5"):
        C.simulate(s, 0.1)


def test_incompatible_constraints_are_refused():
    s = C.System()
    for name, p in (("a", [0, 0, 0]), ("b", [1, 0, 0]), ("c", [0, 1, 0])):
        s.add_particle(name, 1.0, p)
    s.add(C.Distance("a", "b", length=1.0), C.Distance("b", "c", length=1.0),
          C.Distance("a", "c", length=3.0))  # breaks the triangle inequality
    with pytest.raises(C.InconsistentStateError, match="distance a–c"):
        C.simulate(s, 0.1, max_initial_correction=10.0)


def test_trajectory_round_trips_through_npz(tmp_path):
    tr = C.simulate(planar_pendulum(0.3), 0.5, t_eval=np.linspace(0, 0.5, 11))
    path = tr.save(tmp_path / "run.npz")
    back = C.Trajectory.load(path)
    for name in ("t", "x", "v", "multipliers", "constraint_forces", "energy", "constraint_residual"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tr, name))
    assert back.particle_names == ["bob"] and back.constraint_labels == tr.constraint_labels
    assert not list(tmp_path.glob("*.part"))
    import os
    mask = os.umask(0)
    os.umask(mask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~mask  # as a plain open() would make it


def test_outputs_not_asked_for_are_not_computed():
    tr = C.simulate(planar_pendulum(0.3), 0.2, outputs={"energy"})
    assert tr.energy is not None and tr.multipliers is None and tr.constraint_forces is None
    with pytest.raises(C.InputError, match="unknown output"):
        C.simulate(planar_pendulum(0.3), 0.2, outputs={"everything"})


def test_bundled_double_pendulum_scene_over_its_full_run():
    from conftest import SCENARIOS

    scene = C.load_scene(SCENARIOS / "double_pendulum.toml")
    st = scene.settings
    assert st["t_end"] == 10.0 and st["rtol"] == 1e-10
    tr = C.simulate(scene.system, st["t_end"], rtol=st["rtol"], atol=st["atol"])
    assert tr.t[-1] == 10.0
    assert np.max(np.abs(tr.energy / tr.energy[0] - 1)) <= 1e-8
    assert np.max(tr.constraint_residual) <= 1e-10
    # its 10-digit start projects to within 1e-10 of the exact angles (shared/reference)
    assert tr.info["initial_correction"]["position"] < 1e-9
    assert abs(tr.energy[0] - DP_ENERGY) < 1e-8


def test_action_along_a_run_matches_the_closed_form_in_uniform_gravity(tmp_path):
    m, g = 2.0, np.array([0.0, 0.0, -9.81])
    x0, v0 = np.array([0.3, -0.2, 1.0]), np.array([1.0, 0.5, 4.0])
    s = C.System()
    s.add_particle("p", m, x0, v0)
    s.add(C.Gravity(g))
    t = np.linspace(0, 1.5, 31)
    tr = C.simulate(s, 1.5, rtol=1e-12, atol=1e-12, t_eval=t, outputs={"action"})
    # L = ½ m |v0 + g t|² + m g·(x0 + v0 t + ½ g t²), integrated exactly
    gg, gv, vv, gx = g @ g, g @ v0, v0 @ v0, g @ x0
    S = 0.5 * m * (vv * t + gv * t**2 + gg * t**3 / 3) + m * (gx * t + gv * t**2 / 2 + gg * t**3 / 6)
    np.testing.assert_allclose(tr.action, S, rtol=1e-9, atol=1e-12)
    assert tr.multipliers is None  # only what was asked for
    from constrained.output.plot import save_figures

    (png,) = save_figures(tr, ["action"], tmp_path)
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_multipliers_stay_accurate_across_a_mass_ratio_of_1e12():
    """A 1e6 kg bob on a 1 m rod with a 1e-6 kg particle on a 0.5 m string below it, at rest
    hanging straight down: tensions m_total g and m_light g, 18 orders of magnitude apart."""
    s = C.System()
    s.add_particle("heavy", 1e6, [0, -1.0, 0])
    s.add_particle("light", 1e-6, [0, -1.5, 0])
    s.add(C.Distance("heavy", point=[0, 0, 0], length=1.0), C.Distance("heavy", "light", length=0.5),
          C.Gravity([0, -9.81, 0]))
    model = C.assemble(s)
    x = s.positions.ravel()
    F, J, gamma = (np.asarray(a) for a in model.dynamics(x, np.zeros(6), 0.0))
    lam = schur_solve(J, model.inverse_masses, -gamma.ravel() - J @ (model.inverse_masses * F.ravel()))
    np.testing.assert_allclose(-lam, [(1e6 + 1e-6) * 9.81, 1e-6 * 9.81], rtol=1e-9)
