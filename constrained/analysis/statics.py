"""Statics by the principle of virtual work: equilibrium, reactions, stability, generalized forces.

At rest the equations of motion ``M x'' = F + Jᵀλ`` (DESIGN.md) reduce to the KKT conditions

    F(x) + J(x)ᵀ λ = 0,   f(x, t) = 0,

with ``F`` the applied force at zero velocity (for potential forces ``F = −∇V``). This is the
principle of virtual work: ``δW = F·δx = 0`` for every admissible virtual displacement
(``J δx = 0``), because the ideal constraint forces ``Jᵀλ`` do no virtual work.

Sign conventions (the package's): the constraint force on particle i is ``(Jᵀλ)_i``; the
Lagrangian of statics is ``L(x, λ) = V(x) − λᵀ f(x)`` so that ``∇ₓL = −(F + Jᵀλ)``; its
Hessian restricted to the tangent space ``null(J)`` decides stability (all eigenvalues
positive: a strict constrained minimum of V, stable). ``anchor_reactions`` give the force the
support exerts on the particles; the load on the support is the negative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..manifold import residual
from ..manifold.dense import schur_solve, tangent_basis
from ..manifold.manifold import Manifold
from ..model import system as _system
from ..model import velocity
from ..model.structure import Model, assemble
from ..run.unilateral import gaps, has_one_sided, one_sided, scales
from ..threads import one_blas_thread
from .statics_methods import large as _large
from .statics_methods import prestress as _prestress
from .statics_methods.descent import minimize_on_constraints
from .statics_methods.kkt import IPOPT_CPU_S, IPOPT_ITERATIONS, force_round_off  # noqa: F401 (their home was here)
from .statics_methods.kkt import KKT as _KKT
from .statics_methods.kkt import ipopt_minimum as _ipopt
from .statics_methods.kkt import newton as _newton
from .statics_methods.one_sided import held_system, statics_active_set

#: Squared frequencies ω² (mass-weighted tangent-space Hessian) within ``zero_frequency_squared``
#: of 0 count as zero (neutral): ZERO_OMEGA2_UNITS × d ε ‖M^(-1/2) K M^(-1/2)‖ (d degrees of
#: freedom), the eigensolver's and the tangent basis' round-off. Mass-weighting puts a 1e-6 kg bob
#: on a string beside a 1e6 kg one on the same footing: both swing with ω² = g/L. (A fixed 1e-8 ‖K‖
#: called the swing of a pendulum whose bob hangs on a 1e9 N/m spring, ω² = 7.5 /s² against
#: ‖K‖ = 1e9 /s², a soft mode.)
ZERO_OMEGA2_UNITS = 10.0


def zero_frequency_squared(knorm: float, degrees_of_freedom: int, acceleration_residual: float = 0.0,
                           size: float = 1.0) -> float:
    """The ω² (1/s²) that cannot be told from 0 at a state: ``max(u d ε ‖K‖, 10 a / size)``,
    u = ZERO_OMEGA2_UNITS, d the degrees of freedom, ``knorm`` ‖K‖ of the mass-weighted
    stiffness (1/s²), ``acceleration_residual`` a the largest acceleration the state leaves
    unbalanced (m/s²): off an equilibrium by a, the Hessian along a symmetry (a turn about the
    pin of a hanging body) is a / (lever arm) instead of 0."""
    eps = np.finfo(float).eps
    return max(ZERO_OMEGA2_UNITS * max(degrees_of_freedom, 1) * eps * knorm,
               10.0 * acceleration_residual / max(size, 1e-300))


#: Convergence: force balance within FORCE_RTOL × force scale (or the round-off floor of a stiff
#: model, statics_methods.kkt.force_round_off), constraints within LENGTH_RTOL × size.
FORCE_RTOL = 1e-10
LENGTH_RTOL = 1e-12
#: The largest KKT system (3N + C unknowns) the statics solve: the Newton steps are sparse beyond
#: 100 rows (statics_methods.large), the stability verdict's tangent basis is a dense SVD of J
#: (a 3,000-bead chain, 15,000, took 11 GB and did not finish when everything was dense).
MAX_UNKNOWNS = 6000

__all__ = ["Equilibrium", "equilibrium", "virtual_work", "constraint_virtual_work_residual",
           "generalized_forces", "tangent_basis"]


@dataclass
class Equilibrium:
    """A static equilibrium ``F(x) + Jᵀλ = 0, f(x) = 0`` and what follows from it.

    Shapes: ``x``, ``constraint_forces``, ``applied_forces`` (N, 3); ``multipliers`` (C,);
    ``eigenvalues`` (d,) of the tangent-space Hessian of ``V − λ·f`` (d = 3N − rank J);
    ``frequencies_squared`` (d,) the squared small-oscillation frequencies ω² [1/s²] of the
    mass-weighted problem, which decide ``stable``; ``soft_modes`` (k, N, 3) unit tangent
    directions whose ω² is zero within ``stability_tolerance`` [1/s²].
    ``anchor_reactions``: (constraint label, support force) for each constraint tying
    particles to the environment; the support force is the net constraint force on the
    particles, ``Σ_i (J_kᵀ λ_k)_i``; the force on the support is its negative.
    ``stable``: True (strict minimum), False (some negative eigenvalue), None (neutral, or the
    forces are not conservative so the energy test does not apply).
    """

    x: np.ndarray
    multipliers: np.ndarray
    constraint_forces: np.ndarray
    applied_forces: np.ndarray
    anchor_reactions: list[tuple[str, np.ndarray]]
    stable: bool | None
    eigenvalues: np.ndarray
    soft_modes: np.ndarray
    virtual_work_residual: float
    constraint_virtual_work_residual: float
    converged: bool
    iterations: int
    particle_names: list[str] = field(default_factory=list)
    constraint_labels: list[str] = field(default_factory=list)
    t: float = 0.0
    potential_energy: float = 0.0
    conservative: bool = True
    stability_tolerance: float = 0.0
    tangent_basis: np.ndarray | None = None
    frequencies_squared: np.ndarray | None = None
    method: str = "newton"  #: what found it: "newton", "descent" (then Newton) or "ipopt" (then Newton)
    max_constraint_residual: float = 0.0
    #: One-sided constraint rows that do not hold at this equilibrium (their force would have
    #: the forbidden sign there; multiplier 0).
    slack: list[str] = field(default_factory=list)
    velocity_constraints: str = ""  #: what velocity constraints do at it (model/velocity.py: at_rest)
    #: Each constraint row's scale max_p |∂f/∂x_p| at x (constrained.residual): λ_k times it is
    #: a force in N, so the solve's force accuracy bounds |λ_k| by it over this scale.
    row_scales: np.ndarray | None = None
    #: The Hessian at the minimum-norm λ has negative ω², but the redundant rows' self-stress
    #: changes it on the tangent space (statics_methods.prestress): another valid split of the
    #: multipliers may hold those directions at second order (a net with both diagonals hanging
    #: in a plane), so ``stable`` is None, not False.
    undecided_by_self_stress: bool = False

    @property
    def degrees_of_freedom(self) -> int:
        """Dimension of the tangent space, 3N − rank J."""
        return int(len(self.eigenvalues))

    def to_dict(self) -> dict:
        """A JSON-ready dictionary (plain lists and floats)."""
        names = self.particle_names or [f"p{i}" for i in range(len(self.x))]
        labels = self.constraint_labels or [f"constraint {k}" for k in range(len(self.multipliers))]
        fs = self.frequencies_squared
        return {
            "t": self.t, "converged": self.converged, "iterations": self.iterations, "method": self.method,
            "particles": [{"name": n, "position": self.x[i].tolist(),
                           "applied_force": self.applied_forces[i].tolist(),
                           "constraint_force": self.constraint_forces[i].tolist()}
                          for i, n in enumerate(names)],
            "multipliers": [{"constraint": label, "value": float(v)}
                            for label, v in zip(labels, self.multipliers, strict=True)],
            "anchor_reactions": [{"constraint": label, "support_force": f.tolist(),
                                  "load_on_support": (-f).tolist()} for label, f in self.anchor_reactions],
            "potential_energy": self.potential_energy, "stable": self.stable,
            "conservative": self.conservative, "eigenvalues": self.eigenvalues.tolist(),
            "frequencies_squared": [] if fs is None else fs.tolist(),
            "stability_tolerance": self.stability_tolerance, "soft_modes": self.soft_modes.tolist(),
            "virtual_work_residual": self.virtual_work_residual,
            "constraint_virtual_work_residual": self.constraint_virtual_work_residual,
            "max_constraint_residual": self.max_constraint_residual, "slack": list(self.slack),
            "velocity_constraints": self.velocity_constraints,
            "undecided_by_self_stress": self.undecided_by_self_stress,
        }

    def __repr__(self) -> str:
        verdict = {True: "stable", False: "unstable", None: "neutral"}[self.stable]
        return (f"Equilibrium({len(self.x)} particles, {verdict}, virtual work residual "
                f"{self.virtual_work_residual:.3g}, {self.iterations} iterations)")


# --- building blocks ---------------------------------------------------------------------------


def _flat(system, x, what: str = "x") -> np.ndarray:
    n3 = 3 * system.n_particles
    try:
        arr = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be an array of positions, shape (N, 3)", where=what) from None
    if arr.size != n3:
        raise InputError(
            f"{what} must hold one position per particle, shape ({system.n_particles}, 3); "
            f"got shape {arr.shape}",
            where=what,
        )
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what} has non-finite entries", where=what)
    return arr.reshape(n3)


def _forces_at_rest(model: Model, x: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """F(x, v = 0, t) (3N,) and J (C, 3N)."""
    F, J, _ = model.dynamics(x, np.zeros_like(x), t)
    return np.asarray(F, float).ravel(), _large.dense(J).reshape(model.n_constraints, x.size)


def virtual_work(system, x, t: float = 0.0, *, model: Model | None = None) -> float:
    """max |δW| over unit admissible virtual displacements: ‖Nᵀ F‖₂, N an orthonormal basis of
    null(J(x)) (∩ null(A): velocity rows too), F = the forces at (x, v = 0, t); 0 at equilibrium."""
    model = model or assemble(system)
    xf = _flat(system, x)
    F, J = _forces_at_rest(model, xf, t)
    N = tangent_basis(J, xf.size)
    return float(np.linalg.norm(N.T @ F))


def constraint_virtual_work_residual(system, x, lam, t: float = 0.0, *, model: Model | None = None) -> float:
    """max |Σ F_con,i · δx_i| over unit admissible δx: ‖Nᵀ Jᵀλ‖₂ (ideal constraints do no
    virtual work, so this is ~0; it measures the numerical quality of J and its null space)."""
    model = model or assemble(system)
    xf = _flat(system, x)
    _, J = _forces_at_rest(model, xf, t)
    lam = np.asarray(lam, float).ravel()
    if lam.size != model.n_constraints:
        raise InputError(
            f"lam must have {model.n_constraints} entries (one per constraint row), got {lam.size}"
        )
    N = tangent_basis(J, xf.size)
    return float(np.linalg.norm(N.T @ (J.T @ lam))) if lam.size else 0.0


def generalized_forces(system, x, map_jacobian, t: float = 0.0, *, model: Model | None = None) -> np.ndarray:
    """Q_j = Σ_i F_i · ∂x_i/∂q_j (n,), from the Jacobian ∂x/∂q of a coordinate map, shape
    (3N, n) (or (N, 3, n)), with F = all effects' forces at (x, v = 0, t).

    For potential forces Q_j = −∂V/∂q_j. Constraint forces are left out: when the map satisfies
    the constraints identically, (∂x/∂q)ᵀ Jᵀ λ = 0 and they contribute nothing."""
    model = model or assemble(system)
    xf = _flat(system, x)
    D = np.asarray(map_jacobian, dtype=float)
    D = D.reshape(xf.size, -1) if D.ndim != 2 else D
    if D.shape[0] != xf.size:
        raise InputError(
            f"map_jacobian must have 3N = {xf.size} rows (∂x/∂q), got shape {np.shape(map_jacobian)}"
        )
    F, _ = _forces_at_rest(model, xf, t)
    return D.T @ F


def _min_norm_multipliers(model: Model, J: np.ndarray, F: np.ndarray) -> np.ndarray:
    """λ with Jᵀλ = −F in the mass-weighted least-squares sense, (J M⁻¹ Jᵀ) λ = −J M⁻¹ F: the
    multipliers that keep every particle at rest (a = 0), minimum-norm for redundant rows
    (identical rods share the load evenly), accurate whatever the spread of the masses.

    Two steps of iterative refinement on the force balance r = F + Jᵀλ follow the solve,
    ``λ += (J M⁻¹ Jᵀ)⁺ (−J M⁻¹ r)``: J M⁻¹ Jᵀ squares the conditioning the masses give it (a
    1 mg bead between 1 kg beads of a straight hanging chain: its two rods' rows nearly
    parallel, cond ~ 1e6 after scaling), and the solve alone left the force balance off by
    ε × cond × the tension (1.2e-9 N of 29 N), above the statics' tolerance, so Newton, whose λ
    is taken from here after every step, could not converge."""
    if J.shape[0] == 0:
        return np.zeros(0)
    Minv = model.inverse_masses
    lam = schur_solve(J, Minv, -J @ (Minv * F))
    for _ in range(2):
        r = F + J.T @ lam
        if not np.all(np.isfinite(r)):
            break
        lam = lam + schur_solve(J, Minv, -J @ (Minv * r))
    return lam


def _anchor_reactions(model: Model, J: np.ndarray, lam: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Support forces of the constraint rows that tie particles to the environment.

    A row is internal when f is unchanged by a rigid translation of all particles (the sum
    over particles of its gradient blocks vanishes, e.g. a distance between two particles):
    its forces cancel in pairs. Every other row is a support; rows of one constraint acting
    on the same particles (the three rows of a pin) are summed into one force.
    """
    N = model.n_particles
    groups: dict[tuple, list[int]] = {}
    for k in range(model.n_constraints):
        blocks = J[k].reshape(N, 3)
        scale = float(np.max(np.linalg.norm(blocks, axis=1), initial=0.0))
        if scale == 0 or np.linalg.norm(blocks.sum(axis=0)) <= 1e-12 * scale:
            continue
        touched = tuple(np.flatnonzero(np.linalg.norm(blocks, axis=1) > 0))
        groups.setdefault((int(model.constraint_owner[k]), touched), []).append(k)
    out = []
    for (owner, _), rows in groups.items():
        force = sum(J[k].reshape(N, 3).sum(axis=0) * lam[k] for k in rows)
        n_rows_owner = int(np.sum(model.constraint_owner == owner))
        if len(rows) > 1 and len(rows) == n_rows_owner:
            label = model.system.constraints[owner].label
        elif len(rows) > 1:
            label = " + ".join(model.constraint_labels[k] for k in rows)
        else:
            label = model.constraint_labels[rows[0]]
        out.append((label, np.asarray(force, float)))
    return out


def _worst_residual(model: Model, r: np.ndarray, w: np.ndarray, size: float = 1.0) -> str:
    n3 = model.n_coordinates
    k = int(np.nanargmax(np.abs(w * r)))
    if k < n3:
        name = model.system.particles[k // 3].name
        return f"the force balance F + Jᵀλ on particle '{name}' ({'xyz'[k % 3]}) is off by {abs(r[k]):.3g} N"
    label = model.constraint_labels[k - n3]
    return f"constraint '{label}' is violated by {abs(r[k]) * w[k] * LENGTH_RTOL * size:.3g} m"


# --- the equilibrium ---------------------------------------------------------------------------


def equilibrium(
    system,
    x_guess=None,
    t: float = 0.0,
    *,
    method: str = "auto",
    max_iter: int = 100,
    stability_rtol: float | None = None,
    model: Model | None = None,
) -> Equilibrium:
    """A static equilibrium near ``x_guess`` (default: the initial positions projected onto
    the constraints): F(x, 0, t) + J(x)ᵀλ = 0, f(x, t) = 0.

    ``method``: ``"newton"`` (Newton on the KKT conditions with a line search; finds any
    stationary point, also unstable ones, near the guess), ``"ipopt"`` (a constrained minimum
    of V by IPOPT, then Newton polish; potential forces only), ``"auto"`` (Newton; if it fails
    and the forces have a potential, a trust-region descent of V that stays on the constraints,
    statics_methods.descent, then Newton polish: ``method`` "descent" in the result; IPOPT last,
    unless the descent found V falling away without bound). Multipliers are the minimum-norm
    solution of Jᵀλ = −F (redundant constraints share the load). Raises InputError naming the
    largest residual when no equilibrium is found. ``stability_rtol``: ω² within it × ‖K‖ (the
    mass-weighted stiffness) count as zero; default: ``zero_frequency_squared``, the round-off.

    One-sided constraints (constrained.unilateral) hold only where their force has the
    allowed sign: starting from the rows touching at the guess, a row pulling (pushing) the
    wrong way is dropped and a slack row that the equilibrium would violate is added, until
    both hold; ``slack`` names the one-sided rows that do not hold (multiplier 0)."""
    _system.require_system(system, "equilibrium")
    with one_blas_thread():  # constrained/threads.py: spin-waiting BLAS threads cost more than they give
        return _equilibrium_one_sided(system, x_guess, t, method, max_iter, stability_rtol, model)


def _equilibrium_one_sided(system, x_guess, t, method, max_iter, stability_rtol, model) -> Equilibrium:
    """``equilibrium``, its one-sided constraints held or slack by an active-set loop."""
    model = model or (assemble(system) if system.n_particles else None)
    if model is None or not has_one_sided(model):
        return _equilibrium(system, x_guess, t, method=method, max_iter=max_iter,
                            stability_rtol=stability_rtol, model=model)
    info = one_sided(model)
    x0 = system.positions.ravel() if x_guess is None else _flat(system, x_guess, "x_guess")
    g = gaps(model, x0, t) / scales(model, x0, t)
    held = {k for k in info.rows if g[k] <= 1e-8 * system.size()}
    for _ in range(2 * len(info.rows) + 1):
        sub, rows = held_system(system, model, held)
        eq = _equilibrium(sub, x_guess, t, method=method, max_iter=max_iter, stability_rtol=stability_rtol,
                          model=None)
        lam = np.zeros(model.n_constraints)
        lam[rows] = eq.multipliers
        step = statics_active_set(model, eq.x.ravel(), t, lam, held, system.size())
        if step is None:
            break
        held = held - {step[1]} if step[0] == "drop" else held | {step[1]}
    else:
        raise InputError("no consistent set of holding one-sided constraints found (the active set "
                         "cycles); give a starting configuration nearer the equilibrium (x_guess)")
    eq.multipliers, eq.constraint_labels = lam, list(model.constraint_labels)
    eq.row_scales = residual.row_scales(model, eq.x.ravel(), t)
    eq.slack = [model.constraint_labels[k] for k in info.rows if k not in held]
    return eq


def _equilibrium(system, x_guess, t, *, method, max_iter, stability_rtol, model) -> Equilibrium:
    """``equilibrium`` with every constraint two-sided."""
    if system.n_particles == 0:
        raise InputError("the system has no particles")
    if method not in ("auto", "newton", "ipopt"):
        raise InputError(f"unknown method {method!r} (choose from auto, newton, ipopt)", where="method")
    if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
        raise InputError(f"t must be a finite number of seconds, got {t!r}", where="t")
    model = model or assemble(system)
    n3, C = model.n_coordinates, model.n_constraints
    if n3 + C > MAX_UNKNOWNS:
        raise InputError(
            f"the statics' KKT system has 3N + C = {n3 + C} unknowns here ({n3} coordinates, {C} "
            f"constraint rows), above the {MAX_UNKNOWNS} they take (their stability verdict takes a dense "
            f"basis of the tangent space: {8 * n3 * n3 / 1e9:.2g} GB and minutes of SVD); for a large model "
            "let a run settle instead (a damping effect and `constrained run`), or study a coarser "
            "discretization")
    kkt = _KKT(model, float(t))
    large = _large.is_large(model)  # (sparse J, K and multipliers: statics_methods.large)
    state = (lambda x: _large.forces_at_rest(model, x, t)) if large else (
        lambda x: _forces_at_rest(model, x, t))
    balance = (lambda J, F: _large.multipliers(model, J, F)) if large else (
        lambda J, F: _min_norm_multipliers(model, J, F))
    stiffness = (lambda x, lam: _large.stiffness(kkt.stiffness, x, lam)) if large else (
        lambda x, lam: _large.dense(kkt.stiffness(x, lam)))
    x0 = system.positions.ravel() if x_guess is None else _flat(system, x_guess, "x_guess")
    size = system.size()
    manifold = Manifold.at(model, x0, t)
    if C:
        projected = manifold.project_positions(x0, t, tol=1e-13 * size, max_iter=50)
        if np.isfinite(projected.residual) and np.all(np.isfinite(projected.x)):
            x0 = projected.x
    F0, J0 = state(x0)
    lam0 = balance(J0, F0)
    if large:  # (redundant rows: the sparse Newton step holds their multipliers out)
        kkt.dependent = n3 + _large.dependent_rows(model, J0)
    force_scale = max(
        float(np.max(np.abs(F0), initial=0.0)), float(np.max(np.abs(J0.T @ lam0), initial=0.0)) if C else 0.0
    )
    force_scale = force_scale if force_scale > 0 else 1.0
    # residual weights: one unit of the scaled residual is the convergence tolerance
    # (constraint rows in metres: each over its scale, constrained.residual)
    # (a force balance tighter than the stiffness times the positions' round-off cannot be met:
    # kkt.force_round_off; a 1 kg bob below a 1e7 N/m spring failed here)
    floor = force_round_off(stiffness(x0, lam0), x0, size)
    w = np.concatenate(
        [1.0 / np.maximum(FORCE_RTOL * force_scale, floor),
         1.0 / (LENGTH_RTOL * size * residual.row_scales(model, x0, t)[:model.n_position_rows])]
    )

    def restore(z: np.ndarray) -> np.ndarray:
        """Project x onto f = 0 (mass-weighted Newton) and take the least-squares λ there."""
        if not C:
            return z
        with np.errstate(all="ignore"):
            projected = manifold.project_positions(z[:n3], t, tol=1e-14 * size, max_iter=8)
            xr, err = projected.x, projected.residual
            if not (np.isfinite(err) and err <= 1e-10 * size and np.all(np.isfinite(xr))):
                return z
            Fr, Jr = state(xr)
            return np.concatenate([xr, balance(Jr, Fr)])

    used, why, descent = "newton", "", None
    iterations, converged, z = 0, False, np.concatenate([x0, lam0])
    if method in ("auto", "newton"):
        z, iterations, converged = _newton(kkt, np.concatenate([x0, lam0]), w, max_iter, restore)
    conservative_only = not ({"applied_force", "generalized_potential"} & model.active_terms)
    if not converged and method == "auto" and conservative_only:  # descend V on the constraints
        descent = minimize_on_constraints(model, kkt, manifold, x0, t, size, force_scale)
        zd, it2 = restore(np.concatenate([descent.x, lam0])), 0
        if descent.reason in ("minimum", "stalled", "budget"):  # (where Newton may finish)
            zd, it2, converged = _newton(kkt, zd, w, max_iter, restore)
        iterations += descent.iterations + it2
        z, used, why = (zd, "descent", "") if converged else (z, used, f" ({descent.explanation()})")
    unbounded = descent is not None and descent.reason == "far"  # (IPOPT would only chase it)
    if not converged and method in ("auto", "ipopt") and conservative_only and not unbounded:
        xi = _ipopt(kkt, x0)
        Fi, Ji = state(xi) if xi is not None else (None, None)
        # (IPOPT may end where a gradient is 0/0, after V ran downhill without bound)
        if xi is not None and np.all(np.isfinite(Fi)) and np.all(np.isfinite(Ji.data if large else Ji)):
            zi = np.concatenate([xi, balance(Ji, Fi)])
            zi, it2, conv2 = _newton(kkt, zi, w, max_iter, restore)
            if conv2 or method == "ipopt":
                z, iterations, converged, used = zi, iterations + it2, conv2, "ipopt"
    r, _ = kkt.residual_and_jacobian(z)
    if not converged or not np.all(np.isfinite(z)):
        raise InputError(
            f"no static equilibrium found near the guess after {iterations} iterations: "
            f"{_worst_residual(model, r, w, size)}{why}; try another starting configuration (x_guess, or the "
            "particles' positions), or check that the forces can be balanced by the constraints"
        )
    x = z[:n3]
    F, G = state(x)  # G: J, then velocity rows' A (d'Alembert: A δx = 0 too)
    lam = balance(G, F)
    G = G.toarray() if large else G  # (the tangent basis: one dense SVD below the statics' limit)
    note, held = velocity.at_rest(model, x, t, size, G, lam, force_scale)
    J = G[:model.n_position_rows]
    N = tangent_basis(J, n3)  # stability on the configuration's tangent space
    Nv = N if large else tangent_basis(G, n3)  # (large: no velocity rows, G = J)
    K = stiffness(x, lam)
    knorm = _large.spectral_norm(K)
    conservative = bool(_large.frobenius(K - K.T) <= 1e-9 * max(knorm, 1e-300) or knorm == 0.0)
    Ks = 0.5 * (K + K.T)
    # the verdict on the mass-weighted problem: ω² of (M^(-1/2) K M^(-1/2)) on null(J M^(-1/2)),
    # congruent to H (same signs) but with every particle's scale its own
    r = np.sqrt(model.inverse_masses)
    Kw = _large.scaled(Ks, r)
    Nw = (_large.weighted_basis(N, r) if large else tangent_basis(J * r[None, :], n3)) if C else np.eye(n3)
    H = N.T @ Ks @ N
    eig = np.linalg.eigvalsh(H) if H.size else np.zeros(0)
    omega2, vec = np.linalg.eigh(Nw.T @ Kw @ Nw) if Nw.size else (np.zeros(0), np.zeros((0, 0)))
    kw_norm = _large.spectral_norm(Kw)
    unbalanced = float(np.max(np.abs((F + G.T @ lam) * model.inverse_masses), initial=0.0)) if C else 0.0
    tol = (zero_frequency_squared(kw_norm, len(omega2), unbalanced, size) if stability_rtol is None
           else stability_rtol * kw_norm)
    soft = np.abs(omega2) <= tol
    self_stress = False
    if not conservative or held or note and np.any(omega2 <= tol):  # see velocity.at_rest
        stable = None
    elif np.any(omega2 < -tol) and _prestress.stress_matters(model, stiffness, x, J, large, N):
        stable, self_stress = None, True  # another valid split of the self-stress may hold them
    elif np.any(omega2 < -tol):
        stable = False
    elif np.any(soft):
        stable = None
    else:
        stable = True
    modes = r[:, None] * (Nw @ vec[:, soft])
    modes = modes / np.maximum(np.linalg.norm(modes, axis=0), 1e-300)
    soft_modes = modes.T.reshape(-1, model.n_particles, 3)
    Fc = G.T @ lam if C else np.zeros(n3)
    return Equilibrium(
        x=x.reshape(-1, 3),
        multipliers=lam,
        constraint_forces=Fc.reshape(-1, 3),
        applied_forces=F.reshape(-1, 3),
        anchor_reactions=_anchor_reactions(model, G, lam) if C else [],
        stable=stable,
        eigenvalues=eig,
        frequencies_squared=omega2,
        soft_modes=soft_modes,
        virtual_work_residual=float(np.linalg.norm(Nv.T @ F)),
        constraint_virtual_work_residual=float(np.linalg.norm(Nv.T @ Fc)),
        converged=converged,
        iterations=iterations,
        particle_names=list(system.names),
        constraint_labels=list(model.constraint_labels),
        t=float(t),
        potential_energy=float(kkt.potential(x)),
        conservative=conservative,
        stability_tolerance=tol,
        tangent_basis=N,
        method=used,
        max_constraint_residual=residual.position_residual(model, x, t),  # metres
        velocity_constraints=note,
        row_scales=residual.row_scales(model, x, t) if C else np.zeros(0),
        undecided_by_self_stress=self_stress,
    )
