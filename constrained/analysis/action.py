"""The principle of least action on the Cartesian route.

Three tools (docs/least-action.md walks through them):

- :func:`action` — the cumulative action ``S(t) = ∫ L dt`` along a Trajectory, with
  ``L = T − V − U`` in particle coordinates (the effects' ``potential`` and
  ``generalized_potential`` slots; damping and applied forces have no Lagrangian and are
  listed in ``ActionResult.excluded``).
- :func:`stationarity` — the action of the trajectory against the action of admissible
  variations ``x + ε η``, ``η(t) = P(x(t)) c(t)`` (P the projector onto the null space of J,
  c(t) a sum of ``sin²`` bumps vanishing at both ends): ``ΔS = O(ε²)`` for the true motion,
  ``O(ε)`` for a wrong one. The varied paths leave ``f = 0`` at O(ε²); the action is taken
  with the augmented Lagrangian ``L + λ·f`` (λ the trajectory's multipliers), whose
  first-order stationarity holds for *all* variations and whose second variation is the
  constrained one (the Hessian of the Lagrangian on the tangent space).
- :func:`stationary_path` — the two-point boundary-value problem by making the discrete
  action ``S_d = Σ L_d(x_k, x_{k+1})`` stationary with IPOPT, the constraints imposed at
  every node; reports whether the stationary point is a minimum (second variation on the
  tangent space positive) or a saddle (beyond a conjugate point).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from .. import interrupt
from ..errors import InputError, RunInterrupted, SimulationError
from ..manifold.dense import schur_solve, tangent_basis
from ..manifold.manifold import Manifold
from ..model.structure import Model
from ..run.action_integral import (
    ActionResult,
    StationarityResult,
    action,
    as_model,
    end_configuration,
    flat_samples,
    independent_rows,
    lagrangian_function,
    require_lagrangian,
    save_action_figure,
    save_path_figure,
    stationarity,
)
from ..run.quantities import OUTPUT_NAMES, trajectory_from
from ..run.trajectory import Trajectory

__all__ = [
    "ActionResult",
    "PathResult",
    "end_configuration",
    "StationarityResult",
    "action",
    "lagrangian_function",
    "save_action_figure",
    "save_path_figure",
    "stationarity",
    "stationary_path",
]

QUADRATURES = ("midpoint", "trapezoid")
#: |conjugate_margin| below which a path is reported as next to a conjugate point.
NEAR_CONJUGATE = 1e-2
PATH_METHODS = ("stationary", "minimize")

_NLPSOL_KEYS = ("print_time", "error_on_fail", "iteration_callback")


# --- boundary-value paths --------------------------------------------------------------------


@dataclass
class PathResult:
    """A stationary path of the discrete action between two configurations.

    ``trajectory``: nodes t_k, positions, velocities (discrete Legendre transform, projected
    onto J v + f_t = 0), multipliers and constraint forces (KKT at the nodes), energy.
    ``action``: the discrete action S_d at the solution; ``history``: S_d at each IPOPT
    iterate; ``second_variation``: the smallest eigenvalue of the Hessian of the Lagrangian of
    the NLP on the tangent space of the constraints, divided by h (so that it approximates
    min δ²S / ∫|η|² dt, in N/m); ``is_minimum``: second variation > 0 (a saddle after a
    conjugate point otherwise); ``conjugate_margin``: the second variation over the kinetic
    term's alone (1 − (ωT/π)² for an oscillator; 0 at a conjugate point, where the path is
    refused when |margin| < min((π/K)², 0.01), and flagged by ``near_conjugate`` below 0.01).
    """

    trajectory: Trajectory
    action: float
    converged: bool
    iterations: int
    return_status: str
    second_variation: float
    is_minimum: bool
    history: list[float]
    nodes: int
    quadrature: str
    method: str
    wall_time_s: float = 0.0
    info: dict = field(default_factory=dict)
    conjugate_margin: float = math.nan

    @property
    def near_conjugate(self) -> bool:
        """The second variation is within 1 % of the kinetic term's (|conjugate_margin| < 0.01):
        T is next to a conjugate point, the path is ill-conditioned (small changes of the ends
        or of K move it a lot)."""
        return bool(abs(self.conjugate_margin) < NEAR_CONJUGATE)

    @property
    def t(self) -> np.ndarray:
        return self.trajectory.t

    @property
    def x(self) -> np.ndarray:
        return self.trajectory.x

    @property
    def v(self) -> np.ndarray:
        return self.trajectory.v

    def summary(self) -> str:
        kind = "minimum" if self.is_minimum else "SADDLE (not a minimum: beyond a conjugate point)"
        return "\n".join([
            f"stationary path: {self.nodes} intervals, {self.quadrature} rule, method {self.method}",
            f"IPOPT: {'converged' if self.converged else 'NOT converged'} ({self.return_status}) "
            f"after {self.iterations} iterations, {self.wall_time_s:.3g} s",
            f"action S = {self.action:.12g} J·s",
            f"second variation {self.second_variation:.6g} N/m: {kind}",
        ] + ([f"WARNING: next to a conjugate point (second variation {self.conjugate_margin:.2g} of the "
              "kinetic term's): the path is ill-conditioned, small changes of T or of the ends move it a lot"]
             if self.near_conjugate else []))

    def __repr__(self) -> str:
        return (f"PathResult(S={self.action:.10g}, converged={self.converged}, "
                f"is_minimum={self.is_minimum}, {self.nodes} intervals)")


class _IterationLog(ca.Callback):
    """IPOPT iteration callback: records x at every iterate; stops the search on Ctrl-C."""

    def __init__(self, nx: int, ng: int, npar: int):
        ca.Callback.__init__(self)
        self.nx, self.ng, self.npar = nx, ng, npar
        self.iterates: list[np.ndarray] = []
        self.construct("iteration_log", {})

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "ret"

    def get_sparsity_in(self, i):
        name = ca.nlpsol_out(i)
        if name == "f":
            return ca.Sparsity.scalar()
        if name in ("x", "lam_x"):
            return ca.Sparsity.dense(self.nx)
        if name in ("g", "lam_g"):
            return ca.Sparsity.dense(self.ng)
        return ca.Sparsity(0, 0)

    def _record(self, arg):
        self.iterates.append(np.array(arg[0]).ravel().copy())
        return [1 if interrupt.requested() else 0]  # Ctrl-C: IPOPT stops (User_Requested_Stop)

    eval = _record  # the name CasADi calls (not Python's eval)


def _configuration(value, model: Model, what: str) -> np.ndarray:
    try:
        x = np.asarray(value, float)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be an array of positions (N, 3), got {value!r}") from None
    if x.size != model.n_coordinates:
        raise InputError(f"{what} must hold {model.n_particles} positions (N, 3), got shape {x.shape}")
    x = x.ravel()
    if not np.all(np.isfinite(x)):
        raise InputError(f"{what} has non-finite entries")
    return x


def _refuse_one_sided(model: Model) -> None:
    """One-sided rows (g = side · f ≥ 0) are inequalities; the discrete Euler–Lagrange system
    here imposes equalities only, so a path along, off or bouncing on them is not computed."""
    one = [c.label for c in model.system.constraints if getattr(c, "unilateral", False)]
    if one:
        raise InputError(
            f"stationary paths are computed with two-sided constraints only; "
            f"{', '.join(repr(c) for c in one)} {'is' if len(one) == 1 else 'are'} one-sided "
            "(unilateral): the particle may leave or hit it, and a path with impacts or lift-off is "
            "not a solution of the discrete Euler–Lagrange equations with equality constraints. "
            "Remove 'unilateral' if the path stays in contact, or remove the constraint if the path "
            "never touches it")


def _on_constraints(model: Model, x, t, what: str, tolerance: float) -> np.ndarray:
    """x, projected onto f(x, t) = 0 when it is within ``tolerance``; refused otherwise."""
    if model.n_constraints == 0:
        return x
    f = np.asarray(model.constraint(x, t)).ravel()
    k = int(np.argmax(np.abs(f)))
    if not np.isfinite(f[k]) or abs(f[k]) > tolerance:
        raise InputError(
            f"the {what} configuration violates constraint '{model.constraint_labels[k]}' by "
            f"{abs(f[k]):.3g} at t = {t:g} s (allowed {tolerance:.3g}); give positions that satisfy "
            "the constraints"
        )
    tol = 1e-14 * max(1.0, float(np.max(np.abs(x))))
    return Manifold.at(model, x, t).project_positions(x, t, tol=tol, max_iter=20).x


def _guess(model: Model, guess, xs, xe, tn, rows) -> np.ndarray:
    """Initial path (K+1, 3N): the given one, or the straight line, projected onto f = 0."""
    K1 = len(tn)
    if guess is None:
        s = (tn - tn[0]) / (tn[-1] - tn[0])
        W = xs[None, :] + s[:, None] * (xe - xs)[None, :]
    elif isinstance(guess, Trajectory):
        g_t, g_x, _ = flat_samples(guess)
        W = np.column_stack([np.interp(tn, g_t, g_x[:, i]) for i in range(g_x.shape[1])])
    else:
        try:
            W = np.asarray(guess, float)
        except (TypeError, ValueError):
            raise InputError(f"guess must be a Trajectory or an array of positions ({K1}, "
                             f"{model.n_particles}, 3), got {type(guess).__name__}") from None
        if W.size != K1 * model.n_coordinates:
            raise InputError(f"guess must hold positions at the {K1} nodes: shape ({K1}, "
                             f"{model.n_particles}, 3) for nodes = {K1 - 1}, got shape {W.shape}")
        W = W.reshape(K1, -1)
    W = np.array(W, float)
    if W.shape[1] != model.n_coordinates:
        raise InputError(f"the guess has {W.shape[1] // 3} particles, the system {model.n_particles}")
    if not np.all(np.isfinite(W)):
        bad = int(np.argmax(~np.isfinite(W).all(axis=1)))
        raise InputError(f"guess has non-finite positions (first at node {bad}, t = {tn[bad]:g} s)")
    if model.n_constraints:
        manifold = Manifold.at(model, W[0], tn[0])
        for k in range(1, K1 - 1):
            W[k] = manifold.project_positions(W[k], tn[k], tol=1e-12, max_iter=30).x
    return W


def stationary_path(
    system,
    x_start,
    x_end,
    T: float,
    *,
    nodes: int = 100,
    quadrature: str = "midpoint",
    t0: float = 0.0,
    method: str = "stationary",
    guess=None,
    tol: float = 1e-10,
    max_iter: int = 200,
    end_tolerance: float = 1e-6,
    ipopt_options: dict | None = None,
    model: Model | None = None,
) -> PathResult:
    """The motion from ``x_start`` at ``t0`` to ``x_end`` at ``t0 + T`` by the action principle.

    Positions x_k at t_k = t0 + k h (h = T / nodes, k = 0..nodes), fixed at both ends;
    discrete Lagrangian ``L_d = h L((x_k + x_{k+1})/2, (x_{k+1} − x_k)/h, t_k + h/2)``
    (``midpoint``) or ``h/2 [L(x_k, v_k, t_k) + L(x_{k+1}, v_k, t_{k+1})]`` (``trapezoid``);
    the constraints ``f(x_k, t_k) = 0`` at every node.

    ``method="stationary"`` (default) solves the discrete Euler–Lagrange equations
    ``∇_k S_d + J_kᵀ μ_k = 0, f(x_k, t_k) = 0`` with IPOPT (a square system: it converges to
    the stationary point near the start path, a minimum or a saddle); ``"minimize"`` lets
    IPOPT minimize S_d subject to the constraints (it finds minima only: beyond a conjugate
    point it leaves the saddle for another path). The start path is ``guess`` (a Trajectory
    or an array (nodes + 1, N, 3)) or the straight line, projected onto the constraints.

    Ends within ``end_tolerance`` × system size of the constraints are projected onto them;
    farther ones are refused (InputError naming the constraint). When IPOPT does not
    converge a SimulationError is raised with the last iterate as ``trajectory`` (and the
    PathResult as ``path``). ``ipopt_options`` are passed on (``{"print_level": 5}`` to watch).
    """
    started = time.perf_counter()
    for key, value in (("T", T), ("t0", t0)):
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise InputError(f"{key} must be a finite number of seconds, got {value!r}")
    if T <= 0:
        raise InputError(f"the time T between the two configurations must be > 0 s, got {T:g} s")
    if isinstance(nodes, bool) or not isinstance(nodes, int) or nodes < 2:
        raise InputError(f"nodes (the number of time intervals) must be an integer >= 2, got {nodes!r}")
    if quadrature not in QUADRATURES:
        raise InputError(f"unknown quadrature {quadrature!r} (choose from {', '.join(QUADRATURES)})")
    if method not in PATH_METHODS:
        raise InputError(f"unknown method {method!r} (choose from {', '.join(PATH_METHODS)})")
    if not (isinstance(max_iter, int) and max_iter >= 1):
        raise InputError(f"max_iter must be a positive integer, got {max_iter!r}")
    model = model or as_model(system)
    system = model.system
    require_lagrangian(model, "the action principle")
    _refuse_one_sided(model)
    size = system.size()
    t0, T = float(t0), float(T)
    K, h = nodes, T / nodes
    if not 1e-150 < h < 1e150:  # S_d holds m/h and its Hessian m/h²: both must be finite doubles
        raise InputError(f"T = {T:g} s over {K} intervals gives a time step h = {h:.3g} s whose square is "
                         "not a finite double (m/h² overflows or h² underflows); give T in seconds "
                         "between about 1e-140 and 1e140")
    tn = t0 + h * np.arange(K + 1)
    tn[-1] = t0 + T
    xs = _on_constraints(model, _configuration(x_start, model, "start"), t0, "start", end_tolerance * size)
    xe = _on_constraints(model, _configuration(x_end, model, "end"), t0 + T, "end", end_tolerance * size)
    rows = independent_rows(model, xs, t0)
    n3, C = model.n_coordinates, len(rows)

    # the discrete action, symbolic in the interior nodes W (n3, K-1), ends as parameters
    Lf = lagrangian_function(model)
    a, b, tk = ca.SX.sym("a", n3), ca.SX.sym("b", n3), ca.SX.sym("tk")
    vk = (b - a) / h
    if quadrature == "midpoint":
        Ld = h * Lf(0.5 * (a + b), vk, tk + 0.5 * h)
    else:
        Ld = 0.5 * h * (Lf(a, vk, tk) + Lf(b, vk, tk + h))
    Ld_fun = ca.Function("L_d", [a, b, tk], [Ld])
    W = ca.SX.sym("W", n3, K - 1)
    P = ca.SX.sym("p", 2 * n3)
    Xall = ca.horzcat(P[:n3], W, P[n3:])
    S_d = ca.sum2(Ld_fun.map(K)(Xall[:, :-1], Xall[:, 1:], ca.DM(tn[:-1]).T))
    w = ca.vec(W)
    if C:
        xq, tq = ca.SX.sym("xq", n3), ca.SX.sym("tq")
        f_sel = ca.Function("f_sel", [xq, tq], [model.constraint(xq, tq)[[int(r) for r in rows]]])
        G = ca.vec(f_sel.map(K - 1)(W, ca.DM(tn[1:-1]).T))
    else:
        G = ca.SX(0, 1)
    mu = ca.SX.sym("mu", C * (K - 1))
    lagr = S_d + (ca.dot(mu, G) if C else 0)
    p_val = np.concatenate([xs, xe])

    W0 = _guess(model, guess, xs, xe, tn, rows)
    w0 = W0[1:-1].ravel()  # node-major = column-major vec of (n3, K-1)
    S_fun = ca.Function("S_d", [w, P], [S_d])
    if method == "stationary":
        grad = ca.gradient(lagr, w)
        z = ca.vertcat(w, mu)
        nlp = {"x": z, "p": P, "f": ca.SX(0), "g": ca.vertcat(grad, G)}
        mu0 = _least_squares_multipliers(model, rows, S_d, w, P, G, w0, p_val, K, C)
        z0 = np.concatenate([w0, mu0])
    else:
        nlp = {"x": w, "p": P, "f": S_d, "g": G}
        z0 = w0
    nz = int(nlp["x"].numel())
    ng = int(nlp["g"].numel())
    log = _IterationLog(nz, ng, 2 * n3)
    opts = {
        "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
        "ipopt.tol": tol, "ipopt.max_iter": max_iter, "iteration_callback": log,
        "ipopt.constr_viol_tol": tol, "error_on_fail": False,
    }
    opts.update({k if "." in k or k in _NLPSOL_KEYS else f"ipopt.{k}": v
                 for k, v in (ipopt_options or {}).items()})
    solver = ca.nlpsol("stationary_path", "ipopt", nlp, opts)
    with interrupt.watch():
        sol = solver(x0=z0, p=p_val, lbg=0, ubg=0)
        stopped = interrupt.requested()
    stats = solver.stats()
    z = np.array(sol["x"]).ravel()
    w_sol = z[: n3 * (K - 1)]
    if method == "stationary":
        mu_sol = z[n3 * (K - 1):]
    else:
        mu_sol = np.array(sol["lam_g"]).ravel()
    history = [float(S_fun(it[: n3 * (K - 1)], p_val)) for it in log.iterates]
    S_val = float(S_fun(w_sol, p_val))
    X = np.vstack([xs, w_sol.reshape(K - 1, n3), xe])
    second, kinetic = (math.nan, math.nan) if stopped else _second_variation(
        lagr, w, mu, P, w_sol, mu_sol, p_val, model, rows, tn, X, K, h)
    # second variation relative to the kinetic term's: 1 − (ωT/π)² for an oscillator, 0 at a conjugate point
    margin = second / kinetic if math.isfinite(kinetic) and kinetic > 0 else math.nan
    resolution = min((math.pi / K) ** 2, NEAR_CONJUGATE)  # the discrete lowest mode: relative error (π/K)²/12
    V = _legendre_velocities(model, Ld_fun, X, tn)
    converged = bool(stats.get("success", False))
    status = str(stats.get("return_status", "unknown"))
    iterations = int(stats.get("iter_count", len(history)))
    wall = time.perf_counter() - started
    traj = trajectory_from(model, tn, X, V, OUTPUT_NAMES,
                           {"iterations": iterations, "wall_time_s": wall, "method": "path"})
    traj.action = action(model, traj).cumulative
    scale = _hessian_scale(model, h)
    traj.info.update({
        "kind": "stationary path", "system": system.name, "quadrature": quadrature, "nodes": K,
        "action": S_val, "converged": converged, "ipopt_status": status,
        "second_variation": second, "method": method, "conjugate_margin": margin,
    })
    result = PathResult(
        trajectory=traj, action=S_val, converged=converged, iterations=iterations,
        return_status=status, second_variation=second,
        is_minimum=bool(second > 1e-9 * scale), history=history, nodes=K, quadrature=quadrature,
        method=method, wall_time_s=wall,
        info={"end_points_projected": True, "independent_rows": rows.tolist()},
        conjugate_margin=margin,
    )
    conjugate = (f"the second variation is {second:.3g} N/m, {margin:.2g} of the lowest free mode's "
                 f"{kinetic:.3g} N/m: T = {T:g} s is at or next to a conjugate point of the path, where the "
                 "Euler–Lagrange boundary-value problem is singular (a family of paths, or none)")
    if not converged:
        hint = (f"; {conjugate} — try a T further from it" if abs(margin) < NEAR_CONJUGATE else
                " (try more nodes, a shorter time T, or a start path closer to the motion via guess=; "
                "or T may be near a conjugate point, π√(l/g) for a pendulum's small swings)")
        exc = RunInterrupted(f"the search was interrupted (Ctrl-C) after {iterations} iterations; the last "
                             "iterate is kept", trajectory=traj) if stopped else SimulationError(
            f"IPOPT did not find a stationary path ({status}) after {iterations} iterations; "
            f"the last iterate is kept{hint}",
            trajectory=traj,
        )
        exc.path = result
        raise exc
    steps = np.linalg.norm(np.diff(X, axis=0), axis=1)
    if K >= 8 and steps.sum() > 1e-9 * size and steps.max() > 0.25 * steps.sum():
        k = int(np.argmax(steps))
        exc = SimulationError(
            f"the stationary path IPOPT found is not resolved: the step from t = {tn[k]:g} s to "
            f"{tn[k + 1]:g} s carries {steps[k] / steps.sum():.0%} of the path length ({steps[k]:.3g} m). It "
            "is a stationary point of the discrete action, not a motion (often from a start path through a "
            "singular configuration, e.g. the straight line between opposite points of a circle through its "
            "centre); give a start path with guess=, or more nodes (the path is kept)", trajectory=traj)
        exc.path = result
        raise exc
    if abs(margin) < resolution:
        exc = SimulationError(
            f"no well-defined stationary path: {conjugate}. Within the discretization's resolution "
            f"(π/K)² = {resolution:.2g} the discrete system is singular, so the path IPOPT returned "
            f"(S_d = {S_val:.6g} J·s) is not determined by the two ends; change T, or the end "
            "configuration, away from the conjugate point (the path is kept)", trajectory=traj)
        exc.path = result
        raise exc
    return result


def _hessian_scale(model: Model, h: float) -> float:
    return float(np.max(model.masses)) / h**2


def _least_squares_multipliers(model, rows, S_d, w, P, G, w0, p_val, K, C) -> np.ndarray:
    """μ at the start path: per node, the least-squares solution of ∇_k S_d + J_kᵀ μ_k = 0."""
    if not C:
        return np.zeros(0)
    g = np.array(ca.Function("g", [w, P], [ca.gradient(S_d, w)])(w0, p_val)).ravel()
    Jg = _to_scipy(ca.Function("Jg", [w], [ca.jacobian(G, w)])(w0)).tocsr()
    n3 = model.n_coordinates
    mu = np.zeros(C * (K - 1))
    for k in range(K - 1):
        Jk = Jg[k * C:(k + 1) * C, k * n3:(k + 1) * n3].toarray()
        # least squares of Jₖᵀ μ = −g: (Jₖ Jₖᵀ) μ = −Jₖ g, the Schur solve with unit weights
        mu[k * C:(k + 1) * C] = -schur_solve(Jk, np.ones(n3), Jk @ g[k * n3:(k + 1) * n3])
    return mu


def _to_scipy(M: ca.DM) -> sp.csc_matrix:
    sparsity = M.sparsity()
    return sp.csc_matrix((np.array(M.nonzeros()), sparsity.row(), sparsity.colind()), shape=M.shape)


def _second_variation(lagr, w, mu, P, w_sol, mu_sol, p_val, model, rows, tn, X, K, h) -> tuple[float, float]:
    """λ_min of Zᵀ ∇²_ww(S_d + μ·G) Z over h, Z a block-diagonal null-space basis of the J_k;
    and     the lowest mode of a free particle of the smallest tangent mass m_t (min over nodes of
    λ_min(Z_kᵀ M Z_k)), m_t (2/h)² sin²(π/2K) → m_t π²/T² (the reference for conjugate points)."""
    H = ca.Function("H", [w, mu, P], [ca.hessian(lagr, w)[0]])(w_sol, mu_sol, p_val)
    H = _to_scipy(H)
    n3 = model.n_coordinates
    blocks = []
    for k in range(1, K):
        if len(rows):
            Jk = np.asarray(model.jacobian(X[k], tn[k])[1])[rows]
            blocks.append(tangent_basis(Jk, n3))
        else:
            blocks.append(np.eye(n3))
    d = blocks[0].shape[1]
    if d == 0:
        return math.inf, math.inf
    Z = sp.block_diag(blocks, format="csc")
    masses = np.asarray(model.masses, float)
    m_tangent = min(float(np.linalg.eigvalsh(B.T @ (masses[:, None] * B))[0]) for B in blocks)
    free = m_tangent * (2 / h * math.sin(math.pi / (2 * K))) ** 2  # discrete m π²/T²
    return _lowest(Z.T @ H @ Z, d) / h, free


def _lowest(Hr, d: int) -> float:
    """The smallest eigenvalue of a block-tridiagonal (d × d blocks) symmetric matrix, from band
    storage."""
    n = Hr.shape[0]
    bw = min(2 * d - 1, n - 1)
    band = np.zeros((bw + 1, n))
    Hd = sp.csr_matrix(Hr)
    for off in range(bw + 1):
        band[off, : n - off] = Hd.diagonal(-off)
    return float(sla.eig_banded(band, lower=True, select="i", select_range=(0, 0), eigvals_only=True)[0])


def _legendre_velocities(model: Model, Ld_fun: ca.Function, X: np.ndarray, tn: np.ndarray) -> np.ndarray:
    """v_k from the discrete momenta p_k = −D1 L_d(x_k, x_{k+1}) (p_K = D2 L_d(x_{K−1}, x_K)),
    v = M⁻¹(p − ∂L/∂v(x, 0, t)), projected (mass-weighted) onto J v + f_t = 0."""
    n3 = model.n_coordinates
    a, b, tk = ca.SX.sym("a", n3), ca.SX.sym("b", n3), ca.SX.sym("tk")
    Ld = Ld_fun(a, b, tk)
    D = ca.Function("D", [a, b, tk], [ca.gradient(Ld, a), ca.gradient(Ld, b)])
    K = len(tn) - 1
    D1, D2 = D.map(K)(X[:-1].T, X[1:].T, tn[:-1][None, :])
    D1, D2 = np.array(D1).T, np.array(D2).T
    p = np.vstack([-D1, D2[-1:]])
    Lf = lagrangian_function(model)
    s = model.symbols
    dLdv0 = ca.Function("dLdv0", [s.x, s.t], [ca.substitute(ca.gradient(Lf(s.x, s.v, s.t), s.v), s.v,
                                                            ca.SX.zeros(n3))])
    W = np.asarray(model.evaluate(dLdv0, X, tn)[0]).T
    V = model.inverse_masses * (p - W)
    manifold = Manifold.at(model, X[0], tn[0])
    return np.array([manifold.project_velocities(X[k], V[k], tn[k]) for k in range(K + 1)])
