"""The KKT solve's LDLᵀ in C: A Λ = B for A = J M⁻¹ Jᵀ (symmetric positive definite) of a
fixed sparsity, the factorization's structure worked out once here and compiled in, the numbers
factorized at every call (issue 28).

Two factorizations, by the pattern:

* **a path's** (tridiagonal in some order of the rows: A's graph is paths, as a chain's rods
  give), twisted: factorized from both ends at once and joined in the middle row m (two
  independent chains of divisions, where one chain's latency was the whole cost), with g_q =
  A[q, q−1] in the path's order,

      D_q = A_qq − l_q g_q,  l_q = g_q / D_{q−1}      (q < m, from the top)
      D_q = A_qq − l_q g_{q+1},  l_q = g_{q+1} / D_{q+1}   (q > m, from the bottom)
      D_m = A_mm − l_m g_m − G g_{m+1},  G = g_{m+1} / D_{m+1};

  then forward from both ends to m, x_m, and back out to both ends;

* **the sparse up-looking LDLᵀ** of T. A. Davis (ACM TOMS 31, 2005) in CasADi's symbolic order
  (AMD, or the rows' own where that saves no fill): a cloth's or a mesh's A. L's pattern is
  CasADi's symbolic factorization, so each row's pattern and the place of each of its entries
  in L's columns are index data (no walk of the elimination tree per call: 10–40 % faster on
  cloths),

      row k of L:  y = Ã[:k+1, k];  for i in the pattern of row k (ascending):
                   y[rows of L[:, i] so far] −= L[·, i] y_i,  L_ki = y_i / D_i,  D_k −= L_ki y_i.

The table holds what is O(n + nnz(A) + nnz(L)).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ...codegen.external import IndexTable


def path_order(sparsity: ca.Sparsity) -> np.ndarray | None:
    """An order of the rows in which A is tridiagonal, or None: where A's graph is paths (every
    row coupled to at most two others, no loop), each path walked from one end, one after
    another (a chain's rods in any order, several chains)."""
    n = sparsity.size1()
    r, c = (np.asarray(v, np.int64) for v in sparsity.get_triplet())
    off = r != c
    r, c = r[off], c[off]
    if np.all(np.abs(r - c) == 1):
        return np.arange(n)
    degree = np.bincount(r, minlength=n)
    if n == 0 or degree.max() > 2:
        return None
    neighbours = np.full((n, 2), -1, np.int64)
    slot = np.zeros(n, np.int64)
    for i, j in zip(r.tolist(), c.tolist(), strict=True):
        neighbours[i, slot[i]] = j
        slot[i] += 1
    order, seen = [], np.zeros(n, bool)
    for start in np.flatnonzero(degree <= 1).tolist():
        previous, k = -1, start
        while k >= 0 and not seen[k]:
            seen[k] = True
            order.append(k)
            a, b = neighbours[k]
            previous, k = k, (b if a == previous else a)
    return np.asarray(order, np.int64) if len(order) == n else None  # (else a loop)


def _path(sparsity: ca.Sparsity, order: np.ndarray, table: IndexTable, ks: tuple) -> tuple[dict, int, int]:
    n = sparsity.size1()
    position = np.empty(n, np.int64)
    position[order] = np.arange(n)
    r, c = (np.asarray(v, np.int64) for v in sparsity.get_triplet())
    qr, qc = position[r], position[c]
    diagonal = np.zeros(n, np.int64)
    diagonal[qr[qr == qc]] = np.flatnonzero(qr == qc)
    coupling = np.full(n, -1, np.int64)  # A[q, q − 1]'s place (−1: none, a path's start)
    below = np.flatnonzero(qr == qc + 1)
    coupling[qr[below]] = below
    m = n // 2
    identity = bool(np.all(order == np.arange(n)))
    names = {"Dz": diagonal, "Oz": coupling, **({} if identity else {"P": order})}
    arrays = "\n".join(f"  const int *{k} = {table.add(v)};" for k, v in names.items())

    def at(q: str) -> str:
        return q if identity else f"P[{q}]"
    factor = f"""{arrays}
  casadi_int q, s, col;
  casadi_real *g = w, *a = w + {n}, *l = w + {2 * n}, *D = w + {3 * n}, *y = w + {4 * n}, G, lm;
  for (q = 0; q < {n}; ++q) {{
    g[q] = Oz[q] >= 0 ? A[Oz[q]] : 0;
    a[q] = A[Dz[q]];
  }}
  D[0] = a[0];
  D[{n - 1}] = a[{n - 1}];
  {{
    casadi_real top = a[0], bottom = a[{n - 1}];
    for (s = 1; s < {m}; ++s) {{  /* from both ends at once: two independent chains */
      const casadi_int t = {n - 1} - s;
      const casadi_real ls = g[s] / top, lt = g[t + 1] / bottom;
      top = a[s] - ls * g[s];
      l[s] = ls;
      D[s] = top;
      if (t > {m}) {{
        bottom = a[t] - lt * g[t + 1];
        l[t] = lt;
        D[t] = bottom;
      }}
    }}
  }}
  lm = g[{m}] / D[{m - 1}];
  G = {f"g[{m + 1}] / D[{m + 1}]" if m + 1 < n else "0"};
  l[{m}] = lm;
  D[{m}] = a[{m}] - lm * g[{m}]{f" - G * g[{m + 1}]" if m + 1 < n else ""};"""
    bottom_y = f"y[{m + 1}]" if m + 1 < n else "0"
    bodies = {}
    for k in ks:
        bodies[f"solve{k}"] = f"""{factor}
  for (col = 0; col < {k}; ++col) {{
    const casadi_real *b = B + col * {n};
    casadi_real *o = out + col * {n}, top = b[{at("0")}], bottom = b[{at(str(n - 1))}], up, down;
    y[0] = top;
    y[{n - 1}] = bottom;
    for (s = 1; s < {m}; ++s) {{
      const casadi_int t = {n - 1} - s;
      top = b[{at("s")}] - l[s] * top;
      y[s] = top;
      if (t > {m}) {{
        bottom = b[{at("t")}] - l[t] * bottom;
        y[t] = bottom;
      }}
    }}
    up = down = (b[{at(str(m))}] - lm * y[{m - 1}] - G * {bottom_y}) / D[{m}];
    o[{at(str(m))}] = up;
    for (s = {m - 1}; s >= 0; --s) {{  /* back from the middle to both ends */
      const casadi_int t = {2 * m} - s;
      up = y[s] / D[s] - l[s + 1] * up;
      o[{at("s")}] = up;
      if (t < {n}) {{
        down = y[t] / D[t] - (t == {m + 1} ? G : l[t - 1]) * down;
        o[{at("t")}] = down;
      }}
    }}
  }}
  return 0;"""
    return bodies, 5 * n, 0


def _up_looking(sparsity: ca.Sparsity, lt: ca.Sparsity, p, table: IndexTable,
                ks: tuple) -> tuple[dict, int, int]:
    n = sparsity.size1()
    p = np.asarray(p, np.int64)
    pinv = np.empty(n, np.int64)
    pinv[p] = np.arange(n)
    ti, tk = (np.asarray(v, np.int64) for v in lt.get_triplet())  # L[k, i] != 0, i < k
    by_column = np.lexsort((tk, ti))  # L's entries column by column, rows ascending
    rows, columns = tk[by_column], ti[by_column]
    lp = np.concatenate([[0], np.cumsum(np.bincount(ti, minlength=n))])
    by_row = np.lexsort((columns, rows))  # the same entries row by row: each row's pattern,
    rp = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))])  # columns ascending
    r, c = (np.asarray(v, np.int64) for v in sparsity.get_triplet())
    ii, kk = pinv[r], pinv[c]
    z = np.flatnonzero(ii <= kk)
    z = z[np.lexsort((ii[z], kk[z]))]
    ap = np.concatenate([[0], np.cumsum(np.bincount(kk[z], minlength=n))])
    n_l = len(ti)
    names = {"Ap": ap, "Az": z, "Ai": ii[z], "Lp": lp, "Li": rows, "Rp": rp, "Ri": columns[by_row],
             "Rpos": by_row, "P": p}
    arrays = "\n".join(f"  const int *{k} = {table.add(v)};" for k, v in names.items())
    factor = f"""{arrays}
  casadi_int k, s, q, e, t, col;
  casadi_real *y = w, *D = w + {n}, *Lx = w + {2 * n}, *x = w + {2 * n + n_l};
  for (k = 0; k < {n}; ++k) y[k] = 0;
  for (k = 0; k < {n}; ++k) {{
    casadi_real d;
    for (e = Ap[k]; e < Ap[k + 1]; ++e) y[Ai[e]] += A[Az[e]];
    d = y[k];
    y[k] = 0;
    for (t = Rp[k]; t < Rp[k + 1]; ++t) {{  /* row k's pattern, columns ascending */
      const int i = Ri[t], end = Rpos[t];
      const casadi_real yi = y[i], l = yi / D[i];
      y[i] = 0;
      for (s = Lp[i]; s < end; ++s) y[Li[s]] -= Lx[s] * yi;
      d -= l * yi;
      Lx[end] = l;
    }}
    D[k] = d;
  }}"""
    bodies = {}
    for k in ks:
        bodies[f"solve{k}"] = f"""{factor}
  for (col = 0; col < {k}; ++col) {{
    const casadi_real *b = B + col * {n};
    casadi_real *o = out + col * {n};
    for (q = 0; q < {n}; ++q) x[q] = b[P[q]];
    for (q = 0; q < {n}; ++q) {{
      const casadi_real xq = x[q];
      for (s = Lp[q]; s < Lp[q + 1]; ++s) x[Li[s]] -= Lx[s] * xq;
    }}
    for (q = 0; q < {n}; ++q) x[q] /= D[q];
    for (q = {n} - 1; q >= 0; --q) {{
      casadi_real xq = x[q];
      for (s = Lp[q]; s < Lp[q + 1]; ++s) xq -= Lx[s] * x[Li[s]];
      x[q] = xq;
    }}
    for (q = 0; q < {n}; ++q) o[P[q]] = x[q];
  }}
  return 0;"""
    return bodies, 3 * n + n_l, 0


def ldl_bodies(sparsity: ca.Sparsity, table: IndexTable, ks: tuple) -> tuple[dict, int, int]:
    """The bodies of ``solve{k}`` (A's nonzeros, B (n, k) -> A⁻¹ B) for A of ``sparsity``
    (symmetric, positive definite), k in ``ks``, and their scratch lengths (reals, integers):
    the envelope where it holds no more than the sparse factor, else the up-looking LDLᵀ (see
    the module)."""
    lt, p = sparsity.ldl(True)
    natural, identity = sparsity.ldl(False)
    if natural.nnz() <= lt.nnz():
        lt, p = natural, identity
    order = path_order(sparsity) if sparsity.size1() >= 2 else None
    if order is not None:
        return _path(sparsity, order, table, ks)
    return _up_looking(sparsity, lt, p, table, ks)
