"""The solver family: accuracy on the reference, drift control, long-run energy behaviour."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DP_REF_T2, double_pendulum
from test_vectorized import rope

import constrained as C
from constrained.solvers import METHODS


def driven_pendulum() -> C.System:
    s = C.System(name="driven pivot")
    s.add_particle("bob", 1.0, [np.sin(0.5), -np.cos(0.5), 0.0])
    s.add(C.Distance("bob", point=["0.2*sin(3*t)", "0", "0"], length=1.0),
          C.Plane("bob", [0, 0, 1]), C.Gravity([0, -9.81, 0]))
    return s


@pytest.mark.parametrize("method, settings, max_error", [
    ("projection", dict(rtol=1e-12, atol=1e-12), 1e-9),
    ("projection", dict(rtol=1e-12, atol=1e-12, base="CVODES"), 1e-9),
    ("baumgarte", dict(rtol=1e-12, atol=1e-12), 1e-9),
    ("idas", dict(rtol=1e-13, atol=1e-13), 1e-9),
    ("ggl", dict(rtol=1e-12, atol=1e-12), 1e-9),
])
def test_adaptive_methods_reach_the_reference_at_t2(method, settings, max_error):
    tr = C.simulate(double_pendulum(), 2.0, method=method, t_eval=np.linspace(0, 2, 21), **settings)
    assert np.max(np.abs(tr.x[-1, :, :2] - DP_REF_T2)) <= max_error
    assert tr.stats["steps"] > 0 and tr.stats["nfev"] > 0
    if method != "baumgarte":
        assert np.max(tr.constraint_residual) <= 1e-10


def test_baumgarte_feedback_controls_the_drift():
    t = np.linspace(0, 10, 201)
    with_feedback = C.simulate(double_pendulum(), 10.0, method="baumgarte", rtol=1e-6, atol=1e-6, t_eval=t)
    without = C.simulate(double_pendulum(), 10.0, method="baumgarte", rtol=1e-6, atol=1e-6, t_eval=t,
                         alpha=0.0, beta=0.0)
    drift_fb = np.max(with_feedback.constraint_residual)
    drift_raw = np.max(without.constraint_residual)
    assert drift_raw > 10 * drift_fb  # the bare index-1 ODE drifts away
    # with feedback the violation does not accumulate: the end is no worse than the worst
    assert with_feedback.constraint_residual[-1] < 0.1 * without.constraint_residual[-1]


@pytest.mark.parametrize("method, settings", [
    ("baumgarte", dict(rtol=1e-11, atol=1e-12)),
    ("idas", dict(rtol=1e-12, atol=1e-12)),
    ("ggl", dict(rtol=1e-11, atol=1e-10)),
    ("rattle", dict(dt=2e-4)),
])
def test_methods_agree_with_projection_on_a_rheonomic_scene(method, settings):
    t = np.linspace(0, 2, 11)
    ref = C.simulate(driven_pendulum(), 2.0, rtol=1e-12, atol=1e-12, t_eval=t)
    tr = C.simulate(driven_pendulum(), 2.0, method=method, t_eval=t, **settings)
    tol = 1e-6 if method == "rattle" else 1e-7
    np.testing.assert_allclose(tr.x, ref.x, atol=tol)
    np.testing.assert_allclose(tr.multipliers, ref.multipliers, atol=tol * 1e3)


def test_rattle_is_second_order():
    errors = []
    for dt in (4e-3, 2e-3):
        tr = C.simulate(double_pendulum(0.3, -0.2), 1.0, method="rattle", dt=dt, t_eval=[0, 1.0])
        ref = C.simulate(double_pendulum(0.3, -0.2), 1.0, rtol=1e-12, atol=1e-12, t_eval=[0, 1.0])
        errors.append(np.max(np.abs(tr.x[-1] - ref.x[-1])))
    assert 3.5 < errors[0] / errors[1] < 4.5


@pytest.mark.slow
def test_rattle_long_run_energy_stays_bounded():
    """1000 s of the chaotic double pendulum at dt = 1e-3: a million steps in compiled code."""
    tr = C.simulate(double_pendulum(), 1000.0, method="rattle", dt=1e-3,
                    outputs={"energy", "constraint_residual"})
    err = np.abs(tr.energy - tr.energy[0])
    # the error oscillates (its 100 s maxima wander between ~1e-3 and ~2.5e-3 on this chaotic
    # run); a secular drift would grow with t: compare the halves' envelopes
    first = err[tr.t <= 500].max()
    last = err[tr.t >= 500].max()
    assert last <= 2 * first
    assert first < 1e-2  # O(dt²) energy error, no secular growth
    assert np.max(tr.constraint_residual) <= 1e-10
    assert tr.stats["steps"] == 1_000_000


def test_every_method_has_counters_and_refuses_bad_arguments():
    from conftest import SCENARIOS

    from constrained.run.reduced import ReducedModel

    rm = ReducedModel.from_scene(C.load_scene(SCENARIOS / "double_pendulum.toml"))
    extra = {"rattle": {"dt": 1e-2}, "reduced": {"reduced_model": rm}}
    for name in METHODS:
        tr = C.simulate(double_pendulum(), 0.1, method=name, **extra.get(name, {}))
        assert tr.stats["steps"] > 0 and "wall_time_s" in tr.stats
    with pytest.raises(C.InputError, match="give dt"):
        C.simulate(double_pendulum(), 0.1, method="rattle")
    with pytest.raises(C.InputError, match="unknown method"):
        C.simulate(double_pendulum(), 0.1, method="euler")
    with pytest.raises(C.InputError, match="does not take the option"):
        C.simulate(double_pendulum(), 0.1, method="projection", alpha=3.0)


@pytest.mark.parametrize("method", ["dopri", "rattle", "baumgarte", "idas", "ggl", "pantelides", "rodas"])
def test_every_method_takes_the_redundant_cube(method):
    """28 distances, 18 independent: each method solves with an independent subset (the
    manifold's rows), keeps the cube rigid and its angular momentum, and follows projection."""
    from test_core_physics import spinning_cube

    cube, masses = spinning_cube()
    t = np.linspace(0, 0.5, 6)
    ref = C.simulate(cube, 0.5, rtol=1e-10, atol=1e-12, t_eval=t)
    opts = {"dt": 1e-4, "t_eval": None} if method == "rattle" else {"t_eval": t}
    # GGL's index-2 corrector fails below atol 1e-10 (see solvers.sundials.idas.GGL)
    atol = 1e-10 if method == "ggl" else 1e-12
    tr = C.simulate(cube, 0.5, method=method, rtol=1e-10, atol=atol, **opts)
    if method == "rattle":
        tr_x, tr_v = tr.x[::len(tr.t) // 5], tr.v[::len(tr.t) // 5]
        assert np.allclose(tr.t[::len(tr.t) // 5], t)
    else:
        tr_x, tr_v = tr.x, tr.v
    # baumgarte damps drift, ggl and pantelides keep it at the IDAS tolerance; the rest project
    drift = {"baumgarte": 1e-5, "ggl": 1e-7, "pantelides": 1e-7}.get(method, 1e-9)
    assert np.max(tr.constraint_residual) < drift
    tol = 1e-5 if method in ("rattle", "baumgarte") else 1e-7
    assert np.max(np.abs(tr_x - ref.x)) < tol
    com_v = np.einsum("n,tnk->tk", masses, tr_v) / masses.sum()
    com = np.einsum("n,tnk->tk", masses, tr_x) / masses.sum()
    L = np.einsum("n,tnk->tk", masses, np.cross(tr_x - com[:, None], tr_v - com_v[:, None]))
    assert np.max(np.abs(L - L[0])) < 10 * tol * np.max(np.abs(L[0]))
    # the multipliers are the minimum-norm ones over all 28 rows, whichever method ran
    lam = C.simulate(cube, 0.5, method=method, rtol=1e-10, atol=atol,
                     **({"dt": 1e-4} if method == "rattle" else {})).multipliers
    assert lam.shape[1] == 28 and np.all(np.isfinite(lam))


def test_reduced_method_reaches_the_reference_and_maps_back_to_the_constraints():
    from conftest import SCENARIOS

    from constrained.run.reduced import ReducedModel

    scene = C.load_scene(SCENARIOS / "double_pendulum.toml")
    exact = double_pendulum()  # the reference's exact angles, carried into q by the method
    rm = ReducedModel.from_scene(scene)
    tr = C.simulate(exact, 2.0, method="reduced", reduced_model=rm, rtol=1e-12, atol=1e-12,
                    t_eval=[0.0, 1.0, 2.0])
    assert np.max(np.abs(tr.x[-1, :, :2] - DP_REF_T2)) <= 1e-9
    assert np.max(tr.constraint_residual) <= 1e-14  # the map satisfies the constraints exactly
    with pytest.raises(C.InputError, match="needs generalized coordinates"):
        C.simulate(exact, 0.1, method="reduced")


@pytest.mark.parametrize("system", [double_pendulum, driven_pendulum])
def test_pantelides_agrees_with_projection(system):
    t = np.linspace(0, 2, 11)
    ref = C.simulate(system(), 2.0, rtol=1e-12, atol=1e-12, t_eval=t)
    tr = C.simulate(system(), 2.0, method="pantelides", rtol=1e-12, atol=1e-12, t_eval=t)
    assert tr.stats["index"] == 3  # CasADi found the index of the raw DAE
    np.testing.assert_allclose(tr.x, ref.x, atol=1e-7)
    assert np.max(tr.constraint_residual) <= 1e-10


@pytest.mark.parametrize("method, settings", [
    ("rattle", dict(dt=1e-3)), ("idas", dict(rtol=1e-8)), ("projection", {}),
    ("projection", dict(base="CVODES")), ("baumgarte", {}),
])
def test_solvers_report_their_progress_in_simulated_time(method, settings):
    reached = []
    C.simulate(double_pendulum(), 1.0, method=method, t_eval=np.linspace(0, 1, 11),
               progress=reached.append, **settings)
    assert len(reached) >= 5 and np.all(np.diff(reached) > 0)
    assert reached[-1] == pytest.approx(1.0)
    with pytest.raises(C.InputError, match="progress must be a function"):
        C.simulate(double_pendulum(), 0.1, method=method, progress=3, **settings)


def test_baumgarte_refuses_the_cvodes_bases():
    # CVODES would integrate projection's equations, silently dropping the feedback terms
    with pytest.raises(C.InputError, match="method 'baumgarte' steps in SciPy"):
        C.simulate(double_pendulum(), 0.1, method="baumgarte", base="CVODES")


def test_a_stop_carries_its_status_not_only_words():
    """Solvers report how a run ended as a Status (one message each); simulate branches on it
    and records it in trajectory.info["stop"]."""
    from constrained.solvers.base import Failure, Status

    assert all(isinstance(s.message, str) and s.message for s in Status)
    with pytest.raises(C.SimulationError) as info:
        C.simulate(double_pendulum(), 2.0, method="dopri", rtol=1e-12, atol=1e-14, max_steps=20,
                   compiled=False)
    assert info.value.trajectory.info["stop"] == Status.STEP_LIMIT.value

    import os
    import signal

    def stop(t):  # Ctrl-C, as the terminal sends it, once the run is under way
        if t > 0.3:
            os.kill(os.getpid(), signal.SIGINT)

    for method, extra in (("projection", {}), ("rattle", {"dt": 1e-3, "compiled": False})):
        with pytest.raises(C.RunInterrupted) as info:
            C.simulate(double_pendulum(), 2.0, method=method, progress=stop, **extra)
        assert info.value.trajectory.info["stop"] == Status.INTERRUPTED.value
    done = C.simulate(double_pendulum(), 0.1, method="dopri", compiled=False)
    assert done.info["stop"] == Status.COMPLETED.value
    text = Failure(Status.NON_FINITE, "non-finite state at t = 1 s")
    assert text.status is Status.NON_FINITE and text.startswith("non-finite")


def test_pantelides_refuses_a_model_too_large_for_its_symbolic_reduction():
    """CasADi's index reduction is one uninterruptible call whose time grows as the cube of the
    size: above ``max_coordinates`` the method refuses before it starts, naming the others."""
    from constrained.errors import InputError

    system = rope(160)
    with pytest.raises(InputError, match=r"480 coordinates, above max_coordinates = 450: use method 'idas'"):
        C.simulate(system, 0.01, method="pantelides")
    with pytest.raises(InputError, match="max_coordinates must be a whole number"):
        C.simulate(rope(5), 0.01, method="pantelides", max_coordinates=0)
    run = C.simulate(rope(5), 0.01, method="pantelides", max_coordinates=15)
    assert run.t[-1] == pytest.approx(0.01)
