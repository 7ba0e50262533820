"""The rest of a vectorized build (the rows and terms in no group: a pin's rows, a few odd
springs) as SX Functions of the entries of x, v and p they read, not of the whole vectors.

A Function of the Structure's x, v and p costs CasADi about 50 ns per symbol to build, used
or not: 5 ms on a 100 x 100 cloth (30,000 coordinates each, 69,000 entries of p), for a pin's
six rows, and the build asks for a dozen such Functions (each set of outputs a start or a step
evaluates). Here the Function takes x[x_at], v[v_at], t and p[p_at], the entries its outputs
read (``ca.symvar``), and its callers gather those: the same instructions on the same numbers.
``grouping``'s probes of the rows (``Rows``) are built the same way.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .columns import take


class RestFunction:
    """The rest's outputs as an SX ``function`` of (x[x_at], v[v_at], t, p[p_at])."""

    def __init__(self, function: ca.Function, x_at: np.ndarray, v_at: np.ndarray, p_at: np.ndarray):
        self.function, self.x_at, self.v_at, self.p_at = function, x_at, v_at, p_at

    def __call__(self, X, V, T, P):
        """The outputs at MX (X, V, T, P) (V None: zeros), as ``function`` returns them."""
        v = ca.MX.zeros(len(self.v_at)) if V is None else take(V, self.v_at)
        return self.function(take(X, self.x_at), v, T, take(P, self.p_at))

    def arguments(self, x: np.ndarray, v: np.ndarray, t: float, p: np.ndarray) -> tuple:
        """``function``'s inputs at numbers (flat arrays)."""
        return x[self.x_at], v[self.v_at], t, p[self.p_at]


class Rows:
    """Rows (one column) as a Function of the entries ``x_at`` of x and ``p_at`` of p they read
    and t, not of the whole vectors (a cloth's 30,000 + 69,000 symbols cost 4 ms to build and
    as much per point to convert): which entries each row reads, its values at a point
    (``grouping``'s probe)."""

    def __init__(self, function: ca.Function, x_at: np.ndarray, p_at: np.ndarray):
        self.function, self.x_at, self.p_at = function, x_at, p_at

    def reads(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(colind, row) of the rows' reads (transposed Jacobian pattern) of x (k = 0) or p (k = 2),
        positions in the whole vector (a third of the time of the SX's)."""
        pattern = self.function.jac_sparsity(0, k).T
        at = self.x_at if k == 0 else self.p_at
        return np.array(pattern.colind(), np.int64), at[np.array(pattern.row(), np.int64)]

    def at(self, x0, t0, p0):
        return self.function(x0[self.x_at], t0, p0[self.p_at])


class Positions:
    """Where symbols are in a Structure's x and v (by their names, x_i and v_i, checked) and
    in p (located once by a Function of p, then remembered); v None: no velocities."""

    def __init__(self, x, v, t, p):
        self.x, self.v, self.t, self.p = x, v, t, p
        self._in_p: dict[int, int] = {}  # element hash -> position in p

    @staticmethod
    def _named(s, vector, prefix: str) -> int | None:
        head, _, tail = s.name().rpartition("_")
        if vector is None or head != prefix or not tail.isdigit() or int(tail) >= vector.numel():
            return None
        return int(tail) if ca.is_equal(vector[int(tail)], s) else None

    def of(self, symbols: list) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The positions (ascending) in x, v and p of ``symbols`` (t left out); None where one of
        them is in none of these."""
        x_at, v_at, unknown = [], [], []
        for s in symbols:
            if ca.is_equal(s, self.t):
                continue
            i, j = self._named(s, self.x, "x"), self._named(s, self.v, "v")
            if i is not None:
                x_at.append(i)
            elif j is not None:
                v_at.append(j)
            elif s.element_hash() not in self._in_p:
                unknown.append(s)
        if unknown and not self._locate(unknown):
            return None
        p_at = [self._in_p[s.element_hash()] for s in symbols if s.element_hash() in self._in_p]
        return tuple(np.array(sorted(set(at)), np.int64) for at in (x_at, v_at, p_at))

    def _locate(self, symbols: list) -> bool:
        # each symbol's row of ∂symbols/∂p: its one entry where it is p's (a Function of p
        # evaluated at 0, 1, 2, … took 10 ms for a cloth's 69,000 entries, this 4 ms)
        rows, cols = ca.jacobian_sparsity(ca.vertcat(*symbols), self.p).get_triplet()
        if len(rows) != len(symbols) or sorted(rows) != list(range(len(symbols))):
            return False  # (a symbol that is not in p)
        at = np.empty(len(symbols), np.int64)
        at[np.asarray(rows, np.int64)] = cols
        if not all(ca.is_equal(self.p[int(i)], s) for i, s in zip(at, symbols, strict=True)):
            return False
        self._in_p.update((s.element_hash(), int(i)) for i, s in zip(at, symbols, strict=True))
        return True


#: Beyond this many symbols read, the rest's Functions take the whole x, v and p (placing each
#: symbol in Python would cost more than the Function's inputs).
MAX_PLACED = 2000


def rest_function(e, outputs: list, positions: Positions) -> RestFunction:
    """``outputs`` (SX of the Structure's x, v, t, p: ``e``) as a RestFunction on the entries they
    read; on the whole vectors where ``positions`` cannot place a symbol."""
    read = ca.symvar(ca.veccat(*outputs)) if outputs else []
    at = positions.of(read) if len(read) <= MAX_PLACED else None
    if at is None:
        n3, n_p = e.x.numel(), e.p.numel()
        at = (np.arange(n3), np.arange(n3), np.arange(n_p))
    x_at, v_at, p_at = at
    inputs = [e.x[x_at.tolist()], e.v[v_at.tolist()], e.t, e.p[p_at.tolist()]]
    return RestFunction(ca.Function("rest", inputs, outputs, {"cse": True}), x_at, v_at, p_at)
