"""simulate: System -> consistent start -> solver -> Trajectory."""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Iterable

import numpy as np
from threadpoolctl import ThreadpoolController

from .analysis import dense_full_row_rank, jacobian_rank, sparse_full_row_rank
from .errors import InconsistentStateError, InputError, SimulationError
from .model import Model, assemble
from .solvers import METHODS
from .trajectory import QUANTITIES, Trajectory

#: Output names accepted by ``outputs`` (``positions``/``velocities`` are always computed).
OUTPUT_NAMES = frozenset({"positions", "velocities", *QUANTITIES})


#: From this many constraint rows, full rank is first checked with a sparse factorization.
SPARSE_RANK_FROM = 100


def flag_redundancy(model: Model, x, t: float) -> bool:
    """Set ``model.redundant`` when J has dependent rows at (x, t); True if newly set."""
    if model.redundant or model.n_constraints == 0:
        return False
    J = model.jacobian(x, t)[1]
    # the sparse test settles the usual case (independent rows) in O(N); the dense
    # rank-revealing QR, O(N³), runs only when it cannot
    if model.n_constraints > SPARSE_RANK_FROM:
        if sparse_full_row_rank(J, model.inverse_masses):
            return False
    elif dense_full_row_rank(np.asarray(J), model.inverse_masses):
        return False
    rank, _ = jacobian_rank(np.asarray(J))
    model.redundant = rank < model.n_constraints
    return model.redundant


def consistent_state(model: Model, x0, v0, t0: float = 0.0, *, max_correction: float = 1e-3,
                     size: float | None = None):
    """Project (x0, v0) onto f = 0 and J v + f_t = 0 (minimum mass-weighted change).

    Refuses with InconsistentStateError when the position correction exceeds
    ``max_correction × size`` or when the constraints cannot all hold. Returns
    (x, v, report) with the sizes of the corrections.
    """
    x0 = np.asarray(x0, float).ravel()
    v0 = np.asarray(v0, float).ravel()
    flag_redundancy(model, x0, t0)
    size = size or max(float(np.max(np.abs(x0), initial=0.0)), 1.0)
    labels = model.constraint_labels
    f0 = np.asarray(model.constraint(x0, t0)).ravel()
    if model.n_constraints and not np.all(np.isfinite(f0)):
        bad = labels[int(np.argmax(~np.isfinite(f0)))]
        raise InconsistentStateError(f"constraint '{bad}' is not finite at the initial state")
    worst = int(np.argmax(np.abs(f0))) if f0.size else 0
    try:
        x, err, _ = model.project_positions(x0, t0, tol=1e-13 * size, max_iter=50)
    except RuntimeError:  # CasADi's solve with a singular J M⁻¹ Jᵀ (constraints that touch)
        raise InconsistentStateError(
            "the constraints cannot be projected onto near the initial state: their Jacobian is "
            "singular there; the constraints may only touch (tangent surfaces, a rod just "
            "reaching), or a particle sits on a singular point; "
            f"the worst at the start is '{labels[worst]}', violated by {abs(f0[worst]):.3g}. "
            "Check the lengths and anchors, or move the particles") from None
    dx = float(np.max(np.linalg.norm((x - x0).reshape(-1, 3), axis=1), initial=0.0))
    if err > 1e-8 * size or not np.isfinite(err):
        f = np.asarray(model.constraint(x, t0)).ravel()
        k = int(np.nanargmax(np.abs(f)))
        from .diagnostics import incompatible_constraints

        clash = incompatible_constraints(model, x0, t0)
        named = (f"; {clash.describe()}" if not clash.compatible else
                 "; check that the constraints are compatible (lengths, triangle inequalities, anchors)")
        raise InconsistentStateError(
            f"the constraints cannot all be satisfied near the initial state: after projection "
            f"constraint '{labels[k]}' is still violated by {abs(f[k]):.3g} (at the given start the "
            f"worst was '{labels[worst]}', violated by {abs(f0[worst]):.3g}){named}"
        )
    limit = max_correction * size
    if dx > limit:
        raise InconsistentStateError(
            f"the initial positions are too far from the constraints: constraint '{labels[worst]}' "
            f"is violated by {abs(f0[worst]):.3g} at t = {t0:g}, and the nearest consistent state "
            f"moves a particle by {dx:.3g} m, more than the allowed {max_correction:g} × system size "
            f"{size:.3g} m = {limit:.3g} m. Correct the positions, or raise "
            "simulate.max_initial_correction"
        )
    if not np.array_equal(x, x0) and flag_redundancy(model, x, t0):
        x, err, _ = model.project_positions(x, t0, tol=1e-13 * size, max_iter=50)
    v = model.project_velocities(x, v0, t0)
    dv = float(np.max(np.linalg.norm((v - v0).reshape(-1, 3), axis=1), initial=0.0))
    report = {
        "position": dx,
        "velocity": dv,
        "max_residual_before": float(np.max(np.abs(f0), initial=0.0)),
        "worst_constraint": labels[worst] if f0.size else None,
    }
    return x, v, report


@functools.cache
def _blas_threads() -> ThreadpoolController:
    """The loaded BLAS/OpenMP libraries, found once (≈ 1 ms); limiting them then costs ≈ 20 µs."""
    return ThreadpoolController()


def simulate(
    system,
    t_end: float,
    *,
    method: str = "projection",
    rtol: float = 1e-8,
    atol: float = 1e-10,
    dt: float | None = None,
    t_eval: Iterable[float] | None = None,
    t_start: float = 0.0,
    outputs: Iterable[str] | None = None,
    max_initial_correction: float = 1e-3,
    model: Model | None = None,
    **options,
) -> Trajectory:
    """Simulate ``system`` from ``t_start`` to ``t_end`` and return a Trajectory.

    ``method`` picks the solver (see ``constrained.solvers.METHODS``); ``outputs`` limits the
    derived quantities computed (default: all). The initial state is projected onto the
    constraints first; the correction is in ``trajectory.info["initial_correction"]``.
    """
    if method not in METHODS:
        raise InputError(f"unknown method {method!r} (choose from {', '.join(sorted(METHODS))})")
    for key, value in (("t_end", t_end), ("t_start", t_start)):
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise InputError(f"{key} must be a finite number of seconds, got {value!r}")
    if t_end <= t_start:
        raise InputError(f"t_end ({t_end:g} s) must be later than t_start ({t_start:g} s)")
    if not (isinstance(max_initial_correction, int | float) and max_initial_correction >= 0):
        raise InputError(f"max_initial_correction must be >= 0, got {max_initial_correction!r}")
    wanted = OUTPUT_NAMES if outputs is None else set(outputs)
    unknown = wanted - OUTPUT_NAMES
    if unknown:
        raise InputError(
            f"unknown output(s) {', '.join(sorted(unknown))} (known: {', '.join(sorted(OUTPUT_NAMES))})"
        )
    if t_eval is not None:
        t_eval = np.asarray(list(t_eval), dtype=float).ravel()
        if t_eval.size == 0 or not np.all(np.isfinite(t_eval)):
            raise InputError("t_eval must be a non-empty list of finite times")
        if np.any(np.diff(t_eval) <= 0):
            raise InputError("t_eval must be strictly increasing")
        if t_eval[0] < t_start or t_eval[-1] > t_end:
            raise InputError(f"t_eval must lie within [t_start, t_end] = [{t_start:g}, {t_end:g}]")
    if system.n_particles == 0:
        raise InputError("the system has no particles")

    started = time.perf_counter()
    model = model or assemble(system)
    build_time = time.perf_counter() - started
    x0, v0, correction = consistent_state(
        model, system.positions, system.velocities, t_start,
        max_correction=max_initial_correction, size=system.size(),
    )
    started = time.perf_counter()
    solver = METHODS[method](model, rtol=rtol, atol=atol, dt=dt, **options)
    setup_time = time.perf_counter() - started
    # The dense algebra inside a run is small (J is C × 3N at most); a multithreaded BLAS only
    # adds spin-waiting, which on a busy 2-core machine made one 128 × 192 SVD take 0.1–1 s
    # instead of 1.5 ms. One thread for the run; the caller's setting is restored after.
    with _blas_threads().limit(limits=1, user_api="blas"):
        started = time.perf_counter()
        solution = solver.run(x0, v0, float(t_start), float(t_end), t_eval)
        wall = time.perf_counter() - started
        stats = {**solution.stats, "wall_time_s": wall, "build_time_s": build_time,
                 "setup_time_s": setup_time, "method": method}
        traj = trajectory_from(model, solution.t, solution.x, solution.v, wanted, stats)
    traj.info.update(
        {
            "initial_correction": correction,
            "system": system.name,
            "method": method,
            "rtol": rtol,
            "atol": atol,
            "active_terms": sorted(model.active_terms),
        }
    )
    if solution.failure and solution.failure.startswith("interrupted"):
        raise SimulationError(f"the run was {solution.failure}; what was computed is kept",
                              trajectory=traj)
    if solution.failure:
        cause = ("" if "likely cause" in solution.failure else
                 " (likely cause: a singular configuration, stiffness, or forces that blow up)")
        last = f"t = {traj.t[-1]:.6g} s" if len(traj.t) else "the start"
        raise SimulationError(
            f"the run stopped early: {solution.failure}; the last good state is at {last}{cause}",
            trajectory=traj,
        )
    return traj


def trajectory_from(model: Model, t, X, V, wanted, stats=None) -> Trajectory:
    """Build a Trajectory with the derived quantities in ``wanted`` evaluated at each sample."""
    t = np.asarray(t, float)
    n = len(t)
    N = model.n_particles
    traj = Trajectory(
        t=t,
        x=X.reshape(n, N, 3),
        v=V.reshape(n, N, 3),
        particle_names=[p.name for p in model.system.particles],
        constraint_labels=list(model.constraint_labels),
        stats=dict(stats or {}),
    )
    if n == 0:
        return traj
    if "multipliers" in wanted or "constraint_forces" in wanted:
        lam = model.multipliers_along(X, V, t)
        if "multipliers" in wanted:
            traj.multipliers = lam
        if "constraint_forces" in wanted:
            traj.constraint_forces = model.constraint_forces_along(X, t, lam)
    if "energy" in wanted:
        traj.energy = model.evaluate(model.energy, X, V, t)[0].ravel()
    if "constraint_residual" in wanted:
        if model.n_constraints:
            f = model.evaluate(model.constraint, X, t)[0]
            traj.constraint_residual = np.max(np.abs(f), axis=0)
        else:
            traj.constraint_residual = np.zeros(n)
    if "action" in wanted and n >= 2:
        from .action import action

        traj.action = action(model, traj).cumulative
    if "velocity_residual" in wanted:
        if model.n_constraints:
            Jcat, f_t = model.evaluate(model.velocity_terms, X, t)
            J = Jcat.reshape(model.n_constraints, n, -1).transpose(1, 0, 2)
            c = np.einsum("kci,ki->kc", J, V.reshape(n, -1)) + f_t.T
            traj.velocity_residual = np.max(np.abs(c), axis=1)
        else:
            traj.velocity_residual = np.zeros(n)
    return traj
