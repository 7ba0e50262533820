"""Statics of a large model (session 15): a catenary of 1 cm links, solved with sparse
matrices (statics_methods.large and the sparse Newton of statics_methods.kkt). A 300-link
catenary took 48 s with every matrix dense, a 1,000-link one 138 s; the sparse route
answers the same.

Closed form of the discrete chain (N links of length ℓ, N − 1 beads of mass m, supports at
(0, 0) and (d, 0)): the horizontal tension H is the same in every link, link k (from the left,
k = 0 … N − 1) carries the vertical tension V₀ − k m g with V₀ = (N − 1) m g / 2 by symmetry,
so it points at the angle θ_k = atan((V₀ − k m g)/H) below the horizontal; H is the root of
Σ ℓ cos θ_k = d, and bead j sits at Σ_{k<j} ℓ (cos θ_k, −sin θ_k)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from constrained import System
from constrained.analysis import statics
from constrained.analysis.statics import equilibrium
from constrained.analysis.statics_methods import kkt, large
from constrained.model.constraints import Distance, Plane
from constrained.model.effects import Gravity
from constrained.model.system import Particle

G, LINK, MASS = 9.81, 0.01, 0.001


def catenary(n, *, doubled: int | None = None):
    """n links, hung from (0, 0, 0) and (d, 0, 0) with d = 0.75 n ℓ, started as a V of exact
    links; ``doubled``: that link's rod stated twice (redundant rows)."""
    half = n // 2
    c = 0.75 * n / (2 * half) if n % 2 == 0 else 0.75
    s = np.sqrt(1 - c * c)
    points = [np.zeros(3)]
    for i in range(n):
        points.append(points[-1] + LINK * np.array([c, -s if i < half else s, 0.0]))
    points = np.array(points)
    names = [f"p{i}" for i in range(1, n)]
    rods = [Distance("p1", point=[0, 0, 0], length=LINK)]
    rods += [Distance(f"p{i}", f"p{i + 1}", length=LINK) for i in range(1, n - 1)]
    rods += [Distance(f"p{n - 1}", point=points[n].tolist(), length=LINK)]
    if doubled is not None:
        rods.append(Distance(f"p{doubled}", f"p{doubled + 1}", length=LINK))
    system = System([Particle(name, MASS, points[i + 1].tolist()) for i, name in enumerate(names)],
                    [*rods, Plane(names, [0, 0, 1], 0.0)], [Gravity([0, -G, 0])])
    return system, float(points[n][0])


def discrete_catenary(n, d):
    k = np.arange(n)
    V0 = (n - 1) * MASS * G / 2
    def angles(H):
        return np.arctan((V0 - k * MASS * G) / H)
    H = brentq(lambda H: np.sum(LINK * np.cos(angles(H))) - d, 1e-6, 1e6)
    theta = angles(H)
    steps = LINK * np.stack([np.cos(theta), -np.sin(theta)], axis=1)
    return np.cumsum(steps, axis=0)[:-1], H, V0


def test_a_large_catenary_by_the_sparse_route_is_the_discrete_catenary():
    n = 120
    system, d = catenary(n)
    eq = equilibrium(system)
    assert large.is_large(eq_model := statics.assemble(system)) and eq_model.n_constraints > 100
    exact, H, V0 = discrete_catenary(n, d)
    np.testing.assert_allclose(eq.x[:, :2], exact, atol=1e-10)
    assert eq.stable is True and eq.method == "newton"
    left = eq.anchor_reactions[0][1]
    np.testing.assert_allclose(left, [-H, V0, 0.0], atol=1e-9 * V0)  # the support's pull
    # every rod's tension: the multipliers' forces match the closed form's link tensions
    theta = np.arctan((V0 - np.arange(n) * MASS * G) / H)
    rod_forces = np.linalg.norm(eq.constraint_forces[:, :2], axis=1)  # (a bead's net: its weight)
    np.testing.assert_allclose(rod_forces, MASS * G, rtol=1e-9)
    assert np.all(np.diff(theta) < 0)


def test_the_sparse_and_dense_routes_agree(monkeypatch):
    system, _ = catenary(120)
    sparse_eq = equilibrium(system)
    monkeypatch.setattr(large, "is_large", lambda model: False)
    monkeypatch.setattr(kkt, "SPARSE_KKT_FROM", 10 ** 9)
    dense_eq = equilibrium(system)
    np.testing.assert_allclose(sparse_eq.x, dense_eq.x, atol=1e-12)
    np.testing.assert_allclose(sparse_eq.multipliers, dense_eq.multipliers, rtol=1e-8,
                               atol=1e-9 * np.max(np.abs(dense_eq.multipliers)))
    np.testing.assert_allclose(sparse_eq.frequencies_squared[:10], dense_eq.frequencies_squared[:10],
                               rtol=1e-7)
    assert sparse_eq.stable is dense_eq.stable is True


def test_a_rod_stated_twice_shares_its_tension_evenly_at_scale():
    """Redundant rows in the sparse route: the minimum-norm split gives each copy half."""
    n = 120
    system, d = catenary(n, doubled=40)
    eq = equilibrium(system)
    exact, H, V0 = discrete_catenary(n, d)
    np.testing.assert_allclose(eq.x[:, :2], exact, atol=1e-10)
    labels = eq.constraint_labels
    rows = [k for k, label in enumerate(labels) if label.startswith("distance p40–p41")]
    assert len(rows) == 2
    lam = eq.multipliers[rows]
    np.testing.assert_allclose(lam[0], lam[1], rtol=1e-9)
    single = equilibrium(catenary(n)[0])  # the rod stated once carries what the two copies share
    once = single.multipliers[single.constraint_labels.index(labels[rows[0]])]
    assert lam[0] + lam[1] == pytest.approx(once, rel=1e-9)
