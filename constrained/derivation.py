"""Derivation checks on the reduced route: hand-derived equations, conservation laws, printouts.

- ``check_equations``: is a candidate equation of motion implied by Lagrange's equations?
  At random states (q, q̇, t) the accelerations q̈ come from ``M q̈ = rhs``; a right
  equation (any nonzero multiple or combination of Lagrange's equations) then vanishes,
  relative to the size of its terms.
- ``conservation``: conjugate momenta ``p = ∂L/∂q̇``, cyclic coordinates (``∂L/∂q_j = 0``
  and no non-conservative generalized force on q_j), the Hamiltonian ``H = p·q̇ − L`` and
  whether it equals ``T + V``; their drift along a reduced trajectory.
- ``describe``: a readable printout of T, V, L and the equations for small systems.
"""

from __future__ import annotations

import ast
from collections.abc import Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from . import expressions
from .errors import InputError
from .reduced import ReducedModel

__all__ = [
    "Conservation",
    "EquationCheck",
    "check_equations",
    "conservation",
    "describe",
    "pretty",
]

#: A candidate equation is right when |residual| ≤ EQUATION_RTOL × (sum of |terms|) everywhere.
EQUATION_RTOL = 1e-8
#: |∂L/∂q_j| below this × the scale of the Lagrangian's terms counts as zero (cyclic).
CYCLIC_RTOL = 1e-10


def _reduced(scene_or_model, parameters=None) -> ReducedModel:
    if isinstance(scene_or_model, ReducedModel):
        return scene_or_model
    return ReducedModel.from_scene(scene_or_model, parameters=parameters)


# --- hand-derivation checks --------------------------------------------------------------------


@dataclass
class EquationCheck:
    """The verdict on one candidate equation.

    ``residual`` is the largest |lhs − rhs| found with q̈ from Lagrange's equations,
    ``relative_residual`` the largest ratio of it to the sum of the sizes of the terms.
    """

    equation: str
    ok: bool
    residual: float
    relative_residual: float
    message: str
    state: dict = field(default_factory=dict)

    def __bool__(self) -> bool:
        return self.ok


def _terms(node: ast.AST, limit: int = 400) -> list[ast.AST]:
    """Additive terms of an expression tree, distributing products and quotients over sums."""
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add | ast.Sub):
        right = _terms(node.right, limit)
        if isinstance(node.op, ast.Sub):
            right = [ast.UnaryOp(ast.USub(), r) for r in right]
        return _terms(node.left, limit) + right
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        inner = _terms(node.operand, limit)
        return inner if isinstance(node.op, ast.UAdd) else [ast.UnaryOp(ast.USub(), t) for t in inner]
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult):
        a, b = _terms(node.left, limit), _terms(node.right, limit)
        if len(a) * len(b) <= limit:
            return [ast.BinOp(x, ast.Mult(), y) for x in a for y in b]
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
        return [ast.BinOp(x, ast.Div(), node.right) for x in _terms(node.left, limit)]
    return [node]


def _split(text: str, where: str) -> tuple[str, str | None]:
    if not isinstance(text, str) or not text.strip():
        raise InputError(f"an equation must be a non-empty string, got {text!r}", where=where)
    stripped = text.replace("==", "=")
    parts = stripped.split("=")
    if len(parts) > 2:
        raise InputError(f"equation {text!r} has more than one '='", where=where)
    if len(parts) == 2:
        if not parts[0].strip() or not parts[1].strip():
            raise InputError(f"equation {text!r} has an empty side", where=where)
        return parts[0].strip(), parts[1].strip()
    return parts[0].strip(), None


def check_equations(
    scene_or_model,
    equations: Sequence[str] | str,
    *,
    samples: int = 40,
    seed: int = 1,
    rtol: float = EQUATION_RTOL,
    parameters: dict | None = None,
) -> list[EquationCheck]:
    """Check hand-derived equations of motion against Lagrange's equations.

    Each equation is ``"lhs = rhs"`` or an expression (meaning ``= 0``) in the coordinates,
    ``<q>_dot``, ``<q>_ddot``, ``t`` and the parameters. It is right when it holds whenever
    Lagrange's equations do: at ``samples`` random states (q, q̇, t) with q̈ solved from
    ``M q̈ = rhs``, ``|lhs − rhs| ≤ rtol × Σ|terms|`` (terms after expanding sums). An
    equation without accelerations that holds everywhere is an identity, not an equation
    of motion, and is reported as not ok. Unknown names raise InputError.
    """
    rm = _reduced(scene_or_model, parameters)
    if isinstance(equations, str):
        equations = [equations]
    names = dict(rm.names)
    q, qd, qdd, t = rm.q, rm.q_dot, rm.q_ddot, rm.t
    parsed = []
    for k, text in enumerate(equations):
        where = f"equation {k + 1}"
        lhs, rhs = _split(text, where)
        node = ast.parse(lhs.strip(), mode="eval").body if _syntax_ok(lhs) else None
        expr = expressions.parse(lhs, names, where=where)
        terms_src = [ast.unparse(n) for n in _terms(node)] if node is not None else [lhs]
        if rhs is not None:
            expr = expr - expressions.parse(rhs, names, where=where)
            node_r = ast.parse(rhs.strip(), mode="eval").body
            terms_src += [ast.unparse(n) for n in _terms(node_r)]
        terms = [ca.SX(expressions.parse(s, names, where=where)) for s in terms_src]
        parsed.append((text, ca.SX(expr), terms))
    Q, Qd, Ts = rm.sample_states(samples, seed)
    Qdd = np.array([np.asarray(rm.acceleration(a, b, c)).ravel() for a, b, c in zip(Q, Qd, Ts, strict=True)])
    out = []
    for k, (text, expr, terms) in enumerate(parsed):
        f = ca.Function("candidate", [q, qd, qdd, t], [expr, ca.vertcat(*terms), ca.gradient(expr, qdd)])
        worst_rel, worst_abs, worst_i, involves_acc = 0.0, 0.0, 0, False
        for i in range(samples):
            e, tv, g = f(Q[i], Qd[i], Qdd[i], Ts[i])
            e = float(e)
            scale = float(np.sum(np.abs(np.asarray(tv)))) or 1.0
            involves_acc = involves_acc or bool(np.any(np.abs(np.asarray(g)) > 0))
            rel = abs(e) / scale if np.isfinite(e) else np.inf
            if rel > worst_rel or not np.isfinite(rel):
                worst_rel, worst_abs, worst_i = rel, abs(e), i
            if not np.isfinite(rel):
                break
        state = {c: float(Q[worst_i][j]) for j, c in enumerate(rm.coordinates)}
        state.update({f"{c}_dot": float(Qd[worst_i][j]) for j, c in enumerate(rm.coordinates)})
        state.update({f"{c}_ddot": float(Qdd[worst_i][j]) for j, c in enumerate(rm.coordinates)})
        state["t"] = float(Ts[worst_i])
        at = ", ".join(f"{n} = {v:.6g}" for n, v in state.items())
        if worst_rel > rtol:
            ok = False
            message = (
                f"equation {k + 1} ({text}) disagrees with Lagrange's equations by {worst_abs:.3g} "
                f"({worst_rel:.3g} of the size of its terms) at {at} (accelerations from "
                "Lagrange's equations)"
            )
        elif not involves_acc:
            ok = False
            message = (
                f"equation {k + 1} ({text}) holds at every sampled state but contains no "
                "acceleration: it is an identity, not an equation of motion"
            )
        else:
            ok = True
            message = (
                f"equation {k + 1} ({text}) holds whenever Lagrange's equations do "
                f"(largest relative residual {worst_rel:.2g} over {samples} random states)"
            )
        out.append(EquationCheck(text, ok, worst_abs, worst_rel, message, state))
    return out


def _syntax_ok(text: str) -> bool:
    try:
        ast.parse(text.strip(), mode="eval")
    except SyntaxError:
        return False
    return True


# --- conservation laws ------------------------------------------------------------------------


@dataclass
class Conservation:
    """Conserved quantities found in a reduced model, and their drift along a trajectory.

    ``cyclic``: coordinates with ∂L/∂q_j = 0 and no non-conservative force on them (their
    momenta p_j are conserved); ``structurally_cyclic``: those whose L does not even mention
    q_j; ``hamiltonian_conserved``: ∂L/∂t = 0 and no non-conservative forces at all;
    ``hamiltonian_is_energy``: H = T + V at the sampled states (not for rheonomic maps or
    velocity-dependent potentials). Drifts (max |Δ| relative to the starting value, or to
    1 when that is zero) are filled in when a trajectory is given.
    """

    coordinates: list[str]
    cyclic: list[str]
    structurally_cyclic: list[str]
    hamiltonian_conserved: bool
    hamiltonian_is_energy: bool
    momenta: dict[str, np.ndarray] = field(default_factory=dict)
    hamiltonian: np.ndarray | None = None
    energy: np.ndarray | None = None
    momentum_drift: dict[str, float] = field(default_factory=dict)
    hamiltonian_drift: float | None = None
    energy_drift: float | None = None

    def summary(self) -> str:
        lines = []
        for c in self.coordinates:
            tag = "cyclic: p conserved" if c in self.cyclic else "not cyclic"
            drift = self.momentum_drift.get(c)
            more = f", drift {drift:.3g}" if drift is not None else ""
            lines.append(f"p_{c} = ∂L/∂{c}_dot  ({tag}{more})")
        h = "conserved" if self.hamiltonian_conserved else "not conserved"
        e = "= T + V" if self.hamiltonian_is_energy else "≠ T + V"
        line = f"H = p·q_dot − L  ({h}; H {e}"
        if self.hamiltonian_drift is not None:
            line += f"; drift {self.hamiltonian_drift:.3g}"
        if self.energy_drift is not None:
            line += f"; T + V drift {self.energy_drift:.3g}"
        lines.append(line + ")")
        return "\n".join(lines)


def _rel_drift(values: np.ndarray) -> float:
    values = np.asarray(values, float)
    if not len(values):
        return 0.0
    ref = abs(values[0]) if values[0] != 0 else 1.0
    return float(np.max(np.abs(values - values[0])) / ref)


def conservation(scene_or_model, trajectory=None, *, samples: int = 20, seed: int = 2,
                 parameters: dict | None = None) -> Conservation:
    """Find cyclic coordinates, decide whether H is conserved and equals T + V; with a
    reduced ``trajectory`` (from ``ReducedModel.solve``) also evaluate p, H, T + V along it."""
    rm = _reduced(scene_or_model, parameters)
    ex = rm.expressions
    L, q, qd, t = ex["L"], rm.q, rm.q_dot, rm.t
    Qs, Qds, Ts = rm.sample_states(samples, seed)
    pieces = ca.Function("pieces", [q, qd, t], [
        ex["dL_dq"], ex["Q"], ca.gradient(ex["T"], q), ca.gradient(ex["V"], q), ca.gradient(ex["U"], q),
        ca.jacobian(L, t), ex["H"], ex["T"] + ex["V"], ex["T"], ex["V"], ex["U"],
    ])
    n = rm.n
    dL = np.zeros((samples, n))
    Qnc = np.zeros((samples, n))
    scale = np.zeros(samples)
    dLdt = np.zeros(samples)
    h_gap = np.zeros(samples)
    for i in range(samples):
        vals = [np.asarray(v).ravel() for v in pieces(Qs[i], Qds[i], Ts[i])]
        dL[i], Qnc[i] = vals[0], vals[1]
        scale[i] = sum(float(np.sum(np.abs(vals[k]))) for k in (2, 3, 4, 8, 9, 10)) or 1.0
        dLdt[i] = float(vals[5][0])
        h_gap[i] = abs(float(vals[6][0]) - float(vals[7][0])) / scale[i]
    cyclic, structural = [], []
    for j, c in enumerate(rm.coordinates):
        struct = not ca.depends_on(L, q[j])
        numeric = bool(np.all(np.abs(dL[:, j]) <= CYCLIC_RTOL * scale))
        free_of_forces = bool(np.all(np.abs(Qnc[:, j]) <= CYCLIC_RTOL * scale))
        if struct:
            structural.append(c)
        if (struct or numeric) and free_of_forces:
            cyclic.append(c)
    h_conserved = bool(np.all(np.abs(dLdt) <= CYCLIC_RTOL * scale)) and bool(
        np.all(np.abs(Qnc) <= CYCLIC_RTOL * scale[:, None])
    )
    result = Conservation(
        coordinates=list(rm.coordinates),
        cyclic=cyclic,
        structurally_cyclic=structural,
        hamiltonian_conserved=h_conserved,
        hamiltonian_is_energy=bool(np.all(h_gap <= 1e-10)),
    )
    if trajectory is not None:
        info = trajectory.info
        if "q" not in info or "q_dot" not in info:
            raise InputError("the trajectory has no generalized coordinates: use ReducedModel.solve")
        Qt, Qdt, tt = np.asarray(info["q"]), np.asarray(info["q_dot"]), np.asarray(trajectory.t)
        P = rm._along(rm.momenta, Qt, Qdt, tt)
        H = rm._along(rm.hamiltonian, Qt, Qdt, tt).ravel()
        TVU = rm._along(rm.energies, Qt, Qdt, tt)
        E = TVU[:, 0] + TVU[:, 1]
        result.momenta = {c: P[:, j] for j, c in enumerate(rm.coordinates)}
        result.hamiltonian, result.energy = H, E
        result.momentum_drift = {c: _rel_drift(P[:, j]) for j, c in enumerate(rm.coordinates)}
        result.hamiltonian_drift = _rel_drift(H)
        result.energy_drift = _rel_drift(E)
    return result


# --- readable printout -----------------------------------------------------------------------

_BINARY = {
    ca.OP_ADD: ("+", 1), ca.OP_SUB: ("-", 1), ca.OP_MUL: ("*", 2), ca.OP_DIV: ("/", 2),
}
_UNARY = {
    ca.OP_SIN: "sin", ca.OP_COS: "cos", ca.OP_TAN: "tan", ca.OP_EXP: "exp", ca.OP_LOG: "log",
    ca.OP_SQRT: "sqrt", ca.OP_ASIN: "asin", ca.OP_ACOS: "acos", ca.OP_ATAN: "atan",
    ca.OP_SINH: "sinh", ca.OP_COSH: "cosh", ca.OP_TANH: "tanh", ca.OP_FABS: "abs",
}


def pretty(expr, digits: int = 6, *, simplify: bool = True) -> str:
    """A compact infix string of a scalar SX expression (``sq(x)`` → ``x^2``).

    With SymPy installed (the ``pretty`` extra) and ``simplify``, the expression is
    expanded and trigonometrically simplified first (``cos(a)cos(b) + sin(a)sin(b)`` →
    ``cos(a - b)``); without it, CasADi's graph is printed as it is.
    """
    expr = ca.SX(expr)
    if expr.numel() != 1:
        return "[" + ", ".join(pretty(expr[k], digits, simplify=simplify)
                               for k in range(expr.numel())) + "]"
    if simplify:
        try:
            import sympy
        except ImportError:
            sympy = None
        if sympy is not None:
            simplified = sympy.trigsimp(sympy.expand(_to_sympy(expr, sympy, {})))
            if simplified.atoms(sympy.Float):
                simplified = simplified.evalf(digits)
                simplified = simplified.xreplace({f: sympy.Integer(int(f)) for f in
                                                  simplified.atoms(sympy.Float) if float(f).is_integer()})
            return str(simplified).replace("**", "^")
    return _pp(expr, digits)[0]


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


def describe(scene_or_model, *, parameters: dict | None = None, max_chars: int = 4000) -> str:
    """T, V, L, the conjugate momenta and Lagrange's equations ``M q̈ = rhs`` as text."""
    rm = _reduced(scene_or_model, parameters)
    ex = rm.expressions
    lines = [f"coordinates: {', '.join(rm.coordinates)}" + ("  (rheonomic map)" if rm.rheonomic else "")]
    for name in ("T", "V", "U", "R", "L"):
        e = ex[name]
        if name in ("U", "R") and ca.SX(e).is_zero():
            continue
        lines.append(f"{name} = {pretty(e)}")
    for j, c in enumerate(rm.coordinates):
        lines.append(f"p_{c} = {pretty(ex['p'][j])}")
    E = ca.mtimes(ex["M"], rm.q_ddot) - ex["rhs"]
    for j, c in enumerate(rm.coordinates):
        lines.append(f"equation for {c}: {pretty(E[j])} = 0")
    text = "\n".join(lines)
    if len(text) > max_chars:
        text = text[:max_chars] + "\n… (truncated)"
    return text
