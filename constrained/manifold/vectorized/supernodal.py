"""The KKT solve's supernodal LDLᵀ in C (issue 28): the sparse factorization of
``manifold.vectorized.ldl`` for a cloth's or a mesh's A, with L's columns grouped into
supernodes, each a dense panel, updated from the supernodes below it with dense loops.

Symbolic (here, once, NumPy): CasADi's fill-reducing order p and L's pattern; the elimination
tree parent(j) = min{i > j : L_ij ≠ 0}, walked in postorder (the same L, reordered: every
chain of the tree's columns becomes a run of consecutive columns); the fundamental supernodes,
the runs j .. j + c − 1 with parent(j) = j + 1 and |L[:, j]| = |L[:, j + 1]| + 1; then relaxed:
a supernode merged with the one just before it where that one ends in a child of its first
column and the merged panel holds few explicit zeros (CHOLMOD's rule: at most 4 columns
always, 16 if ≤ 80 % zeros, 48 if ≤ 10 %, any if ≤ 5 %). A supernode J of columns
f .. f + c − 1 has rows R_J = (f, …, f + c − 1, the rows of L[:, f + c − 1] below it), m of
them, and stores L[R_J, J] as a dense m × c panel (column-major, diagonal D in its place).

Numeric (C, per call), left-looking over the supernodes J in order:

    panel = A[R_J, J]  (in p's order);
    for every K < J with rows in J's columns (R_K[a:b], static index data):
        panel[R_K[r], R_K[s]] −= Σ_t L_K[r, t] D_t L_K[s, t]   (a ≤ s < b, s ≤ r < m_K:
                                   a dense column of the update, four t at a time, then
                                   scattered to the places of R_K[r] in R_J, index data);
    the dense LDLᵀ of the panel: for t in J's columns,  D_t = panel[t, t],
        L[r, t] = panel[r, t] / D_t,  panel[r, s] −= L[r, t] D_t L[s, t]  (t < s ≤ r).

Solve: x = P B;  x_R[r] −= L[r, j] x_j (columns ascending);  x /= D;
x_j −= Σ_r L[r, j] x_R[r] (columns descending);  out = Pᵀ x.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ...codegen.external import IndexTable
from .columns import triplet

#: CHOLMOD's relaxed amalgamation: (columns at most, fraction of explicit zeros at most)
RELAX = ((4, 1.0), (16, 0.8), (48, 0.1), (None, 0.05))


def _postorder(parent: np.ndarray) -> np.ndarray:
    """The columns in a postorder of the elimination tree (children in ascending order)."""
    n = len(parent)
    roots = parent < 0
    # children grouped by parent, as Python lists: the walk below is one list operation per
    # column (slicing NumPy arrays per column took 0.05 s of a 100 x 100 cloth's start)
    order = np.argsort(np.where(roots, n, parent), kind="stable").tolist()
    head = np.concatenate([[0], np.cumsum(np.bincount(parent[~roots], minlength=n))]).tolist()
    post, stack = [], np.flatnonzero(roots)[::-1].tolist()
    while stack:  # j ≥ 0: visit j (its children, then j itself: ~j)
        j = stack.pop()
        if j < 0:
            post.append(~j)
            continue
        stack.append(~j)
        stack += order[head[j]:head[j + 1]][::-1]
    return np.asarray(post, np.int64)


def _merge(first: list, count: np.ndarray, parent: np.ndarray, relax=RELAX) -> np.ndarray:
    """The first columns of the relaxed supernodes, from the fundamental ones' (``first``, with
    n at the end) and L's column counts (below the diagonal)."""
    count, parent = count.tolist(), parent.tolist()  # (Python numbers: one loop step per supernode)
    total = np.concatenate([[0], np.cumsum(count)]).tolist()
    limits = [(float("inf") if top is None else top, most) for top, most in relax]
    groups = []  # [first column, columns, nonzeros of L in them (diagonal included)]
    for s in range(len(first) - 1):
        f, e = first[s], first[s + 1]
        group = [f, e - f, total[e] - total[f] + e - f]
        while groups and parent[group[0] - 1] == group[0]:
            g, c, z = groups[-1]
            columns, below = c + group[1], count[e - 1]
            dense = columns * (columns + 1) // 2 + columns * below
            zeros = 1 - (z + group[2]) / dense
            for top, most in limits:
                if columns <= top and zeros <= most:
                    break
            else:
                break
            groups.pop()
            group = [g, columns, z + group[2]]
        groups.append(group)
    return np.asarray([g[0] for g in groups] + [len(parent)], np.int64)


def symbolic(lt: ca.Sparsity, p, relax=RELAX) -> dict:
    """The supernodal structure of L (``lt``: CasADi's pattern of Lᵀ, strictly upper, in the
    order ``p``): the order q (p, then the tree's postorder), the supernodes' first columns F,
    their rows R_J (pointers Rp), their panels' offsets O into L's values, and the updates
    J ← K (K's rows R_K[a:b] in J's columns) by J (pointers Up), each with the places of
    R_K[a:] in R_J (Rel from Uo)."""
    n = lt.size1()
    ti, tk = triplet(lt)  # L[k, i] != 0, i < k
    count = np.bincount(ti, minlength=n)
    lowest = np.full(n, n, np.int64)
    np.minimum.at(lowest, ti, tk)
    post = _postorder(np.where(lowest < n, lowest, -1))
    where = np.empty(n + 1, np.int64)
    where[post], where[n] = np.arange(n), -1
    ti, tk, count, parent = where[ti], where[tk], count[post], where[lowest[post]]
    j = np.arange(1, n)
    join = (parent[:-1] == j) & (count[:-1] == count[1:] + 1)
    first = _merge(np.concatenate([[0], j[~join], [n]]).tolist() if n else [0], count, parent, relax)
    ns, width = len(first) - 1, np.diff(first)
    group = np.repeat(np.arange(ns), width)
    # R_J: J's columns, then the rows of its last column below it
    last = np.zeros(n, bool)
    last[first[1:] - 1] = True
    keep = last[ti]
    owner = np.concatenate([group, group[ti[keep]]])
    row = np.concatenate([np.arange(n), tk[keep]])
    order = np.lexsort((row, owner))
    owner, ri = owner[order], row[order]
    rp = np.concatenate([[0], np.cumsum(np.bincount(owner, minlength=ns))])
    m = np.diff(rp)
    offset = np.concatenate([[0], np.cumsum(m * width)])
    # updates: each K's rows below its columns, in runs of one supernode J each
    place = np.arange(len(ri)) - rp[owner]  # an entry's place in its R_K
    below = np.flatnonzero(place >= width[owner])
    target = group[ri[below]]
    start = np.ones(len(below), bool)
    start[1:] = (owner[below[1:]] != owner[below[:-1]]) | (target[1:] != target[:-1])
    runs = np.flatnonzero(start)
    uk, uj, ua = owner[below[runs]], target[runs], place[below[runs]]
    ub = np.append(place[below[runs[1:] - 1]] + 1, place[below[-1]] + 1 if len(below) else [])
    ub = ub.astype(np.int64)
    by_target = np.argsort(uj, kind="stable")
    uk, uj, ua, ub = uk[by_target], uj[by_target], ua[by_target], ub[by_target]
    up = np.concatenate([[0], np.cumsum(np.bincount(uj, minlength=ns))])
    # Rel: the places in R_J of R_K[a:], found among all (supernode, row) keys (sorted)
    length = m[uk] - ua
    uo = np.concatenate([[0], np.cumsum(length)])
    entry = np.repeat(rp[uk] + ua - uo[:-1], length) + np.arange(uo[-1])
    key = np.repeat(uj, length) * n + ri[entry]
    rel = np.searchsorted(owner * n + ri, key) - np.repeat(rp[uj], length)
    assert np.array_equal(ri[rp[np.repeat(uj, length)] + rel], ri[entry])  # R_K[a:] ⊆ R_J
    return {"q": np.asarray(p, np.int64)[post], "F": first, "R": ri, "Rp": rp, "O": offset, "Up": up,
            "Uk": uk, "Ua": ua, "Ub": ub, "Uo": uo[:-1], "Rel": rel, "m": m, "group": group}


def entries_in(sparsity: ca.Sparsity, order) -> tuple[np.ndarray, np.ndarray]:
    """The rows and columns of A's nonzeros (CasADi's order of them) as places in ``order``
    (row ``order[q]`` of A is row q of the factorized matrix)."""
    n = sparsity.size1()
    place = np.empty(n, np.int64)
    place[np.asarray(order, np.int64)] = np.arange(n)
    r, c = triplet(sparsity)
    return place[r], place[c]


def permuted_columns(substitution: str, n: int, k: int) -> str:
    """The solve of B's k columns by a factorization in the order P: for each column x = P b,
    ``substitution`` (forward, D, back on x in place), out = Pᵀ x."""
    return f"""  for (col = 0; col < {k}; ++col) {{
    const casadi_real *b = B + col * {n};
    casadi_real *o = out + col * {n};
    for (q = 0; q < {n}; ++q) x[q] = b[P[q]];
{substitution}    for (q = 0; q < {n}; ++q) o[P[q]] = x[q];
  }}
"""


def composed(declarations: str, compute: str, columns, stored: int, ks: tuple, restore: str = "") -> dict:
    """The bodies of a factorization that keeps its factors in w[0:stored]: ``solve{k}`` (A, B
    -> A⁻¹ B: ``compute`` then ``columns(k)``), ``factor`` (A -> the factors, ``stored`` numbers)
    and ``substitute{k}`` (the factors LD, B -> A⁻¹ B: LD into w, ``restore``, ``columns(k)``),
    so that solves with one matrix share one factorization."""
    bodies = {"factor": f"""{declarations}
{compute}
  {{
    casadi_int z_;
    for (z_ = 0; z_ < {stored}; ++z_) out[z_] = w[z_];
  }}
  return 0;"""}
    for k in ks:
        bodies[f"solve{k}"] = f"{declarations}\n{compute}\n{columns(k)}  return 0;"
        bodies[f"substitute{k}"] = f"""{declarations}
  {{
    casadi_int z_;
    for (z_ = 0; z_ < {stored}; ++z_) w[z_] = LD[z_];
  }}
{restore}{columns(k)}  return 0;"""
    return bodies


def supernodal_bodies(sparsity: ca.Sparsity, lt: ca.Sparsity, p, table: IndexTable,
                      ks: tuple, relax=RELAX) -> tuple[dict, int, int, int]:
    """The bodies (``composed``) of the supernodal LDLᵀ (see the module) in the order ``p`` with
    Lᵀ's pattern ``lt`` (CasADi's symbolic factorization), their scratch lengths (reals,
    integers) and the factors' length."""
    n = sparsity.size1()
    s = symbolic(lt, p, relax)
    q, first, rp, ri, offset = s["q"], s["F"], s["Rp"], s["R"], s["O"]
    ns = len(first) - 1
    ii, kk = entries_in(sparsity, q)
    z = np.flatnonzero(ii >= kk)  # A's lower triangle, to its place in the panels
    g = s["group"][kk[z]]
    owner = np.repeat(np.arange(ns), np.diff(rp))
    at = np.searchsorted(owner * n + ri, g * n + ii[z]) - rp[g]
    place = offset[g] + (kk[z] - first[g]) * (rp[g + 1] - rp[g]) + at
    order = np.lexsort((place, g))
    z, place, g = z[order], place[order], g[order]
    ap = np.concatenate([[0], np.cumsum(np.bincount(g, minlength=ns))])
    names = {"F": first, "Rp": rp, "Ri": ri, "O": offset, "Ap": ap, "Az": z, "Apos": place,
             "Up": s["Up"], "Uk": s["Uk"], "Ua": s["Ua"], "Ub": s["Ub"], "Uo": s["Uo"], "Rel": s["Rel"],
             "P": q}
    arrays = "\n".join(f"  const int *{k} = {table.add(v)};" for k, v in names.items())
    m = s["m"]
    n_l = int(offset[-1])
    most = int(m.max()) if ns else 0
    declarations = f"""{arrays}
  casadi_int J, u, e, i, j, t, col, q;
  casadi_real *D = w, *Lx = w + {n}, *x = w + {n + n_l}, *C = w + {2 * n + n_l};"""
    compute = f"""  for (J = 0; J < {ns}; ++J) {{
    const casadi_int f = F[J], nj = F[J + 1] - f, m = Rp[J + 1] - Rp[J];
    const int *R = Ri + Rp[J];
    casadi_real *Pn = Lx + O[J];
    for (e = 0; e < m * nj; ++e) Pn[e] = 0;
    for (e = Ap[J]; e < Ap[J + 1]; ++e) Lx[Apos[e]] = A[Az[e]];
    for (u = Up[J]; u < Up[J + 1]; ++u) {{  /* K's rows R_K[a:b] in J's columns */
      const casadi_int K = Uk[u], a = Ua[u], b = Ub[u], fk = F[K], nk = F[K + 1] - fk,
                       mk = Rp[K + 1] - Rp[K];
      const int *RK = Ri + Rp[K], *Rl = Rel + Uo[u];
      const casadi_real *LK = Lx + O[K], *DK = D + fk;
      for (j = a; j < b; ++j) {{
        casadi_real *Pj = Pn + (RK[j] - f) * m;
        for (i = j; i < mk; ++i) C[i] = 0;
        for (t = 0; t < nk; t += 4) {{  /* four of K's columns at a time: C += L_K[:, t] D_t L_K[j, t] */
          const casadi_real *L0 = LK + t * mk, *L1 = L0 + mk, *L2 = L1 + mk, *L3 = L2 + mk;
          switch (nk - t) {{
            case 1: {{
              const casadi_real s0 = L0[j] * DK[t];
              for (i = j; i < mk; ++i) C[i] += L0[i] * s0;
              break;
            }}
            case 2: {{
              const casadi_real s0 = L0[j] * DK[t], s1 = L1[j] * DK[t + 1];
              for (i = j; i < mk; ++i) C[i] += L0[i] * s0 + L1[i] * s1;
              break;
            }}
            case 3: {{
              const casadi_real s0 = L0[j] * DK[t], s1 = L1[j] * DK[t + 1], s2 = L2[j] * DK[t + 2];
              for (i = j; i < mk; ++i) C[i] += L0[i] * s0 + L1[i] * s1 + L2[i] * s2;
              break;
            }}
            default: {{
              const casadi_real s0 = L0[j] * DK[t], s1 = L1[j] * DK[t + 1], s2 = L2[j] * DK[t + 2],
                                s3 = L3[j] * DK[t + 3];
              for (i = j; i < mk; ++i) C[i] += L0[i] * s0 + L1[i] * s1 + L2[i] * s2 + L3[i] * s3;
            }}
          }}
        }}
        for (i = j; i < mk; ++i) Pj[Rl[i - a]] -= C[i];
      }}
    }}
    for (j = 0; j < nj; ++j) {{  /* the panel's dense LDLᵀ */
      casadi_real *Pj = Pn + j * m;
      const casadi_real d = Pj[j], inv = 1 / d;
      D[f + j] = d;
      for (i = j + 1; i < m; ++i) Pj[i] *= inv;
      for (t = j + 1; t < nj; ++t) {{
        casadi_real *Pt = Pn + t * m;
        const casadi_real s = Pj[t] * d;
        for (i = t; i < m; ++i) Pt[i] -= Pj[i] * s;
      }}
    }}
  }}"""
    substitution = f"""    for (J = 0; J < {ns}; ++J) {{
      const casadi_int f = F[J], nj = F[J + 1] - f, m = Rp[J + 1] - Rp[J];
      const int *R = Ri + Rp[J];
      const casadi_real *Pn = Lx + O[J];
      for (j = 0; j < nj; ++j) {{
        const casadi_real *Pj = Pn + j * m, xj = x[f + j];
        for (i = j + 1; i < m; ++i) x[R[i]] -= Pj[i] * xj;
      }}
    }}
    for (q = 0; q < {n}; ++q) x[q] /= D[q];
    for (J = {ns} - 1; J >= 0; --J) {{
      const casadi_int f = F[J], nj = F[J + 1] - f, m = Rp[J + 1] - Rp[J];
      const int *R = Ri + Rp[J];
      const casadi_real *Pn = Lx + O[J];
      for (j = nj - 1; j >= 0; --j) {{
        const casadi_real *Pj = Pn + j * m;
        casadi_real s = x[f + j];
        for (i = j + 1; i < m; ++i) s -= Pj[i] * x[R[i]];
        x[f + j] = s;
      }}
    }}
"""
    bodies = composed(declarations, compute, lambda k: permuted_columns(substitution, n, k), n + n_l, ks)
    return bodies, 2 * n + n_l + most, 0, n + n_l
