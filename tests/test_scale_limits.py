"""What the dense analyses do with a model too large for them (session 13: `constrained statics`
and `modes` on a 3,000-bead rope ran past 2 minutes in 11 GB): they refuse before building
anything dense, naming the size and what to do instead."""

from __future__ import annotations

import pytest
from test_vectorized import rope

from constrained.analysis import statics
from constrained.errors import InputError


def test_statics_refuse_a_kkt_system_beyond_their_dense_limit(monkeypatch):
    system = rope(130)  # 390 coordinates + 260 rows
    monkeypatch.setattr(statics, "MAX_UNKNOWNS", 600)
    monkeypatch.setattr(statics, "_KKT", lambda *a: pytest.fail("the dense KKT was built"))
    with pytest.raises(InputError, match=r"3N \+ C = 650 unknowns here \(390 coordinates, 260 constraint"):
        statics.equilibrium(system)


def test_below_the_limit_the_statics_still_solve():
    eq = statics.equilibrium(rope(4))
    assert eq.converged and eq.virtual_work_residual < 1e-9
