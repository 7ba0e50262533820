"""Interval bounds of SX formulas of t (constrained.codegen.interval), what the refusal of a
negative damping coefficient rests on (docs/hard-cases.md, section 13): every bound holds the
formula's values over its piece, a dip far narrower than any sampling is found at its closed-form
place, and formulas that only touch zero pass."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from constrained.codegen.interval import bounds, where_negative
from constrained.model.expressions import FUNCTIONS, parse

#: Formulas of t over [−2, 3] with every function of the scene grammar and the operations the
#: SX graphs hold (powers, comparisons, if_else, min/max); some leave their domain on part of it.
FORMULAS = [f"{name}(t)" for name in FUNCTIONS if name not in ("atan2", "min", "max", "hypot")] + [
    "atan2(t, 0.3)", "min(t, 0.5)", "max(t, -t)", "hypot(t, 1 - t)", "t**2.5", "t**3 - 2*t", "1/(t - 0.25)",
    "t**-2", "exp(-((t - 0.4)/0.01)**2)", "sin(40*t)*cos(3*t) + t/3", "(t - 1)**4 - 0.2", "2**t", "abs(t)**t",
]


def _function(text: str) -> ca.Function:
    t = ca.SX.sym("t")
    return ca.Function("f", [t], [parse(text, {"t": t})])


@pytest.mark.parametrize("text", FORMULAS)
def test_every_bound_holds_the_values_over_its_piece(text):
    """On 300 random pieces of [−2, 3] (widths from 1e-6 to 5), L ≤ f(t) ≤ U at 64 points of each;
    where f is not finite somewhere on a piece, its bound proves nothing there (NaN or ∞)."""
    f = _function(text)
    rng = np.random.default_rng(11)
    width = 10 ** rng.uniform(-6, np.log10(5), 300)
    lo = rng.uniform(-2, 3 - width)
    hi = lo + width
    L, U = bounds(f, lo, hi)
    t = lo[:, None] + (hi - lo)[:, None] * np.linspace(0, 1, 64)[None, :]
    with np.errstate(all="ignore"):
        values = np.asarray(f.map(t.size)(t.ravel()[None, :]), float).reshape(t.shape)
    finite = np.isfinite(values).all(axis=1)
    proven = np.isfinite(L) & np.isfinite(U)
    assert not np.any(proven & ~finite), text
    ok = proven & finite
    assert np.all(L[ok] <= values[ok].min(axis=1)) and np.all(values[ok].max(axis=1) <= U[ok]), text
    assert ok.sum() > 0.3 * len(ok)  # (most pieces are bounded at all)


def test_a_bound_on_a_point_is_the_value():
    f = _function("0.1 - 0.2*exp(-((t - 0.4137)/0.001)**2) + sin(3*t)**2")
    t = np.linspace(0.0, 1.0, 101)
    L, U = bounds(f, t, t)
    values = np.asarray(f.map(t.size)(t[None, :]), float).ravel()
    np.testing.assert_allclose(L, values, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(U, values, rtol=1e-13, atol=1e-15)


def test_a_dip_far_narrower_than_any_sampling_is_found_where_it_is():
    """c = 0.1 − 0.2 exp(−((t − 0.4137)/τ)²) with τ = 0.1 µs is negative for 0.17 µs of a 1 s span
    (|t − 0.4137| < τ √(ln 2)); its lowest value, 0.1 − 0.2 = −0.1, is at t = 0.4137."""
    t_dip, value = where_negative(_function("0.1 - 0.2*exp(-((t - 0.4137)/1e-7)**2)"), 0.0, 1.0)
    assert t_dip == pytest.approx(0.4137, abs=1e-7 * np.sqrt(np.log(2)))
    assert value == pytest.approx(-0.1, rel=1e-9)


@pytest.mark.parametrize("text", ["0.1*(t - 0.5)**2 + 1e-6", "0.1*(t - 0.5)**2", "0.5*(1 - t)",
                                  "abs(sin(3.141592653589793*t))", "1.0000001 + sin(1000*t)", "exp(-t/1e-3)",
                                  "min(t, 1 - t) + 1e-9"])
def test_formulas_at_or_above_zero_pass(text):
    assert where_negative(_function(text), 0.0, 1.0) is None


@pytest.mark.parametrize("text, t_low, lowest", [
    ("0.1*(t - 0.5)**2 - 1e-12", 0.5, -1e-12),  # negative for 6 µs about t = 0.5
    ("0.5*(1 - t) - 1e-3", 1.0, -1e-3),  # at the end of the span
    ("min(0.2 - t, -0.1)", 1.0, -0.8),  # negative all along, lowest at the end
    ("0.1 - 0.3*exp(-((t - 0.3)/0.01)**2) - 0.2*exp(-((t - 0.8)/0.01)**2)", 0.3, -0.2),  # the deeper dip
])
def test_the_lowest_point_is_named(text, t_low, lowest):
    """The lowest value over the span and its time (closed forms: a dip's centre, a line's end)."""
    t, value = where_negative(_function(text), 0.0, 1.0)
    assert t == pytest.approx(t_low, abs=1e-6)
    assert value == pytest.approx(lowest, rel=1e-4)


def test_equal_troughs_and_a_formula_not_finite_are_named():
    """0.9999 + sin(1000 t) dips to −1e-4 at each trough, 1000 t = 3π/2 + 2kπ: one of them is named;
    √(t − 0.7) is not finite before t = 0.7: a time there is named with its value."""
    t, value = where_negative(_function("0.9999 + sin(1000*t)"), 0.0, 1.0)
    phase = (1000 * t - 1.5 * np.pi) / (2 * np.pi)
    assert abs(phase - round(phase)) < 1e-6 and value == pytest.approx(-1e-4, rel=1e-6)
    t, value = where_negative(_function("sqrt(t - 0.7) + 1"), 0.0, 1.0)
    assert t < 0.7 and not np.isfinite(value)


@pytest.mark.parametrize("text, t0, t1, found", [
    ("2.5 + t", -2.0, -1.0, None),  # ≥ 0.5 all over a span before t = 0
    ("0.5", -2.0, -1.0, None),
    ("0.5 + t", -2.0, -1.0, (-2.0, -1.5)),  # lowest at the start
    ("0.3 - 0.5", 0.0, 1.0, (0.0, -0.2)),  # no t: its value, at the start
    ("0", 0.0, 1.0, None),
])
def test_a_span_before_zero_and_a_formula_without_t(text, t0, t1, found):
    """The search began with the pair (t0, t1) as its lowest sample, so over [−2, −1] it took
    t1 = −1 for a value found and refused 2.5 + t, which is ≥ 0.5 there, naming 0.5 at t = −2.
    A formula without t is its value at t0, as the search finds it (without minimizing a constant);
    one that is not finite (a graph built in code: the parser refuses it) is named so."""
    t = ca.SX.sym("t")
    assert where_negative(ca.Function("f", [t], [ca.SX(np.inf)]), 0.0, 1.0) == (0.0, np.inf)
    result = where_negative(_function(text), t0, t1)
    if found is None:
        assert result is None
    else:
        assert result[0] == pytest.approx(found[0], abs=1e-9)
        assert result[1] == pytest.approx(found[1], rel=1e-9)
