"""Hand-derived equations of motion checked against the reduced route (``check_equations``): at
random states (q, q̇, t) the accelerations q̈ come from ``M q̈ = rhs``; a right equation (any
nonzero multiple or combination of Lagrange's equations) then vanishes, relative to the size of
its terms."""

from __future__ import annotations

import ast
from collections.abc import Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import InputError
from ..model import expressions
from ..run.reduced import ReducedModel

#: A candidate equation is right when |residual| ≤ EQUATION_RTOL × (sum of |terms|) everywhere.
EQUATION_RTOL = 1e-8


def _reduced(scene_or_model, parameters=None) -> ReducedModel:
    if isinstance(scene_or_model, ReducedModel):
        return scene_or_model
    return ReducedModel.from_scene(scene_or_model, parameters=parameters)


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

    With velocity constraints the states have q̇ on them (``consistent_rates``), q̈ and the
    multipliers ``mu1, mu2 …`` (one per velocity row, in order) come from the
    Lagrange–d'Alembert equations ``M q̈ = rhs + Ãᵀμ``, and equations may use the ``mu``.
    """
    rm = _reduced(scene_or_model, parameters)
    if isinstance(equations, str):
        equations = [equations]
    names = dict(rm.names)
    q, qd, qdd, t = rm.q, rm.q_dot, rm.q_ddot, rm.t
    mu = ca.SX.sym("mu", rm.n_velocity_rows)
    names.update({f"mu{k + 1}": mu[k] for k in range(rm.n_velocity_rows) if f"mu{k + 1}" not in names})
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
    Qd = np.array([rm.consistent_rates(a, b, c) for a, b, c in zip(Q, Qd, Ts, strict=True)])
    Qdd = np.array([np.asarray(rm.acceleration(a, b, c)).ravel() for a, b, c in zip(Q, Qd, Ts, strict=True)])
    Mu = (np.array([np.asarray(rm.velocity_multipliers(a, b, c)).ravel() for a, b, c in zip(Q, Qd, Ts,
                                                                                           strict=True)])
          if rm.n_velocity_rows else np.zeros((samples, 0)))
    out = []
    for k, (text, expr, terms) in enumerate(parsed):
        f = ca.Function("candidate", [q, qd, qdd, t, mu], [expr, ca.vertcat(*terms), ca.gradient(expr, qdd)])
        worst_rel, worst_abs, worst_i, involves_acc = 0.0, 0.0, 0, False
        for i in range(samples):
            e, tv, g = f(Q[i], Qd[i], Qdd[i], Ts[i], Mu[i])
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
