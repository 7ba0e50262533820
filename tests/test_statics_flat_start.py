"""Statics from a degenerate start (docs/hard-cases.md, section 7): a rope of 1 cm links laid out
straight and horizontal, hung from the origin, asked for its equilibrium from there.

At the straight line the rods are at right angles to gravity: the least-squares multipliers are
0, ∇²(V − λᵀf) = 0, and the KKT Newton step cannot lift the weights (from 30 beads Newton failed
at its first iteration and IPOPT ran off the constraints). The answer is known in closed form: a
chain of point masses hangs straight down from its anchor whatever the masses, and the rod
above bead k carries the weight of beads k, k+1, ...: its multiplier is −g Σ_{j≥k} m_j (the
package's sign: a rod in tension has λ = −tension)."""

from __future__ import annotations

import numpy as np
import pytest

import constrained as C
from constrained.analysis.statics import equilibrium

G = 9.81


def flat_rope(masses, links, *, direction=(1.0, 0.0, 0.0), planar=True) -> C.System:
    """Beads of ``masses`` on rods of ``links`` from an anchor at the origin, laid out straight along
    ``direction`` (at rest), in the plane z = 0 when ``planar``; gravity −g ŷ."""
    s = C.System(name=f"flat rope of {len(masses)}")
    along = np.cumsum(links)[:, None] * np.asarray(direction, float)[None, :]
    for i, (m, at) in enumerate(zip(masses, along, strict=True)):
        s.add_particle(f"p{i}", float(m), at)
    s.add(C.Distance("p0", point=[0, 0, 0], length=float(links[0])))
    for i in range(1, len(masses)):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=float(links[i])))
    if planar:
        s.add(C.Plane(s.names, [0, 0, 1], 0.0))
    s.add(C.Gravity([0, -G, 0]))
    return s


def assert_hangs_straight_down(eq, masses, links):
    n = len(masses)
    assert eq.converged and eq.stable is True
    np.testing.assert_allclose(eq.x[:, 0], 0.0, atol=1e-9, rtol=0)
    np.testing.assert_allclose(eq.x[:, 1], -np.cumsum(links), atol=1e-9, rtol=0)
    np.testing.assert_allclose(eq.x[:, 2], 0.0, atol=1e-9, rtol=0)
    weight_below = G * np.cumsum(np.asarray(masses)[::-1])[::-1]  # rod k holds beads k .. n-1
    np.testing.assert_allclose(eq.multipliers[:n], -weight_below, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(eq.multipliers[n:], 0.0, atol=1e-9 * weight_below[0])  # planes: no load
    support = np.sum([force for _, force in eq.anchor_reactions], axis=0)  # the rod's, and the planes' 0
    np.testing.assert_allclose(support, [0.0, weight_below[0], 0.0], atol=1e-9 * weight_below[0])
    assert eq.virtual_work_residual < 1e-9 * weight_below[0]
    assert eq.max_constraint_residual < 1e-12


@pytest.mark.parametrize("n", [30, 100])
def test_rope_released_horizontal_hangs_straight_down(n):
    masses, links = np.full(n, 0.01), np.full(n, 0.01)
    s = flat_rope(masses, links)
    eq = equilibrium(s, s.positions)
    assert eq.method == "descent"  # Newton alone cannot start from the straight line
    assert_hangs_straight_down(eq, masses, links)
    assert np.all(eq.frequencies_squared > 0) and len(eq.eigenvalues) == n


def test_uneven_beads_and_links_laid_out_the_other_way():
    """Masses 1 g .. 50 g and links 0.5 .. 2 cm in no order, laid out exactly horizontal along −x."""
    rng = np.random.default_rng(20240611)
    masses, links = rng.uniform(0.001, 0.05, 40), rng.uniform(0.005, 0.02, 40)
    masses[[0, -1]] = 0.05, 0.001  # the extremes at the anchor and at the free end
    s = flat_rope(masses, links, direction=(-1.0, 0.0, 0.0))
    assert_hangs_straight_down(equilibrium(s), masses, links)


def test_rope_in_space_released_horizontal():
    """No plane: the rope may swing out of z = 0 too (two neutral-looking directions per bead at
    the start); it still comes to hang straight down, stable in both directions."""
    masses, links = np.full(25, 0.01), np.full(25, 0.01)
    s = flat_rope(masses, links, planar=False)
    eq = equilibrium(s)
    assert_hangs_straight_down(eq, masses, links)
    assert len(eq.eigenvalues) == 2 * 25


def test_newton_alone_still_reports_the_flat_start_as_no_equilibrium():
    """``method="newton"`` looks for a stationary point near the guess only: it fails cleanly."""
    s = flat_rope(np.full(30, 0.01), np.full(30, 0.01))
    with pytest.raises(C.InputError, match="no static equilibrium found near the guess"):
        equilibrium(s, method="newton")


def test_rope_pointing_up_is_the_inverted_equilibrium_near_it():
    """A stationary point at the guess is still what Newton returns (unstable), not the minimum."""
    s = flat_rope(np.full(30, 0.01), np.full(30, 0.01), direction=(0.0, 1.0, 0.0))
    eq = equilibrium(s)
    assert eq.method == "newton" and eq.stable is False
    np.testing.assert_allclose(eq.x[:, 1], 0.01 * np.arange(1, 31), atol=1e-12)


@pytest.mark.parametrize("unanchored", [1, 20])
def test_no_equilibrium_on_a_frictionless_incline_fails_cleanly(unanchored):
    """A bead (or a rope of 20) on a frictionless incline with nothing holding it: V is unbounded
    below; the descent follows it a bounded distance, then the failure names the reason."""
    s = C.System(name="incline")
    for i in range(unanchored):
        s.add_particle(f"p{i}", 0.01, [0.01 * i, 0.0, 0.0])
    for i in range(1, unanchored):
        s.add(C.Distance(f"p{i - 1}", f"p{i}", length=0.01))
    s.add(C.Plane(s.names, [0.0, np.cos(0.3), np.sin(0.3)], 0.0), C.Gravity([0, -G, 0]))
    with pytest.raises(C.InputError, match="no static equilibrium found near the guess.*V kept decreasing"):
        equilibrium(s)


def test_ctrl_c_during_the_descent_stops_it(monkeypatch):
    """A stop request (constrained.interrupt, as inside a watched run) ends the descent between
    iterations with KeyboardInterrupt, as Ctrl-C would outside one."""
    from constrained import interrupt

    monkeypatch.setattr(interrupt, "requested", lambda: True)
    s = flat_rope(np.full(30, 0.01), np.full(30, 0.01))
    with pytest.raises(KeyboardInterrupt):
        equilibrium(s)
