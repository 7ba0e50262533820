"""Hand-derived equations of motion checked against the reduced route (``check_equations``): at
random states (q, q̇, t) the accelerations q̈ come from ``M q̈ = rhs``; a right equation (any
nonzero multiple or combination of Lagrange's equations) then vanishes, relative to the size of
its terms.

Shared with the other candidate checks (constrained.analysis.candidates): the random states where
the derived equations determine q̈ (``regular_states``), and other values of the parameters a
candidate names (``ParameterVariation``): a slip such as l1 for l2 is invisible at l1 = l2, so a
candidate right at the scene's values is checked again where they differ."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import InputError
from ..model import expressions
from ..run.reduced import ReducedModel

#: A candidate equation is right when |residual| ≤ EQUATION_RTOL × (sum of |terms|) everywhere.
EQUATION_RTOL = 1e-8
#: A sampled state is dropped when the mass matrix there, scaled to a unit diagonal, has its
#: smallest singular value below this × its largest: the coordinates are singular there (the
#: pole of spherical angles), q̈ is not determined, and no candidate can be judged.
SINGULAR_RTOL = 1e-10
#: Other sets of parameter values each candidate is checked at, and the range of the random
#: relative change: each named parameter is multiplied by exp(±u), u uniform in VARIATION, so
#: values that were equal (l1 = l2 = 1) become distinct and no sign changes.
VARIANTS = 2
VARIATION = (0.15, 0.45)


def _reduced(scene_or_model, parameters=None) -> ReducedModel:
    if isinstance(scene_or_model, ReducedModel):
        return scene_or_model
    return ReducedModel.from_scene(scene_or_model, parameters=parameters)


@dataclass
class EquationCheck:
    """The verdict on one candidate equation.

    ``residual`` is the largest |lhs − rhs| found with q̈ from Lagrange's equations,
    ``relative_residual`` the largest ratio of it to the sum of the sizes of the terms.
    ``message`` starts with ``label`` (the candidate as named in it); ``parameters``: the
    parameter values of the verdict when they are not the scene's (a slip the scene's values hide).
    """

    equation: str
    ok: bool
    residual: float
    relative_residual: float
    message: str
    state: dict = field(default_factory=dict)
    label: str = ""
    parameters: dict = field(default_factory=dict)

    def __bool__(self) -> bool:
        return self.ok


def _split(text: str, where: str) -> tuple[str, str | None]:
    if not isinstance(text, str) or not text.strip():
        raise InputError(f"an equation must be a non-empty string, got {text!r}", where=where)
    for sign in ("<", ">", "!"):
        if sign in text:
            raise InputError(f"{text!r} is not an equation: '{sign}' compares; write 'lhs = rhs', or an "
                             "expression that is zero", where=where)
    stripped = text.replace("==", "=")
    parts = stripped.split("=")
    if len(parts) > 2:
        raise InputError(f"equation {text!r} has more than one '='", where=where)
    if len(parts) == 2:
        if not parts[0].strip() or not parts[1].strip():
            raise InputError(f"equation {text!r} has an empty side", where=where)
        return parts[0].strip(), parts[1].strip()
    return parts[0].strip(), None


def _state_of(rm: ReducedModel, q, qd, t, qdd=None) -> dict:
    state = {c: float(q[j]) for j, c in enumerate(rm.coordinates)}
    state.update({f"{c}_dot": float(qd[j]) for j, c in enumerate(rm.coordinates)})
    if qdd is not None:
        state.update({f"{c}_ddot": float(qdd[j]) for j, c in enumerate(rm.coordinates)})
    state["t"] = float(t)
    return state


def _state_text(state: dict) -> str:
    return ", ".join(f"{n} = {v:.6g}" for n, v in state.items())


# --- the states a candidate is judged at ------------------------------------------------------


@dataclass
class States:
    """Random states (q, q̇, t) where the derived equations determine q̈, with q̈ and, with
    velocity constraints, the multipliers μ; ``dropped`` states were singular (the first one
    as text in ``dropped_at``)."""

    q: np.ndarray
    q_dot: np.ndarray
    t: np.ndarray
    q_ddot: np.ndarray
    mu: np.ndarray
    dropped: int = 0
    dropped_at: str = ""
    narrowed: str = ""

    def __len__(self) -> int:
        return len(self.t)

    def note(self) -> str:
        """'' or what limits the states: singular ones left out, a map defined near q0 only."""
        text = f"; {self.narrowed}" if self.narrowed else ""
        if self.dropped:
            text += (f"; {self.dropped} sampled state(s) left out where the derived equations do not "
                     f"determine q̈, e.g. {self.dropped_at}")
        return text


def _singular(M: np.ndarray) -> bool:
    """Whether M, scaled to a unit diagonal (so that 1 g beside 1 kg is not "singular"), has a
    smallest singular value at most SINGULAR_RTOL × its largest."""
    d = np.diag(M)
    if not np.all(np.isfinite(M)) or np.any(d <= 0.0):
        return True
    s = 1.0 / np.sqrt(d)
    sv = np.linalg.svd(M * np.outer(s, s), compute_uv=False)
    return bool(sv[-1] <= SINGULAR_RTOL * sv[0])


#: Why a sampled state was left out: the reason's text in the verdict.
_DROPPED = {
    "singular": "the coordinates are singular there: ∂²L/∂q̇² singular, so q̈ is not determined",
    "map": "the map is not finite there",
    "overflow": "q̈ is not finite there though ∂²L/∂q̇² is regular: the equations overflow, so check "
                "the parameter values (rescale the units)",
}


def regular_states(rm: ReducedModel, samples: int, seed: int) -> States:
    """``samples`` random states (``ReducedModel.sample_states``), the rates brought onto the
    velocity constraints, q̈ (and μ) from the derived equations; states where the mass matrix is
    singular or q̈ not finite are left out, and InputError when none is left."""
    Q, Qd, Ts = rm.sample_states(samples, seed)
    keep, acc, mus, dropped = [], [], [], []
    with np.errstate(all="ignore"):
        for i in range(samples):
            if not np.all(np.isfinite(np.asarray(rm.position(Q[i], Ts[i]), float))):
                dropped.append((i, "map"))
                continue
            try:
                qd = rm.consistent_rates(Q[i], Qd[i], Ts[i])
                M = np.asarray(rm.mass_rhs(Q[i], qd, Ts[i])[0], float)
                a = np.asarray(rm.acceleration(Q[i], qd, Ts[i]), float).ravel()
                mu = (np.asarray(rm.velocity_multipliers(Q[i], qd, Ts[i]), float).ravel()
                      if rm.n_velocity_rows else np.zeros(0))
            except np.linalg.LinAlgError:
                dropped.append((i, "singular"))
                continue
            if _singular(M) or not (np.all(np.isfinite(a)) and np.all(np.isfinite(mu))):
                dropped.append((i, "singular" if _singular(M) else "overflow"))
                continue
            Qd[i] = qd
            keep.append(i)
            acc.append(a)
            mus.append(mu)
    first, why = "", ""
    if dropped:
        i, reason = dropped[0]
        first, why = _state_text(_state_of(rm, Q[i], Qd[i], Ts[i])), _DROPPED[reason]
    if not keep:
        advice = ("; move the [reduced] initial values away from that point" if why == _DROPPED["singular"]
                  else "")
        raise InputError(f"the derived Lagrange equations do not determine q̈ at any of {samples} sampled "
                         f"states (e.g. at {first}): {why}{advice}", where="reduced")
    narrowed = ""
    if np.any(rm.spread < np.maximum(1.0, np.abs(rm.initial))):  # check_map found the map's domain
        half = zip(rm.coordinates, rm.spread / 2, strict=True)
        narrowed = ("states within " + ", ".join(f"{c} ± {h:.3g}" for c, h in half)
                    + " of the initial values, where the map is defined")
    return States(Q[keep], Qd[keep], Ts[keep], np.array(acc), np.array(mus).reshape(len(keep), -1),
                  len(dropped), f"{first}: {why}" if dropped else "", narrowed)


def not_finite(label: str, state: dict, values: str = "") -> InputError:
    """The InputError for a candidate that has no finite value at a state where the derived
    equations are regular."""
    at = f" with {values}" if values else ""
    return InputError(
        f"{label} is not finite at {_state_text(state)}{at}, where the derived equations are regular: "
        "the formula divides by zero there, leaves a function's domain (log, sqrt of a negative "
        "number) or overflows; write it in a form that is finite there (multiply through by the "
        "denominator), or move the [reduced] initial values away")


# --- other parameter values ---------------------------------------------------------------------


class ParameterVariation:
    """The scene's derived equations at other values of the parameters a candidate names.

    At the scene's values a slip can cancel out: with l1 = l2 = 1 an equation with l1 in place of
    l2 holds exactly. Varied: the scene's [parameters] that its derived equations (L, R, the
    applied forces, the velocity constraints) depend on and the candidate names, each multiplied
    by its own random exp(±u) (VARIATION), in VARIANTS sets. Held: parameters the equations do
    not depend on (the candidate's name stands for its value), parameters whose value is 0, and
    parameters the equations depend on that the candidate does not name (a number written in
    their place holds only at their value).
    """

    def __init__(self, rm: ReducedModel, seed: int = 3):
        from .printing import symbolic_reduced

        self.rm = rm
        system = rm.system
        self.own = [k for k in system.parameters if k in rm.parameters]
        self.extra = {k: v for k, v in rm.parameters.items()
                      if k not in system.parameters and k not in system.definitions}
        self.dependent: list[str] = []
        if self.own:
            rs = symbolic_reduced(rm)
            ex = rs.expressions
            derived = ca.veccat(ex["L"], ex["R"], ex["Q"], ex["velocity_rows"])
            self.dependent = [k for k in self.own if ca.depends_on(derived, ca.SX(rs.parameters[k]))]
        rng = np.random.default_rng(seed)
        self.factors = [{k: float(np.exp(rng.choice((-1.0, 1.0)) * rng.uniform(*VARIATION)))
                         for k in self.dependent} for _ in range(VARIANTS)]
        self._models: dict = {}

    def expand(self, named) -> set[str]:
        """``named`` with the parameters its definitions are made of (M = mP + 2*mS names mP, mS)."""
        definitions = self.rm.system.definitions
        out, todo = set(), list(named)
        while todo:
            k = todo.pop()
            if k not in out:
                out.add(k)
                if k in definitions:
                    todo += sorted(expressions.free_names(str(definitions[k])))
        return out

    def varied(self, named) -> list[str]:
        """The parameters among ``named`` that are varied (in the scene's order)."""
        return [k for k in self.dependent if k in named and self.rm.parameters[k] != 0.0]

    def model(self, k: int, names) -> tuple[ReducedModel, dict]:
        """The reduced model with ``names`` changed by the factors of set ``k`` (the rest at the
        scene's values), and the values used: the reciprocal changes where the map is not defined
        at the initial values with the first (X = 0.9 beside l shrunk below it). InputError when
        the scene cannot be built either way (a mass formula turning negative)."""
        key = (k, tuple(names))
        if key not in self._models:
            self._models[key] = self._build(k, names)
        built = self._models[key]
        if isinstance(built, InputError):
            raise built
        return built

    def _build(self, k: int, names):
        rm, error = self.rm, None
        for power in (1.0, -1.0):
            values = {n: float(rm.parameters[n]) * self.factors[k][n] ** power for n in names}
            try:
                model = ReducedModel(
                    rm.system, rm.coordinates, rm.map, parameters={**self.extra, **values},
                    initial=dict(zip(rm.coordinates, rm.initial, strict=True)),
                    rates=dict(zip(rm.coordinates, rm.rates, strict=True)), t0=rm.t0, check=False)
            except InputError as exc:
                error = exc
                continue
            with np.errstate(all="ignore"):
                x0 = np.asarray(model.position(rm.initial, rm.t0), float)
            if np.all(np.isfinite(x0)):
                model.spread = rm.spread.copy()
                return model, values
            error = InputError(f"the map is not finite at the initial values with {_values_text(values)}")
        return error

    def held(self, named, fixed) -> str:
        """What the verdict could not vary, for its message ('' when nothing that matters):
        named parameters at 0, named parameters the equations do not depend on, and ``fixed``,
        parameters it does not name whose other values make it fail."""
        scene = self.rm.parameters
        parts = []
        zero = [k for k in self.dependent if k in named and scene[k] == 0.0]
        if zero:
            parts.append(f"{', '.join(zero)} held at 0 (a relative change keeps 0: give "
                         f"{'them' if len(zero) > 1 else 'it'} another value with --set to check "
                         "the terms it multiplies)")
        unused = [k for k in sorted(named) if k in self.own and k not in self.dependent]
        if unused:
            values = ", ".join(f"{k} = {scene[k]:g}" for k in unused)
            parts.append(f"{values} held (the scene's equations do not depend on "
                         f"{'them' if len(unused) > 1 else 'it'}: the name stands for this value)")
        if fixed:
            values = ", ".join(f"{k} = {scene[k]:g}" for k in fixed)
            parts.append(f"right for {values} only: it does not name {'them' if len(fixed) > 1 else 'it'} "
                         "and fails at other values (a number written in place of a parameter?)")
        return "; " + "; ".join(parts) if parts else ""


def beyond_scene_values(variation: ParameterVariation, check: EquationCheck, named,
                        check_at: Callable[[ReducedModel, str], EquationCheck]) -> EquationCheck:
    """``check`` (a verdict at the scene's parameter values) checked again at VARIANTS other
    sets of values of the parameters ``named`` (``check_at(model, values_text)``): right there
    too, or WRONG with where it fails and which parameters, changed alone, make it fail. A right
    one is also tried with each parameter it does not name changed alone: one whose change makes
    it fail is named in the verdict (right for that value only)."""
    if not check.ok:
        return check
    scene = variation.rm.parameters
    named = variation.expand(named)

    def fails(k: int, names: list) -> bool:
        try:
            model, values = variation.model(k, names)
            return not check_at(model, _values_text(values)).ok
        except InputError:
            return False

    fixed = [u for u in variation.dependent if u not in named and scene[u] != 0.0 and fails(0, [u])]
    held = variation.held(named, fixed)
    names = variation.varied(named)
    if not names:
        return _appended(check, held)
    for k in range(VARIANTS):
        try:
            model, values = variation.model(k, names)
            text = _values_text(values)
            other = check_at(model, text)
        except InputError as exc:
            why = f"; not checked at other values of {', '.join(names)}: {exc.reason}"
            return _appended(check, why + held)
        if other.ok:
            continue
        alone = [n for n in names if fails(k, [n])] if len(names) > 1 else []
        was = ", ".join(f"{n} = {scene[n]:g}" for n in names)
        blame = (f"; it fails when {' or '.join(alone)} alone changes: look for a slip in "
                 f"{'them' if len(alone) > 1 else 'it'}" if alone else "")
        finding = other.message[len(other.label):] if other.message.startswith(other.label) else other.message
        where = f"at {text} it{finding}" if finding.startswith(" ") else f"at {text}{finding}"
        message = (f"{check.label} holds at the scene's parameter values ({was}), which hide a slip: "
                   f"{where}{blame} (meant for these values only, it is right for them)")
        return EquationCheck(check.equation, False, other.residual, other.relative_residual, message,
                             other.state, check.label, values)
    return _appended(check, f"; also at {VARIANTS} other sets of values of {', '.join(names)}{held}")


def _values_text(values: dict) -> str:
    return ", ".join(f"{n} = {v:.6g}" for n, v in values.items())


def _appended(check: EquationCheck, text: str) -> EquationCheck:
    if text:
        closing = check.message.endswith(")")
        check.message = check.message[:-1] + text + ")" if closing else check.message + text
    return check


# --- equations of motion --------------------------------------------------------------------------


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
    of motion, and is reported as not ok. Unknown names raise InputError, and so does an
    equation that is not finite at a sampled state. States where the coordinates are singular
    (M not invertible) are left out. An equation right at the scene's parameter values is
    checked again with the parameters it names changed (``ParameterVariation``).

    With velocity constraints the states have q̇ on them (``consistent_rates``), q̈ and the
    multipliers ``mu1, mu2 …`` (one per velocity row, in order) come from the
    Lagrange–d'Alembert equations ``M q̈ = rhs + Ãᵀμ``, and equations may use the ``mu``.
    """
    rm = _reduced(scene_or_model, parameters)
    if isinstance(equations, str):
        equations = [equations]
    sides = [_split(text, f"equation {k + 1}") for k, text in enumerate(equations)]
    states: dict = {}

    def at(model: ReducedModel, k: int, values: str = "") -> EquationCheck:
        if id(model) not in states:
            states[id(model)] = (model, regular_states(model, samples, seed))
        return _check_one(model, states[id(model)][1], k, equations[k], sides[k], rtol, values)

    variation = ParameterVariation(rm)
    out = []
    for k in range(len(equations)):
        named = set().union(*(expressions.free_names(s) for s in sides[k] if s is not None))
        out.append(beyond_scene_values(variation, at(rm, k), named,
                                       lambda model, values, k=k: at(model, k, values)))
    return out


def _check_one(rm: ReducedModel, st: States, k: int, text: str, sides, rtol: float,
               values: str) -> EquationCheck:
    """One equation at the states ``st`` of ``rm`` (the names take ``rm``'s parameter values)."""
    where = f"equation {k + 1}"
    label = f"equation {k + 1} ({text})"
    names = dict(rm.names)
    mu = ca.SX.sym("mu", rm.n_velocity_rows)
    names.update({f"mu{j + 1}": mu[j] for j in range(rm.n_velocity_rows) if f"mu{j + 1}" not in names})
    lhs, rhs = sides
    expr = ca.SX(expressions.parse(lhs, names, where=where))
    terms = expressions.terms(lhs, names, where=where)
    if rhs is not None:
        expr = expr - expressions.parse(rhs, names, where=where)
        terms += expressions.terms(rhs, names, where=where)
    f = ca.Function("candidate", [rm.q, rm.q_dot, rm.q_ddot, rm.t, mu],
                    [expr, ca.densify(ca.vertcat(*[ca.SX(s) for s in terms])), ca.gradient(expr, rm.q_ddot)])
    worst_rel, worst_abs, worst_i, involves_acc = -1.0, 0.0, 0, False
    with np.errstate(all="ignore"):
        for i in range(len(st)):
            args = (st.q[i], st.q_dot[i], st.q_ddot[i], st.t[i])
            e, tv, g = (np.asarray(v, float) for v in f(*args, st.mu[i]))
            e = float(e.ravel()[0])
            if not (np.isfinite(e) and np.all(np.isfinite(tv))):
                raise not_finite(label, _state_of(rm, st.q[i], st.q_dot[i], st.t[i], st.q_ddot[i]), values)
            scale = float(np.sum(np.abs(tv))) or 1.0
            involves_acc = involves_acc or bool(np.any(np.abs(g) > 0))
            rel = abs(e) / scale
            if rel > worst_rel:
                worst_rel, worst_abs, worst_i = rel, abs(e), i
    state = _state_of(rm, st.q[worst_i], st.q_dot[worst_i], st.t[worst_i], st.q_ddot[worst_i])
    if worst_rel > rtol:
        ok = False
        message = (
            f"{label} disagrees with Lagrange's equations by {worst_abs:.3g} "
            f"({worst_rel:.3g} of the size of its terms) at {_state_text(state)} (accelerations from "
            "Lagrange's equations)"
        )
    elif not involves_acc:
        ok = False
        message = (f"{label} holds at every sampled state but contains no acceleration: it is an "
                   "identity, not an equation of motion")
    else:
        ok = True
        message = (f"{label} holds whenever Lagrange's equations do (largest relative residual "
                   f"{worst_rel:.2g} over {len(st)} random states{st.note()})")
    return EquationCheck(text, ok, worst_abs, worst_rel, message, state, label)
