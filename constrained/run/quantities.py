"""Derived quantities along a trajectory: multipliers, constraint forces, energy, residuals.

Everything here works in blocks of samples, so no dense (samples × rows × coordinates)
array is ever held whole.

Only what a run asks for (``wanted``) is computed. The action, which needs the Lagrangian
along the path, is added by the caller (constrained.action).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..codegen.fast_call import FastCall
from ..manifold import residual
from ..manifold.algebra import algebra_for
from ..manifold.manifold import (
    RANK,
    RankPolicy,
    acceleration_function,
    dynamics_values,
    redundant_rows,
    structural_call,
)
from ..manifold.vectorized import graphs as vectorized
from ..model.cache import ParametricView, built_once, structure_cache
from ..model.structure import Model
from .trajectory import QUANTITIES, Trajectory

#: Output names accepted by ``outputs`` (``positions``/``velocities`` are always computed).
OUTPUT_NAMES = frozenset({"positions", "velocities", *QUANTITIES})


def trajectory_from(model: Model, t, X, V, wanted, stats=None) -> Trajectory:
    """Build a Trajectory with the derived quantities in ``wanted`` evaluated at each sample."""
    t = np.asarray(t, float)
    n = len(t)
    N = model.n_particles
    traj = Trajectory(
        t=t,
        x=X.reshape(n, N, 3),
        v=V.reshape(n, N, 3),
        particle_names=list(model.particle_names),
        constraint_labels=list(model.constraint_labels),
        stats=dict(stats or {}),
    )
    if n == 0:
        return traj
    if vectorized.applies(model):  # large: one call of the vectorized build per sample
        _along_vectorized(model, traj, X.reshape(n, -1), V.reshape(n, -1), t, wanted)
        return traj
    if "multipliers" in wanted or "constraint_forces" in wanted:
        lam = multipliers_along(model, X, V, t)
        if "multipliers" in wanted:
            traj.multipliers = lam
        if "constraint_forces" in wanted:
            traj.constraint_forces = constraint_forces_along(model, X, t, lam)
    if "energy" in wanted:
        traj.energy = energy_along(model, X.reshape(n, -1), V.reshape(n, -1), t)
    if "constraint_residual" in wanted:  # in metres, whatever the scale of the formulas
        traj.constraint_residual = residual.position_residual_along(model, X, t)
    if "velocity_residual" in wanted:  # in m/s
        traj.velocity_residual = residual.velocity_residual_along(model, X, V.reshape(n, -1), t)
    return traj


def _along_vectorized(model: Model, traj: Trajectory, X: np.ndarray, V: np.ndarray, t: np.ndarray,
                      wanted) -> None:
    """The quantities ``wanted`` of a large model, sample by sample from one call of
    ``vectorized.quantities_function`` each: the multipliers by the sparse LDLᵀ where its check
    holds (else, and for dependent rows, the minimum-norm solve of ``multipliers_along``), the
    constraint forces Jᵀλ, the energy and the residuals."""
    n, C = len(t), model.n_constraints
    kkt = bool({"multipliers", "constraint_forces"} & set(wanted)) and C > 0
    full_rank = kkt and redundant_rows(model, X[0], float(t[0])) is None
    names = tuple(k for k in vectorized.QUANTITY_OUTPUTS
                  if (k in ("multipliers", "check", "constraint_forces") and full_rank) or k in wanted
                  and k in ("energy", "constraint_residual", "velocity_residual"))
    out = {}
    if names:
        fast = FastCall(vectorized.quantities_function(model, names))
        sizes = {"multipliers": C, "constraint_forces": model.n_coordinates}
        out = {k: np.empty((n, sizes.get(k, 1))) for k in names}
        p = model.parameter_vector
        for k in range(n):
            for name, value in zip(names, fast(X[k], V[k], t[k], p), strict=True):
                out[name][k] = value
    if kkt:
        lam = out["multipliers"] if full_rank else np.full((n, C), np.nan)
        forces = out["constraint_forces"] if full_rank else np.full((n, model.n_coordinates), np.nan)
        good = np.zeros(n, bool)
        if full_rank:
            good = (out["check"][:, 0] <= 1e-9) & np.all(np.isfinite(lam), axis=1)
        redo = np.flatnonzero(~good)
        if len(redo):
            lam[redo] = _minimum_norm(model, X, V, t, redo, RANK, full_rank)
            forces[redo] = constraint_forces_along(model, X[redo], t[redo], lam[redo]).reshape(len(redo), -1)
        if "multipliers" in wanted:
            traj.multipliers = lam
        if "constraint_forces" in wanted:
            traj.constraint_forces = forces.reshape(n, model.n_particles, 3)
    if "energy" in wanted:
        traj.energy = out["energy"].ravel()
    if "constraint_residual" in wanted:
        traj.constraint_residual = out["constraint_residual"].ravel()
    if "velocity_residual" in wanted:
        traj.velocity_residual = out["velocity_residual"].ravel()


# --- along a trajectory ---------------------------------------------------------------------------
#: Samples evaluated per block along a trajectory: bounds the dense (samples × rows × coordinates)
#: Jacobians held at once to about this many floats.
BLOCK_FLOATS = 4_000_000


def _blocks(n: int, per_sample: int):
    size = max(1, BLOCK_FLOATS // max(per_sample, 1))
    for start in range(0, n, size):
        yield slice(start, min(n, start + size))


def energy_along(model: Model, X: np.ndarray, V: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The energy at each sample (T,): the Model's Function mapped over the samples; with pair
    potentials that keep neighbour lists (a cutoff), sample by sample through the parametric
    Function with each sample's list (rebuilt where the particles have moved: O(N) a sample
    where the bound Function, which holds no list, would sum every pair)."""
    potentials = getattr(model.structure, "pair_potentials", None)
    if potentials is None or not any(term.size for term in potentials.terms):
        return model.evaluate(model.energy, X, V, t)[0].ravel()
    energy = built_once(model.structure, "energy with lists", lambda: FastCall(model.parametric("energy")))
    p, out = model.parameter_vector, np.empty(len(t))
    for k in range(len(t)):
        fresh = potentials.refreshed(p, X[k])
        p = p if fresh is None else fresh
        out[k] = energy(X[k], V[k], float(t[k]), p)[0][0]
    return out


def _checked_multipliers(model: Model) -> ca.Function:
    """``(x, v, t) -> (λ, r)``: the sparse LDLᵀ multipliers and the relative residual
    r = |J a + γ|∞ / (|γ|∞ + |J M⁻¹ F|∞ + tiny) of the acceleration they give. A factorization
    that met dependent rows gives large λ without a NaN; r shows it.

    A model below ``VECTORIZED_FROM`` coordinates without pair kernels gets the graph built once
    per structure with p an input, bound to its values (a fresh call assembles a new Model of
    the same structure: it builds nothing again); others build it on the Model's Functions."""
    def graph(view, X, V, T, acceleration):
        F, J, gamma = view.dynamics(X, V, T)
        inverse_masses = view.inverse_masses
        inverse_masses = ca.DM(inverse_masses) if isinstance(inverse_masses, np.ndarray) else inverse_masses
        load = ca.mtimes(J, inverse_masses * F)
        scale = ca.mmax(ca.fabs(gamma)) + ca.mmax(ca.fabs(load)) + 1e-300
        a, lam = acceleration
        return lam, ca.mmax(ca.fabs(ca.mtimes(J, a) + gamma)) / scale

    n3 = model.n_coordinates
    X, V, T = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
    if getattr(model.structure, "pairs", ()) or n3 >= vectorized.VECTORIZED_FROM:
        def build():
            return ca.Function("checked_multipliers", [X, V, T],
                               list(graph(model, X, V, T, acceleration_function(model)(X, V, T))))
        return built_once(model, "checked_multipliers", build)

    cache, prefix = structure_cache(model)
    key = (*prefix, "checked_multipliers")
    if key not in cache:
        P = ca.MX.sym("p", len(model.parameter_vector))
        acceleration = acceleration_function(model, parametric=True)(X, V, T, P)
        cache[key] = ca.Function("checked_multipliers", [X, V, T, P],
                                 list(graph(ParametricView(model, P), X, V, T, acceleration)))
    parametric = cache[key]

    def bind():
        return ca.Function("checked_multipliers", [X, V, T],
                           parametric(X, V, T, ca.DM(model.parameter_vector)))
    return built_once(model, "checked_multipliers", bind)


def multipliers_along(model: Model, X: np.ndarray, V: np.ndarray, t: np.ndarray, *,
                      policy: RankPolicy = RANK, full_rank: bool | None = None) -> np.ndarray:
    """λ at each sample (T, C) from the KKT system at (x, v, t), in blocks of samples.

    Independent rows (``full_rank``; None: decided at the first sample): the sparse LDLᵀ,
    mapped over the samples (O(N) per sample on a chain), kept where the acceleration it
    gives satisfies J a + γ = 0 to 1e-9. Other samples, and redundant rows, take
    ``schur_solve`` (minimum-norm, accurate whatever the spread of the masses): on the dense J
    in blocks of samples, or beyond ``algebra.SPARSE_FROM`` rows sample by sample on the sparse J."""
    t = np.asarray(t, float)
    n, C, n3 = len(t), model.n_constraints, model.n_coordinates
    if C == 0:
        return np.zeros((n, 0))
    X, V = np.asarray(X, float).reshape(n, n3), np.asarray(V, float).reshape(n, n3)
    if full_rank is None:
        full_rank = n == 0 or redundant_rows(model, X[0], float(t[0]), policy) is None
    lam = np.full((n, C), np.nan)
    if full_rank:
        fast = _checked_multipliers(model)
        for block in _blocks(n, 4 * (C + n3)):
            values, residual = model.evaluate(fast, X[block], V[block], t[block])
            good = np.asarray(residual, float).ravel() <= 1e-9
            lam[block] = np.where(good[:, None], np.asarray(values, float).T, np.nan)
    redo = np.flatnonzero(~np.all(np.isfinite(lam), axis=1))
    lam[redo] = _minimum_norm(model, X, V, t, redo, policy, full_rank)
    return lam


def _minimum_norm(model: Model, X: np.ndarray, V: np.ndarray, t: np.ndarray, redo: np.ndarray,
                  policy: RankPolicy, full_rank: bool) -> np.ndarray:
    """λ (len(redo), C) at the samples ``redo`` by ``schur_solve`` (minimum-norm, accurate
    whatever the spread of the masses): on the dense J in blocks of samples, or beyond
    ``algebra.SPARSE_FROM`` rows sample by sample on the sparse J."""
    C, n3 = model.n_constraints, model.n_coordinates
    lam = np.full((len(redo), C), np.nan)
    minv = model.inverse_masses
    algebra = algebra_for(C)
    if algebra.name == "sparse":  # one sample at a time with J sparse
        dynamics = dynamics_values(model) if len(redo) else None
        for i, k in enumerate(redo):
            F, J, gamma = dynamics(X[k], V[k], float(t[k]))
            J = algebra.matrix(J)
            lam[i] = algebra.multipliers(J, minv, F, gamma, policy=policy, full_rank=full_rank)
        return lam
    per_block = max(1, BLOCK_FLOATS // (C * n3))
    for start in range(0, len(redo), per_block):
        rows = redo[start:start + per_block]
        F, Jcat, gamma = model.evaluate(model.dynamics, X[rows], V[rows], t[rows])
        J = Jcat.reshape(C, len(rows), n3).transpose(1, 0, 2)
        for i in range(len(rows)):
            lam[start + i] = algebra.multipliers(J[i], minv, F[:, i], gamma[:, i], policy=policy,
                                                 full_rank=full_rank)
    return lam


def _constraint_force_function(model: Model) -> ca.Function:
    """``(x, t, λ) -> Jᵀλ`` (3N,) with J kept sparse inside: O(nnz J) per sample, built once
    per structure (with velocity rows, J is [J; A] and λ is [λ; μ]: ``velocity_terms``)."""
    def build(view, X, T, L, P):
        J, _ = view.velocity_terms(X, T)
        return ca.Function("constraint_force", [X, T, L, P], [ca.densify(ca.mtimes(J.T, L))])

    fast = structural_call(model, "constraint_force", build, "x", "t", "lam")
    return lambda x, t, lam: fast(x, t, lam)[0]


def constraint_forces_along(model: Model, X: np.ndarray, t: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """(Jᵀλ)_i for each particle, (T, N, 3): the sparse product sample by sample (never a
    dense J). Samples whose λ is not finite give NaN forces."""
    t = np.asarray(t, float)
    n, C, n3 = len(t), model.n_constraints, model.n_coordinates
    out = np.zeros((n, model.n_particles, 3))
    if C == 0 or n == 0:
        return out
    X = np.asarray(X, float).reshape(n, n3)
    lam = np.asarray(lam, float).reshape(n, C)
    if n3 < vectorized.VECTORIZED_FROM and not getattr(model.structure, "pairs", ()):
        for block in _blocks(n, 2 * n3 + C):  # a small model: all samples in one mapped call
            forces = model.evaluate(_bound_constraint_force(model), X[block], t[block], lam[block])[0]
            out[block] = np.asarray(forces, float).T.reshape(-1, model.n_particles, 3)
        return out
    force = _constraint_force_function(model)
    for k in range(n):
        out[k] = force(X[k], t[k], lam[k]).reshape(-1, 3)
    return out


def _bound_constraint_force(model: Model) -> ca.Function:
    """``(x, t, λ) -> Jᵀλ`` of a small model for mapping over samples: the SX graph built once
    per structure with p an input, bound to the model's values (a fresh call builds no graph)."""
    cache, prefix = structure_cache(model)
    key = (*prefix, "constraint_force_sx")
    n3, C = model.n_coordinates, model.n_constraints
    X, T, L = ca.SX.sym("x", n3), ca.SX.sym("t"), ca.SX.sym("lam", C)
    if key not in cache:
        P = ca.SX.sym("p", len(model.parameter_vector))
        J, _ = ParametricView(model, P).velocity_terms(X, T)
        cache[key] = ca.Function("constraint_force", [X, T, L, P], [ca.densify(ca.mtimes(J.T, L))])
    parametric = cache[key]
    return built_once(model, "constraint_force_sx", lambda: ca.Function(
        "constraint_force", [X, T, L], [parametric(X, T, L, ca.DM(model.parameter_vector))]))
