"""A rope released horizontal falls flat onto a one-sided floor: dozens of beads land at one
instant (session 14: a 1,000-bead rope stopped with "non-finite state" right after the burst).

The segment after the burst starts from a state where a few beads move fast and the rest
slowly; dopri's first-step heuristic proposed 0.02 s there, a trial step whose stages left the
rope (beads on top of each other: a singular KKT solve) and came out NaN. DOP853's error blend
read that NaN error as 0, so the trial was *accepted* (its step grown tenfold) and the NaN
state passed on. A trial that is not finite must be rejected and its step shrunk."""

from __future__ import annotations

import numpy as np
import pytest

import constrained as C
from constrained.manifold.manifold import Manifold
from constrained.model.held import held
from constrained.model.structure import assemble
from constrained.run import hybrid
from constrained.solvers import METHODS
from constrained.solvers.dopri import SCALARS, Dopri

N, LINK, MASS, FLOOR, E = 60, 0.01, 0.01, -0.1, 0.5


def _rope_over_a_floor(n: int = N, restitution: float = E) -> C.System:
    """n beads on 1 cm links hung from the origin by the first, released horizontal at rest
    in z = 0 above a one-sided floor y >= FLOOR under every bead."""
    s = C.System(name="rope over a floor")
    for i in range(n):
        s.add_particle(f"p{i}", MASS, [LINK * (i + 1), 0.0, 0.0], [0.0, 0.0, 0.0])
    s.add(C.Distance("p0", point=[0.0, 0.0, 0.0], length=LINK))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=LINK))
    beads = [f"p{i}" for i in range(n)]
    s.add(C.Plane(beads, [0, 0, 1], 0.0), C.Gravity([0, -9.81, 0]))
    s.add(C.Plane(beads, [0, 1, 0], FLOOR, unilateral=True, restitution=restitution))
    return s


def _generous_first_step(self, x0, v0, a0, t0, t_end):
    """A first-step proposal as generous as the heuristic's on the 1,000-bead rope (0.02 s
    from the state after the burst): an adaptive method must survive any proposal."""
    return min(0.1, t_end - t0)


def test_a_rope_slamming_flat_onto_a_floor_runs_on(monkeypatch):
    monkeypatch.setattr(Dopri, "_initial_step", _generous_first_step)
    t_end = 1.5 * np.sqrt(2 * abs(FLOOR) / 9.81)  # past the landing of the free-falling beads
    traj = C.simulate(_rope_over_a_floor(), t_end, method="dopri", rtol=1e-6,
                      atol=1e-6, compiled=False)
    assert traj.info["status"] == "completed" and traj.t[-1] == pytest.approx(t_end)
    assert np.all(np.isfinite(traj.x)) and np.all(np.isfinite(traj.v))
    impacts = [r for r in traj.events if r.kind == "impact"]
    first = min(r.t for r in impacts)
    assert sum(r.t == first for r in impacts) >= N // 3  # many beads land at one instant
    # no bead below the floor, the held rows kept
    y = traj.x.reshape(len(traj.t), N, 3)[:, :, 1]
    assert y.min() >= FLOOR - 1e-9
    assert np.max(traj.constraint_residual) < 1e-9
    # impacts (e <= 1) never add energy: every one loses some, and the total energy never rises
    assert all(r.energy_lost >= 0 for r in impacts)
    scale = MASS * 9.81 * abs(FLOOR) * N
    assert np.max(np.diff(traj.energy)) <= 1e-6 * scale
    assert traj.energy[-1] < traj.energy[0] - 1e-3 * scale  # the slam did dissipate


def test_a_trial_step_that_is_not_finite_is_rejected_and_shrunk():
    """From the state just after the burst of impacts, a 0.1 s trial step leaves the rope
    (its stages come out NaN): dopri's attempt refuses it (t unchanged, a smaller step)."""
    system = _rope_over_a_floor()
    model = assemble(system, reuse=False)
    segments = []
    run_segment = hybrid.run_segment

    def recording(model, rows, x0, v0, t0, t_end, **kw):
        segments.append((tuple(rows), x0.copy(), v0.copy(), t0))
        return run_segment(model, rows, x0, v0, t0, t_end, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(hybrid, "run_segment", recording)
        C.simulate(system, 0.145, method="dopri", rtol=1e-6, atol=1e-6, compiled=False, model=model)
    rows, x0, v0, t0 = segments[1]  # the segment right after the first burst
    stepper = METHODS["dopri"](Manifold.at(held(model, rows), x0, t0), rtol=1e-6, atol=1e-6, compiled=False)
    n = model.n_coordinates
    state = stepper.init(x0, v0, t0, t0 + 1.0, first_step=0.1)
    state[3 * n + SCALARS.index("t_target")] = t0 + 1.0
    (out,) = stepper._chunks[1](state)
    out = np.asarray(out, float).ravel()
    assert np.all(np.isfinite(out))
    assert out[3 * n + SCALARS.index("t")] == t0  # rejected
    assert 0 < out[3 * n + SCALARS.index("h")] < 0.1  # and shrunk
