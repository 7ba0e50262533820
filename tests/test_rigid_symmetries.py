"""The rigid motions that are symmetries, found (analysis/conservation/rigid_motions.py) and
listed by `derive`: each found charge is checked against its closed form and for conservation
along a run the tool did not tune (chaotic, tilted gravity, offset pivots, a screw, a gauge)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from conftest import SCENARIOS

import constrained as C
from constrained.analysis.conservation.rigid_motions import null_space_rows, rigid_symmetries
from constrained.analysis.derivation import describe_conserved
from constrained.analysis.symmetry import charge_drift, is_symmetry, noether_charge

TIGHT = {"rtol": 1e-11, "atol": 1e-12}


def _charges_along(model, traj, symmetries) -> list[np.ndarray]:
    return [noether_charge(model, traj, translation=s.translation,
                           rotation=(s.rotation, [0.0, 0.0, 0.0]) if np.any(s.rotation) else None)
            for s in symmetries]


def _double_spherical_pendulum(pivot, gravity) -> C.System:
    """Two bobs of 0.3 and 1.7 kg on rods of 0.7 and 1.3 m from ``pivot``: chaotic in 3-D."""
    pivot = np.asarray(pivot, float)
    s = C.System(name="double spherical pendulum")
    s.add_particle("a", 0.3, pivot + [0.7, 0.0, 0.0], [0.0, 1.1, 0.4])
    s.add_particle("b", 1.7, pivot + [0.7, 0.0, -1.3], [0.9, -0.2, 0.4])
    s.add(C.Distance("a", point=list(pivot), length=0.7), C.Distance("a", "b", length=1.3),
          C.Gravity(list(gravity)))
    return s


def test_tilted_gravity_and_an_offset_pivot_leave_one_rotation_about_the_line_of_gravity():
    pivot, gravity = [1.0, 2.0, 3.0], [2.0, -1.0, -9.0]
    system = _double_spherical_pendulum(pivot, gravity)
    model = C.assemble(system)
    (found,) = rigid_symmetries(model)
    g = np.asarray(gravity) / np.linalg.norm(gravity)
    assert abs(abs(found.rotation @ g) - 1) < 1e-12  # the axis is the line of gravity …
    closest = found.translation  # ε = −ω × c: the axis passes through the pivot
    assert np.allclose(np.cross(found.rotation, np.asarray(pivot)) + closest, 0, atol=1e-10)
    assert found.name.startswith("L·(") and found.name.endswith("about (1, 2, 3)")  # named at the pivot
    assert is_symmetry(model, rotation=(found.rotation, pivot)).holds
    traj = C.simulate(system, 3.0, model=model, t_eval=np.linspace(0, 3, 61), **TIGHT)
    (charge,) = _charges_along(model, traj, [found])
    # closed form: n·Σ m (x − c) × v
    x, v, m = traj.x, traj.v, np.array([0.3, 1.7])
    L = np.einsum("i,tij->tj", m, np.cross(x - np.asarray(pivot), v))
    assert np.allclose(charge, L @ found.rotation, rtol=0, atol=1e-12)
    assert charge_drift(charge) < 1e-8
    assert charge_drift(L @ [1.0, 0.0, 0.0]) > 1e-3  # a rotation that is not one is not conserved


def test_two_bodies_in_their_own_coordinates_momentum_and_angular_momentum(tmp_path):
    scene = tmp_path / "two.toml"
    scene.write_text("""
[parameters]
k = 3.0
m1 = 1.0
m2 = 2.0
[[particles]]
name = "a"
mass = "m1"
position = [1.0, 0.0, 0.0]
velocity = [0.0, 0.5, 0.0]
[[particles]]
name = "b"
mass = "m2"
position = [-1.0, 0.2, 0.0]
velocity = [0.1, -0.25, 0.0]
[[constraints]]
type = "plane"
particles = ["a", "b"]
normal = [0.0, 0.0, 1.0]
offset = 0.0
[[effects]]
type = "spring"
a = "a"
b = "b"
k = "k"
rest = 1.5
[reduced]
coordinates = ["x1", "y1", "x2", "y2"]
initial = { x1 = 1.0, y1 = 0.0, x2 = -1.0, y2 = 0.2 }
rates = { x1 = 0.0, y1 = 0.5, x2 = 0.1, y2 = -0.25 }
map = { a = ["x1", "y1", "0"], b = ["x2", "y2", "0"] }
""")
    loaded = C.load_scene(scene)
    assert [s.name for s in rigid_symmetries(C.assemble(loaded.system))] == ["P_x", "P_y", "L_z"]
    text = describe_conserved(loaded)
    lines = {line.split(" = ")[0].strip(): line for line in text.splitlines() if " = " in line}
    assert "P_x = m1*x1_dot + m2*x2_dot" in lines["P_x"]
    assert "P_y = m1*y1_dot + m2*y2_dot" in lines["P_y"]
    assert "m1*x1*y1_dot - m1*x1_dot*y1 + m2*x2*y2_dot - m2*x2_dot*y2" in lines["L_z"]
    assert "Noether's charge" in lines["L_z"] and "p_x1 is not conserved" in text


def test_a_cyclic_coordinate_names_the_rotation_it_comes_from():
    text = describe_conserved(C.load_scene(SCENARIOS / "kepler.toml"))
    assert "L_z = p_phi  (rotation about the z axis through (0, 0, 0)" in text
    assert "the same conserved quantity" in text


def test_bead_on_a_helix_conserves_a_screw_charge_not_lz_nor_pz():
    radius, pitch = 0.4, 0.15  # x = R cos(z/c), y = R sin(z/c): one turn rises 2π c
    s = C.System(name="bead on a helix")
    s.add_particle("bead", 0.05, [radius, 0.0, 0.0], [0.0, 0.8, 0.8 * pitch / radius])
    s.add(C.Curve("bead", [f"x - {radius}*cos(z/{pitch})", f"y - {radius}*sin(z/{pitch})"]))
    s.add(C.Spring("bead", point=[0.0, 0.0, 0.0], k=0.3, rest=0.0))  # radial pull: rotations only
    model = C.assemble(s)
    found = rigid_symmetries(model)
    assert len(found) == 0  # the spring to the origin breaks the translation part of the screw
    s2 = C.System(name="free bead on a helix")
    s2.add_particle("bead", 0.05, [radius, 0.0, 0.0], [0.0, 0.8, 0.8 * pitch / radius])
    s2.add(C.Curve("bead", [f"x - {radius}*cos(z/{pitch})", f"y - {radius}*sin(z/{pitch})"]))
    model2 = C.assemble(s2)
    (screw,) = rigid_symmetries(model2)
    assert np.allclose(screw.rotation, [0, 0, 1]) and np.allclose(screw.translation, [0, 0, pitch])
    assert screw.name == f"L_z + {pitch:.6g}·P_z" and "screw" in screw.description
    traj = C.simulate(s2, 2.0, model=model2, t_eval=np.linspace(0, 2, 41), **TIGHT)
    x, v = traj.x[:, 0], traj.v[:, 0]
    charge = 0.05 * ((x[:, 0] * v[:, 1] - x[:, 1] * v[:, 0]) + pitch * v[:, 2])
    assert charge_drift(charge) < 1e-8 and abs(charge[0]) > 1e-3


def test_electromagnetic_gauge_decides_which_translations_are_symmetries():
    scene = C.load_scene(SCENARIOS / "charged_particle_em.toml")  # φ = −E0 x, A = (0, B x, 0)
    model = C.assemble(scene.system)
    found = rigid_symmetries(model)
    assert [s.name for s in found] == ["P_y", "P_z"]  # x: the field E; rotations: the gauge
    s = model.symbols
    charge_y = ca.Function("Q", [s.x, s.v], [found[0].charge])
    x, v = np.array([0.7, -0.2, 0.1]), np.array([0.3, 0.4, -0.5])
    assert float(charge_y(x, v)) == pytest.approx(0.5 * 0.4 + 2.0 * 1.5 * 0.7, rel=1e-14)  # m v_y + q B x
    run = scene.run(["simulate.t_end=3"])
    q_y = run.trajectory.v[:, 0, 1] * 0.5 + 2.0 * 1.5 * run.trajectory.x[:, 0, 0]
    m_vy = 0.5 * run.trajectory.v[:, 0, 1]  # not conserved: the particle drifts along y
    assert np.max(np.abs(q_y - q_y[0])) < 1e-9 * np.max(np.abs(m_vy)) and np.ptp(m_vy) > 0.1


@pytest.mark.parametrize("scenario", ["four_bar_linkage", "chaplygin_sleigh", "hanging_chain"])
def test_scenes_without_a_rigid_symmetry_find_none(scenario):
    assert rigid_symmetries(C.assemble(C.load_scene(SCENARIOS / f"{scenario}.toml").system)) == []


def test_a_free_body_has_all_six_and_each_is_conserved():
    scene = C.load_scene(SCENARIOS / "spinning_cube_dzhanibekov.toml")
    model = C.assemble(scene.system)
    found = rigid_symmetries(model)
    assert [s.name for s in found] == ["P_x", "P_y", "P_z", "L_x", "L_y", "L_z"]
    traj = C.simulate(scene.system, 1.0, model=model, t_eval=np.linspace(0, 1, 21), **TIGHT)
    for s, charge in zip(found, _charges_along(model, traj, found), strict=True):
        assert np.max(np.abs(charge - charge[0])) < 1e-9 * max(1.0, np.max(np.abs(charge))), s.name


def test_a_sphere_given_as_a_surface_names_its_centre_for_all_three_rotations():
    s = C.System(name="bead on a sphere about (1, 2, 3)")
    s.add_particle("p", 0.2, [2.0, 2.0, 3.0], [0.0, 0.3, 0.1])
    s.add(C.Surface("p", "(x - 1)**2 + (y - 2)**2 + (z - 3)**2 - 1"))
    found = rigid_symmetries(s)
    assert [f.name for f in found] == ["L_x about (1, 2, 3)", "L_y about (1, 2, 3)", "L_z about (1, 2, 3)"]


def test_null_space_rows_reads_tilted_and_aligned_spaces():
    assert null_space_rows(np.zeros((0, 3)), 1e-9).tolist() == np.eye(3).tolist()
    plane = null_space_rows(np.array([[1.0, 1.0, 0.0]]), 1e-9)  # s_x + s_y = 0
    assert np.allclose(plane, [[1, -1, 0], [0, 0, 1]])
    assert null_space_rows(np.eye(3), 1e-9).shape == (0, 3)


def test_a_motion_that_moves_nothing_is_not_listed():
    """A bead held on the x axis: the rotation about x maps its constraints onto themselves
    (J ξ = 0) but moves nothing, so its charge L_x is 0 at every state: not a conserved
    quantity worth naming. The translation along x is one (no force along x)."""
    s = C.System(name="bead on the x axis")
    s.add_particle("bead", 0.3, [0.4, 0.0, 0.0], [0.2, 0.0, 0.0])
    s.add(C.Plane(["bead"], normal=[0.0, 1.0, 0.0]), C.Plane(["bead"], normal=[0.0, 0.0, 1.0]))
    assert [f.name for f in rigid_symmetries(s)] == ["P_x"]
    pinned = C.System(name="pinned")
    pinned.add_particle("p", 1.0, [2.0, 2.0, 3.0])
    pinned.add(C.Pin("p", point=[2.0, 2.0, 3.0]))
    assert rigid_symmetries(pinned) == []


def test_check_lists_the_symmetries_a_scene_can_expect(capsys):
    from constrained.cli.main import main

    assert main(["check", str(SCENARIOS / "rigid_tetrahedron.toml")]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("symmetries"))
    assert line == ("symmetries (rigid motions), their Noether charges conserved: P_x (translation along x); "
                    "P_y (translation along y); L_z (rotation about the z axis through (0, 0, 0))")
    assert main(["check", str(SCENARIOS / "double_pendulum.toml")]) == 0
    assert "symmetries (rigid motions): none" in capsys.readouterr().out


def test_a_pendulum_hung_far_from_the_origin_has_the_three_rotations_about_its_pivot_only():
    # Sampled at 0.3 of the size (|x| ≈ 7e5 m), the states could not be brought back onto 0.7 m
    # rods: 2 states of 12 were left, and they allowed a translation and a screw that are not.
    pivot = np.array([5e5, 5e5, 0.0])
    s = C.System(name="double spherical pendulum, 700 km from the origin, no gravity")
    s.add_particle("a", 0.3, pivot + [0.7, 0.0, 0.0], [0.0, 1.1, 0.4])
    s.add_particle("b", 1.7, pivot + [0.7, 0.0, -1.3], [0.9, -0.2, 0.4])
    s.add(C.Distance("a", point=list(pivot), length=0.7), C.Distance("a", "b", length=1.3))
    model = C.assemble(s)
    found = rigid_symmetries(model)
    assert [f.name for f in found] == [f"L_{axis} about (500000, 500000, 0)" for axis in "xyz"]
    for f in found:  # every one a rotation about an axis through the pivot: ε = −ω × pivot
        assert np.allclose(f.translation, -np.cross(f.rotation, pivot), rtol=0, atol=1e-6)
    traj = C.simulate(s, 2.0, model=model, t_eval=np.linspace(0, 2, 41), **TIGHT)
    x, v, m = traj.x, traj.v, np.array([0.3, 1.7])
    about_pivot = np.einsum("i,tij->tj", m, np.cross(x - pivot, v))  # closed form, all three conserved
    assert np.max(np.abs(about_pivot - about_pivot[0])) < 1e-7 * np.max(np.abs(about_pivot))
    for f, charge in zip(found, _charges_along(model, traj, found), strict=True):
        assert np.allclose(charge, about_pivot @ f.rotation, rtol=0, atol=1e-6), f.name


def test_a_charge_combining_cyclic_momenta_with_a_parameter_says_its_coefficients_are_numbers(tmp_path):
    """A bead on a cylinder in (u = z + c φ, φ): L_z = c p_u + p_φ, printed at c = 0.5 as
    0.5*p_u and said to be at the scene's values (not a formula in c)."""
    scene = tmp_path / "cylinder.toml"
    scene.write_text("""
[parameters]
c = 0.5
R = 1.0
[[particles]]
name = "p"
mass = 1.0
position = [1.0, 0.0, 0.0]
velocity = [0.0, 0.3, 0.2]
[[constraints]]
type = "surface"
particles = ["p"]
expr = "x**2 + y**2 - R**2"
[reduced]
coordinates = ["u", "ph"]
initial = { u = 0.0, ph = 0.0 }
rates = { u = 0.35, ph = 0.3 }
map = { p = ["R*cos(ph)", "R*sin(ph)", "u - c*ph"] }
""")
    text = describe_conserved(C.load_scene(scene))
    lines = {line.split(" = ")[0].strip(): line for line in text.splitlines() if " = " in line}
    assert lines["P_z"].startswith("  P_z = p_u  (") and "parameter values" not in lines["P_z"]
    assert lines["L_z"].startswith("  L_z = 0.5*p_u + p_ph  (")
    assert lines["L_z"].endswith("(coefficients at the scene's parameter values))")


def test_too_few_states_on_the_constraints_is_a_refusal_not_a_list(monkeypatch):
    """Two or three states cannot rule out a false motion (the far pendulum's false screw came
    from 2 of 12): the search refuses, naming why, and `check` says it did not search."""
    from constrained.analysis.conservation import rigid_motions

    s = C.System(name="bead on a sphere")
    s.add_particle("p", 1.0, [2.0, 2.0, 3.0], [0.0, 0.3, 0.1])
    s.add(C.Distance("p", point=[1.0, 2.0, 3.0], length=1.0))
    sampled = rigid_motions.manifold_samples
    monkeypatch.setattr(rigid_motions, "manifold_samples", lambda m, n, seed: sampled(m, n, seed)[:3])
    with pytest.raises(C.InputError, match="only 3 states on the constraints"):
        rigid_symmetries(s)
