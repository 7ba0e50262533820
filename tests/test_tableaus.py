"""The Dormand–Prince tableaus ``dopri`` runs are written out in constrained (so that a run
need not import SciPy's integrators): they must be SciPy's numbers exactly, and satisfy the
order conditions their orders claim."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import DOP853, RK45

from constrained.solvers.tableaus import TABLEAUS
from constrained.solvers.tableaus.tableau import from_scipy


@pytest.mark.parametrize("name, solver, errors", [("DOP853", DOP853, ("E5", "E3")), ("DOPRI5", RK45, ("E",))])
def test_the_written_tableaus_are_scipys(name, solver, errors):
    ours, scipys = TABLEAUS[name], from_scipy(name, solver, tuple(getattr(solver, e) for e in errors))
    for field in ("A", "B", "C"):
        np.testing.assert_array_equal(getattr(ours, field), getattr(scipys, field), err_msg=field)
    for a, b in zip(ours.E, scipys.E, strict=True):
        np.testing.assert_array_equal(a, b)
    assert (ours.order, ours.error_order) == (scipys.order, scipys.error_order)


@pytest.mark.parametrize("name", ["DOP853", "DOPRI5", "Tsit5"])
def test_the_weights_integrate_polynomials_to_the_claimed_order(name):
    """Quadrature conditions Σ b_i c_i^(k−1) = 1/k for k ≤ order (a necessary part of the
    order conditions; a mistyped coefficient breaks them)."""
    t = TABLEAUS[name]
    for k in range(1, t.order + 1):
        assert float(t.B @ t.C ** (k - 1)) == pytest.approx(1.0 / k, abs=1e-13), k
