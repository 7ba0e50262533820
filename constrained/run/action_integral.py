"""The action of a run, S(t) = ∫ L dt with L = T − V − U, and the stationarity check of a
trajectory against admissible variations (see constrained.action for the principle's three
tools; this module holds the two that take a trajectory)."""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from .. import tomlparse
from ..errors import InputError, listed
from ..manifold.constraint_report import jacobian_rank
from ..model.structure import Model, assemble
from .event_records import checked_segments
from .quantities import multipliers_along
from .trajectory import Trajectory, atomic_write
from .unilateral import ActiveSet, one_sided

__all__ = ["ActionResult", "StationarityResult", "action", "end_configuration", "lagrangian_function",
           "save_action_figure", "save_path_figure", "stationarity"]

#: Slots of effects that have no Lagrangian (left out of L, refused by the action principle).
NON_LAGRANGIAN_SLOTS = ("dissipation", "applied_force")

_L_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


# --- the Lagrangian --------------------------------------------------------------------------


def as_model(model_or_system) -> Model:
    if isinstance(model_or_system, Model):
        return model_or_system
    if getattr(model_or_system, "n_particles", 0) == 0:
        raise InputError("the system has no particles")
    return assemble(model_or_system)


def lagrangian_function(model: Model) -> ca.Function:
    """``L(x, v, t) = T − V − U`` of an assembled model, a CasADi Function (3N vectors).

    Built from ``model.symbols`` and the system's effects, summed per slot as the Model
    does; the effects without a Lagrangian (damping, applied forces) are not in it (see
    :func:`excluded_effects`).
    """
    cached = _L_CACHE.get(model)
    if cached is not None:
        return cached
    if not getattr(model.structure, "pairs", ()) and "generalized_potential" not in model.active_terms:
        # T − V from the Model's bound Functions: shared by Models of equal values (a fresh call
        # of the same scene parses no effect again)
        x, v, t = (ca.SX.sym(name, n) for name, n in (("x", model.n_coordinates), ("v", model.n_coordinates),
                                                       ("t", 1)))
        L = ca.Function("L", [x, v, t], [model.kinetic(v) - model.potential(x, t)], ["x", "v", "t"], ["L"])
        _L_CACHE[model] = L
        return L
    s = model.symbols
    V = ca.SX(0)
    U = ca.SX(0)
    for effect in model.system.effects:
        if effect.slot == "potential":
            V = V + effect.term(s)
        elif effect.slot == "generalized_potential":
            U = U + effect.term(s)
    T = 0.5 * ca.dot(ca.DM(model.masses) * s.v, s.v)
    L = ca.Function("L", [s.x, s.v, s.t], [T - V - U], ["x", "v", "t"], ["L"])
    _L_CACHE[model] = L
    return L


def excluded_effects(model: Model) -> list[str]:
    """Labels of the effects that have no Lagrangian (damping, applied forces)."""
    return [e.label for e in model.system.effects if e.slot in NON_LAGRANGIAN_SLOTS]


def require_lagrangian(model: Model, what: str) -> None:
    if model.n_position_rows < model.n_constraints:
        raise InputError(
            f"{what} is for holonomic constraints: a motion under velocity constraints follows "
            "d'Alembert's principle, and is not a stationary path of the action among the paths that "
            "obey them (that path would be the 'vakonomic' motion, another mechanics)")
    bad = excluded_effects(model)
    if bad:
        raise InputError(
            f"{what} needs forces that come from a Lagrangian (potentials and generalized "
            f"potentials); the system has {', '.join(repr(b) for b in bad)}, whose forces "
            "(dissipation, applied forces) are not in L = T − V − U"
        )


def flat_samples(traj: Trajectory):
    n = len(traj.t)
    return (np.asarray(traj.t, float), np.asarray(traj.x, float).reshape(n, -1),
            np.asarray(traj.v, float).reshape(n, -1))


def _check_trajectory(model: Model, traj: Trajectory, minimum: int) -> None:
    if not isinstance(traj, Trajectory):
        raise InputError(f"expected a Trajectory, got {type(traj).__name__}")
    n = len(traj.t)
    if n < minimum:
        raise InputError(f"the trajectory has {n} samples; at least {minimum} are needed")
    if traj.x.reshape(n, -1).shape[1] != model.n_coordinates:
        raise InputError(
            f"the trajectory has {traj.x.shape[1]} particles, the system {model.n_particles}"
        )
    if np.any(np.diff(traj.t) <= 0):
        raise InputError("the trajectory's times must be strictly increasing")


def _cumulative(y: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, str]:
    """∫ y dt from t[0] at every sample: composite Simpson (O(h⁴)) where SciPy has it."""
    if len(t) < 3:
        from scipy.integrate import cumulative_trapezoid

        return cumulative_trapezoid(y, t, initial=0.0), "trapezoid"
    try:
        from scipy.integrate import cumulative_simpson
    except ImportError:  # SciPy < 1.12
        from scipy.integrate import cumulative_trapezoid

        return cumulative_trapezoid(y, t, initial=0.0), "trapezoid"
    return cumulative_simpson(y, x=t, initial=0.0), "simpson"


def _integral(y: np.ndarray, t: np.ndarray) -> float:
    from scipy.integrate import simpson

    return float(simpson(y, x=t))


# --- the action of a run ---------------------------------------------------------------------


@dataclass
class ActionResult:
    """The action along a trajectory: ``total = S(t_end)``, ``cumulative`` S(t) (T,),
    ``lagrangian`` L(t) (T,), ``quadrature`` used, ``excluded`` effects not in L."""

    t: np.ndarray
    lagrangian: np.ndarray
    cumulative: np.ndarray
    total: float
    quadrature: str
    excluded: list[str] = field(default_factory=list)

    def __repr__(self) -> str:
        note = f", without {', '.join(self.excluded)}" if self.excluded else ""
        return f"ActionResult(S = {self.total:.10g} J·s over t = {self.t[0]:g}..{self.t[-1]:g} s{note})"


def action(model_or_system, trajectory: Trajectory) -> ActionResult:
    """The cumulative action ``S(t) = ∫ L dt`` along ``trajectory`` (Cartesian L = T − V − U).

    L is evaluated at the samples with the trajectory's positions and velocities and
    integrated by composite Simpson on the sample times (error O(h⁴) for smooth motion;
    sample densely for an accurate number).
    """
    model = as_model(model_or_system)
    _check_trajectory(model, trajectory, 2)
    t, X, V = flat_samples(trajectory)
    L = model.evaluate(lagrangian_function(model), X, V, t)[0].ravel()
    S, rule = _cumulative(L, t)
    return ActionResult(t=t, lagrangian=L, cumulative=S, total=float(S[-1]), quadrature=rule,
                        excluded=excluded_effects(model))


# --- stationarity under admissible variations ------------------------------------------------


@dataclass
class StationarityResult:
    """ΔS(ε) = S[x + εη] − S[x] for each ε (augmented Lagrangian L + λ·f).

    ``order``: slope of log|ΔS| against log ε (≈ 2 for the true motion, ≈ 1 for a wrong
    one); ``ratio``: (|ΔS|/ε at the smallest ε) / (|ΔS|/ε at the largest) (≈ ε_min/ε_max for
    the true motion, ≈ 1 for a wrong one); ``first_variation`` δS = dS/dε at 0 and
    ``second_variation`` d²S/dε² from ±ε at the smallest ε; ``constraint_violation`` the
    largest |f| on each varied path (O(ε²)). ε is relative to the system size: the variation
    is ε · size · η with max |η| = 1.
    """

    eps: np.ndarray
    delta_S: np.ndarray
    delta_S_minus: np.ndarray
    order: float
    ratio: float
    first_variation: float
    second_variation: float
    constraint_violation: np.ndarray
    action: float
    scale: float
    n_bumps: int
    seed: int
    #: the variation's direction η at each sample (T, N, 3), scaled so that max |η| = size
    variation: np.ndarray | None = None
    #: the smooth pieces (t0, t1) varied separately, each with η = dη/dt = 0 at its ends
    pieces: list = field(default_factory=list)

    @property
    def delta_S_over_eps(self) -> np.ndarray:
        return self.delta_S / self.eps

    @property
    def local_orders(self) -> np.ndarray:
        """Slopes of log|ΔS| against log ε between neighbouring ε (the last is the asymptotic one)."""
        d = np.log(np.abs(self.delta_S) + np.finfo(float).tiny)
        return np.diff(d) / np.diff(np.log(self.eps))

    @property
    def is_stationary(self) -> bool:
        """True when ΔS is second order in ε (measured slope above 1.5)."""
        return bool(self.order > 1.5)

    def table(self) -> str:
        lines = [f"{'eps':>10}  {'dS(+eps)':>13}  {'dS/eps':>13}  {'max|f|':>9}"]
        for e, d, c in zip(self.eps, self.delta_S, self.constraint_violation, strict=True):
            lines.append(f"{e:10.4g}  {d:13.6g}  {d / e:13.6g}  {c:9.2g}")
        verdict = "stationary" if self.is_stationary else "NOT stationary"
        lines.append(f"order {self.order:.3f}, ratio {self.ratio:.4g}, δS ≈ {self.first_variation:.4g}, "
                     f"δ²S ≈ {self.second_variation:.4g} ({verdict})")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"StationarityResult(order={self.order:.3f}, ratio={self.ratio:.4g}, "
                f"first_variation={self.first_variation:.4g})")


def independent_rows(model: Model, x, t) -> np.ndarray:
    if model.n_constraints == 0:
        return np.zeros(0, dtype=int)
    J = np.asarray(model.jacobian(x, t)[1])
    rank, order = jacobian_rank(J)
    return np.sort(order[:rank])


def _tangent_function(model: Model, rows: np.ndarray) -> ca.Function:
    """eta(x, v, t, c, c_dot) -> (P c, d/dt (P c)) with P = I − Jᵀ(J Jᵀ)⁻¹J on the rows given."""
    s = model.symbols
    x, v, t = s.x, s.v, s.t
    c, cd = ca.SX.sym("c", model.n_coordinates), ca.SX.sym("c_dot", model.n_coordinates)
    if len(rows):
        f = model.constraint(x, t)[[int(r) for r in rows]]
        J = ca.jacobian(f, x)
        A = ca.mtimes(J, J.T)

        def P(w):
            return w - ca.mtimes(J.T, ca.solve(A, ca.mtimes(J, w)))

        Pc = P(c)
        dPc = ca.jtimes(Pc, x, v) + (ca.jacobian(Pc, t) if ca.depends_on(Pc, t) else 0)
        eta, eta_dot = Pc, P(cd) + dPc
    else:
        eta, eta_dot = c, cd
    return ca.Function("eta", [x, v, t, c, cd], [eta, eta_dot])


def _pieces(model: Model, t: np.ndarray, X: np.ndarray, segments, where: str, t_end=None) -> list:
    """The smooth pieces of the path as (sample indices, t0, t1, rows that project η there, rows
    held there).

    Without one-sided constraints: one piece, the whole trajectory, with the independent rows
    at its first sample. With them: one piece per segment of the run (``segments`` as in
    ``Trajectory.info["segments"]``, checked by ``checked_segments``), projected with the
    independent ones of the rows held there: the two-sided rows and the one-sided rows the
    segment names; a segment of zero length or with fewer than 3 samples is not varied.
    """
    one = one_sided(model).rows
    if not one:
        rows = independent_rows(model, X[0], t[0])
        return [(np.arange(len(t)), float(t[0]), float(t[-1]), rows, rows)]
    if not segments:
        raise InputError(
            "the system has one-sided constraints, and the trajectory does not say where each one is "
            "held: pass the trajectory returned by constrained.simulate (its info['segments']) or "
            "segments=[{'t_start': .., 't_end': .., 'held': [labels]}, ...]")
    labels = list(model.constraint_labels)
    segments = checked_segments(segments, t, labels, where, "pass the segments of the run, as "
                                "constrained.simulate records them in trajectory.info['segments']", t_end)
    two = set(one_sided(model).bilateral)
    pieces = []
    for seg in segments:
        t0, t1 = seg["t_start"], seg["t_end"]
        idx = np.flatnonzero((t >= t0) & (t <= t1))
        if not t1 > t0 or len(idx) < 3:
            continue
        held = np.array(sorted(two | {labels.index(h) for h in seg["held"]}), dtype=int)
        rows = held
        if len(rows):
            J = np.asarray(model.jacobian(X[idx[0]], t[idx[0]])[1])[rows]
            rank, order = jacobian_rank(J)
            rows = np.sort(rows[order[:rank]])
        pieces.append((idx, t0, t1, rows, held))
    if not pieces:
        raise InputError("no segment of the run has 3 samples or more: nothing to vary")
    return pieces


def held_multipliers(model: Model, X: np.ndarray, V: np.ndarray, t: np.ndarray, pieces) -> np.ndarray:
    """λ (T, C) on each piece from the KKT system of the rows held there (M a = F + Jᵀλ,
    J a = −J̇ v over those rows, minimum-norm where they are dependent), 0 on the other rows and
    outside the pieces: the multipliers a hybrid run records, for a trajectory saved without them."""
    lam = np.zeros((len(t), model.n_constraints))
    for idx, _, _, _, held in pieces:
        if len(held):
            active = ActiveSet(model, held, at=(X[idx[0]], t[idx[0]]))
            for i in idx:
                lam[i] = active.multipliers(X[i], V[i], t[i])
    return lam


def stationarity(
    model_or_system,
    trajectory: Trajectory,
    *,
    eps_list: Sequence[float] = (1e-2, 5e-3, 2.5e-3, 1.25e-3),
    n_bumps: int = 3,
    seed: int = 0,
    segments: Sequence[dict] | None = None,
) -> StationarityResult:
    """Measure how the action changes under admissible variations of ``trajectory``.

    The variation is ``δx(t) = ε · size · η(t)``, ``η = P(x(t)) c(t)``: P projects onto the
    null space of J (a smooth choice of the null-space directions), ``c(t) = Σ_j sin²(π j s)
    c_j`` (s = (t − t0)/T, j = 1..n_bumps, c_j seeded normal vectors), normalized to
    max |η| = 1. It vanishes with its derivative at both ends and keeps ``f = 0`` to first
    order. ``δv = ε · size · dη/dt`` exactly (CasADi AD of P along the trajectory's velocity),
    so the varied path's velocity is the derivative of its positions.

    With one-sided constraints the path is smooth only between impacts, lift-offs and
    landings, and Hamilton's principle holds per smooth piece with its end times fixed. The
    check is then made per segment of the run (``segments``, default
    ``trajectory.info["segments"]`` from :func:`constrained.simulate`, kept by
    ``Trajectory.save`` and checked by ``Trajectory.load``): on each, c(t) uses
    s = (t − t_start)/(t_end − t_start), so η and dη/dt vanish at the segment's ends, and P
    projects with the rows active there only — the two-sided rows and the one-sided rows held
    on that segment. A ball in free flight is thus varied in every direction, not only along
    the floor. ΔS is the sum of the segments' ΔS (each by Simpson on its own samples, no
    quadrature across a kink); the multipliers of rows not held are taken as 0.

    The action of each path is taken with the augmented Lagrangian ``L + λ·f`` (λ the
    trajectory's multipliers; without them, the KKT system's, over the rows each segment holds
    where there are one-sided rows: ``held_multipliers``), integrated by Simpson on the samples:
    for the true motion the first variation vanishes and ΔS = O(ε²); for a wrong motion
    ΔS = O(ε). ``constraint_violation`` is the largest |f| of the projecting rows on the varied
    samples. Sample densely: the quadrature error and the integration tolerance of the
    trajectory set the floor below which ΔS/ε stops falling.
    """
    model = as_model(model_or_system)
    require_lagrangian(model, "the stationarity check")
    _check_trajectory(model, trajectory, 5)
    eps = np.asarray(list(eps_list), float).ravel()
    if eps.size < 2 or not np.all(np.isfinite(eps)) or np.any(eps <= 0):
        raise InputError(f"eps_list must hold at least two positive numbers, got {list(eps_list)!r}")
    if isinstance(n_bumps, bool) or not isinstance(n_bumps, int) or n_bumps < 1:
        raise InputError(f"n_bumps must be a positive integer, got {n_bumps!r}")
    eps = np.sort(eps)[::-1]
    t, X, V = flat_samples(trajectory)
    n, n3 = X.shape
    asked = trajectory.info.get("t_end")
    pieces = _pieces(model, t, X, trajectory.info.get("segments") if segments is None else segments,
                     "trajectory.info['segments']" if segments is None else "segments=",
                     asked if isinstance(asked, int | float) and not isinstance(asked, bool) else None)
    one = one_sided(model).rows
    lam = trajectory.multipliers
    if lam is None or np.asarray(lam).shape != (n, model.n_constraints):  # (a file saved without them)
        lam = held_multipliers(model, X, V, t, pieces) if one else multipliers_along(model, X, V, t)
    lam = np.array(lam, float).reshape(n, model.n_constraints)

    # the variation η(t) and its exact time derivative along the trajectory, piece by piece
    rng = np.random.default_rng(seed)
    coeffs = rng.standard_normal((n_bumps, n3))
    j = np.arange(1, n_bumps + 1)[:, None]
    eta, eta_dot = np.zeros((n, n3)), np.zeros((n, n3))
    for idx, t0, t1, rows, held in pieces:
        s = (t[idx] - t0) / (t1 - t0)
        b = np.sin(np.pi * j * s) ** 2                                  # (n_bumps, n_piece)
        bd = np.pi * j / (t1 - t0) * np.sin(2 * np.pi * j * s)          # d/dt sin²(π j s)
        c, cd = b.T @ coeffs, bd.T @ coeffs                             # (n_piece, 3N)
        e_, ed = model.evaluate(_tangent_function(model, rows), X[idx], V[idx], t[idx], c, cd)
        eta[idx], eta_dot[idx] = e_.T, ed.T
        if one:  # a one-sided row not held on this piece pushes with λ = 0
            free = [k for k in one if k not in set(held.tolist())]
            lam[np.ix_(idx, free)] = 0.0
    size = model.system.size()
    peak = float(np.max(np.linalg.norm(eta.reshape(n, -1, 3), axis=2)))
    if peak == 0.0:
        raise InputError("the system has no freedom to vary (J has full column rank)")
    eta, eta_dot = eta * (size / peak), eta_dot * (size / peak)

    Lf = lagrangian_function(model)
    s_ = model.symbols
    lam_sym = ca.SX.sym("lam", model.n_constraints)
    f = model.constraint(s_.x, s_.t)
    L_aug = Lf(s_.x, s_.v, s_.t) + (ca.dot(lam_sym, f) if model.n_constraints else 0)
    Laug = ca.Function("L_aug", [s_.x, s_.v, s_.t, lam_sym], [L_aug, f if model.n_constraints else ca.SX(0)])

    def L_of(Xp, Vp):
        Lv, fv = model.evaluate(Laug, Xp, Vp, t, lam)
        return np.asarray(Lv, float).ravel(), np.asarray(fv, float).reshape(-1, n)

    def delta(Lp, L0):
        return sum(_integral(Lp[idx] - L0[idx], t[idx]) for idx, *_ in pieces)

    def violation(fv):
        if not one:  # every row, every sample
            return float(np.max(np.abs(fv), initial=0.0))
        return max(float(np.max(np.abs(fv[np.ix_(rows, idx)]), initial=0.0)) for idx, _, _, rows, _ in pieces)

    L0, _ = L_of(X, V)
    S0 = _integral(L0, t)
    dplus, dminus, viol = [], [], []
    for e in eps:
        Lp, fp = L_of(X + e * eta, V + e * eta_dot)
        Lm, _ = L_of(X - e * eta, V - e * eta_dot)
        dplus.append(delta(Lp, L0))
        dminus.append(delta(Lm, L0))
        viol.append(violation(fp))
    dplus, dminus = np.array(dplus), np.array(dminus)
    tiny = np.finfo(float).tiny
    order = float(np.polyfit(np.log(eps), np.log(np.abs(dplus) + tiny), 1)[0])
    ratio = float((abs(dplus[-1]) / eps[-1]) / max(abs(dplus[0]) / eps[0], tiny))
    e = eps[-1]
    return StationarityResult(
        eps=eps, delta_S=dplus, delta_S_minus=dminus, order=order, ratio=ratio,
        first_variation=float((dplus[-1] - dminus[-1]) / (2 * e)),
        second_variation=float((dplus[-1] + dminus[-1]) / e**2),
        constraint_violation=np.array(viol), action=S0, scale=size, n_bumps=n_bumps, seed=seed,
        variation=eta.reshape(n, -1, 3), pieces=[(t0, t1) for _, t0, t1, _, _ in pieces],
    )


def save_action_figure(result: ActionResult, path) -> Path:
    """L(t) and S(t) against time, one PNG (matplotlib's Agg canvas, written atomically)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 5))
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(result.t, result.lagrangian)
    ax1.set_ylabel("L = T − V − U  [J]")
    ax2.plot(result.t, result.cumulative)
    ax2.set_ylabel("S(t) = ∫ L dt  [J·s]")
    ax2.set_xlabel("t [s]")
    ax1.set_title(f"action along the run: S = {result.total:.6g} J·s")
    fig.tight_layout()
    return save_figure(fig, path)


def save_figure(fig, path) -> Path:
    path = Path(path)
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110))
    return path


# --- the path verb's figure and end configuration --------------------------------------------


def save_path_figure(result, path) -> Path:
    """The path (the two coordinates with the largest spread) and the action per iteration."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    tr = result.trajectory
    fig = Figure(figsize=(10, 4.5))
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(1, 2)
    spread = np.ptp(tr.x.reshape(-1, 3), axis=0)
    i, j = sorted(np.argsort(spread)[-2:])
    names = tr.particle_names or [f"p{k}" for k in range(tr.n_particles)]
    for k, name in enumerate(names):
        line, = ax1.plot(tr.x[:, k, i], tr.x[:, k, j], label=name)
        ax1.plot(tr.x[0, k, i], tr.x[0, k, j], "o", color=line.get_color())
        ax1.plot(tr.x[-1, k, i], tr.x[-1, k, j], "s", color=line.get_color())
    ax1.set_xlabel(f"{'xyz'[i]} [m]")
    ax1.set_ylabel(f"{'xyz'[j]} [m]")
    ax1.set_aspect("equal", adjustable="datalim")
    ax1.legend(loc="best", fontsize="small")
    kind = "minimum" if result.is_minimum else "saddle"
    ax1.set_title(f"stationary path ({kind}), o start, □ end")
    if result.history:
        ax2.plot(np.arange(len(result.history)), result.history, "o-")
    ax2.set_xlabel("IPOPT iteration")
    ax2.set_ylabel("discrete action S_d [J·s]")
    ax2.set_title(f"S = {result.action:.8g} J·s ({'converged' if result.converged else 'not converged'})")
    fig.tight_layout()
    return save_figure(fig, path)


def end_configuration(text: str, system) -> np.ndarray:
    """Positions (N, 3) from ``--to``: a trajectory ``.npz`` (its last positions) or inline
    ``"p1=[0,-1,0]; p2=[0,-2,0]"`` naming every particle."""
    text = str(text).strip()
    names = system.names
    if text.lower().endswith(".npz"):
        traj = Trajectory.load(text)
        x = np.asarray(traj.x[-1], float)
        if x.shape != (system.n_particles, 3):
            raise InputError(f"--to {text}: the trajectory has {x.shape[0]} particles, the scene "
                             f"{system.n_particles}")
        return x
    if "=" not in text:
        raise InputError(f"--to must be a trajectory .npz or positions like 'p1=[0,-1,0]; p2=[0,-2,0]', "
                         f"got {text!r}")
    x = np.full((system.n_particles, 3), np.nan)
    for part in filter(None, (p.strip() for p in text.split(";"))):
        name, _, value = part.partition("=")
        name = name.strip()
        if name not in names:
            raise InputError(f"--to names unknown particle {name!r} (particles: {listed(names)})")
        try:
            vec = tomlparse.loads(f"v = {value.strip()}")["v"]
            vec = np.asarray(vec, float)
        except (tomlparse.TOMLDecodeError, TypeError, ValueError, RecursionError):
            vec = None
        if vec is None or vec.shape != (3,) or not np.all(np.isfinite(vec)):
            raise InputError(f"--to: the position of {name!r} must be 3 numbers like [0, -1, 0], "
                             f"got {value.strip()!r}")
        x[names.index(name)] = vec
    missing = [n for n, row in zip(names, x, strict=True) if np.isnan(row).any()]
    if missing:
        raise InputError(f"--to gives no end position for {', '.join(missing)} (name every particle)")
    return x
