"""simulate: System -> consistent start -> solver -> Trajectory."""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Iterable

import numpy as np
from threadpoolctl import ThreadpoolController

from . import diagnostics, interrupt, residual
from .analysis import dense_full_row_rank, jacobian_rank, sparse_full_row_rank
from .errors import InconsistentStateError, InputError, RunInterrupted, SimulationError
from .model import Model, assemble
from .solvers import METHODS
from .solvers.base import INTERRUPTED
from .trajectory import QUANTITIES, Trajectory

#: Output names accepted by ``outputs`` (``positions``/``velocities`` are always computed).
OUTPUT_NAMES = frozenset({"positions", "velocities", *QUANTITIES})


#: From this many constraint rows, full rank is first checked with a sparse factorization.
SPARSE_RANK_FROM = 100
#: An interrupted run with more samples than this keeps t, x, v only (see ``simulate``).
INTERRUPTED_QUANTITY_SAMPLES = 5000


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
    # residuals and tolerances in metres: each row divided by its scale (constrained.residual)
    scales = residual.row_scales(model, x0, t0) if model.n_constraints else np.ones(0)
    f0 = f0 / scales if np.all(np.isfinite(scales)) and np.all(scales > 0) else f0
    worst = int(np.argmax(np.abs(f0))) if f0.size else 0
    s_min = float(np.min(scales)) if scales.size and np.isfinite(np.min(scales)) else 1.0
    x, err, _ = model.project_positions(x0, t0, tol=1e-13 * size * s_min, max_iter=50)
    if np.isfinite(err) and err > 1e-8 * size * s_min:
        err = residual.position_residual(model, x, t0)
    dx = float(np.max(np.linalg.norm((x - x0).reshape(-1, 3), axis=1), initial=0.0))
    if err > 1e-8 * size or not np.isfinite(err):
        f = np.asarray(model.constraint(x, t0)).ravel() / np.where(scales > 0, scales, 1.0)
        k = int(np.nanargmax(np.abs(f)))
        from .diagnostics import incompatible_constraints

        clash = incompatible_constraints(model, x0, t0)
        named = (f"; {clash.describe()}" if not clash.compatible else
                 "; check that the constraints are compatible (lengths, triangle inequalities, anchors)")
        raise InconsistentStateError(
            f"the constraints cannot all be satisfied near the initial state: after projection "
            f"constraint '{labels[k]}' is still violated by {abs(f[k]):.3g} m (at the given start the "
            f"worst was '{labels[worst]}', violated by {abs(f0[worst]):.3g} m){named}"
        )
    limit = max_correction * size
    if dx > limit:
        raise InconsistentStateError(
            f"the initial positions are too far from the constraints: constraint '{labels[worst]}' "
            f"is violated by {abs(f0[worst]):.3g} m at t = {t0:g}, and the nearest consistent state "
            f"moves a particle by {dx:.3g} m, more than the allowed {max_correction:g} × system size "
            f"{size:.3g} m = {limit:.3g} m. Correct the positions, or raise "
            "simulate.max_initial_correction"
        )
    if not np.array_equal(x, x0) and flag_redundancy(model, x, t0):
        x, err, _ = model.project_positions(x, t0, tol=1e-13 * size * s_min, max_iter=50)
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
    _refuse_nonfinite_start(model, x0, v0, float(t_start))
    started = time.perf_counter()
    solver = METHODS[method](model, rtol=rtol, atol=atol, dt=dt, **options)
    setup_time = time.perf_counter() - started
    # The dense algebra inside a run is small (J is C × 3N at most); a multithreaded BLAS only
    # adds spin-waiting, which on a busy 2-core machine made one 128 × 192 SVD take 0.1–1 s
    # instead of 1.5 ms. One thread for the run; the caller's setting is restored after.
    with _blas_threads().limit(limits=1, user_api="blas"):
        started = time.perf_counter()
        # Ctrl-C becomes a request the solver honours after its current step or chunk
        with interrupt.watch():
            solution = solver.run(x0, v0, float(t_start), float(t_end), t_eval)
        wall = time.perf_counter() - started
        stats = {**solution.stats, "wall_time_s": wall, "build_time_s": build_time,
                 "setup_time_s": setup_time, "method": method}
        interrupted = bool(solution.failure and solution.failure.startswith(INTERRUPTED))
        if interrupted and len(solution.t) > INTERRUPTED_QUANTITY_SAMPLES:
            # the derived quantities cost ~30 µs a sample: a stop must be prompt, so a long
            # interrupted run keeps t, x, v (plot/analysis can derive the rest later)
            skipped, wanted = sorted(wanted & set(QUANTITIES)), set()
        else:
            skipped = []
        traj = trajectory_from(model, solution.t, solution.x, solution.v, wanted, stats)
    reached = float(traj.t[-1]) if len(traj.t) else float(t_start)
    traj.info.update(
        {
            "initial_correction": correction,
            "system": system.name,
            "method": method,
            "rtol": rtol,
            "atol": atol,
            "active_terms": sorted(model.active_terms),
            "status": "interrupted" if interrupted else ("stopped" if solution.failure else "completed"),
            "t_end": float(t_end),
            "t_end_reached": reached,
        }
    )
    if interrupted:
        note = (f" (the derived quantities {', '.join(skipped)} were not computed for its "
                f"{len(traj.t)} samples)" if skipped else "")
        if skipped:
            traj.info["quantities_skipped"] = skipped
        raise RunInterrupted(f"the run was {solution.failure} (Ctrl-C) before t_end = {t_end:g} s; "
                             f"what was computed is kept{note}", trajectory=traj)
    bad = None if solution.failure else _first_nonfinite(model, traj, wanted)
    if bad is not None:
        what, k = bad
        state = (traj.x[k].ravel(), traj.v[k].ravel(), float(traj.t[k]))
        kept = traj.head(k)
        kept.info.update(status="stopped", t_end_reached=float(kept.t[-1]) if k else float(t_start))
        raise SimulationError(
            f"non-finite {what} at t = {traj.t[k]:.6g} s; "
            f"{diagnostics.nonfinite_cause(model, *state)}",
            trajectory=kept,
        )
    if solution.failure:
        cause = ("" if "likely cause" in solution.failure else
                 _stiff_spring_cause(model, traj, x0, float(t_start), float(t_end), stats) or
                 " (likely cause: a singular configuration, stiffness, or forces that blow up)")
        last = f"t = {traj.t[-1]:.6g} s" if len(traj.t) else "the start"
        raise SimulationError(
            f"the run stopped early: {solution.failure}; the last good state is at {last}{cause}",
            trajectory=traj,
        )
    return traj


def _stiff_spring_cause(model: Model, traj: Trajectory, x0, t0: float, t_end: float, stats: dict) -> str:
    """'; likely cause: stiffness: ...' when a barely stretched spring far faster than the run
    explains a stop the solver could not name (diagnostics.StiffnessWatch), else ''."""
    try:
        watch = diagnostics.StiffnessWatch(model, x0, t0, t_end, method=stats.get("method", ""))
        t = float(traj.t[-1]) if len(traj.t) else t0
        element = watch.fastest()  # as at the start: an unstable step stretches it later
        if element is None or not element.rigid_like:
            return ""
        dt = stats.get("dt")
        limit = (f"; the fixed step dt = {dt:.3g} s is beyond its stability limit 2/ω = "
                 f"{2 / element.omega:.3g} s" if dt and dt * element.omega > 2 else "")
        return f"; {watch.describe(element, t, int(stats.get('steps', 0) or 0))}{limit}"
    except Exception:  # a diagnosis must never hide the stop itself
        return ""


def _refuse_nonfinite_start(model: Model, x0, v0, t0: float) -> None:
    """Stop before stepping when the forces (or the energy) are not finite at the start."""
    F = np.asarray(model.dynamics(x0, v0, t0)[0], float).ravel()
    E = float(np.asarray(model.energy(x0, v0, t0), float).ravel()[0])
    if np.all(np.isfinite(F)) and np.isfinite(E):
        return
    what = "forces" if not np.all(np.isfinite(F)) else f"energy ({E:g} J)"
    start = trajectory_from(model, [t0], np.asarray(x0)[None], np.asarray(v0)[None], set())
    start.info.update(status="stopped", t_end_reached=t0)
    raise SimulationError(f"non-finite {what} at the initial state (t = {t0:g} s); "
                          f"{diagnostics.nonfinite_cause(model, x0, v0, t0)}", trajectory=start)


def _first_nonfinite(model: Model, traj: Trajectory, wanted):
    """(name, index) of the first sample where a state or a computed quantity is not finite
    (the energy is checked at the last sample even when not asked for), or None."""
    n = len(traj.t)
    if n == 0:
        return None
    first = None
    for name in ("x", "v", *QUANTITIES):
        values = getattr(traj, name)
        if values is None or name == "action":
            continue
        ok = np.all(np.isfinite(values.reshape(n, -1)), axis=1)
        if not ok.all():
            k = int(np.argmin(ok))
            if first is None or k < first[1]:
                first = ({"x": "positions", "v": "velocities"}.get(name, name.replace("_", " ")), k)
    if first is None and "energy" not in wanted:
        E = np.asarray(model.energy(traj.x[-1].ravel(), traj.v[-1].ravel(), traj.t[-1]), float)
        if not np.all(np.isfinite(E)):  # then find the first sample where it is not
            E = model.evaluate(model.energy, traj.x.reshape(n, -1), traj.v.reshape(n, -1), traj.t)[0]
            first = ("energy", int(np.argmin(np.isfinite(np.asarray(E).ravel()))))
    return first


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
    if "constraint_residual" in wanted:  # in metres, whatever the scale of the formulas
        traj.constraint_residual = residual.position_residual_along(model, X, t)
    if "action" in wanted and n >= 2:
        from .action import action

        traj.action = action(model, traj).cumulative
    if "velocity_residual" in wanted:  # in m/s
        traj.velocity_residual = residual.velocity_residual_along(model, X, V.reshape(n, -1), t)
    return traj
