"""Symmetries and Noether charges, in Cartesian coordinates and in generalized coordinates.

A one-parameter family of point transformations ``x → x + s·ξ(x) + O(s²)`` is a symmetry
of ``L = T − V − U`` (with the constraints) when, on the constraint manifold,

- ``δL = ∂L/∂x · ξ + ∂L/∂v · ξ̇ = 0`` with ``ξ̇ = (∂ξ/∂x) v`` (the prolonged generator),
- ``δf = J ξ = 0`` for every constraint row (the family maps the manifold onto itself),
- ``F_nc · ξ = 0`` for dissipative and applied forces (else ``dQ/dt = F_nc · ξ``).

Then Noether's charge ``Q = Σ_i ∂L/∂v_i · ξ_i``, ``∂L/∂v_i = m_i v_i − ∂U/∂v_i``, is
conserved; constraint forces ``Jᵀλ`` do no work along ``ξ`` because ``J ξ = 0``. For the
electromagnetic ``U = q(φ − v·A)``, ``∂L/∂v = m v + q A`` (the canonical momentum).

Generators: a translation ``ε`` (``ξ_i = ε``) and a rotation ``(axis, point)``
(``ξ_i = n × (x_i − c)``, ``n = axis/|axis|``); both together add up (a screw motion).

In generalized coordinates the user gives ``∂q/∂s = ξ(q, t)`` as formulas, and
``Q = p · ξ`` with ``p = ∂L/∂q̇``. Also here: the Euler–Lagrange residual of any CasADi
Lagrangian, and adding a total time derivative ``dF(q, t)/dt`` to a Lagrangian.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import InputError
from ..manifold.manifold import Manifold
from ..model import expressions
from ..model.structure import Model, assemble
from ..run.trajectory import Trajectory

__all__ = [
    "SymmetryReport",
    "charge_drift",
    "euler_lagrange",
    "is_symmetry",
    "is_symmetry_reduced",
    "jacobi_integral",
    "noether_charge",
    "noether_charge_reduced",
    "with_total_derivative",
]

#: A term changes under the symmetry when |δterm| > SYMMETRY_RTOL × (size of its variation terms).
SYMMETRY_RTOL = 1e-9
_TINY = np.finfo(float).tiny


# --- Cartesian generators ---------------------------------------------------------------------


def _model(model_or_system) -> Model:
    return model_or_system if isinstance(model_or_system, Model) else assemble(model_or_system)


def _vector3(value, where: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float).ravel() if not isinstance(value, str) else np.zeros(0)
    if arr.size != 3 or not np.all(np.isfinite(arr)):
        raise InputError(f"must be 3 finite numbers, got {value!r}", where=where)
    return arr


def _generator(model: Model, translation, rotation) -> tuple[ca.SX, str]:
    """ξ(x) ∈ R^(3N) and a description of the transformation."""
    if translation is None and rotation is None:
        raise InputError("declare a symmetry: give translation=ε and/or rotation=(axis, point)",
                         where="symmetry")
    x = model.symbols.x
    n = model.n_particles
    xi = ca.SX.zeros(3 * n)
    parts = []
    if translation is not None:
        eps = _vector3(translation, "translation")
        xi += ca.DM(np.tile(eps, n))
        parts.append(f"translation along ({', '.join(f'{e:g}' for e in eps)})")
    if rotation is not None:
        if isinstance(rotation, str) or not isinstance(rotation, Sequence | np.ndarray) or len(rotation) != 2:
            raise InputError(f"must be (axis, point), got {rotation!r}", where="rotation")
        axis = _vector3(rotation[0], "rotation axis")
        point = _vector3(rotation[1], "rotation point")
        norm = float(np.linalg.norm(axis))
        if norm == 0:
            raise InputError("the rotation axis must not be the zero vector", where="rotation axis")
        nvec = ca.DM(axis / norm)
        for i in range(n):
            xi[3 * i : 3 * i + 3] += ca.cross(nvec, x[3 * i : 3 * i + 3] - ca.DM(point))
        parts.append(f"rotation about ({', '.join(f'{a:g}' for a in axis / norm)}) through "
                     f"({', '.join(f'{c:g}' for c in point)})")
    return xi, " plus ".join(parts)


def _lagrangian_parts(model: Model):
    """Per-effect terms (kind, label, expression) built on the model's own symbols."""
    s = model.symbols
    parts = []
    for effect in model.system.effects:
        parts.append((effect.slot, effect.label, ca.SX(effect.term(s))))
    return parts


def canonical_momentum(model: Model) -> ca.SX:
    """∂L/∂v = M v − ∂U/∂v (3N), on the model's symbols."""
    return momentum_of(model.symbols, model.system.effects, ca.DM(model.masses))


def momentum_of(s, effects, masses) -> ca.SX:
    """``masses ∘ v − ∂U/∂v`` on the symbols ``s`` (U: the generalized potentials among
    ``effects``; ``masses``: 3N, numbers or formulas)."""
    U = sum((ca.SX(e.term(s)) for e in effects if e.slot == "generalized_potential"), ca.SX(0))
    return masses * s.v - ca.gradient(U, s.v)


def _columns(trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.asarray(trajectory.t, float).ravel()
    n = len(t)
    return np.asarray(trajectory.x, float).reshape(n, -1), np.asarray(trajectory.v, float).reshape(n, -1), t


def _along(function: ca.Function, *columns: np.ndarray) -> np.ndarray:
    """Evaluate ``function`` at each row of the (T, k) columns; (T, out) array."""
    n = len(columns[0])
    if n == 0:
        return np.zeros((0, function.size1_out(0)))
    args = [np.asarray(c, float).reshape(n, -1).T for c in columns]
    return np.asarray(function.map(n)(*args)).T.reshape(n, -1)


def noether_charge(model, trajectory: Trajectory, *, translation=None, rotation=None) -> np.ndarray:
    """Noether charge ``Q = Σ_i (m_i v_i − ∂U/∂v_i) · ξ_i`` at each sample of ``trajectory``.

    ``model``: a Model or a System. ``translation``: ε (ξ_i = ε, Q = ε·P for plain particles);
    ``rotation``: (axis, point) (ξ_i = n × (x_i − c), Q = n·Σ (x_i − c) × p_i). For the
    electromagnetic effect p_i = m_i v_i + q_i A(x_i, t). Returns a (T,) array.
    """
    model = _model(model)
    s = model.symbols
    xi, _ = _generator(model, translation, rotation)
    Q = ca.dot(canonical_momentum(model), xi)
    fun = ca.Function("noether_charge", [s.x, s.v, s.t], [Q], ["x", "v", "t"], ["Q"])
    return _along(fun, *_columns(trajectory)).ravel()


# --- is it a symmetry? ------------------------------------------------------------------------


@dataclass
class SymmetryReport:
    """Whether a declared transformation leaves L and the constraints invariant.

    ``changes``: term name -> largest relative first-order change found
    (|δterm| / size of its variation terms); ``breaking``: the names above ``rtol``.
    Truthy when the transformation is a symmetry (its Noether charge is then conserved).
    """

    transformation: str
    holds: bool
    breaking: list[str]
    changes: dict[str, float] = field(default_factory=dict)
    message: str = ""
    samples: int = 0

    def __bool__(self) -> bool:
        return self.holds


def manifold_samples(model: Model, samples: int, seed: int):
    """Random (x, v, t) on f = 0, J v + f_t = 0 near the system's start (the start first).

    The positions are spread by 0.3 of the system's size, halved after each point the
    projection cannot bring onto f = 0: the size counts |x_i|, so a 1 m pendulum hung 10 km from
    the origin is spread by metres after a dozen halvings, not by kilometres it cannot return
    from (which left 2 states of 12 and rigid motions that 2 states could not rule out)."""
    system = model.system
    rng = np.random.default_rng(seed)
    x0 = system.positions.ravel()
    v0 = system.velocities.ravel()
    size = system.size()
    vscale = max(float(np.max(np.abs(v0), initial=0.0)), 1.0)
    out = []
    tries = 0
    spread = 0.3 * size
    while len(out) < samples and tries < 5 * samples:
        tries += 1
        first = not out
        t = 0.0 if first else float(rng.uniform(0.0, 1.0))
        x = x0 + (0.0 if first else spread) * rng.standard_normal(x0.size)
        v = v0 if first else v0 + vscale * rng.standard_normal(v0.size)
        manifold = Manifold.at(model, x, t)
        projected = manifold.project_positions(x, t, tol=1e-13 * size, max_iter=50)
        x, err = projected.x, projected.residual
        if not np.isfinite(err) or err > 1e-9 * size:
            spread *= 0.5
            continue
        v = manifold.project_velocities(x, v, t)
        if np.all(np.isfinite(v)):
            out.append((x, v, t))
    if not out:
        raise InputError("could not find states on the constraint manifold near the start")
    return out


def variation_checks(model: Model, xi: ca.SX) -> list[tuple[str, ca.SX, ca.SX]]:
    """(name, change, scale) of each term under ``x → x + s·ξ(x)`` (see ``is_symmetry``): the
    first-order change of T, each potential and generalized potential, the power of each
    dissipation and applied force along ξ, and ``∇c_k·ξ`` of each constraint row (a velocity
    row's by v); ``scale`` is the size of the change's terms, for a relative test."""
    s = model.symbols
    x, v = s.x, s.v
    xi_dot = ca.jtimes(xi, x, v)
    nxi, nxid = ca.norm_2(xi), ca.norm_2(xi_dot)
    checks: list[tuple[str, ca.SX, ca.SX]] = []

    def scalar_term(name: str, e: ca.SX) -> None:
        gx, gv = ca.gradient(e, x), ca.gradient(e, v)
        checks.append((name, ca.dot(gx, xi) + ca.dot(gv, xi_dot), ca.norm_2(gx) * nxi + ca.norm_2(gv) * nxid))

    scalar_term("kinetic energy", 0.5 * ca.dot(ca.DM(model.masses) * v, v))
    kinds = {"potential": "potential", "generalized_potential": "generalized potential"}
    for slot, label, e in _lagrangian_parts(model):
        if slot in kinds:
            scalar_term(f"{kinds[slot]} '{label}'", e)
        elif slot == "dissipation":
            dR = ca.gradient(e, v)
            checks.append((f"dissipation '{label}'", ca.dot(dR, xi), ca.norm_2(dR) * nxi))
        elif slot == "applied_force":
            checks.append((f"applied force '{label}'", ca.dot(e, xi), ca.norm_2(e) * nxi))
    for k, constraint in enumerate(model.system.constraints):
        # d/dt (p·ξ) = δL + λ·(J ξ) + μ·(A ξ): a row must not act along ξ (a velocity row's A = ∂c/∂v)
        by = v if getattr(constraint, "level", "position") == "velocity" else x
        for row, label in constraint.rows(s):
            g = ca.gradient(row, by)
            checks.append((f"constraint {k} ({label})", ca.dot(g, xi), ca.norm_2(g) * nxi))
    return checks


def is_symmetry(model, *, translation=None, rotation=None, samples: int = 20, seed: int = 0,
                rtol: float = SYMMETRY_RTOL) -> SymmetryReport:
    """Check a declared symmetry at ``samples`` random states on the constraint manifold.

    For each term of L (``T``, each potential V, each generalized potential U):
    ``δ = ∂term/∂x·ξ + ∂term/∂v·ξ̇``, ``ξ̇ = (∂ξ/∂x) v``; for each constraint row ``J_k ξ``;
    for each dissipation R and applied force F the power along ξ, ``−∂R/∂v·ξ`` and ``F·ξ``;
    for each velocity row ``A_k ξ`` (its force's power along ξ, d'Alembert: the charge of a
    symmetry the velocity constraints forbid is not conserved).
    A term breaks the symmetry when ``|δ| > rtol × (|∂term/∂x||ξ| + |∂term/∂v||ξ̇|)`` somewhere.
    (Invariance up to a total time derivative, a quasi-symmetry, is reported as broken.)
    """
    model = _model(model)
    s = model.symbols
    x, v, t = s.x, s.v, s.t
    xi, what = _generator(model, translation, rotation)
    checks = variation_checks(model, xi)
    fun = ca.Function("variations", [x, v, t],
                      [ca.vertcat(*[c for _, c, _ in checks]), ca.vertcat(*[sc for _, _, sc in checks])])
    states = manifold_samples(model, samples, seed)
    worst = np.zeros(len(checks))
    for xs, vs, ts in states:
        change, scale = (np.asarray(a).ravel() for a in fun(xs, vs, ts))
        rel = np.abs(change) / np.maximum(scale, _TINY)
        rel[~np.isfinite(rel)] = np.inf
        worst = np.maximum(worst, np.where(np.abs(change) == 0, 0.0, rel))
    changes = {name: float(w) for (name, _, _), w in zip(checks, worst, strict=True)}
    breaking = [name for name, w in changes.items() if w > rtol]
    if breaking:
        detail = "; ".join(f"{b} (relative change up to {changes[b]:.3g})" for b in breaking)
        message = (f"{what} is not a symmetry: it changes {detail}, so its Noether charge is not "
                   "conserved")
    else:
        message = (f"{what} is a symmetry of L and of the constraints at {len(states)} sampled "
                   f"states (largest relative change {max(changes.values(), default=0.0):.2g}); "
                   "its Noether charge is conserved")
    return SymmetryReport(what, not breaking, breaking, changes, message, len(states))


# --- constraints moving rigidly: the Jacobi integral ------------------------------------------


def _moving_frame(model: Model, samples: int, seed: int) -> tuple[dict | None, str]:
    """If every constraint moves rigidly at a constant rate, ``f(x, t)`` invariant under
    ``x → x + s ξ(x), t → t + s`` with ``ξ = Ω × x + b`` (the same for every particle), the
    generator as ``noether_charge`` keywords plus its ``scale`` (|Ω|, or 1 for a translation);
    fitted by least squares from ``∂f/∂t + J ξ = 0`` at states on the manifold."""
    s = model.symbols
    x, t, n = s.x, s.t, model.n_particles
    rows = []
    for constraint in model.system.constraints:
        if getattr(constraint, "level", "position") == "velocity":
            return None, "a velocity-level constraint: how it moves is not decided here"
        rows += [row for row, _ in constraint.rows(s)]
    if not rows:
        return None, "no constraints"
    f = ca.vertcat(*rows)
    J, ft = ca.jacobian(f, x), ca.jacobian(f, t)
    xs = ca.reshape(x, 3, n)
    coeff = []  # per constraint row: the coefficients of (Ω, b) in J ξ = Ω·Σ x_i × g_i + b·Σ g_i
    for k in range(f.numel()):
        g = [J[k, 3 * i : 3 * i + 3].T for i in range(n)]
        coeff.append(ca.vertcat(sum((ca.cross(xs[:, i], g[i]) for i in range(n)), ca.SX.zeros(3)),
                                sum(g, ca.SX.zeros(3))).T)
    scale = ft.__abs__() + ca.sum2(J.__abs__()) * (ca.norm_inf(x) + 1.0)
    fun = ca.Function("moving", [x, s.v, t], [ca.vertcat(*coeff), ft, scale])
    A, rhs, sc = [], [], []
    for xv, vv, tv in manifold_samples(model, samples, seed):
        a, b, c = (np.asarray(o) for o in fun(xv, vv, tv))
        A.append(a / c), rhs.append(-b.ravel() / c.ravel()), sc.append(c)
    A, rhs = np.vstack(A), np.concatenate(rhs)
    theta = np.linalg.lstsq(A, rhs, rcond=None)[0]
    misfit = float(np.max(np.abs(A @ theta - rhs)))
    if misfit > 1e-8:
        return None, (f"the constraints' time dependence is not a rigid motion at a constant rate "
                      f"(best fit ∂f/∂t + J(Ω × x + b) off by {misfit:.1g} relative)")
    theta = np.round(theta, 12) + 0.0  # round-off of the fit out of the description (and -0.0)
    omega, b = theta[:3], theta[3:]
    rate = float(np.linalg.norm(omega))
    if rate < 1e-12 * max(float(np.linalg.norm(b)), 1.0):
        velocity = ", ".join(f"{e:.6g}" for e in b)
        return {"translation": b, "scale": 1.0}, f"a translation at velocity ({velocity})"
    axis = omega / rate
    centre = np.round(np.cross(omega, b) / rate**2, 12) + 0.0
    return ({"rotation": (axis, centre), "translation": axis * float(axis @ b) / rate, "scale": rate},
            f"a rotation at ω = {rate:.6g} rad/s about ({', '.join(f'{a:.6g}' for a in axis)}) through "
            f"({', '.join(f'{c:.6g}' for c in centre)})")


def jacobi_integral(model, *, samples: int = 20, seed: int = 0) -> tuple[ca.Function | None, str]:
    """For rheonomic constraints moving rigidly (uniform rotation and/or translation, ``ξ``)
    with L and the other effects invariant under that motion: ``(Q, why)`` with ``Q(x, v, t) =
    p·ξ`` (for a rotation ``ω n·Σ (x_i − c) × p_i``, ω times the angular momentum about the
    axis), so that ``h − Q`` is conserved (the Jacobi integral, the energy in the moving frame):
    ``dh/dt`` is the constraint forces' power ``λ·∂f/∂t`` and ``dQ/dt = δL − λ·J ξ``, equal to
    it since ``J ξ = −∂f/∂t``. ``(None, why not)`` otherwise."""
    model = _model(model)
    frame, what = _moving_frame(model, samples, seed)
    if frame is None:
        return None, what
    spec = {k: frame[k] for k in ("rotation", "translation") if k in frame}
    report = is_symmetry(model, samples=samples, seed=seed, **spec)
    others = [b for b in report.breaking if not b.startswith("constraint ")]
    if others:
        return None, f"the constraints move as {what}, but that motion changes {', '.join(others)}"
    s = model.symbols
    xi, _ = _generator(model, spec.get("translation"), spec.get("rotation"))
    Q = frame["scale"] * ca.dot(canonical_momentum(model), xi)
    return ca.Function("moving_frame_charge", [s.x, s.v, s.t], [Q], ["x", "v", "t"], ["Q"]), what


# --- generalized coordinates ------------------------------------------------------------------


def _reduced_generator(rm, generator) -> ca.SX:
    if isinstance(generator, str) or not isinstance(generator, Sequence) or len(generator) != rm.n:
        raise InputError(f"needs one formula per coordinate ({', '.join(rm.coordinates)}), got {generator!r}",
                         where="generator")
    names = {"t": rm.t, **rm.parameters}
    names.update({c: rm.q[j] for j, c in enumerate(rm.coordinates)})
    return ca.vertcat(*[ca.SX(expressions.parse(g, names, where=f"generator[{j}] (∂{c}/∂s)"))
                        for j, (g, c) in enumerate(zip(generator, rm.coordinates, strict=True))])


def _reduced_columns(rm, data):
    if isinstance(data, Trajectory) or hasattr(data, "info"):
        info = data.info
        if "q" not in info or "q_dot" not in info:
            raise InputError("the trajectory has no generalized coordinates: use ReducedModel.solve, "
                             "or pass (q, q_dot, t)")
        Q, Qd, t = info["q"], info["q_dot"], data.t
    else:
        Q, Qd, t = data
    t = np.atleast_1d(np.asarray(t, float)).ravel()
    n = len(t)
    return np.asarray(Q, float).reshape(n, rm.n), np.asarray(Qd, float).reshape(n, rm.n), t


def noether_charge_reduced(reduced_model, trajectory_or_q_qdot, generator: Sequence) -> np.ndarray:
    """``Q = p · ξ(q, t)`` with ``p = ∂L/∂q̇`` along a reduced trajectory (or ``(q, q_dot, t)``).

    ``generator``: formulas ∂q_j/∂s in the coordinates, t and the parameters, e.g. ``["0", "1"]``
    for a shift of the second coordinate (then Q = p_2). Returns a (T,) array.
    """
    rm = reduced_model
    xi = _reduced_generator(rm, generator)
    Q = ca.dot(rm.expressions["p"], xi)
    fun = ca.Function("noether_charge", [rm.q, rm.q_dot, rm.t], [Q])
    return _along(fun, *_reduced_columns(rm, trajectory_or_q_qdot)).ravel()


def is_symmetry_reduced(reduced_model, generator: Sequence, *, samples: int = 20, seed: int = 0,
                        rtol: float = SYMMETRY_RTOL) -> SymmetryReport:
    """``δL = ∂L/∂q·ξ + ∂L/∂q̇·ξ̇ = 0`` (``ξ̇ = (∂ξ/∂q) q̇ + ∂ξ/∂t``) and ``Q_nc·ξ = 0`` at random
    states; the breaking terms are named ``T``, ``V``, ``U`` or ``non-conservative forces``."""
    rm = reduced_model
    q, qd, t = rm.q, rm.q_dot, rm.t
    xi = _reduced_generator(rm, generator)
    xi_dot = ca.jtimes(xi, q, qd) + ca.jacobian(xi, t)
    nxi, nxid = ca.norm_2(xi), ca.norm_2(xi_dot)
    ex = rm.expressions
    names, changes_e, scales_e = [], [], []
    for name in ("T", "V", "U"):
        e = ex[name]
        gq, gv = ca.gradient(e, q), ca.gradient(e, qd)
        names.append(name)
        changes_e.append(ca.dot(gq, xi) + ca.dot(gv, xi_dot))
        scales_e.append(ca.norm_2(gq) * nxi + ca.norm_2(gv) * nxid)
    # T, V, U may each change while L does not (e.g. a rheonomic map): judge L as a whole
    gq, gv = ca.gradient(ex["L"], q), ca.gradient(ex["L"], qd)
    dL = ca.dot(gq, xi) + ca.dot(gv, xi_dot)
    names.append("non-conservative forces")
    changes_e.append(ca.dot(ex["Q"], xi))
    scales_e.append(ca.norm_2(ex["Q"]) * nxi)
    fun = ca.Function("variations", [q, qd, t], [ca.vertcat(*changes_e), ca.vertcat(*scales_e), dL])
    Qs, Qds, Ts = rm.sample_states(samples, seed)
    worst = np.zeros(len(names))
    worst_L = 0.0
    for a, b, c in zip(Qs, Qds, Ts, strict=True):
        ch, sc, dl = (np.asarray(o).ravel() for o in fun(a, b, c))
        rel = np.where(ch == 0, 0.0, np.abs(ch) / np.maximum(sc, _TINY))
        worst = np.maximum(worst, rel)
        worst_L = max(worst_L, float(abs(dl[0]) / max(float(np.sum(sc[:3])), _TINY)) if dl[0] else 0.0)
    changes = {n: float(w) for n, w in zip(names, worst, strict=True)}
    changes["L"] = worst_L
    what = f"the shift ∂q/∂s = ({', '.join(str(g) for g in generator)})"
    if worst_L <= rtol:
        breaking = [n for n in ("non-conservative forces",) if changes[n] > rtol]
    else:
        breaking = [n for n in ("T", "V", "U", "non-conservative forces") if changes[n] > rtol] or ["L"]
    if breaking:
        message = f"{what} is not a symmetry: it changes " + ", ".join(
            f"{b} (relative change up to {changes[b]:.3g})" for b in breaking)
    else:
        message = f"{what} is a symmetry of L (largest relative change {worst_L:.2g}); Q = p·ξ is conserved"
    return SymmetryReport(what, not breaking, breaking, changes, message, samples)


def charge_drift(values) -> float:
    """``max |Q − Q0| / max(|Q0|, tiny)`` over a series of charge values (0 for an empty one)."""
    values = np.asarray(values, float).ravel()
    if values.size == 0:
        return 0.0
    return float(np.max(np.abs(values - values[0])) / max(abs(values[0]), _TINY))


# --- Lagrangians as CasADi Functions ---------------------------------------------------------


def _symbols(function: ca.Function, n: int):
    sym = ca.MX.sym if function.is_a("MXFunction") else ca.SX.sym
    return sym("q", n), sym("q_dot", n), sym("q_ddot", n), sym("t")


def euler_lagrange(L_function: ca.Function, n: int) -> ca.Function:
    """``E(q, q̇, q̈, t) = d/dt ∂L/∂q̇ − ∂L/∂q`` for any CasADi ``L(q, q̇, t)`` (n coordinates).

    ``d/dt ∂L/∂q̇ = (∂p/∂q̇) q̈ + (∂p/∂q) q̇ + ∂p/∂t`` with ``p = ∂L/∂q̇``, all by AD.
    """
    q, qd, qdd, t = _symbols(L_function, n)
    L = L_function(q, qd, t)
    p = ca.gradient(L, qd)
    E = ca.jtimes(p, qd, qdd) + ca.jtimes(p, q, qd) + ca.jacobian(p, t) - ca.gradient(L, q)
    return ca.Function("euler_lagrange", [q, qd, qdd, t], [E], ["q", "q_dot", "q_ddot", "t"], ["E"])


def with_total_derivative(reduced_model, F_formula: str) -> ca.Function:
    """``L̃(q, q̇, t) = L + dF/dt = L + (∂F/∂q)·q̇ + ∂F/∂t`` as a CasADi Function.

    ``F_formula``: a formula in the coordinates, t and the parameters. L̃ has the same
    Euler–Lagrange equations as L (``euler_lagrange`` of both agree identically).
    """
    rm = reduced_model
    names = {"t": rm.t, **rm.parameters}
    names.update({c: rm.q[j] for j, c in enumerate(rm.coordinates)})
    F = ca.SX(expressions.parse(F_formula, names, where="F (total derivative)"))
    Lt = rm.expressions["L"] + ca.dot(ca.gradient(F, rm.q), rm.q_dot) + ca.jacobian(F, rm.t)
    return ca.Function("lagrangian_plus_dF_dt", [rm.q, rm.q_dot, rm.t], [Lt], ["q", "q_dot", "t"], ["L"])
