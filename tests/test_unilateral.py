"""One-sided constraints: release, free flight, impacts, rest, against closed forms.

Derivations (m the mass, g gravity, R the sphere's or L the string's length):

* bead on a smooth sphere from angle θ0 (from the top) with speed v0: energy gives
  v² = v0² + 2gR(cos θ0 − cos θ); the normal force N = m(g cos θ − v²/R) vanishes when
  g R cos θ = v0² + 2gR cos θ0 − 2gR cos θ, i.e. cos θ* = (2/3) cos θ0 + v0²/(3gR).
  From rest at the top: cos θ* = 2/3. Then free flight: a parabola.
* ball whirled in a vertical circle from the bottom with speed v0 (angle α from the bottom):
  v² = v0² − 2gL(1 − cos α), tension T = m v²/L + m g cos α = 0 at
  cos α* = (2gL − v0²)/(3gL). Then a parabola until |x| = L again; with restitution 0 the
  string removes the radial velocity: v⁺ = v⁻ − (v⁻·n) n, impulse m|v⁻·n|, energy lost
  m (v⁻·n)²/2.
* ball dropped from height h onto a plane with restitution e: first impact at
  t1 = √(2h/g) with speed u1 = g t1; the k-th rebound speed is e^k u1, so the k-th rebound
  height is h e^(2k) and the impacts are at t_(k+1) = t_k + 2 e^k u1/g (a geometric series,
  at rest at t∞ = t1 + 2 e u1 / (g (1 − e))).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from constrained import System
from constrained.errors import InputError
from constrained.model.constraints import Distance, Plane, Surface
from constrained.model.effects import Gravity
from constrained.model.system import Particle
from constrained.run.simulate import simulate

G = 9.81
TIGHT = {"rtol": 1e-12, "atol": 1e-12}
#: The methods that run one-sided constraints (hybrid.SEGMENT_METHODS) with closed-form accuracy.
METHODS = {"projection": {}, "dopri": {"compiled": False}}


def bead_on_sphere(theta0, v0, R=1.0, **kw):
    """A bead outside a sphere of radius R in the plane z = 0, at angle θ0 from the top,
    moving along the sphere with speed v0."""
    pos = [R * np.sin(theta0), R * np.cos(theta0), 0.0]
    vel = [v0 * np.cos(theta0), -v0 * np.sin(theta0), 0.0]
    return System([Particle("p", 1.0, pos, vel)],
                  [Surface("p", f"x**2 + y**2 + z**2 - {R}**2", unilateral=True, **kw),
                   Plane("p", [0, 0, 1], 0)],
                  [Gravity([0, -G, 0])])


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("theta0, v0, R", [(0.05, 0.0, 1.0), (0.3, 0.5, 1.0), (0.1, 1.2, 2.0)])
def test_bead_leaves_the_sphere_where_the_normal_force_vanishes(theta0, v0, R, method):
    traj = simulate(bead_on_sphere(theta0, v0, R), 2.0, method=method, **METHODS[method], **TIGHT)
    releases = [e for e in traj.events if e.kind == "release"]
    assert len(releases) == 1 and len(traj.events) == 1
    cos_theta = releases[0].x[0, 1] / R
    expected = 2 / 3 * np.cos(theta0) + v0**2 / (3 * G * R)
    assert cos_theta == pytest.approx(expected, abs=1e-9)
    # the release is where the multiplier changed sign: the bead was on the sphere until then
    k = traj.t <= releases[0].t
    assert np.all(traj.multipliers[k, 0] >= -1e-9) and np.all(traj.multipliers[~k, 0] == 0)
    # then free flight: a parabola from the release state
    t1, x1, v1 = releases[0].t, releases[0].x[0], releases[0].v[0]
    after = traj.t > t1
    dt = traj.t[after] - t1
    parabola = x1 + np.outer(dt, v1) + 0.5 * np.outer(dt**2, [0, -G, 0])
    assert np.max(np.abs(traj.x[after, 0] - parabola)) < 1e-8
    # the DOF went from 1 (on the sphere, in the plane) to 2 (in the plane)
    assert [s["dof"] for s in traj.info["segments"]] == [1, 2]


def test_from_rest_at_the_top_the_bead_leaves_at_cos_two_thirds():
    # exactly at the top it would balance there for ever: a hair off it, it leaves after
    # θ = θ0 cosh(√(g/R) t) has grown to O(1), about 4 s
    traj = simulate(bead_on_sphere(1e-5, 0.0), 6.0, **TIGHT)
    # cos θ* = (2/3) cos θ0 = 2/3 to O(θ0²) = 1e-10
    assert traj.events[0].kind == "release"
    assert traj.events[0].x[0, 1] == pytest.approx(2 / 3, abs=1e-9)


def whirled_string(v0, L=1.0):
    return System([Particle("p", 1.0, [0, -L, 0], [v0, 0, 0])],
                  [Distance("p", point=[0, 0, 0], length=L, unilateral=True, name="string"),
                   Plane("p", [0, 0, 1], 0)],
                  [Gravity([0, -G, 0])])


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("ratio", [3.2, 3.5, 4.4])
def test_slack_string_then_parabola_then_taut_again(ratio, method):
    L, m = 1.0, 1.0
    v0 = np.sqrt(ratio * G * L)
    traj = simulate(whirled_string(v0, L), 2.0, method=method, **METHODS[method], **TIGHT)
    kinds = [e.kind for e in traj.events]
    assert kinds[:2] == ["release", "impact"]
    release, jerk = traj.events[:2]
    assert release.constraint == "string"
    # slack where the tension vanishes: the angle from the bottom
    cos_alpha = -release.x[0, 1] / L
    assert cos_alpha == pytest.approx((2 * G * L - v0**2) / (3 * G * L), abs=1e-9)
    # the tension was ≥ 0 (λ ≤ 0) while taut
    held = traj.t <= release.t
    assert np.all(traj.multipliers[held, 0] <= 1e-9)
    # the parabola from the release point meets the circle again: the closed-form instant
    x1, v1 = release.x[0], release.v[0]

    def radius_gap(s):
        p = x1 + v1 * s + 0.5 * np.array([0, -G, 0]) * s**2
        return p @ p - L**2

    grid = np.linspace(1e-3, 5.0, 50001)
    values = np.array([radius_gap(s) for s in grid])
    first = np.flatnonzero(values >= 0)[0]
    s_taut = brentq(radius_gap, grid[first - 1], grid[first], xtol=1e-15)
    assert jerk.t - release.t == pytest.approx(s_taut, abs=1e-9)
    p = x1 + v1 * s_taut + 0.5 * np.array([0, -G, 0]) * s_taut**2
    v_minus = v1 + np.array([0, -G, 0]) * s_taut
    n = p / L
    radial = v_minus @ n
    assert radial > 0  # it was flying outward when the string caught it
    np.testing.assert_allclose(jerk.x[0], p, atol=1e-8)
    np.testing.assert_allclose(jerk.v[0], v_minus - radial * n, atol=1e-8)
    assert jerk.impulse == pytest.approx(m * radial, rel=1e-8)
    assert jerk.energy_lost == pytest.approx(0.5 * m * radial**2, rel=1e-8)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("e", [0.5, 0.8])
def test_bouncing_ball_heights_and_impact_times(e, method):
    h, m = 1.0, 2.0
    ball = System([Particle("b", m, [0.3, h, 0], [0.2, 0, 0])],
                  [Plane("b", [0, 1, 0], 0, unilateral=True, restitution=e, name="floor")],
                  [Gravity([0, -G, 0])])
    t1 = np.sqrt(2 * h / G)
    u1 = G * t1
    t_rest = t1 + 2 * e * u1 / (G * (1 - e))
    traj = simulate(ball, t_rest + 0.5, method=method, **METHODS[method], **TIGHT)
    impacts = [r for r in traj.events if r.kind == "impact"]
    expected_t = t1 + np.concatenate([[0.0], np.cumsum(2 * u1 * e ** np.arange(1, 8) / G)])
    got_t = np.array([r.t for r in impacts[:8]])
    np.testing.assert_allclose(got_t, expected_t, atol=1e-9)
    for k, r in enumerate(impacts[:8]):
        rebound = r.v[0, 1]
        assert rebound == pytest.approx(e ** (k + 1) * u1, rel=1e-8)
        assert rebound**2 / (2 * G) == pytest.approx(h * e ** (2 * (k + 1)), rel=1e-8)  # heights
        approach = e**k * u1
        assert r.impulse == pytest.approx(m * (1 + e) * approach, rel=1e-8)
        assert r.energy_lost == pytest.approx(0.5 * m * approach**2 * (1 - e**2), rel=1e-8)
        assert r.v[0, 0] == pytest.approx(0.2)  # momentum along the floor is kept
    # the rest rule: it settles (within round-off of the geometric series' sum) and then
    # lies on the floor carrying its weight
    assert traj.info["segments"][-1]["held"] == ["floor [b]"]
    assert traj.info["segments"][-1]["t_start"] == pytest.approx(t_rest, abs=1e-6)
    assert traj.x[-1, 0, 1] == pytest.approx(0.0, abs=1e-12)
    assert traj.multipliers[-1, 0] == pytest.approx(m * G, rel=1e-9)


def test_particle_in_a_bowl_never_leaves():
    """Inside a spherical bowl below the rim the normal force m(v²/R + g cos φ) stays
    positive: no event, and the same motion as with a two-sided constraint."""
    R, v0 = 1.0, 2.0  # v0² < 2gR: stays below the equator

    def bowl(unilateral):
        return System([Particle("p", 1.0, [0, -R, 0], [v0, 0, 0.3])],
                      [Surface("p", "1 - x**2 - y**2 - z**2", unilateral=unilateral)],
                      [Gravity([0, -G, 0])])

    one_sided = simulate(bowl(True), 3.0, t_eval=np.linspace(0, 3, 61), **TIGHT)
    two_sided = simulate(bowl(False), 3.0, t_eval=np.linspace(0, 3, 61), **TIGHT)
    assert one_sided.events == []
    assert np.all(one_sided.multipliers[:, 0] > 0)
    np.testing.assert_allclose(one_sided.x, two_sided.x, atol=1e-7)
    assert np.max(one_sided.constraint_residual) < 1e-12


def test_events_survive_save_and_load(tmp_path):
    traj = simulate(whirled_string(np.sqrt(3.5 * G)), 1.5, **TIGHT)
    from constrained.run.trajectory import Trajectory

    back = Trajectory.load(traj.save(tmp_path / "t.npz"))
    def summary(t):
        return [(e.t, e.constraint, e.kind) for e in t.events]

    assert summary(back) == summary(traj)
    np.testing.assert_array_equal(back.events[1].v, traj.events[1].v)
    assert back.events[1].impulse == traj.events[1].impulse


def test_user_events_in_the_habits_of_solve_ivp():
    """A falling particle crosses y = 0.5 at t = √(2 (h − 0.5)/g): recorded (not terminal)
    or the run stops there (terminal), and direction filters the crossings."""
    h = 1.0
    fall = System([Particle("p", 1.0, [0, h, 0], [0, 0, 0])], [], [Gravity([0, -G, 0])])

    def half(t, x, v):
        return x[1] - 0.5

    traj = simulate(fall, 1.0, events=half, **TIGHT)
    assert [e.kind for e in traj.events] == ["half"]
    assert traj.events[0].t == pytest.approx(np.sqrt(2 * (h - 0.5) / G), abs=1e-12)
    assert traj.t[-1] == 1.0
    half.terminal, half.direction = True, 1  # only rising crossings: none while falling
    assert simulate(fall, 1.0, events=half, **TIGHT).events == []
    half.direction = -1
    stopped = simulate(fall, 1.0, events=half, t_eval=np.linspace(0, 1, 11), **TIGHT)
    assert stopped.t[-1] == pytest.approx(np.sqrt(2 * (h - 0.5) / G), abs=1e-12)  # the stop's state
    assert stopped.x[-1, 0, 1] == pytest.approx(0.5, abs=1e-12)
    np.testing.assert_array_equal(stopped.t[:-1], np.linspace(0, 1, 11)[:4])
    assert stopped.info["stop"] == "terminal event" and stopped.events[-1].kind == "half"


def test_start_on_the_forbidden_side_is_refused():
    inside = System([Particle("p", 1.0, [0, 0.5, 0])],
                    [Surface("p", "x**2 + y**2 + z**2 - 1", unilateral=True)], [Gravity([0, -G, 0])])
    with pytest.raises(InputError, match="forbidden side"):
        simulate(inside, 1.0)


def test_other_methods_refuse_one_sided_constraints():
    for method in ("rattle", "idas", "ggl", "pantelides"):
        with pytest.raises(InputError, match="cannot run one-sided constraints: use projection, dopri"):
            simulate(bead_on_sphere(0.2, 0.0), 1.0, method=method)


def test_pin_cannot_be_one_sided_and_restitution_needs_unilateral():
    from constrained.model.constraints import Pin

    with pytest.raises(InputError, match="no side"):
        Pin("p", [0, 0, 0], unilateral=True)
    with pytest.raises(InputError, match="add unilateral = true"):
        Plane("p", [0, 1, 0], 0, restitution=0.5)
    with pytest.raises(InputError, match="energy"):
        Plane("p", [0, 1, 0], 0, unilateral=True, restitution=1.5)


# --- scenes ------------------------------------------------------------------------------------
BALL = """
[[particles]]
name = "b"
mass = 1.0
position = [0, 1, 0]
[[constraints]]
name = "floor"
type = "plane"
particles = ["b"]
normal = [0, 1, 0]
{constraint}
[[effects]]
type = "gravity"
g = [0, -9.81, 0]
[simulate]
t_end = 1.0
rtol = 1e-12
atol = 1e-12
{events}
"""


def ball_scene(tmp_path, constraint="unilateral = true", events=""):
    from constrained.scene.load import load_scene

    path = tmp_path / "ball.toml"
    path.write_text(BALL.format(constraint=constraint, events=events))
    return load_scene(path)


def test_scene_keys_unilateral_restitution_and_events(tmp_path):
    events = '[[events]]\nname = "half"\nexpr = "y_b - 0.5"\ndirection = "falling"\nstop = true'
    scene = ball_scene(tmp_path, "unilateral = true\nrestitution = 0.5", events)
    floor = scene.system.constraints[0]
    assert floor.unilateral and floor.restitution == 0.5
    traj, _ = scene.run()
    assert [e.kind for e in traj.events] == ["half"]
    assert traj.t[-1] == pytest.approx(np.sqrt(2 * 0.5 / G), abs=1e-12)


@pytest.mark.parametrize("constraint, events, message", [
    ("unilateral = 1", "", r"constraints\[0\].unilateral: must be true"),
    ("unilateral = true\nrestitution = 2.0", "", "restitution must be at most 1.*create energy"),
    ("unilateral = true\nrestitution = -0.5", "", "restitution must be at least 0.*into the constraint"),
    ("unilateral = true\nrestitution = \"e\"", "", "restitution must be at most 1, got 'e' = 2.71"),
    ("unilateral = true\nrestitution = \"e_r\"", "", "restitution.*unknown name 'e_r'"),
    ("unilateral = true\nrestitution = true", "", "restitution.*coefficient of restitution"),
    ("restitution = 0.5", "", "add unilateral = true"),
    ("unilateral = true\nelastic = true", "", "unknown key 'elastic'.*unilateral, restitution"),
    ("", '[[events]]\nname = "e"\nexpr = "y_c"', "events\\[0\\].expr"),
    ("", '[[events]]\nname = "e"\nexpr = "y_b"\ndirection = "up"', "rising"),
    ("", '[[events]]\nname = "release"\nexpr = "y_b"', "taken"),
    ("", '[[events]]\nexpr = "y_b"', "missing required key 'name'"),
])
def test_bad_one_sided_keys_are_refused_with_the_key_named(tmp_path, constraint, events, message):
    from constrained.scene.load import SceneError

    with pytest.raises(SceneError, match=message):
        ball_scene(tmp_path, constraint, events)


def test_viewer_lists_the_events_and_jumps_to_them(tmp_path):
    """The page of a bouncing ball lists its impacts; choosing the last moves the time there."""
    import test_viewer

    if test_viewer.CHROMIUM is None:
        pytest.skip("no chromium on this machine (the viewer's browser tests run in CI)")
    from constrained.output import viewer

    ball = System([Particle("b", 1.0, [0, 1, 0])],
                  [Plane("b", [0, 1, 0], 0, unilateral=True, restitution=0.5, name="floor")],
                  [Gravity([0, -G, 0])])
    traj = simulate(ball, 1.5, t_eval=np.linspace(0, 1.5, 301))
    page = viewer.write_viewer(traj, tmp_path / "ball.html", system=ball, title="ball")
    report = test_viewer.selftest(test_viewer.CHROMIUM, page)
    assert report["errors"] == [], report
    assert report["events"]["listed"] == len(traj.events) > 3
    assert report["events"]["jumped_to"] == pytest.approx(traj.events[-1].t, abs=1e-9)


@pytest.mark.parametrize("L", [0.3, 0.7])
def test_statics_a_string_beside_a_spring_holds_only_when_taut(L):
    """A mass on a spring (k, rest length 0) and a string of length L from the same anchor:
    the spring alone would hang it at d = mg/k. Shorter string (L < mg/k): the string holds
    at d = L with tension mg − kL. Longer: the string is slack, d = mg/k, multiplier 0."""
    from constrained.analysis.statics import equilibrium
    from constrained.analysis.statics_report import format_equilibrium
    from constrained.model.effects import Spring

    m, k = 1.0, 20.0
    system = System([Particle("p", m, [0.0, -0.4, 0.0])],
                    [Distance("p", point=[0, 0, 0], length=L, unilateral=True, name="string"),
                     Plane("p", [0, 0, 1], 0), Plane("p", [1, 0, 0], 0)],
                    [Gravity([0, -G, 0]), Spring("p", point=[0, 0, 0], k=k)])
    eq = equilibrium(system)
    if L < m * G / k:
        assert eq.x[0, 1] == pytest.approx(-L, abs=1e-12)
        assert -eq.multipliers[0] == pytest.approx(m * G - k * L, rel=1e-10)  # tension
        assert eq.slack == []
    else:
        assert eq.x[0, 1] == pytest.approx(-m * G / k, abs=1e-12)
        assert eq.multipliers[0] == 0 and eq.slack == ["string"]
        assert "slack at the equilibrium" in format_equilibrium(eq)
    assert eq.stable is True


@pytest.mark.parametrize("e", [0.0, 0.6])
def test_pendulum_hits_a_tilted_wall_keeping_its_rod(e):
    """A bob on a rod (two-sided) swings into a wall through the pivot, tilted (normal
    n ∝ (1, 0.3, 0)). The jump keeps the rod: v⁺ stays tangent, and the wall reverses its
    normal part with factor e, so v⁺ = −e v⁻ whatever the tilt; energy lost ½ m u² (1 − e²)
    with u² = 2gL (cos φ − cos θ0) at the wall's angle tan φ = 0.3."""
    m, L, theta0 = 1.5, 1.0, 1.0
    wall = Plane("p", [1.0, 0.3, 0.0], 0.0, unilateral=True, restitution=e, name="wall")
    system = System([Particle("p", m, [L * np.sin(theta0), -L * np.cos(theta0), 0.0])],
                    [Distance("p", point=[0, 0, 0], length=L, name="rod"), Plane("p", [0, 0, 1], 0), wall],
                    [Gravity([0, -G, 0])])
    traj = simulate(system, 1.0, **TIGHT)
    hit = traj.events[0]
    assert hit.kind == "impact" and hit.constraint == "wall [p]"
    phi = np.arctan(0.3)
    np.testing.assert_allclose(hit.x[0], [L * np.sin(phi), -L * np.cos(phi), 0.0], atol=1e-9)
    u = np.sqrt(2 * G * L * (np.cos(phi) - np.cos(theta0)))
    tangent = np.array([np.cos(phi), np.sin(phi), 0.0])
    np.testing.assert_allclose(hit.v[0], e * u * tangent, atol=1e-8)  # was −u·tangent
    assert hit.energy_lost == pytest.approx(0.5 * m * u**2 * (1 - e**2), rel=1e-8)
    assert abs(hit.x[0] @ hit.v[0]) < 1e-9  # the rod still holds: no radial velocity


def test_string_between_two_particles_jerks_taut_keeping_momentum():
    """Two free particles on a slack string of length L fly apart: when it jerks taut (e = 0)
    the momentum is kept and the relative velocity along the string is removed."""
    m1, m2, L = 1.0, 3.0, 1.0
    system = System([Particle("a", m1, [0, 0, 0], [-1.0, 0.4, 0.0]),
                     Particle("b", m2, [0.5, 0, 0], [0.5, 0.0, 0.2])],
                    [Distance("a", "b", length=L, unilateral=True)])
    traj = simulate(system, 2.0, **TIGHT)
    assert [e.kind for e in traj.events][:1] == ["impact"]
    jerk = traj.events[0]
    p0 = m1 * np.array([-1.0, 0.4, 0.0]) + m2 * np.array([0.5, 0.0, 0.2])
    np.testing.assert_allclose(m1 * jerk.v[0] + m2 * jerk.v[1], p0, atol=1e-10)
    d = jerk.x[1] - jerk.x[0]
    assert np.linalg.norm(d) == pytest.approx(L, abs=1e-12)
    n = d / L
    assert (jerk.v[1] - jerk.v[0]) @ n == pytest.approx(0.0, abs=1e-10)
    # closed form of the free flight: the gap closes at |d0 + w t| = L, w the relative velocity
    d0, w = np.array([0.5, 0, 0]), np.array([1.5, -0.4, 0.2])
    t_taut = (-(d0 @ w) + np.sqrt((d0 @ w) ** 2 - (w @ w) * (d0 @ d0 - L**2))) / (w @ w)
    assert jerk.t == pytest.approx(t_taut, abs=1e-10)
    mu = m1 * m2 / (m1 + m2)
    assert jerk.energy_lost == pytest.approx(0.5 * mu * (w @ (d0 + w * t_taut) / L) ** 2, rel=1e-8)


def test_check_verb_reports_one_sided_rows_at_the_start(tmp_path, capsys):
    from constrained.cli.main import main

    scene = tmp_path / "ball.toml"
    scene.write_text(BALL.format(constraint="unilateral = true", events=""))
    assert main(["check", str(scene)]) == 0
    assert "floor [b] open (gap 1 m)" in capsys.readouterr().out
    below = BALL.format(constraint="unilateral = true", events="")
    below = below.replace("[0, 1, 0]\n[[c", "[0, -1, 0]\n[[c")
    scene.write_text(below)
    assert main(["check", str(scene)]) == 2
    assert "forbidden side" in capsys.readouterr().err


def test_a_start_far_from_the_two_sided_constraints_is_refused():
    from constrained.errors import InconsistentStateError

    far = System([Particle("p", 1.0, [0.0, -1.5, 0.0])],
                 [Distance("p", point=[0, 0, 0], length=1.0), Plane("p", [0, 1, 0], -3.0, unilateral=True)],
                 [Gravity([0, -G, 0])])
    with pytest.raises(InconsistentStateError, match="too far from the constraints.*distance"):
        simulate(far, 1.0)


def test_ctrl_c_stops_a_hybrid_run_keeping_the_segments_done():
    """Ctrl-C (SIGINT) during the flight after the bead left: the run stops with
    RunInterrupted and keeps the segment on the sphere, its release and the flight computed
    up to the stop (the driver keeps what a segment computed)."""
    import os
    import signal

    from constrained.errors import RunInterrupted

    sent = []

    def press_ctrl_c(t, x, v):
        if t > 1.0 and not sent:
            sent.append(t)
            os.kill(os.getpid(), signal.SIGINT)
        return 1.0

    with pytest.raises(RunInterrupted) as caught:
        simulate(bead_on_sphere(0.3, 0.0), 3.0, events=press_ctrl_c, t_eval=np.linspace(0, 3, 301), **TIGHT)
    kept = caught.value.trajectory
    assert kept.info["status"] == "interrupted"
    assert [e.kind for e in kept.events] == ["release"]
    assert 1.0 < kept.t[-1] < 3.0 and np.all(np.isin(kept.t, np.linspace(0, 3, 301)))


def test_bead_leaves_a_sphere_in_3d_at_the_same_angle():
    """Without the plane the speed may have any tangential direction: the normal force depends
    on |v| only, so cos θ* = (2/3) cos θ0 + v0²/(3gR) still holds."""
    R, theta0, v0 = 1.5, 0.4, 1.1
    pos = [R * np.sin(theta0), R * np.cos(theta0), 0.0]
    vel = [0.3 * v0 * np.cos(theta0), -0.3 * v0 * np.sin(theta0), np.sqrt(1 - 0.09) * v0]
    system = System([Particle("p", 2.0, pos, vel)],
                    [Surface("p", f"x**2 + y**2 + z**2 - {R}**2", unilateral=True)], [Gravity([0, -G, 0])])
    traj = simulate(system, 3.0, **TIGHT)
    assert [e.kind for e in traj.events] == ["release"]
    expected = 2 / 3 * np.cos(theta0) + v0**2 / (3 * G * R)
    assert traj.events[0].x[0, 1] / R == pytest.approx(expected, abs=1e-9)


def test_ball_into_a_corner_meets_both_walls_at_once():
    """Thrown at 45° into the corner of two walls at x = 1 and y = 1 (no gravity) with e = 1,
    it reaches both at once: one impact on each, and it comes straight back."""
    system = System([Particle("b", 1.0, [0.0, 0.0, 0.0], [1.0, 1.0, 0.0])],
                    [Plane("b", [-1, 0, 0], -1.0, unilateral=True, restitution=1.0, name="wall x"),
                     Plane("b", [0, -1, 0], -1.0, unilateral=True, restitution=1.0, name="wall y")])
    traj = simulate(system, 1.5, **TIGHT)
    assert [e.kind for e in traj.events] == ["impact", "impact"]
    assert {e.constraint for e in traj.events} == {"wall x [b]", "wall y [b]"}
    assert traj.events[0].t == pytest.approx(1.0, abs=1e-12) and traj.events[1].t == traj.events[0].t
    np.testing.assert_allclose(traj.events[-1].v[0], [-1.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(traj.x[-1, 0], [0.5, 0.5, 0.0], atol=1e-10)


def test_a_hybrid_start_whose_velocity_the_rods_forbid_warns_as_a_two_sided_run_does():
    """A pendulum (a rod, two-sided) swinging over a one-sided floor, started with a velocity
    that has a component along its rod: the start removes it and says so with an
    InitialStateWarning, as a run without one-sided rows does (it was silent)."""
    from constrained.errors import InitialStateWarning

    s = System(name="pendulum over a floor")
    s.add_particle("b", 0.2, [0.8, 0.5, 0.0], [0.3, 0.4, 0.0])  # 0.3 m/s along the rod
    s.add(Distance("b", point=[0.0, 0.5, 0.0], length=0.8), Plane("b", [0, 1, 0], 0, unilateral=True),
          Gravity([0, -9.81, 0]))
    with pytest.warns(InitialStateWarning, match="velocities changed by 0.3 m/s"):
        tr = simulate(s, 0.3)
    assert "segments" in tr.stats  # the hybrid route
    assert tr.info["initial_correction"]["velocity"] == pytest.approx(0.3, rel=1e-12)
    assert np.allclose(tr.v[0].ravel(), [0.0, 0.4, 0.0], atol=1e-12)
