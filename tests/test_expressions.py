"""The whitelisted formula parser: correct values, and refusals that name the problem."""

from __future__ import annotations

import math

import casadi as ca
import pytest
from hypothesis import given
from hypothesis import strategies as st

from constrained.errors import ExpressionError
from constrained.model.expressions import parse


def value(expr) -> float:
    return float(ca.evalf(expr)) if isinstance(expr, ca.SX) else float(expr)


@given(st.floats(-3, 3), st.floats(0.1, 3))
def test_formulas_evaluate_like_the_math_they_spell(a, b):
    names = {"a": ca.SX(a), "b": ca.SX(b)}
    got = value(parse("sin(a)**2 + cos(a)**2 - a*b/b + sqrt(b)*exp(-b) + atan2(a, b) - 2*pi", names))
    want = 1 - a + math.sqrt(b) * math.exp(-b) + math.atan2(a, b) - 2 * math.pi
    assert got == pytest.approx(want, rel=1e-12, abs=1e-12)


def test_symbols_stay_symbolic_and_differentiable():
    t = ca.SX.sym("t")
    expr = parse("0.2*sin(3*t)", {"t": t})
    assert float(ca.evalf(ca.substitute(ca.jacobian(expr, t), t, 0))) == pytest.approx(0.6)


@pytest.mark.parametrize(
    "text, message",
    [
        ("x.__class__", "attribute access"),
        ("__import__('os')", "not allowed"),
        ("open(1)", "function 'open' is not allowed"),
        ("foo + 1", "unknown name 'foo'"),
        ("x ^ 2", "write '\\*\\*'"),
        ("lambda: 1", "lambda"),
        ("[1, 2][0]", "not allowed"),
        ("sin", "is a function"),
        ("sin(x, x)", "takes 1 argument"),
        ("1 +", "syntax error"),
        ("'text'", "not a number"),
        ("x if x else 1", "not allowed"),
        ("", "empty"),
    ],
)
def test_forbidden_or_unknown_constructs_are_refused(text, message):
    with pytest.raises(ExpressionError, match=message) as info:
        parse(text, {"x": ca.SX.sym("x")}, where="constraints[0].expr")
    assert "constraints[0].expr" in str(info.value)


def test_non_finite_numbers_are_refused():
    with pytest.raises(ExpressionError, match="not finite"):
        parse(float("nan"), {}, where="k")
