"""The dense statics route (a small model) converts CasADi's sparse J and K to arrays with
``statics_methods.large.dense`` (fast for large sparse matrices). It must give np.asarray's
array bit for bit, the sign of a zero included: J of a net at rest holds −0.0 entries
(x_a − x_b of equal coordinates, negated), whose sign the route's QR and eigh read. SciPy's
``toarray`` (adding each entry to a zero array) made them +0.0, and a 5 × 4 net's equilibrium
moved by 1e-14 against the conversion by np.asarray (found by differential probing)."""

from __future__ import annotations

import casadi as ca
import numpy as np

import constrained as C
from constrained.analysis.statics_methods import large


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_dense_keeps_negative_zeros_and_structural_zeros():
    m = ca.DM(ca.Sparsity.lower(3), [1e-320, -0.0, 3.0, np.inf, -0.0, -6.0])
    assert _same_bits(large.dense(m), np.asarray(m, float))
    assert np.signbit(large.dense(m)[1, 0])
    wide = ca.DM(ca.Sparsity.triplet(2, 5, [0, 1, 1], [4, 0, 2]), [-0.0, 2.0, -0.0])
    assert _same_bits(large.dense(wide), np.asarray(wide, float))
    assert _same_bits(large.dense(ca.DM(2, 3)), np.zeros((2, 3)))


def _net(w: int = 5, h: int = 4) -> C.System:
    """A w × h net in the plane y = 0 (rods along its rows, springs down its columns and across
    its cells, one at rest length 0), pinned at its two top corners, under gravity −z."""
    s = C.System()
    name = lambda i, j: f"n{i}_{j}"  # noqa: E731
    for j in range(h):
        for i in range(w):
            s.add_particle(name(i, j), 0.1, [float(i), 0.0, -0.9 * j + 0.05 * ((7 * i + 3 * j) % 5)])
    for j in range(h):
        for i in range(w):
            if i + 1 < w:
                s.add(C.Distance(name(i, j), name(i + 1, j), length=1.02))
            if j + 1 < h:
                s.add(C.Spring(name(i, j), name(i, j + 1), k=50.0, rest=1.0))
            if i + 1 < w and j + 1 < h:
                s.add(C.Spring(name(i, j), name(i + 1, j + 1), k=5, rest=0))
    s.add(C.Pin(name(0, 0), [0.0, 0.0, 0.0]), C.Pin(name(w - 1, 0), [w - 1.0, 0.0, 0.0]))
    s.add(C.Gravity([0, 0, -9.81]))
    return s


def test_net_equilibrium_equals_the_one_by_np_asarray(monkeypatch):
    net = _net()
    model = C.assemble(net)
    x = net.positions.ravel()
    J = model.dynamics(x, np.zeros_like(x), 0.0)[1]
    assert np.signbit(np.asarray(J, float)).any()  # (the case: −0.0 entries in J)
    fast = C.equilibrium(net)
    monkeypatch.setattr(large, "dense", lambda dm: np.asarray(dm, float))
    general = C.equilibrium(_net())
    assert fast.converged and general.converged
    assert _same_bits(fast.x, general.x)
    assert _same_bits(fast.multipliers, general.multipliers)
