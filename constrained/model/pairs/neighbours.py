"""Neighbour lists of a pair potential with a cutoff, built outside the symbolic graph (NumPy,
SciPy's cKDTree): the particles put in blocks of BLOCK along a Morton curve, never straddling
a cell of the curve's grid (compact blocks), and for each block the blocks whose bounding boxes
come within a reach (r_c + skin) of its own, each pair of blocks held by one of the two. The
result is data for the mapped kernel (constrained.model.pairs.kernel), not code."""

from __future__ import annotations

import numpy as np

#: Particles per block: a tile is BLOCK² pairs written out once (64 pairs, ~1.7k operations);
#: larger tiles amortize the map's call more but waste more pairs at a cutoff's edge.
BLOCK = 8
MORTON_BITS = 10


def morton_codes(y: np.ndarray) -> np.ndarray:
    """Morton (Z-order) codes of the points y (n, 3) on a 2^MORTON_BITS grid over their box."""
    lo, extent = y.min(axis=0), np.ptp(y, axis=0)
    top = 2 ** MORTON_BITS - 1e-3
    cells = np.floor((y - lo) / np.where(extent > 0, extent, 1.0) * top).astype(np.uint64)
    code = np.zeros(len(y), dtype=np.uint64)
    for bit in range(MORTON_BITS):
        for axis in range(3):
            code |= ((cells[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return code


def blocks(y: np.ndarray, capacity: int) -> np.ndarray:
    """The places of the points y (n, 3) in blocks of BLOCK: (blocks·BLOCK,) point indices, n
    for an empty place. Points go along the Morton curve; a block never holds points of two
    cells of its grid at the finest level whose blocks fit in ``capacity`` (compact blocks)."""
    n = len(y)
    if n == 0:
        return np.zeros(0)
    code = morton_codes(y)
    order = np.argsort(code, kind="stable")
    code = code[order]
    best = None
    for level in range(MORTON_BITS + 1):
        cell = code >> np.uint64(3 * (MORTON_BITS - level))
        starts = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
        occupancy = np.diff(np.r_[starts, n])
        if int(np.sum(-(-occupancy // BLOCK))) > capacity:
            break
        best = starts, occupancy
    starts, occupancy = best
    first_place = BLOCK * np.concatenate([[0], np.cumsum(-(-occupancy // BLOCK))[:-1]])
    places = np.full(capacity * BLOCK, n, dtype=float)
    within = np.arange(n) - np.repeat(starts, occupancy)
    places[np.repeat(first_place, occupancy) + within] = order
    used = -(-int(first_place[-1] + occupancy[-1]) // BLOCK) * BLOCK
    return places[:max(used, BLOCK)]


def _block_pairs(lo: np.ndarray, hi: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (a, b), a < b, of boxes whose gap is at most ``reach`` (cKDTree on the centres)."""
    n_blocks = len(lo)
    centre, radius = (lo + hi) / 2, np.linalg.norm(hi - lo, axis=1) / 2
    if n_blocks <= 64:
        a, b = np.triu_indices(n_blocks, 1)
    else:
        from scipy.spatial import cKDTree

        candidates = cKDTree(centre).query_pairs(reach + 2 * radius.max(), output_type="ndarray")
        a, b = (candidates[:, 0], candidates[:, 1]) if len(candidates) else (np.zeros(0, int),) * 2
    gap = np.maximum(0.0, np.maximum(lo[b] - hi[a], lo[a] - hi[b]))
    near = np.einsum("ij,ij->i", gap, gap) <= reach * reach
    return a[near], b[near]


def _balanced_owners(a: np.ndarray, b: np.ndarray, n_blocks: int) -> np.ndarray:
    """For each pair of blocks (a, b) the one that holds it: greedily the one holding fewer so
    far (every block's slots are one map's length: the fullest block sets it for all)."""
    load = [1] * n_blocks  # (each block holds its own pairs first)
    owner = []
    for i, j in zip(a.tolist(), b.tolist(), strict=True):
        k = i if load[i] <= load[j] else j
        load[k] += 1
        owner.append(k)
    return np.array(owner, dtype=np.int64)


def neighbour_data(y: np.ndarray, reach: float, block_capacity: int, slot_capacity: int | None):
    """(places, slots) of the points y (n, 3): their places in blocks (``blocks``, padded to
    ``block_capacity`` blocks), and for each block the blocks whose bounding boxes come within
    ``reach`` of its own, itself first, each pair of blocks held by one of the two (the one
    holding fewer so far), as a (slot_capacity, block_capacity) array of
    block + 1 (0: an empty slot). ``slot_capacity`` None: as many slots as the fullest block
    needs. (None, None) when the blocks do not fit; (places, None) when the slots do not."""
    n = len(y)
    places = blocks(y, block_capacity)
    n_blocks = len(places) // BLOCK
    full = places.reshape(n_blocks, BLOCK)
    real = full < n
    points = y[np.where(real, full, 0).astype(np.int64)]
    big = np.finfo(float).max
    lo = np.where(real[..., None], points, big).min(axis=1)
    hi = np.where(real[..., None], points, -big).max(axis=1)
    a, b = _block_pairs(lo, hi, reach)
    owner = _balanced_owners(a, b, n_blocks)
    other = np.where(owner == a, b, a)
    owner = np.concatenate([np.arange(n_blocks), owner])
    other = np.concatenate([np.arange(n_blocks), other])
    rank = np.argsort(owner, kind="stable")
    owner, other = owner[rank], other[rank]
    counts = np.bincount(owner, minlength=n_blocks)
    capacity = int(counts.max()) if slot_capacity is None else slot_capacity
    padded = np.full(block_capacity * BLOCK, float(n))
    padded[:len(places)] = places
    if counts.max() > capacity:
        return padded, None
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slots = np.zeros((capacity, block_capacity))
    slots[np.arange(len(owner)) - starts[owner], owner] = other + 1
    return padded, slots
