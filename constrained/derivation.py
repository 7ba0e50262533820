"""Derivation checks on the reduced route: hand-derived equations, conservation laws, printouts.

- ``check_equations``: is a candidate equation of motion implied by Lagrange's equations?
  At random states (q, q̇, t) the accelerations q̈ come from ``M q̈ = rhs``; a right
  equation (any nonzero multiple or combination of Lagrange's equations) then vanishes,
  relative to the size of its terms.
- ``conservation``: conjugate momenta ``p = ∂L/∂q̇``, cyclic coordinates (``∂L/∂q_j = 0``
  and no non-conservative generalized force on q_j), the Hamiltonian ``H = p·q̇ − L`` and
  whether it equals ``T + V``; their drift along a reduced trajectory.
- ``describe`` (from constrained.printing): a readable printout of T, V, L and the equations.
"""

from __future__ import annotations

import ast
from collections.abc import Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from . import expressions
from .errors import InputError
from .printing import describe, pretty, symbolic_reduced, to_sympy  # noqa: F401 (public here too)
from .reduced import ReducedModel

__all__ = [
    "Conservation",
    "EquationCheck",
    "check_equations",
    "check_generalized_forces",
    "check_lagrangian",
    "conservation",
    "describe",
    "pretty",
    "symbolic_reduced",
    "to_sympy",
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
        if self.hamiltonian_conserved:
            h = "a constant of the motion: ∂L/∂t = 0, no non-conservative forces"
        else:
            h = "not conserved: L depends on t or non-conservative forces act"
        e = "h = T + V" if self.hamiltonian_is_energy else "h ≠ T + V"
        line = f"Jacobi integral h = p·q_dot − L  ({h}; {e}"
        if self.hamiltonian_drift is not None:
            line += f"; measured drift {self.hamiltonian_drift:.3g}"
        elif self.hamiltonian_conserved:
            line += "; not measured: pass a reduced trajectory to see its drift"
        if self.energy_drift is not None:
            line += f"; T + V drift {self.energy_drift:.3g}"
        lines.append(line + ")")
        return "\n".join(lines)

    @property
    def jacobi_integral_conserved(self) -> bool:
        """Whether the Jacobi integral h = p·q̇ − L (``hamiltonian``) is a constant of the motion."""
        return self.hamiltonian_conserved

    @property
    def jacobi_integral(self) -> np.ndarray | None:
        """h = p·q̇ − L along the trajectory given (None without one)."""
        return self.hamiltonian

    @property
    def jacobi_integral_drift(self) -> float | None:
        """max |h − h0| / |h0| along the trajectory given (None without one)."""
        return self.hamiltonian_drift


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


# --- candidate Lagrangians and generalized forces ----------------------------------------------

#: ∂²L/∂q̇² counts as singular when its smallest singular value is below this × its largest.
HESSIAN_RTOL = 1e-10


def _state_of(rm: ReducedModel, q, qd, t, qdd=None) -> dict:
    state = {c: float(q[j]) for j, c in enumerate(rm.coordinates)}
    state.update({f"{c}_dot": float(qd[j]) for j, c in enumerate(rm.coordinates)})
    if qdd is not None:
        state.update({f"{c}_ddot": float(qdd[j]) for j, c in enumerate(rm.coordinates)})
    state["t"] = float(t)
    return state


def _state_text(state: dict) -> str:
    return ", ".join(f"{n} = {v:.6g}" for n, v in state.items())


def _state_names(rm: ReducedModel) -> dict:
    """Names a formula in (q, q̇, t, parameters) may use: no accelerations."""
    names = {"t": rm.t, **rm.parameters}
    for j, c in enumerate(rm.coordinates):
        names[c] = rm.q[j]
        names[f"{c}_dot"] = rm.q_dot[j]
    return names


def _effect_forces(rm: ReducedModel) -> list[tuple[str, str, ca.SX]]:
    """Per effect (slot, label, generalized force in q, q̇, q̈, t) on the reduced symbols.

    potential: −∂V/∂q; generalized potential: d/dt ∂U/∂q̇ − ∂U/∂q; dissipation: −∂R/∂q̇;
    applied: (∂x/∂q)ᵀ F. Their sum is the total generalized force Σ_i F_i·∂x_i/∂q_j.
    """
    s = rm.symbols
    ex = rm.expressions
    q, qd, qdd, t = rm.q, rm.q_dot, rm.q_ddot, rm.t
    cart = ca.vertcat(s.x, s.v)
    red = ca.densify(ca.vertcat(ex["x"], ex["x_dot"]))
    Jq = ca.jacobian(ex["x"], q)
    out = []
    for effect in rm.system.effects:
        term = ca.substitute(ca.SX(effect.term(s)), cart, red)
        slot = effect.slot
        if slot == "potential":
            Q = -ca.gradient(term, q)
        elif slot == "dissipation":
            Q = -ca.gradient(term, qd)
        elif slot == "applied_force":
            Q = ca.mtimes(Jq.T, term)
        else:  # generalized potential U
            pu = ca.gradient(term, qd)
            Q = ca.jtimes(pu, qd, qdd) + ca.jtimes(pu, q, qd) + ca.jacobian(pu, t) - ca.gradient(term, q)
        out.append((slot, effect.label, ca.densify(ca.SX(Q))))
    return out


def _regular_samples(rm: ReducedModel, samples: int, seed: int):
    """Random states with q̈ from the derived equations; states where those fail are dropped."""
    Q, Qd, Ts = rm.sample_states(samples, seed)
    keep, acc = [], []
    with np.errstate(all="ignore"):
        for i in range(samples):
            a = np.asarray(rm.acceleration(Q[i], Qd[i], Ts[i]), float).ravel()
            if np.all(np.isfinite(a)):
                keep.append(i)
                acc.append(a)
    if not keep:
        raise InputError("the derived Lagrange equations do not determine q̈ at any sampled state "
                         "(singular mass matrix ∂²L/∂q̇²)", where="reduced")
    return Q[keep], Qd[keep], Ts[keep], np.array(acc)


def check_lagrangian(
    scene_or_model,
    lagrangian: str,
    *,
    samples: int = 40,
    seed: int = 1,
    rtol: float = EQUATION_RTOL,
    parameters: dict | None = None,
) -> EquationCheck:
    """Does a candidate Lagrangian generate the scene's motion?

    ``lagrangian``: a formula (optionally ``"L = ..."``) in the coordinates, ``<q>_dot``,
    ``t`` and the parameters. Its Euler–Lagrange expressions
    ``E_j = d/dt ∂L/∂q̇_j − ∂L/∂q_j`` (CasADi AD, ``symmetry.euler_lagrange``) minus the
    derived non-conservative generalized forces (applied ``(∂x/∂q)ᵀF`` and damping
    ``−∂R/∂q̇``, ``ReducedModel.expressions["Q"]``) must vanish at ``samples`` random states
    (q, q̇, t) with q̈ from the derived Lagrange equations: ``|E_j − Q_j| ≤ rtol × Σ|terms|``.
    Its Hessian ``∂²L/∂q̇²`` must be nonsingular there, or its equations do not fix q̈
    (a "degenerate Lagrangian"). A nonzero multiple of the scene's L, or L + dF(q, t)/dt,
    is right when there are no non-conservative forces; with them only the scale that
    matches the given Rayleigh function and applied forces is. Unknown names raise InputError.
    """
    from .symmetry import euler_lagrange

    rm = _reduced(scene_or_model, parameters)
    if not isinstance(lagrangian, str) or not lagrangian.strip():
        raise InputError(f"the Lagrangian must be a non-empty formula, got {lagrangian!r}",
                         where="lagrangian")
    text = lagrangian.strip()
    lhs, rhs = _split(text, "lagrangian")
    if rhs is not None:
        if lhs != "L":
            raise InputError(f"write the Lagrangian as a formula or as 'L = formula', got {text!r}",
                             where="lagrangian")
        formula = rhs
    else:
        formula = lhs
    q, qd, t = rm.q, rm.q_dot, rm.t
    Lc = ca.SX(expressions.parse(formula, _state_names(rm), where="lagrangian"))
    n = rm.n
    L_fun = ca.Function("candidate_lagrangian", [q, qd, t], [Lc], ["q", "q_dot", "t"], ["L"])
    E_fun = euler_lagrange(L_fun, n)
    ex = rm.expressions
    dR = ca.gradient(ex["R"], qd)
    applied = ex["Q"] + dR
    p = ca.gradient(Lc, qd)
    pieces = ca.Function("candidate_pieces", [q, qd, t], [
        ca.densify(ca.jacobian(p, qd)), ca.densify(ca.jacobian(p, q)), ca.densify(ca.jacobian(p, t)),
        ca.densify(ca.gradient(Lc, q)), ca.densify(ex["Q"]), ca.densify(dR), ca.densify(applied),
    ])
    Qs, Qds, Ts, Qdds = _regular_samples(rm, samples, seed)
    worst = (0.0, 0.0, 0, 0)  # (relative, absolute, sample, coordinate)
    for i in range(len(Ts)):
        Mc, Pq, pt, dLq, Qnc, dRv, Fa = (np.asarray(v, float) for v in pieces(Qs[i], Qds[i], Ts[i]))
        sv = np.linalg.svd(Mc, compute_uv=False)
        if not np.all(np.isfinite(sv)) or sv[0] == 0.0 or sv[-1] <= HESSIAN_RTOL * sv[0]:
            state = _state_of(rm, Qs[i], Qds[i], Ts[i])
            rank = int(np.sum(sv > HESSIAN_RTOL * sv[0])) if np.all(np.isfinite(sv)) and sv[0] > 0 else 0
            detail = "∂²L/∂q̇² = 0" if rank == 0 else f"∂²L/∂q̇² has rank {rank} of {n}"
            message = (f"degenerate Lagrangian: no q̈ in its equations ({detail} at {_state_text(state)}), "
                       "so they cannot determine the motion")
            return EquationCheck(text, False, float("nan"), float("nan"), message, state)
        E = np.asarray(E_fun(Qs[i], Qds[i], Qdds[i], Ts[i]), float).ravel() - Qnc.ravel()
        scale = (np.abs(Mc) @ np.abs(Qdds[i]) + np.abs(Pq) @ np.abs(Qds[i]) + np.abs(pt).ravel()
                 + np.abs(dLq).ravel() + np.abs(dRv).ravel() + np.abs(Fa).ravel())
        scale = np.where(scale > 0, scale, 1.0)
        rel = np.where(np.isfinite(E), np.abs(E) / scale, np.inf)
        j = int(np.argmax(rel))
        if rel[j] > worst[0] or not np.isfinite(rel[j]):
            worst = (float(rel[j]), float(abs(E[j])), i, j)
        if not np.isfinite(rel[j]):
            break
    rel, res, i, j = worst
    state = _state_of(rm, Qs[i], Qds[i], Ts[i], Qdds[i])
    kinds = [k for slot, k in (("dissipation", "damping −∂R/∂q̇"), ("applied_force", "applied (∂x/∂q)ᵀF"))
             if slot in rm.active_terms]
    forces = f" minus the derived non-conservative forces: {' and '.join(kinds)}" if kinds else ""
    if rel > rtol:
        c = rm.coordinates[j]
        message = (
            f"the Euler–Lagrange equation for {c} of L = {formula} (d/dt ∂L/∂{c}_dot − ∂L/∂{c}"
            f"{forces}) disagrees with the derived Lagrange equations by {res:.3g} ({rel:.3g} of the "
            f"size of its terms) at {_state_text(state)} (accelerations from the derived equations): "
            "this Lagrangian generates a different motion"
        )
        return EquationCheck(text, False, res, rel, message, state)
    message = (
        f"L = {formula} generates the derived equations of motion (Euler–Lagrange{forces}; largest "
        f"relative residual {rel:.2g} over {len(Ts)} random states, ∂²L/∂q̇² nonsingular)"
    )
    return EquationCheck(text, True, res, rel, message, state)


def check_generalized_forces(
    scene_or_model,
    forces: Sequence[str],
    *,
    samples: int = 40,
    seed: int = 1,
    rtol: float = EQUATION_RTOL,
    parameters: dict | None = None,
) -> list[EquationCheck]:
    """Compare candidate generalized forces with the derived total ``Q_j = Σ_i F_i · ∂x_i/∂q_j``.

    ``forces``: one formula per coordinate, in coordinate order, in the coordinates,
    ``<q>_dot``, ``t`` and the parameters. The derived Q_j sums every effect of the scene:
    potentials ``−∂V/∂q_j``, generalized potentials ``d/dt ∂U/∂q̇_j − ∂U/∂q_j`` (q̈ from the
    derived equations where U is not linear in q̇), dissipation ``−∂R/∂q̇_j`` and applied
    forces ``(∂x/∂q_j)ᵀF``. A candidate is right when ``|Q_cand − Q_j| ≤ rtol × scale`` at
    ``samples`` random states, scale = Σ over effects |their Q_j| + Σ|terms of the candidate|.
    Returns one EquationCheck per coordinate; unknown names raise InputError.
    """
    rm = _reduced(scene_or_model, parameters)
    if isinstance(forces, str):
        forces = [forces]
    forces = list(forces)
    if len(forces) != rm.n:
        raise InputError(f"needs one generalized force per coordinate ({rm.n}: "
                         f"{', '.join(rm.coordinates)}), got {len(forces)}", where="forces")
    names = _state_names(rm)
    q, qd, qdd, t = rm.q, rm.q_dot, rm.q_ddot, rm.t
    cand, cand_terms = [], []
    for j, (c, text) in enumerate(zip(rm.coordinates, forces, strict=True)):
        where = f"force {j + 1} (Q_{c})"
        if isinstance(text, int | float) and not isinstance(text, bool):
            text = repr(float(text))
        if not isinstance(text, str) or not text.strip():
            raise InputError(f"must be a non-empty formula, got {text!r}", where=where)
        cand.append(ca.SX(expressions.parse(text, names, where=where)))
        node = ast.parse(text.strip(), mode="eval").body
        cand_terms.append(ca.vertcat(*[ca.SX(expressions.parse(ast.unparse(s), names, where=where))
                                       for s in _terms(node)]))
    per_effect = _effect_forces(rm)
    outs = [ca.vertcat(*cand)] + [ca.densify(cand_terms[j]) for j in range(rm.n)]
    outs += [Q for _, _, Q in per_effect]
    fun = ca.Function("forces", [q, qd, qdd, t], outs)
    Qs, Qds, Ts, Qdds = _regular_samples(rm, samples, seed)
    n, ne = rm.n, len(per_effect)
    worst = [(0.0, 0.0, 0, 0.0, np.zeros(ne)) for _ in range(n)]
    for i in range(len(Ts)):
        vals = [np.asarray(v, float).ravel() for v in fun(Qs[i], Qds[i], Qdds[i], Ts[i])]
        qc = vals[0]
        effects_q = np.array([vals[1 + n + k] for k in range(ne)]).reshape(ne, n)
        derived = effects_q.sum(axis=0)
        for j in range(n):
            scale = float(np.sum(np.abs(effects_q[:, j])) + np.sum(np.abs(vals[1 + j]))) or 1.0
            diff = qc[j] - derived[j]
            rel = abs(diff) / scale if np.isfinite(diff) else np.inf
            if rel > worst[j][0] or (not np.isfinite(rel) and np.isfinite(worst[j][0])):
                worst[j] = (rel, abs(diff), i, float(derived[j]), effects_q[:, j].copy())
    out = []
    for j, c in enumerate(rm.coordinates):
        rel, res, i, derived, parts = worst[j]
        text = forces[j]
        state = _state_of(rm, Qs[i], Qds[i], Ts[i])
        label = f"Q_{c} = {text}"
        if rel > rtol:
            breakdown = "; ".join(f"{lab}: {v:.6g}" for (_, lab, _), v in zip(per_effect, parts, strict=True))
            message = (
                f"{label} disagrees with the derived generalized force by {res:.3g} ({rel:.3g} of its "
                f"scale) at {_state_text(state)}: derived Q_{c} = {derived:.6g} there"
                + (f" ({breakdown})" if breakdown else " (the scene has no effects)")
            )
            out.append(EquationCheck(label, False, res, rel, message, state))
        else:
            message = (f"{label} equals the derived Σ_i F_i·∂x_i/∂{c} (largest relative difference "
                       f"{rel:.2g} over {len(Ts)} random states)")
            out.append(EquationCheck(label, True, res, rel, message, state))
    return out
