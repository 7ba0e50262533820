"""Initial assembly where the mass-weighted projection fails (session 14).

A start a few per cent off its rods, with 0.1 mg … 10 g beads between 1 kg ones, was refused:
"the constraints cannot all be satisfied near the initial state" — they can. The mass-weighted
Newton step moves the light beads most, and they alone cannot close a kinked, stretched chain:
the projection stalled. Even equal masses failed 10 % off. The start is now assembled first by
Gauss–Newton on the rows in metres (minimum-norm steps, a line search on |f|²), then projected
as before; constraints that cannot all hold are still refused, with the clash named.
"""

from __future__ import annotations

import numpy as np
import pytest

import constrained as C

LINK = 0.01


def _kinked_chain(ratio: float, stretch: float, n: int = 10) -> C.System:
    """n beads, 1 kg and 1/ratio kg in turn, on 1 cm rods from the origin, placed ``stretch``
    too far apart along x with every other bead 4 mm off the line (a kink at each)."""
    s = C.System(name="light and heavy beads, a stretched kinked start")
    for i in range(n):
        mass = 1.0 if i % 2 == 0 else 1.0 / ratio
        s.add_particle(f"p{i}", mass, [LINK * (i + 1) * (1 + stretch), 0.004 * (i % 2), 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=LINK))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=LINK))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1], 0.0), C.Gravity([0, -9.81, 0]))
    return s


@pytest.mark.parametrize("ratio, stretch", [(1e2, 0.01), (1e4, 0.03), (1e6, 0.03), (1.0, 0.1)])
def test_a_stretched_kinked_start_is_assembled(ratio, stretch):
    system = _kinked_chain(ratio, stretch)
    x0 = np.asarray(system.positions, float)
    tr = C.simulate(system, 0.01, max_initial_correction=1.0, rtol=1e-9, atol=1e-9)
    assert tr.info["status"] == "completed"
    x = tr.x[0]
    links = np.linalg.norm(np.diff(np.vstack([[0, 0, 0], x]), axis=0), axis=1)
    np.testing.assert_allclose(links, LINK, rtol=0, atol=1e-13)  # on every rod
    moved = float(np.max(np.linalg.norm(x - x0, axis=1)))
    assert tr.info["initial_correction"]["position"] == pytest.approx(moved, rel=1e-12)  # reported
    assert moved < 0.5 * 10 * LINK  # near the start, not anywhere on the manifold
    assert np.max(tr.constraint_residual) < 1e-12


def test_constraints_that_cannot_all_hold_are_still_refused():
    """A bead held 0.2 m from two anchors 1 m apart: |f|² has its minimum at 0.6 m."""
    s = C.System(name="two rods too short")
    s.add_particle("a", 1.0, [0.5, 0.0, 0.0])
    s.add(C.Distance("a", point=[0, 0, 0], length=0.2), C.Distance("a", point=[1, 0, 0], length=0.2))
    with pytest.raises(C.InconsistentStateError, match="cannot all be satisfied"):
        C.simulate(s, 0.1, max_initial_correction=1.0)


def test_a_large_correction_is_still_refused_by_default():
    """Assembled, the start moves beads by 3 mm: more than the default bound, which names the
    constraint and the setting."""
    with pytest.raises(C.InconsistentStateError, match="max_initial_correction"):
        C.simulate(_kinked_chain(1e4, 0.03), 0.01)
