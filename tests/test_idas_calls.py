"""``idas`` projects every output, but no longer restarts IDAS at each one (session 14).

Every SUNDIALS call restarts IDAS at order 1 with small steps. ``idas`` made one call per output
time, so that it could continue from each projected output: on a rope of 300 beads of 10 g on
1 cm links, released horizontal, the first 0.02 s (201 outputs) took 2,497 IDAS steps, about
twelve per restart, where one call takes 171. Now a call covers 1, 8, 64, … output times,
growing while it takes few steps and the state it ends in stays within atol of the constraints
(index 1: f = 0 is only implied), and every output is still projected.
"""

from __future__ import annotations

import numpy as np
import pytest

import constrained as C
from constrained.solvers.sundials.idas import CALL_STEPS, CallSize, _canonical

N, LINK, MASS = 300, 0.01, 0.01


def _rope(n: int = N) -> C.System:
    s = C.System(name="rope released horizontal")
    for i in range(n):
        s.add_particle(f"p{i}", MASS, [LINK * (i + 1), 0.0, 0.0], [0.0, 0.0, 0.0])
    s.add(C.Distance("p0", point=[0.0, 0.0, 0.0], length=LINK))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=LINK))
    s.add(C.Gravity([0.0, -9.81, 0.0]))
    return s


def test_idas_on_a_fine_rope_takes_the_steps_of_its_accuracy_not_of_its_restarts():
    rope = _rope()
    tr = C.simulate(rope, 0.02, method="idas", rtol=1e-6, atol=1e-6)
    assert tr.info["status"] == "completed" and len(tr.t) == 201
    # one call over the whole run takes 171 steps; a restart at every output took 2,497
    assert tr.stats["steps"] < 600
    assert np.max(tr.constraint_residual) < 1e-12  # every output projected
    ref = C.simulate(rope, 0.02, method="dopri", rtol=1e-10, atol=1e-10, t_eval=tr.t)
    assert np.max(np.abs(tr.x - ref.x)) < 1e-5  # the tolerance's accuracy (3e-7 m measured)
    assert np.max(np.abs(tr.v - ref.v)) < 1e-3 * np.max(np.abs(ref.v))


def test_calls_grow_while_cheap_and_shrink_when_the_state_drifts():
    calls = CallSize(first=1)
    calls.took(0.01, steps=CALL_STEPS // 10)
    assert calls.size == 8
    calls.took(0.01, steps=CALL_STEPS // 10)
    assert calls.size == 64
    calls.took(10.0, steps=CALL_STEPS)  # seconds alone never decide: the same steps on any machine
    assert calls.size == 64
    calls.took(0.01, steps=CALL_STEPS // 10, drifted=True)
    assert calls.size == 8
    calls.took(0.01, steps=9 * CALL_STEPS)
    assert calls.size == 1
    calls.took(0.01, steps=9 * CALL_STEPS, drifted=True)
    assert calls.size == 1
    # a failed call is retried in eighths whatever it took (the same outputs on any machine)
    assert calls.retry_smaller(64, seconds=100.0, by_steps=True) and calls.size == 8
    assert not calls.retry_smaller(1, seconds=0.0, by_steps=True)


def test_equally_spaced_calls_share_one_grid():
    t = 0.37 + np.linspace(0, 0.02, 201)
    a = _canonical(tuple((t[1:9] - t[0]) / (t[8] - t[0])))
    b = _canonical(tuple((t[9:17] - t[8]) / (t[16] - t[8])))
    assert a == b == tuple(np.arange(1, 9) / 8)
    uneven = (0.1, 0.5, 1.0)
    assert _canonical(uneven) == uneven


@pytest.mark.parametrize("rtol, restarting_steps", [(1e-6, 5336), (1e-9, 12113)])
def test_a_chaotic_double_pendulum_keeps_its_energy_with_fewer_restarts(rtol, restarting_steps):
    """Larger calls continue from unprojected states inside a call: the drift gate keeps that
    within atol, so the energy of a chaotic double pendulum (released horizontal, 5 s) is kept
    to a few hundred rtol of m g L, as it was with a restart at every output (then 2.7e-3 J at
    1e-6 and 4.1e-6 J at 1e-9: its restarts' low-order steps cost accuracy too), in fewer
    steps than ``restarting_steps`` (what the restarts took) by a third at least."""
    s = C.System(name="double pendulum")
    s.add_particle("a", 1.0, [1.0, 0.0, 0.0])
    s.add_particle("b", 0.3, [2.0, 0.0, 0.0])
    s.add(C.Distance("a", point=[0, 0, 0], length=1.0), C.Distance("a", "b", length=1.0),
          C.Plane(["a", "b"], [0, 0, 1], 0.0), C.Gravity([0, -9.81, 0]))
    tr = C.simulate(s, 5.0, method="idas", rtol=rtol, atol=rtol)
    assert tr.info["status"] == "completed"
    assert np.max(tr.constraint_residual) < 1e-12
    mgl = (1.0 + 0.3) * 9.81 * 1.0
    assert np.max(np.abs(tr.energy - tr.energy[0])) < 250 * rtol * mgl
    assert tr.stats["steps"] < 2 / 3 * restarting_steps


@pytest.mark.parametrize("method", ["idas", "ggl"])
def test_a_loaded_machine_takes_the_same_steps(method, monkeypatch):
    """Calls are sized by their steps, never by the clock (session 15: ``ggl``'s were sized by
    their seconds, so a run on a loaded machine took other calls and other steps, and the
    collapse of a rod driven to zero length was predicted at t* = 0.9982 s idle, 0.9999 s
    under load). A clock on which every call takes 100 s gives the same run."""
    import time as _time

    from constrained.solvers.sundials import idas as module

    pendulum = C.System(name="pendulum")
    pendulum.add_particle("p", 1.0, [0.6, -0.8, 0.0], [0.0, 0.0, 0.0])
    pendulum.add(C.Distance("p", point=[0.0, 0.0, 0.0], length=1.0), C.Plane("p", [0, 0, 1]),
                 C.Gravity([0.0, -9.81, 0.0]))
    grid = np.linspace(0.0, 3.0, 2001)  # (several calls)
    idle = C.simulate(pendulum, 3.0, method=method, rtol=1e-8, atol=1e-10, t_eval=grid)

    class SlowClock:
        now = 0.0

        @classmethod
        def perf_counter(cls):
            cls.now += 50.0
            return cls.now

    monkeypatch.setattr(module, "time", type("T", (), {"perf_counter": SlowClock.perf_counter,
                                                        "process_time": _time.process_time}))
    loaded = C.simulate(pendulum, 3.0, method=method, rtol=1e-8, atol=1e-10, t_eval=grid)
    assert loaded.stats["steps"] == idle.stats["steps"]
    np.testing.assert_array_equal(loaded.x, idle.x)
