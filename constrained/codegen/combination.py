"""y + Σ_j c_j K_j over long columns as ONE pass in C (issue 28).

A Runge–Kutta step on the vectorized build advances its state by combinations of its
stages, y_i = y + h Σ_j A_ij K_j: in CasADi's virtual machine each term is two passes over
3N numbers (a product, a sum) with a temporary between them — on the 1 cm rope, 9 of the 23
million numbers a DOP853 attempt writes. ``combination(n, k)`` is that sum as one loop that
reads each column once and writes the result once:

    out[i] = y[i] + Σ_{j<k} c[j] K_j[i]        (or without y: Σ_{j<k} c[j] K_j[i])

All k from 1 to MAX_TERMS for one n are entry points of one library, compiled once and cached
(``codegen.external``); None where compiled code cannot be had (the caller then writes the
products and sums as MX)."""

from __future__ import annotations

import casadi as ca

from . import compiled
from .external import c_functions, cached_loops

#: The most stages one combination sums (DOP853: 12, its error estimates 13).
MAX_TERMS = 16


def _body(k: int, n: int, with_y: bool) -> str:
    terms = " + ".join(f"c{j} * K{j}[i]" for j in range(k))
    coefficients = "\n".join(f"  const casadi_real c{j} = c ? c[{j}] : 0;" for j in range(k))
    nulls = " || ".join(f"!K{j}" for j in range(k))
    y = "y[i] + " if with_y else ""
    return f"""{coefficients}
  casadi_int i;
  if (!out) return 0;
  if ({nulls}{" || !y" if with_y else ""}) return 1;  /* (the caller passes dense columns) */
  for (i = 0; i < {n}; ++i) out[i] = {y}{terms};
  return 0;"""


#: The libraries built in this process, by column length.
_libraries: dict[int, _Library | None] = {}


class _Library:
    """The 2 × MAX_TERMS entry points for one column length n: each loaded from the cached
    library when first asked for (a DOP853 step uses about a dozen: each ``casadi.external``
    and the Function it is checked against cost ~1 ms), all of them compiled and loaded at
    once (``c_functions``) when the cache does not hold the library whole and signed."""

    def __init__(self, n: int):
        column = ca.Sparsity.dense(n, 1)
        self.specs = []
        for with_y in (True, False):
            for k in range(1, MAX_TERMS + 1):
                names = [*(["y"] if with_y else []), *(f"K{j}" for j in range(k)), "c"]
                sparsity = [column] * (k + with_y) + [ca.Sparsity.dense(k, 1)]
                self.specs.append((f"{'combination' if with_y else 'sum'}_{n}_{k}", _body(k, n, with_y),
                                   names, sparsity, ["out"], [column]))
        self.path = cached_loops(self.specs)
        self.loaded: list[ca.Function | None] = [None] * len(self.specs)

    def __getitem__(self, i: int) -> ca.Function | None:
        if self.loaded[i] is None and self.path is not None:
            name, _, _, sparsity_in, _, sparsity_out = self.specs[i]
            try:
                f = ca.external(name, str(self.path))
            except RuntimeError:
                f = None
            matches = f is not None and (f.n_in(), f.n_out()) == (len(sparsity_in), 1) and all(
                f.sparsity_in(j) == s for j, s in enumerate(sparsity_in))
            matches = matches and f.sparsity_out(0) == sparsity_out[0]
            if matches:
                self.loaded[i] = f
            else:  # (not what its source says: ``c_functions`` rebuilds it, with a notice)
                self.path = None
        if self.loaded[i] is None:
            every = c_functions(self.specs)
            if every is None:
                return None
            self.loaded = every
        return self.loaded[i]


def combination(n: int, k: int, with_y: bool = True) -> ca.Function | None:
    """(y (n,), K_0 … K_{k−1} (n,), c (k,)) -> y + Σ c_j K_j in one pass of C (``with_y``
    False: no y, Σ c_j K_j); or None (no compiled code, or k outside 1 … MAX_TERMS)."""
    if not 1 <= k <= MAX_TERMS or not compiled.enabled():
        return None
    if n not in _libraries:
        _libraries[n] = _Library(n)
    library = _libraries[n]
    f = None if library is None else library[(0 if with_y else MAX_TERMS) + k - 1]
    if f is None and not compiled.cut_short():  # no compiled code: not asked for again
        _libraries[n] = None
    return f
