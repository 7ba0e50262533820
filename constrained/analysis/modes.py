"""Small oscillations on the constraint manifold: the linearized system and its normal modes.

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

both Jacobians by CasADi AD. ``K`` holds the stiffness of the forces and the constraints'
curvature weighted by the multipliers (``−Σ λ_k ∇²f_k``: a hanging chain's tension), and in a
frame the centrifugal softening; ``D`` (symmetric part) the Rayleigh damping; ``G`` (skew part)
the gyroscopic terms: Coriolis ``2 Tᵀ M [Ω]× T``, magnetic forces. The modes are the roots
``s`` of ``det(s² I + s (G + D) + K) = 0``: frequency ``|Im s|``, natural frequency ``|s|``,
damping ratio ``−Re s / |s|``; shapes are particle displacements ``δx = T q̂``.

The reduced route cross-checks it (``Modes.cross_check``): ``M(q) q̈ = rhs(q, q̇, t)``
linearized at the same state (``M0 δq̈ = rhs_q δq + rhs_q̇ δq̇``) has the same roots ``s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.linalg as sla

from ..errors import InputError
from ..manifold.dense import tangent_basis
from ..manifold.manifold import Manifold
from ..model.structure import Model, assemble
from ..run.trajectory import Trajectory
from .statics import _flat, _newton, equilibrium

__all__ = ["Mode", "Modes", "ModesCrossCheck", "RotatingFrame", "modes"]

#: The state must be at rest in the frame: tangential acceleration and frame velocity within
#: this fraction of the system's acceleration and velocity scales.
STATIONARY_RTOL = 1e-6
#: ω² (undamped, symmetric) with |ω²| <= SOFT_RTOL × ‖K‖ count as zero: a soft (neutral) mode.
SOFT_RTOL = 1e-8
#: Roots with Re s > GROWTH_RTOL × max|s| grow (unstable); within it they count as undamped.
GROWTH_RTOL = 1e-7
#: Newton on the relative equilibrium: force balance within this × the force scale.
FORCE_RTOL = 1e-10


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


@dataclass(frozen=True)
class Mode:
    """One root s of the quadratic eigenproblem (the upper one of a complex pair).

    ``frequency`` |Im s| (rad/s, the damped frequency; 0 for a real root), ``natural_frequency``
    |s|, ``damping_ratio`` −Re s/|s| (NaN at s = 0), ``growth_rate`` Re s (1/s, negative:
    decay), ``shape`` (N, 3) complex particle displacements, the largest one of length 1 and
    its largest component real and positive; ``kind``: "oscillatory", "overdamped" (real,
    decaying), "divergent" (real, growing), "soft" (s = 0, neutral)."""

    eigenvalue: complex
    shape: np.ndarray
    kind: str

    @property
    def frequency(self) -> float:
        return abs(self.eigenvalue.imag)

    @property
    def frequency_hz(self) -> float:
        return self.frequency / (2 * math.pi)

    @property
    def period(self) -> float:
        return 2 * math.pi / self.frequency if self.frequency > 0 else math.inf

    @property
    def natural_frequency(self) -> float:
        return abs(self.eigenvalue)

    @property
    def damping_ratio(self) -> float:
        return -self.eigenvalue.real / abs(self.eigenvalue) if abs(self.eigenvalue) > 0 else math.nan

    @property
    def growth_rate(self) -> float:
        return self.eigenvalue.real

    def to_dict(self) -> dict:
        return {"kind": self.kind, "eigenvalue": [self.eigenvalue.real, self.eigenvalue.imag],
                "frequency_rad_s": self.frequency, "frequency_hz": self.frequency_hz,
                "period_s": self.period if math.isfinite(self.period) else None,
                "natural_frequency_rad_s": self.natural_frequency,
                "damping_ratio": None if math.isnan(self.damping_ratio) else self.damping_ratio,
                "growth_rate_per_s": self.growth_rate,
                "shape_real": self.shape.real.tolist(), "shape_imag": self.shape.imag.tolist()}


@dataclass(frozen=True)
class Modes:
    """The linearized system about a state at rest in ``frame`` and its modes.

    ``x``, ``v`` (N, 3) and ``t``: the state (inertial); ``multipliers`` (C,) there. In the
    tangent coordinates q (``basis`` T, (3N, n), ``Tᵀ M T = I``): ``M`` (= I), ``G`` (skew,
    gyroscopic), ``D`` (symmetric, damping), ``K`` (stiffness, symmetric when the forces are
    conservative) — ``q̈ + (G + D) q̇ + K q = 0``. ``eigenvalues`` (2n,) every root s;
    ``modes`` one Mode per complex pair or real root, by frequency (then by s). ``stable``:
    True (every mode decays, or oscillates undamped), False (one grows), None (a soft mode:
    neutral); ``stability`` says it in words."""

    x: np.ndarray
    v: np.ndarray
    t: float
    frame: RotatingFrame | None
    multipliers: np.ndarray
    basis: np.ndarray
    M: np.ndarray
    G: np.ndarray
    D: np.ndarray
    K: np.ndarray
    eigenvalues: np.ndarray
    modes: list[Mode]
    stable: bool | None
    stability: str
    particle_names: list[str] = field(default_factory=list)
    conservative: bool = True
    residual: float = 0.0

    @property
    def degrees_of_freedom(self) -> int:
        return int(self.basis.shape[1])

    @property
    def frequencies(self) -> np.ndarray:
        """The modes' damped frequencies |Im s| (rad/s), in the order of ``modes``."""
        return np.array([m.frequency for m in self.modes])

    @property
    def damping_ratios(self) -> np.ndarray:
        return np.array([m.damping_ratio for m in self.modes])

    @property
    def shapes(self) -> np.ndarray:
        """(modes, N, 3) complex particle displacements."""
        return np.array([m.shape for m in self.modes])

    def table(self) -> str:
        """One line per mode: frequency, period, damping, what moves most."""
        frame = "" if self.frame is None else (f" in the frame turning at Ω = {_vec(self.frame.omega)} rad/s "
                                               f"about {_vec(self.frame.point)} m")
        lines = [f"{self.degrees_of_freedom} degree(s) of freedom about the state at t = {self.t:g} s{frame}: "
                 f"{self.stability}"]
        names = self.particle_names or [f"p{i}" for i in range(len(self.x))]
        for k, m in enumerate(self.modes, 1):
            amp = np.linalg.norm(np.abs(m.shape), axis=1)
            moves = names[int(np.argmax(amp))]
            if m.kind == "oscillatory":
                text = (f"ω = {m.frequency:.6g} rad/s ({m.frequency_hz:.6g} Hz, period {m.period:.6g} s), "
                        f"damping ratio {m.damping_ratio + 0.0:.3g}")
            elif m.kind == "soft":
                text = "s = 0 (soft: neutral, no restoring force)"
            else:
                text = f"real root s = {m.eigenvalue.real:.6g} 1/s ({'grows' if m.growth_rate > 0 else 'decays'})"
            lines.append(f"  mode {k} ({m.kind}): {text}; largest motion: {moves}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"t": self.t, "x": self.x.tolist(), "v": self.v.tolist(),
                "frame": None if self.frame is None else {"omega": list(self.frame.omega),
                                                          "point": list(self.frame.point)},
                "degrees_of_freedom": self.degrees_of_freedom, "stable": self.stable,
                "stability": self.stability, "conservative": self.conservative,
                "stationarity_residual": self.residual, "particles": list(self.particle_names),
                "multipliers": self.multipliers.tolist(),
                "matrices": {k: getattr(self, k).tolist() for k in ("M", "G", "D", "K")},
                "modes": [m.to_dict() for m in self.modes]}

    def trajectory(self, k: int = 0, *, amplitude: float | None = None, periods: float = 2.0,
                   frames: int = 120, system=None) -> Trajectory:
        """Mode ``k`` (0-based) as a Trajectory for the animation and the viewer:
        x(τ) = x0 + A Re(shape e^{sτ}), projected onto the constraints at t0 (so rods keep their
        lengths at a visible amplitude), over ``periods`` periods (a real root: over 2/|s|;
        a soft mode: its shape swept once). ``amplitude`` A in metres (default 5 % of the
        system's size; the largest particle moves by A); ``system`` gives the projection."""
        if not 0 <= k < len(self.modes):
            raise InputError(f"there is no mode {k + 1}: the state has {len(self.modes)} mode(s)",
                             where="mode")
        mode = self.modes[k]
        size = max(float(np.max(np.ptp(self.x, axis=0))), float(np.max(np.linalg.norm(self.x, axis=1))), 1e-3)
        A = 0.05 * size if amplitude is None else float(amplitude)
        if not (math.isfinite(A) and A > 0):
            raise InputError(f"the amplitude must be a positive length, got {amplitude!r}", where="amplitude")
        s = complex(mode.eigenvalue)
        span = periods * mode.period if mode.frequency > 0 else (2.0 / abs(s) if abs(s) > 0 else 1.0)
        tau = np.linspace(0.0, span, max(2, int(frames)))
        if mode.kind == "soft":
            wave = np.sin(2 * math.pi * tau / span)[:, None, None] * mode.shape.real[None]
            rate = (2 * math.pi / span) * np.cos(2 * math.pi * tau / span)[:, None, None] * mode.shape.real[None]
        else:
            e = np.exp(s * tau)[:, None, None]
            wave, rate = (e * mode.shape[None]).real, (s * e * mode.shape[None]).real
        X = self.x[None] + A * wave
        V = A * rate
        if system is not None:
            model = assemble(system)
            manifold = Manifold.at(model, self.x.ravel(), self.t)
            for i in range(len(tau)):
                X[i] = manifold.project_positions(X[i].ravel(), self.t, tol=1e-12 * size, max_iter=20).x \
                    .reshape(-1, 3)
        traj = Trajectory(t=self.t + tau, x=X, v=V, particle_names=list(self.particle_names))
        traj.info.update({"mode": k + 1, "eigenvalue": [s.real, s.imag], "amplitude": A, "kind": mode.kind})
        return traj

    def cross_check(self, reduced) -> ModesCrossCheck:
        """The roots of the reduced route's linearization at the same state (a ReducedModel
        whose coordinates are at rest at it: in a rotating frame, coordinates turning with it)."""
        rate = float(np.max(np.abs(self.eigenvalues), initial=0.0))
        M0, C0, K0, q0 = reduced_linearization(reduced, self.x, self.v, self.t, rate=rate)
        s = quadratic_roots(M0, C0, K0)[0]
        return ModesCrossCheck(_sorted_roots(self.eigenvalues), _sorted_roots(s), q0)


@dataclass(frozen=True)
class ModesCrossCheck:
    """The Cartesian roots beside the reduced route's (each sorted by Im s, then Re s) and
    ``q`` the reduced coordinates of the state; ``difference`` the largest |Δs| over max|s|."""

    cartesian: np.ndarray
    reduced: np.ndarray
    q: np.ndarray

    @property
    def difference(self) -> float:
        if self.cartesian.shape != self.reduced.shape:
            return math.inf
        scale = max(float(np.max(np.abs(self.cartesian), initial=0.0)), 1e-300)
        return float(np.max(np.abs(self.cartesian - self.reduced), initial=0.0)) / scale


def _vec(v) -> str:
    return "(" + ", ".join(f"{c:.6g}" for c in v) + ")"


def _sorted_roots(s: np.ndarray) -> np.ndarray:
    s = np.asarray(s, complex)
    scale = max(float(np.max(np.abs(s), initial=0.0)), 1e-300)
    key = np.round(np.column_stack([s.imag, s.real]) / (1e-6 * scale))  # ties within round-off
    return s[np.lexsort((key[:, 1], key[:, 0]))]


# --- the linearization -------------------------------------------------------------------------


def _cross(omega: np.ndarray, r):
    """Ω × r for every particle of a flat CasADi column r (3N,)."""
    R = ca.reshape(r, 3, -1)
    wx, wy, wz = (float(c) for c in omega)
    out = ca.vertcat(wy * R[2, :] - wz * R[1, :], wz * R[0, :] - wx * R[2, :], wx * R[1, :] - wy * R[0, :])
    return ca.reshape(out, -1, 1)


def _frame_arrays(frame: RotatingFrame | None, n_particles: int) -> tuple[np.ndarray, np.ndarray]:
    omega = np.zeros(3) if frame is None else np.asarray(frame.omega)
    centre = np.zeros(3 * n_particles) if frame is None else np.tile(frame.point, n_particles)
    return omega, centre


def _balance(model: Model, t: float, omega: np.ndarray, centre: np.ndarray):
    """CasADi Function (y, u, λ) -> r: the frame's equation of motion at the multipliers λ,
    r = F(y, u + Ω×(y − c), t) + Jᵀλ − M(2 Ω×u + Ω×(Ω×(y − c))), with ∂r/∂y, ∂r/∂u."""
    n3, C = model.n_coordinates, model.n_constraints
    y, u, lam = ca.SX.sym("y", n3), ca.SX.sym("u", n3), ca.SX.sym("lam", C)
    arm = y - centre
    F, J, _ = model.dynamics(y, u + _cross(omega, arm), t)
    m = ca.DM(model.masses)
    r = F - m * (2 * _cross(omega, u) + _cross(omega, _cross(omega, arm)))
    if C:
        r = r + ca.mtimes(J.T, lam)
    return ca.Function("frame_balance", [y, u, lam], [r, ca.jacobian(r, y), ca.jacobian(r, u), J, F])


def _relative_equilibrium(model: Model, x0: np.ndarray, t: float, omega, centre, size: float) -> np.ndarray:
    """Positions at rest in the frame near x0: r(y, 0, λ) = 0 with f(y, t) = 0 (Newton on the
    KKT conditions, statics' line search and least-squares steps)."""
    n3, C = model.n_coordinates, model.n_constraints
    fun = _balance(model, t, omega, centre)
    manifold = Manifold.at(model, x0, t)

    class Kkt:
        @staticmethod
        def residual_and_jacobian(z):
            r, Ry, _, J, _ = fun(z[:n3], np.zeros(n3), z[n3:])
            f, _ = model.jacobian(z[:n3], t)
            J = np.asarray(J, float).reshape(C, n3)
            res = np.concatenate([np.asarray(r, float).ravel(), np.asarray(f, float).ravel()])
            jac = np.block([[np.asarray(Ry, float), J.T], [J, np.zeros((C, C))]])
            return res, jac

    def restore(z):
        if not C:
            return z
        projected = manifold.project_positions(z[:n3], t, tol=1e-14 * size, max_iter=8)
        return z if not np.all(np.isfinite(projected.x)) else np.concatenate([projected.x, z[n3:]])

    x0 = restore(np.concatenate([x0, np.zeros(C)]))[:n3]
    _, lam = manifold.accelerations(x0, omega_velocity(omega, centre, x0), t)
    scale = _force_scale(model, *fun(x0, np.zeros(n3), lam)[3:], lam, omega, x0)
    w = np.concatenate([np.full(n3, 1.0 / (FORCE_RTOL * scale)), np.full(C, 1e12 / size)])
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
    """(T, G + D, K, λ, residual) about the state (x, v, t) (flat), at rest in ``frame``:
    see the module's docstring. ``residual``: the largest tangential acceleration left
    (m/s²) over the acceleration scale; InputError when the state is not at rest in the frame."""
    n3 = model.n_coordinates
    omega, centre = _frame_arrays(frame, model.n_particles)
    u0 = v - omega_velocity(omega, centre, x)
    _, lam = Manifold.at(model, x, t).accelerations(x, v, t)
    r, Ry, Ru, J, F = _balance(model, t, omega, centre)(x, u0, lam)
    r, Ry, Ru = np.asarray(r, float).ravel(), np.asarray(Ry, float), np.asarray(Ru, float)
    accel = _force_scale(model, J, F, lam, omega, x, per_mass=True)
    J = np.asarray(J, float).reshape(model.n_constraints, n3)
    minv_sqrt = 1.0 / np.sqrt(model.masses)
    T = minv_sqrt[:, None] * (tangent_basis(J * minv_sqrt[None, :], n3) if model.n_constraints else np.eye(n3))
    speed = max(float(np.max(np.abs(v), initial=0.0)), float(np.linalg.norm(omega)) * _size(x), 1e-300)
    tangential = T @ (T.T @ r)  # M⁻¹-free: T Tᵀ r is the tangential acceleration (m/s²)
    residual = float(np.max(np.abs(tangential), initial=0.0)) / accel
    moving = float(np.max(np.abs(u0), initial=0.0)) / speed
    if residual > STATIONARY_RTOL or moving > STATIONARY_RTOL:
        where = "" if frame is None else " in the given frame"
        raise InputError(
            f"the state is not at rest{where}: " + (
                f"its velocity relative to the frame is {np.max(np.abs(u0)):.3g} m/s" if moving > STATIONARY_RTOL
                else f"the forces leave a tangential acceleration of {np.max(np.abs(tangential)):.3g} m/s²")
            + "; linearize about an equilibrium (leave x out: statics finds one), or give the rotating "
            "frame in which the motion is steady", where="x")
    return T, -T.T @ Ru @ T, -T.T @ Ry @ T, lam, residual


def _force_scale(model: Model, J, F, lam, omega, x, *, per_mass: bool = False) -> float:
    """The largest of the applied forces, the constraint forces Jᵀλ and the centrifugal
    forces M Ω×(Ω×r) on any coordinate (divided by its mass: ``per_mass``)."""
    J = np.asarray(J, float).reshape(model.n_constraints, -1)
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
    knorm = max(float(np.linalg.norm(K, 2)), 1e-300)
    if np.linalg.norm(C) <= 1e-14 * math.sqrt(knorm * float(np.linalg.norm(M, 2))) and \
            np.linalg.norm(K - K.T) <= 1e-10 * knorm:
        w2, Z = sla.eigh(0.5 * (K + K.T), M)
        root = np.sqrt(-w2.astype(complex))  # s = ±i ω for ω² > 0, ±σ for ω² = −σ² < 0
        return np.concatenate([root, -root]), np.hstack([Z, Z]).astype(complex), True
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-K, -C]])
    B = np.block([[np.eye(n), np.zeros((n, n))], [np.zeros((n, n)), M]])
    s, Z = sla.eig(A, B)
    return s, Z[:n], False


def _modes_from_roots(s, Z, symmetric: bool, T: np.ndarray, K: np.ndarray, n_particles: int):
    """(list of Mode, stable, stability) from the roots; see Mode.kind."""
    n = T.shape[1]
    scale = max(float(np.max(np.abs(s), initial=0.0)), 1e-300)
    soft_s = math.sqrt(SOFT_RTOL * max(float(np.linalg.norm(K, 2)), 1e-300))
    picked = []
    if symmetric:  # ω² and its shape: one mode per degree of freedom
        for j in range(n):
            root = s[j]
            kind = ("soft" if abs(root) <= soft_s else "oscillatory" if abs(root.imag) > 0 else "divergent")
            picked.append((complex(0, root.imag) if kind == "oscillatory" else
                           (0j if kind == "soft" else complex(abs(root.real), 0)), Z[:, j], kind))
    else:
        for j, root in enumerate(s):
            if not np.isfinite(root):
                continue
            if root.imag > GROWTH_RTOL * scale:
                picked.append((complex(root), Z[:, j], "oscillatory"))
            elif abs(root.imag) <= GROWTH_RTOL * scale:
                kind = "soft" if abs(root) <= soft_s else ("divergent" if root.real > 0 else "overdamped")
                picked.append((complex(root.real, 0.0), Z[:, j], kind))
    modes = []
    for root, z, kind in picked:
        shape = (T @ z).reshape(n_particles, 3)
        k = np.unravel_index(int(np.argmax(np.abs(shape))), shape.shape)
        shape = shape * (abs(shape[k]) / shape[k]) if abs(shape[k]) > 0 else shape
        size = float(np.max(np.linalg.norm(np.abs(shape), axis=1), initial=0.0))
        modes.append(Mode(root, shape / size if size > 0 else shape, kind))
    modes.sort(key=lambda m: (m.frequency, m.eigenvalue.real))
    growing = [m for m in modes if m.growth_rate > GROWTH_RTOL * scale]
    soft = [m for m in modes if m.kind == "soft"]
    if growing:
        return modes, False, f"UNSTABLE ({len(growing)} growing mode(s))"
    if soft:
        return modes, None, f"neutral ({len(soft)} soft mode(s), s = 0)"
    if all(m.growth_rate < -GROWTH_RTOL * scale for m in modes):
        return modes, True, "asymptotically stable (every mode decays)"
    return modes, True, "stable (undamped oscillations)"


def modes(system, x=None, v=None, t: float = 0.0, *, frame: RotatingFrame | None = None,
          parameters: dict | None = None, model: Model | None = None, refine: bool | None = None) -> Modes:
    """Normal modes of ``system`` about a state at rest (in ``frame``, if given).

    ``x`` (N, 3): the state's positions; left out, the equilibrium near the system's initial
    positions (constrained.statics ``equilibrium``; in a frame, the state at rest in it,
    found by Newton the same way). ``v``: the velocities (default: at rest in the frame,
    Ω × (x − c)). ``refine``: Newton from the given x to the state at rest (default: only
    when x is left out). ``parameters``: other values for this call. The state must be at
    rest in the frame (InputError otherwise: rheonomic constraints, time-dependent or
    velocity-dependent forces are linearized at the instant ``t``).
    """
    if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
        raise InputError(f"t must be a finite number of seconds, got {t!r}", where="t")
    if frame is not None and not isinstance(frame, RotatingFrame):
        raise InputError("frame must be a RotatingFrame(omega, point)", where="frame")
    if system.n_particles == 0:
        raise InputError("the system has no particles")
    model = (model or assemble(system)).with_parameters(parameters)
    system = system.with_parameters(parameters)
    omega, centre = _frame_arrays(frame, model.n_particles)
    size = system.size()
    if x is None and frame is None:
        x_flat = equilibrium(system, t=t, model=model).x.ravel()
    else:
        guess = system.positions.ravel() if x is None else _flat(system, x, "x")
        if model.n_constraints:
            projected = Manifold.at(model, guess, t).project_positions(guess, t, tol=1e-14 * size, max_iter=50)
            if not projected.converged and projected.residual > 1e-9 * size:
                raise InputError(f"the positions are not on the constraints (off by {projected.residual:.3g} "
                                 "after projection)", where="x")
            guess = projected.x
        refine = x is None if refine is None else refine
        x_flat = _relative_equilibrium(model, guess, t, omega, centre, size) if refine else guess
    v_flat = omega_velocity(omega, centre, x_flat) if v is None else _flat(system, v, "v")
    T, C, K, lam, residual = linearize(model, x_flat, v_flat, float(t), frame)
    n = T.shape[1]
    M = np.eye(n)
    s, Z, symmetric = quadratic_roots(M, C, K)
    mode_list, stable, stability = _modes_from_roots(s, Z, symmetric, T, K, model.n_particles)
    knorm = max(float(np.linalg.norm(K)), 1e-300)
    return Modes(x=x_flat.reshape(-1, 3), v=v_flat.reshape(-1, 3), t=float(t), frame=frame, multipliers=lam,
                 basis=T, M=M, G=0.5 * (C - C.T), D=0.5 * (C + C.T), K=K, eigenvalues=s, modes=mode_list,
                 stable=stable, stability=stability, particle_names=list(system.names),
                 conservative=bool(np.linalg.norm(K - K.T) <= 1e-9 * knorm), residual=residual)


# --- the reduced route's linearization ----------------------------------------------------------


def reduced_linearization(reduced, x, v, t: float, *, rate: float = 0.0):
    """(M0, C0, K0, q0) of the reduced route M(q) q̈ = rhs(q, q̇, t) at the state (x, v, t):
    q0 by Gauss-Newton on x(q, t) = x (from the [reduced] initial values and a few turns of
    them), q̇0 by least squares on ẋ(q0, q̇, t) = v (must vanish, against the speeds |v|,
    |∂x/∂t| and ``rate`` × size: a state at rest in the coordinates), then K0 = −∂rhs/∂q, C0 = −∂rhs/∂q̇ by CasADi AD."""
    x, v = np.asarray(x, float).ravel(), np.asarray(v, float).ravel()
    q, qd, tt = reduced.q, reduced.q_dot, reduced.t
    ex = reduced.expressions
    fun = ca.Function("reduced_linear", [q, qd, tt], [ex["M"], ca.jacobian(ex["rhs"], q),
                                                    ca.jacobian(ex["rhs"], qd)])
    size = max(float(np.max(np.abs(x), initial=0.0)), 1.0)
    best, best_miss = None, math.inf
    starts = [reduced.initial] + [reduced.initial + d for d in (np.pi, -np.pi / 2, np.pi / 2)] + [np.zeros(reduced.n)]
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
    xt = np.asarray(reduced.velocity(q0, np.zeros(reduced.n), t), float).ravel()
    qd0 = np.linalg.lstsq(Jq, v - xt, rcond=None)[0]
    speed = max(float(np.max(np.abs(v), initial=0.0)), float(np.max(np.abs(xt), initial=0.0)), rate * size,
                1e-300)
    if float(np.max(np.abs(Jq @ qd0), initial=0.0)) > STATIONARY_RTOL * speed:
        raise InputError("the reduced coordinates move at this state (q̇ ≠ 0): their linearization is not "
                         "about a fixed point; use coordinates that turn with the frame", where="reduced")
    M0, Rq, Rqd = (np.asarray(a, float) for a in fun(q0, np.zeros(reduced.n), t))
    return M0, -Rqd, -Rq, q0
