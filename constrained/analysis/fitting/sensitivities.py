"""Exact sensitivities of a run: ∂(observables at the output times)/∂(parameters, initial state).

Discretize, then differentiate: the run is dopri's (constrained.solvers.dopri, compiled step
loop, error control), and its accepted steps ``t_0 < t_1 < … `` are replayed as one CasADi
graph — the same Runge–Kutta stages, the same mass-weighted Newton and velocity projection,
the accelerations from the KKT system — with the step sizes frozen:

    s_{j+1} = Φ(s_j; t_j, t_{j+1}, p),   s = [x; v; a; p],   s_0 = start(x0(p) + δx0, v0(p) + δv0),
    y(t_k) = g(x, v, a, t_k, p)          (constrained.fitting.observables),

chained with ``mapaccum`` (the steps between two output times, padded with skipped steps to
a power of two, then the output intervals), so CasADi's forward or adjoint AD gives the
derivative of exactly the numbers the run produced. ``start`` is the start's formulas of the
parameters (positions written as ``l*sin(th0)``) followed by three Newton projections onto
the constraints: a derivative with respect to the initial state is the derivative of the
projected start, tangent to the manifold. No finite differences anywhere.

The frozen step sizes leave out how the error control would move the steps for other
parameters: the difference is the derivative of the local error, of the order of the
tolerance (tests: 1e-6 against a high-order finite difference at rtol 1e-10).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ... import interrupt
from ...errors import InputError, LinearRangeWarning, RunInterrupted, SimulationError
from ...manifold.graph import projection_graph
from ...manifold.manifold import acceleration_function
from ...model import expressions
from ...model.cache import ParametricView, structure_cache
from ...model.parameters import symbolic as symbolic_parameters
from ...model.structure import Model, assemble
from ...run.ensemble import _projector
from ...run.start import consistent_start
from ...run.unilateral import has_one_sided
from ...solvers.base import Status
from ...solvers.dopri import SYMBOLIC_MAX_CONSTRAINTS, Dopri
from ...solvers.tableaus import TABLEAUS
from .observables import observables, position_names

__all__ = ["Sensitivities", "StepSequence", "sensitivities", "step_sequence"]

#: Steps (accepted and rejected) one sensitivity run may take.
MAX_STEPS = 1_000_000
MODES = ("auto", "forward", "adjoint")


@dataclass(frozen=True)
class StepSequence:
    """The accepted steps of a dopri run, output interval by output interval: ``intervals[k]``
    the step ends in (t_out[k−1], t_out[k]] (the last one is t_out[k]); ``start`` its
    consistent start (constrained.start), ``rejected`` the steps refused."""

    t0: float
    t_out: np.ndarray
    intervals: list[np.ndarray]
    start: object
    rejected: int

    @property
    def steps(self) -> int:
        return int(sum(len(i) for i in self.intervals))

    def table(self, width: int) -> np.ndarray:
        """(2, width · K): [t_start; t_end] of each step, each interval padded to ``width``
        steps with skipped ones (t_start = t_end)."""
        out = np.empty((2, width * len(self.intervals)))
        t = self.t0
        for k, ends in enumerate(self.intervals):
            cols = slice(k * width, (k + 1) * width)
            starts = np.concatenate([[t], ends[:-1]]) if len(ends) else np.zeros(0)
            t = float(ends[-1]) if len(ends) else t
            block = np.full((2, width), t)
            block[0, :len(ends)], block[1, :len(ends)] = starts, ends
            out[:, cols] = block
        return out


def _times(t_eval, t0: float) -> np.ndarray:
    try:
        t = np.asarray(t_eval, float).ravel()
    except (TypeError, ValueError):
        raise InputError(f"the output times must be numbers, got {t_eval!r}", where="t_eval") from None
    if t.size == 0 or not np.all(np.isfinite(t)):
        raise InputError("the output times must be a non-empty list of finite times", where="t_eval")
    if np.any(np.diff(t) <= 0):
        raise InputError("the output times must be strictly increasing", where="t_eval")
    if t[0] < t0:
        raise InputError(f"the first output time {t[0]:g} s is before the start t = {t0:g} s", where="t_eval")
    return t


def step_sequence(model: Model, system, t_eval, t0: float = 0.0, *, rtol: float = 1e-10, atol: float = 1e-12,
                  base: str = "DOP853", max_steps: int = MAX_STEPS, compiled="auto",
                  max_initial_correction: float = 1e-3) -> StepSequence:
    """Run dopri from the system's (consistent) start to the last output time, landing on each
    output time, and keep the ends of the accepted steps (SimulationError when it stops)."""
    if has_one_sided(model):
        raise InputError("sensitivities through releases, contacts and impacts of one-sided constraints "
                         "are not supported (the step sequence is not smooth there); for a run where the "
                         "constraint holds throughout, make it two-sided (unilateral = false)",
                         where="constraints")
    if any(getattr(e, "terminal", False) for e in getattr(system, "events", ())):
        raise InputError("the system has terminal events: sensitivities run to the last output time "
                         "without them; remove the [[events]] or make them non-terminal", where="events")
    t_out = _times(t_eval, t0)
    start = consistent_start(model, system.positions, system.velocities, t0,
                             max_correction=max_initial_correction, size=system.size())
    stepper = Dopri(start.manifold, rtol=rtol, atol=atol, base=base, compiled=compiled)
    stepper.prepare(t0, float(t_out[-1]), t_out)
    state = stepper.init(start.x, start.v, t0, float(t_out[-1]))
    intervals, t = [], t0
    with interrupt.watch():
        for tk in t_out:
            ends: list[float] = []
            while t < tk:
                if interrupt.requested():
                    raise RunInterrupted(f"the sensitivity run was stopped (Ctrl-C) at t = {t:.6g} s")
                adv = stepper.step(state, float(tk))
                state = adv.state
                if adv.status is not Status.COMPLETED:
                    raise SimulationError(f"the run for the sensitivities stopped near t = {t:.6g} s: "
                                          f"{adv.message}")
                ends.extend(float(e) for e in adv.t)
                t = ends[-1] if ends else t
                if stepper.stats["steps"] + stepper.stats.get("rejected", 0) > max_steps:
                    raise SimulationError(f"more than {max_steps} steps before t = {tk:g} s "
                                          "(max_steps): raise rtol, or shorten the run")
            intervals.append(np.array(ends))
    return StepSequence(float(t0), t_out, intervals, start, int(stepper.stats.get("rejected", 0)))


# --- the replay graph ----------------------------------------------------------------------------


def _start(model: Model, system) -> tuple[ca.Function, tuple, np.ndarray, np.ndarray]:
    """(start, signature, x_plain, v_plain): ``start(p, x_plain, v_plain) -> (x0, v0)`` takes the
    entries given by formulas of the parameters from p and the plain numbers from its inputs
    (so one Function serves every start of the same formulas); ``signature`` the formulas."""
    entries = {key: [e for q in system.particles for e in q.formulas.get(key, getattr(q, key))]
               for key in ("position", "velocity")}
    signature = tuple(e if isinstance(e, str) else None for key in entries for e in entries[key])
    plain = {key: np.array([0.0 if isinstance(e, str) else float(e) for e in values])
             for key, values in entries.items()}
    cache, prefix = structure_cache(model)
    key = (*prefix, "sensitivity start", signature)
    if key not in cache:
        p, names = symbolic_parameters(system.parameters, system.definitions)
        # the rest of p (plain numbers, pair potentials' neighbour lists): unused by the start
        P = ca.vertcat(p, ca.SX.sym("number", len(model.parameter_vector) - p.numel()))
        n = model.n_coordinates
        given = {"position": ca.SX.sym("x_plain", n), "velocity": ca.SX.sym("v_plain", n)}
        out = {}
        for kind, column in given.items():
            rows = []
            for j, entry in enumerate(entries[kind]):
                where = f"particle '{system.particles[j // 3].name}'.{kind}[{j % 3}]"
                rows.append(column[j] if not isinstance(entry, str) else
                            ca.SX(expressions.parse(entry, names, where=where)))
            out[kind] = ca.vertcat(*rows) if rows else ca.SX(0, 1)
        cache[key] = ca.Function("start", [P, given["position"], given["velocity"]],
                                 [out["position"], out["velocity"]])
    return cache[key], signature, plain["position"], plain["velocity"]


def _step_function(model: Model, rows, tableau) -> ca.Function:
    """One accepted step with its size frozen: (s, [t; t_next]) -> s_next, s = [x; v; a; p];
    a step of zero length is skipped (short-circuit). dopri's stages and projection."""
    n = model.n_coordinates
    n_s = 3 * n + len(model.parameter_vector)
    S, ts = ca.MX.sym("s", n_s), ca.MX.sym("ts", 2)
    x, v, a, P = S[:n], S[n:2 * n], S[2 * n:3 * n], S[3 * n:]
    t, t1 = ts[0], ts[1]
    h = t1 - t
    symbolic = len(rows if rows is not None else range(model.n_constraints)) <= SYMBOLIC_MAX_CONSTRAINTS
    accel = acceleration_function(model, rows, symbolic=symbolic, parametric=True)
    view = ParametricView(model, P)

    def combine(K, w):
        return ca.mtimes(ca.horzcat(*K), ca.DM(np.asarray(w, float)))

    Kx, Kv = [v], [a]
    for i in range(1, tableau.stages):
        xi, vi = x + h * combine(Kx, tableau.A[i, :i]), v + h * combine(Kv, tableau.A[i, :i])
        ai, _ = accel(xi, vi, t + tableau.C[i] * h, P)
        Kx.append(vi)
        Kv.append(ai)
    x1, v1 = x + h * combine(Kx, tableau.B), v + h * combine(Kv, tableau.B)
    if model.n_constraints:
        x1, v1, _ = projection_graph(view, x1, v1, t1, rows=rows, linsol="symbolicqr" if symbolic else "ldl")
    a1, _ = accel(x1, v1, t1, P)
    step = ca.Function("replayed_step", [S, ts], [ca.vertcat(x1, v1, a1, P)])
    if symbolic:
        step = step.expand()
    S2, ts2 = ca.MX.sym("s", n_s), ca.MX.sym("ts", 2)
    return ca.Function("replay_step", [S2, ts2], [ca.if_else(ts2[1] > ts2[0], step(S2, ts2), S2, True)])


def _replay(model: Model, start, signature, rows, tableau, width: int, n_out: int, obs,
            chosen: tuple[int, ...], wrt_state: bool, mode: str) -> ca.Function:
    """(p, steps table, t0, t_out, p[chosen], x_plain, v_plain[, δx0, δv0]) -> (y (k, n_out),
    ∂vec(y)/∂z) with z = [p[chosen]; δx0; δv0] (the initial-state part when ``wrt_state``),
    built once per structure, start formulas and shape."""
    cache, prefix = structure_cache(model)
    key = (*prefix, "sensitivity replay", signature, rows, tableau.name, width, n_out, obs.names,
           obs.formulas, chosen, wrt_state, mode)
    if key in cache:
        return cache[key]
    n, n_p = model.n_coordinates, len(model.parameter_vector)
    P_in, table, T0, T_out = ca.MX.sym("p", n_p), ca.MX.sym("steps", 2, width * n_out), ca.MX.sym("t0"), \
        ca.MX.sym("t_out", 1, n_out)
    theta = ca.MX.sym("theta", len(chosen))
    pick = ca.DM(ca.Sparsity.triplet(n_p, len(chosen), list(chosen), list(range(len(chosen)))), 1.0)
    keep = ca.DM.eye(n_p) - ca.mtimes(pick, pick.T)
    P = ca.mtimes(keep, P_in) + ca.mtimes(pick, theta)
    dx, dv = ca.MX.sym("dx0", n), ca.MX.sym("dv0", n)
    x_plain, v_plain = ca.MX.sym("x_plain", n), ca.MX.sym("v_plain", n)
    x0, v0 = start(P, x_plain, v_plain)
    if wrt_state:
        x0, v0 = x0 + dx, v0 + dv
    x, v, _ = _projector(model, rows)(x0, v0, T0, P)
    symbolic = len(rows if rows is not None else range(model.n_constraints)) <= SYMBOLIC_MAX_CONSTRAINTS
    a, _ = acceleration_function(model, rows, symbolic=symbolic, parametric=True)(x, v, T0, P)
    step = _step_function(model, rows, tableau)
    inner = step.mapaccum("interval", width)
    Si, Ti = ca.MX.sym("s", step.size1_in(0)), ca.MX.sym("ts", 2, width)
    last = ca.Function("interval_end", [Si, Ti], [inner(Si, Ti)[:, -1]])
    ends = last.mapaccum("outputs", n_out)(ca.vertcat(x, v, a, P), table)  # (n_s, n_out)
    y = obs.function.map(n_out)(ends[:n, :], ends[n:2 * n, :], ends[2 * n:3 * n, :], T_out,
                                ca.repmat(P, 1, n_out))
    z = ca.vertcat(theta, dx, dv) if wrt_state else theta
    yv = ca.vec(y)
    if mode == "auto":
        mode = "forward" if z.numel() <= yv.numel() else "adjoint"
    if mode == "forward":
        J = ca.jtimes(yv, z, ca.DM.eye(z.numel()))
    else:
        J = ca.jtimes(yv, z, ca.DM.eye(yv.numel()), True).T
    inputs = [P_in, table, T0, T_out, theta, x_plain, v_plain] + ([dx, dv] if wrt_state else [])
    fun = ca.Function("sensitivity_replay", inputs, [y, J])
    cache[key] = fun
    return fun


@dataclass(frozen=True)
class Sensitivities:
    """Observables at the output times and their exact derivatives.

    ``t`` (T,), ``outputs`` (k names), ``values`` (T, k); ``parameters`` (P names) and
    ``d_parameters`` (T, k, P): ∂y/∂p; ``d_x0``, ``d_v0`` (T, k, N, 3): ∂y/∂(initial positions,
    velocities) before the start's projection onto the constraints (None unless asked for);
    ``steps`` the accepted steps replayed, ``stats`` mode, rejected steps, tolerances."""

    t: np.ndarray
    outputs: tuple[str, ...]
    values: np.ndarray
    parameters: tuple[str, ...]
    d_parameters: np.ndarray
    d_x0: np.ndarray | None = None
    d_v0: np.ndarray | None = None
    steps: int = 0
    stats: dict = field(default_factory=dict)

    def jacobian(self) -> np.ndarray:
        """(T·k, P [+ 6N]): rows output by output within each time, columns the parameters
        (then the initial positions and velocities, when computed)."""
        T, k = self.values.shape
        parts = [self.d_parameters.reshape(T * k, -1)]
        if self.d_x0 is not None:
            parts += [self.d_x0.reshape(T * k, -1), self.d_v0.reshape(T * k, -1)]
        return np.hstack(parts)


def sensitivities(system, t_eval, *, outputs=None, parameters: Sequence[str] | None = None,
                  initial_state: bool = False, values: dict | None = None, t_start: float = 0.0,
                  rtol: float = 1e-10, atol: float = 1e-12, base: str = "DOP853", mode: str = "auto",
                  model: Model | None = None, compiled="auto", max_steps: int = MAX_STEPS) -> Sensitivities:
    """∂(observables at ``t_eval``)/∂(parameters, initial state) of ``system``'s run, by CasADi
    forward or adjoint AD through the replayed dopri steps (see the module).

    ``outputs``: observable formulas (constrained.fitting.observables; default every
    particle's x, y, z); ``parameters``: the [parameters] to differentiate by (default all);
    ``initial_state``: also ∂/∂(x0, v0); ``values``: other parameter values for this call;
    ``mode``: "forward", "adjoint" or "auto" (the cheaper: fewer inputs than outputs ->
    forward); ``rtol``/``atol``/``base``: dopri's settings for the run."""
    if mode not in MODES:
        raise InputError(f"unknown mode {mode!r} (choose from {', '.join(MODES)})", where="mode")
    if base not in TABLEAUS:
        raise InputError(f"unknown base tableau {base!r} (choose from {', '.join(TABLEAUS)})", where="base")
    if isinstance(t_start, bool) or not isinstance(t_start, int | float) or not math.isfinite(t_start):
        raise InputError(f"t_start must be a finite number of seconds, got {t_start!r}", where="t_start")
    if not hasattr(system, "particles"):
        raise InputError(f"expected a System, got {type(system).__name__} (for a Scene, pass scene.system)",
                         where="system")
    model = (model or assemble(system)).with_parameters(values)
    system = system.with_parameters(values)
    names = list(model.parameter_names) if parameters is None else list(parameters)
    unknown = [p for p in names if p not in model.parameter_names]
    if unknown:
        known = ", ".join(model.parameter_names) or "none"
        raise InputError(f"unknown parameter(s) {', '.join(unknown)} (the system's [parameters]: {known})",
                         where="parameters")
    if len(set(names)) != len(names):
        raise InputError("a parameter is named twice", where="parameters")
    obs = observables(model, position_names(model) if outputs is None else outputs)
    seq = step_sequence(model, system, t_eval, float(t_start), rtol=rtol, atol=atol, base=base,
                        max_steps=max_steps, compiled=compiled)
    longest = max((len(i) for i in seq.intervals), default=0)
    width = 1 << max(0, math.ceil(math.log2(max(longest, 1))))
    chosen = tuple(model.parameter_names.index(p) for p in names)
    start, signature, x_plain, v_plain = _start(model, system)
    fun = _replay(model, start, signature, seq.start.manifold.rows, TABLEAUS[base], width, len(seq.t_out),
                  obs, chosen, initial_state, mode)
    p = model.parameter_vector
    args = [p, seq.table(width), float(t_start), seq.t_out[None, :], p[list(chosen)], x_plain, v_plain]
    if initial_state:
        n = model.n_coordinates
        args += [np.zeros(n), np.zeros(n)]
    try:
        with interrupt.watch(), interrupt.external():  # one CasADi call: Ctrl-C ends it
            y, J = fun(*args)
    except (KeyboardInterrupt, RuntimeError):
        if not interrupt.requested():
            raise
        raise RunInterrupted("the sensitivity computation was stopped (Ctrl-C)") from None
    y, J = np.asarray(y, float), np.asarray(J, float)
    T, k = len(seq.t_out), len(obs.names)
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(J))):
        raise SimulationError("the sensitivities are not finite: the run passes through a singular "
                              "configuration, or the forces are not differentiable along it")
    J = J.reshape(k, T, -1, order="F").transpose(1, 0, 2)  # vec(y) is column-major: time-major rows
    n_par = len(chosen)
    d_x0 = d_v0 = None
    if initial_state:
        N = model.n_particles
        d_x0 = J[:, :, n_par:n_par + 3 * N].reshape(T, k, N, 3)
        d_v0 = J[:, :, n_par + 3 * N:].reshape(T, k, N, 3)
    growth = relative_growth(y.T, J[:, :, :n_par], p[list(chosen)], tuple(names))
    stats = {"mode": mode, "rejected": seq.rejected, "rtol": rtol, "atol": atol, "base": base,
             "padded_width": width, "relative_growth": {name: g for name, (g, _, _) in growth.items()}}
    _warn_if_grown(growth, obs.names, seq.t_out)
    return Sensitivities(t=seq.t_out, outputs=obs.names, values=y.T, parameters=tuple(names),
                         d_parameters=J[:, :, :n_par], d_x0=d_x0, d_v0=d_v0, steps=seq.steps, stats=stats)


#: Sensitivities grown beyond this (relative: |∂y/∂p| |p| / max |y|) are named by a
#: LinearRangeWarning: their first-order prediction holds only for relative changes of p far
#: below its inverse.
GROWN = 1e6


def relative_growth(values: np.ndarray, d_parameters: np.ndarray, p: np.ndarray, names: tuple) -> dict:
    """Per parameter j (of nonzero value): ``(G_j, output index, time index)`` with
    G_j = max over outputs k and times i of |∂y_k(t_i)/∂p_j| |p_j| / max_i |y_k(t_i)|: how much a
    relative change of p_j is magnified in the outputs, relative to their own size."""
    scale = np.max(np.abs(values), axis=0)  # (k,) each output's size over the run
    out = {}
    for j, name in enumerate(names):
        if not p[j]:
            continue
        with np.errstate(all="ignore"):
            G = np.abs(d_parameters[:, :, j]) * abs(p[j]) / np.where(scale > 0, scale, np.inf)[None, :]
        i, k = np.unravel_index(int(np.argmax(G)), G.shape)
        out[name] = (float(G[i, k]), int(k), int(i))
    return out


def _warn_if_grown(growth: dict, outputs: tuple, t: np.ndarray) -> None:
    grown = {name: g for name, g in growth.items() if g[0] > GROWN}
    if not grown:
        return
    import warnings

    words = "; ".join(f"∂({outputs[k]})/∂{name} × |{name}| / max|{outputs[k]}| = {g:.2g} at t = {t[i]:.6g} s"
                      for name, (g, k, i) in grown.items())
    warnings.warn(LinearRangeWarning(
        f"the sensitivities grew by orders of magnitude ({words}): exact derivatives of this run, but "
        "y(p + δp) ≈ y + (∂y/∂p) δp holds only for relative changes δp/p far below the inverse of that "
        "growth (the motion is chaotic, or passes near a bifurcation); use a shorter span, or fit over "
        "shorter windows"), stacklevel=3)
