"""simulate: System -> consistent start -> solver -> Trajectory."""

from __future__ import annotations

import math
import time
from collections.abc import Iterable

import numpy as np

from .action import action
from .errors import InputError, SimulationError
from .model import Model, assemble
from .quantities import OUTPUT_NAMES, trajectory_from
from .solvers import METHODS
from .start import consistent_start, consistent_state  # noqa: F401  (consistent_state: public name)
from .threads import one_blas_thread
from .trajectory import Trajectory


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
    start = consistent_start(
        model, system.positions, system.velocities, t_start,
        max_correction=max_initial_correction, size=system.size(),
    )
    x0, v0, correction = start.x, start.v, start.correction
    started = time.perf_counter()
    solver = METHODS[method](start.manifold, rtol=rtol, atol=atol, dt=dt, **options)
    setup_time = time.perf_counter() - started
    with one_blas_thread():  # see constrained.threads
        started = time.perf_counter()
        solution = solver.run(x0, v0, float(t_start), float(t_end), t_eval)
        wall = time.perf_counter() - started
        stats = {**solution.stats, "wall_time_s": wall, "build_time_s": build_time,
                 "setup_time_s": setup_time, "method": method}
        traj = trajectory_from(model, solution.t, solution.x, solution.v, wanted, stats)
        if "action" in wanted and len(traj.t) >= 2:
            traj.action = action(model, traj).cumulative
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
