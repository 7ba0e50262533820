"""Parameters and definitions: the named numbers of a system and the formulas built on them.

A System's ``parameters`` are named numbers (``m1 = 1.0``, ``l1 = 0.5``); its ``definitions``
are named formulas in parameters and other definitions (``I1 = "m1*l1**2/3"``). A definition
may use any parameter and any other definition, in any order, as long as no definition
depends on itself (a cycle is refused, naming it). Each is read in two ways:

- numeric (``values``): every name a float. Initial positions, velocities and masses given by
  formulas, and the analyses' own formulas, use these.
- symbolic (``symbolic``): every parameter a CasADi SX symbol named after it, stacked in the
  order of ``parameters`` into the vector ``p``; each definition an SX expression of them.
  The Model's parametric Functions take ``p`` as their last input, so that new values of the
  parameters never rebuild anything.
"""

from __future__ import annotations

import functools
import keyword
import math
from collections.abc import Mapping

import casadi as ca

from ..codegen.fast_call import FastCall
from ..errors import ExpressionError, InputError
from . import expressions

#: Names a parameter or a definition may not take (they mean something in formulas).
RESERVED_NAMES = frozenset(
    {"t", "x", "y", "z", "r", "vx", "vy", "vz"} | set(expressions.FUNCTIONS) | set(expressions.CONSTANTS)
)


def check_value(name: str, value, where: str = "parameters") -> float:
    """A parameter's value as a float: a finite number, or an InputError naming it."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InputError(f"the parameter '{name}' must be a finite number, got {value!r}",
                         where=f"{where}.{name}")
    return float(value)


def check_name(name, where: str, *, taken: Mapping | set = frozenset(), what: str = "parameter") -> str:
    """A parameter's or a definition's name: a plain identifier that means nothing else."""
    if not isinstance(name, str) or not name.isidentifier():
        raise InputError(f"{what} name {name!r} must be a plain identifier (letters, digits, "
                         "underscore; not starting with a digit)", where=where)
    if keyword.iskeyword(name):  # formulas are read with Python's syntax: 'lambda' cannot be a name there
        raise InputError(f"the {what} name '{name}' is a keyword of the formula syntax (Python's), so no "
                         f"formula could use it; choose another, e.g. '{name}_' or '{name}1'", where=where)
    if name == "e":
        raise InputError(f"the {what} name 'e' is taken: in formulas e is Euler's number 2.718...; a "
                         "coefficient of restitution can be a parameter named e.g. 'e_r' (then "
                         "restitution = \"e_r\" in the one-sided constraint), or be written there as a "
                         "number", where=where)
    if name in RESERVED_NAMES:
        raise InputError(f"the {what} name '{name}' is taken (it already means something in "
                         "formulas); choose another", where=where)
    if name in taken:
        raise InputError(f"the {what} name '{name}' is used twice (as a parameter and as a "
                         "definition); rename one", where=where)
    return name


#: The longest chain of definitions each using the next (as ``expressions.MAX_DEPTH`` for the
#: nesting inside one formula): a model's expressions, and the time to build them, grow with it.
MAX_DEFINITION_DEPTH = 1000


def order(definitions: Mapping[str, object], where: str = "definitions") -> list[str]:
    """The definitions' names ordered so that each comes after the definitions it uses.

    Raises InputError naming the cycle (``a -> b -> a``) when a definition depends on itself,
    or the definition at the end of a chain more than MAX_DEFINITION_DEPTH deep.
    """
    try:
        return list(_order(tuple(definitions.items()), where))
    except TypeError:  # an unhashable formula: order it without the memo
        return _order.__wrapped__(tuple(definitions.items()), where)


@functools.lru_cache(maxsize=256)
def _order(items: tuple, where: str) -> tuple[str, ...]:
    definitions = dict(items)
    names = set(definitions)
    uses = {name: (expressions.free_names(text) & names) if isinstance(text, str) else set()
            for name, text in definitions.items()}
    done: list[str] = []
    state: dict[str, int] = {}  # 1: being visited, 2: done
    depth: dict[str, int] = {}  # the longest chain of definitions below each, itself included

    for root in definitions:  # depth first, with a stack of its own: a chain may be thousands long
        if state.get(root) == 2:
            continue
        state[root], path, stack = 1, [root], [iter(sorted(uses[root]))]
        while stack:
            other = next(stack[-1], None)
            if other is None:  # every definition it uses is placed: place it
                stack.pop()
                name = path.pop()
                state[name] = 2
                depth[name] = 1 + max((depth[u] for u in uses[name]), default=0)
                if depth[name] > MAX_DEFINITION_DEPTH:
                    raise InputError(
                        f"the definitions nest more than {MAX_DEFINITION_DEPTH} deep: {name} heads a chain "
                        f"of {depth[name]} definitions, each using the next; write some of them as "
                        "formulas of the parameters", where=f"{where}.{name}")
                done.append(name)
            elif state.get(other) == 1:
                cycle = path[path.index(other):] + [other]
                raise InputError(
                    f"the definitions form a cycle: {' -> '.join(cycle)}; a definition may use "
                    "parameters and other definitions, but never (through others) itself",
                    where=f"{where}.{cycle[0]}")
            elif state.get(other) != 2:
                state[other] = 1
                path.append(other)
                stack.append(iter(sorted(uses[other])))
    return tuple(done)


def values(parameters: Mapping[str, float], definitions: Mapping[str, object],
           where: str = "definitions") -> dict[str, float]:
    """Every parameter and definition as a number (definitions evaluated in dependency order)."""
    out = dict(parameters)
    for name in order(definitions, where):
        out[name] = evaluate(definitions[name], out, f"{where}.{name}")
    return out


@functools.lru_cache(maxsize=4096)
def _numeric(formula: str, used: tuple[str, ...]) -> FastCall | None:
    """The formula as a Function of the names it uses (parsed once; a new set of values is
    then one call, not a parse), or None when it does not parse (``evaluate`` then raises
    with the place named)."""
    symbols = [ca.SX.sym(name) for name in used]
    try:
        expr = expressions.parse(formula, dict(zip(used, symbols, strict=True)), where="")
    except (ExpressionError, InputError):
        return None
    if not isinstance(expr, ca.SX):
        expr = ca.SX(expr)
    if expr.numel() != 1:
        return None
    return FastCall(ca.Function("formula", [ca.vertcat(*symbols) if symbols else ca.SX(0, 1)], [expr]))


def evaluate(formula, names: Mapping[str, float], where: str) -> float:
    """A number, or a formula in the given names (parameters, definitions), as a float."""
    function = None
    if isinstance(formula, str):
        used = tuple(sorted(n for n in expressions.free_names(formula) if n in names))
        function = _numeric(formula, used)
    if function is not None:
        value = float(function([float(names[n]) for n in used])[0][0])
        if math.isfinite(value):
            return value
    value = expressions.parse(formula, names, where=where)
    try:
        value = float(value)
    except (TypeError, ValueError, RuntimeError):
        raise ExpressionError(f"the formula {formula!r} does not give a number from the "
                              "parameters and definitions alone", where=where) from None
    if not math.isfinite(value):
        raise ExpressionError(f"the formula {formula!r} is not finite ({value!r}) for the "
                              "parameters' values", where=where)
    return value


def symbolic(parameters: Mapping[str, float], definitions: Mapping[str, object],
             where: str = "definitions") -> tuple[ca.SX, dict]:
    """``(p, names)``: ``p`` stacks one SX symbol per parameter (named after it, in the order
    of ``parameters``); ``names`` maps each parameter to its symbol and each definition to its
    SX expression (or a float when it uses no parameter)."""
    symbols = [ca.SX.sym(name) for name in parameters]
    p = ca.vertcat(*symbols) if symbols else ca.SX(0, 1)
    names: dict = dict(zip(parameters, symbols, strict=True))
    for name in order(definitions, where):
        names[name] = expressions.parse(definitions[name], names, where=f"{where}.{name}")
    return p, names
