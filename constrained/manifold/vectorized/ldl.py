"""The KKT solve's LDLᵀ in C: A Λ = B for A = J M⁻¹ Jᵀ (symmetric positive definite) of a
fixed sparsity, the factorization's structure worked out once here and compiled in, the numbers
factorized at every call (issue 28).

Three factorizations, by the pattern (``factorization``):

* **a path's** (tridiagonal in some order of the rows: A's graph is paths, as a chain's rods
  give), twisted: factorized from both ends at once and joined in the middle row m (two
  independent chains of divisions, where one chain's latency was the whole cost), with g_q =
  A[q, q−1] in the path's order,

      D_q = A_qq − l_q g_q,  l_q = g_q / D_{q−1}      (q < m, from the top)
      D_q = A_qq − l_q g_{q+1},  l_q = g_{q+1} / D_{q+1}   (q > m, from the bottom)
      D_m = A_mm − l_m g_m − G g_{m+1},  G = g_{m+1} / D_{m+1};

  then forward from both ends to m, x_m, and back out to both ends;

* **short columns** where L, in CasADi's symbolic order (AMD), holds at most SHORT_COLUMNS
  entries per row (a chain with branches: a junction of three rods couples their three rows, so
  A's graph is not a path, but L has one or two entries a column): right-looking, every
  update's place in L index data, no panels to set up;

* **the supernodal LDLᵀ** (``manifold.vectorized.supernodal``) in CasADi's symbolic order (AMD,
  or the rows' own where that saves no fill): a cloth's or a mesh's A. L's pattern is CasADi's
  symbolic factorization; its columns of one structure are grouped into dense panels, each
  updated from the panels below it with dense loops, four columns at a time,

      panel J = A[R_J, J] − Σ_K L[R_K, K] D_K L[J, K]ᵀ,  then the panel's dense LDLᵀ

  (the 100 x 100 cloth's factor + solve 1.4 x faster than the up-looking LDLᵀ of T. A. Davis
  it replaced, which took L's rows one by one).

The table holds what is O(n + nnz(A) + nnz(L)), and the supernodal updates' places of rows
(Σ over the updates J ← K of K's rows from J's on: 0.27 nnz(L) on the 100 x 100 cloth).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ...codegen.external import IndexTable
from .columns import triplet
from .supernodal import composed, entries_in, permuted_columns, supernodal_bodies


def path_order(sparsity: ca.Sparsity) -> np.ndarray | None:
    """An order of the rows in which A is tridiagonal, or None: where A's graph is paths (every
    row coupled to at most two others, no loop), each path walked from one end, one after
    another (a chain's rods in any order, several chains)."""
    n = sparsity.size1()
    r, c = triplet(sparsity)
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


def _diagonal(rows: np.ndarray, columns: np.ndarray, n: int) -> np.ndarray:
    """Where each diagonal entry of A is among its nonzeros (rows, columns: ``entries_in``)."""
    diagonal = np.zeros(n, np.int64)
    diagonal[rows[rows == columns]] = np.flatnonzero(rows == columns)
    return diagonal


#: The short-column LDLᵀ serves factors of at most this many entries of L per row of A on
#: average (a chain with branches: one or two); beyond, the supernodal panels pay.
SHORT_COLUMNS = 3


def _short_columns(sparsity: ca.Sparsity, lt: ca.Sparsity, p, table: IndexTable,
                   ks: tuple) -> tuple[dict, int, int, int]:
    """Right-looking LDLᵀ with every update's place as index data, for a factor of short columns
    (a branching chain: one entry below most diagonals, two at a junction of three rods):

        column j:  g_i = Ã_ij,  L_ij = g_i / D_j,  D_i −= L_ij g_i,  Ã_ik −= L_ij g_k  (i > k > j)

    over j's entries i, k, in the order ``p`` with Lᵀ's pattern ``lt`` (CasADi's symbolic
    factorization)."""
    n = sparsity.size1()
    p = np.asarray(p, np.int64)
    ti, tk = triplet(lt)  # L[k, i] != 0, i < k
    by_column = np.lexsort((tk, ti))
    rows, columns = tk[by_column], ti[by_column]
    lp = np.concatenate([[0], np.cumsum(np.bincount(columns, minlength=n))])
    keys = columns * n + rows  # L's entries in their order (by column, then row): ascending

    def place(i, k):  # L[i, k]'s place among them
        return np.searchsorted(keys, np.asarray(k, np.int64) * n + np.asarray(i, np.int64))
    ii, kk = entries_in(sparsity, p)
    lower = np.flatnonzero(ii > kk)
    a_to_l = place(ii[lower], kk[lower])
    diagonal = _diagonal(ii, kk, n)
    first, second, up = [], [], [0]
    for j in range(n):  # (short columns: a few pairs each)
        for s in range(lp[j], lp[j + 1]):
            first += [s] * (s - lp[j])
            second += range(s - lp[j])
        up.append(len(first))
    first, second = np.asarray(first, np.int64), np.asarray(second, np.int64)
    owner = np.repeat(np.arange(n), np.diff(up))
    targets = place(rows[first], rows[lp[owner] + second])
    names = {"P": p, "Dz": diagonal, "Az": lower, "At": a_to_l, "Lp": lp, "Li": rows, "Up": up,
             "T": targets, "S": first, "G": second}
    arrays = "\n".join(f"  const int *{k} = {table.add(v)};" for k, v in names.items())
    n_l, widest = len(rows), int(np.diff(lp).max(initial=0))
    declarations = f"""{arrays}
  casadi_int j, s, u, q, col;
  casadi_real *D = w, *Lx = w + {n}, *x = w + {n + n_l}, *g = w + {2 * n + n_l};"""
    compute = f"""  for (j = 0; j < {n}; ++j) D[j] = A[Dz[j]];
  for (s = 0; s < {n_l}; ++s) Lx[s] = 0;
  for (s = 0; s < {len(lower)}; ++s) Lx[At[s]] = A[Az[s]];
  for (j = 0; j < {n}; ++j) {{
    const casadi_real d = D[j];
    for (s = Lp[j]; s < Lp[j + 1]; ++s) {{
      const casadi_real gs = Lx[s], l = gs / d;
      g[s - Lp[j]] = gs;
      Lx[s] = l;
      D[Li[s]] -= l * gs;
    }}
    for (u = Up[j]; u < Up[j + 1]; ++u) Lx[T[u]] -= Lx[S[u]] * g[G[u]];
  }}"""
    substitution = f"""    for (q = 0; q < {n}; ++q) {{
      const casadi_real xq = x[q];
      for (s = Lp[q]; s < Lp[q + 1]; ++s) x[Li[s]] -= Lx[s] * xq;
    }}
    for (q = 0; q < {n}; ++q) x[q] /= D[q];
    for (q = {n} - 1; q >= 0; --q) {{
      casadi_real xq = x[q];
      for (s = Lp[q]; s < Lp[q + 1]; ++s) xq -= Lx[s] * x[Li[s]];
      x[q] = xq;
    }}
"""
    bodies = composed(declarations, compute, lambda k: permuted_columns(substitution, n, k), n + n_l, ks)
    return bodies, 2 * n + n_l + max(widest, 1), 0, n + n_l


def _path(sparsity: ca.Sparsity, order: np.ndarray, table: IndexTable,
          ks: tuple) -> tuple[dict, int, int, int]:
    n = sparsity.size1()
    qr, qc = entries_in(sparsity, order)
    diagonal = _diagonal(qr, qc, n)
    coupling = np.full(n, -1, np.int64)  # A[q, q − 1]'s place (−1: none, a path's start)
    below = np.flatnonzero(qr == qc + 1)
    coupling[qr[below]] = below
    m = n // 2
    identity = bool(np.all(order == np.arange(n)))
    names = {"Dz": diagonal, "Oz": coupling, **({} if identity else {"P": order})}
    arrays = "\n".join(f"  const int *{k} = {table.add(v)};" for k, v in names.items())

    def at(q: str) -> str:
        return q if identity else f"P[{q}]"
    declarations = f"""{arrays}
  casadi_int q, s, col;
  casadi_real *g = w, *a = w + {n}, *l = w + {2 * n}, *D = w + {3 * n}, *y = w + {4 * n}, G, lm;"""
    compute = f"""  for (q = 0; q < {n}; ++q) {{
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

    def columns(k: int) -> str:
        return f"""  for (col = 0; col < {k}; ++col) {{
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
"""
    restore = f"""  lm = l[{m}];
  G = {f"g[{m + 1}] / D[{m + 1}]" if m + 1 < n else "0"};
"""
    bodies = composed(declarations, compute, columns, 4 * n, ks, restore)
    return bodies, 5 * n, 0, 4 * n


#: The rows' own order is tried against AMD's only when its envelope holds at most this many
#: times AMD's fill: its fill lies within its envelope, and a 2-D mesh's fills it (the
#: 100 x 100 cloth: 3.9e6 entries against AMD's 4.1e5, whose symbolic factorization alone
#: took 0.25 s of every run's start).
ENVELOPE_CHECKED = 2


def _envelope(sparsity: ca.Sparsity) -> int:
    """The entries of L's envelope in the rows' own order, Σ_i (i − the first column of row i),
    an upper bound on the fill of the factorization in that order."""
    r, c = triplet(sparsity)
    n = sparsity.size1()
    first = np.arange(n)
    np.minimum.at(first, r, c)
    return int(np.sum(np.arange(n) - first))


def factorization(sparsity: ca.Sparsity) -> tuple:
    """Which LDLᵀ serves A of ``sparsity`` (see the module), with what it needs: ("path", its
    order), else ("short columns", Lᵀ's pattern, order) where L holds at most SHORT_COLUMNS
    entries per row of A in CasADi's symbolic order, else ("supernodal", Lᵀ's pattern, order)."""
    order = path_order(sparsity) if sparsity.size1() >= 2 else None
    if order is not None:
        return "path", order
    lt, p = sparsity.ldl(True)
    if _envelope(sparsity) <= ENVELOPE_CHECKED * lt.nnz():  # (the rows' own order may fill less)
        natural, identity = sparsity.ldl(False)
        if natural.nnz() <= lt.nnz():
            lt, p = natural, identity
    return ("short columns" if lt.nnz() <= SHORT_COLUMNS * sparsity.size1() else "supernodal"), lt, p


def ldl_bodies(sparsity: ca.Sparsity, table: IndexTable, ks: tuple) -> tuple[dict, int, int, int]:
    """The bodies of ``solve{k}`` (A's nonzeros, B (n, k) -> A⁻¹ B), ``factor`` (A's nonzeros ->
    its factors F) and ``substitute{k}`` (F, B -> A⁻¹ B) for A of ``sparsity`` (symmetric,
    positive definite), k in ``ks`` (``supernodal.composed``), their scratch lengths (reals,
    integers) and F's length, by the ``factorization`` the pattern takes."""
    kind, *needs = factorization(sparsity)
    build = {"path": _path, "short columns": _short_columns, "supernodal": supernodal_bodies}[kind]
    return build(sparsity, *needs, table, ks)
