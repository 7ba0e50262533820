"""Exact sensitivities and the fits built on them, on scenes nobody in this repository chose
(session 15): every derivative against a closed form or a five-point finite difference of whole
runs; refusals where the step sequence is not smooth (impacts, terminal events); measurement
files that are out of order, named by line; parameters the data cannot see; a fit out of budget.
Fields and dissipation: tests/test_fields_unfriendly.py."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.special import ellipk

import constrained as C
from constrained.analysis.fitting.sensitivities import GROWN
from constrained.errors import LinearRangeWarning

TIGHT = dict(method="dopri", rtol=1e-12, atol=1e-14)


def five_point(system, t, outputs_of, name, h):
    """(−f(2h) + 8 f(h) − 8 f(−h) + f(−2h)) / 12h of whole runs, error O(h⁴)."""
    base = system.parameters[name]

    def f(d):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", C.InitialStateWarning)
            run = C.simulate(system, float(t[-1]), t_eval=t, parameters={name: base + d}, **TIGHT)
        return outputs_of(run)

    return (-f(2 * h) + 8 * f(h) - 8 * f(-h) + f(-2 * h)) / (12 * h)


def spring(k=4.0, m=0.5, A=0.3):
    s = C.System(name="mass on a spring", parameters={"k": k, "m": m, "A": A})
    s.add_particle("p", "m", ["A", 0, 0])
    s.add(C.Spring("p", point=[0, 0, 0], k="k"))
    return s


def test_a_mass_on_a_spring_has_the_closed_form_derivatives():
    """x = A cos ωt, ω = √(k/m): ∂x/∂k = −A t sin(ωt) ∂ω/∂k, ∂x/∂m likewise, ∂x/∂A = cos ωt,
    ∂v/∂k = −A ∂ω/∂k (sin ωt + ωt cos ωt) — a mass and an initial position given as formulas."""
    k, m, A = 4.0, 0.5, 0.3
    w, t = np.sqrt(k / m), np.linspace(0.0, 3.0, 7)
    dw_dk, dw_dm = 1 / (2 * np.sqrt(k * m)), -np.sqrt(k) / (2 * m ** 1.5)
    sens = C.sensitivities(spring(), t, outputs=["x_p", "vx_p"], parameters=["k", "m", "A"])
    d = sens.d_parameters
    np.testing.assert_allclose(d[:, 0, 0], -A * t * np.sin(w * t) * dw_dk, atol=1e-9)
    np.testing.assert_allclose(d[:, 0, 1], -A * t * np.sin(w * t) * dw_dm, atol=1e-9)
    np.testing.assert_allclose(d[:, 0, 2], np.cos(w * t), atol=1e-9)
    np.testing.assert_allclose(d[:, 1, 0], -A * dw_dk * (np.sin(w * t) + w * t * np.cos(w * t)), atol=1e-9)


def test_a_pendulums_period_grows_as_the_square_root_of_its_length_at_any_amplitude():
    """Released at θ₀ from rest, T = 4 √(L/g) K(sin²(θ₀/2)) whatever θ₀, so dT/dL = T/(2L) and
    dT/dg = −T/(2g). At T/4 the bob crosses x = 0 with velocity vx: ∂x/∂L = −vx ∂(T/4)/∂L; at T
    it is back at θ₀ at rest: ∂θ/∂L = 0, ∂θ/∂θ₀ = 1."""
    L, g, th0 = 0.8, 9.81, 0.6
    s = C.System(name="pendulum", parameters={"L": L, "g": g, "th0": th0})
    s.add_particle("b", 1.3, ["L*sin(th0)", "-L*cos(th0)", 0])
    s.add(C.Distance("b", point=[0, 0, 0], length="L"))
    s.add(C.Gravity([0, "-g", 0]))
    T = 4 * np.sqrt(L / g) * ellipk(np.sin(th0 / 2) ** 2)
    sens = C.sensitivities(s, [T / 4, T], outputs=["x_b", "vx_b", "atan2(x_b, -y_b)"],
                           parameters=["L", "g", "th0"])
    vx = sens.values[0, 1]
    assert abs(sens.values[0, 0]) < 1e-9 and abs(sens.values[1, 2] - th0) < 1e-9
    np.testing.assert_allclose(sens.d_parameters[0, 0, :2], [-vx * T / (8 * L), vx * T / (8 * g)], rtol=1e-8)
    np.testing.assert_allclose(sens.d_parameters[1, 2], [0.0, 0.0, 1.0], atol=1e-8)


def test_a_chaotic_double_pendulum_agrees_over_short_horizons_and_grows_without_nan():
    """Over 3 s the exact derivative matches a finite difference of whole runs; over 40 s it
    grows by orders of magnitude (the largest Lyapunov exponent), and stays finite."""
    scene = C.load_scene("scenarios/double_pendulum_parametric.toml")
    s = scene.system
    t = np.array([1.0, 3.0])
    sens = C.sensitivities(s, t, outputs=["x_p2", "y_p2"], parameters=["th1", "l2"])
    for j, name in enumerate(sens.parameters):
        fd = five_point(s, t, lambda r: r.x[:, 1, :2], name, 1e-4)
        np.testing.assert_allclose(sens.d_parameters[:, :, j], fd, atol=1e-6 * np.abs(fd).max())
    assert max(sens.stats["relative_growth"].values()) < GROWN  # (3 s: no warning above)
    with pytest.warns(LinearRangeWarning, match=r"∂\(x_p2\)/∂th1") as caught:
        long = C.sensitivities(s, np.linspace(0.0, 40.0, 5), outputs=["x_p2"], parameters=["th1"], rtol=1e-9,
                               atol=1e-11)
    growth = np.abs(long.d_parameters[:, 0, 0])
    assert np.all(np.isfinite(growth)) and growth[-1] > 1e6 * growth[0]
    # the warning's number is |∂x/∂θ| |θ| / max |x| at its worst time (session 15: it came back silently)
    worst = np.max(growth) * 2.0 / np.max(np.abs(long.values[:, 0]))
    assert long.stats["relative_growth"]["th1"] == pytest.approx(worst, rel=1e-12)
    assert f"{worst:.2g}" in str(caught[0].message)


def test_a_growing_rod_a_velocity_constraint_and_a_doubled_rod_match_finite_differences():
    """A rheonomic length L₀ + u t, a non-holonomic row vy = c vx, and a rod stated twice (the
    minimum-norm split of its force): ∂/∂(L₀, u, c, L) against five-point differences."""
    grow = C.System(name="growing rod", parameters={"L0": 1.0, "u": 0.1})
    grow.add_particle("b", 1.0, ["L0*sin(0.5)", "-L0*cos(0.5)", 0])
    grow.add(C.Distance("b", point=[0, 0, 0], length="L0 + u*t"), C.Gravity([0, -9.81, 0]))
    slide = C.System(name="skate", parameters={"c": 0.5})
    slide.add_particle("b", 1.0, [0, 0, 0], velocity=[1.0, 0.5, 0])
    slide.add(C.Velocity("vy_b - c*vx_b"), C.Gravity([0, -9.81, 0]))
    twice = C.System(name="rod stated twice", parameters={"L": 1.0})
    twice.add_particle("b", 1.0, ["L*sin(0.5)", "-L*cos(0.5)", 0])
    twice.add(C.Distance("b", point=[0, 0, 0], length="L"), C.Distance("b", point=[0, 0, 0], length="L"),
              C.Gravity([0, -9.81, 0]))
    t = np.array([0.5, 1.5])
    for system, names, outputs, of in [
            (grow, ["L0", "u"], ["x_b", "y_b"], lambda r: r.x[:, 0, :2]),
            (slide, ["c"], ["x_b", "y_b"], lambda r: r.x[:, 0, :2]),
            (twice, ["L"], ["x_b", "Fx_b"], lambda r: np.column_stack([r.x[:, 0, 0],
                                                                         r.constraint_forces[:, 0, 0]]))]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", C.InitialStateWarning)
            sens = C.sensitivities(system, t, outputs=outputs, parameters=names)
        for j, name in enumerate(names):
            fd = five_point(system, t, of, name, 1e-4)
            np.testing.assert_allclose(sens.d_parameters[:, :, j], fd, atol=1e-7 * max(1.0, np.abs(fd).max()),
                                       err_msg=f"{system.name}: ∂/∂{name}")


def test_impacts_and_terminal_events_are_refused_never_differentiated_wrongly():
    """The apex after a bounce, h₁ = e² h₀, has dh₁/de = 2 e h₀: a saltation the replay does not
    carry. It must say so, not return the smooth flight's derivative; so must a terminal event."""
    ball = C.System(name="bouncing ball", parameters={"er": 0.8})
    ball.add_particle("b", 1.0, [0, 1.0, 0])
    ball.add(C.Plane("b", [0, 1, 0], 0.0, unilateral=True, restitution="er"), C.Gravity([0, -9.81, 0]))
    with pytest.raises(C.InputError, match="one-sided.*not supported"):
        C.sensitivities(ball, [0.5, 1.0], outputs=["y_b"], parameters=["er"])
    s = spring()
    s.events = [C.Event("crossing", lambda t, x, v: x[0], terminal=True)]
    with pytest.raises(C.InputError, match="terminal events"):
        C.sensitivities(s, [0.5, 1.0], outputs=["x_p"], parameters=["k"])


def test_a_charge_in_a_magnetic_field_and_a_damped_oscillator_have_the_closed_form_derivatives():
    """Cyclotron motion from the origin with v = (v₀, 0, 0): x = (v₀/ω) sin ωt, ω = qB/m, so
    ∂x/∂B = (v₀ q/m)(t cos ωt/ω − sin ωt/ω²). A damped oscillator's ∂x/∂c: the closed form
    differentiated by a complex step (an independent derivative)."""
    q, m, B, v0 = 2.0, 0.5, 1.5, 1.0
    s = C.System(name="cyclotron", parameters={"B": B})
    s.add_particle("ion", m, [0, 0, 0], velocity=[v0, 0, 0])
    s.add(C.Electromagnetic({"ion": q}, A=["0", "B*x", "0"]))
    t = np.linspace(0.2, 3.0, 5)
    w = q * B / m
    sens = C.sensitivities(s, t, outputs=["x_ion"], parameters=["B"])
    np.testing.assert_allclose(sens.d_parameters[:, 0, 0],
                               v0 * q / m * (t * np.cos(w * t) / w - np.sin(w * t) / w ** 2), atol=1e-9)

    def x(t, c, k=4.0, mass=1.0):  # x(0) = 1, v(0) = 0, underdamped
        g, W = c / (2 * mass), np.sqrt(k / mass - (c / (2 * mass)) ** 2)
        return np.exp(-g * t) * (np.cos(W * t) + g / W * np.sin(W * t))

    osc = C.System(name="damped", parameters={"c": 0.6})
    osc.add_particle("p", 1.0, [1.0, 0, 0])
    osc.add(C.Spring("p", point=[0, 0, 0], k=4.0), C.Damping("c"))
    sens = C.sensitivities(osc, t, outputs=["x_p"], parameters=["c"])
    np.testing.assert_allclose(sens.d_parameters[:, 0, 0], np.imag(x(t, 0.6 + 1e-30j)) / 1e-30, atol=1e-9)


# --- fitting ---------------------------------------------------------------------------------------


def oscillator():
    s = C.System(name="damped oscillator", parameters={"k": 4.0, "m": 1.0, "c": 0.3, "A": 0.5})
    s.add_particle("p", "m", ["A", 0, 0])
    s.add(C.Spring("p", point=[0, 0, 0], k="k"), C.Damping("c"))
    return s


@pytest.fixture(scope="module")
def noisy():
    s = oscillator()
    t = np.linspace(0.05, 6.0, 120)
    true = C.simulate(s, 6.0, t_eval=t, rtol=1e-11, atol=1e-13)
    rng = np.random.default_rng(1)
    return s, C.Measurements(t, ("x_p",), true.x[:, 0, :1] + 1e-3 * rng.standard_normal((len(t), 1)))


def test_a_far_start_finds_the_truth_within_the_stated_errors(noisy):
    s, data = noisy
    r = C.fit(s, data, ["k", "c"], start={"k": 6.0, "c": 0.05}, sigma=1e-3)
    assert r.success
    assert np.all(np.abs(r.estimates - [4.0, 0.3]) < 4 * r.standard_errors)
    assert 0.6 < r.reduced_chi2 < 1.5


def test_mass_stiffness_and_damping_together_leave_their_common_scale_undetermined(noisy):
    """m x'' + c x' + k x = 0 sees k/m and c/m only: the direction (k, m, c) ∝ (4, 1, 0.3) is
    reported as not determined (infinite errors), and the fit still reproduces the data."""
    s, data = noisy
    r = C.fit(s, data, ["k", "m", "c"], sigma=1e-3)
    assert len(r.unidentified) == 1
    v = np.array([r.unidentified[0][n] for n in ("k", "m", "c")])
    scale = np.array([4.0, 1.0, 0.3])
    np.testing.assert_allclose(np.abs(v), scale / np.linalg.norm(scale), atol=1e-4)
    assert np.all(np.isinf(r.standard_errors))
    assert r.estimates[0] / r.estimates[1] == pytest.approx(4.0, abs=4e-3)


def test_a_fit_out_of_budget_says_so_and_keeps_a_better_point_than_its_start(noisy):
    s, data = noisy
    start = {"k": 1.0, "c": 2.0}
    r = C.fit(s, data, ["k", "c"], start=start, sigma=1e-3, max_nfev=3)
    assert not r.success and "NOT converged" in r.table()
    first = C.fit(s, data, ["k", "c"], start=start, sigma=1e-3, max_nfev=1)
    assert r.chi2 < first.chi2


def test_missing_values_are_left_out(noisy):
    s, data = noisy
    values = data.values.copy()
    values[::3] = np.nan
    r = C.fit(s, C.Measurements(data.t, data.names, values), ["k", "c"], sigma=1e-3)
    assert r.dof == np.isfinite(values).sum() - 2
    assert np.all(np.abs(r.estimates - [4.0, 0.3]) < 4 * r.standard_errors)


@pytest.mark.parametrize("rows, match", [
    ("0,1\n0.2,2\n0.1,3\n", r"line 4: t = 0.1 s goes back in time"),
    ("0,1\n0.1,2\n0.1,3\n", r"line 4: t = 0.1 s repeats the time before it"),
    ("0,1\nnan,2\n", r"line 3: the time is missing"),
], ids=["unsorted", "duplicate", "nan time"])
def test_measurement_files_out_of_order_are_refused_naming_the_line(tmp_path, rows, match):
    path = tmp_path / "data.csv"
    path.write_text("t,x_p\n" + rows)
    with pytest.raises(C.InputError, match=match):
        C.read_measurements(path)


def test_a_negative_sigma_is_refused_naming_its_line_and_column(tmp_path):
    path = tmp_path / "data.csv"
    path.write_text("t,x_p,sigma_x_p\n0,1,0.1\n0.1,2,-1\n")
    with pytest.raises(C.InputError, match=r"line 3: the standard deviation of 'x_p' is -1"):
        C.read_measurements(path)
