"""Least action on scenes nobody in this repository chose (docs/hard-cases.md, section 17):
closed forms for the oscillator, the rotor, the bouncing ball and a time-dependent force;
conjugate points; one-sided constraints; bad input to stationary_path and to `constrained path`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import constrained as C
from constrained.analysis.action import action, stationary_path
from constrained.cli.main import main
from constrained.errors import InputError, SimulationError

G = 9.81


def oscillator(m: float = 2.0, k: float = 8.0, x0: float = 0.3) -> C.System:
    s = C.System(name="oscillator")
    s.add_particle("a", m, [x0, 0.0, 0.0])
    s.add(C.Spring("a", point=[0.0, 0.0, 0.0], k=k))
    return s


def oscillator_action(m: float, w: float, x0: float, x1: float, T: float) -> float:
    """S = (m ω / 2 sin ωT) [(x0² + x1²) cos ωT − 2 x0 x1] (the classical action)."""
    return m * w / (2 * np.sin(w * T)) * ((x0**2 + x1**2) * np.cos(w * T) - 2 * x0 * x1)


def rotor(m: float = 1.5, l: float = 0.8) -> C.System:
    """A particle on a circle of radius l in z = 0, no gravity: S = m l² Δθ² / (2T) per winding."""
    s = C.System(name="rotor")
    s.add_particle("bob", m, [l, 0.0, 0.0])
    s.add(C.Distance("bob", point=[0, 0, 0], length=l), C.Plane("bob", [0, 0, 1]))
    return s


def on_circle(theta, l: float = 0.8) -> np.ndarray:
    theta = np.atleast_1d(theta)
    return np.stack([l * np.cos(theta), l * np.sin(theta), 0 * theta], axis=-1)[:, None, :]


# --- the oscillator: closed-form action, minimum before and saddle after the conjugate point ---


@pytest.mark.parametrize("wT_over_pi", [0.3, 0.9, 1.3])
def test_oscillator_path_action_and_conjugate_margin(wT_over_pi):
    m, k, x0, x1 = 2.0, 8.0, 0.3, -0.1
    w = np.sqrt(k / m)
    T = wT_over_pi * np.pi / w
    r = stationary_path(oscillator(m, k, x0), [[x0, 0, 0]], [[x1, 0, 0]], T, nodes=200)
    S = oscillator_action(m, w, x0, x1, T)
    assert r.action == pytest.approx(S, rel=2e-3, abs=2e-4)
    # the nodes lie on x(t) = [x0 sin ω(T − t) + x1 sin ωt] / sin ωT, to O(h²)
    exact = (x0 * np.sin(w * (T - r.t)) + x1 * np.sin(w * r.t)) / np.sin(w * T)
    assert np.abs(r.x[:, 0, 0] - exact).max() < 1e-3
    # second variation over the kinetic term's: (π²/T² − ω²)/(π²/T²) = 1 − (ωT/π)²
    assert r.conjugate_margin == pytest.approx(1 - wT_over_pi**2, abs=1e-3)
    assert r.is_minimum == (wT_over_pi < 1)
    assert not r.near_conjugate


def test_oscillator_at_the_conjugate_point_is_refused_not_answered():
    """At T = π/ω the ends x0 = 0.3, x1 = −0.1 are joined by no motion (x(π/ω) = −x0 for all):
    the discrete system is singular and IPOPT's answer (S_d ~ −1e3) means nothing."""
    m, k = 2.0, 8.0
    T = np.pi / np.sqrt(k / m)
    with pytest.raises(SimulationError, match="conjugate point") as err:
        stationary_path(oscillator(m, k), [[0.3, 0, 0]], [[-0.1, 0, 0]], T, nodes=200)
    assert abs(err.value.path.conjugate_margin) < (np.pi / 200) ** 2


@pytest.mark.parametrize("wT_over_pi", [0.999, 1.001])
def test_oscillator_next_to_the_conjugate_point_is_flagged(wT_over_pi):
    m, k = 2.0, 8.0
    T = wT_over_pi * np.pi / np.sqrt(k / m)
    r = stationary_path(oscillator(m, k), [[0.3, 0, 0]], [[-0.1, 0, 0]], T, nodes=200)
    assert r.conjugate_margin == pytest.approx(1 - wT_over_pi**2, rel=0.1)
    assert r.near_conjugate and "conjugate point" in r.summary()
    assert r.is_minimum == (wT_over_pi < 1)  # the sign is still resolved: a saddle past π/ω


def test_action_of_an_oscillator_run_matches_the_closed_form():
    m, k, x0, T = 2.0, 8.0, 0.3, 2.0  # ωT = 4 > π: past the conjugate point, S still the closed form
    traj = C.simulate(oscillator(m, k, x0), T, rtol=1e-11, atol=1e-12, t_eval=np.linspace(0, T, 2001))
    x1 = x0 * np.cos(np.sqrt(k / m) * T)
    assert traj.x[-1, 0, 0] == pytest.approx(x1, abs=1e-8)
    assert action(oscillator(m, k, x0), traj).total == pytest.approx(
        oscillator_action(m, np.sqrt(k / m), x0, x1, T), rel=1e-8)


# --- the rotor: two ways round, closed paths ---------------------------------------------------


@pytest.mark.parametrize("dtheta", [np.pi / 2, -1.5 * np.pi, 0.0, 2 * np.pi, np.pi])
def test_rotor_paths_between_two_angles(dtheta):
    """Every winding is a stationary path with S = m l² Δθ²/(2T), all minima (δ²S = m l² ∫ δθ'²);
    equal ends give rest (S = 0) or a full turn."""
    m, l, T, K = 1.5, 0.8, 1.0, 100
    start, end = 0.3, 0.3 + dtheta
    guess = on_circle(np.linspace(start, end, K + 1)) if dtheta != 0.0 else None
    r = stationary_path(rotor(m, l), on_circle(start)[0], on_circle(end)[0], T, nodes=K, guess=guess)
    S = m * l**2 * dtheta**2 / (2 * T)
    assert r.action == pytest.approx(S, rel=1e-3, abs=1e-12)
    assert np.allclose(np.linalg.norm(r.x[:, 0], axis=1), l, atol=1e-9)
    assert r.is_minimum and r.conjugate_margin == pytest.approx(1.0, abs=1e-2)


def test_rotor_antipodal_straight_start_is_refused_not_a_jump():
    """The straight line between opposite points passes through the pivot; projected node by node it
    is a step (rest, a jump of π, rest), and IPOPT converged on it as a discrete stationary point with
    S_d = 192 J·s (the true motions have m l² π²/2T = 4.7 J·s): now refused, naming the jump."""
    with pytest.raises(SimulationError, match="not resolved.*guess="):
        stationary_path(rotor(), on_circle(0.3)[0], on_circle(0.3 + np.pi)[0], 1.0, nodes=100)


# --- a time-dependent potential and a bouncing ball --------------------------------------------


def test_time_dependent_force_path_is_the_cubic():
    """V = −a t x: m x'' = a t, x = c t + a t³/(6m), exact at the nodes (the discrete equations are
    m Δ²x/h² = a t_k, which a cubic satisfies: its central second difference is exact)."""
    m, a, T, x1 = 2.0, 3.0, 1.5, 1.0
    s = C.System(name="pushed")
    s.add_particle("p", m, [0.0, 0.0, 0.0])
    s.add(C.Potential(f"-{a}*t*x_p"))
    c = (x1 - a * T**3 / (6 * m)) / T
    b = a / (6 * m)  # x = c t + b t³, v = c + 3 b t²; S = ∫ ½ m v² + a t x dt
    S = 0.5 * m * (c**2 * T + 2 * c * b * T**3 + 9 * b**2 * T**5 / 5) + a * (c * T**3 / 3 + b * T**5 / 5)
    for quadrature in ("midpoint", "trapezoid"):
        r = stationary_path(s, [[0, 0, 0]], [[x1, 0, 0]], T, nodes=200, quadrature=quadrature)
        assert np.abs(r.x[:, 0, 0] - (c * r.t + a * r.t**3 / (6 * m))).max() < 1e-9
        assert r.action == pytest.approx(S, rel=1e-4)


def test_action_of_a_bouncing_ball_and_no_path_through_a_one_sided_floor():
    s = C.System(name="ball")
    s.add_particle("a", 1.0, [0.0, 1.0, 0.0])
    s.add(C.Plane("a", [0, 1, 0], unilateral=True, restitution=1.0, name="floor"), C.Gravity([0, -G, 0]))
    traj = C.simulate(s, 1.0, rtol=1e-10, atol=1e-12, t_eval=np.linspace(0, 1, 1001))
    # fall from rest, elastic bounce at √(2/g): L = v² − g (E = g·1 m), ∫₀^τ (g² t² − g) dt per fall
    th = np.sqrt(2 / G)

    def fall(t):
        return G**2 * t**3 / 3 - G * t

    assert action(s, traj).total == pytest.approx(2 * fall(th) + fall(1.0 - 2 * th), rel=1e-5)
    with pytest.raises(InputError, match="'floor' is one-sided"):
        stationary_path(s, [[0, 1, 0]], [[0.5, 1, 0]], 1.0, nodes=50)


# --- bad input ----------------------------------------------------------------------------------


@pytest.mark.parametrize("guess, match", [
    (np.zeros((5, 1, 3)), "positions at the 11 nodes"),
    (np.full((11, 1, 3), np.nan), "non-finite"),
    ("abc", "Trajectory or an array"),
])
def test_bad_guess_is_input_error(guess, match):
    with pytest.raises(InputError, match=match):
        stationary_path(rotor(), on_circle(0)[0], on_circle(1)[0], 1.0, nodes=10, guess=guess)


@pytest.mark.parametrize("T", [1e300, 1e-300])
def test_unrepresentable_time_step_is_input_error(T):
    with pytest.raises(InputError, match="time step"):
        stationary_path(rotor(), on_circle(0)[0], on_circle(1)[0], T, nodes=10)


@pytest.mark.parametrize("time", ["1e300", "1e-300"])
def test_cli_path_extreme_time_exits_2(tmp_path: Path, capsys, time):
    scene = Path(__file__).resolve().parents[1] / "scenarios" / "simple_pendulum.toml"
    out = tmp_path / "out"
    assert main(["path", str(scene), "--to", "bob=[0,-1,0]", "--time", time, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "time step" in err and "Traceback" not in err
    assert not (out / "path.npz").exists()


# --- stationarity with one-sided constraints: per segment, with the rows held there ---------------


def bouncing_ball(T: float = 1.6, samples: int = 3201):
    s = C.System(name="ball")
    s.add_particle("a", 1.0, [0.0, 1.0, 0.0])
    s.add(C.Plane("a", [0, 1, 0], unilateral=True, restitution=1.0, name="floor"), C.Gravity([0, -G, 0]))
    return s, C.simulate(s, T, rtol=1e-11, atol=1e-12, t_eval=np.linspace(0, T, samples))


def test_bouncing_ball_is_stationary_against_vertical_variations_in_flight():
    s, traj = bouncing_ball()
    r = C.stationarity(s, traj)
    assert r.is_stationary and r.order > 1.8
    # the pieces are the flights between the elastic impacts at √(2/g)(1 + 2k)
    th = np.sqrt(2 / G)
    assert [p[0] for p in r.pieces[1:]] == pytest.approx([th, 3 * th], abs=1e-8)
    # in flight the floor is not held: the ball is varied vertically, not only along the floor
    flight = (traj.t > 0.1) & (traj.t < th - 0.1)
    assert np.abs(r.variation[flight, 0, 1]).max() > 0.1 * r.scale
    # and η vanishes at the impact instants
    at_impact = np.abs(traj.t - th) < 1e-3
    assert np.abs(r.variation[at_impact]).max() < 1e-4 * r.scale


def test_bouncing_ball_with_a_wrong_flight_is_not_stationary():
    """Between the first two impacts the ball follows y = v0 τ − 0.45 g τ² (0.9 g, same impact
    times): its δS is ∫ m (−g − y'') η_y dt = −0.1 m g ∫ η_y dt on that flight. ε is small enough
    that ε·δ²S/2 (δ²S ~ 2e2 J·s here) stays below that δS, so ΔS is first order."""
    s, traj = bouncing_ball()
    th = np.sqrt(2 / G)
    t1, t2 = th, 3 * th
    wrong = traj.head(len(traj.t))
    x, v = wrong.x.copy(), wrong.v.copy()
    tau = traj.t - t1
    mid = (traj.t > t1) & (traj.t < t2)
    v0 = 0.45 * G * (t2 - t1)
    x[mid, 0, 1] = v0 * tau[mid] - 0.45 * G * tau[mid] ** 2
    v[mid, 0, 1] = v0 - 0.9 * G * tau[mid]
    wrong.x, wrong.v = x, v
    r = C.stationarity(s, wrong, eps_list=(1e-4, 5e-5, 2.5e-5, 1.25e-5))
    assert not r.is_stationary and r.order < 1.3
    eta_y = np.where(mid, r.variation[:, 0, 1], 0.0)
    expected = -0.1 * 1.0 * G * np.trapezoid(eta_y, traj.t)
    assert r.first_variation == pytest.approx(expected, rel=1e-2)


def test_one_sided_run_without_segments_is_refused():
    s, traj = bouncing_ball(0.5, 501)
    bare = traj.head(len(traj.t))
    bare.info = {}
    with pytest.raises(InputError, match="one-sided"):
        C.stationarity(s, bare)
    r = C.stationarity(s, bare, segments=traj.info["segments"])
    assert r.is_stationary


def test_pendulum_without_one_sided_rows_is_one_piece_as_before():
    """No one-sided rows: one piece over the whole run, projected on the rod (η ⟂ the rod)."""
    s = C.System(name="pendulum")
    s.add_particle("bob", 1.0, [0.8, -0.6, 0.0])
    s.add(C.Distance("bob", point=[0, 0, 0], length=1.0), C.Gravity([0, -G, 0]))
    traj = C.simulate(s, 1.5, rtol=1e-11, atol=1e-12, t_eval=np.linspace(0, 1.5, 1501))
    r = C.stationarity(s, traj)
    assert r.is_stationary and r.pieces == [(0.0, 1.5)]
    radial = np.einsum("ij,ij->i", r.variation[:, 0], traj.x[:, 0])
    assert np.abs(radial).max() < 1e-9 * r.scale
    # the same swing with gravity 0.9 g (a wrong motion for this system) is not stationary
    s_weak = C.System(name="pendulum")
    s_weak.add_particle("bob", 1.0, [0.8, -0.6, 0.0])
    s_weak.add(C.Distance("bob", point=[0, 0, 0], length=1.0), C.Gravity([0, -0.9 * G, 0]))
    weak = C.simulate(s_weak, 1.5, rtol=1e-11, atol=1e-12, t_eval=np.linspace(0, 1.5, 1501))
    weak.multipliers = None
    assert not C.stationarity(s, weak).is_stationary


# --- one-sided rows held on a segment: the variations stay on the surface -------------------------

ALPHA, SLIDER = 0.4, 2.0  # incline angle (rad), mass (kg)
NORMAL = np.array([-np.sin(ALPHA), np.cos(ALPHA), 0.0])    # out of the incline
DOWNHILL = -np.array([np.cos(ALPHA), np.sin(ALPHA), 0.0])  # along it, downwards


def sliding_down_an_incline(T: float = 1.0, samples: int = 2001):
    """A block released at rest on a smooth one-sided incline through the origin: it slides
    down at g sin α, held by the incline's push N = m g cos α the whole run."""
    s = C.System(name="incline")
    s.add_particle("a", SLIDER, [0.0, 0.0, 0.0])
    s.add(C.Plane("a", list(NORMAL), unilateral=True, name="incline"), C.Gravity([0, -G, 0]))
    return s, C.simulate(s, T, rtol=1e-11, atol=1e-12, t_eval=np.linspace(0, T, samples),
                         outputs=["multipliers"])


def test_a_block_on_a_one_sided_incline_is_stationary_against_variations_along_it():
    s, traj = sliding_down_an_incline()
    assert traj.info["segments"] == [{"t_start": 0.0, "t_end": 1.0, "held": ["incline [a]"], "dof": 2}]
    assert np.abs(traj.x[:, 0] - 0.5 * G * np.sin(ALPHA) * traj.t[:, None] ** 2 * DOWNHILL).max() < 1e-12
    r = C.stationarity(s, traj)
    assert r.is_stationary and r.order > 1.9 and r.pieces == [(0.0, 1.0)]
    # the held row projects η onto the incline: no component along its normal, some along it
    assert np.abs(r.variation[:, 0] @ NORMAL).max() < 1e-12 * r.scale
    assert np.abs(r.variation[:, 0] @ DOWNHILL).max() > 0.1 * r.scale


def test_a_block_sliding_at_nine_tenths_of_g_sin_alpha_is_not_stationary():
    """The path x = ½ (0.9 g sin α) t² along the incline: δS = −∫ m (ẍ + g ŷ)·η dt
    = 0.1 m g sin α ∫ η·d dt (η in the incline: the push N does no work on it)."""
    s, traj = sliding_down_an_incline()
    wrong = traj.head(len(traj.t))
    a = 0.9 * G * np.sin(ALPHA)
    wrong.x = (0.5 * a * traj.t**2)[:, None, None] * DOWNHILL
    wrong.v = (a * traj.t)[:, None, None] * DOWNHILL
    r = C.stationarity(s, wrong, eps_list=(1e-4, 5e-5, 2.5e-5, 1.25e-5))
    assert not r.is_stationary and r.order < 1.3
    expected = 0.1 * SLIDER * G * np.sin(ALPHA) * np.trapezoid(r.variation[:, 0] @ DOWNHILL, traj.t)
    assert r.first_variation == pytest.approx(expected, rel=1e-3)


def test_dropping_the_held_incline_lets_the_variation_leave_it_and_the_push_does_work():
    """Told that the incline is not held, the check varies the block off the surface as well,
    with λ = 0 for it: the true motion then has δS = −N ∫ η·n dt, N = m g cos α, and fails."""
    s, traj = sliding_down_an_incline()
    loose = [{"t_start": 0.0, "t_end": 1.0, "held": []}]
    r = C.stationarity(s, traj, segments=loose, eps_list=(1e-4, 5e-5, 2.5e-5, 1.25e-5))
    off = r.variation[:, 0] @ NORMAL
    assert np.abs(off).max() > 0.1 * r.scale
    assert not r.is_stationary
    expected = -SLIDER * G * np.cos(ALPHA) * np.trapezoid(off, traj.t)
    assert r.first_variation == pytest.approx(expected, rel=1e-3)


def test_a_plastic_landing_is_held_on_the_floor_after_the_impact():
    """A ball thrown level from 0.5 m lands plastically (e = 0) at √(2 h/g) and slides: in
    flight it is varied in every direction, on the floor only along it. Dropping the floor from
    the sliding segment gives δS = −m g ∫ η_y dt there (the floor's push, m g)."""
    m, h = 0.5, 0.5
    s = C.System(name="landing")
    s.add_particle("a", m, [0.0, h, 0.0], [1.2, 0.0, 0.0])
    s.add(C.Plane("a", [0, 1, 0], unilateral=True, restitution=0.0, name="floor"), C.Gravity([0, -G, 0]))
    traj = C.simulate(s, 1.0, rtol=1e-11, atol=1e-12, t_eval=np.linspace(0, 1, 2001), outputs=["multipliers"])
    landing = np.sqrt(2 * h / G)
    assert [seg["held"] for seg in traj.info["segments"]] == [[], ["floor [a]"]]
    assert traj.info["segments"][1]["t_start"] == pytest.approx(landing, abs=1e-9)
    r = C.stationarity(s, traj)
    assert r.is_stationary and r.order > 1.9
    sliding = traj.t > landing
    assert np.abs(r.variation[sliding, 0, 1]).max() < 1e-12 * r.scale
    assert np.abs(r.variation[~sliding, 0, 1]).max() > 0.1 * r.scale
    loose = [dict(seg) for seg in traj.info["segments"]]
    loose[1]["held"] = []
    r = C.stationarity(s, traj, segments=loose)
    eta_y = np.where(sliding, r.variation[:, 0, 1], 0.0)
    assert not r.is_stationary
    assert r.first_variation == pytest.approx(-m * G * np.trapezoid(eta_y, traj.t), rel=1e-3)


# --- a run saved to a file keeps its segments -----------------------------------------------------

BALL_SCENE = """
[scene]
name = "ball on a floor"
[[particles]]
name = "a"
mass = 1.0
position = [0.0, 1.0, 0.0]
[[constraints]]
name = "floor"
type = "plane"
particles = ["a"]
normal = [0.0, 1.0, 0.0]
unilateral = true
restitution = 0.7
[[effects]]
type = "gravity"
g = [0.0, -9.81, 0.0]
[simulate]
t_end = 1.6
rtol = 1e-11
atol = 1e-12
output_dt = 0.0005
[outputs]
quantities = ["energy"]
plots = []
"""


def bouncing_ball_run(tmp_path: Path):
    """The ball (e = 0.7) run by `constrained run`, which saves no multipliers unless asked, and
    the same scene in memory."""
    scene = tmp_path / "ball.toml"
    scene.write_text(BALL_SCENE)
    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    saved = C.Trajectory.load(tmp_path / "out" / "trajectory.npz")
    system = C.load_scene(scene).system
    return system, saved, C.simulate(system, 1.6, rtol=1e-11, atol=1e-12, t_eval=saved.t,
                                     outputs=["multipliers"])


def test_a_bouncing_ball_reloaded_from_its_file_gives_the_same_stationarity(tmp_path):
    system, saved, live = bouncing_ball_run(tmp_path)
    assert saved.multipliers is None and saved.info["segments"] == live.info["segments"]
    # impacts at √(2/g), then each flight e times the one before
    first = np.sqrt(2 / G)
    assert [seg["t_start"] for seg in saved.info["segments"][1:3]] == pytest.approx(
        [first, first + 2 * 0.7 * first], abs=1e-8)
    r_live, r_saved = C.stationarity(system, live), C.stationarity(system, saved)
    assert r_live.is_stationary and r_saved.is_stationary and r_live.order > 1.8
    assert r_saved.pieces == r_live.pieces
    np.testing.assert_allclose(r_saved.delta_S, r_live.delta_S, rtol=1e-9, atol=1e-15)
    assert r_saved.first_variation == pytest.approx(r_live.first_variation, rel=1e-6, abs=1e-12)


def test_an_incline_run_saved_without_multipliers_takes_them_from_its_held_rows(tmp_path):
    """No multipliers in the file: on each segment they come from the KKT system of the rows it
    holds (the incline pushes with m g cos α), and the check gives the in-memory numbers."""
    s, traj = sliding_down_an_incline()
    path = traj.save(tmp_path / "incline.npz", quantities=["energy"])
    saved = C.Trajectory.load(path)
    assert saved.multipliers is None
    np.testing.assert_allclose(traj.multipliers[:, 0], SLIDER * G * np.cos(ALPHA), rtol=1e-9)
    r_live, r_saved = C.stationarity(s, traj), C.stationarity(s, saved)
    np.testing.assert_allclose(r_saved.delta_S, r_live.delta_S, rtol=1e-8)
    assert r_saved.second_variation == pytest.approx(r_live.second_variation, rel=1e-8)


def _rewrite_segments(path: Path, edit) -> None:
    import json

    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays["meta"]))
    edit(meta["info"])
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(path, **arrays)


@pytest.mark.parametrize("edit, key, why", [
    (lambda info: info["segments"][1].update(t_end=99.0), "info['segments'][1]", "outside the run"),
    (lambda info: info["segments"][1].update(t_start="soon"), "info['segments'][1]['t_start']",
     "not a time"),
    (lambda info: info["segments"][1].update(held=["no such row"]), "info['segments'][1]['held']",
     "not a constraint row"),
    (lambda info: info["segments"][1].update(t_start=0.0), "info['segments'][1]", "before segment 0 ends"),
    (lambda info: info["segments"][0].update(t_end=-1.0), "info['segments'][0]", "before it starts"),
    (lambda info: info.update(segments={"t_start": 0}), "info['segments']", "not a list"),
])
def test_a_damaged_segments_entry_is_refused_naming_the_file_and_key(tmp_path, edit, key, why):
    _, traj = bouncing_ball(0.9, 901)
    path = traj.save(tmp_path / "ball.npz")
    _rewrite_segments(path, edit)
    with pytest.raises(InputError) as err:
        C.Trajectory.load(path)
    text = str(err.value)
    assert str(path) in text and key in text and why in text and "run the scene again" in text


def test_an_old_file_without_segments_loads_and_is_refused_as_before(tmp_path):
    s, traj = bouncing_ball(0.9, 901)
    path = traj.save(tmp_path / "ball.npz")
    _rewrite_segments(path, lambda info: info.pop("segments"))
    old = C.Trajectory.load(path)
    assert "segments" not in old.info and np.array_equal(old.x, traj.x)
    with pytest.raises(InputError, match="does not say where each one is held"):
        C.stationarity(s, old)
    assert C.stationarity(s, old, segments=traj.info["segments"]).is_stationary


def test_segments_given_by_hand_are_checked_against_the_run():
    s, traj = bouncing_ball(0.5, 501)
    with pytest.raises(InputError, match=r"segments=\[0\] spans t = 0 \.\. 7 s, outside the run"):
        C.stationarity(s, traj, segments=[{"t_start": 0.0, "t_end": 7.0, "held": []}])
    with pytest.raises(InputError, match=r"segments=\[0\]\['held'\] names 'wall'"):
        C.stationarity(s, traj, segments=[{"t_start": 0.0, "t_end": 0.5, "held": ["wall"]}])
