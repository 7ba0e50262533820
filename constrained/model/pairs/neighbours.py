"""Neighbour lists of a pair potential with a cutoff, built outside the symbolic graph (NumPy,
SciPy's cKDTree): every pair (i, j), i < j, of points closer than a reach (r_c + skin), held
by i in *rows* of ROW neighbours j (a point with more has several rows; its last is padded),
the rows padded to a fixed capacity in whole groups of GROUP_ROWS. The result is data for the
mapped kernel (constrained.model.pairs.kernel), not code."""

from __future__ import annotations

import numpy as np

#: Neighbours per row: a row is one particle i and ROW particles j (the padding of each
#: particle's last row is about ROW/2 places; i is gathered and its force scattered once per row).
ROW = 8
#: Rows per call of the listed kernel (GROUP_ROWS · ROW pairs written out once; the shift's
#: constants computed once per call). A list is padded to whole groups.
GROUP_ROWS = 4
#: Below this many points the pairs are found by brute force (no tree).
BRUTE_FORCE_BELOW = 64


def pairs_within(y: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (i, j), i < j, of points y (n, 3) at most ``reach`` apart, ordered by i."""
    n = len(y)
    if n < BRUTE_FORCE_BELOW:
        i, j = np.triu_indices(n, 1)
        d = y[i] - y[j]
        near = np.einsum("ij,ij->i", d, d) <= reach * reach
        return i[near].astype(np.int64), j[near].astype(np.int64)
    from scipy.spatial import cKDTree

    # (an unbalanced tree of uncompacted nodes: built and searched ~1.4x faster here)
    found = cKDTree(y, balanced_tree=False, compact_nodes=False).query_pairs(reach, output_type="ndarray")
    if not len(found):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    i, j = found[:, 0], found[:, 1]  # (i < j: query_pairs' documented order within a pair)
    # (a stable sort of small integers is a radix sort: ~3x faster than a lexsort of both)
    order = np.argsort(i.astype(np.int16) if n < 2 ** 15 else i, kind="stable")
    return i[order].astype(np.int64, copy=False), j[order].astype(np.int64, copy=False)


def without(i: np.ndarray, j: np.ndarray, n: int,
            excluded: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (i, j) (ordered by i) less the ``excluded`` ones ((E, 2), either order). An
    excluded pair is never summed at all: a bond 0.05 σ long inside an r⁻¹² repulsion has
    φ ~ 1e15, which added and subtracted again leaves only round-off of the other pairs."""
    if excluded is None or not len(excluded) or not len(i):
        return i, j
    lo, hi = np.minimum(excluded[:, 0], excluded[:, 1]), np.maximum(excluded[:, 0], excluded[:, 1])
    keep = ~np.isin(i * n + j, lo.astype(np.int64) * n + hi)
    return i[keep], j[keep]


def rows_needed(i: np.ndarray, n: int) -> int:
    """The rows that hold the pairs whose first points are ``i``."""
    return int(np.sum(-(-np.bincount(i, minlength=n) // ROW)))


def capacity_for(rows: int, factor: float, n: int) -> int:
    """Room for ``factor`` times ``rows`` rows (at most the rows of every pair), in whole
    groups, at least one."""
    most = int(np.sum(-(-(n - 1 - np.arange(n)) // ROW)))
    wanted = min(most, int(np.ceil(factor * rows)) + GROUP_ROWS)
    return max(1, -(-wanted // GROUP_ROWS)) * GROUP_ROWS


def pair_rows(y: np.ndarray, reach: float, capacity: int,
              excluded: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """(I, J): the pairs of the points y (n, 3) within ``reach`` (``pairs_within``), less the
    ``excluded`` ones ((E, 2): never listed), in rows:
    I (capacity,) the row's point, J (capacity·ROW,) its ROW neighbours, row after row; a
    row's empty places hold n + 1, an empty row's point n (two placeholders, which the kernel
    places beyond the cutoff from each other and from every point: they count nothing); as
    floats. None when the pairs need more than ``capacity`` rows."""
    n = len(y)
    i, j = without(*pairs_within(y, reach), n, excluded)
    counts = np.bincount(i, minlength=n)
    per_point = -(-counts // ROW)
    if per_point.sum() > capacity:
        return None
    first_row = np.concatenate([[0], np.cumsum(per_point)[:-1]])
    first_pair = np.concatenate([[0], np.cumsum(counts)[:-1]])
    within = np.arange(len(i)) - first_pair[i]  # each pair's place in its point's list
    I = np.full(capacity, float(n))
    I[:per_point.sum()] = np.repeat(np.arange(n), per_point)
    J = np.full(capacity * ROW, float(n + 1))
    J[first_row[i] * ROW + within] = j
    return I, J
