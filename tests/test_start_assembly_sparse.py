"""The start's assembly of a large model by sparse steps (session 18).

`constrained check` of a generated 400-bead chain (charged beads in an electric field, springs,
dampers) with one rod overridden to ten times its link ran past 150 s: the start, 0.9 m off,
went to the Gauss–Newton assembly (``run.start.assemble_positions``), whose every iteration
converted J to a full 1200-column array and took NumPy's dense ``lstsq`` (147 iterations, 28 s
of the 29). A large model's step is now dx = Jᵀy with the minimum-norm y of (J Jᵀ) y = −f by
the sparse algebra: the same minimum-norm least-squares step, O(N) on a chain.
"""

from __future__ import annotations

import numpy as np
import pytest

import constrained as C
from constrained.manifold import residual
from constrained.model.structure import assemble
from constrained.run import start

N, LINK = 150, 0.1  # 150 rods and 150 plane rows: the sparse algebra


def _chain() -> C.System:
    particles = [C.Particle(f"p{i}", 1.0, [(i + 1) * LINK, 0.0, 0.0]) for i in range(N)]
    rods = [C.Distance("p0", point=[0.0, 0.0, 0.0], length=LINK)]
    rods += [C.Distance(f"p{i - 1}", f"p{i}", length=LINK) for i in range(1, N)]
    plane = C.Plane([f"p{i}" for i in range(N)], normal=[0.0, 0.0, 1.0])
    return C.System(particles, [*rods, plane], [C.Gravity([0.0, -9.81, 0.0])])


def _far_start(model) -> np.ndarray:
    """The straight chain crumpled in its plane by up to 3 cm a bead (rods off by up to 30 %)."""
    rng = np.random.default_rng(7)
    x = np.asarray(model.system.positions, float).reshape(-1, 3).copy()
    x[:, :2] += rng.uniform(-0.03, 0.03, size=(N, 2))
    return x.ravel()


def test_a_large_chain_is_assembled_by_sparse_steps_onto_its_rods(monkeypatch):
    model = assemble(_chain())
    x0 = _far_start(model)
    scales = residual.row_scales(model, x0)[:model.n_position_rows]

    def dense_step(*args, **kwargs):
        raise AssertionError("a large model's assembly took a dense least-squares step")

    monkeypatch.setattr(start.np.linalg, "lstsq", dense_step)
    x = start.assemble_positions(model, x0, 0.0, scales, tol=1e-10 * N * LINK)
    assert x is not None
    beads = np.vstack([np.zeros(3), x.reshape(-1, 3)])
    np.testing.assert_allclose(np.linalg.norm(np.diff(beads, axis=0), axis=1), LINK, atol=1e-9)
    assert np.max(np.abs(beads[:, 2])) < 1e-12  # still in its plane


def test_the_sparse_step_is_the_dense_minimum_norm_least_squares_step():
    model = assemble(_chain())
    x0 = _far_start(model)
    rows = model.n_position_rows
    scales = residual.row_scales(model, x0)[:rows]
    f = np.asarray(model.constraint(x0, 0.0), float).ravel()[:rows] / scales
    J = start.sparse_jacobian(model)(x0, 0.0)
    sparse_step = start._least_squares_step(start.algebra_for(rows), J, rows, scales, f)
    dense_step = start._least_squares_step(start.DENSE, J, rows, scales, f)
    assert sparse_step == pytest.approx(dense_step, abs=1e-12 * np.max(np.abs(dense_step)))
