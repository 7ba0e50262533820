"""A group's kernel over all its instances as ONE loop in C (issue 28).

``columns.on_columns`` evaluates a group's SX kernel (a rod's row: f, its six entries of J,
f_t, γ, the row's scale) on whole columns: one node of CasADi's virtual machine per
instruction, each a pass over the group's n instances, and one gather per input column — on
the 1 cm rope, about sixty passes over 10,000 numbers for each evaluation of J and γ, and
fourteen evaluations per step. Here the kernel's instructions are the body of one C loop
over the instances (``codegen.scalar_c``, the same whitelist as the pair forces):

    for each instance i:   x_l[j] = x[index[j, i]],  v_l[j] = v[index[j, i]],
                           c[j] = values[sources[j, i]]   (values = p, then the constants)
                           (its outputs, every scalar of them) = kernel(x_l, v_l, c, t, p)

with all of the kernel's outputs in the loop and those not wanted (a null output) written to
scratch: no branch in the loop, which the compiler then vectorizes (``external.LOOP_FLAGS``).
The C source of all the groups of a build is one library (``codegen.external``), compiled once
and cached: a later run of the same model loads it. Where it cannot be had (no C compiler,
``CONSTRAINED_COMPILE=0``, an operation outside the whitelist) the group is evaluated on
columns as before; the numbers are the same up to rounding.

The loop has no derivatives: it serves the vectorized build, which the virtual machine's
step loops and the manifold's checks evaluate, and nothing differentiates.
"""

from __future__ import annotations

import hashlib

import casadi as ca
import numpy as np

from ...codegen.external import IndexTable, c_functions
from ...codegen.scalar_c import scalar_c


def flat(kernel: ca.Function) -> ca.Function:
    """``kernel`` (SX; inputs x_l, v_l, c, t, p) with each scalar of its outputs an output."""
    inputs = kernel.sx_in()
    scalars = [o[k] for o in kernel.call(inputs) for k in range(o.numel())]
    return ca.Function(f"{kernel.name()}_flat", inputs, scalars, {"cse": True})


def loop_body(kernel: ca.Function, index: np.ndarray, sources: np.ndarray, constants: np.ndarray, n3: int,
              n_p: int, table: IndexTable) -> str | None:
    """The C loop of ``kernel`` (``flat``'s form) over the instances of a group: ``index``
    (d, n) their coordinates, ``sources`` (n_c, n) where their constants are in p (below n_p)
    or in ``constants`` (from n_p), both in the library's ``table`` (no copy per call); None
    when the kernel has an operation outside the whitelist. Inputs x, v (3N), t, p; outputs
    y0 … (n each)."""
    if not np.all(np.isfinite(constants)):
        return None  # (no C literal)
    m = kernel.n_out()
    # (a rod divides six times by its length: one division and six products)
    work = scalar_c(kernel, ["xl[]", "vl[]", "cl[]", "tt", "pp[]"], [f"o{k}" for k in range(m)], prefix="s",
                    repeated_divisors=True)
    if work is None:
        return None
    d, n = index.shape
    n_c = sources.shape[0] if sources.size else 0
    # (an output not wanted is written to scratch: no branch in the loop, which can then be vectorized)
    targets = "\n  ".join(f"casadi_real *t{k} = y{k} ? y{k} : w;" for k in range(m))
    writes = "\n    ".join(f"t{k}[i] = o{k};" for k in range(m))
    literals = ",".join(map(repr, constants.tolist())) or "0"
    at_x, at_c = _per_instance(index, "index", table), _per_instance(sources, "sources", table)
    return f"""{at_x[0]}
{at_c[0]}
  static const casadi_real constants[{max(constants.size, 1)}] = {{{literals}}};
  static const casadi_real zero_x[{n3}], zero_p[{max(n_p, 1)}];
  const casadi_real *xx = x ? x : zero_x, *vv = v ? v : zero_x, *pp = p ? p : zero_p;
  const casadi_real tt = t ? t[0] : 0;
  {targets}
  casadi_int i;
  int j;
  for (i = 0; i < {n}; ++i) {{
    casadi_real xl[{max(d, 1)}], vl[{max(d, 1)}], cl[{max(n_c, 1)}];
    casadi_real {', '.join(f'o{k}' for k in range(m))};
    for (j = 0; j < {d}; ++j) {{
      const int c = {at_x[1]};
      xl[j] = xx[c];
      vl[j] = vv[c];
    }}
    for (j = 0; j < {n_c}; ++j) {{
      const int c = {at_c[1]};
      cl[j] = c < {n_p} ? pp[c] : constants[c - {n_p}];
    }}
    {{
{work}
    }}
    {writes}
  }}
  return 0;"""


def _per_instance(index: np.ndarray, name: str, table: IndexTable) -> tuple[str, str]:
    """(declarations, expression): ``index[j, i]`` (d, n) in C, as ``base[j] + step[j] i``
    where every row steps evenly (a chain's rods: no index read per instance), else read from
    ``table``."""
    if index.size == 0:
        return "", "0"
    d = index.shape[0]
    steps = index[:, 1:2] - index[:, :1] if index.shape[1] > 1 else np.zeros((d, 1), np.int64)
    if np.all(np.diff(index, axis=1) == steps):
        base, step = (", ".join(map(str, v.ravel().tolist())) for v in (index[:, 0], steps))
        return (f"  static const int {name}_base[{d}] = {{{base}}}, {name}_step[{d}] = {{{step}}};",
                f"{name}_base[j] + {name}_step[j] * (int) i")
    return f"  const int *{name} = {table.add(index.T)};", f"{name}[{d} * i + j]"


class FusedGroup:
    """One group's loop: ``__call__(X, V, T, P)`` -> every scalar output, an MX column (n,)."""

    def __init__(self, function: ca.Function):
        self.function = function

    def __call__(self, X, V, T, P) -> list:
        return self.function(X, V if V is not None else ca.MX(X.numel(), 1), T, P)


def fused_groups(groups: list, kernels: list[ca.Function], n3: int, n_p: int) -> list[FusedGroup | None]:
    """For each group and its kernel (inputs x_l, v_l, c, t, p), its ``FusedGroup``, all in one
    compiled library; None for a group the whitelist does not cover, and all None when
    compiled code cannot be had."""
    bodies, specs, table = [], [], IndexTable()
    for g, kernel in zip(groups, kernels, strict=True):
        k = flat(kernel)
        n = g.index.shape[1]
        constants = np.asarray(g.constants, float).reshape(-1)
        body = loop_body(k, np.asarray(g.index), np.asarray(g.sources), constants, n3, n_p, table)
        if body is None:
            specs.append(None)
            continue
        names_in = ["x", "v", "t", "p"]
        sparsity_in = [ca.Sparsity.dense(n3, 1), ca.Sparsity.dense(n3, 1), ca.Sparsity.dense(1, 1),
                       ca.Sparsity.dense(n_p, 1)]
        names_out = [f"y{j}" for j in range(k.n_out())]
        sparsity_out = [ca.Sparsity.dense(n, 1)] * k.n_out()
        specs.append((body, names_in, sparsity_in, names_out, sparsity_out, n))
        bodies.append(body)
    if not bodies:
        return [None] * len(groups)
    data = table.data()
    tag = hashlib.sha256("\n".join(bodies).encode() + data).hexdigest()[:12]
    named = [None if s is None else (f"rows_{tag}_{i}", *s) for i, s in enumerate(specs)]
    functions = c_functions([s for s in named if s is not None], table.c, key=data)
    if functions is None:
        return [None] * len(groups)
    it = iter(functions)
    return [None if s is None else FusedGroup(next(it)) for s, g in zip(named, groups, strict=True)]

