"""Safe parsing of formula strings into CasADi expressions.

A formula is parsed with Python's ``ast`` module and walked node by node; only numbers,
the names the caller provides, ``+ - * / **``, unary minus and calls of the whitelisted
functions below are accepted. Nothing is ever passed to ``eval``.

Limits (each refused with a message, never a crash): at most MAX_LENGTH characters, at most
MAX_DEPTH levels of nesting (parentheses, signs, calls, operators), and numbers -- literals
and the parts the parser works out itself, such as ``2**10`` -- must be finite and at most
MAX_MAGNITUDE in size.
"""

from __future__ import annotations

import ast
import contextlib
import difflib
import functools
import math
import re
from collections.abc import Mapping

import casadi as ca
import numpy as np

from ..errors import ExpressionError, InconsistentStateError, InputError, listed

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

#: The longest formula accepted (characters).
MAX_LENGTH = 10_000
#: The deepest nesting accepted: operators, signs, parentheses and calls inside each other.
MAX_DEPTH = 100
#: The largest number a formula may hold or work out (literals and constant parts alike):
#: beyond it products and squares in the equations of motion overflow.
MAX_MAGNITUDE = 1e100

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
    if len(text) > MAX_LENGTH:
        raise ExpressionError(
            f"the formula is {len(text)} characters long, more than the {MAX_LENGTH} accepted; "
            "split it with [parameters] or simplify it", where=where)
    tree = _syntax_tree(text, where)
    depth = _depth(tree.body)
    if depth > MAX_DEPTH:
        raise ExpressionError(
            f"the formula {_short(text)} is nested {depth} levels deep (operators, signs, "
            f"parentheses and calls inside each other), more than the {MAX_DEPTH} accepted; "
            "simplify it", where=where)
    return _Walker(text, names, where).visit(tree.body)


def terms(text: str, names: Mapping[str, object], *, where: str = "formula", limit: int = 400) -> list:
    """The additive terms of a formula, as CasADi expressions whose sum is ``parse(text)``:
    sums split, signs carried in, products and quotients distributed over sums
    (``a*(b + c)/d`` → ``a*b/d``, ``a*c/d``) as long as one product gives at most ``limit``
    terms. A residual is sized against them: terms that cancel in it show its scale.

    Long chains (``a + b + c + …``, thousands of terms) are walked in loops, not recursion,
    as ``parse`` walks them; ``parse(text)`` runs first, so the limits and messages are its own."""
    parse(text, names, where=where)
    tree = _syntax_tree(text, where)
    walker = _Walker(text, names, where)
    return [walker.visit(node) for node in _expand(tree.body, limit)]


def _spine(node: ast.AST, ops: tuple) -> tuple[ast.AST, list]:
    """A left-nested chain ``((a op b) op c) …`` as ``a, [(op, b), (op, c), …]`` (in a loop)."""
    links = []
    while isinstance(node, ast.BinOp) and isinstance(node.op, ops):
        links.append((node.op, node.right))
        node = node.left
    return node, links[::-1]


def _negated(node: ast.AST) -> ast.AST:
    return node.operand if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub) \
        else ast.UnaryOp(ast.USub(), node)


def _expand(node: ast.AST, limit: int) -> list[ast.AST]:
    """``terms``' syntax trees: recursion only into nested operands (at most MAX_DEPTH deep)."""
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        inner = _expand(node.operand, limit)
        return inner if isinstance(node.op, ast.UAdd) else [_negated(t) for t in inner]
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add | ast.Sub):
        first, links = _spine(node, (ast.Add, ast.Sub))
        out = _expand(first, limit)
        for op, right in links:
            part = _expand(right, limit)
            out += part if isinstance(op, ast.Add) else [_negated(t) for t in part]
        return out
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult | ast.Div):
        first, links = _spine(node, (ast.Mult, ast.Div))
        out = _expand(first, limit)
        for op, right in links:
            if isinstance(op, ast.Div):
                out = [ast.BinOp(t, ast.Div(), right) for t in out]
                continue
            part = _expand(right, limit)
            if len(out) * len(part) > limit:
                return [node]
            out = [ast.BinOp(a, ast.Mult(), b) for a in out for b in part]
        return out
    return [node]


def _short(text: str, limit: int = 60) -> str:
    """``text`` quoted, shortened to ``limit`` characters for messages."""
    text = text.strip()
    return repr(text) if len(text) <= limit else repr(text[: limit - 3] + "...")


def _syntax_tree(text: str, where: str) -> ast.Expression:
    """``ast.parse`` with its failures (syntax, too deep for Python's parser, huge integer
    literals) turned into ExpressionErrors."""
    try:
        return ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        detail = f" ({exc.msg})" if exc.msg and exc.msg != "invalid syntax" else ""
        raise ExpressionError(
            f"cannot read formula {_short(text)}: syntax error near column {exc.offset}{detail}",
            where=where) from None
    except (RecursionError, MemoryError):
        raise ExpressionError(
            f"the formula {_short(text)} is too deeply nested or too long a chain of operators "
            f"to read (accepted: {MAX_DEPTH} levels of signs, parentheses and calls inside each "
            "other, about 2000 terms in a row); simplify it or split it with [parameters]",
            where=where) from None
    except ValueError as exc:  # e.g. an integer literal of thousands of digits
        raise ExpressionError(f"cannot read formula {_short(text)}: {exc}", where=where) from None


def _depth(root: ast.AST) -> int:
    """The nesting depth of a syntax tree (iterative: deep trees must not exhaust the stack)."""
    deepest, stack = 0, [(root, 1)]
    while stack:
        node, d = stack.pop()
        deepest = max(deepest, d)
        if d > MAX_DEPTH:
            return d
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.expr_context | ast.operator | ast.unaryop):
                continue
            # a + b + c + ... is a chain, not nesting: the walker folds it in a loop
            chained = isinstance(node, ast.BinOp) and child is node.left and _chains(node)
            stack.append((child, d if chained else d + 1))
    return deepest


def _chains(node: ast.AST) -> bool:
    """Whether ``node`` continues a left-to-right chain of + - * / (walked in a loop)."""
    return isinstance(node, ast.BinOp) and not isinstance(node.op, ast.Pow)


def free_names(text: str) -> set[str]:
    """The bare names a formula string mentions (without checking them)."""
    return set(_free_names(text))


@functools.lru_cache(maxsize=4096)
def _free_names(text: str) -> frozenset[str]:
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, RecursionError, MemoryError, ValueError):
        return frozenset()
    return frozenset(node.id for node in ast.walk(tree) if isinstance(node, ast.Name))


class _Walker:
    def __init__(self, text: str, names: Mapping[str, object], where: str):
        self.text = text
        self.names = names
        self.where = where

    def fail(self, message: str):
        raise ExpressionError(f"in formula {_short(self.text)}: {message}", where=self.where)

    def source(self, node) -> str:
        """The piece of the formula that ``node`` spells, quoted (for messages)."""
        return _short(ast.get_source_segment(self.text.strip(), node) or "?", 30)

    def number(self, value, what: str) -> float:
        """A number the formula holds or works out: finite and at most MAX_MAGNITUDE."""
        if not math.isfinite(value) or abs(value) > MAX_MAGNITUDE:
            self.fail(f"{what} is too large (beyond {MAX_MAGNITUDE:g} in size, or not finite): "
                      "numbers this big overflow in the equations of motion; rescale the units")
        return value

    def binary(self, node, op, left, right):
        """``op(left, right)``; worked out here when both are numbers, and checked then."""
        if not (isinstance(left, float) and isinstance(right, float)):
            return op(left, right)
        what = f"the constant part {self.source(node)}"
        try:
            value = op(left, right)
        except OverflowError:
            value = math.inf
        except ZeroDivisionError:
            self.fail(f"{what} divides by zero")
        if isinstance(value, complex):
            self.fail(f"{what} is not a real number (a negative number to a fractional power)")
        return self.number(value, what)

    def visit(self, node):
        if isinstance(node, ast.Constant):
            if isinstance(node.value, bool) or not isinstance(node.value, int | float):
                self.fail(f"the literal {node.value!r} is not a number")
            try:
                value = float(node.value)
            except OverflowError:
                value = math.inf
            return self.number(value, f"the number {self.source(node)}")
        if isinstance(node, ast.Name):
            if node.id in self.names:
                return self.names[node.id]
            if node.id in CONSTANTS:
                return CONSTANTS[node.id]
            if node.id in FUNCTIONS:
                self.fail(f"'{node.id}' is a function; call it as {node.id}(...)")
            known = listed(sorted(self.names)) or "(none)"
            close = difflib.get_close_matches(node.id, list(self.names), n=1)
            self.fail(f"unknown name '{node.id}' (known names: {known})"
                      + (f"; did you mean '{close[0]}'?" if close else ""))
        if isinstance(node, ast.BinOp):
            op = _BINARY.get(type(node.op))
            if op is None:
                hint = _FORBIDDEN_HINTS.get(type(node.op), f"operator {type(node.op).__name__}")
                self.fail(f"{hint} is not allowed" if hint.startswith("operator") else hint)
            chain = [node]  # a + b + c + ...: folded in a loop, not by recursion
            while _chains(chain[-1]) and _chains(chain[-1].left):
                chain.append(chain[-1].left)
            for link in chain[1:]:
                if type(link.op) not in _BINARY:
                    self.visit(link)  # refuses it
            value = self.visit(chain[-1].left)
            for link in reversed(chain):
                value = self.binary(link, _BINARY[type(link.op)], value, self.visit(link.right))
            return value
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
            args = [self.visit(a) for a in node.args]
            try:
                value = FUNCTIONS[name](*args)
            except (OverflowError, ValueError, ZeroDivisionError):
                value = math.nan
            if all(isinstance(a, float) for a in args):  # a constant: check it
                try:
                    value = float(value)
                except (TypeError, ValueError, RuntimeError):
                    return value
                what = self.source(node)
                if not math.isfinite(value):
                    self.fail(f"{what} is not a finite number (outside the function's domain, "
                              "or too large)")
                return self.number(value, what)
            return value
        hint = _FORBIDDEN_HINTS.get(type(node))
        self.fail(hint or f"the construct {type(node).__name__} is not allowed")


# --- labels of a lifted system: its Number tokens (constrained.model.lifting) filled in ------------

_TOKEN = re.compile("⟦([0-9]+)⟧")


def fill(text: str, values: np.ndarray) -> str:
    """``text`` with each Number token replaced by its value (formatted ``:g``, as a label
    formats a number)."""
    if "⟦" not in text:
        return text
    return _TOKEN.sub(lambda m: f"{values[int(m.group(1))]:g}", text)


def fill_all(texts: list[str], values: np.ndarray) -> list[str]:
    """``[fill(text, values) for text in texts]`` in one pass over them all (a large model's
    labels), each distinct value formatted once."""
    joined = "\0".join(texts)
    if joined.count("\0") != len(texts) - 1:  # (a text with the separator in it)
        return [fill(text, values) for text in texts]
    parts = _TOKEN.split(joined)  # (text, a token's index, text, …, text)
    picked = list(map(np.asarray(values, float).tolist().__getitem__, map(int, parts[1::2])))
    formatted = {v: f"{v:g}" for v in dict.fromkeys(picked)}  # (equal values: the first one's text)
    parts[1::2] = map(formatted.__getitem__, picked)
    return "".join(parts).split("\0") if texts else []


@contextlib.contextmanager
def shown(values: np.ndarray):
    """Inside the block (the Structure's build, which reads a lifted system), an InputError's
    place and reason show the numbers the scene wrote, not their tokens."""
    try:
        yield
    except InputError as exc:
        if type(exc) not in (InputError, ExpressionError, InconsistentStateError) or "⟦" not in str(exc):
            raise
        where = fill(exc.where, values) if exc.where else None
        raise type(exc)(fill(exc.reason, values), where=where) from None
