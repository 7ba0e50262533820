"""Session 16: ggl on long chains of 10 g beads on 1 cm rods hanging from a point, at its
default tolerances. It stopped at t = 0 with IDA_CONV_FAIL at N = 100, 200, 1000 and 2000
(not at 10, 30 or 400): IDAS's corrector tested the multipliers Δ²λ and Δμ, whose corrections
are the round-off of the constraints amplified by (α/h)(J M⁻¹ Jᵀ)⁻¹ — at least their absolute
tolerance from N = 100 on, so the iteration never looked converged (solvers/sundials/idas.py,
``GGL.absolute_tolerances``). The stop was then put down to "a singular configuration" at
σ = 5.6e-4, which for a straight chain of 2,000 rods is its longest mode, not a dependency.

Closed forms: a straight chain at rest with no force stays put; a straight chain at rest along
e with gravity g starts with every bead accelerating at g − (g·e) e (the KKT solution: rods in
line take the component along e, T_i = m (g·e) (N − i)), which the free end keeps for a long
while (the pivot's pull reaches it only at high order in t); the row-normalized J of a straight
chain has Ĵ Ĵᵀ tridiagonal (1 on the diagonal, −1/√2 between the pivot's row and the next,
−1/2 between the others), whose smallest eigenvalue is σ².
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import eigvalsh_tridiagonal

import constrained as C
from constrained.manifold import diagnostics
from constrained.manifold.manifold import Manifold
from constrained.manifold.rank_policy import RANK

HARD = Path(__file__).resolve().parent.parent / "scenarios" / "hard"
MASS, LINK = 0.01, 0.01
#: Gravity 30° off the chain's normal: the rods in line take the part along the chain.
GRAVITY = 9.81 * np.array([-0.5, -np.sqrt(3) / 2, 0.0])


def chain(n: int, gravity=None) -> C.System:
    """n beads of 10 g on 1 cm rods, straight along x from a pivot at the origin, at rest."""
    s = C.System(name="chain of 1 cm links")
    for i in range(n):
        s.add_particle(f"p{i}", MASS, [LINK * (i + 1), 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=LINK))
    for i in range(1, n):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=LINK))
    if gravity is not None:
        s.add(C.Gravity(list(gravity)))
    return s


@pytest.mark.parametrize("n", [100, 1000, 2000])
def test_ggl_keeps_a_chain_at_rest_put(n):
    """Old: "IDAS stopped after t = 0 s (IDA_CONV_FAIL)" at both sizes."""
    system = chain(n)
    traj = C.simulate(system, 0.002, method="ggl")
    assert traj.success and traj.t[-1] == pytest.approx(0.002)
    x0 = np.asarray(system.positions, float)
    assert np.abs(traj.x - x0).max() < 1e-12  # atol is 1e-10: nothing moves but round-off
    assert np.abs(traj.v).max() < 1e-10
    assert traj.constraint_residual.max() < 1e-12


def test_ggl_starts_a_chain_falling_with_the_kkt_acceleration_and_agrees_with_dopri():
    n = 200
    e = np.array([1.0, 0.0, 0.0])
    a0 = GRAVITY - (GRAVITY @ e) * e  # every bead's acceleration at t = 0
    t = np.linspace(0, 0.002, 5)
    traj = C.simulate(chain(n, GRAVITY), 0.002, method="ggl", t_eval=t)
    assert traj.success
    # the tensions at the start: the rods carry the part of gravity along the chain
    tension = MASS * abs(GRAVITY @ e) * (n - np.arange(n))
    np.testing.assert_allclose(np.abs(traj.multipliers[0]), tension, rtol=1e-9)
    # the free end falls as ½ a0 t² (its y); the first bead leaves it as the pivot pulls
    fall = traj.x[:, -1] - traj.x[0, -1]
    np.testing.assert_allclose(fall[1:, 1], 0.5 * a0[1] * t[1:] ** 2, rtol=1e-6)
    first = (traj.x[1:, 0, 1] - traj.x[0, 0, 1]) / (0.5 * a0[1] * t[1:] ** 2) - 1
    assert abs(first[0]) < 0.01 and np.all(np.diff(np.abs(first)) > 0)
    # the whole chain against dopri at rtol 1e-12, to what ggl's rtol claims (rtol × the size)
    ref = C.simulate(chain(n, GRAVITY), 0.002, method="dopri", rtol=1e-12, atol=1e-14, t_eval=t)
    assert np.abs(traj.x - ref.x).max() < 1e-8 * np.abs(ref.x).max()
    assert traj.constraint_residual.max() < 1e-10  # of order atol


def test_a_long_straight_chain_is_not_called_singular_but_a_dead_centre_is():
    """Old: a stop on a 2,000-bead chain at t = 0 said "likely cause: a singular configuration …
    (smallest singular value … 0.00056)": the chain's σ ≈ 1.1 / N is below the old fixed 1e-3."""
    n = 2000
    system = chain(n)
    model = C.assemble(system)
    x = np.asarray(system.positions, float).ravel()
    off = np.full(n - 1, -0.5)
    off[0] = -1 / np.sqrt(2)
    sigma = np.sqrt(eigvalsh_tridiagonal(np.ones(n), off, select="i", select_range=(0, 0))[0])
    found = diagnostics.singularity(model, x, 0.0)  # (the sparse route above 300 coordinates)
    assert found.sigma == pytest.approx(sigma, rel=1e-3) and sigma < 1e-3
    assert RANK.singular_cause(n) < 0.1 * sigma
    message = diagnostics.likely_cause(model, x, 0 * x, 0.0, Manifold.at(model, x, 0.0))
    assert "singular" not in message and "blow up" not in message
    assert message.startswith("likely cause: none found") and "no particle accelerates" in message

    # the non-Grashof four-bar of scenarios/hard 1e-8 rad short of its limit, where coupler and
    # rocker fall in line (cos θ = 0.3): σ ≈ 1e-4, a dependency of those two rods
    four = C.load_scene(HARD / "fourbar_limit.toml").system
    m4 = C.assemble(four)
    th = np.arccos(0.3) - 1e-8
    b, d = 0.6 * np.array([np.cos(th), np.sin(th)]), np.array([1.0, 0.0])
    gap = np.linalg.norm(d - b)
    c = (b + d) / 2 + np.sqrt(0.25 - gap**2 / 4) * np.array([b[1] - d[1], d[0] - b[0]]) / gap
    x4 = np.array([*b, 0.0, *c, 0.0])
    assert np.linalg.norm(c - b) == pytest.approx(0.5) and np.linalg.norm(c - d) == pytest.approx(0.5)
    assert RANK.singular_cause(m4.n_constraints) == 1e-3  # (a small set: as before)
    message = diagnostics.likely_cause(m4, x4, 0 * x4, th, Manifold.at(m4, x4, th))
    assert message.startswith("likely cause: a singular configuration")
    assert "'coupler BC'" in message and "'rocker DC'" in message
