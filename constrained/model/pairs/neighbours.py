"""Neighbour lists of a pair potential with a cutoff, built outside the symbolic graph (NumPy,
SciPy's cKDTree): every pair of points closer than a reach (r_c + skin), as two index arrays
padded to a fixed capacity in whole chunks. The result is data for the mapped kernel
(constrained.model.pairs.kernel), not code."""

from __future__ import annotations

import numpy as np

#: Pairs per call of the listed kernel (written out once: CHUNK pairs, ~40 operations each;
#: the shift's constants computed once per chunk). A list is padded to whole chunks.
CHUNK = 32
#: Below this many points the pairs are found by brute force (no tree).
BRUTE_FORCE_BELOW = 64


def pairs_within(y: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (i, j), i < j, of points y (n, 3) at most ``reach`` apart, ordered by i then j
    (so that the positions a chunk reads lie close together in memory)."""
    n = len(y)
    if n < BRUTE_FORCE_BELOW:
        i, j = np.triu_indices(n, 1)
        d = y[i] - y[j]
        near = np.einsum("ij,ij->i", d, d) <= reach * reach
        return i[near].astype(np.int64), j[near].astype(np.int64)
    from scipy.spatial import cKDTree

    found = cKDTree(y).query_pairs(reach, output_type="ndarray")
    if not len(found):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    found = np.sort(found, axis=1)
    order = np.lexsort((found[:, 1], found[:, 0]))
    return found[order, 0].astype(np.int64), found[order, 1].astype(np.int64)


def capacity_for(count: int, factor: float, n: int) -> int:
    """Room for ``factor`` times ``count`` pairs (at most every pair of n points), in whole
    chunks, at least one."""
    most = n * (n - 1) // 2
    wanted = min(most, int(np.ceil(factor * count)) + CHUNK)
    return max(1, -(-wanted // CHUNK)) * CHUNK


def pair_list(y: np.ndarray, reach: float, capacity: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(I, J): the pairs of the points y (n, 3) within ``reach`` (``pairs_within``) padded to
    ``capacity`` with the pair (n, n + 1) of two placeholders (which the kernel places beyond
    the cutoff: they count nothing), as floats; None when there are more than ``capacity``."""
    n = len(y)
    i, j = pairs_within(y, reach)
    if len(i) > capacity:
        return None
    I, J = np.full(capacity, float(n)), np.full(capacity, float(n + 1))
    I[:len(i)], J[:len(j)] = i, j
    return I, J
