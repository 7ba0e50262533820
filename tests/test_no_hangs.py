"""Scenes a new user writes that once hung or ran away (issue 26, items 1-3): a ball bouncing
down an incline past its accumulation point, an event that is zero at the start, a rod driven
to zero length. Each must end in bounded work with the physics right, for every method that
accepts the scene. ``within`` turns a hang into a failure instead of a stuck suite."""

from __future__ import annotations

import contextlib
import math
import os
import signal

import numpy as np
import pytest
from conftest import planar_pendulum
from scipy.special import ellipk

import constrained as C
from constrained.run.hybrid import ZENO_TIME
from constrained.solvers.driver import STEP_SAMPLES

G = 9.81
SLOPE = math.radians(20.0)
E = 0.7
MASS = 0.057  # a tennis ball, kg
HEIGHT = 1.0  # dropped from 1 m above the incline's foot (the origin), at rest
SEGMENT_METHODS = ("dopri", "projection", "baumgarte")


@contextlib.contextmanager
def within(seconds: float):
    """Fail (TimeoutError) instead of hanging when the block runs longer than ``seconds``."""
    def expire(signum, frame):
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def incline(restitution=E) -> C.System:
    """A ball over the incline y = −tan(α) x (one-sided, e), in the plane z = 0."""
    s = C.System(name="ball on an incline")
    s.add_particle("ball", MASS, [0.0, HEIGHT, 0.0])
    normal = [math.sin(SLOPE), math.cos(SLOPE), 0.0]
    s.add(C.Plane("ball", normal, unilateral=True, restitution=restitution, name="incline"),
          C.Plane("ball", [0, 0, 1]), C.Gravity([0, -G, 0]))
    return s


def incline_closed_form():
    """Normal drop h0 = H cos α under g_n = g cos α: first impact at t1 = √(2 h0 / g_n) = √(2H/g);
    each flight is e times the one before, so the impacts accumulate at t∞ = t1 (1 + e)/(1 − e).
    The plane is frictionless: normal impulses leave the motion along the slope a free fall
    under g sin α, and the energy lost is all of the normal energy, m g_n h0."""
    t1 = math.sqrt(2 * HEIGHT / G)
    return t1, t1 * (1 + E) / (1 - E), MASS * G * math.cos(SLOPE) * HEIGHT * math.cos(SLOPE)


@pytest.mark.parametrize("grid", [False, True], ids=["steps", "output grid"])
@pytest.mark.parametrize("method", SEGMENT_METHODS)
def test_a_ball_bouncing_down_an_incline_settles_at_its_accumulation_point(method, grid):
    t1, t_inf, lost = incline_closed_form()
    t_end = 3.0
    t_eval = np.linspace(0.0, t_end, 3001) if grid else None
    with within(120):
        tr = C.simulate(incline(), t_end, method=method, rtol=1e-10, atol=1e-10, t_eval=t_eval)
    assert tr.info["status"] == "completed"
    impacts = [e for e in tr.events if e.kind == "impact"]
    assert abs(impacts[0].t - t1) < 1e-8
    flights = np.diff([e.t for e in impacts[:6]])
    np.testing.assert_allclose(flights[1:] / flights[:-1], E, rtol=1e-6)
    # the sequence ends by the rest rule (a rebound below 1000 × atol = 1e-7 m/s) or the Zeno
    # rule (the accumulation point within ZENO_TIME = 1 µs), just before t∞
    last = impacts[-1]
    rest = 1e3 * 1e-10
    assert "settles" in last.extra.get("note", "")
    assert last.extra["approach_speed"] * E <= rest or "Zeno" in last.extra["note"]
    assert 0 < t_inf - last.t <= ZENO_TIME
    named = float(last.extra["note"].split("t∞ ≈ ")[1].split(" s")[0])  # the accumulation point
    assert abs(named - t_inf) < 1e-6
    for e in impacts[:-1]:  # every earlier impact rebounded faster than the rest speed, from t∞ afar
        assert e.extra["approach_speed"] * E > rest and t_inf - e.t > ZENO_TIME
    # after t∞: sliding down the slope, as if the bounces had never been
    along = np.array([math.cos(SLOPE), -math.sin(SLOPE), 0.0])
    normal = np.array([math.sin(SLOPE), math.cos(SLOPE), 0.0])
    x_end = tr.x[-1, 0]
    start_along = float(np.dot([0.0, HEIGHT, 0.0], along))
    assert abs(np.dot(x_end, along) - start_along - 0.5 * G * math.sin(SLOPE) * t_end**2) < 1e-6
    assert abs(np.dot(x_end, normal)) < 1e-9
    assert abs(np.dot(tr.v[-1, 0], normal)) < 1e-9
    assert abs(sum(e.energy_lost for e in tr.events) - lost) < 1e-6 * lost
    if grid:
        np.testing.assert_array_equal(tr.t, t_eval)


def test_rest_speed_is_a_simulate_key_and_the_rule_is_what_it_says(tmp_path):
    """rest_speed in [simulate]: an impact whose rebound e·u would be slower settles, and no
    faster one does."""
    scene = tmp_path / "incline.toml"
    scene.write_text(f"""
[[particles]]
name = "ball"
mass = {MASS}
position = [0.0, {HEIGHT}, 0.0]

[[constraints]]
name = "incline"
type = "plane"
particles = ["ball"]
normal = [{math.sin(SLOPE)!r}, {math.cos(SLOPE)!r}, 0.0]
unilateral = true
restitution = {E}

[[constraints]]
type = "plane"
particles = ["ball"]
normal = [0.0, 0.0, 1.0]

[[effects]]
type = "gravity"
g = [0.0, -{G}, 0.0]

[simulate]
t_end = 3.0
rest_speed = 0.5
""")
    with within(60):
        tr = C.load_scene(scene).run().trajectory
    impacts = [e for e in tr.events if e.kind == "impact"]
    rebounds = [e.extra["approach_speed"] * E for e in impacts]
    assert all(w > 0.5 for w in rebounds[:-1]) and rebounds[-1] <= 0.5
    assert "0.5 m/s" in impacts[-1].extra["note"]
    u1 = G * math.cos(SLOPE) * math.sqrt(2 * HEIGHT / G)  # the first approach speed
    assert len(impacts) == 1 + math.ceil(math.log(0.5 / (E * u1)) / math.log(E))
    with pytest.raises(C.InputError, match="rest_speed"):
        C.load_scene(scene, ["simulate.rest_speed=-1"])


def test_a_ball_that_comes_to_rest_on_a_floor_with_output_times():
    """Bounces (e = 0.5) with a horizontal speed, then rolls... slides at rest vertically: the
    run ends with the floor holding it, its push m g, and the horizontal motion untouched."""
    s = C.System(name="ball on a floor")
    s.add_particle("ball", 0.1, [0.0, 0.5, 0.0], [0.3, 0.0, 0.0])
    s.add(C.Plane("ball", [0, 1, 0], unilateral=True, restitution=0.5, name="floor"),
          C.Gravity([0, -G, 0]))
    t_eval = np.linspace(0.0, 5.0, 501)
    with within(60):
        tr = C.simulate(s, 5.0, t_eval=t_eval)
    t1 = math.sqrt(2 * 0.5 / G)
    t_inf = t1 * 1.5 / 0.5
    assert tr.events[-1].t < t_inf
    np.testing.assert_allclose(tr.x[:, 0, 0], 0.3 * t_eval, atol=1e-9)
    after = t_eval > t_inf
    assert np.max(np.abs(tr.x[after, 0, 1])) < 1e-12
    np.testing.assert_allclose(tr.multipliers[after, 0], 0.1 * G, rtol=1e-9)


def test_ctrl_c_stops_a_zeno_run_promptly():
    """Ctrl-C among the ever shorter flights before the accumulation point: the run stops
    there and keeps what it computed."""
    def press_ctrl_c(t):
        if t > 2.4:
            os.kill(os.getpid(), signal.SIGINT)

    with within(60), pytest.raises(C.RunInterrupted) as stopped:
        C.simulate(incline(), 3.0, rtol=1e-10, atol=1e-10, progress=press_ctrl_c, rest_speed=0.0)
    kept = stopped.value.trajectory
    assert 2.4 < kept.t[-1] < 2.6 and kept.info["status"] == "interrupted"


# --- events that are zero at the start ---------------------------------------------------------
EVENT_METHODS = ("dopri", "projection", "baumgarte", "idas", "ggl", "pantelides", "rattle")
SETTINGS = {"rattle": dict(dt=1e-3)}


@pytest.mark.parametrize("method", EVENT_METHODS)
def test_an_event_zero_at_the_start_is_not_a_crossing(method):
    """A pendulum released from rest with the event vx = 0: the start is where the run begins;
    the turning points come every half period, √(l/g) 2K(sin²(θ0/2))."""
    theta0 = math.asin(0.6)
    half = 2 * math.sqrt(1 / G) * ellipk(math.sin(theta0 / 2) ** 2)
    turning = C.Event("turning", lambda t, x, v: v[0], terminal=False)
    stop = C.Event("stop at vx = 0", lambda t, x, v: v[0], terminal=True)
    settings = SETTINGS.get(method, dict(rtol=1e-10, atol=1e-10))
    accuracy = 1e-3 if method == "rattle" else 1e-6
    with within(120):
        tr = C.simulate(planar_pendulum(theta0), 2.5, method=method, events=[turning], **settings)
        hits = [e.t for e in tr.events if e.kind == "turning"]
        np.testing.assert_allclose(hits, [half, 2 * half], atol=accuracy)
        stopped = C.simulate(planar_pendulum(theta0), 2.5, method=method, events=[stop], **settings)
    assert abs(stopped.t[-1] - half) < accuracy


@pytest.mark.parametrize("method", SEGMENT_METHODS)
def test_an_event_that_stays_zero_does_not_stall(method):
    """A ball resting on a one-sided floor with the event y = 0 all along: no crossing, no stall."""
    s = C.System(name="ball at rest")
    s.add_particle("ball", 0.2, [0.0, 0.0, 0.0])
    s.add(C.Plane("ball", [0, 1, 0], unilateral=True, name="floor"), C.Gravity([0, -G, 0]))
    height = C.Event("height", lambda t, x, v: x[1], terminal=False)
    with within(60):
        tr = C.simulate(s, 2.0, method=method, events=[height], t_eval=np.linspace(0, 2, 201))
    assert tr.info["status"] == "completed"
    # (Baumgarte's feedback lets y wander at 1e-28 m: within the run's resolution, no crossing)
    assert not [e for e in tr.events if e.kind == "height"]
    np.testing.assert_allclose(tr.multipliers[:, 0], 0.2 * G, rtol=1e-9)


@pytest.mark.parametrize("method", ["dopri", "projection", "idas", "ggl", "pantelides", "rattle", "rodas"])
def test_an_event_the_constraints_hold_at_zero_only_to_round_off_is_not_crossed(method):
    """A particle on a two-sided floor with a rod standing on it (balanced upright, at rest):
    its y and vy are zero, the run's values ±1e-70 to ±1e-33. Each such sign flip was a crossing:
    a terminal event on y stopped the run at once (dopri, ggl, rattle), and idas, restarted
    at every flip of vy, stopped with a false "step size collapsed". A flip within the run's
    resolution (how much g moves when the state moves by atol) is not a crossing; a real one
    still is (the same events on a ball that falls through y = 0 of a free particle)."""
    s = C.System(name="upright rod on a floor")
    s.add_particle("foot", 0.2, [0.3, 0.0, 0.0])
    s.add_particle("top", 0.1, [0.3, 0.5, 0.0])
    s.add(C.Plane("foot", [0, 1, 0]), C.Distance("foot", "top", length=0.5), C.Gravity([0, -G, 0]))
    y = C.Event("y", lambda t, x, v: x[1], terminal=True)
    vy = C.Event("vy", lambda t, x, v: v[1], terminal=False)
    settings = SETTINGS.get(method, dict(t_eval=np.linspace(0, 3, 31)))
    with within(120):
        tr = C.simulate(s, 3.0, method=method, events=[y, vy], **settings)
    assert tr.info["status"] == "completed" and tr.t[-1] == pytest.approx(3.0)
    assert not tr.events
    # the rod stays upright (unstable, but balanced to round-off over 3 s): its force is the
    # top's weight, the floor carries both weights
    np.testing.assert_allclose(tr.x[:, 1, 1], 0.5, atol=1e-6)
    # a real crossing of y = 0 is still located: a particle thrown up from y = 0 comes back at 2 u / g
    ball = C.System(name="thrown")
    ball.add_particle("b", 0.1, [0.0, 0.0, 0.0], [0.0, 2.0, 0.0])
    ball.add(C.Plane("b", [0, 0, 1]), C.Gravity([0, -G, 0]))
    with within(120):
        thrown = C.simulate(ball, 1.0, method=method, events=[y], **SETTINGS.get(method, {}))
    assert thrown.t[-1] == pytest.approx(2 * 2.0 / G, abs=1e-3 if method == "rattle" else 1e-7)


# --- a collapse diagnosed within seconds ------------------------------------------------------
def shrinking_rod() -> C.System:
    """A pendulum whose rod length 1 − t is driven to zero at t = 1: the angular momentum kept,
    the speed grows as 1/(1 − t) without bound (a finite-time singularity)."""
    s = C.System(name="shrinking rod")
    s.add_particle("bob", 1.0, [0.6, -0.8, 0.0], [-0.6, 0.8, 0.0])  # drawn in with the rod: 1 m/s
    s.add(C.Distance("bob", point=[0, 0, 0], length="1 - t"), C.Plane("bob", [0, 0, 1]),
          C.Gravity([0, -G, 0]))
    return s


@pytest.mark.parametrize("method", ["dopri", "projection", "baumgarte", "idas", "ggl", "pantelides"])
def test_a_rod_driven_to_zero_length_stops_near_the_singularity_with_bounded_output(method, capsys):
    with within(60), pytest.raises(C.SimulationError) as stopped:
        C.simulate(shrinking_rod(), 1.5, method=method, outputs={"energy"})
    # SUNDIALS' own lines ("At t = ..., mxstep steps taken ...") stay off the terminal
    assert "mxstep" not in capsys.readouterr().err
    kept = stopped.value.trajectory
    message = str(stopped.value)
    assert "collapsed" in message or "singular" in message
    assert 0.99 < kept.t[-1] < 1.0
    assert len(kept.t) <= STEP_SAMPLES + 2
    if "collapsed" in message:  # the instant it names is the rod's end, t = 1
        t_star = float(message.split("t* ≈ ")[1].split(" s")[0])
        assert abs(t_star - 1.0) < 2e-3


def test_a_close_passage_is_not_a_collapse():
    """Kepler, e = 0.95: the steps shrink 100-fold at each periapsis and recover; two orbits
    run to the end with the energy kept."""
    s = C.System(name="kepler")
    a, ecc, mu = 1.0, 0.95, 1.0
    r_apo = a * (1 + ecc)
    s.add_particle("planet", 1.0, [r_apo, 0.0, 0.0], [0.0, math.sqrt(mu / a * (1 - ecc) / (1 + ecc)), 0.0])
    s.add(C.Central("planet", point=[0, 0, 0], expr="-1/r"), C.Plane("planet", [0, 0, 1]))
    period = 2 * math.pi * math.sqrt(a**3 / mu)
    with within(120):
        tr = C.simulate(s, 2 * period, rtol=1e-10, atol=1e-10)
    assert tr.info["status"] == "completed"
    assert np.max(np.abs(tr.energy - tr.energy[0])) < 1e-7 * abs(tr.energy[0])


def test_a_run_without_output_times_keeps_a_bounded_number_of_steps():
    """Many small steps (a stiff spring at tight tolerances) are kept at most one per
    span / STEP_SAMPLES, the last state included."""
    s = C.System(name="fast spring")
    s.add_particle("p", 1e-3, [1.0, 0.0, 0.0])
    s.add(C.Spring("p", point=[0, 0, 0], k=1e4, rest=0.5))
    tr = C.simulate(s, 2.0, rtol=1e-12, atol=1e-12, outputs={"energy"})
    assert tr.stats["steps"] > STEP_SAMPLES
    assert len(tr.t) <= STEP_SAMPLES + 2 and tr.t[-1] == 2.0
    assert np.min(np.diff(tr.t)) > 0
    assert np.max(np.abs(tr.energy - tr.energy[0])) < 1e-8 * abs(tr.energy[0])


def test_a_large_model_keeps_about_step_values_positions_by_default(monkeypatch):
    """A run given no output times on a large model keeps its steps evenly thinned to about
    STEP_VALUES position values (driver.step_samples), the last state included; a grid the
    user asks for is not thinned. Checked on a 40-link rope with STEP_VALUES lowered so that
    it stands for a 10,000-particle one."""
    from constrained.solvers import driver

    n = 40
    s = C.System(name="rope")
    for i in range(n):
        s.add_particle(f"p{i}", 0.01, [0.01 * (i + 1), 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=0.01), C.Plane("p0", [0, 0, 1]))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=0.01), C.Plane(f"p{i}", [0, 0, 1]))
    s.add(C.Gravity([0, -G, 0]))
    monkeypatch.setattr(driver, "STEP_VALUES", 60 * 3 * n)
    assert driver.step_samples(3 * n) == 60
    tr = C.simulate(s, 1.0, outputs={"energy"})
    assert tr.stats["steps"] > 120
    assert 50 <= len(tr.t) <= 62 and tr.t[-1] == 1.0
    assert np.min(np.diff(tr.t[:-1])) >= 1.0 / 60 * (1 - 1e-12)
    full = C.simulate(s, 1.0, outputs={"energy"}, t_eval=np.linspace(0, 1, 121))
    assert len(full.t) == 121
    assert np.max(np.abs(tr.energy - tr.energy[0])) < 1e-5


def test_sundials_messages_are_kept_from_the_calling_thread_only(capsys):
    """``quiet()`` keeps what its thread writes to sys.stderr; another thread's writes pass
    through, and sys.stderr is itself again afterwards."""
    import sys
    import threading

    from constrained.solvers.sundials.messages import quiet

    before = sys.stderr
    with quiet() as kept:
        sys.stderr.write("At t = 1, mxstep steps taken before reaching tout.\n")
        other = threading.Thread(target=lambda: sys.stderr.write("another thread's line\n"))
        other.start()
        other.join()
    assert sys.stderr is before
    assert kept == ["At t = 1, mxstep steps taken before reaching tout.\n"]
    assert capsys.readouterr().err == "another thread's line\n"


def test_rattle_keeps_about_step_values_positions_by_default_on_a_large_model(monkeypatch):
    """rattle's own default grid (every step up to DEFAULT_SAMPLES) is thinned like the other
    methods' on a large model (driver.step_samples): 400 steps of a model standing for a
    10,000-particle one keep about 60 samples, evenly, the end included."""
    from constrained.solvers import driver

    s = C.System(name="pendulum")
    s.add_particle("bob", 1.0, [1.0, 0.0, 0.0])
    s.add(C.Distance("bob", point=[0, 0, 0], length=1.0), C.Gravity([0, -G, 0]))
    monkeypatch.setattr(driver, "STEP_VALUES", 60 * 3)
    tr = C.simulate(s, 0.4, method="rattle", dt=1e-3, outputs={"energy"})
    assert tr.stats["steps"] == 400
    assert 55 <= len(tr.t) <= 70 and tr.t[-1] == pytest.approx(0.4, abs=1e-15)
    assert np.allclose(np.diff(tr.t[:-1]), tr.t[1] - tr.t[0])
    assert np.max(np.abs(tr.energy - tr.energy[0])) < 1e-5 * G  # (m g L: the swing's energy)
