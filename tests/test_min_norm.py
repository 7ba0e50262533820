"""Redundant rows of mixed kinds with asymmetric masses (issue 26, item 4): the multipliers
reported by every method, by statics and by the sparse solve are the minimum-norm ones — no
component along the self-stress space null(Jᵀ) — while the constraint forces Jᵀλ stay the
physical ones. Symmetric duplicates cannot tell: any split of two equal rods looks right."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import null_space

import constrained as C
from constrained.manifold import algebra

G = np.array([0.0, -9.81, -2.0])  # a z component: the plane rows and the pin's z row carry load
CORNERS = {"p1": (0.0, 0.0), "p2": (1.0, 0.0), "p3": (1.0, 1.0), "p4": (0.0, 1.0)}
MASSES = (1.0, 2.0, 0.5, 1.5)


def frame(chain: int = 0) -> C.System:
    """A square frame of six rods (four sides, two diagonals: one self-stress) on four particles
    of unequal masses, all on the plane z = 0, pinned at p1 (the pin's z row repeats p1's plane
    row). ``chain`` links of 10 cm hang from p3 (rows enough for the sparse solve)."""
    s = C.System(name="over-constrained square frame")
    for (name, (x, y)), m in zip(CORNERS.items(), MASSES, strict=True):
        s.add_particle(name, m, [x, y, 0.0])
    for a, b in (("p1", "p2"), ("p2", "p3"), ("p3", "p4"), ("p4", "p1"), ("p1", "p3"), ("p2", "p4")):
        (xa, ya), (xb, yb) = CORNERS[a], CORNERS[b]
        s.add(C.Distance(a, b, length=float(np.hypot(xa - xb, ya - yb))))
    s.add(C.Plane(list(CORNERS), [0, 0, 1], name="table"), C.Pin("p1", [0, 0, 0]))
    previous = "p3"
    for k in range(chain):
        name = f"c{k}"
        s.add_particle(name, 0.01 * (1 + k % 3), [1.0 + 0.1 * (k + 1), 1.0, 0.0])
        s.add(C.Distance(previous, name, length=0.1))
        previous = name
    s.add(C.Gravity(G))
    return s


def self_stress_share(model, x, t, lam) -> float:
    """|projection of λ on null(Jᵀ)| / |λ|."""
    J = np.asarray(model.jacobian(np.ravel(x), t)[1])
    N = null_space(J.T)
    assert N.shape[1] >= 2  # the rods' self-stress and the pin/plane overlap, at least
    return float(np.linalg.norm(N.T @ lam) / np.linalg.norm(lam))


METHODS = {"dopri": {}, "projection": {}, "baumgarte": {}, "idas": {}, "ggl": {}, "pantelides": {},
           "rattle": {"dt": 1e-3}}


@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_method_reports_minimum_norm_multipliers(method):
    system = frame()
    model = C.assemble(system)
    tr = C.simulate(system, 0.5, method=method, t_eval=np.linspace(0.0, 0.5, 6), **METHODS[method])
    for k in range(len(tr.t)):
        assert self_stress_share(model, tr.x[k], tr.t[k], tr.multipliers[k]) < 1e-9
    # the duplicate of a different kind: the pin's z row and p1's plane row share p1's z load
    labels = model.constraint_labels
    plane_p1 = next(i for i, label in enumerate(labels) if "table" in label and "p1" in label)
    pin_z = [i for i, label in enumerate(labels) if label.startswith("pin")][2]
    np.testing.assert_allclose(tr.multipliers[:, plane_p1], tr.multipliers[:, pin_z], rtol=1e-9, atol=1e-12)
    # and the forces are the physical ones: the rigid frame's z loads balance gravity's z pull
    z_load = np.broadcast_to(-np.array(MASSES) * G[2], tr.constraint_forces[:, :, 2].shape)
    np.testing.assert_allclose(tr.constraint_forces[:, :, 2], z_load, rtol=1e-9)


def test_statics_reports_minimum_norm_multipliers():
    system = frame()
    eq = C.equilibrium(system)
    assert self_stress_share(C.assemble(system), eq.x, 0.0, eq.multipliers) < 1e-9
    np.testing.assert_allclose(eq.constraint_forces, -np.array(MASSES)[:, None] * G[None, :], atol=1e-9)


def test_the_sparse_solve_gives_the_dense_minimum_norm_multipliers(monkeypatch):
    system = frame(chain=100)  # 113 rows: beyond algebra.SPARSE_FROM
    model = C.assemble(system)
    assert model.n_constraints > algebra.SPARSE_FROM
    t_eval = np.linspace(0.0, 0.05, 3)
    sparse = C.simulate(system, 0.05, t_eval=t_eval, rtol=1e-10, atol=1e-10)
    for k in range(len(t_eval)):
        assert self_stress_share(model, sparse.x[k], t_eval[k], sparse.multipliers[k]) < 1e-8
    monkeypatch.setattr(algebra, "SPARSE_FROM", 10**9)
    dense = C.simulate(system, 0.05, t_eval=t_eval, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sparse.multipliers, dense.multipliers, rtol=1e-7, atol=1e-9)
