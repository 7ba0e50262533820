"""J's products and the KKT solve's assembly as loops in C over J's nonzeros (issue 28).

The vectorized build writes J y, Jᵀ λ and A = J M⁻¹ Jᵀ as gathers, products and sums of
whole columns (``build.Jacobian``): on the 1 cm rope about forty passes over 10,000 numbers
for each acceleration, each a node of CasADi's virtual machine with its temporary. Here each
is one loop over the entries (stream s, position i) of J, reading the build's own index data
(rows r_s, coordinates c_s, A's products) from a static table compiled into the library:

    J y:      out[r_s[i]] += J_s[i] y[c_s[i]]
    Jᵀ λ:     out[c_s[i]] += J_s[i] λ[r_s[i]]
    A:        A[t] += J_s[i] J_s'[i'] m⁻¹[c]        over the products of ``_Gram``

and, where rows with one coordinate are eliminated (``_Elimination``), the reduced right-hand
side before CasADi's sparse LDLᵀ and Λ after it (the formulas of ``Jacobian.solve``). The
factorization stays CasADi's. The numbers are those of the columns up to the order of
floating-point sums. The library is compiled once per model and cached, keyed by the index
data; where compiled code cannot be had the columns serve.
"""

from __future__ import annotations

import hashlib

import casadi as ca
import numpy as np

from ...codegen.external import IndexTable, c_functions


def _dense(n: int, k: int = 1) -> ca.Sparsity:
    return ca.Sparsity.dense(n, k)


class CompiledProducts:
    """The build's products as C loops (see the module): ``times``, ``transpose_times`` and
    ``solve``; built by ``compiled_products``."""

    def __init__(self, build, functions: dict):
        self.build, self.f = build, functions

    def times(self, streams, y):
        return self.f["times"](*streams, y)

    def transpose_times(self, streams, lam):
        return self.f["transpose_times"](*streams, lam)

    def solve(self, streams, minv, B):
        """Λ with (J M⁻¹ Jᵀ) Λ = B for B of 1 or 2 columns, rows with one coordinate
        eliminated first where the build has them (``Jacobian.solve``)."""
        e, k = self.build.single, B.shape[1]
        if e is None:
            return self.f[f"solve{k}"](self.f["gram"](*streams, minv), B)
        reduced = self.f[f"before{k}"](*streams, B)
        lam = self.f[f"solve{k}"](self.f["gram"](*streams, minv), reduced) if len(e.others) else ca.MX(0, k)
        return self.f[f"after{k}"](*streams, minv, B, lam)


def _gram_body(gram, table: IndexTable, streams: list[str]) -> str:
    """A's nonzeros from the products of ``gram`` (a ``_Gram``)."""
    n_a = gram.sparsity.nnz()
    lines = [f"  casadi_int i;\n  for (i = 0; i < {n_a}; ++i) A[i] = 0;"]
    for d, (s, k) in enumerate(gram.diagonal):
        K, C, T = table.add(k), table.add(gram.cols[s][k]), table.add(gram.targets[d])
        lines.append(f"""  {{ const int *K = {K}, *C = {C}, *T = {T};
    for (i = 0; i < {len(k)}; ++i) {{
      const casadi_real a = {streams[s]}[K[i]];
      A[T[i]] += a * a * m[C[i]];
    }} }}""")
    first = len(gram.diagonal)
    for q, (s1, p1, s2, p2) in enumerate(gram.pairs):
        ta, tb = gram.targets[first + 2 * q], gram.targets[first + 2 * q + 1]
        P, Q, C = table.add(p1), table.add(p2), table.add(gram.cols[s2][p2])
        TA, TB = table.add(ta), table.add(tb)
        lines.append(f"""  {{ const int *P = {P}, *Q = {Q}, *C = {C}, *TA = {TA}, *TB = {TB};
    for (i = 0; i < {len(p1)}; ++i) {{
      const casadi_real a = {streams[s1]}[P[i]] * {streams[s2]}[Q[i]] * m[C[i]];
      A[TA[i]] += a; A[TB[i]] += a;
    }} }}""")
    return "\n".join(lines) + "\n  return 0;"


def _stream_loop(table: IndexTable, n: int, statement: str, r, c) -> str:
    return (f"  {{ const int *R = {table.add(r)}, *C = {table.add(c)};\n"
            f"    for (i = 0; i < {n}; ++i) {statement} }}")


def _elimination(e, table: IndexTable, streams: list[str], n_rows: int, ks: tuple) -> dict:
    """The bodies of ``before{k}`` (B -> the reduced right-hand side) and ``after{k}`` (Λ_R -> Λ)
    for B of k columns, k in ``ks``."""
    n_s, n_r = len(e.rows), len(e.others)
    S, R, SC = table.add(e.rows), table.add(e.others), table.add(e.cols)
    j_entries = "\n".join(
        f"  {{ const int *P = {table.add(p)}, *Q = {table.add(q)};\n"
        f"    for (i = 0; i < {len(p)}; ++i) j[Q[i]] += {streams[s]}[P[i]]; }}" for s, p, q in e.entries)
    coupling = [(streams[s], table.add(p), table.add(r), table.add(q), len(p)) for s, p, r, q in e.coupling]
    entries_j = f"""  casadi_int i, col;
  casadi_real *j = w, *y = w + {n_s};
  const int *S = {S}, *R = {R}, *SC = {SC};
  for (i = 0; i < {n_s}; ++i) j[i] = 0;
{j_entries}"""
    subtract = "\n".join(f"""    {{ const int *P = {p}, *RR = {r}, *Q = {q};
      for (i = 0; i < {n}; ++i) red[RR[i]] -= {J}[P[i]] * y[Q[i]]; }}""" for J, p, r, q, n in coupling)
    gather = "\n".join(f"""    {{ const int *P = {p}, *RR = {r}, *Q = {q};
      for (i = 0; i < {n}; ++i) y[Q[i]] += {J}[P[i]] * l[RR[i]]; }}""" for J, p, r, q, n in coupling)
    bodies = {}
    for k in ks:
        bodies[f"before{k}"] = f"""{entries_j}
  (void) SC;
  for (col = 0; col < {k}; ++col) {{
    const casadi_real *b = B + col * {n_rows};
    casadi_real *red = out + col * {n_r};
    for (i = 0; i < {n_s}; ++i) y[i] = b[S[i]] / j[i];
    for (i = 0; i < {n_r}; ++i) red[i] = b[R[i]];
{subtract}
  }}
  return 0;"""
        bodies[f"after{k}"] = f"""{entries_j}
  for (col = 0; col < {k}; ++col) {{
    const casadi_real *b = B + col * {n_rows}, *l = lam + col * {n_r};
    casadi_real *o = out + col * {n_rows};
    for (i = 0; i < {n_s}; ++i) y[i] = 0;
{gather}
    for (i = 0; i < {n_s}; ++i) o[S[i]] = (b[S[i]] / (m[SC[i]] * j[i]) - y[i]) / j[i];
    for (i = 0; i < {n_r}; ++i) o[R[i]] = l[i];
  }}
  return 0;"""
    return bodies


def _ldl_bodies(sparsity: ca.Sparsity, table: IndexTable, ks: tuple) -> tuple[dict, int, int]:
    """The bodies of ``solve{k}`` (A's nonzeros, B (n, k) -> A⁻¹ B) for A of ``sparsity``
    (symmetric, positive definite), and their scratch lengths (reals, integers): A[p, p] =
    L D Lᵀ in the order p of CasADi's symbolic factorization (AMD, or the rows' own where that
    saves no fill: a chain's loops then run through memory in order), numerically row by row
    as T. A. Davis' LDL does (ACM TOMS 31, 2005), the pattern of each row found by walking the
    elimination tree from A's entries,

        row k of L:  y = Ã[:k+1, k];  for i in the pattern of row k (in topological order):
                     y[rows of L[:, i] so far] −= L[·, i] y_i,  L_ki = y_i / D_i,  D_k −= L_ki y_i,

    then forward and back substitution. The table holds only what is O(n + nnz(A)): A's
    upper entries in the order p, the tree and the column starts of L."""
    n = sparsity.size1()
    lt, p = sparsity.ldl(True)
    natural, identity = sparsity.ldl(False)
    if natural.nnz() <= lt.nnz():
        lt, p = natural, identity
    p = np.asarray(p, np.int64)
    pinv = np.empty(n, np.int64)
    pinv[p] = np.arange(n)
    ti, tk = (np.asarray(v, np.int64) for v in lt.get_triplet())  # L[k, i] != 0, i < k
    lp = np.concatenate([[0], np.cumsum(np.bincount(ti, minlength=n))])
    parent = np.full(n, -1, np.int64)
    first = np.full(n, np.iinfo(np.int64).max)
    np.minimum.at(first, ti, tk)
    parent[first < n] = first[first < n]
    r, c = (np.asarray(v, np.int64) for v in sparsity.get_triplet())
    ii, kk = pinv[r], pinv[c]
    z = np.flatnonzero(ii <= kk)
    z = z[np.lexsort((ii[z], kk[z]))]
    ap = np.concatenate([[0], np.cumsum(np.bincount(kk[z], minlength=n))])
    n_l = len(ti)
    names = {"Ap": ap, "Az": z, "Ai": ii[z], "Lp": lp, "Parent": parent, "P": p}
    arrays = "\n".join(f"  const int *{k} = {table.add(v)};" for k, v in names.items())
    factor = f"""{arrays}
  casadi_int k, s, q, e, col, i, top, len;
  casadi_real *y = w, *D = w + {n}, *Lx = w + {2 * n}, *x = w + {2 * n + n_l};
  casadi_int *pattern = iw, *flag = iw + {n}, *lnz = iw + {2 * n}, *Li = iw + {3 * n};
  for (k = 0; k < {n}; ++k) {{
    y[k] = 0;
    top = {n};
    flag[k] = k;
    lnz[k] = 0;
    for (e = Ap[k]; e < Ap[k + 1]; ++e) {{
      i = Ai[e];
      y[i] += A[Az[e]];
      for (len = 0; flag[i] != k; i = Parent[i]) {{
        pattern[len++] = i;
        flag[i] = k;
      }}
      while (len > 0) pattern[--top] = pattern[--len];
    }}
    D[k] = y[k];
    y[k] = 0;
    for (; top < {n}; ++top) {{
      const casadi_int end = Lp[pattern[top]] + lnz[pattern[top]];
      const casadi_real yi = y[pattern[top]], l = yi / D[pattern[top]];
      i = pattern[top];
      y[i] = 0;
      for (s = Lp[i]; s < end; ++s) y[Li[s]] -= Lx[s] * yi;
      D[k] -= l * yi;
      Li[end] = k;
      Lx[end] = l;
      ++lnz[i];
    }}
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
    return bodies, 3 * n + n_l, 3 * n + n_l


def compiled_products(build) -> CompiledProducts | None:
    """The ``CompiledProducts`` of ``build`` (a VectorizedBuild), or None where compiled code
    cannot be had."""
    b = build
    names = [f"J{s}" for s in range(len(b.rows))]
    stream_sp = [_dense(len(r)) for r in b.rows]
    table = IndexTable()
    specs = []

    def add(kind, body, extra_in, extra_sp, out_name, out_sp, work=0):
        specs.append((kind, body, [*names, *extra_in], [*stream_sp, *extra_sp], [out_name], [out_sp], work))

    pairs = list(enumerate(zip(b.rows, b.cols, strict=True)))
    for kind, n_out, update in (("times", b.n_rows, "out[R[i]] += J{s}[i] * y[C[i]];"),
                                ("transpose_times", b.n3, "out[C[i]] += J{s}[i] * y[R[i]];")):
        loops = "\n".join(_stream_loop(table, len(r), update.format(s=s), r, c) for s, (r, c) in pairs)
        add(kind, f"  casadi_int i;\n  for (i = 0; i < {n_out}; ++i) out[i] = 0;\n{loops}\n  return 0;",
            ["y"], [_dense(b.n3 + b.n_rows - n_out)], "out", _dense(n_out))
    e = b.single
    gram = b.gram if e is None else e.gram
    add("gram", _gram_body(gram, table, names), ["m"], [_dense(b.n3)], "A", _dense(gram.sparsity.nnz()))
    n_a = gram.sparsity.size1()
    if n_a:
        bodies, work, iwork = _ldl_bodies(gram.sparsity, table, (1, 2))
        for k in (1, 2):
            specs.append((f"solve{k}", bodies[f"solve{k}"], ["A", "B"], [_dense(gram.sparsity.nnz()),
                          _dense(n_a, k)], ["out"], [_dense(n_a, k)], work, iwork))
    if e is not None:
        work = 2 * max(len(e.rows), 1)
        bodies = _elimination(e, table, names, b.n_rows, (1, 2))
        for k in (1, 2):
            n_r = len(e.others)
            add(f"before{k}", bodies[f"before{k}"], ["B"], [_dense(b.n_rows, k)], "out", _dense(n_r, k), work)
            add(f"after{k}", bodies[f"after{k}"], ["m", "B", "lam"],
                [_dense(b.n3), _dense(b.n_rows, k), _dense(n_r, k)], "out", _dense(b.n_rows, k), work)
    data = table.data()
    tag = hashlib.sha256(data).hexdigest()[:12]
    named = [(f"kkt_{tag}_{kind}", *rest) for kind, *rest in specs]
    loaded = c_functions(named, table.c, key=data)
    if loaded is None:
        return None
    return CompiledProducts(b, {kind: f for (kind, *_), f in zip(specs, loaded, strict=True)})
