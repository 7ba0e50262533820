"""Normal modes on the constraint manifold against closed forms, the reduced route and runs.

Every expected value is computed here independently of the package: the double pendulum's
characteristic polynomial, the discrete hanging string's tridiagonal matrix and Bessel zeros,
the bead on a spinning hoop, the Foucault and Larmor splittings, a damped pendulum's roots.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.special import jn_zeros

import constrained as C
from constrained.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
G = 9.81


def double_pendulum(m1=1.0, m2=1.0, l1=1.0, l2=1.0, planar=True, repeat_rod=False) -> C.System:
    s = C.System(name="double pendulum")
    s.add_particle("p1", m1, [0.3 * l1, -l1, 0.0])  # off the equilibrium: statics finds it
    s.add_particle("p2", m2, [0.1 * l2, -l1 - l2, 0.0])
    s.add(C.Distance("p1", point=[0, 0, 0], length=l1), C.Distance("p1", "p2", length=l2),
          C.Gravity([0, -G, 0]))
    if repeat_rod:  # the same rod again, and a plane written twice in two ways: redundant rows
        s.add(C.Distance("p2", "p1", length=l2), C.Plane(["p1", "p2"], [0, 0, 2.0]))
    if planar:
        s.add(C.Plane(["p1", "p2"], [0, 0, 1]))
    return s


def double_pendulum_omega2(m1, m2, l1, l2) -> np.ndarray:
    """m1 l1 l2 ω⁴ − (m1 + m2) g (l1 + l2) ω² + (m1 + m2) g² = 0 (linearized Lagrange)."""
    M = m1 + m2
    return np.sort(np.roots([m1 * l1 * l2, -M * G * (l1 + l2), M * G**2]).real)


def test_double_pendulum_frequencies_are_the_closed_form():
    modes = C.modes(double_pendulum())
    assert modes.degrees_of_freedom == 2 and modes.stable is True
    assert modes.stability.startswith("stable")
    np.testing.assert_allclose(modes.frequencies**2, G * np.array([2 - np.sqrt(2), 2 + np.sqrt(2)]),
                               rtol=1e-12)
    assert all(m.kind == "oscillatory" and m.damping_ratio == 0 for m in modes.modes)
    # the slow mode swings both bobs the same way, the fast one opposite (x components)
    slow, fast = modes.shapes.real
    assert slow[0, 0] * slow[1, 0] > 0 > fast[0, 0] * fast[1, 0]
    # θ2/θ1 = √2 in the slow mode, so x2/x1 = (θ1 + θ2)/θ1 = 1 + √2
    np.testing.assert_allclose(slow[1, 0] / slow[0, 0], 1 + np.sqrt(2), rtol=1e-10)


@pytest.mark.parametrize("m1, m2, l1, l2", [(0.003, 0.017, 0.01, 0.023), (2e3, 1.0, 1.7, 0.4)])
def test_asymmetric_double_pendulum_grams_and_centimetres(m1, m2, l1, l2):
    modes = C.modes(double_pendulum(m1, m2, l1, l2))
    np.testing.assert_allclose(modes.frequencies**2, double_pendulum_omega2(m1, m2, l1, l2), rtol=1e-10)


def test_spatial_double_pendulum_has_each_frequency_twice_and_redundant_rows_change_nothing():
    spatial = C.modes(double_pendulum(planar=False))
    w2 = double_pendulum_omega2(1.0, 1.0, 1.0, 1.0)
    np.testing.assert_allclose(spatial.frequencies**2, np.repeat(w2, 2), rtol=1e-10)
    redundant = C.modes(double_pendulum(repeat_rod=True))
    np.testing.assert_allclose(redundant.frequencies**2, w2, rtol=1e-10)


def test_the_reduced_route_linearized_at_the_same_state_has_the_same_roots():
    scene = C.load_scene(ROOT / "scenarios" / "double_pendulum_parametric.toml")
    modes = C.modes(scene.system, x=[[0, -1, 0], [0, -2, 0]])
    check = modes.cross_check(C.ReducedModel.from_scene(scene))
    assert check.difference < 1e-12
    np.testing.assert_allclose(np.abs(check.q) % (2 * np.pi), 0.0, atol=1e-10)
    # the scene's start is near the inverted equilibrium, which statics finds: unstable
    inverted = C.modes(scene.system)
    assert inverted.stable is False and "UNSTABLE" in inverted.stability
    np.testing.assert_allclose(sorted(m.growth_rate for m in inverted.modes),
                               np.sqrt(G * np.array([2 - np.sqrt(2), 2 + np.sqrt(2)])), rtol=1e-10)


def hanging_chain(masses, lengths, planar=True) -> C.System:
    s = C.System(name="hanging chain")
    y = -np.cumsum(lengths)
    for i, (m, yi) in enumerate(zip(masses, y, strict=True)):
        s.add_particle(f"p{i}", m, [0.1 * lengths[i] * np.sin(i), yi, 0.0])  # statics finds the rest
    s.add(C.Distance("p0", point=[0, 0, 0], length=lengths[0]))
    for i in range(1, len(masses)):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=lengths[i]))
    s.add(C.Gravity([0, -G, 0]))
    if planar:
        s.add(C.Plane(s.names, [0, 0, 1]))
    return s


def discrete_string_omega2(masses, lengths) -> np.ndarray:
    """The hanging string of point masses: link j carries the weight below it, τ_j = g Σ_{i≥j} m_i,
    and m_j ü_j = τ_{j+1}(u_{j+1} − u_j)/l_{j+1} − τ_j (u_j − u_{j−1})/l_j (u_{−1} = 0): K u = ω² M u."""
    m, lengths = np.asarray(masses, float), np.asarray(lengths, float)
    n = len(m)
    tau = G * np.cumsum(m[::-1])[::-1]
    k = tau / lengths
    K = np.zeros((n, n))
    for j in range(n):
        K[j, j] = k[j] + (k[j + 1] if j + 1 < n else 0.0)
        if j + 1 < n:
            K[j, j + 1] = K[j + 1, j] = -k[j + 1]
    from scipy.linalg import eigh

    return eigh(K, np.diag(m), eigvals_only=True)


def test_hanging_chain_modes_are_the_discrete_strings_with_uneven_grams_and_centimetres():
    rng = np.random.default_rng(5)
    masses = rng.uniform(0.001, 0.02, 9)  # grams
    lengths = rng.uniform(0.005, 0.02, 9)  # centimetres
    modes = C.modes(hanging_chain(masses, lengths))
    np.testing.assert_allclose(modes.frequencies**2, discrete_string_omega2(masses, lengths), rtol=1e-9)


def test_fine_uniform_chain_approaches_the_continuous_chains_bessel_frequencies():
    n, L = 60, 1.2
    straight = np.column_stack([np.zeros(n), -L / n * np.arange(1, n + 1), np.zeros(n)])
    modes = C.modes(hanging_chain(np.full(n, 0.01), np.full(n, L / n)), x=straight)
    continuous = jn_zeros(0, 3) / 2 * np.sqrt(G / L)  # ω_k = (j_{0,k}/2) √(g/L)
    np.testing.assert_allclose(modes.frequencies[:3], continuous, rtol=0.02)
    string = discrete_string_omega2(np.full(n, 0.01), np.full(n, L / n))
    np.testing.assert_allclose(modes.frequencies**2, string, rtol=1e-8)


def hoop(R=0.5, w=7.0, m=0.03) -> C.System:
    """A bead on a hoop of radius R spinning at w about the vertical z axis (rheonomic)."""
    s = C.System(name="hoop", parameters={"w": w})
    s.add_particle("bead", m, [0.0, 0.0, -R])
    s.add(C.Distance("bead", point=[0, 0, 0], length=R), C.Plane(["bead"], ["-sin(w*t)", "cos(w*t)", "0"]),
          C.Gravity([0, 0, -G]))
    return s


def test_bead_on_a_spinning_hoop_above_the_critical_speed_oscillates_at_omega_sin_theta():
    R, w = 0.5, 7.0
    th = np.arccos(G / (R * w**2))
    frame = C.RotatingFrame(omega=[0, 0, w])
    guess = [[R * np.sin(th + 0.2), 0, -R * np.cos(th + 0.2)]]
    modes = C.modes(hoop(R, w), x=guess, frame=frame, refine=True)  # the steady motion, found by Newton
    np.testing.assert_allclose(modes.x[0], [R * np.sin(th), 0, -R * np.cos(th)], atol=1e-12)
    np.testing.assert_allclose(modes.v[0], [0, w * R * np.sin(th), 0], atol=1e-12)
    assert modes.stable is True
    np.testing.assert_allclose(modes.frequencies, [w * np.sin(th)], rtol=1e-10)
    # the bottom is a steady motion too, unstable above the critical speed: growth √(w² − g/R)
    bottom = C.modes(hoop(R, w), x=[[0, 0, -R]], frame=frame)
    np.testing.assert_allclose([m.growth_rate for m in bottom.modes], [np.sqrt(w**2 - G / R)], rtol=1e-10)
    assert bottom.stable is False
    # below the critical speed the bottom oscillates at √(g/R − w²)
    slow = C.modes(hoop(R, 3.0), x=[[0, 0, -R]], frame=C.RotatingFrame([0, 0, 3.0]))
    np.testing.assert_allclose(slow.frequencies, [np.sqrt(G / R - 9.0)], rtol=1e-10)


def test_the_hoop_scene_agrees_with_its_reduced_coordinate():
    scene = C.load_scene(ROOT / "scenarios" / "bead_on_rotating_hoop.toml")
    w = scene.system.parameters["w"]
    th = np.arccos(G / w**2)
    modes = C.modes(scene.system, x=[[np.sin(th), 0, -np.cos(th)]], frame=C.RotatingFrame([0, 0, w]))
    check = modes.cross_check(C.ReducedModel.from_scene(scene))
    assert check.difference < 1e-10
    np.testing.assert_allclose(check.q, [th], atol=1e-10)


def test_a_steady_motion_in_the_wrong_frame_is_refused():
    R, w = 0.5, 7.0
    th = np.arccos(G / (R * w**2))
    x = [[R * np.sin(th), 0, -R * np.cos(th)]]
    with pytest.raises(C.InputError, match="not at rest"):
        C.modes(hoop(R, w), x=x, frame=C.RotatingFrame([0, 0, 5.0]))
    with pytest.raises(C.InputError, match="not at rest"):  # no frame: the bead moves
        C.modes(hoop(R, w), x=x, v=[[0, w * R * np.sin(th), 0]])


def foucault(latitude=0.7, Om=0.4, L=2.0, m=1.3) -> tuple[C.System, float]:
    """A spherical pendulum on a turntable tilted by the latitude: the Coriolis force
    −2 m Ω × v written as a velocity-dependent force (no centrifugal term)."""
    W = np.array([0.0, Om * np.cos(latitude), Om * np.sin(latitude)])
    s = C.System(name="Foucault")
    s.add_particle("bob", m, [0.1, 0.05, -L])
    F = [f"-2*{m}*({W[1]}*vz_bob - {W[2]}*vy_bob)", f"-2*{m}*({W[2]}*vx_bob - {W[0]}*vz_bob)",
         f"-2*{m}*({W[0]}*vy_bob - {W[1]}*vx_bob)"]
    s.add(C.Distance("bob", point=[0, 0, 0], length=L), C.Gravity([0, 0, -G]), C.Force("bob", F))
    return s, W[2]


def test_coriolis_splits_the_swing_into_two_circular_modes():
    s, wz = foucault()
    modes = C.modes(s)
    w0 = np.sqrt(G / 2.0)
    np.testing.assert_allclose(modes.frequencies, [np.hypot(w0, wz) - wz, np.hypot(w0, wz) + wz], rtol=1e-12)
    assert np.linalg.norm(modes.G) > 0 and np.linalg.norm(modes.D) == 0 and modes.stable is True
    # circular modes: x and y move a quarter period apart, with equal amplitudes
    for shape in modes.shapes:
        assert abs(abs(shape[0, 0]) - abs(shape[0, 1])) < 1e-9
        assert abs(np.angle(shape[0, 1] / shape[0, 0])) == pytest.approx(np.pi / 2, abs=1e-9)


def test_a_rotating_observer_sees_a_spherical_pendulum_split_by_twice_the_rotation():
    s = C.System(name="spherical")
    s.add_particle("bob", 0.4, [0.0, 0.0, -1.5])
    s.add(C.Distance("bob", point=[0, 0, 0], length=1.5), C.Gravity([0, 0, -G]))
    w0 = np.sqrt(G / 1.5)
    modes = C.modes(s, frame=C.RotatingFrame([0, 0, 0.8]))
    np.testing.assert_allclose(modes.frequencies, [w0 - 0.8, w0 + 0.8], rtol=1e-12)


def test_a_magnetic_field_splits_a_trapped_charge_into_the_larmor_pair():
    q, m, B, k = 2.0, 0.5, 1.5, 8.0
    s = C.System(name="Penning-like trap")
    s.add_particle("e", m, [0.01, 0.0, 0.0])
    s.add(C.Plane(["e"], [0, 0, 1]), C.Spring("e", point=[0, 0, 0], k=k, rest=0.0),
          C.Electromagnetic({"e": q}, A=[f"-{B}*y/2", f"{B}*x/2", "0"]))
    modes = C.modes(s)
    wc, w0 = q * B / m, np.sqrt(k / m)
    larmor = np.hypot(w0, wc / 2)
    np.testing.assert_allclose(modes.frequencies, [larmor - wc / 2, larmor + wc / 2], rtol=1e-12)


def damped_pendulum(m=0.7, l=1.5, c=0.2) -> C.System:
    s = C.System(name="damped pendulum")
    s.add_particle("bob", m, [0.0, -l, 0])
    s.add(C.Distance("bob", point=[0, 0, 0], length=l), C.Plane(["bob"], [0, 0, 1]), C.Gravity([0, -G, 0]),
          C.Damping(c))
    return s


def test_a_damped_modes_decay_rate_is_the_closed_form_and_the_runs():
    m, l, c = 0.7, 1.5, 0.2
    modes = C.modes(damped_pendulum(m, l, c))
    (mode,) = modes.modes
    rate = c / (2 * m)
    assert mode.eigenvalue.real == pytest.approx(-rate, rel=1e-12)
    assert mode.frequency == pytest.approx(np.sqrt(G / l - rate**2), rel=1e-12)
    assert mode.damping_ratio == pytest.approx(rate / np.sqrt(G / l), rel=1e-12)
    assert modes.stable is True and "decays" in modes.stability
    # a small swing in a run decays at that rate: successive peaks of x fall by e^(−rate·T)
    s = damped_pendulum(m, l, c).with_state([[1e-4 * l, -l, 0]])
    run = C.simulate(s, 12.0, t_eval=np.linspace(0, 12, 24001), rtol=1e-11, atol=1e-14)
    x = run.x[:, 0, 0]
    peaks = np.flatnonzero((x[1:-1] > x[:-2]) & (x[1:-1] > x[2:])) + 1
    fitted = -np.polyfit(run.t[peaks], np.log(x[peaks]), 1)[0]
    assert fitted == pytest.approx(rate, rel=2e-4)


def test_an_overdamped_pendulum_has_two_real_decaying_roots():
    m, l, c = 0.1, 0.5, 5.0
    modes = C.modes(damped_pendulum(m, l, c))
    rate, w0 = c / (2 * m), np.sqrt(G / l)
    expected = sorted([-rate - np.sqrt(rate**2 - w0**2), -rate + np.sqrt(rate**2 - w0**2)])
    np.testing.assert_allclose(sorted(m.eigenvalue.real for m in modes.modes), expected, rtol=1e-10)
    assert all(m.kind == "overdamped" for m in modes.modes) and modes.stable is True


def test_a_free_direction_is_a_soft_mode_and_neutral():
    s = C.System(name="bead on a level wire")
    s.add_particle("b", 0.2, [0.3, 0.0, 0.0])
    s.add(C.Plane(["b"], [0, 1, 0]), C.Plane(["b"], [0, 0, 1]), C.Gravity([0, -G, 0]))
    modes = C.modes(s)
    assert [m.kind for m in modes.modes] == ["soft"] and modes.stable is None


def test_a_start_along_a_mode_swings_at_its_frequency():
    """The mode shape is a direction the nonlinear run keeps to first order: started a little
    along mode 2 of the double pendulum, the run's x_p1 repeats with mode 2's period."""
    s = double_pendulum()
    modes = C.modes(s)
    fast = modes.modes[1]
    start = modes.trajectory(1, amplitude=1e-4, system=s).x[0]  # projected onto the rods
    run = C.simulate(s.with_state(start), 3 * fast.period, t_eval=np.linspace(0, 3 * fast.period, 6001),
                     rtol=1e-12, atol=1e-15)
    x = run.x[:, 0, 0]
    up = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    crossings = run.t[up] - x[up] * (run.t[up + 1] - run.t[up]) / (x[up + 1] - x[up])
    assert np.mean(np.diff(crossings)) == pytest.approx(fast.period, rel=1e-6)


def test_the_mode_animation_stays_on_the_constraints_and_repeats():
    s = double_pendulum()
    modes = C.modes(s)
    traj = modes.trajectory(0, periods=1.0, frames=61, system=s)
    np.testing.assert_allclose(np.linalg.norm(traj.x[:, 0], axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(traj.x[:, 1] - traj.x[:, 0], axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(traj.x[-1], traj.x[0], atol=1e-12)
    assert traj.t[-1] - traj.t[0] == pytest.approx(modes.modes[0].period)


def test_bad_input_is_named():
    s = double_pendulum()
    with pytest.raises(C.InputError, match="frame"):
        C.RotatingFrame(omega=[0, 1])
    with pytest.raises(C.InputError, match="x"):
        C.modes(s, x=[[0, -1, 0]])
    with pytest.raises(C.InputError, match="off the constraints"):
        C.modes(s, x=[[0, -1.1, 0], [0, -2, 0]])
    near = C.modes(s, x=[[0.01, -1.1, 0], [0.01, -2, 0]], refine=True)  # a guess: Newton finds the rest
    np.testing.assert_allclose(near.x, [[0, -1, 0], [0, -2, 0]], atol=1e-12)
    with pytest.raises(C.InputError, match="not at rest"):
        C.modes(s, x=[[0.6, -0.8, 0], [0.6, -1.8, 0]])
    with pytest.raises(C.InputError, match="no mode 5"):
        C.modes(s).trajectory(4)
    string = C.System(name="bob on a string")
    string.add_particle("bob", 0.1, [0.0, -1.0, 0.0])
    string.add(C.Distance("bob", point=[0, 0, 0], length=1.0, unilateral=True), C.Gravity([0, -G, 0]))
    with pytest.raises(C.InputError, match="one-sided"):
        C.modes(string)
    with pytest.raises(C.InputError, match="scene.system"):
        C.modes(C.load_scene(ROOT / "scenarios" / "pendulum_fit.toml"))


def test_a_defective_zero_root_is_zero_and_unstable_as_a_power_of_t():
    """A skate held across a slope (velocities: along the blade, turning). Turned by δθ it
    keeps its heading (centre of mass on the blade: no torque) and slides along the blade as
    s = ½ g_t sin δθ t²: q̈_s = g_t q_θ, q̈_θ = 0, a nilpotent 4×4 first-order system. eig gave
    its four zero roots as ~1e-4 (ε^(1/4)), reported as a growing mode and an oscillation of
    period ~4 h; they are 0, and the state is unstable as t², not exponentially."""
    from test_nonholonomic import skate

    system, down, side, g_t = skate(heading=math.pi / 2, omega=0.0)  # across the slope, at rest
    found = C.modes(system)
    assert found.degrees_of_freedom == 2
    # the skate's configuration (x, y, heading) has 3 degrees of freedom; the table says both
    assert found.configuration_degrees_of_freedom == 3
    assert found.table().startswith("3 configuration degree(s) of freedom, 2 velocity degree(s)")
    assert np.all(found.eigenvalues == 0)
    assert all(m.kind == "soft" for m in found.modes)
    assert found.stable is False and "t^3" in found.stability  # chain of 4: a push δθ̇ gives t³
    dth = 1e-3
    turned, *_ = skate(heading=math.pi / 2 - dth, omega=0.0)
    tr = C.simulate(turned, 1.0, rtol=1e-11, atol=1e-13, t_eval=[0.0, 1.0])
    blade = (tr.x[0, 2] - tr.x[0, 1]) / np.linalg.norm(tr.x[0, 2] - tr.x[0, 1])
    s = (tr.x[-1, 0] - tr.x[0, 0]) @ blade
    assert abs(s) == pytest.approx(0.5 * g_t * math.sin(dth), rel=1e-7)


def test_a_free_direction_with_damping_keeps_its_one_zero_root():
    """The kernel chain must not swallow real roots: a damped bead on a line has s = 0 (once)
    and s = −c/m; an undamped free one s = 0 twice (q = a + b t: neutral, not unstable)."""
    for c, expected in ((0.3, [-0.3 / 0.5, 0.0]), (0.0, [0.0, 0.0])):
        bead = C.System([C.Particle("b", 0.5, [0.0, 0.0, 0.0])],
                        [C.Curve("b", ["y", "z"])] + ([C.Damping(c)] if c else []) + [C.Gravity([0, 0, -G])])
        found = C.modes(bead, x=[[0.0, 0.0, 0.0]])
        np.testing.assert_allclose(np.sort(found.eigenvalues.real), expected, atol=1e-12)
        assert found.stable is None, found.stability


def test_modes_for_other_parameter_values_animate_with_those_values():
    scene = C.load_scene(ROOT / "scenarios" / "pendulum_fit.toml")
    modes = C.modes(scene.system, parameters={"l": 0.5, "b": 0.0})
    assert modes.frequencies[0] == pytest.approx(np.sqrt(G / 0.5), rel=1e-12)
    swing = modes.trajectory(0, amplitude=0.1, system=scene.system)
    np.testing.assert_allclose(np.linalg.norm(swing.x[:, 0], axis=1), 0.5, atol=1e-12)  # the rod of l = 0.5


def test_cli_modes_writes_the_report_the_figure_and_the_animation(tmp_path, capsys):
    out = tmp_path / "modes"
    pendulum = str(ROOT / "scenarios" / "pendulum_fit.toml")
    hoop_scene = str(ROOT / "scenarios" / "bead_on_rotating_hoop.toml")
    code = main(["modes", pendulum, "--out", str(out), "--set", "parameters.b=0.0"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "reduced route" in text and "agree" in text
    data = json.loads((out / "modes.json").read_text())
    l = 0.7  # the scene's l
    assert data["modes"][0]["frequency_rad_s"] == pytest.approx(np.sqrt(G / l), rel=1e-12)
    for name in ("modes.png", "mode1.gif", "mode1.html"):
        assert (out / name).stat().st_size > 1000
    assert main(["modes", pendulum, "--rotating", "0,1", "--out", str(out)]) == 2
    assert "--rotating" in capsys.readouterr().err
    code = main(["modes", hoop_scene, "--at", "start", "--rotating", "0,0,3", "--out", str(out)])
    assert code == 2 and "not at rest" in capsys.readouterr().err
