"""Statics and modes on 2-D meshes (docs/hard-cases.md, section 21): a drum of springs, nets of
rods hanging under gravity, a net with both diagonals in every cell (redundant rods).

Closed forms used:
- Drum: an (n+2) × (n+2) grid of beads of mass m at spacing a, the border pinned, neighbours
  joined by springs of stiffness k and rest length ρ (tension T = k (a − ρ)). At the flat
  equilibrium a spring's stiffness is k along it and T/a across it, so the interior's z motion is
  (T/a) times the grid Laplacian and the x motion k along x plus T/a along y:
  ω²_z(p, q) = (4T/(m a)) (S_p + S_q), ω²_x(p, q) = (4/m) (k S_p + (T/a) S_q), S_p = sin²(pπ/(2(n+1))),
  with the shape sin(p i π/(n+1)) sin(q j π/(n+1)).
- A net pinned along one edge hangs with each column a vertical chain; the rod above the bead
  j rows below the edge carries m g (n − j) (the beads below it), the rods across carry nothing.
  Its small motions: out of the hanging plane every column swings as a hanging chain on its own;
  in the plane the rods across tie each row together, so the net swings as one hanging chain of
  rows: n + 1 copies of the spectrum of the hanging chain of n − 1 beads."""

from __future__ import annotations

import numpy as np
import pytest

import constrained as C
from constrained.analysis.modes import modes
from constrained.analysis.statics import equilibrium

G = 9.81


def drum(n, *, m=0.01, k=50.0, a=0.1, rest=0.05, centre=None):
    s = C.System(name=f"drum {n}")
    N = n + 2
    for i in range(N):
        for j in range(N):
            heavy = centre is not None and i == j == (N - 1) // 2
            s.add_particle(f"b{i}_{j}", centre if heavy else m, [i * a, j * a, 0.0])
    for i in range(N):
        for j in range(N):
            if i in (0, N - 1) or j in (0, N - 1):
                s.add(C.Pin(f"b{i}_{j}", [i * a, j * a, 0.0]))
            if i + 1 < N and j not in (0, N - 1):
                s.add(C.Spring(f"b{i}_{j}", f"b{i + 1}_{j}", k=k, rest=rest))
            if j + 1 < N and i not in (0, N - 1):
                s.add(C.Spring(f"b{i}_{j}", f"b{i}_{j + 1}", k=k, rest=rest))
    return s


def membrane_spectrum(n, m, k, a, rest):
    T = k * (a - rest)
    S = np.sin(np.arange(1, n + 1) * np.pi / (2 * (n + 1))) ** 2
    z = (4 * T / (m * a)) * (S[:, None] + S[None, :])
    x = (4 / m) * (k * S[:, None] + (T / a) * S[None, :])
    return z, x, np.sort(np.concatenate([z.ravel(), x.ravel(), x.T.ravel()]))


def test_a_small_drum_has_every_mode_of_the_discrete_membrane():
    n, m, k, a, rest = 4, 0.01, 50.0, 0.1, 0.05
    s = drum(n, m=m, k=k, a=a, rest=rest)
    eq = equilibrium(s)
    assert eq.converged and eq.stable is True
    np.testing.assert_allclose(eq.x, s.positions, atol=1e-12)  # flat: the springs balance
    _, _, every = membrane_spectrum(n, m, k, a, rest)
    np.testing.assert_allclose(np.sort(eq.frequencies_squared), every, rtol=1e-10)
    md = modes(s)
    assert md.stable is True and len(md.modes) == 3 * n * n
    np.testing.assert_allclose(np.sort(md.frequencies ** 2), every, rtol=1e-10)


def _interior_z(shape, n):
    """The z displacements of the interior beads, (n, n), from a mode shape (N, 3) in grid order."""
    return np.asarray(shape).real.reshape(n + 2, n + 2, 3)[1:-1, 1:-1, 2]


def test_the_lowest_modes_of_a_10_by_10_drum_and_their_degenerate_pair():
    """count=6 (the sparse route: 132 pin rows) gives the lowest six: z (1, 1), the in-plane
    (1, 1) in x and in y, the z pair (1, 2), (2, 1), whose two computed shapes span the two sine
    products (any basis of that plane), and the in-plane (1, 2)."""
    n, m, k, a, rest = 10, 0.01, 50.0, 0.1, 0.05
    s = drum(n, m=m, k=k, a=a, rest=rest)
    md = modes(s, count=6)
    assert md.partial and md.total_degrees_of_freedom == 3 * n * n and md.stable is True
    z, x, every = membrane_spectrum(n, m, k, a, rest)
    np.testing.assert_allclose(md.frequencies ** 2, every[:6], rtol=1e-9)
    assert np.isclose(every[3], z[0, 1]) and np.isclose(every[4], z[1, 0])  # modes 4, 5: z's pair
    assert np.isclose(every[1], x[0, 0]) and np.isclose(every[2], x[0, 0])  # 2, 3: in-plane (1, 1), x and y
    i = np.arange(1, n + 1)
    sines = [np.outer(np.sin(p * i * np.pi / (n + 1)), np.sin(q * i * np.pi / (n + 1))).ravel()
             for p, q in ((1, 2), (2, 1))]
    want = np.linalg.qr(np.column_stack(sines))[0]
    got = np.linalg.qr(np.column_stack([_interior_z(md.modes[j].shape, n).ravel() for j in (3, 4)]))[0]
    np.testing.assert_allclose(np.linalg.svd(want.T @ got, compute_uv=False), 1.0, atol=1e-8)  # same plane
    for j in (3, 4):  # and no in-plane motion in them
        assert np.max(np.abs(np.asarray(md.modes[j].shape).real[:, :2])) < 1e-8


def test_a_drum_with_a_heavy_centre_bead_against_its_own_eigenproblem():
    """Centre bead 20 m: the z motion solves (T/a) L z = ω² M z, L the grid Laplacian, the x
    motion (k Lx + (T/a) Ly) x = ω² M x (Lx, Ly the second differences along x and y), y the
    same turned: all three computed here independently."""
    n, m, k, a, rest = 9, 0.01, 50.0, 0.1, 0.05
    s = drum(n, m=m, k=k, a=a, rest=rest, centre=20 * m)
    md = modes(s, count=6)
    L1 = 2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
    Lx, Ly = np.kron(L1, np.eye(n)), np.kron(np.eye(n), L1)  # (bead index i * n + j, i along x)
    masses = np.full(n * n, m)
    masses[(n // 2) * n + n // 2] = 20 * m
    d = 1 / np.sqrt(masses)
    T = k * (a - rest)
    blocks = ((T / a) * (Lx + Ly), k * Lx + (T / a) * Ly, (T / a) * Lx + k * Ly)  # z, x, y
    w2 = np.sort(np.concatenate([np.linalg.eigvalsh(d[:, None] * K * d[None, :]) for K in blocks]))
    np.testing.assert_allclose(md.frequencies ** 2, w2[:6], rtol=1e-9)
    even = (4 * T / (m * a)) * 2 * np.sin(np.pi / (2 * (n + 1))) ** 2
    assert md.frequencies[0] ** 2 < 0.5 * even  # the heavy bead lowers the fundamental


def net(n, *, m=0.01, a=0.1, pin="edge", diagonals=False, shrink=1.0):
    """n × n beads laid flat in z = 0 at spacing a·shrink, rods of length a between neighbours
    (and across each cell's diagonals), pinned along the row y = 0 or at the four corners;
    gravity −z."""
    s = C.System(name=f"net {n}")
    for i in range(n):
        for j in range(n):
            s.add_particle(f"b{i}_{j}", m, [i * a * shrink, j * a * shrink, 0.0])
    if pin == "edge":
        for i in range(n):
            s.add(C.Pin(f"b{i}_0", [i * a, 0.0, 0.0]))
    else:
        for i, j in [(0, 0), (n - 1, 0), (0, n - 1), (n - 1, n - 1)]:
            s.add(C.Pin(f"b{i}_{j}", [i * a * shrink, j * a * shrink, 0.0]))
    for i in range(n):
        for j in range(n):
            if i + 1 < n and not (pin == "edge" and j == 0):
                s.add(C.Distance(f"b{i}_{j}", f"b{i + 1}_{j}", length=a))
            if j + 1 < n:
                s.add(C.Distance(f"b{i}_{j}", f"b{i}_{j + 1}", length=a))
            if diagonals and i + 1 < n and j + 1 < n:
                s.add(C.Distance(f"b{i}_{j}", f"b{i + 1}_{j + 1}", length=a * np.sqrt(2)))
                s.add(C.Distance(f"b{i + 1}_{j}", f"b{i}_{j + 1}", length=a * np.sqrt(2)))
    s.add(C.Gravity([0, 0, -G]))
    return s


def hanging_chain_spectrum(beads, m, a):
    """ω² of a chain of ``beads`` beads (mass m, links a) hanging from a point, computed directly:
    m ÿ_j = (T_j (y_{j-1} − y_j) − T_{j+1} (y_j − y_{j+1}))/a, T_j = m g (beads − j) (j from 0)."""
    T = m * G * (beads - np.arange(beads + 1))  # T_j above bead j; T_beads = 0
    K = np.zeros((beads, beads))
    for j in range(beads):
        K[j, j] = (T[j] + T[j + 1]) / a
        if j + 1 < beads:
            K[j, j + 1] = K[j + 1, j] = -T[j + 1] / a
    return np.linalg.eigvalsh(K / m)


@pytest.mark.parametrize("n", [6, 12])  # 73 rows: a dense tangent basis; 282: the sparse descent
def test_a_net_pinned_along_one_edge_released_flat_hangs_straight_down(n):
    """From flat (every rod at right angles to gravity, the multipliers zero) the descent lets the
    beads fall; the net hangs in vertical columns with the tensions of hanging chains. The 12 × 12
    net takes the large model's descent (projected conjugate gradients, no dense basis: the 30 × 30
    net took 144–220 s on the dense one, about 8 s now)."""
    from constrained.analysis.statics_methods.large import is_large
    from constrained.model.structure import assemble

    m, a = 0.01, 0.1
    s = net(n, m=m, a=a)
    assert is_large(assemble(s)) == (n > 6)
    eq = equilibrium(s)  # flat: every rod at right angles to gravity
    assert eq.converged and eq.stable is True and eq.method == "descent"
    row = np.array([int(name.split("_")[1]) for name in s.names])
    col = np.array([int(name.split("_")[0][1:]) for name in s.names])
    np.testing.assert_allclose(eq.x[:, 0], col * a, atol=1e-9)
    np.testing.assert_allclose(eq.x[:, 1], 0.0, atol=1e-9)
    np.testing.assert_allclose(eq.x[:, 2], -row * a, atol=1e-9)
    labels = eq.constraint_labels
    for k, label in enumerate(labels):
        if label.startswith("distance"):
            names = label.split()[1].split("–")
            rows = sorted(int(nm.split("_")[1]) for nm in names)
            down = rows[0] != rows[1]
            tension = m * G * (n - rows[1]) if down else 0.0  # beads at rows[1] and below in the column
            assert eq.multipliers[k] == pytest.approx(-tension, abs=1e-9), label
    support = np.sum([f for _, f in eq.anchor_reactions], axis=0)
    np.testing.assert_allclose(support, [0, 0, n * n * m * G], atol=1e-9)
    chain = hanging_chain_spectrum(n - 1, m, a)
    np.testing.assert_allclose(np.sort(eq.frequencies_squared), np.sort(np.repeat(chain, n + 1)), rtol=1e-8)


def test_a_net_hung_from_four_corners_nearer_than_its_width():
    """Corners 0.8 of the flat width apart, started flat (off the rods' lengths): the net sags,
    symmetric under both mirror lines, each corner carries a quarter of the weight."""
    n, m, a = 5, 0.01, 0.1
    s = net(n, m=m, a=a, pin="corners", shrink=0.8)
    eq = equilibrium(s)
    assert eq.converged and eq.stable is True and eq.max_constraint_residual < 1e-12
    X = eq.x.reshape(n, n, 3)
    np.testing.assert_allclose(X[::-1, :, 2], X[:, :, 2], atol=1e-9)
    np.testing.assert_allclose(X[:, ::-1, 2], X[:, :, 2], atol=1e-9)
    assert np.all(X[1:-1, 1:-1, 2] < -0.05)  # it sags
    assert len(eq.anchor_reactions) == 4
    for _, f in eq.anchor_reactions:
        assert f[2] == pytest.approx(n * n * m * G / 4, rel=1e-9)
    assert eq.virtual_work_residual < 1e-10


def test_a_net_stretched_flat_between_its_corners_has_no_equilibrium():
    """Pinned at the corners of its flat extent, inextensible rods cannot sag at all: the flat net
    is the only configuration, and its horizontal rods cannot carry the weight."""
    with pytest.raises(C.InputError, match="no static equilibrium"):
        equilibrium(net(4, pin="corners"))


@pytest.mark.parametrize("n", [5, 8])  # 83 rows (dense), 227 (the large statics' sparse route)
def test_a_hanging_net_with_both_diagonals_is_not_called_unstable(n):
    """Both diagonals in every cell: rigid squares, hinged along the lines between rows, so the
    hanging net swings as a chain of rigid strips (stable); 28 self-stresses. The minimum-norm
    multipliers give negative ω² out of the plane (−49 /s²), which the old code reported as
    unstable; another valid split of the self-stress holds those first-order motions. The verdict
    is now undecided (None), the multipliers still minimum-norm (no part along the self-stresses)."""
    m, a = 0.01, 0.1
    s = net(n, m=m, a=a, diagonals=True)
    x = s.positions.copy()
    row = np.array([int(name.split("_")[1]) for name in s.names])
    x[:, 1], x[:, 2] = 0.0, -row * a
    eq = equilibrium(s, x)
    assert eq.converged and np.min(eq.frequencies_squared) < -1.0
    assert eq.stable is None and eq.undecided_by_self_stress
    np.testing.assert_allclose(eq.x, x, atol=1e-12)
    from constrained.analysis.statics import _forces_at_rest
    from constrained.model.structure import assemble

    model = assemble(s)
    F, J = _forces_at_rest(model, eq.x.ravel(), 0.0)
    import scipy.linalg as sla

    S = sla.null_space(J.T)
    assert S.shape[1] == J.shape[0] - (J.shape[1] - len(eq.frequencies_squared)) > 0  # rows − rank
    assert np.linalg.norm(S.T @ eq.multipliers) < 1e-9 * np.linalg.norm(eq.multipliers)
    np.testing.assert_allclose(F + J.T @ eq.multipliers, 0.0, atol=1e-10)
    support = np.sum([f for _, f in eq.anchor_reactions], axis=0)
    np.testing.assert_allclose(support, [0, 0, n * n * m * G], atol=1e-9)


def test_a_rod_stated_twice_still_gets_a_verdict():
    """The self-stress of a doubled rod has a zero stress matrix: an inverted pendulum on two
    identical rods is still UNSTABLE (ω² = −g/L), not undecided."""
    s = C.System([C.Particle("p", 1.0, [0.0, 1.0, 0.0])],
                 [C.Distance("p", point=[0, 0, 0], length=1.0), C.Distance("p", point=[0, 0, 0], length=1.0),
                  C.Plane("p", [0, 0, 1], 0.0)], [C.Gravity([0, -G, 0])])
    eq = equilibrium(s)
    assert eq.stable is False and not eq.undecided_by_self_stress
    np.testing.assert_allclose(eq.frequencies_squared, [-G], rtol=1e-9)


def test_modes_of_the_hanging_net_with_both_diagonals_say_undecided_as_statics():
    """``modes`` about the same hanging net: its growing modes at the minimum-norm multipliers
    (ω² = −49 /s² out of the plane) were "UNSTABLE" though another split of the self-stress holds
    them; the verdict is now undecided, as statics', and says why. The doubled rod of an inverted
    pendulum, whose self-stress changes nothing, is still UNSTABLE with its ω² = −g/L."""
    a = 0.1
    s = net(5, m=0.01, a=a, diagonals=True)
    x = s.positions.copy()
    row = np.array([int(name.split("_")[1]) for name in s.names])
    x[:, 1], x[:, 2] = 0.0, -row * a
    md = modes(s, x)
    assert md.stable is None and "undecided" in md.stability and "self-stress" in md.stability
    assert sum(m.growth_rate > 0 for m in md.modes) == 2  # (the modes themselves are unchanged)
    pendulum = C.System([C.Particle("p", 1.0, [0.0, 1.0, 0.0])],
                        [C.Distance("p", point=[0, 0, 0], length=1.0),
                         C.Distance("p", point=[0, 0, 0], length=1.0), C.Plane("p", [0, 0, 1], 0.0)],
                        [C.Gravity([0, -G, 0])])
    inverted = modes(pendulum)
    assert inverted.stable is False and inverted.stability.startswith("UNSTABLE")
    assert [m.growth_rate for m in inverted.modes] == pytest.approx([np.sqrt(G)], rel=1e-9)


def test_the_sparse_modes_route_gives_the_dense_routes_verdict_on_self_stressed_nets():
    """``count`` on a model of more than 100 rows takes the sparse route, which has no basis of the
    tangent space: it called the hanging 8 × 8 net with both diagonals (227 rows) "UNSTABLE (at
    least 4 growing modes)" where the dense route and statics say undecided. Random tangent
    directions now stand in for the basis in the self-stress check. The same net standing upright
    above its pinned edge without diagonals, one rod stated twice (a self-stress that changes
    nothing), is still UNSTABLE by both routes, with the same lowest ω²."""
    n, a = 8, 0.1
    row = np.array([int(name.split("_")[1]) for name in net(n).names])
    hanging = net(n, m=0.01, a=a, diagonals=True)
    x = hanging.positions.copy()
    x[:, 1], x[:, 2] = 0.0, -row * a
    sparse, dense = modes(hanging, x, count=4), modes(hanging, x)
    assert sparse.total_degrees_of_freedom is not None  # (the sparse route: a partial set)
    assert sparse.stable is None and dense.stable is None
    assert "undecided" in sparse.stability and "self-stress" in sparse.stability
    upright = net(n, m=0.01, a=a)
    upright.add(C.Distance("b0_1", "b0_2", length=a))
    x[:, 2] = row * a
    sparse, dense = modes(upright, x, count=4), modes(upright, x)
    assert sparse.stable is False and dense.stable is False
    assert sparse.stability.startswith("UNSTABLE (at least")
    def omega2(md):
        return np.sort([m.frequency ** 2 - m.growth_rate ** 2 for m in md.modes])

    np.testing.assert_allclose(omega2(sparse), omega2(dense)[:4], rtol=1e-8)
    assert omega2(sparse)[0] < -1000.0


def test_the_sparse_descent_reaches_the_dense_ones_equilibrium_on_an_uneven_net(monkeypatch):
    """A 10 × 10 net pinned along one edge, one bead 100 times heavier than the rest and every
    other bead of one row half as heavy (uneven masses weigh the descent's metric), started flat:
    the sparse descent and the dense one (forced by calling every model small) end at the same
    hanging net, and the pins carry its weight."""
    from constrained.analysis.statics_methods import descent

    n, m, a = 10, 0.01, 0.1
    s = net(n, m=m, a=a)
    masses = np.full(n * n, m)
    masses[3 * n + 6] = 100 * m
    masses[5 * n:6 * n:2] = 0.5 * m
    for p, mass in zip(s.particles, masses, strict=True):
        p.mass = float(mass)
    sparse = equilibrium(s)
    monkeypatch.setattr(descent, "is_large", lambda model: False)
    dense = equilibrium(s)
    assert sparse.converged and dense.converged and sparse.method == dense.method == "descent"
    np.testing.assert_allclose(sparse.x, dense.x, atol=1e-9)
    assert sparse.stable is True
    support = np.sum([f for _, f in sparse.anchor_reactions], axis=0)
    np.testing.assert_allclose(support, [0, 0, masses.sum() * G], rtol=1e-9, atol=1e-12)


def test_a_fine_rope_released_horizontal_hangs_by_the_sparse_descent_within_its_budget(monkeypatch):
    """150 links of 1 cm and 10 g, pinned at one end, released horizontal (301 rows: the large
    model's descent). Steihaug's truncated CG, tried first, stopped at every step on the first
    direction of zero curvature and ran out of the descent's 2,000 iterations on 300 links; on
    Krylov spaces it ends at a minimum well inside the budget. The rope hangs straight down with
    the tension m g (n − k) in its k-th link."""
    from constrained.analysis import statics
    from constrained.analysis.statics_methods.descent import DESCENT_ITERATIONS

    n, a, m = 150, 0.01, 0.01
    s = C.System(name="rope")
    for i in range(n):
        s.add_particle(f"p{i}", m, [(i + 1) * a, 0.0, 0.0])
    s.add(C.Distance("p0", point=[0, 0, 0], length=a))
    for i in range(n - 1):
        s.add(C.Distance(f"p{i}", f"p{i + 1}", length=a))
    s.add(C.Plane([f"p{i}" for i in range(n)], [0, 0, 1], 0.0))
    s.add(C.Gravity([0, -G, 0]))
    descents = []
    real = statics.minimize_on_constraints
    monkeypatch.setattr(statics, "minimize_on_constraints", lambda *a, **k: descents.append(real(*a, **k))
                        or descents[-1])
    eq = equilibrium(s)
    assert eq.converged and eq.method == "descent" and eq.stable is True
    assert descents[0].reason == "minimum" and descents[0].iterations < DESCENT_ITERATIONS // 4
    np.testing.assert_allclose(eq.x[:, 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(eq.x[:, 1], -a * np.arange(1, n + 1), atol=1e-9)
    np.testing.assert_allclose(np.sort(np.abs(eq.multipliers[:n])), m * G * np.arange(1, n + 1), rtol=1e-9)
