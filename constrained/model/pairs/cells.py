"""A neighbour list's rows built by a cell list in C (issue 28): the same rows as
``neighbours.pair_rows`` — every pair (i, j), i < j, at most ``reach`` apart, held by i in rows
of ROW neighbours, the rows padded to a capacity, placeholders n and n + 1 where empty — at
about a quarter of its cost at 10,000 particles (SciPy's tree and NumPy's sort and scatter
become one pass), which a run pays at every refresh of its list.

The points are binned into cubic cells of side at least ``reach`` (larger when the points
spread over more than MAX_CELLS_PER_POINT · n cells: the memory stays O(n)); a point's
partners are then in its own cell and the 26 around it. Walking the points in order writes
each one's rows as it goes: the rows come out ordered by i with no sort.

Compiled once per process and list shape through ``Function.jit`` (``fused.jit``); where that
cannot be had (no C compiler, compiled code off) ``rows_function`` gives None and the NumPy
route serves.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .fused import jit
from .neighbours import ROW

#: A point's pairs beyond the cutoff kept aside to be listed after its others, at most.
FAR = 1024
#: Cells of the grid at most per point (and at least 64 in all).
MAX_CELLS_PER_POINT = 8


def _exclusions(n: int, excluded: np.ndarray | None) -> tuple[str, str]:
    """C declarations of the excluded pairs (each point's partners j > i, in compressed rows:
    ``ex_start`` (n + 1), ``ex_j``) and the test that skips them; two empty strings for none."""
    if excluded is None or not len(excluded):
        return "", ""
    lo, hi = np.minimum(excluded[:, 0], excluded[:, 1]), np.maximum(excluded[:, 0], excluded[:, 1])
    order = np.lexsort((hi, lo))
    lo, hi = lo[order], hi[order]
    start = np.concatenate([[0], np.cumsum(np.bincount(lo, minlength=n))])
    declare = (f"static const casadi_int ex_start[{n + 1}] = {{{', '.join(map(str, start.tolist()))}}};\n"
               f"static const casadi_int ex_j[{len(hi)}] = {{{', '.join(map(str, hi.tolist()))}}};\n"
               "casadi_int e;\n")
    skip = ("for (e = ex_start[i]; e < ex_start[i + 1] && ex_j[e] != j; ++e) {}\n"
            "        if (e < ex_start[i + 1]) continue;  /* an excluded pair: never listed */")
    return declare, skip


def _body(n: int, capacity: int, reach: float, inner: float, max_cells: int,
          excluded: np.ndarray | None = None) -> str:
    # scratch: each point's cell (n), the points sorted by cell (n), their coordinates in that
    # order (3n: the inner loop reads memory in sequence), each cell's first place (cells + 1)
    declare, skip = _exclusions(n, excluded)
    return f"""{declare}
const casadi_int n = {n}, rows = {capacity}, row = {ROW}, max_cells = {max_cells};
const casadi_real reach = {float(reach)!r}, reach2 = reach * reach, inner2 = {float(inner) ** 2!r};
casadi_int far[{FAR}], n_far;  /* a point's pairs beyond ``inner``, listed after the others */
/* the next pair of point i: a new row every ROW pairs; none left: no list */
#define PUT(jv) do {{ if (count % row == 0) {{ if (used == rows) return 0; I[used++] = i; }} \
  J[(used - 1) * row + count % row] = (jv); ++count; }} while (0)
casadi_real *I = out + 1, *J = out + 1 + rows;
casadi_real *cell_of = scratch, *order = scratch + n, *ys = scratch + 2 * n, *start = scratch + 5 * n;
casadi_real lo[3], hi[3], cell;
casadi_int k, i, d, dims[3], cells, used = 0;
if (!out) return 0;
out[0] = 0;
for (k = 0; k < rows; ++k) I[k] = n;
for (k = 0; k < row * rows; ++k) J[k] = n + 1;
if (!y || !scratch || n == 0) return 0;
for (d = 0; d < 3; ++d) {{ lo[d] = y[d]; hi[d] = y[d]; }}
for (i = 0; i < n; ++i) for (d = 0; d < 3; ++d) {{
  const casadi_real v = y[3 * i + d];
  if (!(v == v) || v - v != 0) return 0;  /* not finite: no list */
  if (v < lo[d]) lo[d] = v;
  if (v > hi[d]) hi[d] = v;
}}
cell = reach;
for (;;) {{
  casadi_real total = 1;
  for (d = 0; d < 3; ++d) {{ dims[d] = (casadi_int) ((hi[d] - lo[d]) / cell) + 1; total *= dims[d]; }}
  if (total <= max_cells) break;
  cell *= 1.26;
}}
cells = dims[0] * dims[1] * dims[2];
for (k = 0; k <= cells; ++k) start[k] = 0;
for (i = 0; i < n; ++i) {{
  casadi_int c[3];
  for (d = 0; d < 3; ++d) {{
    c[d] = (casadi_int) ((y[3 * i + d] - lo[d]) / cell);
    if (c[d] >= dims[d]) c[d] = dims[d] - 1;
  }}
  k = (c[2] * dims[1] + c[1]) * dims[0] + c[0];
  cell_of[i] = k;
  start[k + 1] += 1;
}}
for (k = 0; k < cells; ++k) start[k + 1] += start[k];
for (i = 0; i < n; ++i) {{  /* a counting sort: each cell's points in increasing order */
  const casadi_int place = (casadi_int) start[(casadi_int) cell_of[i]];
  start[(casadi_int) cell_of[i]] += 1;
  order[place] = i;
  for (d = 0; d < 3; ++d) ys[3 * place + d] = y[3 * i + d];
}}
for (k = cells; k > 0; --k) start[k] = start[k - 1];  /* back to each cell's first place */
start[0] = 0;
for (i = 0; i < n; ++i) {{
  const casadi_real yi0 = y[3 * i], yi1 = y[3 * i + 1], yi2 = y[3 * i + 2];
  const casadi_int home = (casadi_int) cell_of[i];
  const casadi_int c0 = home % dims[0], c1 = (home / dims[0]) % dims[1], c2 = home / (dims[0] * dims[1]);
  casadi_int a1, a2, count = 0;
  n_far = 0;
  for (a2 = c2 - 1; a2 <= c2 + 1; ++a2) {{
    if (a2 < 0 || a2 >= dims[2]) continue;
    for (a1 = c1 - 1; a1 <= c1 + 1; ++a1) {{
      casadi_int first, last, p;
      if (a1 < 0 || a1 >= dims[1]) continue;
      /* the three cells along x are consecutive: one run of places */
      first = (a2 * dims[1] + a1) * dims[0] + (c0 > 0 ? c0 - 1 : 0);
      last = (a2 * dims[1] + a1) * dims[0] + (c0 + 1 < dims[0] ? c0 + 1 : dims[0] - 1);
      for (p = (casadi_int) start[first]; p < (casadi_int) start[last + 1]; ++p) {{
        const casadi_real e0 = yi0 - ys[3 * p], e1 = yi1 - ys[3 * p + 1], e2 = yi2 - ys[3 * p + 2];
        casadi_int j;
        if (e0 * e0 + e1 * e1 + e2 * e2 > reach2) continue;
        j = (casadi_int) order[p];
        if (j <= i) continue;
        {skip}
        if (e0 * e0 + e1 * e1 + e2 * e2 >= inner2 && n_far < {FAR}) {{
          far[n_far++] = j;
          continue;
        }}
        PUT(j);
      }}
    }}
  }}
  for (k = 0; k < n_far; ++k) {{
    PUT(far[k]);
  }}
}}
#undef PUT
out[0] = 1;
return 0;
"""


def rows_function(n: int, capacity: int, reach: float, inner: float,
                  excluded: np.ndarray | None = None) -> ca.Function | None:
    """y (3n) -> ([valid, I (capacity), J (ROW·capacity)], scratch): the rows of the pairs of
    the points y within ``reach`` less the ``excluded`` ones ((E, 2): never listed) (valid 0
    and the placeholders alone when they need more than ``capacity`` rows or a coordinate is
    not finite); each point's pairs closer than ``inner`` (the cutoff) first, which makes the
    fused loop's test of the cutoff predictable (~1.4x faster at 10,000 particles); None
    where C cannot be compiled."""
    max_cells = max(64, MAX_CELLS_PER_POINT * n)
    body = _body(n, capacity, reach, inner, max_cells, excluded)
    return jit(f"pair_cells_{n}", body, ["y"], ["out", "scratch"],
               [ca.Sparsity.dense(3 * n, 1)],
               [ca.Sparsity.dense(1 + (1 + ROW) * capacity, 1), ca.Sparsity.dense(5 * n + max_cells + 1, 1)])

