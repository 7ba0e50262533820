"""The supernodal LDLᵀ (manifold.vectorized.supernodal): its supernodes on patterns whose
supernodes are known (a chain, rows with no coupling, dense blocks), its updates' places, and
its solves, to round-off × the condition number, on grids, arrows, random patterns, dense
matrices, n = 1 and 2, with no relaxation, the default one and the most, so that updates
from panels of 1, 2, 3, 4 and more columns all run."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from test_kkt_ldl import _matrix, _sparse

from constrained.codegen import compiled
from constrained.codegen.external import IndexTable, c_functions
from constrained.manifold.vectorized import supernodal

NONE, MOST = ((None, 0.0),), ((None, 1.0),)


def _structure(a: np.ndarray, relax=supernodal.RELAX, amd: bool = True) -> dict:
    lt, p = _sparse(a).sparsity().ldl(amd)
    return supernodal.symbolic(lt, p, relax)


def test_a_chain_in_its_order_is_columns_then_one_pair_or_one_panel():
    """Tridiagonal: L[:, j] = {j + 1}, so only the last two columns share a structure; relaxed,
    the chain's columns merge into panels (at most 4 columns whatever their zeros)."""
    a = _matrix("chain", 9, np.random.default_rng(0))
    assert _structure(a, NONE, amd=False)["F"].tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 9]
    assert np.all(np.diff(_structure(a, amd=False)["F"]) >= 2)
    assert _structure(a, MOST, amd=False)["F"].tolist() == [0, 9]


def test_rows_with_no_coupling_are_one_column_each_and_update_nothing():
    s = _structure(np.diag(np.arange(1.0, 6.0)))
    assert s["F"].tolist() == [0, 1, 2, 3, 4, 5]
    assert len(s["Uk"]) == 0 and s["Up"].tolist() == [0] * 6


def test_dense_blocks_are_one_supernode_each_and_an_arrow_one_more():
    """Two dense 3 x 3 blocks coupled to one last row: the blocks (with the row in their
    structure) are a supernode each, updating the last one, whose rows are all theirs."""
    a = np.eye(7) * 10
    a[:3, :3] += 1
    a[3:6, 3:6] += 1
    a[6, :] = a[:, 6] = 1
    a[6, 6] = 10
    s = _structure(a, NONE, amd=False)
    assert s["F"].tolist() == [0, 3, 7]
    assert s["R"].tolist() == [0, 1, 2, 6, 3, 4, 5, 6]
    assert s["Uk"].tolist() == [0] and s["Ua"].tolist() == [3] and s["Ub"].tolist() == [4]
    assert s["Rel"].tolist() == [3]  # row 6: the 4th of the last supernode's rows


@pytest.mark.parametrize("kind, n", [("grid", 400), ("random", 150), ("band", 40)])
def test_the_updates_places_are_the_same_rows(kind, n):
    """Rel maps each update's rows R_K[a:] to the same rows among R_J, and the updates of J
    come from supernodes before it whose rows R_K[a:b] are J's columns."""
    s = _structure(_matrix(kind, n, np.random.default_rng(1)))
    first, ri, rp = s["F"], s["R"], s["Rp"]
    for j in range(len(first) - 1):
        for u in range(s["Up"][j], s["Up"][j + 1]):
            k, a, b = s["Uk"][u], s["Ua"][u], s["Ub"][u]
            rows_k = ri[rp[k] + a:rp[k + 1]]
            assert k < j and a < b and first[j] <= ri[rp[k] + a] and ri[rp[k] + b - 1] < first[j + 1]
            rel = s["Rel"][s["Uo"][u]:s["Uo"][u] + len(rows_k)]
            assert np.array_equal(ri[rp[j] + rel], rows_k)


def _solve(a: np.ndarray, relax, name: str, ks=(1, 2)):
    sp = _sparse(a).sparsity()
    lt, p = sp.ldl(True)
    table = IndexTable()
    bodies, work, iwork, _ = supernodal.supernodal_bodies(sp, lt, p, table, ks, relax)
    n = a.shape[0]
    specs = [(f"{name}_solve{k}", bodies[f"solve{k}"], ["A", "B"], [ca.Sparsity.dense(sp.nnz()),
              ca.Sparsity.dense(n, k)], ["out"], [ca.Sparsity.dense(n, k)], work, iwork) for k in ks]
    functions = c_functions(specs, table.c, key=table.data())
    assert functions is not None, compiled.last_error
    return _sparse(a).nonzeros(), functions


@pytest.mark.skipif(not compiled.enabled(), reason="no C compiler")
@pytest.mark.parametrize("kind, n", [("grid", 900), ("grid", 49), ("random", 120), ("arrow down", 30),
                                     ("arrow up", 30), ("dense", 12), ("dense", 1), ("dense", 2),
                                     ("loop", 40)])
@pytest.mark.parametrize("relax", [NONE, supernodal.RELAX, MOST])
@pytest.mark.parametrize("condition", [1.0, 1e8])
def test_the_supernodal_ldl_solves_the_system(kind, n, relax, condition, tmp_path, monkeypatch):
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    rng = np.random.default_rng(n)
    if kind == "dense":
        g = rng.standard_normal((n, n))
        a = g @ g.T + n * np.eye(n)
        d = np.logspace(0, np.log10(condition), n)
        a = d[:, None] * a * d[None, :]
    else:
        a = _matrix(kind, n, rng, condition)
    nonzeros, (solve1, solve2) = _solve(a, relax, f"sn{abs(hash((kind, n, relax, condition))) % 10**8}")
    b = rng.standard_normal((n, 2))
    expected = np.linalg.solve(a, b)
    tol = 1e-13 * np.linalg.cond(a) * np.linalg.norm(expected, axis=0)
    assert np.all(np.linalg.norm(np.asarray(solve2(nonzeros, b)) - expected, axis=0) <= tol)
    assert np.linalg.norm(np.asarray(solve1(nonzeros, b[:, :1]))[:, 0] - expected[:, 0]) <= tol[0]


@pytest.mark.parametrize("relax", [NONE, supernodal.RELAX, MOST])
def test_a_grid_has_updates_from_panels_of_every_width_the_kernel_treats_apart(relax):
    """The update kernel takes K's columns four at a time with a remainder of 1, 2 or 3: the
    30 x 30 grid of the solve test has updates from panels of each (so that each case runs)."""
    s = _structure(_matrix("grid", 900, np.random.default_rng(900)), relax)
    widths = set(np.diff(s["F"])[s["Uk"]].tolist())
    assert {1, 2, 3} <= {w % 4 for w in widths} and max(widths) >= 4


def _forest(rng, n: int) -> np.ndarray:
    """An elimination forest of n columns: parent(j) > j, or −1 (a root)."""
    parent = np.array([int(rng.integers(j + 1, min(n, j + 6) + 1)) if rng.random() > 0.05 else -1
                       for j in range(n)], np.int64)
    parent[parent >= n] = -1
    return parent


@pytest.mark.parametrize("seed", range(6))
def test_the_postorder_is_the_recursive_one(seed):
    """The iterative walk gives the recursive definition's order: every subtree, children in
    ascending order, then its root; the roots ascending."""
    rng = np.random.default_rng(seed)
    parent = _forest(rng, int(rng.integers(1, 300)))
    children = {j: sorted(np.flatnonzero(parent == j).tolist()) for j in range(len(parent))}

    def walk(j):
        return [k for c in children[j] for k in walk(c)] + [j]

    expected = [k for root in np.flatnonzero(parent < 0).tolist() for k in walk(root)]
    assert supernodal._postorder(parent).tolist() == expected


def _merged_reference(first, count, parent, relax):
    """``supernodal._merge`` as the rule reads (CHOLMOD's), on NumPy numbers."""
    groups = []
    for s in range(len(first) - 1):
        f, e = first[s], first[s + 1]
        group = [f, e - f, int(count[f:e].sum()) + e - f]
        while groups and parent[group[0] - 1] == group[0]:
            g, c, z = groups[-1]
            columns = c + group[1]
            zeros = 1 - (z + group[2]) / (columns * (columns + 1) // 2 + columns * count[e - 1])
            if not any((top is None or columns <= top) and zeros <= most for top, most in relax):
                break
            groups.pop()
            group = [g, columns, z + group[2]]
        groups.append(group)
    return [g[0] for g in groups] + [len(parent)]


@pytest.mark.parametrize("seed", range(6))
def test_the_relaxed_supernodes_follow_the_rule(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 300))
    parent = np.where(rng.random(n) < 0.8, np.arange(1, n + 1), _forest(rng, n))
    parent[parent >= n] = -1
    count = rng.integers(0, 40, n)
    first = sorted({0, *rng.integers(1, n, n // 3).tolist()}) + [n]
    for relax in (supernodal.RELAX, ((2, 1.0), (None, 0.3))):
        assert supernodal._merge(first, count, parent, relax).tolist() == _merged_reference(
            first, count, parent, relax)


@pytest.mark.parametrize("shape", [(0, 0), (3, 0), (1, 1), (5, 7), (40, 12), (200, 200)])
def test_the_triplet_from_rows_and_offsets_is_casadis(shape):
    """``columns.triplet`` (rows and column offsets) gives ``get_triplet``'s entries, in its order,
    with empty columns and empty patterns among them."""
    from constrained.manifold.vectorized.columns import triplet

    rng = np.random.default_rng(sum(shape))
    n, m = shape
    k = int(rng.integers(0, n * m + 1)) if n * m else 0
    sparsity = ca.Sparsity.triplet(n, m, rng.integers(0, max(n, 1), k).tolist(),
                                   rng.integers(0, max(m, 1), k).tolist())
    rows, cols = triplet(sparsity)
    expected = sparsity.get_triplet()
    assert rows.dtype == cols.dtype == np.int64
    assert rows.tolist() == list(expected[0]) and cols.tolist() == list(expected[1])
