"""Hand-given candidates checked against the reduced route: a Lagrangian (``check_lagrangian``:
does it give the same equations of motion, up to a total derivative and a constant factor?) and
generalized forces (``check_generalized_forces``: Q_j = F · ∂x/∂q_j of the scene's effects).
Both judge at the states of ``equations.regular_states`` and, when right at the scene's parameter
values, again at other values of the parameters the candidate names (``ParameterVariation``)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import casadi as ca
import numpy as np

from ..errors import InputError
from ..model import expressions
from ..run.reduced import ReducedModel
from .equations import (
    EQUATION_RTOL,
    EquationCheck,
    ParameterVariation,
    _reduced,
    _split,
    _state_of,
    _state_text,
    beyond_scene_values,
    not_finite,
    regular_states,
)

#: ∂²L/∂q̇² counts as singular when its smallest singular value is below this × its largest.
HESSIAN_RTOL = 1e-10
#: Subsets of at most this many effects are tried when a generalized force is wrong, to say
#: which effects it leaves out (2^n − 2 sums).
SUBSET_EFFECTS = 6


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


# --- Lagrangians ---------------------------------------------------------------------------------


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
    (q, q̇, t) with q̈ from the derived Lagrange equations: ``|E_j − Q_j| ≤ rtol × Σ|terms|``;
    with velocity constraints ``E − Q`` must be a force of theirs, ``Ãᵀμ`` for some μ (its part
    outside the range of Ãᵀ must vanish). Its Hessian ``∂²L/∂q̇²`` must be nonsingular there, or
    its equations do not fix q̈ (a "degenerate Lagrangian"). A nonzero multiple of the scene's L,
    or L + dF(q, t)/dt, is right when there are no non-conservative forces; with them only the
    scale that matches the given Rayleigh function and applied forces is (the verdict names the
    factor). Unknown names raise InputError, and so does a Lagrangian that is not finite at a
    sampled state. Right at the scene's parameter values, it is checked again at others.
    """
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
    expressions.parse(formula, _state_names(rm), where="lagrangian")  # names checked before sampling

    def at(model: ReducedModel, values: str = "") -> EquationCheck:
        return _lagrangian_at(model, regular_states(model, samples, seed), text, formula, rtol, values)

    return beyond_scene_values(ParameterVariation(rm), at(rm), expressions.free_names(formula), at)


def _lagrangian_at(rm: ReducedModel, st, text: str, formula: str, rtol: float, values: str) -> EquationCheck:
    from .symmetry import euler_lagrange

    label = f"L = {formula}"
    q, qd, t, n = rm.q, rm.q_dot, rm.t, rm.n
    Lc = ca.SX(expressions.parse(formula, _state_names(rm), where="lagrangian"))
    L_fun = ca.Function("candidate_lagrangian", [q, qd, t], [Lc], ["q", "q_dot", "t"], ["L"])
    E_fun = euler_lagrange(L_fun, n)
    ex = rm.expressions
    dR = ca.gradient(ex["R"], qd)
    p = ca.gradient(Lc, qd)
    pieces = ca.Function("candidate_pieces", [q, qd, t], [ca.densify(v) for v in (
        ca.jacobian(p, qd), ca.jacobian(p, q), ca.jacobian(p, t), ca.gradient(Lc, q), ex["Q"], dR,
        ex["Q"] + dR, ca.jacobian(ex["velocity_rows"], qd), Lc)])
    worst = (-1.0, 0.0, 0, 0)  # (relative, absolute, sample, coordinate)
    EL, Qs, scales = [], [], []
    with np.errstate(all="ignore"):
        for i in range(len(st)):
            args = (st.q[i], st.q_dot[i], st.t[i])
            Mc, Pq, pt, dLq, Qnc, dRv, Fa, A, Lv = (np.asarray(v, float) for v in pieces(*args))
            E = np.asarray(E_fun(st.q[i], st.q_dot[i], st.q_ddot[i], st.t[i]), float).ravel()
            if not (np.all(np.isfinite(E)) and np.all(np.isfinite(Mc)) and np.all(np.isfinite(Lv))):
                raise not_finite(f"the Lagrangian {label}", _state_of(rm, *args), values)
            sv = np.linalg.svd(Mc, compute_uv=False)
            if sv[0] == 0.0 or sv[-1] <= HESSIAN_RTOL * sv[0]:
                state = _state_of(rm, st.q[i], st.q_dot[i], st.t[i])
                rank = int(np.sum(sv > HESSIAN_RTOL * sv[0])) if sv[0] > 0 else 0
                detail = "∂²L/∂q̇² = 0" if rank == 0 else f"∂²L/∂q̇² has rank {rank} of {n}"
                message = (f"{label}: degenerate Lagrangian: no q̈ in its equations ({detail} at "
                           f"{_state_text(state)}), so they cannot determine the motion")
                return EquationCheck(text, False, float("nan"), float("nan"), message, state, label)
            r = E - Qnc.ravel()
            if A.size:  # Lagrange–d'Alembert: E − Q = Ãᵀμ, so only the part outside range(Ãᵀ) counts
                r = r - A.T @ np.linalg.lstsq(A.T, r, rcond=None)[0]
            scale = (np.abs(Mc) @ np.abs(st.q_ddot[i]) + np.abs(Pq) @ np.abs(st.q_dot[i]) + np.abs(pt).ravel()
                     + np.abs(dLq).ravel() + np.abs(dRv).ravel() + np.abs(Fa).ravel())
            scale = np.where(scale > 0, scale, 1.0)
            rel = np.abs(r) / scale
            j = int(np.argmax(rel))
            if rel[j] > worst[0]:
                worst = (float(rel[j]), float(abs(r[j])), i, j)
            EL.append(E)
            Qs.append(Qnc.ravel())
            scales.append(scale)
    rel, res, i, j = worst
    state = _state_of(rm, st.q[i], st.q_dot[i], st.t[i], st.q_ddot[i])
    kinds = [k for slot, k in (("dissipation", "damping −∂R/∂q̇"), ("applied_force", "applied (∂x/∂q)ᵀF"))
             if slot in rm.active_terms]
    forces = f" minus the derived non-conservative forces: {' and '.join(kinds)}" if kinds else ""
    if rm.n_velocity_rows:
        forces += ", up to the velocity constraints' forces Ãᵀμ"
    if rel > rtol:
        c = rm.coordinates[j]
        message = (
            f"{label}: its Euler–Lagrange equation for {c} (d/dt ∂L/∂{c}_dot − ∂L/∂{c}{forces}) disagrees "
            f"with the derived Lagrange equations by {res:.3g} ({rel:.3g} of the size of its terms) at "
            f"{_state_text(state)} (accelerations from the derived equations): this Lagrangian generates "
            f"a different motion{_scaled_hint(np.array(EL), np.array(Qs), np.array(scales), rtol, rm)}"
        )
        return EquationCheck(text, False, res, rel, message, state, label)
    message = (
        f"{label} generates the derived equations of motion (Euler–Lagrange{forces}; largest relative "
        f"residual {rel:.2g} over {len(st)} random states{st.note()}, ∂²L/∂q̇² nonsingular)"
    )
    return EquationCheck(text, True, res, rel, message, state, label)


def _scaled_hint(E: np.ndarray, Q: np.ndarray, scale: np.ndarray, rtol: float, rm: ReducedModel) -> str:
    """When the candidate's Euler–Lagrange expressions are c × the derived non-conservative forces
    at every state (E = c Q, as for c × the scene's L), the factor c and what it means."""
    qq = float(np.sum(Q * Q))
    if rm.n_velocity_rows or qq == 0.0:
        return ""
    c = float(np.sum(E * Q)) / qq
    if abs(c - 1.0) <= 1e-6 or np.any(np.abs(E - c * Q) > 1e3 * rtol * scale):
        return ""
    return (f"; its equations are the scene's with the damping and applied forces scaled by {c:.6g}: a "
            f"Lagrangian multiplied by a constant needs its Rayleigh function and forces multiplied too, and "
            f"these are the scene's, so divide it by {c:.6g}")


# --- generalized forces --------------------------------------------------------------------------


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
    A wrong one is told when it is −Q_j (the sign convention) or the sum of only some effects.
    Returns one EquationCheck per coordinate; unknown names and candidates that are not finite
    at a sampled state raise InputError. Right at the scene's parameter values, each is checked
    again at other values of the parameters it names.
    """
    rm = _reduced(scene_or_model, parameters)
    if isinstance(forces, str):
        forces = [forces]
    forces = list(forces)
    if len(forces) != rm.n:
        raise InputError(f"needs one generalized force per coordinate ({rm.n}: "
                         f"{', '.join(rm.coordinates)}), got {len(forces)}", where="forces")
    texts = []
    for j, (c, text) in enumerate(zip(rm.coordinates, forces, strict=True)):
        if isinstance(text, int | float) and not isinstance(text, bool):
            text = repr(float(text))
        if not isinstance(text, str) or not text.strip():
            raise InputError(f"must be a non-empty formula, got {text!r}", where=f"force {j + 1} (Q_{c})")
        texts.append(text)
    done: dict = {}

    def at(model: ReducedModel, j: int, values: str = "") -> EquationCheck:
        if id(model) not in done:
            states = regular_states(model, samples, seed)
            done[id(model)] = (model, _forces_at(model, states, texts, rtol, values))
        return done[id(model)][1][j]

    variation = ParameterVariation(rm)
    return [beyond_scene_values(variation, at(rm, j), expressions.free_names(texts[j]),
                                lambda model, values, j=j: at(model, j, values)) for j in range(rm.n)]


def _forces_at(rm: ReducedModel, st, texts: list[str], rtol: float, values: str) -> list[EquationCheck]:
    names = _state_names(rm)
    n = rm.n
    cand, cand_terms = [], []
    for j, (c, text) in enumerate(zip(rm.coordinates, texts, strict=True)):
        where = f"force {j + 1} (Q_{c})"
        cand.append(ca.SX(expressions.parse(text, names, where=where)))
        terms = expressions.terms(text, names, where=where)
        cand_terms.append(ca.densify(ca.vertcat(*[ca.SX(s) for s in terms])))
    per_effect = _effect_forces(rm)
    ne = len(per_effect)
    fun = ca.Function("forces", [rm.q, rm.q_dot, rm.q_ddot, rm.t],
                      [ca.vertcat(*cand), *cand_terms, *[Q for _, _, Q in per_effect]])
    subsets = ([s for r in range(1, ne) for s in itertools.combinations(range(ne), r)]
               if ne <= SUBSET_EFFECTS else [])
    worst = [(-1.0, 0.0, 0, 0.0, np.zeros(ne)) for _ in range(n)]
    flipped = np.zeros(n)  # largest relative |Q_cand + Q_j|: −Q_j everywhere when ≤ rtol
    partial = np.zeros((n, len(subsets)))  # largest relative |Q_cand − Σ_S Q_e| per subset S of effects
    with np.errstate(all="ignore"):
        for i in range(len(st)):
            vals = [np.asarray(v, float).ravel() for v in fun(st.q[i], st.q_dot[i], st.q_ddot[i], st.t[i])]
            qc = vals[0]
            effects_q = np.array([vals[1 + n + k] for k in range(ne)]).reshape(ne, n)
            derived = effects_q.sum(axis=0)
            for j in range(n):
                if not (np.isfinite(qc[j]) and np.all(np.isfinite(vals[1 + j]))):
                    raise not_finite(f"force {j + 1} (Q_{rm.coordinates[j]} = {texts[j]})",
                                     _state_of(rm, st.q[i], st.q_dot[i], st.t[i]), values)
                scale = float(np.sum(np.abs(effects_q[:, j])) + np.sum(np.abs(vals[1 + j]))) or 1.0
                rel = abs(qc[j] - derived[j]) / scale
                if rel > worst[j][0]:
                    worst[j] = (rel, abs(qc[j] - derived[j]), i, float(derived[j]), effects_q[:, j].copy())
                flipped[j] = max(flipped[j], abs(qc[j] + derived[j]) / scale)
                for k, s in enumerate(subsets):
                    partial[j, k] = max(partial[j, k], abs(qc[j] - effects_q[list(s), j].sum()) / scale)
    out = []
    for j, c in enumerate(rm.coordinates):
        rel, res, i, derived, parts = worst[j]
        state = _state_of(rm, st.q[i], st.q_dot[i], st.t[i])
        label = f"Q_{c} = {texts[j]}"
        if rel <= rtol:
            message = (f"{label} equals the derived Σ_i F_i·∂x_i/∂{c} (largest relative difference "
                       f"{rel:.2g} over {len(st)} random states{st.note()})")
            out.append(EquationCheck(label, True, res, rel, message, state, label))
            continue
        breakdown = "; ".join(f"{lab}: {v:.6g}" for (_, lab, _), v in zip(per_effect, parts, strict=True))
        hint = ""
        if flipped[j] <= rtol:
            hint = (f"; it is −1 × the derived Q_{c}: Q_{c} = Σ_i F_i·∂x_i/∂{c} is the forces' component "
                    f"along increasing {c} (−∂V/∂{c} for a potential, not +∂V/∂{c})")
        else:
            hits = [s for k, s in enumerate(subsets) if partial[j, k] <= rtol]
            if hits:
                s = hits[0]
                given = ", ".join(per_effect[e][1] for e in s)
                missing = ", ".join(per_effect[e][1] for e in range(ne) if e not in s)
                hint = (f"; it equals the forces of {given} alone: Q_{c} sums every effect of the scene, "
                        f"{missing} included")
        message = (
            f"{label} disagrees with the derived generalized force by {res:.3g} ({rel:.3g} of its "
            f"scale) at {_state_text(state)}: derived Q_{c} = {derived:.6g} there"
            + (f" ({breakdown})" if breakdown else " (the scene has no effects)") + hint
        )
        out.append(EquationCheck(label, False, res, rel, message, state, label))
    return out
