"""The neighbour list's forces as ONE fused loop in C: gather, pair, scatter-add in a single
pass over the list, no intermediate arrays (issue 28).

The mapped kernel (constrained.model.pairs.kernel) gathers the positions of every listed pair
into (3, ~ROW·rows) arrays, maps the pair over them and adds the forces back by transposed
gathers: three passes over ~400,000 slots at 10,000 particles, most of a step's time. Here the
same sum is one loop over the rows of the list (``neighbours.pair_rows``), written as the body
of a CasADi ``Function.jit``: CasADi's code generator writes that body into a compiled step
loop like any other Function's, and evaluates it outside one through the C compiler.

The physics stays CasADi's: the pair's scalar

    g(r) = −φ_c'(r) / r,     f_i = g(r_ij) (x_i − x_j),   f_j = −f_i,

is derived symbolically (SX) and its algorithm translated to C statements one instruction at
a time (``codegen.scalar_c``) from a whitelist of operations; a φ with any other operation is
not fused (the mapped kernel serves it). A pair at r ≥ r_c is skipped before the square root,
which changes nothing: φ_c is 0 there. Where the energy V = Σ φ_c(r_ij) is asked for with the
forces (``forces_and_potential``: RATTLE's energy watch at every step), the same pass sums it,
φ_c sharing its work with g (a second loop, taken only then).

The fused Function has no derivatives (finite differences are turned off): what needs ∂F/∂x
of a listed sum takes the every-pair Function (``lists=False``).
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca

from ...codegen import compiled
from ...codegen.scalar_c import scalar_c
from .neighbours import ROW


def force_body(r: ca.SX, t: ca.SX, q: ca.SX, g: ca.SX, n: int, capacity: int, cutoff: float,
               phi: ca.SX | None = None) -> str | None:
    """The C body of the fused force sum: inputs ``x`` (3n), ``t``, ``q`` (φ's parameters),
    ``data`` (the list: valid, x_ref (3n), I (capacity), J (ROW·capacity)); outputs ``V`` and
    ``F`` (3n). ``g`` is −φ_c'(r)/r in the symbols r, t and q; ``phi`` φ_c itself, summed into V
    when V is asked for (a null V pointer: the loop without it; no ``phi``: V = 0). Their parts
    that depend on t and q alone (φ_c's shift: φ(r_c), φ'(r_c), φ''(r_c)) are computed once
    before the loop (``casadi.extract_parametric``), not once per pair."""
    with_energy = phi is not None
    per_pair, names, invariant = ca.extract_parametric(ca.vertcat(g, phi) if with_energy else g,
                                                       ca.vertcat(t, q))
    e = ca.vertcat(*names) if names else ca.SX.sym("e", 0)
    before = scalar_c(ca.Function("invariant", [t, q], list(invariant)), ["tt", "qv[]"],
                      [f"e[{k}]" for k in range(len(invariant))], prefix="u") if names else ""
    pair = ca.cse(per_pair)
    names_in = ["r", "tt", "qv[]", "e[]"]
    scalar = scalar_c(ca.Function("pair_scale", [r, t, q, e], [pair[0]]), names_in, ["gr"],
                      reciprocals={"r": "rinv"})
    both = scalar_c(ca.Function("pair_scale_energy", [r, t, q, e], [pair[0], pair[1]]), names_in,
                    ["gr", "vr"], reciprocals={"r": "rinv"}) if with_energy else ""
    if scalar is None or before is None or both is None:
        return None
    start, n_q, n_e = 1 + 3 * n, max(1, q.numel()), max(1, e.numel())
    loops = _loop(scalar, energy=False)
    if with_energy:  # (two loops: the force Function's, that never asks for V, pays nothing for it)
        loops = f"if (V) {{\n{_loop(both, energy=True)}}} else {{\n{loops}}}\n"
    return f"""
const casadi_int n = {n}, rows = {capacity}, row = {ROW};
const casadi_real rc2 = {float(cutoff) ** 2!r};
casadi_int k, s, c;
casadi_real energy = 0;
if (V) V[0] = 0;
if (!F) return 0;
for (c = 0; c < 3 * n; ++c) F[c] = 0;
if (!x || !data) return 0;
/* locals: loads the compiler need not repeat for fear of the writes to F */
const casadi_real tt = t ? t[0] : 0;
casadi_real qv[{n_q}], e[{n_e}];
for (c = 0; c < {q.numel()}; ++c) qv[c] = q ? q[c] : 0;
{{
{before}
}}
const casadi_real *I = data + {start}, *J = data + {start} + rows;
{loops}
if (V) V[0] = energy;
return 0;
"""


def _loop(scalar: str, energy: bool) -> str:
    """The loop over the list's rows: each pair within the cutoff adds g(r) (x_i − x_j) to F_i
    and its opposite to F_j (and φ_c(r) to the energy)."""
    declared = "casadi_real gr, vr;" if energy else "casadi_real gr;"
    add = "energy += vr;" if energy else ""
    return f"""for (k = 0; k < rows; ++k) {{
  const casadi_real ik = I[k];
  if (!(ik >= 0 && ik < n)) break;  /* the empty rows are last */
  const casadi_int i = (casadi_int) ik;
  const casadi_real xi0 = x[3 * i], xi1 = x[3 * i + 1], xi2 = x[3 * i + 2];
  casadi_real fi0 = 0, fi1 = 0, fi2 = 0;
  for (s = 0; s < row; ++s) {{
    const casadi_real js = J[row * k + s];
    if (!(js >= 0 && js < n)) break;  /* a row's empty places are last */
    const casadi_int j = (casadi_int) js;
    const casadi_real d0 = xi0 - x[3 * j], d1 = xi1 - x[3 * j + 1], d2 = xi2 - x[3 * j + 2];
    const casadi_real r2 = d0 * d0 + d1 * d1 + d2 * d2;
    if (r2 >= rc2) continue;  /* phi_c is 0 beyond the cutoff */
    const casadi_real r = sqrt(r2), rinv = 1. / r;
    {declared}
    {{
{scalar}
    }}
    {add}
    fi0 += gr * d0; fi1 += gr * d1; fi2 += gr * d2;
    F[3 * j] -= gr * d0; F[3 * j + 1] -= gr * d1; F[3 * j + 2] -= gr * d2;
  }}
  F[3 * i] += fi0; F[3 * i + 1] += fi1; F[3 * i + 2] += fi2;
}}
"""


def fused_forces(name: str, r: ca.SX, t: ca.SX, q: ca.SX, g: ca.SX, phi: ca.SX | None = None, *, n: int,
                 size: int, capacity: int, cutoff: float) -> ca.Function | None:
    """(x (3n), t, q (n_q), data (size)) -> (V, F (3n)): the listed pairs' energy (given ``phi``,
    else 0) and forces in one C loop (``force_body``), or None where that cannot be had: no C
    compiler, compiled code turned off (``CONSTRAINED_COMPILE=0``), an operation of φ outside
    the whitelist, or a failed compilation (``jit``)."""
    body = force_body(r, t, q, g, n, capacity, cutoff, phi)
    if body is None:
        return None
    sparsity_in = [ca.Sparsity.dense(3 * n, 1), ca.Sparsity.dense(1, 1), ca.Sparsity.dense(q.numel(), 1),
                   ca.Sparsity.dense(size, 1)]
    sparsity_out = [ca.Sparsity.dense(1, 1), ca.Sparsity.dense(3 * n, 1)]
    return jit(name, body, ["x", "t", "q", "data"], ["V", "F"], sparsity_in, sparsity_out)


def jit(name: str, body: str, names_in: list[str], names_out: list[str], sparsity_in: list[ca.Sparsity],
        sparsity_out: list[ca.Sparsity]) -> ca.Function | None:
    """``Function.jit`` of ``body`` (unbuffered: a null input is all zeros, a null output not
    wanted; no derivatives), compiled in ``jit_folder``, or None where it cannot be had."""
    folder = jit_folder() if compiled.enabled() else None
    if folder is None:
        return None
    # (the folder is part of the Function's serialization, and so of the compile cache's key:
    # a fixed one, so that a step loop holding this kernel is found again by the next run;
    # CasADi names its files uniquely in it and removes them when the Function goes)
    options = {"compiler": "shell", "buffered": False, "enable_fd": False,
               "jit_options": {"compiler": compiled.compiler(), "directory": str(folder),
                               "compiler_flags": ["-O2"]}}
    try:
        return ca.Function.jit(name, body, names_in, names_out, sparsity_in, sparsity_out, options)
    except RuntimeError:
        return None


def jit_folder() -> Path | None:
    """``jit`` in the compile cache's folder, private as it is (the library compiled there is
    loaded into this process), or None when it cannot be had."""
    folder = compiled.cache_dir() / "jit"
    if compiled.private_folder(compiled.cache_dir()) or compiled.private_folder(folder):
        return None
    return folder
