"""Derivation checks on the reduced route: hand-derived equations, conservation laws, printouts.

- ``check_equations``: is a candidate equation of motion implied by Lagrange's equations?
  At random states (q, q̇, t) the accelerations q̈ come from ``M q̈ = rhs``; a right
  equation (any nonzero multiple or combination of Lagrange's equations) then vanishes,
  relative to the size of its terms.
- ``conservation``: conjugate momenta ``p = ∂L/∂q̇``, cyclic coordinates (``∂L/∂q_j = 0``
  and no non-conservative generalized force on q_j), the Hamiltonian ``H = p·q̇ − L`` and
  whether it equals ``T + V``; their drift along a reduced trajectory.
- ``describe`` (from constrained.printing): a readable printout of T, V, L and the equations;
  ``describe_conserved``: the conserved quantities found, or why there are none.
- ``check_constant_of_motion``: is a hand-derived C(q, q̇, t) conserved? dC/dt = ∂C/∂q·q̇ +
  ∂C/∂q̇·q̈ + ∂C/∂t must vanish at random states, q̈ from the derived equations.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import InputError
from ..model import expressions
from ..run.reduced import ReducedModel
from .candidates import (  # noqa: F401 (check_generalized_forces, check_lagrangian: public here too)
    _effect_forces,
    _state_names,
    check_generalized_forces,
    check_lagrangian,
)
from .conservation.rigid_motions import charge_in_coordinates, combination_of, rigid_symmetries
from .equations import (  # noqa: F401 (EquationCheck, check_equations: public here too)
    EQUATION_RTOL,
    EquationCheck,
    ParameterVariation,
    _reduced,
    _state_of,
    _state_text,
    beyond_scene_values,
    check_equations,
    not_finite,
    regular_states,
)
from .printing import describe, latex_printer, pretty, symbolic_reduced, to_sympy  # noqa: F401 (public here too)

__all__ = [
    "Conservation",
    "EquationCheck",
    "check_constant_of_motion",
    "check_equations",
    "check_generalized_forces",
    "check_lagrangian",
    "conservation",
    "describe",
    "describe_conserved",
    "pretty",
    "symbolic_reduced",
    "to_sympy",
]

#: |∂L/∂q_j| below this × the scale of the Lagrangian's terms counts as zero (cyclic).
CYCLIC_RTOL = 1e-10
#: A candidate constant whose gradient in (q, q̇) is below this × |C| at every state is trivial.
TRIVIAL_RTOL = 1e-12
#: C equals c·K + c0 for a known quantity K when the fit leaves at most this × max |C|.
MATCH_RTOL = 1e-8


# --- conservation laws ------------------------------------------------------------------------


@dataclass
class Conservation:
    """Conserved quantities found in a reduced model, and their drift along a trajectory.

    ``cyclic``: coordinates with ∂L/∂q_j = 0 and no non-conservative force on them, nor a
    velocity constraint acting on them (their momenta p_j are conserved);
    ``structurally_cyclic``: those whose L does not even mention q_j; ``hamiltonian_conserved``:
    ∂L/∂t = 0, the non-conservative forces do no work (Q·q̇ = 0) and velocity constraints do no
    work; ``hamiltonian_is_energy``: H = T + V at the sampled states (not for rheonomic maps or
    velocity-dependent potentials). ``not_cyclic``: why each other p_j is not conserved,
    ``hamiltonian_why``: why h is or is not, ``energy_why``: why h ≠ T + V ('' when equal).
    Drifts (max |Δ| relative to the starting value, or to 1 when that is zero) are filled in
    when a trajectory is given.
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
    not_cyclic: dict[str, str] = field(default_factory=dict)
    hamiltonian_why: str = ""
    energy_why: str = ""

    def summary(self) -> str:
        lines = []
        for c in self.coordinates:
            tag = "cyclic: p conserved" if c in self.cyclic else f"not cyclic: {self.not_cyclic.get(c, '')}"
            drift = self.momentum_drift.get(c)
            more = f", drift {drift:.3g}" if drift is not None else ""
            lines.append(f"p_{c} = ∂L/∂{c}_dot  ({tag.rstrip(': ')}{more})")
        h = ("a constant of the motion: " if self.hamiltonian_conserved else "not conserved: ")
        h += self.hamiltonian_why
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
    """Find cyclic coordinates, decide whether H is conserved and equals T + V, and say why
    not; with a reduced ``trajectory`` (from ``ReducedModel.solve``) also evaluate p, H, T + V
    along it."""
    rm = _reduced(scene_or_model, parameters)
    ex = rm.expressions
    L, q, qd, t, n = ex["L"], rm.q, rm.q_dot, rm.t, rm.n
    Qs, Qds, Ts = rm.sample_states(samples, seed)
    # velocity constraints act on q_j through column j of Ã = ∂c/∂q̇: d/dt p_j = … + (Ãᵀμ)_j,
    # and work at the rate −μ·b̃, b̃ = c(q̇ = 0)
    rows = ex["velocity_rows"]
    acting = ca.sum1(ca.fabs(ca.densify(ca.jacobian(rows, qd))))
    b = ca.substitute(rows, qd, ca.SX.zeros(n))
    noncons = [(label, Q) for slot, label, Q in _effect_forces(rm)
               if slot in ("dissipation", "applied_force")]  # their sum is ex["Q"]
    pieces = ca.Function("pieces", [q, qd, t], [
        ex["dL_dq"], ex["Q"], ca.gradient(ex["T"], q), ca.gradient(ex["V"], q), ca.gradient(ex["U"], q),
        ca.jacobian(L, t), ex["H"], ex["T"] + ex["V"], ex["T"], ex["V"], ex["U"], acting,
        ca.densify(ca.horzcat(ca.SX.zeros(n, 1), *[Q for _, Q in noncons])),
        ca.norm_1(b) - CYCLIC_RTOL * (1 + ca.norm_1(ca.mtimes(ca.jacobian(rows, qd), qd))),
    ])
    dL, Qnc, held = np.zeros((samples, n)), np.zeros((samples, n)), np.zeros((samples, n))
    scale, dLdt, h_gap, power = np.zeros(samples), np.zeros(samples), np.zeros(samples), np.zeros(samples)
    per_effect = np.zeros((samples, n, len(noncons)))
    moving = False
    for i in range(samples):
        vals = [np.asarray(v).ravel() for v in pieces(Qs[i], Qds[i], Ts[i])]
        dL[i], Qnc[i], held[i] = vals[0], vals[1], vals[11] if vals[11].size else 0.0
        scale[i] = sum(float(np.sum(np.abs(vals[k]))) for k in (2, 3, 4, 8, 9, 10)) or 1.0
        dLdt[i] = float(vals[5][0])
        h_gap[i] = abs(float(vals[6][0]) - float(vals[7][0])) / scale[i]
        power[i] = abs(float(Qnc[i] @ Qds[i])) / (scale[i] * (1.0 + float(np.sum(np.abs(Qds[i])))))
        per_effect[i] = vals[12].reshape(n, -1)[:, 1:]
        moving = moving or (rm.n_velocity_rows and float(vals[13][0]) > 0)
    pushing = np.abs(per_effect) > CYCLIC_RTOL * scale[:, None, None]  # (sample, coordinate, effect)
    cyclic, structural, why = [], [], {}
    for j, c in enumerate(rm.coordinates):
        struct = not ca.depends_on(L, q[j])
        numeric = bool(np.all(np.abs(dL[:, j]) <= CYCLIC_RTOL * scale))
        forces = [noncons[k][0] for k in range(len(noncons)) if np.any(pushing[:, j, k])]
        if np.any(np.abs(Qnc[:, j]) > CYCLIC_RTOL * scale) and not forces:
            forces = ["the applied forces"]
        if struct:
            structural.append(c)
        if not (struct or numeric):
            why[c] = f"L depends on {c}"
        elif forces:
            verb = "acts" if len(forces) == 1 else "act"
            why[c] = f"∂L/∂{c} = 0, but the {' and the '.join(forces)} {verb} on {c}"
        elif np.any(held[:, j]):
            why[c] = f"∂L/∂{c} = 0, but a velocity constraint acts on {c}"
        else:
            cyclic.append(c)
    reasons = []
    if not np.all(np.abs(dLdt) <= CYCLIC_RTOL * scale):
        reasons.append("L depends on t explicitly" + (
            " (the map moves with t: a driven pivot or support, and the drive does work)" if rm.rheonomic
            else " (a potential or a field that changes with t)"))
    if not np.all(power <= CYCLIC_RTOL):
        forces = [noncons[k][0] for k in range(len(noncons)) if np.any(pushing[:, :, k])]
        reasons.append(f"non-conservative forces do work: {', '.join(forces or ['applied forces'])}")
    if moving:
        reasons.append("a velocity constraint moves with t (b̃ ≠ 0 in Ã q̇ + b̃ = 0): its force does work")
    h_conserved = not reasons
    is_energy = bool(np.all(h_gap <= 1e-10))
    energy_why = ""
    if not is_energy:
        energy_why = ("the map depends on t (T has terms of degree 0 and 1 in the rates: h = T2 − T0 + V), "
                      "and what drives it does work" if rm.rheonomic else
                      "the velocity-dependent potential U enters h as Σ q_dot ∂U/∂q_dot − U")
    if h_conserved:
        reasons = ["∂L/∂t = 0 and no non-conservative force does work"
                   + ("; the velocity constraints do no work (b̃ = 0)" if rm.n_velocity_rows else "")]
    result = Conservation(
        coordinates=list(rm.coordinates),
        cyclic=cyclic,
        structurally_cyclic=structural,
        hamiltonian_conserved=h_conserved,
        hamiltonian_is_energy=is_energy,
        not_cyclic=why,
        hamiltonian_why="; ".join(reasons),
        energy_why=energy_why,
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


# --- the printout ---------------------------------------------------------------------------------


def describe_conserved(scene_or_model, *, parameters: dict | None = None, latex: bool = False) -> str:
    """The conserved quantities ``conservation`` finds, as formulas in the names of the scene's
    parameters: p_j of each cyclic coordinate, and h = Σ q̇ ∂L/∂q̇ − L when it is conserved (the
    energy when h = T + V, else the Jacobi integral); then what is not conserved and why (L
    depends on q_j, damping, a driven pivot …). ``latex``: formulas as LaTeX, the rest as
    ``%`` comments (needs SymPy, the ``pretty`` extra)."""
    rm = _reduced(scene_or_model, parameters)
    cons = conservation(rm)
    rs = symbolic_reduced(rm)
    ex = rs.expressions
    if latex:
        tex, name = latex_printer(rs)
        formula, p_name, note = tex, (lambda c: f"p_{{{name(c)}}}"), (lambda text: f"  % {text}")
    else:
        formula, p_name, note = pretty, (lambda c: f"p_{c}"), (lambda text: f"  ({text})")
    found, lost = [], []
    for j, c in enumerate(rm.coordinates):
        if c in cons.cyclic:
            found.append(f"{p_name(c)} = {formula(ex['p'][j])}"
                         + note(f"{c} is cyclic: ∂L/∂{c} = 0 and no force acts on {c}"))
        else:
            lost.append(f"p_{c} is not conserved: {cons.not_cyclic[c]}")
    found += _rigid_motion_lines(rm, rs, cons, formula, p_name, note)
    h = "h = Σ q_dot ∂L/∂q_dot − L"
    if cons.hamiltonian_conserved:
        kind = (f"h = T + V, the energy: {cons.hamiltonian_why}" if cons.hamiltonian_is_energy
                else f"the Jacobi integral: {cons.hamiltonian_why}; h ≠ T + V: {cons.energy_why}"
                + (", so T + V is not conserved" if rm.rheonomic else ""))
        found.append(f"h = {formula(ex['H'])}" + note(kind))
    else:
        lost.append(f"{h} is not conserved: {cons.hamiltonian_why}")
    comment = "% " if latex else ""
    if found:
        head = (f"{comment}conserved quantities (the momenta p_j of cyclic coordinates, Noether's charges "
                f"of the rigid motions that are symmetries, and {h} when ∂L/∂t = 0 and nothing does work):")
    else:
        head = f"{comment}conserved quantities: none found"
    return "\n".join([head, *[f"  {line}" for line in found], *[f"  {comment}{line}" for line in lost]])


def _rigid_motion_lines(rm, rs, cons, formula, p_name, note) -> list[str]:
    """A line for each rigid motion that is a symmetry (``rigid_symmetries``): its Noether charge
    in the coordinates, or the combination of cyclic momenta it equals; none when the charge
    vanishes identically (a motion that moves nothing the map can move)."""
    if rm.model is None:
        return []
    try:
        symmetries = rigid_symmetries(rm.model)
    except InputError:  # no states on the constraint manifold to sample: nothing to say
        return []
    cyclic = [j for j, c in enumerate(rm.coordinates) if c in cons.cyclic]
    lines = []
    for symmetry in symmetries:
        coefficients = combination_of(rm, charge_in_coordinates(rm, symmetry), cyclic)
        why = f"{symmetry.description} is a symmetry of L and of the constraints"
        if coefficients is None:
            lines.append(f"{symmetry.name} = {formula(charge_in_coordinates(rs, symmetry))}"
                         + note(f"{why}: Noether's charge"))
            continue
        terms = [(c, rm.coordinates[j]) for c, j in zip(coefficients, cyclic, strict=True)
                 if abs(c) > 1e-9 * max(1.0, float(np.max(np.abs(coefficients))))]
        if terms:
            combination = " + ".join(f"{p_name(name)}" if abs(c - 1) <= 1e-9 else f"{c:.6g}*{p_name(name)}"
                                     for c, name in terms).replace("+ -", "- ")
            numbers = any(abs(abs(c) - 1) > 1e-9 for c, _ in terms) and rm.system.parameters
            at = " (coefficients at the scene's parameter values)" if numbers else ""
            lines.append(f"{symmetry.name} = {combination}"
                         + note(f"{why}: the same conserved quantity{at}"))
    return lines


# --- a hand-derived constant of the motion ---------------------------------------------------------


def check_constant_of_motion(
    scene_or_model,
    constant: str,
    *,
    samples: int = 40,
    seed: int = 1,
    rtol: float = EQUATION_RTOL,
    parameters: dict | None = None,
) -> EquationCheck:
    """Is a hand-derived C(q, q̇, t) a constant of the motion?

    ``constant``: a formula (or ``"NAME = formula"``) in the coordinates, ``<q>_dot``, ``t`` and
    the parameters. Right when ``dC/dt = Σ ∂C/∂q_j q̇_j + Σ ∂C/∂q̇_j q̈_j + ∂C/∂t`` vanishes, relative
    to the sum of the sizes of those terms (``rtol``), at the random states of
    ``equations.regular_states``: q̈ from the derived equations (generalized forces included;
    with velocity constraints q̇ on them and q̈ from the Lagrange–d'Alembert equations). Right at
    the scene's parameter values, it is checked again at other values of the parameters it names
    (``ParameterVariation``). A wrong one gives dC/dt at the worst state, and says when C is a
    known quantity that is not conserved here (h with damping, T + V of a driven scene, p_j of a
    coordinate that is not cyclic), or c × a conserved one plus a remainder; a right one says when
    it is c × one the tool finds (``conservation``). InputError: unknown names, accelerations,
    a C that is not finite at a sampled state, and a C that depends on neither q nor q̇ (trivial).
    """
    rm = _reduced(scene_or_model, parameters)
    if isinstance(constant, int | float) and not isinstance(constant, bool):
        constant = repr(float(constant))
    if not isinstance(constant, str) or not constant.strip():
        raise InputError(f"must be a non-empty formula, got {constant!r}", where="constant")
    text = constant.strip()
    name, formula = "C", text
    if "=" in text:
        lhs, _, formula = (part.strip() for part in text.partition("="))
        if not lhs.isidentifier() or not formula or "=" in formula:
            raise InputError("write the constant of the motion as a formula or as 'NAME = formula', "
                             f"got {text!r}", where="constant")
        name = lhs
    used = expressions.free_names(formula)
    accelerations = sorted(used & {f"{c}_ddot" for c in rm.coordinates})
    if accelerations:
        raise InputError(f"{text!r} contains the acceleration {', '.join(accelerations)}: a constant of the "
                         "motion is a function of q, q_dot and t only (replace accelerations with the "
                         "equations of motion)", where="constant")
    expressions.parse(formula, _state_names(rm), where="constant")  # names checked before sampling

    def at(model: ReducedModel, values: str = "") -> EquationCheck:
        return _constant_at(model, regular_states(model, samples, seed), (text, name, formula), rtol, values)

    return beyond_scene_values(ParameterVariation(rm), at(rm), used, at)


def _known(rm: ReducedModel, cons: Conservation) -> list[tuple[str, str, ca.SX, bool, str]]:
    """The quantities the tool knows, (name, what it is, expression in rm's symbols, conserved,
    why): every p_j, h, and T + V when it is not h."""
    ex = rm.expressions
    out = [(f"p_{c}", f"∂L/∂{c}_dot", ex["p"][j], c in cons.cyclic,
            f"{c} is cyclic" if c in cons.cyclic else cons.not_cyclic[c])
           for j, c in enumerate(rm.coordinates)]
    h = "Σ q_dot ∂L/∂q_dot − L, " + ("= T + V here" if cons.hamiltonian_is_energy else "the Jacobi integral")
    out.append(("h", h, ex["H"], cons.hamiltonian_conserved, cons.hamiltonian_why))
    if not cons.hamiltonian_is_energy:
        out.append(("T + V", "kinetic plus potential energy", ex["T"] + ex["V"], False, cons.energy_why))
    return out


def _constant_at(rm: ReducedModel, st, given: tuple[str, str, str], rtol: float,
                 values: str) -> EquationCheck:
    text, name, formula = given
    label = f"{name} = {formula}"
    q, qd, t, n = rm.q, rm.q_dot, rm.t, rm.n
    C = ca.SX(expressions.parse(formula, _state_names(rm), where="constant"))
    cons = conservation(rm)
    known = _known(rm, cons)
    K = ca.vertcat(*[k[2] for k in known])
    f = ca.Function("constant_of_motion", [q, qd, t], [ca.densify(v) for v in (
        C, ca.gradient(C, q), ca.gradient(C, qd), ca.jacobian(C, t), K, ca.jacobian(K, ca.vertcat(q, qd)))])
    S, nk = len(st), len(known)
    Cv, G, rate, rel = np.zeros(S), np.zeros((S, 2 * n)), np.zeros(S), np.zeros(S)
    Kv, GK = np.zeros((S, nk)), np.zeros((S, nk, 2 * n))
    with np.errstate(all="ignore"):
        for i in range(S):
            c, gq, gv, gt, k, gk = (np.asarray(v, float) for v in f(st.q[i], st.q_dot[i], st.t[i]))
            terms = np.concatenate([gq.ravel() * st.q_dot[i], gv.ravel() * st.q_ddot[i], gt.ravel()])
            if not (np.all(np.isfinite(c)) and np.all(np.isfinite(terms)) and np.all(np.isfinite(gq))
                    and np.all(np.isfinite(gv))):
                state = _state_of(rm, st.q[i], st.q_dot[i], st.t[i])
                raise not_finite(f"the constant {label}", state, values)
            rate[i] = float(np.sum(terms))
            rel[i] = abs(rate[i]) / (float(np.sum(np.abs(terms))) or 1.0)
            Cv[i], G[i] = float(c.ravel()[0]), np.concatenate([gq.ravel(), gv.ravel()])
            Kv[i], GK[i] = k.ravel(), gk
    _refuse_trivial(rm, st, label, Cv, G)
    i = int(np.argmax(rel))
    state = _state_of(rm, st.q[i], st.q_dot[i], st.t[i], st.q_ddot[i])
    how = "q_ddot from the derived equations"
    if rm.n_velocity_rows:
        how += ", q_dot on the velocity constraints"
    d = f"d{name}/dt"
    if rel[i] > rtol:
        hints = _wrong_hints(rm, cons, known, (Cv, Kv, G, GK), name, formula)
        message = (f"{label} is not conserved: {d} = {rate[i]:.6g} ({rel[i]:.3g} of the size of its terms) "
                   f"at {_state_text(state)} ({how}){hints}")
        return EquationCheck(text, False, abs(rate[i]), float(rel[i]), message, state, label)
    match = _multiple(Cv, Kv, [k for k in range(nk) if known[k][3]])
    same = (f"it is {_times(*match[1:], known[match[0]][0])} ({known[match[0]][1]}), which the tool finds"
            if match else
            "not one the tool finds (the momenta of cyclic coordinates and h)")
    message = (f"{label} is a constant of the motion: {d} = Σ ∂{name}/∂q q_dot + Σ ∂{name}/∂q_dot q_ddot "
               f"+ ∂{name}/∂t vanishes along the derived equations (largest relative value {rel[i]:.2g} over "
               f"{S} random states{st.note()}, {how}; {same})")
    return EquationCheck(text, True, abs(rate[i]), float(rel[i]), message, state, label)


def _refuse_trivial(rm: ReducedModel, st, label: str, Cv: np.ndarray, G: np.ndarray) -> None:
    """InputError when C depends on neither q nor q̇, or takes one value at every sampled state
    (with velocity constraints: a function of them, 0 along every motion allowed)."""
    variables = ", ".join([*rm.coordinates, *[f"{c}_dot" for c in rm.coordinates]])
    if np.all(np.sum(np.abs(G), axis=1) <= TRIVIAL_RTOL * np.abs(Cv)):
        raise InputError(f"{label} is trivial: it depends on neither the coordinates nor their rates (a "
                         "constant is conserved whatever the motion, and a function of t alone is not "
                         f"conserved unless it is constant); give a function of {variables}",
                         where="constant")
    z = np.abs(np.concatenate([st.q, st.q_dot], axis=1)) + 1.0
    size = float(np.max(np.abs(Cv) + np.sum(np.abs(G) * z, axis=1)))
    if np.ptp(Cv) <= 1e-10 * size:
        why = (" (q_dot on the velocity constraints: a function of the constraints is constant along "
               "every motion they allow)" if rm.n_velocity_rows else "")
        raise InputError(f"{label} is trivial: it takes the same value, {Cv[0]:.6g}, at every sampled "
                         f"state{why}; give a quantity that differs from one motion to another",
                         where="constant")


def _times(c: float, c0: float, what: str) -> str:
    factor = "" if abs(c - 1.0) <= 1e-9 else f"{c:.6g} × "
    return factor + what + (f" + {c0:.6g}" if c0 else "")


def _multiple(Cv: np.ndarray, Kv: np.ndarray, among: list[int]) -> tuple[int, float, float] | None:
    """(k, c, c0) when C = c K_k + c0 at every sampled state, for the first such k in ``among``."""
    size = float(np.max(np.abs(Cv))) or 1.0
    for k in among:
        Kk = Kv[:, k]
        if not np.all(np.isfinite(Kk)) or np.ptp(Kk) <= 1e-12 * (float(np.max(np.abs(Kk))) or 1.0):
            continue
        A = np.column_stack([Kk, np.ones_like(Kk)])
        (c, c0), *_ = np.linalg.lstsq(A, Cv, rcond=None)
        scale = max(size, float(np.max(np.abs(c * Kk))))
        if c != 0.0 and np.max(np.abs(Cv - A @ [c, c0])) <= MATCH_RTOL * scale:
            return k, float(c), float(c0) if abs(c0) > MATCH_RTOL * size else 0.0
    return None


def _wrong_hints(rm, cons, known, values, name: str, formula: str) -> str:
    """Why a wrong C is close to something: a known quantity not conserved here, or c × a conserved
    one plus a remainder (printed in the parameters' names) that does not depend on some q or q̇."""
    Cv, Kv, G, GK = values
    hints = ""
    match = _multiple(Cv, Kv, [k for k in range(len(known)) if not known[k][3]])
    if match:
        k, c, c0 = match
        hints += (f"; it is {_times(c, c0, known[k][0])} ({known[k][1]}), which is not conserved here: "
                  f"{known[k][4]}")
    tiny = 1e-12 * (float(np.max(np.abs(G))) or 1.0)
    variables = [*rm.coordinates, *[f"{c}_dot" for c in rm.coordinates]]
    for k in (k for k in range(len(known)) if known[k][3]):
        for v in range(G.shape[1]):
            dC, dK = G[:, v], GK[:, k, v]
            mask = np.abs(dK) > tiny
            if not np.any(np.abs(dC) > tiny) or np.any(np.abs(dC[~mask]) > tiny) or np.sum(mask) < 2:
                continue
            ratio = dC[mask] / dK[mask]
            c = float(np.median(ratio))
            if c == 0.0 or np.max(np.abs(ratio - c)) > MATCH_RTOL * abs(c):
                continue  # C − c K still depends on this variable: try the next
            c = 1.0 if abs(c - 1.0) <= 1e-9 else c
            rs = symbolic_reduced(rm)
            Cs = ca.SX(expressions.parse(formula, _state_names(rs), where="constant"))
            rest = pretty(Cs - c * _known(rs, cons)[k][2])
            short, what, _, _, why = known[k]
            rate = f"d/dt ({rest})"
            if len(rest) > 300:
                rest, rate = f"a remainder that does not depend on {variables[v]}", "the remainder's rate"
            return hints + (f"; it is {_times(c, 0.0, short)} ({what}) plus {rest}: {short} is conserved "
                            f"({why}), so d{name}/dt = {rate}")
    return hints
