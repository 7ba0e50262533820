"""SX algorithms evaluated in interval arithmetic, one instruction at a time (as ``scalar_c``
writes them to C): for a formula f(t) and pieces [t_lo, t_hi], bounds L ≤ f(t) ≤ U that hold
for every t of each piece. ``where_negative`` uses them to find where a formula of t is
negative or not finite over a whole span, however briefly, or to prove that it is nowhere.

Each operation maps the intervals of its operands to one that contains every value it can
take (monotone functions at the ends, sin and cos with the extrema they pass, a product from
the four corners, ...), widened by ROUNDING ulps either side for the rounding of the
operation itself. Where an operation may leave its domain on the piece (the square root of an interval
reaching below 0, a division by one holding 0) the bound is NaN or infinite: the piece is
not proven, and is split until its samples show the non-finite value or the bound holds.
An operation outside ``RULES`` bounds nothing (NaN), and the search falls back on samples.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

#: Pieces of the span the search holds at once at most; beyond (a formula that keeps touching
#: 0, or an operation without a rule) it falls back on ``FALLBACK_SAMPLES`` samples.
MAX_PIECES = 4096
#: A piece this much narrower than the span is not split further: its bound is taken from the
#: samples (a formula that touches 0 exactly, b·(1 − t) at t = 1, is never proven ≥ 0 by intervals).
NARROWEST = 1e-12
#: Samples of the fallback, spread evenly over the span (each lowest one refined locally).
FALLBACK_SAMPLES = 1 << 16
#: Each bound is widened by this many ulps of itself for the rounding of its operation (a
#: library's sin, exp or pow is within a few ulps of NumPy's, not the same number).
ROUNDING = 8
#: Operations whose result is 0 or 1 (no rounding to widen).
_LOGICAL = {ca.OP_LT, ca.OP_LE, ca.OP_EQ, ca.OP_NE, ca.OP_NOT, ca.OP_AND, ca.OP_OR}


def _erf():
    """SciPy's erf, imported when a formula has one (a run without SciPy stays without it)."""
    from scipy.special import erf

    return erf


def _increasing(f):
    return lambda a: (f(a[0]), f(a[1]))


def _within(f, low: float, high: float):
    """An increasing f defined on [low, high]: NaN where the piece leaves it."""
    def rule(a):
        ok = (a[0] >= low) & (a[1] <= high)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(ok, f(a[0]), np.nan), np.where(ok, f(a[1]), np.nan)
    return rule


def _magnitude(a):
    """(min |x|, max |x|) over the interval a."""
    lo, hi = a
    low = np.where((lo <= 0) & (hi >= 0), 0.0, np.minimum(np.abs(lo), np.abs(hi)))
    return low, np.maximum(np.abs(lo), np.abs(hi))


def _product(a, b):
    with np.errstate(invalid="ignore"):
        corners = np.stack([a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]])
    corners = np.where(np.isnan(corners) & ~np.isnan(a[0] + a[1] + b[0] + b[1]), 0.0, corners)  # 0·∞
    return corners.min(axis=0), corners.max(axis=0)


def _reciprocal(b):
    holds_zero = (b[0] <= 0) & (b[1] >= 0)
    with np.errstate(divide="ignore"):
        return np.where(holds_zero, -np.inf, 1 / b[1]), np.where(holds_zero, np.inf, 1 / b[0])


def _even(f):
    """An even f increasing in |x| (x², cosh)."""
    def rule(a):
        low, high = _magnitude(a)
        return f(low), f(high)
    return rule


def _periodic(f, peak: float):
    """sin or cos over a: its ends, 1 where it passes a peak (peak + 2kπ), −1 where it passes a
    trough (peak + π + 2kπ)."""
    def rule(a):
        lo, hi = a
        ends = np.stack([f(lo), f(hi)])
        top = np.ceil((lo - peak) / (2 * np.pi)) <= np.floor((hi - peak) / (2 * np.pi))
        bottom = np.ceil((lo - peak - np.pi) / (2 * np.pi)) <= np.floor((hi - peak - np.pi) / (2 * np.pi))
        wide = ~(hi - lo < 2 * np.pi)
        return (np.where(bottom | wide, -1.0, ends.min(axis=0)), np.where(top | wide, 1.0, ends.max(axis=0)))
    return rule


def _tan(a):
    lo, hi = a
    crosses = (np.ceil((lo - np.pi / 2) / np.pi) <= np.floor((hi - np.pi / 2) / np.pi)) | ~(hi - lo < np.pi)
    return np.where(crosses, -np.inf, np.tan(lo)), np.where(crosses, np.inf, np.tan(hi))


def _power(a, b, exponent: float | None):
    """a^b: an integer constant exponent by its parity; else exp(b log a) for a > 0 (its extremes
    at the corners), NaN where a may be ≤ 0."""
    if exponent is not None and float(exponent).is_integer():
        n = int(exponent)
        if n == 0:
            return np.ones_like(a[0]), np.ones_like(a[0])
        if n % 2:
            low, high = a[0] ** float(abs(n)), a[1] ** float(abs(n))
        else:
            low, high = (m ** float(abs(n)) for m in _magnitude(a))
        return (low, high) if n > 0 else _reciprocal((low, high))
    with np.errstate(invalid="ignore", divide="ignore"):
        corners = np.stack([np.exp(y * np.log(x)) for x in a for y in b])
    ok = a[0] > 0
    return np.where(ok, corners.min(axis=0), np.nan), np.where(ok, corners.max(axis=0), np.nan)


def _truth(a):
    """(surely true, surely false) of an interval as a condition."""
    return (a[0] > 0) | (a[1] < 0), (a[0] == 0) & (a[1] == 0)


def _logical(true, false):
    return np.where(true, 1.0, 0.0), np.where(false, 0.0, 1.0)


def _if_else_zero(c, x):
    true, false = _truth(c)
    return (np.where(true, x[0], np.where(false, 0.0, np.minimum(x[0], 0.0))),
            np.where(true, x[1], np.where(false, 0.0, np.maximum(x[1], 0.0))))


def _copysign(a, b):
    low, high = _magnitude(a)
    return (np.where(b[0] >= 0, low, -high), np.where(b[1] < 0, -low, high))


def _same(a, b):
    """Surely equal: both intervals the same single value."""
    return (a[0] == a[1]) & (b[0] == b[1]) & (a[0] == b[0])


def _apart(a, b):
    """Surely different: the intervals do not meet."""
    return (a[1] < b[0]) | (b[1] < a[0])


#: op -> rule(a[, b][, exponent]) giving (lower, upper) arrays.
RULES = {
    ca.OP_ASSIGN: lambda a: a,
    ca.OP_ADD: lambda a, b: (a[0] + b[0], a[1] + b[1]),
    ca.OP_SUB: lambda a, b: (a[0] - b[1], a[1] - b[0]),
    ca.OP_MUL: _product,
    ca.OP_DIV: lambda a, b: _product(a, _reciprocal(b)),
    ca.OP_NEG: lambda a: (-a[1], -a[0]),
    ca.OP_TWICE: lambda a: (2 * a[0], 2 * a[1]),
    ca.OP_INV: _reciprocal,
    ca.OP_SQ: _even(np.square),
    ca.OP_FABS: _magnitude,
    ca.OP_COSH: _even(np.cosh),
    ca.OP_SQRT: _within(np.sqrt, 0.0, np.inf),
    ca.OP_EXP: _increasing(np.exp),
    ca.OP_EXPM1: _increasing(np.expm1),
    ca.OP_LOG: _within(np.log, np.nextafter(0.0, 1.0), np.inf),
    ca.OP_LOG1P: _within(np.log1p, np.nextafter(-1.0, 0.0), np.inf),
    ca.OP_SIN: _periodic(np.sin, np.pi / 2),
    ca.OP_COS: _periodic(np.cos, 0.0),
    ca.OP_TAN: _tan,
    ca.OP_ASIN: _within(np.arcsin, -1.0, 1.0),
    ca.OP_ACOS: lambda a: _within(np.arccos, -1.0, 1.0)(a)[::-1],  # (decreasing)
    ca.OP_ATAN: _increasing(np.arctan),
    ca.OP_SINH: _increasing(np.sinh),
    ca.OP_TANH: _increasing(np.tanh),
    ca.OP_ASINH: _increasing(np.arcsinh),
    ca.OP_ACOSH: _within(np.arccosh, 1.0, np.inf),
    ca.OP_ATANH: _within(np.arctanh, np.nextafter(-1.0, 0.0), np.nextafter(1.0, 0.0)),
    ca.OP_ERF: lambda a: _increasing(_erf())(a),
    ca.OP_FLOOR: _increasing(np.floor),
    ca.OP_CEIL: _increasing(np.ceil),
    ca.OP_SIGN: _increasing(np.sign),
    ca.OP_FMIN: lambda a, b: (np.minimum(a[0], b[0]), np.minimum(a[1], b[1])),
    ca.OP_FMAX: lambda a, b: (np.maximum(a[0], b[0]), np.maximum(a[1], b[1])),
    ca.OP_HYPOT: lambda a, b: (np.hypot(_magnitude(a)[0], _magnitude(b)[0]),
                               np.hypot(_magnitude(a)[1], _magnitude(b)[1])),
    ca.OP_ATAN2: lambda a, b: (np.full_like(a[0], -np.pi), np.full_like(a[0], np.pi)),
    ca.OP_FMOD: lambda a, b: (-_magnitude(b)[1], _magnitude(b)[1]),
    ca.OP_COPYSIGN: _copysign,
    ca.OP_POW: lambda a, b: _power(a, b, None),
    ca.OP_CONSTPOW: lambda a, b: _power(a, b, None),
    ca.OP_LT: lambda a, b: _logical(a[1] < b[0], a[0] >= b[1]),
    ca.OP_LE: lambda a, b: _logical(a[1] <= b[0], a[0] > b[1]),
    ca.OP_EQ: lambda a, b: _logical(_same(a, b), _apart(a, b)),
    ca.OP_NE: lambda a, b: _logical(_apart(a, b), _same(a, b)),
    ca.OP_NOT: lambda a: _logical(_truth(a)[1], _truth(a)[0]),
    ca.OP_AND: lambda a, b: _logical(_truth(a)[0] & _truth(b)[0], _truth(a)[1] | _truth(b)[1]),
    ca.OP_OR: lambda a, b: _logical(_truth(a)[0] | _truth(b)[0], _truth(a)[1] & _truth(b)[1]),
    ca.OP_IF_ELSE_ZERO: _if_else_zero,
}


def _widened(value):
    lo, hi = value
    with np.errstate(invalid="ignore"):
        return (np.where(np.isfinite(lo), lo - ROUNDING * np.spacing(np.abs(lo)), lo),
                np.where(np.isfinite(hi), hi + ROUNDING * np.spacing(np.abs(hi)), hi))


def bounds(function: ca.Function, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(L, U): for each piece [lo_k, hi_k], bounds on the scalar SX ``function`` of one scalar
    input over it, L ≤ f(t) ≤ U (NaN where an operation has no rule or may leave its domain)."""
    with np.errstate(all="ignore"):  # (overflow to ±∞, NaN outside a domain: what a bound says)
        return _bounds(function, np.asarray(lo, float), np.asarray(hi, float))


def _bounds(function: ca.Function, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    work: dict[int, tuple] = {}
    constants: dict[int, float] = {}  # work slot -> the constant it holds (an exponent)
    out = (np.full(lo.shape, np.nan), np.full(lo.shape, np.nan))
    for k in range(function.n_instructions()):
        op, slots = function.instruction_id(k), function.instruction_input(k)
        target = function.instruction_output(k)[0]
        if op == ca.OP_OUTPUT:
            out = work[slots[0]]
            continue
        constants.pop(target, None)
        if op == ca.OP_INPUT:
            value = (lo, hi)
        elif op == ca.OP_CONST:
            c = float(function.instruction_constant(k))
            value = (np.full(lo.shape, c), np.full(lo.shape, c))
            constants[target] = c
        elif op in RULES:
            args = [work[s] for s in slots]
            if op in (ca.OP_POW, ca.OP_CONSTPOW):
                value = _power(*args, constants.get(slots[1]))
            else:
                value = RULES[op](*args)
            if op not in _LOGICAL and op != ca.OP_ASSIGN:  # (the operation's own rounding)
                value = _widened(value)
        else:
            value = (np.full(lo.shape, np.nan), np.full(lo.shape, np.nan))
        work[target] = value
    return out


def where_negative(function: ca.Function, t0: float, t1: float) -> tuple[float, float] | None:
    """(t, f(t)) at the lowest value of the scalar SX ``function`` of t on [t0, t1] when it is
    negative there, however briefly, or at a point where f is not finite; None when f is ≥ 0 and
    finite all over.

    Branch and bound: a piece is done when its interval bound shows f ≥ 0 and finite on it, or
    no lower than the lowest value sampled so far; every other piece is sampled at its middle and
    split, until the pieces left cannot hold a value below the lowest sample by more than
    CLOSE_ENOUGH of it, or are NARROWEST of the span (their samples taken as they are). The
    lowest sample is then refined by a bounded local minimization. More than MAX_PIECES pieces at
    once: the lowest of FALLBACK_SAMPLES samples, the few lowest refined locally. A formula that
    does not use t (``coefficient = "b"``) is its value at t0, the answer the search gives, in one
    call (a refusal used to spend 1.5 ms in the minimization of a constant)."""
    if not any(function.instruction_id(k) == ca.OP_INPUT for k in range(function.n_instructions())):
        value = float(function(t0))
        return None if np.isfinite(value) and value >= 0 else (t0, value)
    span = t1 - t0
    lo, hi = np.array([t0], float), np.array([t1], float)
    t_low, f_low, width = _lowest_sample(function, np.array([t0, t1]), (t0, np.inf), np.inf)
    while lo.size and np.isfinite(f_low):
        L, U = bounds(function, lo, hi)
        open_ = ~((L >= 0) & (U < np.inf)) & ~(L > f_low)
        lo, hi, L = lo[open_], hi[open_], L[open_]
        if f_low < 0 and np.all(L >= f_low - CLOSE_ENOUGH * abs(f_low)):
            break
        middle = 0.5 * (lo + hi)
        t_low, f_low, width = _lowest_sample(function, middle, (t_low, f_low), hi - lo, width)
        wide = hi - lo > NARROWEST * span
        lo, hi, middle = lo[wide], hi[wide], middle[wide]
        if 2 * lo.size > MAX_PIECES:
            return _sampled(function, t0, t1, (t_low, f_low) if f_low < 0 else None)
        lo, hi = np.concatenate([lo, middle]), np.concatenate([middle, hi])
    if not np.isfinite(f_low):
        return t_low, f_low
    if f_low >= 0:
        return None
    return _lowest_near(function, t_low, max(t0, t_low - width), min(t1, t_low + width))


#: The search stops once no piece left can hold a value lower than the lowest sample by more
#: than this share of it (the local minimization then finds the last digits).
CLOSE_ENOUGH = 1e-6


def _values(function: ca.Function, t: np.ndarray) -> np.ndarray:
    if not len(t):
        return np.zeros(0)
    return np.asarray(function.map(len(t))(np.asarray(t, float)[None, :]), float).ravel()


def _lowest_sample(function, t, best, widths, width=np.inf):
    """(t, f(t), the width of its piece) of the lowest of ``best`` (t, f) and the samples at ``t``;
    a sample that is not finite is the lowest of all (the first in time)."""
    values = _values(function, t)
    widths = np.broadcast_to(np.asarray(widths, float), t.shape)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        k = bad[np.argmin(t[bad])]
        return float(t[k]), float(values[k]), float(widths[k])
    k = int(np.argmin(values)) if len(values) else None
    if k is None or not values[k] < best[1]:
        return best[0], best[1], width
    return float(t[k]), float(values[k]), float(widths[k])


def _lowest_near(function, t: float, lo: float, hi: float) -> tuple[float, float]:
    """The lowest value found on [lo, hi] from the sample at t, by a bounded minimization in the
    offset from t (so that its tolerance is one of the offset, not of t)."""
    value = float(function(t))
    if hi <= lo:
        return t, value
    from scipy.optimize import minimize_scalar  # (when a coefficient dips: SciPy only then)

    found = minimize_scalar(lambda u: float(function(t + u)), bounds=(lo - t, hi - t), method="bounded",
                            options={"xatol": 1e-14 * max(1.0, abs(t))})
    if np.isfinite(found.fun) and found.fun < value:
        return t + float(found.x), float(found.fun)
    return t, value


def _sampled(function, t0: float, t1: float, best) -> tuple[float, float] | None:
    """The lowest of FALLBACK_SAMPLES samples (and ``best``, a (t, f) found before), the eight
    lowest refined locally, when it is negative or not finite; else None."""
    t = np.linspace(t0, t1, FALLBACK_SAMPLES)
    values = _values(function, t)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        return float(t[bad[0]]), float(values[bad[0]])
    step = t[1] - t[0]
    found = [_lowest_near(function, float(t[k]), max(t0, t[k] - step), min(t1, t[k] + step))
             for k in np.argsort(values)[:8]]
    t_low, f_low = min([*found, *([best] if best else [])], key=lambda p: p[1])
    return (t_low, f_low) if f_low < 0 else None
