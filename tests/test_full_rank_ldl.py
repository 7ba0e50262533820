"""The sparse full-rank test by CasADi's LDLᵀ (manifold.sparse.clearly_full_row_rank), which spares a
large model's start the SciPy import: it calls rows independent only when they clearly are, and
every redundant set still goes to the careful test (independent_rows) and is found there."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import constrained as C
from constrained.manifold import sparse
from constrained.manifold.manifold import redundant_rows


def chain(n: int, *, duplicate: int | None = None, taut_to: float | None = None) -> C.System:
    """n rods of 0.1 m in a zigzag from the origin (independent rows); ``duplicate``: rod k twice;
    ``taut_to``: straight along x instead, the last particle also on a rod to (taut_to, 0, 0) at
    exactly the rest of the length (a chain held at both ends: dependent x rows)."""
    s = C.System(name="chain")
    previous = None
    for k in range(n):
        x = 0.1 * (k + 1)
        y = 0.0 if taut_to is not None else 0.05 * (k % 2)
        s.add_particle(f"p{k}", 0.01 * (1 + k % 3), [x, y, 0.0])
        if previous is None:
            s.add(C.Distance(f"p{k}", point=[0.0, 0.0, 0.0], length=float(np.hypot(x, y))))
        else:
            (xa, ya), (xb, yb) = previous, (x, y)
            s.add(C.Distance(f"p{k - 1}", f"p{k}", length=float(np.hypot(xb - xa, yb - ya))))
            if duplicate == k:
                s.add(C.Distance(f"p{k - 1}", f"p{k}", length=float(np.hypot(xb - xa, yb - ya))))
        previous = (x, y)
    if taut_to is not None:
        s.add(C.Distance(f"p{n - 1}", point=[taut_to, 0.0, 0.0], length=float(taut_to - 0.1 * n)))
    s.add(C.Plane([f"p{k}" for k in range(n)], [0, 0, 1]))
    return s


def _jacobian(system):
    model = C.assemble(system)
    x = system.positions.ravel()
    return model, model.velocity_terms(x, 0.0)[0], x


@pytest.mark.parametrize("n", [120, 400])
def test_independent_rows_are_called_so_without_scipy(n):
    model, J, x = _jacobian(chain(n))
    assert J.shape[0] > 100 and sparse.clearly_full_row_rank(J, model.inverse_masses)
    assert redundant_rows(model, x, 0.0) is None


@pytest.mark.parametrize("system, cut", [(chain(150, duplicate=70), 1), (chain(150, taut_to=16.0), 1)])
def test_redundant_sets_still_go_to_the_careful_test(system, cut):
    model, J, x = _jacobian(system)
    assert not sparse.clearly_full_row_rank(J, model.inverse_masses)
    assert sparse.full_row_rank(J, model.inverse_masses) is None
    rows = redundant_rows(model, x, 0.0)
    assert rows is not None and len(rows) == model.n_constraints - cut


def test_exact_combinations_and_zero_rows_are_never_clearly_independent():
    rng = np.random.default_rng(3)
    J = np.zeros((150, 240))
    for i in range(150):  # sparse random rows, two particles each
        cols = rng.choice(240, 6, replace=False)
        J[i, cols] = rng.normal(size=6)
    masses = rng.uniform(0.01, 10.0, 240)
    assert sparse.clearly_full_row_rank(ca.sparsify(ca.DM(J)), 1 / masses)
    for combination in ([3, 7, 90], [10, 140], [0]):
        K = J.copy()
        K[120] = sum(rng.normal() * J[k] for k in combination)
        assert not sparse.clearly_full_row_rank(ca.sparsify(ca.DM(K)), 1 / masses)
    K = J.copy()
    K[5] = 0.0
    assert not sparse.clearly_full_row_rank(ca.sparsify(ca.DM(K)), 1 / masses)
    assert not sparse.clearly_full_row_rank(ca.DM(0, 240), 1 / masses)
