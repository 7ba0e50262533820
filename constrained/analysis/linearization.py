"""The linearized equations of motion on the constraint manifold, about a state at rest in a frame.

About a state that is at rest in a frame — an equilibrium, or a steady motion that is at rest
in a frame turning uniformly with ``Ω`` about a point ``c`` (``RotatingFrame``) — write the
positions in the frame's coordinates ``y`` (at the instant t0 the frames coincide) and the
constrained equations of motion there (DESIGN.md, ``M x'' = F + Jᵀλ``):

    M ÿ = F(x, v, t) + J(x, t)ᵀ λ − M (2 Ω × ẏ + Ω × (Ω × (y − c))),   v = ẏ + Ω × (y − c).

Displacements that keep the constraints to first order are ``δy = T q`` with ``T`` a
mass-orthonormal basis of null(J) (``Tᵀ M T = I``: T = M^(-1/2) · orthonormal null(J M^(-1/2))).
The constraint forces do no work along T, so projecting with Tᵀ removes the multipliers'
variation and leaves, with ``r(y, ẏ)`` the right-hand side above at the fixed multipliers λ0,

    q̈ + (G + D) q̇ + K q = 0,   K = −Tᵀ (∂r/∂y) T,   G + D = −Tᵀ (∂r/∂ẏ) T   (M = I),

both Jacobians by CasADi AD (constrained.modes solves it). ``K`` holds the stiffness of the
forces, the constraints' curvature weighted by the multipliers (``−Σ λ_k ∇²f_k``: a hanging
chain's tension) and, in a frame, the centrifugal softening; ``D`` (the symmetric part of the
velocity term) the Rayleigh damping; ``G`` (its skew part) the gyroscopic terms: Coriolis
``2 Tᵀ M [Ω]× T``, magnetic forces.

The reduced route cross-checks it (``Modes.cross_check``): ``M(q) q̈ = rhs(q, q̇, t)``
linearized at the same state (``M0 δq̈ = rhs_q δq + rhs_q̇ δq̇``) has the same roots ``s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.linalg as sla

from ..errors import InputError
from ..manifold import residual
from ..manifold.dense import tangent_basis
from ..manifold.manifold import Manifold
from ..model.structure import Model
from .statics import _newton
from .statics_methods.kkt import force_round_off

__all__ = ["RotatingFrame", "balance_function", "frame_arrays", "linearize", "omega_velocity",
           "quadratic_roots", "reduced_linearization", "relative_equilibrium", "zero_root_chain"]

#: The state must be at rest in the frame: tangential acceleration and frame velocity within
#: this fraction of the system's acceleration and velocity scales.
STATIONARY_RTOL = 1e-6
#: Newton on the relative equilibrium: force balance within FORCE_RTOL × the force scale, the
#: constraints within LENGTH_RTOL × the system's size (statics' tolerances).
FORCE_RTOL = 1e-10
LENGTH_RTOL = 1e-12


@dataclass(frozen=True)
class RotatingFrame:
    """A frame turning uniformly with angular velocity ``omega`` (rad/s, a 3-vector) about the
    point ``point`` (m); it coincides with the inertial frame at the instant of linearization.
    A steady motion at rest in it (a bead carried round by a spinning hoop) is a fixed point
    there, and its modes are those seen by an observer turning with it."""

    omega: tuple = (0.0, 0.0, 0.0)
    point: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        for name in ("omega", "point"):
            value = np.asarray(getattr(self, name), float).ravel() if _numeric(getattr(self, name)) else None
            if value is None or value.size != 3 or not np.all(np.isfinite(value)):
                raise InputError(f"the frame's {name} must be three finite numbers, got "
                                 f"{getattr(self, name)!r}", where=f"frame.{name}")
            object.__setattr__(self, name, tuple(float(c) for c in value))

    def velocity(self, x: np.ndarray) -> np.ndarray:
        """Ω × (x − c) for flat positions x (3N,): the velocity of a point at rest in the frame."""
        r = np.asarray(x, float).reshape(-1, 3) - np.asarray(self.point)
        return np.cross(np.asarray(self.omega), r).ravel()


def _numeric(value) -> bool:
    try:
        np.asarray(value, float)
    except (TypeError, ValueError):
        return False
    return True


# --- the linearization -------------------------------------------------------------------------


def _cross(omega: np.ndarray, r):
    """Ω × r for every particle of a flat CasADi column r (3N,)."""
    R = ca.reshape(r, 3, -1)
    wx, wy, wz = (float(c) for c in omega)
    out = ca.vertcat(wy * R[2, :] - wz * R[1, :], wz * R[0, :] - wx * R[2, :], wx * R[1, :] - wy * R[0, :])
    return ca.reshape(out, -1, 1)


def frame_arrays(frame: RotatingFrame | None, n_particles: int) -> tuple[np.ndarray, np.ndarray]:
    omega = np.zeros(3) if frame is None else np.asarray(frame.omega)
    centre = np.zeros(3 * n_particles) if frame is None else np.tile(frame.point, n_particles)
    return omega, centre


def balance_function(model: Model, t: float, omega: np.ndarray, centre: np.ndarray):
    """CasADi Function (y, u, λ) -> (r, ∂r/∂y, ∂r/∂u, J, F): the frame's equation of motion at the
    multipliers λ, r = F(y, u + Ω×(y − c), t) + Jᵀλ − M(2 Ω×u + Ω×(Ω×(y − c))) (also the sparse
    route's, statics_methods.large_modes)."""
    n3, C = model.n_coordinates, model.n_constraints
    y, u, lam = ca.SX.sym("y", n3), ca.SX.sym("u", n3), ca.SX.sym("lam", C)
    arm = y - centre
    F, J, _ = model.dynamics(y, u + _cross(omega, arm), t)
    m = ca.DM(model.masses)
    r = F - m * (2 * _cross(omega, u) + _cross(omega, _cross(omega, arm)))
    if C:
        r = r + ca.mtimes(J.T, lam)
    return ca.Function("frame_balance", [y, u, lam], [r, ca.jacobian(r, y), ca.jacobian(r, u), J, F])


def relative_equilibrium(model: Model, x0: np.ndarray, t: float, omega, centre, size: float) -> np.ndarray:
    """Positions at rest in the frame near x0: r(y, 0, λ) = 0 with f(y, t) = 0 (Newton on the
    KKT conditions, statics' line search and least-squares steps)."""
    n3, C = model.n_coordinates, model.n_constraints
    fun = balance_function(model, t, omega, centre)
    manifold = Manifold.at(model, x0, t)

    class Kkt:
        @staticmethod
        def residual_and_jacobian(z):
            r, Ry, _, J, _ = fun(z[:n3], np.zeros(n3), z[n3:])
            f, _ = model.jacobian(z[:n3], t)
            J = np.asarray(J, float).reshape(C, n3)  # every row; f only the first (velocity rows: none)
            res = np.concatenate([np.asarray(r, float).ravel(), np.asarray(f, float).ravel()])
            Jf = J[:model.n_position_rows]
            jac = np.block([[np.asarray(Ry, float), J.T], [Jf, np.zeros((len(Jf), C))]])
            return res, jac

    def restore(z):
        if not C:
            return z
        projected = manifold.project_positions(z[:n3], t, tol=1e-14 * size, max_iter=8)
        return z if not np.all(np.isfinite(projected.x)) else np.concatenate([projected.x, z[n3:]])

    x0 = restore(np.concatenate([x0, np.zeros(C)]))[:n3]
    _, lam = manifold.accelerations(x0, omega_velocity(omega, centre, x0), t)
    scale = _force_scale(model, *fun(x0, np.zeros(n3), lam)[3:], lam, omega, x0)
    # one unit of the weighted residual is the tolerance: forces in N, constraint rows in metres
    scales = residual.row_scales(model, x0, t)[:model.n_position_rows]  # the rows of f
    Ry = np.asarray(fun(x0, np.zeros(n3), lam)[1], float)  # −K: the round-off floor of a stiff model
    w = np.concatenate([1.0 / np.maximum(FORCE_RTOL * scale, force_round_off(Ry, x0, size)),
                        1.0 / (LENGTH_RTOL * size * scales)])
    z, iterations, converged = _newton(Kkt, np.concatenate([x0, lam]), w, 100, restore)
    if not converged:
        raise InputError(f"no state at rest in the frame found near the given positions after {iterations} "
                         "Newton iterations; give positions nearer the steady motion (x), or check the "
                         "frame's angular velocity and point", where="x")
    return z[:n3]


def omega_velocity(omega: np.ndarray, centre: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Ω × (x − c) for flat x (3N,)."""
    return np.cross(omega, (x - centre).reshape(-1, 3)).ravel()


def linearize(model: Model, x: np.ndarray, v: np.ndarray, t: float, frame: RotatingFrame | None = None):
    """(T, G + D, K, λ, residual, unbalanced) about the state (x, v, t) (flat), at rest in
    ``frame``: see the module's docstring. ``unbalanced``: the largest tangential acceleration
    left (m/s²), ``residual`` that over the acceleration scale; InputError when the state is
    not at rest in the frame: beyond STATIONARY_RTOL of the scale and beyond what the
    positions' round-off leaves in a stiff model (statics_methods.kkt.force_round_off / m)."""
    n3 = model.n_coordinates
    omega, centre = frame_arrays(frame, model.n_particles)
    u0 = v - omega_velocity(omega, centre, x)
    _, lam = Manifold.at(model, x, t).accelerations(x, v, t)
    r, Ry, Ru, J, F = balance_function(model, t, omega, centre)(x, u0, lam)
    r, Ry, Ru = np.asarray(r, float).ravel(), np.asarray(Ry, float), np.asarray(Ru, float)
    accel = _force_scale(model, J, F, lam, omega, x, per_mass=True)
    J = np.asarray(J, float).reshape(model.n_constraints, n3)
    minv_sqrt = 1.0 / np.sqrt(model.masses)
    null = tangent_basis(J * minv_sqrt[None, :], n3) if model.n_constraints else np.eye(n3)
    T = minv_sqrt[:, None] * null
    speed = max(float(np.max(np.abs(v), initial=0.0)), float(np.linalg.norm(omega)) * _size(x), 1e-300)
    tangential = T @ (T.T @ r)  # M⁻¹-free: T Tᵀ r is the tangential acceleration (m/s²)
    unbalanced = float(np.max(np.abs(tangential), initial=0.0))
    residual = unbalanced / accel
    floor = force_round_off(Ry, x, _size(x)) / model.masses  # m/s²: a stiff model's round-off
    rests = bool(np.all(np.abs(tangential) <= np.maximum(STATIONARY_RTOL * accel, floor)))
    moving = float(np.max(np.abs(u0), initial=0.0)) / speed
    if not rests or moving > STATIONARY_RTOL:
        where = "" if frame is None else " in the given frame"
        why = (f"its velocity relative to the frame is {np.max(np.abs(u0)):.3g} m/s"
               if moving > STATIONARY_RTOL else
               f"the forces leave a tangential acceleration of {unbalanced:.3g} m/s²")
        raise InputError(
            f"the state is not at rest{where}: {why}; linearize about an equilibrium (leave x out: "
            "statics finds one), or give the rotating frame in which the motion is steady", where="x")
    return T, -T.T @ Ru @ T, -T.T @ Ry @ T, lam, residual, unbalanced


def _force_scale(model: Model, J, F, lam, omega, x, *, per_mass: bool = False) -> float:
    """The largest of the applied forces, the constraint forces Jᵀλ and the centrifugal
    forces M Ω×(Ω×r) on any coordinate (divided by its mass: ``per_mass``)."""
    J = np.asarray(J, float).reshape(model.n_constraints, model.n_coordinates)
    w = 1.0 / model.masses if per_mass else np.ones(model.n_coordinates)
    parts = [w * np.asarray(F, float).ravel(), w * (J.T @ lam) if lam.size else np.zeros(1),
             w * model.masses * float(np.linalg.norm(omega)) ** 2 * _size(x)]
    return max(max(float(np.max(np.abs(p), initial=0.0)) for p in parts), 1e-300)


def _size(x: np.ndarray) -> float:
    x = np.asarray(x, float).reshape(-1, 3)
    return max(float(np.max(np.linalg.norm(x, axis=1), initial=0.0)),
               float(np.max(np.ptp(x, axis=0))) if len(x) > 1 else 0.0, 1e-300)


# --- the quadratic eigenproblem ------------------------------------------------------------------


def quadratic_roots(M: np.ndarray, C: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """(s (2n,), vectors (n, 2n), symmetric) with (s² M + s C + K) z = 0. Without C and with K
    symmetric: the generalized symmetric problem K z = ω² M z (exact real shapes, s = ±i ω);
    otherwise the first-order pencil [[I, 0], [0, M]] ż = [[0, I], [−K, −C]] z."""
    n = M.shape[0]
    if n == 0:
        return np.zeros(0, complex), np.zeros((0, 0), complex), True
    # (Frobenius norms: within √n of the spectral ones and no SVD — two of a 1,000 × 1,000 K and M
    # took 16 s; the tests' margins are orders of magnitude)
    knorm = max(float(np.linalg.norm(K)), 1e-300)
    if np.linalg.norm(C) <= 1e-14 * math.sqrt(knorm * float(np.linalg.norm(M))) and \
            np.linalg.norm(K - K.T) <= 1e-10 * knorm:
        w2, Z = sla.eigh(0.5 * (K + K.T), M)
        root = np.sqrt(-w2.astype(complex))  # s = ±i ω for ω² > 0, ±σ for ω² = −σ² < 0
        return np.concatenate([root, -root]), np.hstack([Z, Z]).astype(complex), True
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-K, -C]])
    B = np.block([[np.eye(n), np.zeros((n, n))], [np.zeros((n, n)), M]])
    s, Z = sla.eig(A, B)
    # a zero root of multiplicity m (a defective one: a Jordan chain) comes out of eig as m
    # roots of size ~(ε‖A‖)^(1/m), far above round-off: the kernel chain counts m, and they
    # are zero
    zero = (zero_root_chain(M, C, K) or [0])[-1]
    if zero:
        s = s.copy()
        s[np.argsort(np.abs(s))[:zero]] = 0.0
    return s, Z[:n], False


def zero_root_chain(M: np.ndarray, C: np.ndarray, K: np.ndarray, rtol: float = 1e-10) -> list[int]:
    """``[d_1, d_2, …]``: the dimensions of null(A^j) of the first-order matrix A of
    ``s² M + s C + K``, up to where they stop growing (empty: s = 0 is no root). The last is
    the multiplicity of the root 0; the chain's length the size of its largest Jordan block:
    2 for a free direction (q = a + b t), more when a displacement that no force restores
    drives another one (a skate across a slope, turned, slides along its blade as t²).
    Ranks by SVD relative to ‖A‖ after balancing time (s ↦ s/w, w² = ‖M⁻¹K‖)."""
    n = M.shape[0]
    MK, MC = np.linalg.solve(M, K), np.linalg.solve(M, C)
    w = math.sqrt(max(float(np.linalg.norm(MK, 2)), float(np.linalg.norm(MC, 2)) ** 2, 1e-300))
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-MK / w, -MC / w]])  # (similar to A / w)
    tol = rtol * max(float(np.linalg.norm(A, 2)), 1e-300)
    dims, basis = [], np.zeros((2 * n, 0))
    while len(dims) < 2 * n:
        project = np.eye(2 * n) - basis @ basis.T
        _, sv, vt = np.linalg.svd(project @ A)
        null = vt[np.sum(sv > tol):].T  # {z : A z ∈ span(basis)}
        if null.shape[1] <= basis.shape[1]:
            break
        basis = np.linalg.qr(null)[0]
        dims.append(basis.shape[1])
    return dims


# --- the reduced route's linearization ----------------------------------------------------------


def reduced_linearization(reduced, x, v, t: float, *, rate: float = 0.0):
    """(M0, C0, K0, q0) of the reduced route M(q) q̈ = rhs(q, q̇, t) at the state (x, v, t):
    q0 by Gauss-Newton on x(q, t) = x (from the [reduced] initial values and a few turns of
    them), q̇0 by least squares on ẋ(q0, q̇, t) = v (must vanish, against the speeds |v|,
    |∂x/∂t| and ``rate`` × size: a state at rest in the coordinates), then K0 = −∂rhs/∂q,
    C0 = −∂rhs/∂q̇ by CasADi AD."""
    x, v = np.asarray(x, float).ravel(), np.asarray(v, float).ravel()
    q, qd, tt = reduced.q, reduced.q_dot, reduced.t
    ex = reduced.expressions
    fun = ca.Function("reduced_linear", [q, qd, tt], [ex["M"], ca.jacobian(ex["rhs"], q),
                                                    ca.jacobian(ex["rhs"], qd)])
    size = max(float(np.max(np.abs(x), initial=0.0)), 1.0)
    best, best_miss = None, math.inf
    turns = (np.pi, -np.pi / 2, np.pi / 2)
    starts = [reduced.initial, *(reduced.initial + d for d in turns), np.zeros(reduced.n)]
    for q0 in starts:
        q0 = np.array(q0, float)
        for _ in range(60):
            miss = np.asarray(reduced.position(q0, t), float).ravel() - x
            Jq = np.asarray(reduced.map_jacobian(q0, t), float)
            step = np.linalg.lstsq(Jq, -miss, rcond=None)[0]
            q0 = q0 + step
            if np.max(np.abs(step)) <= 1e-15 * max(1.0, float(np.max(np.abs(q0)))):
                break
        miss = float(np.max(np.abs(np.asarray(reduced.position(q0, t), float).ravel() - x)))
        if miss < best_miss:
            best, best_miss = q0, miss
    if best_miss > 1e-8 * size:
        raise InputError(f"the reduced coordinates do not reach the state (closest miss {best_miss:.3g} m)",
                         where="reduced.map")
    q0 = best
    Jq = np.asarray(reduced.map_jacobian(q0, t), float)
    sv = np.linalg.svd(Jq, compute_uv=False)
    if sv.size < reduced.n or sv[-1] <= 1e-10 * max(float(sv[0]), 1e-300):
        at = ", ".join(f"{c} = {v:.6g}" for c, v in zip(reduced.coordinates, q0, strict=True))
        raise InputError(f"the reduced coordinates are singular at this state ({at}: rank ∂x/∂q < "
                         f"{reduced.n}, M(q) singular, like the pole of spherical angles): Lagrange's "
                         "equations have no linearization there, so there is nothing to compare; the "
                         "Cartesian modes do not need coordinates", where="reduced")
    xt = np.asarray(reduced.velocity(q0, np.zeros(reduced.n), t), float).ravel()
    qd0 = np.linalg.lstsq(Jq, v - xt, rcond=None)[0]
    speed = max(float(np.max(np.abs(v), initial=0.0)), float(np.max(np.abs(xt), initial=0.0)), rate * size,
                1e-300)
    if float(np.max(np.abs(Jq @ qd0), initial=0.0)) > STATIONARY_RTOL * speed:
        raise InputError("the reduced coordinates move at this state (q̇ ≠ 0): their linearization is not "
                         "about a fixed point; use coordinates that turn with the frame", where="reduced")
    M0, Rq, Rqd = (np.asarray(a, float) for a in fun(q0, np.zeros(reduced.n), t))
    if getattr(reduced, "n_velocity_rows", 0):
        return (*_on_velocity_rows(reduced, q0, t, M0, -Rqd, -Rq), q0)
    return M0, -Rqd, -Rq, q0


def _on_velocity_rows(reduced, q0: np.ndarray, t: float, M0, C0, K0):
    """(M, C, K) of the reduced route restricted to the motions its velocity rows allow, as the
    Cartesian modes are (null([J; A])): with Ã = ∂c/∂q̇ at (q0, 0, t) and M0 = L Lᵀ, the basis
    T = L⁻ᵀ null(Ã L⁻ᵀ) (Tᵀ M0 T = I), and the rows' force Ãᵀμ at the state's μ (fixed) added
    to the stiffness: K = Tᵀ (K0 − ∂(Ãᵀμ)/∂q) T, C = Tᵀ C0 T, M = I."""
    q, qd, tt = reduced.q, reduced.q_dot, reduced.t
    c = reduced.expressions["velocity_rows"]
    A = ca.jacobian(c, qd)
    mu = type(q).sym("mu", c.numel())
    rows = ca.Function("reduced_velocity_rows", [q, qd, tt, mu],
                       [A, ca.jacobian(ca.mtimes(A.T, mu), q)])
    zero = np.zeros(reduced.n)
    mu0 = np.asarray(reduced.velocity_multipliers(q0, zero, t), float).ravel()
    A0, dforce = (np.asarray(a, float) for a in rows(q0, zero, t, mu0))
    L = np.linalg.cholesky(0.5 * (M0 + M0.T))
    Linv_T = np.linalg.inv(L).T
    B = A0 @ Linv_T
    _, sv, vt = np.linalg.svd(B)
    rank = int(np.sum(sv > 1e-12 * max(float(sv[0]) if sv.size else 0.0, 1e-300)))
    T = Linv_T @ vt[rank:].T
    return T.T @ M0 @ T, T.T @ C0 @ T, T.T @ (K0 - dforce) @ T
