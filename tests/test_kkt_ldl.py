"""The KKT solve's compiled LDLᵀ (manifold.vectorized.ldl): the twisted tridiagonal one for
paths (chains), the sparse up-looking factorization for everything else. Both must solve
A Λ = B to round-off on patterns a user's model can give: a chain's tridiagonal (short, long,
shuffled), a band, arrows (one row coupled to all), a grid (a cloth), a chain closed into a
loop, rows with no coupling at all, and ill-conditioned values."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from constrained.codegen import compiled
from constrained.codegen.external import IndexTable, c_functions
from constrained.manifold.vectorized import ldl

pytestmark = pytest.mark.skipif(not compiled.enabled(), reason="no C compiler")


def _pattern(kind: str, n: int) -> set[tuple[int, int]]:
    pairs = set()
    if kind in ("chain", "loop"):
        pairs = {(k, k + 1) for k in range(n - 1)} | ({(0, n - 1)} if kind == "loop" else set())
    elif kind == "band":
        pairs = {(k, k + d) for k in range(n) for d in (1, 2, 3) if k + d < n}
    elif kind == "arrow down":
        pairs = {(k, n - 1) for k in range(n - 1)}
    elif kind == "arrow up":
        pairs = {(0, k) for k in range(1, n)}
    elif kind == "grid":
        side = int(round(np.sqrt(n)))
        for i in range(side):
            for j in range(side):
                if j + 1 < side:
                    pairs.add((i * side + j, i * side + j + 1))
                if i + 1 < side:
                    pairs.add((i * side + j, (i + 1) * side + j))
    elif kind in ("y", "tree", "forest"):
        rng = np.random.default_rng(n)
        if kind == "y":  # a chain with a second branch from its middle
            parent = [k - 1 if k != n // 2 + 1 else n // 4 for k in range(n)]
        else:  # each row coupled to one row before it (two trees for a forest)
            parent = [int(rng.integers(0, k)) if k else -1 for k in range(n)]
            if kind == "forest":
                parent[n // 2] = -1
                parent[n // 2 + 1:] = [p if p >= n // 2 else n // 2 for p in parent[n // 2 + 1:]]
        pairs = {(p, k) for k, p in enumerate(parent) if p >= 0}
    elif kind == "random":
        rng = np.random.default_rng(3)
        pairs = {tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(2 * n)}
    return pairs


def _matrix(kind: str, n: int, rng, condition: float = 1.0) -> np.ndarray:
    """A symmetric positive definite matrix of the pattern: G Gᵀ-like values, diagonally
    dominant, scaled by ``condition`` along the rows (D A D)."""
    a = np.zeros((n, n))
    for i, j in _pattern(kind, n):
        a[i, j] = a[j, i] = rng.uniform(-1, 1)
    a[np.diag_indices(n)] = np.abs(a).sum(axis=1) + rng.uniform(0.01, 1, n)
    d = np.logspace(0, np.log10(condition), n)
    rng.shuffle(d)
    return d[:, None] * a * d[None, :]


def _sparse(a: np.ndarray) -> ca.DM:
    r, c = np.nonzero(a)
    return ca.DM(ca.Sparsity.triplet(*a.shape, r.tolist(), c.tolist()), a[r, c])


def _solver(a: np.ndarray, name: str):
    sp = _sparse(a).sparsity()
    table = IndexTable()
    bodies, work, iwork, _ = ldl.ldl_bodies(sp, table, (1, 2))
    specs = [(f"{name}_solve{k}", bodies[f"solve{k}"], ["A", "B"], [ca.Sparsity.dense(sp.nnz()),
              ca.Sparsity.dense(a.shape[0], k)], ["out"], [ca.Sparsity.dense(a.shape[0], k)], work, iwork)
             for k in (1, 2)]
    data = table.data()
    functions = c_functions(specs, table.c, key=data)
    assert functions is not None, compiled.last_error
    return sp, functions


@pytest.mark.parametrize("kind, n", [("chain", 1), ("chain", 2), ("chain", 400), ("loop", 60), ("band", 50),
                                     ("arrow down", 40), ("arrow up", 40), ("grid", 64), ("random", 80),
                                     ("none", 7), ("chain", 3), ("shuffled chain", 101),
                                     ("shuffled chain", 2), ("y", 300), ("tree", 200), ("shuffled tree", 150),
                                     ("forest", 90)])
@pytest.mark.parametrize("condition", [1.0, 1e6])
def test_the_compiled_ldl_solves_the_system(kind, n, condition, tmp_path, monkeypatch):
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    rng = np.random.default_rng(n)
    a = _matrix(kind.removeprefix("shuffled "), n, rng, condition)
    if kind.startswith("shuffled"):
        shuffle = rng.permutation(n)
        a = a[np.ix_(shuffle, shuffle)]
    sp, (solve1, solve2) = _solver(a, f"t{abs(hash((kind, n, condition))) % 10**8}")
    nonzeros = _sparse(a).nonzeros()
    b = rng.standard_normal((n, 2))
    expected = np.linalg.solve(a, b)
    scale = np.linalg.norm(expected, axis=0)
    tol = 1e-13 * np.linalg.cond(a)
    two = np.asarray(solve2(nonzeros, b))
    one = np.asarray(solve1(nonzeros, b[:, :1]))
    assert np.all(np.linalg.norm(two - expected, axis=0) <= tol * scale)
    assert np.linalg.norm(one[:, 0] - expected[:, 0]) <= tol * scale[0]


@pytest.mark.parametrize("kind, n", [("chain", 2), ("chain", 301), ("shuffled chain", 40), ("y", 120),
                                     ("grid", 100), ("random", 60), ("none", 5)])
def test_one_factorization_serves_many_solves(kind, n, tmp_path, monkeypatch):
    """``factor`` then ``substitute{k}`` is ``solve{k}`` (RATTLE's simplified Newton: one
    factorization, a substitution per iteration), for each kind of factorization."""
    monkeypatch.setenv("CONSTRAINED_CACHE", str(tmp_path / "cache"))
    rng = np.random.default_rng(n + 7)
    a = _matrix(kind.removeprefix("shuffled "), n, rng, 1e4)
    if kind.startswith("shuffled"):
        shuffle = rng.permutation(n)
        a = a[np.ix_(shuffle, shuffle)]
    sp = _sparse(a).sparsity()
    table = IndexTable()
    bodies, work, iwork, stored = ldl.ldl_bodies(sp, table, (1, 2))
    A_sp, F_sp = ca.Sparsity.dense(sp.nnz()), ca.Sparsity.dense(stored)
    name = f"f{abs(hash((kind, n))) % 10**8}"
    specs = [(f"{name}_factor", bodies["factor"], ["A"], [A_sp], ["out"], [F_sp], work, iwork)]
    for k in (1, 2):
        B = ca.Sparsity.dense(n, k)
        specs += [(f"{name}_solve{k}", bodies[f"solve{k}"], ["A", "B"], [A_sp, B], ["out"], [B], work, iwork),
                  (f"{name}_substitute{k}", bodies[f"substitute{k}"], ["LD", "B"], [F_sp, B], ["out"], [B],
                   work, iwork)]
    functions = c_functions(specs, table.c, key=table.data())
    assert functions is not None, compiled.last_error
    factor, solve1, substitute1, solve2, substitute2 = functions
    nonzeros = _sparse(a).nonzeros()
    factors = factor(nonzeros)
    for _ in range(2):  # (a substitution leaves the factors as they were)
        b = rng.standard_normal((n, 2))
        assert np.array_equal(np.asarray(substitute2(factors, b)), np.asarray(solve2(nonzeros, b)))
        one = np.asarray(substitute1(factors, b[:, :1]))
        assert np.array_equal(one, np.asarray(solve1(nonzeros, b[:, :1])))
        expected = np.linalg.solve(a, b)
        assert np.allclose(np.asarray(substitute2(factors, b)), expected, rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("kind, n, path", [("chain", 300, True), ("loop", 30, False), ("grid", 100, False),
                                           ("arrow down", 30, False), ("band", 50, False), ("none", 5, True)])
def test_a_path_is_found_in_any_order_of_its_rows(kind, n, path):
    """A chain's rods, shuffled and as two chains, are a path in some order (tridiagonal there);
    a loop, a grid, an arrow and a band are not."""
    rng = np.random.default_rng(0)
    a = _matrix(kind, n, rng)
    shuffle = rng.permutation(n)
    for matrix in (a, a[np.ix_(shuffle, shuffle)], np.block([[a, np.zeros((n, n))], [np.zeros((n, n)), a]])):
        sp = _sparse(matrix).sparsity()
        order = ldl.path_order(sp)
        assert (order is not None) == path
        if path:
            assert sorted(order) == list(range(matrix.shape[0]))
            permuted = matrix[np.ix_(order, order)]
            assert not np.any(np.triu(permuted, 2)) and not np.any(np.tril(permuted, -2))


@pytest.mark.parametrize("kind, n, expected", [
    ("chain", 300, "path"), ("none", 6, "path"), ("y", 200, "short columns"), ("tree", 300, "short columns"),
    ("forest", 100, "short columns"), ("arrow up", 30, "short columns"), ("loop", 30, "short columns"),
    ("band", 40, "short columns"), ("grid", 100, "supernodal"), ("random", 80, "supernodal")])
def test_each_pattern_takes_the_factorization_that_fits_it(kind, n, expected):
    """A chain is a path; a branching chain, a tree, two trees, a star, a closed loop and a band
    of three have L of short columns in AMD's order (a loop: two entries a column, the band:
    three); a grid and a random graph fill in, and take the panels. The same in any order of
    the rows."""
    rng = np.random.default_rng(2)
    a = _matrix(kind, n, rng)
    shuffle = rng.permutation(n)
    for matrix in (a, a[np.ix_(shuffle, shuffle)]):
        assert ldl.factorization(_sparse(matrix).sparsity())[0] == expected
