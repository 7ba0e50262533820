"""Hand-given candidates checked against the reduced route: a Lagrangian (``check_lagrangian``:
does it give the same equations of motion, up to a total derivative and a constant factor?) and
generalized forces (``check_generalized_forces``: Q_j = F · ∂x/∂q_j of the scene's effects)."""

from __future__ import annotations

import ast
from collections.abc import Sequence

import casadi as ca
import numpy as np

from ..errors import InputError
from ..model import expressions
from ..run.reduced import ReducedModel
from .equations import EQUATION_RTOL, EquationCheck, _reduced, _split, _terms

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
