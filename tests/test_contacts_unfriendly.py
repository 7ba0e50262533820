"""Contacts nobody here chose (docs/hard-cases.md, section 8): one-sided constraints, impacts and
events in scenes a demanding physicist would write, each against a closed form or a
conservation law. The ones marked "failed before" failed on the code before session 14's fixes.

Closed forms (m masses, g gravity):

* ball in a wedge of half-angle α (walls through the apex at ±α from the vertical): at rest in
  the apex each wall pushes with N = m g / (2 sin α) (the normals' vertical parts, sin α each,
  carry the weight). In a right-angle corner (α = 45°) the motions along the two walls'
  normals decouple: each is a ball bouncing on a floor under g cos 45°, impacts at
  t₁ = √(2h/a), t_(k+1) = t_k + 2 e^k a t₁ / a, h the start's distance from that wall.
* pendulum (length L, released at θ₀) bouncing elastically off a wall through the pivot at the
  bottom: each flight is half a period, impacts at (2n − 1) √(L/g) K(sin²(θ₀/2)); at rest on
  a wall tilted by φ the wall pushes m g sin φ, the rod pulls m g cos φ.
* Newton's cradle of equal beads, e = 1: impacts in turn pass the velocity on, the last bead
  leaves with the first one's speed, the others stop (binary elastic collisions of equal masses).
* ball on a plate y_p = A sin ωt: the first impact at h − ½ g t² = A sin ωt; relative approach
  u = A ω cos ωt + g t, rebound v⁺ = v_p + e u, energy lost in the plate's frame ½ (1 − e²) m u².
  Held (e = 0), it leaves the plate where the plate's downward acceleration exceeds g:
  A ω² sin ωt = g.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import ellipk

from constrained import Event, System
from constrained.model.constraints import Custom, Distance, Plane
from constrained.model.effects import Gravity
from constrained.model.system import Particle
from constrained.run.simulate import simulate

G = 9.81
TIGHT = {"rtol": 1e-10, "atol": 1e-12}


def _energy(traj, masses):
    m = np.asarray(masses, float)[None, :]
    return 0.5 * np.sum(m[..., None] * traj.v**2, axis=(1, 2)) + G * np.sum(m * traj.x[:, :, 1], axis=1)


# --- a ball in a corner -------------------------------------------------------------------------
def wedge(half_angle, e, m=0.3, start=(0.05, 0.5)):
    """A ball between two one-sided walls through the origin at ±half_angle from the vertical,
    in the plane z = 0, dropped from ``start``; returns (system, the two inward normals)."""
    a = np.radians(half_angle)
    right, left = np.array([-np.cos(a), np.sin(a), 0.0]), np.array([np.cos(a), np.sin(a), 0.0])
    system = System([Particle("b", m, [*start, 0.0])],
                    [Plane("b", right, 0.0, unilateral=True, restitution=e, name="right"),
                     Plane("b", left, 0.0, unilateral=True, restitution=e, name="left"),
                     Plane("b", [0, 0, 1], 0)],
                    [Gravity([0, -G, 0])])
    return system, right, left


def test_ball_rattling_into_a_sharp_wedge_comes_to_rest_in_its_apex():
    """Failed before: 15° half-angle, e = 0.8. After 80 bounces the left wall settles (Zeno)
    and the ball slides into the apex, where its bounce off the right wall started 5e-14 m
    below that wall (the start projected onto the left wall only); the rebound's watch read
    that as a landing at its own start: a segment of zero length, two samples at one instant,
    and the run died with "the trajectory's times must be strictly increasing"."""
    m, alpha = 0.3, 15.0
    system, right, left = wedge(alpha, 0.8, m)
    traj = simulate(system, 2.0, **TIGHT)
    assert traj.info["status"] == "completed"
    assert np.all(np.diff(traj.t) > 0)
    x = traj.x[:, 0]
    assert min(np.min(x @ right), np.min(x @ left)) > -1e-13  # never through a wall
    E = _energy(traj, [m])
    assert np.max(np.diff(E)) < 1e-12 * abs(E[0])  # never gains energy
    assert abs(E[-1]) < 1e-12 and np.linalg.norm(x[-1]) < 1e-12  # at rest in the apex
    N = m * G / (2 * np.sin(np.radians(alpha)))
    np.testing.assert_allclose(traj.multipliers[-1, :2], [N, N], rtol=1e-9)
    assert sum(ev.energy_lost for ev in traj.events) == pytest.approx(E[0], rel=1e-9)


def test_ball_in_a_right_angle_corner_bounces_as_two_independent_balls():
    """Guard: with walls at right angles the normal motions decouple, so each wall's impacts
    follow the bouncing ball's geometric series under g cos 45° (to 1e-10 s over 60+ impacts
    each), and the ball then rests with m g / (2 sin 45°) on each wall."""
    m, e = 0.3, 0.8
    system, right, left = wedge(45.0, e, m)
    traj = simulate(system, 3.5, **TIGHT)
    a = G * np.cos(np.radians(45))
    for name, n in (("right [b]", right), ("left [b]", left)):
        got = np.array([ev.t for ev in traj.events if ev.constraint == name and ev.kind == "impact"])
        t1 = np.sqrt(2 * (np.array([0.05, 0.5, 0.0]) @ n) / a)
        closed = t1 + np.concatenate([[0.0], np.cumsum(2 * e ** np.arange(1, len(got)) * t1)])
        assert len(got) > 60
        np.testing.assert_allclose(got, closed, atol=1e-10)
        assert got[-1] < t1 * (1 + e) / (1 - e)  # the last (settling) impact before t∞
    np.testing.assert_allclose(traj.multipliers[-1, :2], m * G / (2 * np.sin(np.radians(45))), rtol=1e-9)


# --- a pendulum against a wall ------------------------------------------------------------------
def pendulum_at_wall(e, phi=0.0, m=0.4, L=0.7, theta0=0.6):
    return System([Particle("p", m, [L * np.sin(theta0), -L * np.cos(theta0), 0])],
                  [Distance("p", point=[0, 0, 0], length=L, name="rod"), Plane("p", [0, 0, 1], 0),
                   Plane("p", [np.cos(phi), np.sin(phi), 0], 0, unilateral=True, restitution=e, name="wall")],
                  [Gravity([0, -G, 0])])


def test_pendulum_bouncing_elastically_off_a_wall_keeps_its_energy_and_half_period():
    """Guard: e = 1 against a wall at the bottom: every flight is half a period of the free
    pendulum, the impacts at (2n − 1) √(L/g) K to 1e-9 s, the energy kept to 1e-10 of |E0|."""
    L, theta0 = 0.7, 0.6
    traj = simulate(pendulum_at_wall(1.0), 10.0, **TIGHT)
    hits = np.array([ev.t for ev in traj.events if ev.kind == "impact"])
    quarter = np.sqrt(L / G) * ellipk(np.sin(theta0 / 2) ** 2)
    assert len(hits) == 12
    np.testing.assert_allclose(hits, (2 * np.arange(1, 13) - 1) * quarter, atol=1e-9)
    E = _energy(traj, [0.4])
    assert np.max(np.abs(E - E[0])) < 1e-10 * abs(E[0])
    assert np.min(traj.x[:, 0] @ [1.0, 0.0, 0.0]) > -1e-14


@pytest.mark.parametrize("e", [0.0, 0.5])
def test_pendulum_comes_to_rest_against_a_tilted_wall(e):
    """Guard: the wall tilted by φ = 0.2 rad: at rest the wall pushes m g sin φ, the rod pulls
    m g cos φ (λ_rod = −m g cos φ)."""
    m, phi = 0.4, 0.2
    traj = simulate(pendulum_at_wall(e, phi, m), 5.0, **TIGHT)
    assert np.allclose(traj.v[-1], 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.multipliers[-1, [0, 2]], [-m * G * np.cos(phi), m * G * np.sin(phi)],
                               rtol=1e-9)
    assert np.max(np.diff(_energy(traj, [m]))) < 1e-11


# --- Newton's cradle ------------------------------------------------------------------------------
def cradle(n, gap, v0=0.5, m=0.1, L=0.5, d=0.04):
    """n beads of mass m on rods of length L, hanging side by side (centres d apart, the first
    ``gap`` from the second), contacts |x_i+1 − x_i| ≥ d one-sided with e = 1; the first bead
    moves at v0 towards the others."""
    parts, cons = [], []
    for i in range(n):
        px = i * d + (gap if i else 0.0)
        parts.append(Particle(f"b{i}", m, [px, -L, 0], [v0, 0, 0] if i == 0 else [0, 0, 0]))
        cons.append(Distance(f"b{i}", point=[px, 0, 0], length=L, name=f"rod{i}"))
    cons.append(Plane([f"b{i}" for i in range(n)], [0, 0, 1], 0))
    for i in range(n - 1):
        a, b = f"b{i}", f"b{i + 1}"
        cons.append(Custom(f"sqrt((x_{b} - x_{a})**2 + (y_{b} - y_{a})**2) - {d}", unilateral=True,
                           restitution=1.0, name=f"contact {i}{i + 1}"))
    return System(parts, cons, [Gravity([0, -G, 0])])


@pytest.mark.parametrize("n", [3, 5])
@pytest.mark.parametrize("gap", [1e-7, 0.0])
def test_newtons_cradle_passes_the_impact_on_to_the_last_bead(n, gap):
    """Failed before. gap 1e-7 m: the touching beads' contacts, held with a force of ±1e-17 N,
    were rigid in the impact, so the beads behind the first moved as one block (3 beads: the
    first bounced back at −u/3, the block left at 2u/3) or passed the impact on, depending on
    whether round-off had released them yet. gap 0 (touching at the start): the start's
    projection removed the first bead's approach velocity (a plastic collision reported as an
    InitialStateWarning). Now impacts are resolved in turn: the last bead leaves at v0."""
    v0 = 0.5
    traj = simulate(cradle(n, gap, v0), 0.01, **TIGHT)
    impacts = [ev for ev in traj.events if ev.kind == "impact"]
    assert [ev.constraint for ev in impacts] == [f"contact {i}{i + 1}" for i in range(n - 1)]
    assert impacts[-1].t == impacts[0].t  # one instant, in turn
    after = impacts[-1].v[:, 0]
    np.testing.assert_allclose(after[:-1], 0.0, atol=1e-12)
    assert after[-1] == pytest.approx(v0, rel=1e-6)  # (the pendulums turned for 2e-7 s)
    E = _energy(traj, [0.1] * n)
    assert np.max(np.abs(E - E[0])) < 1e-12
    assert sum(ev.energy_lost for ev in impacts) < 1e-15
    assert traj.info["initial_correction"]["velocity"] == 0.0


def test_a_start_touching_the_floor_lifts_off_or_bounces():
    """Failed before: a ball on a one-sided floor at t = 0 moving up at 1 m/s stayed on the
    floor (the start's projection removed the velocity); moving down at 1 m/s with e = 0.5 it
    stopped dead. Now: a flight of 2 v/g, or an impact at t = 0 and the next at 2 e v/g."""
    def ball(vy, e):
        return System([Particle("b", 1.0, [0, 0, 0], [0, vy, 0])],
                      [Plane("b", [0, 1, 0], 0, unilateral=True, restitution=e)], [Gravity([0, -G, 0])])

    up = simulate(ball(1.0, 0.0), 0.3, **TIGHT)
    assert [ev.kind for ev in up.events] == ["impact"] and up.events[0].t == pytest.approx(2 / G, abs=1e-12)
    down = simulate(ball(-1.0, 0.5), 0.15, **TIGHT)
    assert [ev.kind for ev in down.events][:2] == ["impact", "impact"]
    assert down.events[0].t == 0.0 and down.events[0].v[0, 1] == pytest.approx(0.5, rel=1e-12)
    assert down.events[1].t == pytest.approx(1 / G, abs=1e-12)
    assert down.events[0].energy_lost == pytest.approx(0.5 * (1 - 0.25), rel=1e-12)


# --- a moving floor ------------------------------------------------------------------------------
def plate(e, A=0.05, w=20.0, h=0.3, m=0.2):
    return System([Particle("b", m, [0, h, 0])],
                  [Custom(f"y_b - {A}*sin({w}*t)", unilateral=True, restitution=e, name="plate"),
                   Plane("b", [0, 0, 1], 0), Plane("b", [1, 0, 0], 0)],
                  [Gravity([0, -G, 0])])


@pytest.mark.parametrize("e", [0.0, 0.5, 1.0])
def test_ball_on_a_vibrating_plate_first_impact_by_hand(e):
    """Guard: the impact law takes the plate's velocity (restitution of the relative velocity);
    with e = 0 the ball rides the plate until A ω² sin ωt = g (A ω² = 20 m/s² > g)."""
    A, w, h, m = 0.05, 20.0, 0.3, 0.2
    traj = simulate(plate(e, A, w, h, m), 0.6, **TIGHT)
    t1 = brentq(lambda t: h - 0.5 * G * t * t - A * np.sin(w * t), 0.2, 0.3)
    u = A * w * np.cos(w * t1) + G * t1
    first = traj.events[0]
    assert first.kind == "impact" and first.t == pytest.approx(t1, abs=1e-10)
    assert first.v[0, 1] == pytest.approx(A * w * np.cos(w * t1) + e * u, abs=1e-9)
    assert first.energy_lost == pytest.approx(0.5 * (1 - e * e) * m * u * u, abs=1e-9)
    assert first.extra["kinetic_energy_change"] == pytest.approx(
        0.5 * m * ((A * w * np.cos(w * t1) + e * u) ** 2 - (G * t1) ** 2), abs=1e-9)
    assert np.min(traj.x[:, 0, 1] - A * np.sin(w * traj.t)) > -1e-13
    if e == 0.0:
        release = traj.events[1]
        assert release.kind == "release"
        phase = 2 * np.pi + np.arcsin(G / (A * w * w))
        assert release.t == pytest.approx(phase / w, abs=1e-9)


# --- events at the instants of impacts, at t_end ----------------------------------------------------
@pytest.mark.parametrize("method", ["dopri", "projection", "baumgarte"])
def test_a_users_event_at_the_instant_of_an_impact_is_met_by_every_method(method):
    """Failed before: the event y_b (falling) of a ball bouncing on the floor y = 0 is the
    floor's gap itself; the contact and the event were located at the same root (to a few
    ulps), the contact sorted first and ended the segment, and the event was dropped: `dopri`
    never recorded it, `projection` once in three, and a terminal version never stopped
    `dopri`. Now every event at the stop's instant is met, and a user's stop there wins."""
    floor = Plane("b", [0, 1, 0], 0, unilateral=True, restitution=0.5)
    ball = System([Particle("b", 1.0, [0, 1.0, 0])], [floor], [Gravity([0, -G, 0])])
    t1 = np.sqrt(2 / G)
    impacts = t1 * np.array([1.0, 2.0, 2.5])
    def height(t, x, v):
        return x[1]

    traj = simulate(ball, 1.2, method=method, events=[Event("floor", height, -1, False)], **TIGHT)
    met = [ev.t for ev in traj.events if ev.kind == "floor"]
    np.testing.assert_allclose(met, impacts, atol=1e-12)
    np.testing.assert_allclose([ev.t for ev in traj.events if ev.kind == "impact"], impacts, atol=1e-12)
    stop = simulate(ball, 1.2, method=method, events=[Event("floor", height, -1, True)], **TIGHT)
    assert stop.info["stop"] == "terminal event" and stop.t[-1] == pytest.approx(t1, abs=1e-12)


@pytest.mark.parametrize("method, options", [("dopri", {}), ("projection", {}), ("rattle", {"dt": 1e-3}),
                                             ("idas", {}), ("ggl", {})])
def test_events_at_t_end_and_twins_with_every_method(method, options):
    """Guard: an event whose zero is t_end itself is met, and stops there when terminal; two
    events with the same zero are both met at one instant."""
    L, theta0 = 1.0, 0.5
    pend = System([Particle("p", 1.0, [L * np.sin(theta0), -L * np.cos(theta0), 0])],
                  [Distance("p", point=[0, 0, 0], length=L), Plane("p", [0, 0, 1], 0)], [Gravity([0, -G, 0])])
    tol = {} if method == "rattle" else TIGHT
    for terminal in (False, True):
        traj = simulate(pend, 0.5, method=method, events=[Event("end", lambda t, x, v: t - 0.5, 0, terminal)],
                        **tol, **options)
        assert [ev.t for ev in traj.events] == [0.5] and traj.t[-1] == 0.5
    twins = [Event("a", lambda t, x, v: x[0], 0, False), Event("b", lambda t, x, v: 2 * x[0], 0, False)]
    traj = simulate(pend, 0.6, method=method, events=twins, **tol, **options)
    bottom = np.sqrt(L / G) * ellipk(np.sin(theta0 / 2) ** 2)
    assert sorted(ev.kind for ev in traj.events) == ["a", "b"]
    assert traj.events[0].t == pytest.approx(traj.events[1].t, abs=1e-11)
    assert traj.events[0].t == pytest.approx(bottom, abs=1e-6 if method == "rattle" else 1e-8)


# --- extreme mass ratio ------------------------------------------------------------------------------
def test_bead_bouncing_off_a_heavy_ball_lands_on_it_again():
    """Failed before: a 1 g bead dropped 0.2 m onto a 1 kg ball resting on the floor (contact
    |b − B| ≥ R, e = 0.5) bounced at e u, then fell back *through* the ball: its return lay in
    one long step of the exact parabola, from 2 cm above the ball to 4 cm below it, where the
    gap is positive again, and a row that had just bounced was watched without its rate (no
    dip check). It ended 14 cm inside the ball. Now it lands again at t₁ + 2 e u / g."""
    M, m, R, h, e = 1.0, 1e-3, 0.05, 0.2, 0.5
    system = System([Particle("B", M, [0, R, 0]), Particle("b", m, [0, 2 * R + h, 0])],
                    [Plane("B", [0, 1, 0], R, unilateral=True, name="floor"),
                     Custom(f"sqrt((x_b-x_B)**2+(y_b-y_B)**2+(z_b-z_B)**2) - {R}", unilateral=True,
                            restitution=e, name="touch"),
                     Plane(["B", "b"], [1, 0, 0], 0), Plane(["B", "b"], [0, 0, 1], 0)],
                    [Gravity([0, -G, 0])])
    traj = simulate(system, 0.5, **TIGHT)
    u, t1 = np.sqrt(2 * G * h), np.sqrt(2 * h / G)
    hits = [ev for ev in traj.events if ev.constraint == "touch"]
    assert [ev.kind for ev in hits] == ["impact", "impact"]
    assert hits[0].t == pytest.approx(t1, abs=1e-10)
    assert hits[0].v[1, 1] == pytest.approx(e * u, rel=1e-12)  # the loaded ball is rigid against the floor
    assert hits[1].t == pytest.approx(t1 + 2 * e * u / G, abs=1e-10)
    assert np.min(traj.x[:, 1, 1] - traj.x[:, 0, 1]) > R - 1e-12
    np.testing.assert_allclose(traj.x[:, 0, 1], R, atol=1e-13)


# --- through the command line -----------------------------------------------------------------------
PLATE_SCENE = """
[parameters]
e_r = {e}
[[particles]]
name = "b"
mass = 0.2
position = [0, 0.3, 0]
[[constraints]]
name = "plate"
type = "custom"
expr = "y_b - 0.05*sin(20*t)"
unilateral = true
restitution = "e_r"
[[constraints]]
type = "plane"
particles = ["b"]
normal = [0, 0, 1]
[[effects]]
type = "gravity"
g = [0, -9.81, 0]
[[events]]
name = "touchdown"
expr = "y_b - 0.05*sin(20*t)"
direction = "falling"
[simulate]
t_end = 0.8
{method}
"""


def test_the_vibrating_plate_through_the_command_line(tmp_path, capsys):
    """Guard: exit 0 and finite files; e > 1 and rattle with one-sided rows: exit 2, one line."""
    from constrained.cli.main import main

    scene = tmp_path / "plate.toml"
    scene.write_text(PLATE_SCENE.format(e=0.5, method=""))
    assert main(["run", str(scene), "--out", str(tmp_path / "out")]) == 0
    data = np.load(tmp_path / "out" / "trajectory.npz", allow_pickle=True)
    assert all(np.isfinite(data[k]).all() for k in data.files if data[k].dtype.kind == "f")
    y = data["x"].reshape(len(data["t"]), -1)[:, 1]
    assert np.min(y - 0.05 * np.sin(20 * data["t"])) > -1e-12
    capsys.readouterr()
    for e, method, words in ((1.5, "", "restitution must be at most 1"),
                             (0.5, 'method = "rattle"\ndt = 1e-3', "cannot run one-sided constraints")):
        scene.write_text(PLATE_SCENE.format(e=e, method=method))
        assert main(["run", str(scene), "--out", str(tmp_path / "bad")]) == 2
        err = capsys.readouterr().err
        assert words in err and "Traceback" not in err


def test_coinciding_planes_solve_quietly_with_an_even_split(capfd):
    """A bead held by a two-sided plane and resting on a one-sided plane in the same place: the
    active set's rows are dependent. Each plane takes m g / 2 (the minimum-norm split), and the
    solve no longer meets a singular matrix first (CasADi's "LDL factorization has zeros in D",
    printed 58 times on stderr before; session 14)."""
    m = 0.1
    system = System([Particle("b", m, [0.0, 0.0, 0.0], [0.3, 0.0, 0.0])],
                    [Plane("b", [0, 1, 0], 0.0), Plane("b", [0, 1, 0], 0.0, unilateral=True, restitution=0.5),
                     Plane("b", [0, 0, 1], 0.0)],
                    [Gravity([0, -G, 0])])
    traj = simulate(system, 1.0)
    np.testing.assert_allclose(traj.multipliers[:, :2], m * G / 2, rtol=1e-12)
    np.testing.assert_allclose(traj.x[-1, 0], [0.3, 0.0, 0.0], atol=1e-12)  # sliding on, untouched
    assert "zeros in D" not in capfd.readouterr().err
