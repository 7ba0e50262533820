"""The one time loop (constrained/solvers/driver.py): what every method gets from it —
output times, dense output, events located to round-off, the singular-configuration watch
at every size, the step limit and Ctrl-C — checked against closed forms."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import double_pendulum, planar_pendulum
from scipy.special import ellipk

import constrained as C
from constrained.solvers.dense import hermite

HARD = Path(__file__).resolve().parent.parent / "scenarios" / "hard"
G, L = 9.81, 1.0
#: The methods run by the driver on a Cartesian model, with settings for an accurate run.
ACCURATE = {
    "projection": dict(rtol=1e-12, atol=1e-12),
    "dopri": dict(rtol=1e-12, atol=1e-12, compiled=False),
    "baumgarte": dict(rtol=1e-12, atol=1e-12),
    "rattle": dict(dt=1e-4, compiled=False),
    "idas": dict(rtol=1e-10, atol=1e-10),
    "ggl": dict(rtol=1e-10, atol=1e-10),
    "pantelides": dict(rtol=1e-10, atol=1e-10),
}
#: How close each method's own solution is to the exact one at those settings (seconds or m).
ACCURACY = {"projection": 1e-9, "dopri": 1e-9, "baumgarte": 1e-8, "rattle": 1e-6, "idas": 1e-6,
            "ggl": 1e-6, "pantelides": 1e-6}


def quarter_period(theta0: float) -> float:
    """Time from rest at θ0 to the bottom: √(L/g) K(sin²(θ0/2)) (complete elliptic integral)."""
    return np.sqrt(L / G) * ellipk(np.sin(theta0 / 2) ** 2)


def test_quintic_hermite_is_exact_for_quintics(rng):
    c = rng.standard_normal((6, 3))
    t0, t1 = 0.3, 0.7

    def x(t):
        return sum(c[k] * t**k for k in range(6))

    def v(t):
        return sum(k * c[k] * t ** (k - 1) for k in range(1, 6))

    def a(t):
        return sum(k * (k - 1) * c[k] * t ** (k - 2) for k in range(2, 6))

    dense = hermite(t0, x(t0), v(t0), a(t0), t1, x(t1), v(t1), a(t1))
    for t in np.linspace(t0, t1, 7):
        xt, vt = dense(t)
        np.testing.assert_allclose(xt, x(t), atol=1e-13)
        np.testing.assert_allclose(vt, v(t), atol=1e-12)
    cubic = hermite(t0, x(t0), v(t0), None, t1, x(t1), v(t1), None)
    for t in (t0, t1):  # the cubic matches the ends' positions and velocities
        np.testing.assert_allclose(cubic(t)[0], x(t), atol=1e-13)
        np.testing.assert_allclose(cubic(t)[1], v(t), atol=1e-12)


@pytest.mark.parametrize("method", sorted(ACCURATE))
def test_every_method_locates_the_bottom_of_the_swing(method):
    """A pendulum from rest at θ0 = 90° reaches the bottom after √(L/g) K(1/2)."""
    bottom = C.Event("bottom", lambda t, x, v: x[0], direction=-1)
    tr = C.simulate(planar_pendulum(np.pi / 2), 2.0, method=method, events=[bottom],
                    **ACCURATE[method])
    exact = quarter_period(np.pi / 2)
    assert tr.info["stop"] == "terminal event" and tr.info["status"] == "completed"
    (hit,) = tr.info["events"]
    assert hit["name"] == "bottom"
    assert abs(hit["t"] - exact) < ACCURACY[method]
    assert tr.t[-1] == hit["t"] and abs(tr.x[-1, 0, 0]) < ACCURACY[method]
    # at the bottom all the potential energy is kinetic: v = √(2 g L)
    assert abs(np.linalg.norm(tr.v[-1, 0]) - np.sqrt(2 * G * L)) < 1e3 * ACCURACY[method]


@pytest.mark.parametrize("method", ["projection", "dopri", "rattle", "idas"])
def test_non_terminal_events_are_listed_with_their_direction(method):
    """Over three periods the bob passes the bottom six times, three of them moving left."""
    theta0 = 1.0
    period = 4 * quarter_period(theta0)
    both = C.Event("crossing", lambda t, x, v: x[0], terminal=False)
    left = C.Event("leftwards", lambda t, x, v: x[0], direction=-1, terminal=False)
    tr = C.simulate(planar_pendulum(theta0), 3 * period - 0.01, method=method, events=[both, left],
                    **ACCURATE[method])
    assert tr.info["stop"] == "completed"
    times = {name: [h["t"] for h in tr.info["events"] if h["name"] == name]
             for name in ("crossing", "leftwards")}
    expected = period / 4 + period / 2 * np.arange(6)
    np.testing.assert_allclose(times["crossing"], expected, atol=ACCURACY[method])
    np.testing.assert_allclose(times["leftwards"], expected[::2], atol=ACCURACY[method])


@pytest.mark.parametrize("method", sorted(ACCURATE))
def test_every_method_returns_the_requested_output_times(method):
    t_eval = np.linspace(0.0, 1.0, 11)
    reference = C.simulate(double_pendulum(), 1.0, method="dopri", rtol=1e-13, atol=1e-13, t_eval=t_eval,
                           compiled=False)
    tr = C.simulate(double_pendulum(), 1.0, method=method, t_eval=t_eval, **ACCURATE[method])
    np.testing.assert_array_equal(tr.t, t_eval)
    np.testing.assert_allclose(tr.x, reference.x, atol=1e3 * ACCURACY[method])


SINGULAR_METHODS = {"projection": {}, "dopri": dict(compiled=False), "baumgarte": {},
                    "rattle": dict(dt=1e-3, compiled=False), "idas": {}, "ggl": {}, "rodas": {}}


@pytest.mark.parametrize("method", sorted(SINGULAR_METHODS))
def test_every_method_stops_at_the_fourbar_limit_naming_the_constraints(method):
    """The crank of a non-Grashof four-bar is driven past its limit (scenarios/hard): coupler
    and rocker become collinear near t = 1.16 s; every method stops there with their names."""
    sc = C.load_scene(HARD / "fourbar_limit.toml")
    with pytest.raises(C.SimulationError) as err:
        C.simulate(sc.system, 3.0, method=method, **SINGULAR_METHODS[method])
    msg = str(err.value)
    assert "singular configuration" in msg and "'coupler BC'" in msg and "'rocker DC'" in msg
    partial = err.value.trajectory
    assert 1.0 < partial.t[-1] < 1.3 and np.all(np.isfinite(partial.x))


def test_the_singular_watch_covers_large_models():
    """The same four-bar beside 120 free particles (over 300 coordinates: the watch's sparse
    inverse iteration instead of the dense SVD) stops at the same place, naming the same rows."""
    sc = C.load_scene(HARD / "fourbar_limit.toml")
    system = sc.system
    for k in range(120):
        system.add_particle(f"spectator{k}", 1.0, [float(k), 5.0, 0.0])
    assert C.assemble(system).n_coordinates > 300
    with pytest.raises(C.SimulationError) as err:
        C.simulate(system, 3.0, method="dopri", compiled=False)
    msg = str(err.value)
    assert "singular configuration" in msg and "'coupler BC'" in msg and "'rocker DC'" in msg
    assert 1.0 < err.value.trajectory.t[-1] < 1.3


@pytest.mark.parametrize("method", sorted(ACCURATE))
def test_every_method_keeps_to_the_step_limit(method):
    """Stopped after its first call (a SUNDIALS call covers up to 200 outputs first)."""
    t_eval = np.linspace(0, 10, 1001)
    with pytest.raises(C.SimulationError, match="max_steps = 3") as err:
        C.simulate(double_pendulum(), 10.0, method=method, max_steps=3, t_eval=t_eval, **ACCURATE[method])
    kept = err.value.trajectory
    assert kept.t[-1] <= 2.0 and np.all(np.isfinite(kept.x))


@pytest.mark.parametrize("method", sorted(ACCURATE))
def test_a_run_that_reached_t_end_is_never_reported_stopped_early_by_the_step_limit(method):
    """dopri's compiled loop takes a chunk of steps per call: with max_steps = 5 it reached
    t_end in one call of 17 steps and raised 'stopped early ... (at t = 5 s)', the whole run in
    hand. Either the run ends before t_end at the limit, or it is complete and correct."""
    t_end = 2.0
    try:
        tr = C.simulate(double_pendulum(), t_end, method=method, max_steps=5, **ACCURATE[method])
    except C.SimulationError as err:
        assert "max_steps = 5" in str(err)
        assert err.trajectory.t[-1] < t_end
        return
    assert tr.success and tr.t[-1] == pytest.approx(t_end)
    reference = C.simulate(double_pendulum(), t_end, method=method, **ACCURATE[method])
    np.testing.assert_allclose(tr.x[-1], reference.x[-1], atol=1e-12)  # the same run, limit or not


@pytest.mark.parametrize("method", sorted(ACCURATE))
def test_every_method_stops_on_an_interrupt_keeping_what_it_computed(method):
    def stop(t):
        if t > 0.3:
            raise KeyboardInterrupt

    t_eval = np.linspace(0, 10, 1001)
    with pytest.raises(C.RunInterrupted) as err:
        C.simulate(double_pendulum(), 10.0, method=method, t_eval=t_eval, progress=stop, **ACCURATE[method])
    kept = err.value.trajectory
    assert 0.3 <= kept.t[-1] <= 2.0 and np.all(np.isin(kept.t, t_eval))
    assert kept.info["stop"] == "interrupted"


@pytest.mark.parametrize("method", ["projection", "dopri", "baumgarte", "idas", "ggl"])
def test_a_short_flight_lands_at_twice_the_rise_time(method):
    """Thrown up at u = 0.03 m/s from y = 0 (the gap starts at exactly zero), the particle is
    back at y = 0 after 2u/g: a flight far shorter than the run's steps."""
    s = C.System(name="hop")
    s.add_particle("p", 1.0, [0.0, 0.0, 0.0], [0.0, 0.03, 0.0])
    s.add(C.Plane("p", [0, 0, 1]), C.Gravity([0, -G, 0]))
    landing = C.Event("landing", lambda t, x, v: x[1], direction=-1)
    tr = C.simulate(s, 1.0, method=method, events=[landing], **ACCURATE[method])
    (hit,) = tr.info["events"]
    assert abs(hit["t"] - 2 * 0.03 / G) < ACCURACY[method]
    assert abs(hit["v"][1] + 0.03) < 1e3 * ACCURACY[method]  # it comes down as fast as it went up


def test_the_sparse_singular_watch_of_a_large_model_agrees_with_the_dense_svd():
    """Beyond DENSE_WATCH_MAX coordinates the watch takes σ of the row-normalized J by inverse
    iteration on a sparse LU, its J from the vectorized build (``sparse_jacobian``): at a
    rope's nearly straight-and-taut configuration (a 120-link rope between two pins, its
    middle bead lifted by 1e-4 m) σ and the rows it names equal the dense SVD's."""
    from constrained.manifold import diagnostics
    from constrained.manifold.manifold import Manifold
    from constrained.solvers import watches

    n, link = 120, 0.01
    s = C.System(name="taut rope")
    for i in range(n):
        lift = 1e-4 if i == n // 2 else 0.0
        s.add_particle(f"p{i}", 0.01, [link * (i + 1), lift, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=link))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=float(np.hypot(link, 1e-4 if i in (n // 2, n // 2 + 1)
                                                                       else 0.0))))
    s.add(C.Distance(f"p{n - 1}", point=[link * (n + 1), 0, 0], length=link))
    model = C.assemble(s)
    assert model.n_coordinates > watches.DENSE_WATCH_MAX
    rows = list(range(model.n_constraints))
    watch = watches.SingularWatch(Manifold(model), rows, tol=1e-6)
    assert not watch.dense
    x = np.asarray(s.positions, float).ravel()
    sparse = watch.singularity(x, 0.0)
    dense = diagnostics.singularity(model, x, 0.0, rank=len(rows))
    assert sparse.sigma == pytest.approx(dense.sigma, rel=1e-3) and dense.sigma < 1e-2
    assert set(sparse.rows) == set(dense.rows)
