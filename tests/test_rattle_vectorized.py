"""RATTLE on the vectorized build (issue 28): a large model's RATTLE step takes its KKT solves
from the loops' LDLᵀ, its position Newton iteration simplified to A0 = J(x_n) M⁻¹ J(x_n)ᵀ (the
exact Newton matrix J(x_{n+1}) M⁻¹ J(x_n)ᵀ is not symmetric). Both iterations converge to the
same step, so a run must match the exact-Newton step of the Structure's graphs to round-off on
unfriendly models — a 3-D rope of uneven masses with shuffled rods, a cloth, a moving anchor
(rheonomic rows), damping (forces of v: not carried) — keep the energy of a conservative rope,
and say what to change where the simplified iteration does not converge."""

from __future__ import annotations

import numpy as np
import pytest
import test_vectorized as tv
import test_vectorized_loops as tl

import constrained as C
from constrained.errors import SimulationError
from constrained.manifold.manifold import Manifold
from constrained.manifold.vectorized import graphs as vg
from constrained.model.structure import assemble
from constrained.solvers.rattle import Rattle


def _damped_rope() -> C.System:
    s = tv.rope(120, varied=True)
    s.add(C.Damping(0.002, [f"p{i}" for i in range(0, 120, 3)]))
    return s


SYSTEMS = {
    "shuffled 3-D rope": lambda: tl._wavy_rope(120),
    "moving anchor and plane": lambda: tv.rope(120, varied=True, moving=True),
    "damped rope": _damped_rope,
    "cloth": lambda: tv.cloth(12),
}


def _run(system: C.System, *, vectorized: bool, monkeypatch, t_end=0.02, dt=5e-4, **options):
    model = assemble(system, reuse=False)
    assert model.n_coordinates >= vg.VECTORIZED_FROM
    with monkeypatch.context() as m:
        if not vectorized:
            m.setattr(Rattle, "vectorized", lambda self: False)
        return C.simulate(system, t_end, model=model, method="rattle", dt=dt,
                          outputs=["energy", "constraint_residual"], **options)


@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_a_large_models_rattle_takes_the_exact_newton_steps(name, monkeypatch):
    system = SYSTEMS[name]()
    model = assemble(system, reuse=False)
    assert Rattle(Manifold(model), dt=1e-3).vectorized()
    a = _run(system, vectorized=True, monkeypatch=monkeypatch)
    b = _run(system, vectorized=False, monkeypatch=monkeypatch)
    assert a.stats["steps"] == b.stats["steps"] == 40
    scale = np.max(np.abs(b.v))
    assert scale > 1e-3  # (it moved)
    tv._close(a.x, b.x, 1e-12)
    tv._close(a.v, b.v, 1e-10 * max(scale, 1.0))
    assert np.max(a.constraint_residual) < 1e-12


def test_a_conservative_ropes_energy_stays_bounded(monkeypatch):
    """RATTLE is symplectic: over 2,000 steps of a swinging rope of uneven masses the energy
    error stays at the level of its first oscillations (no drift). The step loop's own energy
    watch (the vectorized build's h after every step) finds the largest change the trajectory's
    energy, computed after the run at every step, shows."""
    run = _run(tv.rope(150, varied=True), vectorized=True, monkeypatch=monkeypatch, t_end=0.5, dt=2.5e-4)
    e = run.energy - run.energy[0]
    assert len(run.t) == run.stats["steps"] + 1  # (every step is an output here)
    k = int(np.argmax(np.abs(e)))
    assert run.stats["energy_change"] == pytest.approx(e[k], rel=1e-6)
    assert run.stats["energy_change_t"] == pytest.approx(run.t[k], abs=1e-12)
    swing = np.ptp(run.x[:, :, 1])
    assert swing > 0.01
    early, late = np.max(np.abs(e[: len(e) // 4])), np.max(np.abs(e[len(e) // 4:]))
    assert late < 3 * early + 1e-12
    assert np.max(np.abs(e)) < 1e-4 * np.max(np.abs(run.energy))


def test_a_step_too_long_for_the_simplified_newton_names_dt(monkeypatch):
    """A step far past the rope's motion: the simplified iteration does not reach the
    tolerance, and the error says so and what to change (no NaN passed on)."""
    with pytest.raises(SimulationError, match=r"did not converge.*reduce dt"):
        _run(tv.rope(120, varied=True), vectorized=True, monkeypatch=monkeypatch, t_end=0.2, dt=0.05,
             newton_iterations=2)
