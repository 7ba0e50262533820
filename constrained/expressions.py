"""Safe parsing of formula strings into CasADi expressions.

A formula is parsed with Python's ``ast`` module and walked node by node; only numbers,
the names the caller provides, ``+ - * / **``, unary minus and calls of the whitelisted
functions below are accepted. Nothing is ever passed to ``eval``.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Mapping

import casadi as ca

from .errors import ExpressionError

FUNCTIONS = {
    "sin": ca.sin,
    "cos": ca.cos,
    "tan": ca.tan,
    "asin": ca.asin,
    "acos": ca.acos,
    "atan": ca.atan,
    "atan2": ca.atan2,
    "sinh": ca.sinh,
    "cosh": ca.cosh,
    "tanh": ca.tanh,
    "asinh": ca.asinh,
    "acosh": ca.acosh,
    "atanh": ca.atanh,
    "exp": ca.exp,
    "log": ca.log,
    "log10": ca.log10,
    "sqrt": ca.sqrt,
    "abs": ca.fabs,
    "sign": ca.sign,
    "floor": ca.floor,
    "ceil": ca.ceil,
    "min": ca.fmin,
    "max": ca.fmax,
    "hypot": lambda a, b: ca.sqrt(a * a + b * b),
}
ARITY = {"atan2": 2, "min": 2, "max": 2, "hypot": 2}
CONSTANTS = {"pi": math.pi, "e": math.e}

_BINARY = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
    ast.Pow: lambda a, b: a**b,
}
_FORBIDDEN_HINTS = {
    ast.BitXor: "'^' is not a power here; write '**'",
    ast.Attribute: "attribute access ('.') is not allowed",
    ast.Subscript: "indexing ('[ ]') is not allowed",
    ast.Lambda: "lambda is not allowed",
    ast.Compare: "comparisons are not allowed",
    ast.BoolOp: "'and'/'or' are not allowed",
    ast.IfExp: "'if ... else' is not allowed",
}


def parse(text: str | float | int, names: Mapping[str, object], *, where: str = "formula"):
    """Parse ``text`` into a CasADi expression over ``names`` (name -> SX/MX/number).

    Numbers pass through unchanged. Raises ExpressionError naming ``where`` and the
    offending piece when the formula uses anything outside the whitelist.
    """
    if isinstance(text, bool):
        raise ExpressionError(f"expected a number or a formula string, got {text!r}", where=where)
    if isinstance(text, int | float):
        if not math.isfinite(text):
            raise ExpressionError(f"the number {text!r} is not finite", where=where)
        return float(text)
    if not isinstance(text, str):
        raise ExpressionError(
            f"expected a number or a formula string, got {type(text).__name__}", where=where
        )
    if not text.strip():
        raise ExpressionError("the formula is empty", where=where)
    if len(text) > 10_000:
        raise ExpressionError("the formula is longer than 10000 characters", where=where)
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        raise ExpressionError(
            f"cannot read formula {text!r}: syntax error near column {exc.offset}", where=where
        ) from None
    return _Walker(text, names, where).visit(tree.body)


def free_names(text: str) -> set[str]:
    """The bare names a formula string mentions (without checking them)."""
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError:
        return set()
    return {node.id for node in ast.walk(tree) if isinstance(node, ast.Name)}


class _Walker:
    def __init__(self, text: str, names: Mapping[str, object], where: str):
        self.text = text
        self.names = names
        self.where = where

    def fail(self, message: str):
        raise ExpressionError(f"in formula {self.text!r}: {message}", where=self.where)

    def visit(self, node):
        if isinstance(node, ast.Constant):
            if isinstance(node.value, bool) or not isinstance(node.value, int | float):
                self.fail(f"the literal {node.value!r} is not a number")
            return float(node.value)
        if isinstance(node, ast.Name):
            if node.id in self.names:
                return self.names[node.id]
            if node.id in CONSTANTS:
                return CONSTANTS[node.id]
            if node.id in FUNCTIONS:
                self.fail(f"'{node.id}' is a function; call it as {node.id}(...)")
            known = ", ".join(sorted(self.names)) or "(none)"
            self.fail(f"unknown name '{node.id}' (known names: {known})")
        if isinstance(node, ast.BinOp):
            op = _BINARY.get(type(node.op))
            if op is None:
                hint = _FORBIDDEN_HINTS.get(type(node.op), f"operator {type(node.op).__name__}")
                self.fail(f"{hint} is not allowed" if hint.startswith("operator") else hint)
            return op(self.visit(node.left), self.visit(node.right))
        if isinstance(node, ast.UnaryOp):
            if isinstance(node.op, ast.USub):
                return -self.visit(node.operand)
            if isinstance(node.op, ast.UAdd):
                return self.visit(node.operand)
            self.fail(f"unary operator {type(node.op).__name__} is not allowed")
        if isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name):
                self.fail("only plain function calls such as sin(x) are allowed")
            name = node.func.id
            if name not in FUNCTIONS:
                allowed = ", ".join(sorted(FUNCTIONS))
                self.fail(f"function '{name}' is not allowed (allowed: {allowed})")
            if node.keywords:
                self.fail(f"'{name}' takes no keyword arguments")
            want = ARITY.get(name, 1)
            if len(node.args) != want:
                self.fail(f"'{name}' takes {want} argument(s), got {len(node.args)}")
            return FUNCTIONS[name](*[self.visit(a) for a in node.args])
        hint = _FORBIDDEN_HINTS.get(type(node))
        self.fail(hint or f"the construct {type(node).__name__} is not allowed")
