"""Normal modes about an equilibrium or a steady motion: the roots of the linearized system.

constrained.linearization gives, about a state at rest in a frame (an equilibrium, or a
steady motion at rest in a uniformly rotating frame), the equations in mass-orthonormal
tangent coordinates q (``δx = T q``, ``Tᵀ M T = I``)

    q̈ + (G + D) q̇ + K q = 0      (G skew: gyroscopic; D symmetric: damping; K: stiffness).

The modes are the roots ``s`` of ``det(s² I + s (G + D) + K) = 0``, one Mode per complex pair
(the upper root) or real root: frequency ``|Im s|``, natural frequency ``|s|``, damping ratio
``−Re s / |s|``, growth rate ``Re s``; shapes are particle displacements ``δx = T q̂``. The
reduced route cross-checks it (``Modes.cross_check``): Lagrange's equations linearized at
the same state have the same roots.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..manifold.constraint_report import constraint_report
from ..manifold.manifold import Manifold
from ..model.structure import Model, assemble
from ..run.trajectory import Trajectory
from ..run.unilateral import has_one_sided
from .linearization import (
    STATIONARY_RTOL,
    RotatingFrame,
    balance_function,
    frame_arrays,
    linearize,
    omega_velocity,
    quadratic_roots,
    reduced_linearization,
    relative_equilibrium,
    zero_root_chain,
)
from .statics import _flat, equilibrium, zero_frequency_squared
from .statics_methods.kkt import KKT
from .statics_methods.large import forces_at_rest, is_large
from .statics_methods.large import stiffness as sparse_stiffness
from .statics_methods.large_modes import lowest_modes
from .statics_methods.prestress import stress_matters, tangent_sample

__all__ = ["Mode", "Modes", "ModesCrossCheck", "RotatingFrame", "modes"]

#: Roots s with |s|² within statics.zero_frequency_squared (d ε ‖K‖ units of round-off, and what
#: the state's unbalanced acceleration leaves) count as zero: a soft (neutral) mode. (A fixed
#: 1e-8 ‖K‖ made a pendulum's swing soft when its bob hung on a 1e9 N/m spring.)
#: A given state may be off the constraints by this × the system's size (rounded input); it is
#: projected onto them.
ON_CONSTRAINTS_RTOL = 1e-6
#: Roots with Re s > GROWTH_RTOL × max|s| grow (unstable); within it they count as undamped.
GROWTH_RTOL = 1e-7
#: Every mode (no ``count``) of a model of more unknowns 3N + C than this is refused: the dense
#: tangent basis (an SVD of J) of a 1,000-link chain (5,000) took 49 s of its 136 s (statics'
#: MAX_UNKNOWNS, 6,000, is the same bound).
DENSE_UNKNOWNS = 6000


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
    #: The parameter values the modes are for (``modes(..., parameters=...)`` included).
    parameters: dict = field(default_factory=dict)
    #: With velocity constraints: 3N − rank J, the configuration's freedom (the modes live in
    #: the velocity freedom, ``degrees_of_freedom``); None without them (the two are equal).
    configuration_degrees_of_freedom: int | None = None
    #: With ``count``: the tangent space's dimension, of which ``modes`` holds the lowest
    #: ``len(modes)`` (then ``basis`` spans only theirs and K = diag(ω²)); None: every mode.
    total_degrees_of_freedom: int | None = None

    @property
    def degrees_of_freedom(self) -> int:
        """The dimension of the space the modes live in: the tangent space of the constraints
        (with velocity constraints, null([J; A]): the velocity degrees of freedom)."""
        total = self.total_degrees_of_freedom
        return int(self.basis.shape[1]) if total is None else total

    @property
    def partial(self) -> bool:
        """Whether ``modes`` holds only the lowest of them (``count``)."""
        return self.total_degrees_of_freedom is not None and len(self.modes) < self.total_degrees_of_freedom

    def _freedom(self) -> str:
        if self.configuration_degrees_of_freedom is None:
            return f"{self.degrees_of_freedom} degree(s) of freedom"
        return (f"{self.configuration_degrees_of_freedom} configuration degree(s) of freedom, "
                f"{self.degrees_of_freedom} velocity degree(s) of freedom (the modes' space)")

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
        some = f"; the lowest {len(self.modes)} mode(s)" if self.partial else ""
        lines = [f"{self._freedom()} about the state at t = {self.t:g} s"
                 f"{frame}: {self.stability}{some}"]
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
                trend = "grows" if m.growth_rate > 0 else "decays"
                text = f"real root s = {m.eigenvalue.real:.6g} 1/s ({trend})"
            lines.append(f"  mode {k} ({m.kind}): {text}; largest motion: {moves}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"t": self.t, "x": self.x.tolist(), "v": self.v.tolist(),
                "frame": None if self.frame is None else {"omega": list(self.frame.omega),
                                                          "point": list(self.frame.point)},
                "degrees_of_freedom": self.degrees_of_freedom, "modes_computed": len(self.modes),
                "configuration_degrees_of_freedom": self.configuration_degrees_of_freedom,
                "stable": self.stable,
                "stability": self.stability, "conservative": self.conservative,
                "stationarity_residual": self.residual, "particles": list(self.particle_names),
                "multipliers": self.multipliers.tolist(),
                "matrices": {k: getattr(self, k).tolist() for k in ("M", "G", "D", "K")},
                "modes": [m.to_dict() for m in self.modes]}

    def trajectory(self, k: int = 0, *, amplitude: float | None = None, periods: float = 2.0,
                   frames: int = 60, system=None) -> Trajectory:
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
            phase = (2 * math.pi / span * tau)[:, None, None]
            wave = np.sin(phase) * mode.shape.real[None]
            rate = (2 * math.pi / span) * np.cos(phase) * mode.shape.real[None]
        else:
            e = np.exp(s * tau)[:, None, None]
            wave, rate = (e * mode.shape[None]).real, (s * e * mode.shape[None]).real
        X = self.x[None] + A * wave
        V = A * rate
        if system is not None:
            model = assemble(system).with_parameters(self.parameters)
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
        k = len(self.eigenvalues) // 2
        if k < M0.shape[0]:  # only the lowest k modes (the sparse route, conservative): the lowest k ω²
            w2 = np.linalg.eigvalsh(np.linalg.solve(np.linalg.cholesky(M0), np.linalg.solve(
                np.linalg.cholesky(M0), 0.5 * (K0 + K0.T)).T))[:k]
            root = np.sqrt(-w2.astype(complex))
            s = np.concatenate([root, -root])
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


def _modes_from_roots(s, Z, symmetric: bool, T: np.ndarray, zero_s2: float, n_particles: int):
    """(list of Mode, stable, stability) from the roots; see Mode.kind. ``zero_s2``: |s|² at or
    below it is 0 (statics.zero_frequency_squared)."""
    n = T.shape[1]
    scale = max(float(np.max(np.abs(s), initial=0.0)), 1e-300)
    soft_s = math.sqrt(max(zero_s2, 1e-300))
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
    if picked:  # every shape in one product (one per mode: a 3,000 × 1,000 T cast to complex 1,000 times)
        Zp = np.column_stack([z for _, z, _ in picked])
        shapes = (T @ Zp.real + 1j * (T @ Zp.imag)) if np.iscomplexobj(Zp) else T @ Zp
    for j, (root, _z, kind) in enumerate(picked):
        shape = shapes[:, j].astype(complex).reshape(n_particles, 3)
        k = np.unravel_index(int(np.argmax(np.abs(shape))), shape.shape)
        shape = shape * (abs(shape[k]) / shape[k]) if abs(shape[k]) > 0 else shape
        size = float(np.max(np.linalg.norm(np.abs(shape), axis=1), initial=0.0))
        modes.append(Mode(root, shape / size if size > 0 else shape, kind))
    modes.sort(key=lambda m: (m.frequency, m.eigenvalue.real))
    if n == 0:
        return modes, True, "no degrees of freedom: the constraints fix every particle"
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
          parameters: dict | None = None, model: Model | None = None, refine: bool | None = None,
          count: int | None = None) -> Modes:
    """Normal modes of ``system`` about a state at rest (in ``frame``, if given).

    ``x`` (N, 3): the state's positions; left out, the equilibrium near the system's initial
    positions (constrained.statics ``equilibrium``; in a frame, the state at rest in it,
    found by Newton the same way). ``v``: the velocities (default: at rest in the frame,
    Ω × (x − c)). ``refine``: Newton from the given x to the state at rest (default: only
    when x is left out). ``parameters``: other values for this call. The state must be at
    rest in the frame (InputError otherwise: rheonomic constraints, time-dependent or
    velocity-dependent forces are linearized at the instant ``t``). ``count``: only the lowest
    ``count`` modes — for a large conservative model at rest without a frame by a sparse
    shift-invert solve of the KKT pencil (statics_methods.large_modes: no dense tangent basis),
    otherwise the dense solve's lowest. Without it every mode, densely: refused beyond
    ``DENSE_UNKNOWNS`` (3N + C), where the dense basis takes minutes and gigabytes.
    """
    if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 1):
        raise InputError(f"count must be a positive whole number of modes, got {count!r}", where="count")
    if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
        raise InputError(f"t must be a finite number of seconds, got {t!r}", where="t")
    if frame is not None and not isinstance(frame, RotatingFrame):
        raise InputError("frame must be a RotatingFrame(omega, point)", where="frame")
    if not hasattr(system, "particles"):
        raise InputError(f"expected a System, got {type(system).__name__} (for a Scene, pass scene.system)",
                         where="system")
    if system.n_particles == 0:
        raise InputError("the system has no particles")
    model = (model or assemble(system)).with_parameters(parameters)
    system = system.with_parameters(parameters)
    if has_one_sided(model):
        raise InputError("normal modes of a system with one-sided constraints are not defined (their "
                         "force switches off or on at rest); make them two-sided for the modes about a "
                         "state where they hold", where="constraints")
    n3c = model.n_coordinates + model.n_constraints
    if count is None and n3c > DENSE_UNKNOWNS:
        raise InputError(f"every mode of this model takes a dense basis of its tangent space (3N + C = {n3c} "
                         f"unknowns, above {DENSE_UNKNOWNS}: {8 * model.n_coordinates ** 2 / 1e9:.2g} GB and "
                         "minutes of SVD); ask for the lowest few (count=K, --count K: a sparse solve)",
                         where="count")
    omega, centre = frame_arrays(frame, model.n_particles)
    size = system.size()
    if x is None and frame is None:
        x_flat = equilibrium(system, t=t, model=model).x.ravel()
    else:
        guess = system.positions.ravel() if x is None else _flat(system, x, "x")
        if model.n_constraints:
            manifold = Manifold.at(model, guess, t)
            projected = manifold.project_positions(guess, t, tol=1e-14 * size, max_iter=50)
            if not projected.converged and projected.residual > 1e-9 * size:
                raise InputError(f"the positions are not on the constraints (off by {projected.residual:.3g} "
                                 "after projection)", where="x")
            moved = float(np.max(np.abs(projected.x - guess)))
            if x is not None and not refine and moved > ON_CONSTRAINTS_RTOL * size:
                raise InputError(f"the positions are {moved:.3g} m off the constraints: give the state on "
                                 "them (or refine=True to start Newton there)", where="x")
            guess = projected.x
        refine = x is None if refine is None else refine
        x_flat = relative_equilibrium(model, guess, t, omega, centre, size) if refine else guess
    v_flat = omega_velocity(omega, centre, x_flat) if v is None else _flat(system, v, "v")
    if count is not None and frame is None and is_large(model) and not np.any(v_flat):
        balance = balance_function(model, float(t), omega, centre)
        sparse = lowest_modes(model, balance, x_flat, float(t), count, size, STATIONARY_RTOL)
        if sparse is not None:
            return _sparse_modes(system, model, sparse, x_flat, v_flat, float(t))
    T, C, K, lam, residual, unbalanced = linearize(model, x_flat, v_flat, float(t), frame)
    n = T.shape[1]
    M = np.eye(n)
    s, Z, symmetric = quadratic_roots(M, C, K)
    # ‖K‖₂: for the symmetric problem the largest |ω²| its eigenvalues already give (a second SVD of
    # a 1,000 × 1,000 K took 8 s)
    knorm2 = (float(np.max(np.abs(s[:n] ** 2), initial=0.0)) if symmetric else
              float(np.linalg.norm(K, 2))) if n else 0.0
    zero_s2 = zero_frequency_squared(knorm2, n, unbalanced, size)
    mode_list, stable, stability = _modes_from_roots(s, Z, symmetric, T, zero_s2, model.n_particles)
    if stable is False and symmetric and frame is None and _self_stress_holds(model, x_flat, float(t), T):
        stable, stability = None, _undecided(stability)
    chain = [] if symmetric or not n else zero_root_chain(M, C, K)
    if len(chain) > 2 and stable is not False:  # a Jordan chain at s = 0 longer than a free direction's
        stable, stability = False, (f"UNSTABLE (the root s = 0 is defective, a Jordan chain of length "
                                    f"{len(chain)}: small motions grow as t^{len(chain) - 1}, not "
                                    "exponentially)")
    knorm = max(float(np.linalg.norm(K)), 1e-300)
    configuration = None
    if model.n_position_rows < model.n_constraints:  # velocity rows: the two freedoms differ
        configuration = constraint_report(system, x_flat, float(t), model=model, samples=0).degrees_of_freedom
    total = None
    if count is not None and count < len(mode_list):  # the lowest count of them (the dense route)
        mode_list, total = mode_list[:count], n
    return Modes(x=x_flat.reshape(-1, 3), v=v_flat.reshape(-1, 3), t=float(t), frame=frame, multipliers=lam,
                 basis=T, M=M, G=0.5 * (C - C.T), D=0.5 * (C + C.T), K=K, eigenvalues=s, modes=mode_list,
                 stable=stable, stability=stability, particle_names=list(system.names),
                 conservative=bool(np.linalg.norm(K - K.T) <= 1e-9 * knorm), residual=residual,
                 parameters=model.parameters, configuration_degrees_of_freedom=configuration,
                 total_degrees_of_freedom=total)


def _undecided(stability: str) -> str:
    """The verdict of growing modes that a self-stress may hold (``_self_stress_holds``)."""
    return (stability.replace("UNSTABLE (", "undecided (at the minimum-norm multipliers ")
            + "; another split of the redundant rows' self-stress may hold them, as statics says")


def _self_stress_holds(model: Model, x: np.ndarray, t: float, T: np.ndarray | None) -> bool:
    """Whether a self-stress of the redundant rows changes K on the tangent space (``statics``'
    ``undecided_by_self_stress``, statics_methods.prestress): the growing modes of the minimum-norm
    multipliers may then be held by another valid split (a hanging net with both diagonals).
    ``T``: a basis of the tangent space, or None for the sparse route (random tangent directions,
    ``prestress.tangent_sample``)."""
    if model.n_position_rows < 2 or model.n_position_rows < model.n_constraints:
        return False
    kkt = KKT(model, t)
    if T is None:
        J = forces_at_rest(model, x, t)[1]
        return stress_matters(model, lambda y, lam: sparse_stiffness(kkt.stiffness, y, lam), x, J, True,
                              tangent_sample(model, J))
    J = np.asarray(model.jacobian(x, t)[1], float).reshape(model.n_position_rows, model.n_coordinates)
    return stress_matters(model, lambda y, lam: np.asarray(kkt.stiffness(y, lam), float), x, J, False, T)


def _sparse_modes(system, model: Model, sparse, x_flat: np.ndarray, v_flat: np.ndarray, t: float) -> Modes:
    """Modes from statics_methods.large_modes.lowest_modes: the lowest k, with basis Φ
    (Φᵀ M Φ = I) and K = diag(ω²)."""
    Phi, w2, lam, residual, unbalanced, dof, knorm = sparse
    k = len(w2)
    root = np.sqrt(-w2.astype(complex))
    s = np.concatenate([root, -root])
    zero_s2 = zero_frequency_squared(knorm, dof, unbalanced, system.size())
    mode_list, stable, stability = _modes_from_roots(s, np.eye(k), True, Phi, zero_s2, model.n_particles)
    if stable is False:
        stability = stability.replace("UNSTABLE (", "UNSTABLE (at least ")
        if _self_stress_holds(model, x_flat, t, None):
            stable, stability = None, _undecided(stability)
    return Modes(x=x_flat.reshape(-1, 3), v=v_flat.reshape(-1, 3), t=t, frame=None, multipliers=lam,
                 basis=Phi, M=np.eye(k), G=np.zeros((k, k)), D=np.zeros((k, k)), K=np.diag(w2), eigenvalues=s,
                 modes=mode_list, stable=stable, stability=stability, particle_names=list(system.names),
                 conservative=True, residual=residual, parameters=model.parameters,
                 total_degrees_of_freedom=dof)


