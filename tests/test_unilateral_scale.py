"""One-sided constraints on a large model (session 13: a 3,000-bead rope falling on a floor built
a dense J of 9,000 x 9,000 at every event and its SVD for each segment's degrees of freedom —
10 minutes and 4.5 GB without reaching the floor). Above ``algebra.SPARSE_FROM`` rows the impact
law, the constraint velocities and the segments' degrees of freedom take J sparse; they must
give the dense route's numbers."""

from __future__ import annotations

import numpy as np
import pytest
import test_vectorized as tv

import constrained as C
import constrained.run.unilateral as unilateral
from constrained.manifold import algebra
from constrained.model.structure import assemble
from constrained.run import hybrid


def _rope_on_a_floor(n: int = 60):
    """A planar rope of uneven links and masses whose lowest bead touches a floor (a one-sided
    plane under every bead), moving down and sideways: (model, x, v, the floor's rows)."""
    s = tv.rope(n, varied=True)
    y = np.asarray(s.positions, float)[:, 1]
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 1, 0], float(y.min()), unilateral=True, restitution=0.5))
    model = assemble(s, reuse=False)
    assert model.n_constraints > algebra.SPARSE_FROM
    rng = np.random.default_rng(5)
    x = np.asarray(s.positions, float).ravel()
    v = np.tile([0.3, -1.0, 0.0], n) + 0.05 * rng.standard_normal(3 * n) * np.tile([1, 1, 0], n)
    floor = [k for k in range(model.n_constraints) if model.constraint_owner[k] == len(s.constraints) - 1]
    return model, x, v, floor


def test_an_impact_on_a_large_model_is_the_dense_routes(monkeypatch):
    model, x, v, floor = _rope_on_a_floor()
    held = [k for k in range(model.n_constraints) if k not in floor]
    lowest = [floor[int(np.argmin(x.reshape(-1, 3)[:, 1]))]]
    restitution = {k: 0.5 for k in floor}
    sparse = unilateral.impact(model, x, v, 0.0, held + lowest, lowest, restitution)
    monkeypatch.setattr(unilateral, "algebra_for", lambda n: algebra.DENSE)
    dense = unilateral.impact(model, x, v, 0.0, held + lowest, lowest, restitution)
    scale = np.max(np.abs(dense.v))
    assert np.max(np.abs(sparse.v - dense.v)) <= 1e-11 * scale
    assert sparse.impulse.keys() == dense.impulse.keys() and sparse.released == dense.released
    for k in dense.impulse:
        assert sparse.impulse[k] == pytest.approx(dense.impulse[k], rel=1e-9)
        assert dense.impulse[k] > 0
    assert sparse.energy_lost == pytest.approx(dense.energy_lost, rel=1e-9, abs=1e-15)
    c = unilateral.constraint_velocities(model, x, sparse.v, 0.0)
    assert c[lowest[0]] == pytest.approx(-0.5 * unilateral.constraint_velocities(model, x, v, 0.0)[lowest[0]],
                                         rel=1e-9)  # (Newton's restitution along the row)
    assert np.max(np.abs(c[held])) < 1e-10


def test_a_segments_degrees_of_freedom_on_a_large_model_are_the_dense_rank(monkeypatch):
    model, x, v, floor = _rope_on_a_floor()
    rows = [k for k in range(model.n_constraints) if k not in floor] + floor[:7]
    run = hybrid.HybridRun(t=np.zeros(1), x=x[None, :], v=v[None, :], segments=[], records=[])
    sparse = hybrid._dof(model, run, 0, rows)
    J = np.asarray(model.jacobian(x, 0.0)[1], float)[rows]
    assert sparse == model.n_coordinates - np.linalg.matrix_rank(J)

