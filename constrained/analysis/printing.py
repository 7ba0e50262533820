"""Readable printouts of the reduced route's equations: T, V, L, the momenta and Lagrange's
equations in the names of the coordinates, their rates and the scene's parameters.

- ``describe``: the printout (text, or LaTeX through SymPy, the ``pretty`` extra);
- ``pretty``: one SX expression as compact infix text (simplified by SymPy when installed);
- ``to_sympy``: one SX expression as a SymPy expression, to hand on (``sympy.latex``, solving);
- ``symbolic_reduced``: a ReducedModel's expressions with the parameters as named symbols.
"""

from __future__ import annotations

import casadi as ca

from ..errors import InputError
from ..extras import install_hint
from ..run.reduced import ReducedModel

__all__ = ["describe", "pretty", "symbolic_reduced", "to_sympy"]

_BINARY = {
    ca.OP_ADD: ("+", 1), ca.OP_SUB: ("-", 1), ca.OP_MUL: ("*", 2), ca.OP_DIV: ("/", 2),
}
_UNARY = {
    ca.OP_SIN: "sin", ca.OP_COS: "cos", ca.OP_TAN: "tan", ca.OP_EXP: "exp", ca.OP_LOG: "log",
    ca.OP_SQRT: "sqrt", ca.OP_ASIN: "asin", ca.OP_ACOS: "acos", ca.OP_ATAN: "atan",
    ca.OP_SINH: "sinh", ca.OP_COSH: "cosh", ca.OP_TANH: "tanh", ca.OP_FABS: "abs",
}


def pretty(expr, digits: int = 6, *, simplify: bool = True, latex: bool = False) -> str:
    """A compact infix string of a scalar SX expression (``sq(x)`` → ``x^2``).

    With SymPy installed (the ``pretty`` extra) and ``simplify``, the expression is
    expanded and trigonometrically simplified first (``cos(a)cos(b) + sin(a)sin(b)`` →
    ``cos(a - b)``); without it, CasADi's graph is printed as it is. ``latex``: LaTeX
    (through SymPy, which it needs).
    """
    expr = ca.SX(expr)
    if expr.numel() != 1:
        parts = [pretty(expr[k], digits, simplify=simplify, latex=latex) for k in range(expr.numel())]
        return (r"\left[" + ", ".join(parts) + r"\right]") if latex else "[" + ", ".join(parts) + "]"
    if simplify or latex:
        sympy = _sympy(required=latex)
        if sympy is not None:
            converted = _converted(expr, sympy, {}, simplify=simplify)
            if converted is None:
                return _too_long(expr) if latex else _plain(expr, digits)
            if converted.atoms(sympy.Float):
                converted = converted.evalf(digits)
                converted = converted.xreplace({f: sympy.Integer(int(f)) for f in
                                                converted.atoms(sympy.Float) if float(f).is_integer()})
            return sympy.latex(converted) if latex else str(converted).replace("**", "^")
    return _plain(expr, digits)


#: SymPy takes expressions up to this many CasADi operations, and simplifies their expansion
#: (``trigsimp``) up to this many SymPy operations: its time grows steeply with the size (a
#: 3-link chain's equation of 732 operations took 5 s, a 50-link chain's T did not finish in
#: 10 minutes). Beyond, the expression is printed as CasADi builds it.
SYMPY_OPERATIONS = 600
TRIGSIMP_OPERATIONS = 250
EXPANDED_TERMS = 2000
#: Expressions whose printed form would exceed this many characters are summarized instead.
PRINT_CHARS = 20_000


def _operations(expr) -> int:
    """The number of operations in the SX graph of a scalar ``expr`` (shared nodes once)."""
    leaves = ca.symvar(expr)
    if not leaves:
        return 1
    return int(ca.Function("size", [ca.vertcat(*leaves)], [expr]).n_instructions())


def _converted(expr, sympy, names: dict, *, simplify: bool = True):
    """``expr`` as an expanded SymPy expression, trigonometrically simplified when small enough;
    None when it is too large for SymPy within a bounded time (``SYMPY_OPERATIONS``)."""
    if _operations(expr) > SYMPY_OPERATIONS or _expanded_terms(expr, EXPANDED_TERMS) > EXPANDED_TERMS:
        return None
    try:
        converted = _to_sympy(expr, sympy, names)
        if not simplify:
            return converted
        expanded = sympy.expand(converted)
        return sympy.trigsimp(expanded) if sympy.count_ops(expanded) <= TRIGSIMP_OPERATIONS else expanded
    except RecursionError:
        return None


def _too_long(expr) -> str:
    return f"(an expression of {_operations(expr)} operations, too long to print)"


def _fold(expr, leaf, combine, limit: int) -> int:
    """A count over the graph of ``expr`` bottom-up (``leaf(e)``, ``combine(e, counts of its
    operands)``), each node once, without recursion, capped at ``limit + 1``."""
    counts: dict[int, int] = {}
    stack = [(expr, False)]
    while stack:
        e, ready = stack.pop()
        key = e.element_hash()
        if key in counts:
            continue
        deps = [] if e.is_symbolic() or e.is_constant() else [e.dep(k) for k in range(e.n_dep())]
        if not deps:
            counts[key] = min(limit + 1, leaf(e))
        elif ready:
            counts[key] = min(limit + 1, combine(e, [counts[d.element_hash()] for d in deps]))
        else:
            stack.append((e, True))
            stack.extend((d, False) for d in deps if d.element_hash() not in counts)
    return counts[expr.element_hash()]


def _tree_size(expr, limit: int) -> int:
    """The nodes of ``expr`` written out as a tree (a shared node once per use): a graph of a few
    thousand shared nodes can print to millions of characters."""
    return _fold(expr, lambda e: 1, lambda e, deps: 1 + sum(deps), limit)


def _expanded_terms(expr, limit: int) -> int:
    """An estimate of the number of terms of ``expr`` expanded (sums add, products multiply, an
    integer power n raises to n, a function is one term): SymPy's ``expand`` cannot be stopped,
    and (x² + x)² nested 60 times would not end."""

    def combine(e, deps):
        op = e.op()
        if op in (ca.OP_ADD, ca.OP_SUB):
            return deps[0] + deps[1]
        if op == ca.OP_MUL:
            return deps[0] * deps[1]
        if op == ca.OP_SQ:
            return deps[0] ** 2
        if op == ca.OP_CONSTPOW and e.dep(1).is_constant() and float(e.dep(1)) > 0:
            return deps[0] ** min(int(float(e.dep(1))) + 1, 64)
        return deps[0] if op in (ca.OP_NEG, ca.OP_TWICE, ca.OP_DIV) else 1

    return _fold(expr, lambda e: 1, combine, limit)


def _plain(expr, digits: int) -> str:
    """CasADi's graph as infix text, or a summary when it is too long (or too deep) to print."""
    if _tree_size(expr, PRINT_CHARS) > PRINT_CHARS:
        return _too_long(expr)
    try:
        text = _pp(expr, digits)[0]
    except RecursionError:
        return _too_long(expr)
    return text if len(text) <= PRINT_CHARS else _too_long(expr)


def _sympy(*, required: bool):
    """The sympy module, or None when it is not installed (InputError when ``required``)."""
    try:
        import sympy
    except ImportError:
        if required:
            raise InputError(f"LaTeX output needs SymPy: install the 'pretty' extra "
                             f"({install_hint('pretty')}) or leave LaTeX off") from None
        return None
    return sympy


def to_sympy(expr):
    """A scalar CasADi SX expression as a SymPy expression (symbols keep their names: the
    coordinates, their rates and the parameters). Needs SymPy (the ``pretty`` extra)."""
    expr = ca.SX(expr)
    if expr.numel() != 1:
        raise InputError(f"to_sympy takes a scalar expression, got {expr.numel()} entries")
    return _to_sympy(expr, _sympy(required=True), {})


def _to_sympy(e, sympy, names: dict):
    """The SX graph of ``e`` as a SymPy expression (same op-codes as ``_pp``)."""
    if e.is_symbolic():
        return names.setdefault(e.name(), sympy.Symbol(e.name(), real=True))
    if e.is_constant():
        v = float(e)
        return sympy.Integer(int(v)) if v.is_integer() and abs(v) < 1e15 else sympy.Float(v)
    op = e.op()
    a = _to_sympy(e.dep(0), sympy, names)
    if op == ca.OP_NEG:
        return -a
    if op == ca.OP_SQ:
        return a**2
    if op == ca.OP_TWICE:
        return 2 * a
    if op == ca.OP_INV:
        return 1 / a
    if op in _UNARY:
        return getattr(sympy, {"abs": "Abs"}.get(_UNARY[op], _UNARY[op]))(a)
    b = _to_sympy(e.dep(1), sympy, names)
    if op in (ca.OP_POW, ca.OP_CONSTPOW):
        return a**b
    if op == ca.OP_ATAN2:
        return sympy.atan2(a, b)
    ops = {ca.OP_ADD: a + b, ca.OP_SUB: a - b, ca.OP_MUL: a * b} if op != ca.OP_DIV else {op: a / b}
    if op in ops:
        return ops[op]
    return sympy.sympify(str(e))


def _num(value: float, digits: int) -> str:
    if float(value).is_integer() and abs(value) < 1e15:
        return str(int(value))
    return f"{value:.{digits}g}"


def _pp(e, digits: int) -> tuple[str, int]:
    """(text, precedence): 3 atom, 2 product, 1 sum."""
    if e.is_symbolic():
        return e.name(), 3
    if e.is_constant():
        v = float(e)
        return (_num(v, digits), 3 if v >= 0 else 1)
    op = e.op()
    if op == ca.OP_NEG:
        s, p = _pp(e.dep(0), digits)
        return "-" + (s if p >= 2 else f"({s})"), 1
    if op == ca.OP_SQ:
        s, p = _pp(e.dep(0), digits)
        return (s if p >= 3 else f"({s})") + "^2", 3
    if op == ca.OP_TWICE:
        s, p = _pp(e.dep(0), digits)
        return "2*" + (s if p >= 2 else f"({s})"), 2
    if op == ca.OP_POW or op == ca.OP_CONSTPOW:
        a, pa = _pp(e.dep(0), digits)
        b, pb = _pp(e.dep(1), digits)
        return (a if pa >= 3 else f"({a})") + "^" + (b if pb >= 3 else f"({b})"), 3
    if op in _UNARY:
        return f"{_UNARY[op]}({_pp(e.dep(0), digits)[0]})", 3
    if op in _BINARY:
        sym, prec = _BINARY[op]
        a, pa = _pp(e.dep(0), digits)
        b, pb = _pp(e.dep(1), digits)
        if pa < prec:
            a = f"({a})"
        if pb < prec or (pb == prec and sym in "-/"):
            b = f"({b})"
        if sym == "+" and b.startswith("-"):
            return f"{a} - {b[1:]}" if pb >= 2 else f"{a} + ({b})", 1
        return (f"{a} {sym} {b}" if prec == 1 else f"{a}*{b}" if sym == "*" else f"{a}/{b}"), prec
    return str(e), 3


def describe(scene_or_model, *, parameters: dict | None = None, max_chars: int = 4000,
             latex: bool = False) -> str:
    """T, V, L, the conjugate momenta and Lagrange's equations ``M q̈ = rhs`` (with velocity
    constraints: ``M q̈ = rhs + Ãᵀμ`` and the constraints in q, multipliers mu1 …) as text, in the
    names of the coordinates, their rates and the scene's parameters (``m1``, ``l1``, ``g``:
    their values are not substituted). ``latex``: LaTeX lines (needs SymPy, the ``pretty``
    extra)."""
    if not isinstance(scene_or_model, ReducedModel):
        scene_or_model = ReducedModel.from_scene(scene_or_model, parameters=parameters)
    rm = symbolic_reduced(scene_or_model)
    if latex:
        return _describe_latex(rm)
    ex = rm.expressions
    E, rows = _equations(rm)
    named = [(name, ex[name]) for name in ("T", "V", "U", "R", "L")
             if name not in ("U", "R") or not ca.SX(ex[name]).is_zero()]
    named += [(f"p_{c}", ex["p"][j]) for j, c in enumerate(rm.coordinates)]
    named += [(f"equation for {c}:", E[j]) for j, c in enumerate(rm.coordinates)]
    named += [(f"velocity constraint {k + 1} (multiplier mu{k + 1}):", rows[k]) for k in range(rows.numel())]
    text = f"coordinates: {', '.join(rm.coordinates)}" + ("  (rheonomic map)" if rm.rheonomic else "")
    for name, e in named:  # printed until max_chars: the lines past it are not simplified at all
        if len(text) > max_chars:
            break
        text += f"\n{name} {pretty(e)} = 0" if name.endswith(":") else f"\n{name} = {pretty(e)}"
    if len(text) > max_chars:
        text = text[:max_chars] + "\n… (truncated)"
    return text


def _equations(rm: ReducedModel) -> tuple:
    """(M q̈ − rhs − Ãᵀμ, the velocity rows c(q, q̇, t)): Lagrange's equations, or with velocity
    constraints the Lagrange–d'Alembert ones, μ the symbols mu1, mu2 …"""
    rows = rm.expressions["velocity_rows"]
    mu = ca.vertcat(*[ca.SX.sym(f"mu{k + 1}") for k in range(rows.numel())])
    E = ca.mtimes(rm.expressions["M"], rm.q_ddot) - rm.expressions["rhs"]
    return (E - ca.mtimes(ca.jacobian(rows, rm.q_dot).T, mu) if rows.numel() else E), rows


def symbolic_reduced(rm: ReducedModel) -> ReducedModel:
    """The same reduced model with the system's parameters and definitions as SX symbols and
    expressions named after them (``expressions`` only: no Functions, no checks)."""
    if rm.symbolic_parameters:
        return rm
    system = rm.system
    extra = {k: v for k, v in rm.parameters.items()
             if k not in system.parameters and k not in system.definitions}
    return ReducedModel(system, rm.coordinates, rm.map, parameters=extra, t0=rm.t0, check=False,
                        symbolic_parameters=True)


def latex_printer(rm: ReducedModel):
    """``(tex, name)``: ``tex(expr)`` an expression of ``rm`` as LaTeX (q̇ as \\dot q, q̈ as \\ddot q,
    expanded and trigonometrically simplified), ``name(c)`` a coordinate's LaTeX name. Needs SymPy."""
    sympy = _sympy(required=True)
    names: dict = {}
    for c in rm.coordinates:
        base = sympy.latex(sympy.Symbol(c))
        names[f"{c}_dot"] = sympy.Symbol(rf"\dot{{{base}}}", real=True)
        names[f"{c}_ddot"] = sympy.Symbol(rf"\ddot{{{base}}}", real=True)

    def tex(e) -> str:
        s = _converted(ca.SX(e), sympy, names)
        if s is None:
            return rf"\text{{{_too_long(ca.SX(e))}}}"
        s = s.xreplace({f: sympy.Integer(int(f)) for f in s.atoms(sympy.Float) if float(f).is_integer()})
        return sympy.latex(s)

    return tex, lambda c: sympy.latex(sympy.Symbol(c))


def _describe_latex(rm: ReducedModel) -> str:
    """describe's lines as LaTeX: q̇ as \\dot q, q̈ as \\ddot q."""
    tex, name = latex_printer(rm)
    ex = rm.expressions
    lines = []
    for key in ("T", "V", "U", "R", "L"):
        if key in ("U", "R") and ca.SX(ex[key]).is_zero():
            continue
        lines.append(f"{key} = {tex(ex[key])}")
    for j, c in enumerate(rm.coordinates):
        lines.append(f"p_{{{name(c)}}} = {tex(ex['p'][j])}")
    E, rows = _equations(rm)
    for j in range(len(rm.coordinates)):
        lines.append(f"{tex(E[j])} = 0")
    lines += [f"{tex(rows[k])} = 0" for k in range(rows.numel())]
    return "\n".join(lines)
