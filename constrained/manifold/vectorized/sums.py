"""A ``columns.Summation`` as one loop in C: the potential terms' forces of a step (issue 28).

The vectorized build sums each term group's gradient columns into the coordinates,
F_c = −Σ ∂U_k/∂x_c, with ``columns.Summation``: on a 100 x 100 cloth (two spring kinds and
gravity, seven columns) 18 gathers and 42 additions of whole columns and a reordering, for each
of a dopri step's twelve accelerations — 0.07 s of building the step's graph, and as many
passes of CasADi's virtual machine at each evaluation. Here it is one scatter-add:

    out[c] = −0.0 for every named coordinate c, 0 for the others;
    for each stream s in order, each position i in order:  out[T_s[i]] += s[i]
    (negated: out = −out)

the terms of each target added in the order of (stream, position), as the Summation adds them
(its first term plus the next…: −0.0 + a is a, bit for bit, whatever a's sign), so the numbers
are the same to the last bit. The library is compiled once per model and found in the compile
cache by its index data.
"""

from __future__ import annotations

import hashlib

import casadi as ca
import numpy as np

from ...codegen.external import IndexTable, c_functions, element


def summation_loop(lengths: list[int], targets: list[np.ndarray], n_targets: int,
                   negated: bool = False) -> ca.Function | None:
    """``(s_0, …, s_{k−1}) -> y`` with y[t] = Σ s_j[i] over the entries (j, i) whose target
    ``targets[j][i]`` is t, in the order of (j, i) — ``columns.Summation(lengths, targets,
    n_targets)`` of dense columns, the same bits — negated when asked; targets nobody names are
    0 (−0 negated). None where compiled code cannot be had (or there is nothing to sum)."""
    if not lengths or n_targets == 0:
        return None
    table = IndexTable()
    where = [element(table, np.asarray(t, np.int64)) for t in targets]
    named = "\n".join(f"  for (i = 0; i < {k}; ++i) out[{w}] = -0.0;"
                      for k, w in zip(lengths, where, strict=True))
    added = "\n".join(f"  for (i = 0; i < {k}; ++i) out[{w}] += s{j}[i];"
                      for j, (k, w) in enumerate(zip(lengths, where, strict=True)))
    negate = f"\n  for (i = 0; i < {n_targets}; ++i) out[i] = -out[i];" if negated else ""
    body = (f"  casadi_int i;\n  for (i = 0; i < {n_targets}; ++i) out[i] = 0;\n{named}\n{added}{negate}"
            "\n  return 0;")
    data = table.data()
    tag = hashlib.sha256(body.encode() + data).hexdigest()[:12]
    names = [f"s{j}" for j in range(len(lengths))]
    spec = (f"sums_{tag}", body, names, [ca.Sparsity.dense(int(k), 1) for k in lengths], ["out"],
            [ca.Sparsity.dense(int(n_targets), 1)])
    loaded = c_functions([spec], table.c, key=data)
    return None if loaded is None else loaded[0]
