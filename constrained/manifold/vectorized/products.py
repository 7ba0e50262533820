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
side before the LDLᵀ and Λ after it (the formulas of ``Jacobian.solve``); the LDLᵀ itself is
``ldl``'s (the columns' is CasADi's). The numbers are those of the columns up to the order of
floating-point sums. The library is compiled once per model and cached, keyed by the index
data; where compiled code cannot be had the columns serve.
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

import casadi as ca
import numpy as np

from ...codegen import compiled, external
from ...codegen.external import LOOP_FLAGS, IndexTable, c_functions, element
from .ldl import ldl_bodies


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

    def solve(self, streams, minv, B, factors=None):
        """Λ with (J M⁻¹ Jᵀ) Λ = B for B of 1 or 2 columns, rows with one coordinate
        eliminated first where the build has them (``Jacobian.solve``); ``factors``: those of
        ``factor`` for these streams and minv (then only the substitutions are done)."""
        e, k = self.build.single, B.shape[1]

        def inner(rhs):
            if factors is not None:
                return self.f[f"substitute{k}"](factors, rhs)
            return self.f[f"solve{k}"](self.f["gram"](*streams, minv), rhs)
        if e is None:
            return inner(B)
        reduced = self.f[f"before{k}"](*streams, B)
        lam = inner(reduced) if len(e.others) else ca.MX(0, k)
        return self.f[f"after{k}"](*streams, minv, B, lam)

    def factor(self, streams, minv):
        """The LDLᵀ factors of the (reduced) J M⁻¹ Jᵀ, for ``solve``'s ``factors``; None where
        every row is eliminated (nothing to factorize)."""
        e = self.build.single
        if e is not None and not len(e.others):
            return None
        return self.f["factor"](self.f["gram"](*streams, minv))


def _gram_body(gram, table: IndexTable, streams: list[str]) -> str:
    """A's nonzeros from the products of ``gram`` (a ``_Gram``)."""
    n_a = gram.sparsity.nnz()
    lines = [f"  casadi_int i;\n  for (i = 0; i < {n_a}; ++i) A[i] = 0;"]
    for d, (s, k) in enumerate(gram.diagonal):
        K, C, T = (element(table, v) for v in (k, gram.cols[s][k], gram.targets[d]))
        lines.append(f"""  for (i = 0; i < {len(k)}; ++i) {{
    const casadi_real a = {streams[s]}[{K}];
    A[{T}] += a * a * m[{C}];
  }}""")
    first = len(gram.diagonal)
    for q, (s1, p1, s2, p2) in enumerate(gram.pairs):
        ta, tb = gram.targets[first + 2 * q], gram.targets[first + 2 * q + 1]
        P, Q, C, TA, TB = (element(table, v) for v in (p1, p2, gram.cols[s2][p2], ta, tb))
        lines.append(f"""  for (i = 0; i < {len(p1)}; ++i) {{
    const casadi_real a = {streams[s1]}[{P}] * {streams[s2]}[{Q}] * m[{C}];
    A[{TA}] += a;
    A[{TB}] += a;
  }}""")
    return "\n".join(lines) + "\n  return 0;"


def _elimination(e, table: IndexTable, streams: list[str], n_rows: int, ks: tuple) -> dict:
    """The bodies of ``before{k}`` (B -> the reduced right-hand side) and ``after{k}`` (Λ_R -> Λ)
    for B of k columns, k in ``ks``."""
    n_s, n_r = len(e.rows), len(e.others)
    S, R, SC = (element(table, v) for v in (e.rows, e.others, e.cols))
    j_entries = "\n".join(
        f"  for (i = 0; i < {len(p)}; ++i) j[{element(table, q)}] += {streams[s]}[{element(table, p)}];"
        for s, p, q in e.entries)
    coupling = [(streams[s], *(element(table, v) for v in (p, r, q)), len(p)) for s, p, r, q in e.coupling]
    entries_j = f"""  casadi_int i, col;
  casadi_real *j = w, *y = w + {n_s};
  for (i = 0; i < {n_s}; ++i) j[i] = 0;
{j_entries}"""
    subtract = "\n".join(f"    for (i = 0; i < {n}; ++i) red[{r}] -= {J}[{p}] * y[{q}];"
                         for J, p, r, q, n in coupling)
    gather = "\n".join(f"    for (i = 0; i < {n}; ++i) y[{q}] += {J}[{p}] * l[{r}];"
                       for J, p, r, q, n in coupling)
    bodies = {}
    for k in ks:
        bodies[f"before{k}"] = f"""{entries_j}
  for (col = 0; col < {k}; ++col) {{
    const casadi_real *b = B + col * {n_rows};
    casadi_real *red = out + col * {n_r};
    for (i = 0; i < {n_s}; ++i) y[i] = b[{S}] / j[i];
    for (i = 0; i < {n_r}; ++i) red[i] = b[{R}];
{subtract}
  }}
  return 0;"""
        bodies[f"after{k}"] = f"""{entries_j}
  for (col = 0; col < {k}; ++col) {{
    const casadi_real *b = B + col * {n_rows}, *l = lam + col * {n_r};
    casadi_real *o = out + col * {n_rows};
    for (i = 0; i < {n_s}; ++i) y[i] = 0;
{gather}
    for (i = 0; i < {n_s}; ++i) o[{S}] = (b[{S}] / (m[{SC}] * j[i]) - y[i]) / j[i];
    for (i = 0; i < {n_r}; ++i) o[{R}] = l[i];
  }}
  return 0;"""
    return bodies


#: The modules whose code writes the library's C (with the build's index data, they decide it).
WRITERS = ("products.py", "ldl.py", "supernodal.py", "build.py", "columns.py")


@functools.cache
def _writers() -> bytes:
    digest = hashlib.sha256()
    for path in [*(Path(__file__).parent / name for name in WRITERS), Path(external.__file__)]:
        digest.update(path.read_bytes())
    return digest.digest()


def _kinds(b) -> list[str]:
    """The library's functions for ``b``, in the order ``compiled_products`` writes them."""
    e = b.single
    kinds = ["times", "transpose_times", "gram"]
    if (len(e.others) if e is not None else b.n_rows):
        kinds += ["factor", "solve1", "substitute1", "solve2", "substitute2"]
    return kinds + (["before1", "after1", "before2", "after2"] if e is not None else [])


def _decided_by(b) -> bytes:
    """Bytes that decide the library's whole C source: the code that writes it and the build's
    index data (the rows and coordinates of every stream; A's pattern, the eliminated rows and
    the LDLᵀ's structure follow from them)."""
    sizes = np.array([b.n_rows, b.n3, *(len(r) for r in b.rows)], np.int64)
    index = np.concatenate([np.asarray(v, np.int64) for v in (*b.rows, *b.cols)] or [np.zeros(0, np.int64)])
    return hashlib.sha256(b"kkt products\0" + _writers() + sizes.tobytes() + index.tobytes()).digest()


def compiled_products(build) -> CompiledProducts | None:
    """The ``CompiledProducts`` of ``build`` (a VectorizedBuild), or None where compiled code
    cannot be had. A library in the cache is found by ``_decided_by`` alone: its source (A's
    index data, the LDLᵀ's symbolic factorization: 0.15 s on a 100 x 100 cloth) is written only
    to compile it."""
    b = build
    decided_by = _decided_by(b)
    tag = hashlib.sha256(decided_by).hexdigest()[:12]
    kinds = _kinds(b)
    loaded = compiled.cached_source([f"kkt_{tag}_{kind}" for kind in kinds], decided_by, flags=LOOP_FLAGS)
    if loaded is not None:
        return CompiledProducts(b, dict(zip(kinds, loaded, strict=True)))
    names = [f"J{s}" for s in range(len(b.rows))]
    stream_sp = [_dense(len(r)) for r in b.rows]
    table = IndexTable()
    specs = []

    def add(kind, body, extra_in, extra_sp, out_name, out_sp, work=0):
        specs.append((kind, body, [*names, *extra_in], [*stream_sp, *extra_sp], [out_name], [out_sp], work))

    pairs = list(enumerate(zip(b.rows, b.cols, strict=True)))
    for kind, n_out, update in (("times", b.n_rows, "out[{r}] += J{s}[i] * y[{c}];"),
                                ("transpose_times", b.n3, "out[{c}] += J{s}[i] * y[{r}];")):
        loops = "\n".join(f"  for (i = 0; i < {len(r)}; ++i) "
                          + update.format(s=s, r=element(table, r), c=element(table, c))
                          for s, (r, c) in pairs)
        add(kind, f"  casadi_int i;\n  for (i = 0; i < {n_out}; ++i) out[i] = 0;\n{loops}\n  return 0;",
            ["y"], [_dense(b.n3 + b.n_rows - n_out)], "out", _dense(n_out))
    e = b.single
    gram = b.gram if e is None else e.gram
    add("gram", _gram_body(gram, table, names), ["m"], [_dense(b.n3)], "A", _dense(gram.sparsity.nnz()))
    n_a = gram.sparsity.size1()
    if n_a:
        bodies, work, iwork, stored = ldl_bodies(gram.sparsity, table, (1, 2))
        A_sp, F_sp = _dense(gram.sparsity.nnz()), _dense(stored)
        specs.append(("factor", bodies["factor"], ["A"], [A_sp], ["out"], [F_sp], work, iwork))
        for k in (1, 2):
            specs.append((f"solve{k}", bodies[f"solve{k}"], ["A", "B"], [A_sp, _dense(n_a, k)], ["out"],
                          [_dense(n_a, k)], work, iwork))
            specs.append((f"substitute{k}", bodies[f"substitute{k}"], ["LD", "B"], [F_sp, _dense(n_a, k)],
                          ["out"], [_dense(n_a, k)], work, iwork))
    if e is not None:
        work = 2 * max(len(e.rows), 1)
        bodies = _elimination(e, table, names, b.n_rows, (1, 2))
        for k in (1, 2):
            n_r = len(e.others)
            add(f"before{k}", bodies[f"before{k}"], ["B"], [_dense(b.n_rows, k)], "out", _dense(n_r, k), work)
            add(f"after{k}", bodies[f"after{k}"], ["m", "B", "lam"],
                [_dense(b.n3), _dense(b.n_rows, k), _dense(n_r, k)], "out", _dense(b.n_rows, k), work)
    if [kind for kind, *_ in specs] != kinds:  # (the cache's lookup names them by ``_kinds``)
        raise RuntimeError(f"the products' functions {[k for k, *_ in specs]} are not {kinds}")
    named = [(f"kkt_{tag}_{kind}", *rest) for kind, *rest in specs]
    loaded = c_functions(named, table.c, decided_by=decided_by)
    if loaded is None:
        return None
    return CompiledProducts(b, {kind: f for (kind, *_), f in zip(specs, loaded, strict=True)})
