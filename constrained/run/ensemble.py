"""Many variants in one batched run: ``simulate_many`` (issue 17).

Every variant is a column of one state matrix ``[x; v; a; scalars; p]`` (the layout of
``solvers.dopri``): the parameters p are part of each column, so one step loop — dopri's
step, folded ``CHUNK`` times and mapped over a block of columns — advances all of them in
one CasADi call, each with its own adaptive step size, error control and projection. A
column that fails (non-finite values, a projection that no longer converges, the step
limit) is frozen at its last good state (its last good attempt: variants/stops.py) and
reported, and so is one whose steps a stiff spring or damper holds down, by the single run's
stiffness watch on its share of the batch's clock, or whose steps collapse towards a finite-time
blow-up, by the single run's collapse watch, or that reaches a singular configuration, by the
single run's singular watch on its share of the clock (variants/watch.py); the others go on.
A variant its own run would refuse before stepping — a mass that is not positive, a damping
coefficient (a formula of the parameters and t) negative or not finite somewhere in
[t_start, t_end] — is not run, with its own run's sentence (variants/refusals.py).

The start of each variant is its system's for those parameter values (positions and
velocities may be formulas of the parameters), projected onto the constraints in one
mapped call, and refused (``"inconsistent start"``) where that moves a particle by more
than ``max_initial_correction`` × the system's size.
"""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from .. import interrupt
from ..codegen import compiled as compiled_evaluation
from ..codegen.fast_call import FastCall
from ..errors import InputError
from ..manifold.graph import projection_graph
from ..manifold.manifold import acceleration_function
from ..model import expressions
from ..model.cache import ParametricView, structure_cache
from ..model.parameters import symbolic
from ..model.structure import Model, assemble
from ..model.system import require_system
from ..solvers.base import SINGULAR_TOL
from ..solvers.dopri import PROJECTION_FAIL, SCALARS, Dopri
from ..solvers.driver import DEFAULT_MAX_STEPS
from ..threads import available_cores, one_blas_thread
from .variants import reasons, refusals
from .variants.stops import Replay, judge
from .variants.watch import MemberCollapse, MemberSingular, MemberWatch

#: Steps (attempts) one call advances every column by.
CHUNK = 64
#: Columns per mapped call.
BLOCK = 256
#: Columns per thread at least when ``threads`` is chosen automatically.
MIN_THREAD_COLUMNS = 32
#: Newton sweeps of the mapped start projection.
START_SWEEPS = 3


@dataclass(frozen=True)
class Ensemble:
    """The variants of a batched run: ``parameters`` (N, k) for ``names``, states at the
    output times ``t`` — ``x``, ``v`` (N, T, particles, 3) — and per variant its ``status``
    ("completed", or why it stopped: its samples after that are NaN), ``steps``,
    ``rejected``, ``messages`` (why a variant stopped, as its own run would say) and
    ``corrections`` (max_i |x_i − x0_i| of its start's projection, m). ``stats``: wall time,
    variants per second, evaluation, block size."""

    names: tuple[str, ...]
    parameters: np.ndarray
    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    status: tuple[str, ...]
    steps: np.ndarray
    rejected: np.ndarray
    #: per variant: "" when it completed, else why not, in its own ``simulate``'s words
    messages: tuple[str, ...] = ()
    #: per variant: how far the start's projection moved a particle (m; NaN where refused)
    corrections: np.ndarray | None = None
    stats: dict = field(default_factory=dict)

    @property
    def ok(self) -> np.ndarray:
        """Which variants reached t_end."""
        return np.array([s == "completed" for s in self.status])

    def __len__(self) -> int:
        return len(self.status)

    def __repr__(self) -> str:
        return (f"Ensemble({len(self)} variants of {', '.join(self.names)}, {int(self.ok.sum())} "
                f"completed, {len(self.t)} output times)")


def _table(model: Model, parameters) -> tuple[tuple[str, ...], np.ndarray]:
    """(names, values (N, k)) of a table given as {name: sequence} (or a sequence of dicts)."""
    if isinstance(parameters, Sequence) and not isinstance(parameters, str):
        rows = list(parameters)
        if not rows or not all(isinstance(r, Mapping) for r in rows):
            raise InputError("parameters must be a table {name: [values]} or a list of {name: value}")
        names = tuple(rows[0])
        if any(tuple(r) != names for r in rows):
            raise InputError("every row of the parameter table must name the same parameters")
        columns = {n: [r[n] for r in rows] for n in names}
    elif isinstance(parameters, Mapping):
        columns = dict(parameters)
        names = tuple(columns)
    else:
        raise InputError("parameters must be a table {name: [values]} or a list of {name: value}")
    if not names:
        raise InputError("the parameter table names no parameter")
    unknown = [n for n in names if n not in model.parameter_names]
    if unknown:
        known = ", ".join(model.parameter_names) or "none"
        raise InputError(f"unknown parameter(s) {', '.join(unknown)} in the table (the system's: {known})")
    values = [_column(n, columns[n]) for n in names]
    sizes = {v.size for v in values}
    if len(sizes) != 1 or 0 in sizes:
        raise InputError("every column of the parameter table must have the same, non-zero length")
    table = np.stack(values, axis=1)
    if not np.all(np.isfinite(table)):
        bad = names[int(np.argmax(~np.all(np.isfinite(table), axis=0)))]
        raise InputError(f"the parameter table holds a value of '{bad}' that is not a finite number")
    return names, table


def _column(name: str, values) -> np.ndarray:
    """One column of the parameter table as floats: a flat sequence of real numbers (not
    text, booleans, complex numbers, or nested lists, which used to be flattened into more
    variants than rows) — else an InputError naming the parameter and the entry."""
    array = np.asarray(values, dtype=object) if not isinstance(values, np.ndarray) else values
    array = array.reshape(1) if array.ndim == 0 else array  # one value: one variant
    if array.ndim != 1:
        raise InputError(f"the column '{name}' of the parameter table must be a flat list of numbers, "
                         f"got an array of shape {array.shape}")
    if array.dtype.kind in "iuf":
        return array.astype(float)
    for i, v in enumerate(array.tolist()):
        if isinstance(v, bool | np.bool_) or not isinstance(v, numbers.Real):
            raise InputError(f"the column '{name}' of the parameter table holds {v!r:.60} at row {i}, "
                             "which is not a number; give numbers only")
    return array.astype(float)


def _start_formulas(system) -> tuple:
    """(particle, key, index, formula) of every start entry that is a formula string."""
    return tuple((k, key, i, entry) for k, particle in enumerate(system.particles)
                 for key in ("position", "velocity")
                 for i, entry in enumerate(particle.formulas.get(key, getattr(particle, key)))
                 if isinstance(entry, str))


def _start_function(model: Model, system) -> ca.Function:
    """``(p, x_given, v_given) -> (x0, v0)``: the particles' initial positions and velocities as
    one Function of the parameter vector (``Model.parameter_vector``): entries that are formulas
    of the parameters and definitions are built in, plain numbers are taken from ``x_given``,
    ``v_given`` (the structure is shared by systems whose plain start numbers differ)."""
    formulas = _start_formulas(system)

    def build():
        p, names = symbolic(system.parameters, system.definitions)
        n3 = 3 * len(system.particles)
        given = {"position": ca.SX.sym("x_given", n3), "velocity": ca.SX.sym("v_given", n3)}
        parts = {key: [given[key][j] for j in range(n3)] for key in given}
        for k, key, i, entry in formulas:
            where = f"particle '{system.particles[k].name}'.{key}[{i}]"
            parts[key][3 * k + i] = expressions.parse(entry, names, where=where)
        x0 = ca.vertcat(*parts["position"]) if parts["position"] else ca.SX(0, 1)
        v0 = ca.vertcat(*parts["velocity"]) if parts["velocity"] else ca.SX(0, 1)
        # the rest of p (plain numbers, pair potentials' neighbour lists): unused here
        numbers = ca.SX.sym("number", len(model.parameter_vector) - p.numel())
        return ca.Function("start", [ca.vertcat(p, numbers), given["position"], given["velocity"]], [x0, v0])

    cache, prefix = structure_cache(model)
    key = (*prefix, "ensemble start", formulas)
    if key not in cache:
        cache[key] = build()
    return cache[key]


def _projector(model: Model, rows) -> ca.Function:
    """``(x, v, t, p) -> (x, v, residual)``: START_SWEEPS mapped-ready Newton projections."""
    cache, prefix = structure_cache(model)
    key = (*prefix, "ensemble projection", rows)
    if key not in cache:
        n3 = model.n_coordinates
        X, V, T = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
        P = ca.MX.sym("p", len(model.parameter_vector))
        view = ParametricView(model, P)
        x, v, residual = X, V, ca.MX(0)
        for _ in range(START_SWEEPS):
            if model.n_constraints:
                x, v, residual = projection_graph(view, x, v, T, rows=rows, linsol="qr")
        cache[key] = ca.Function("ensemble_projection", [X, V, T, P], [x, v, residual])
    return cache[key]


def _start_block(model: Model, system, dopri: Dopri, width: int) -> FastCall:
    """``(p, t0) -> (x0, x, v, a, residual)`` mapped over ``width`` columns: the start's formulas
    of p, START_SWEEPS projections onto the constraints (the residual before the last Newton
    step, m) and the accelerations there; compiled when
    dopri is (once per structure, row set and width)."""
    cache, prefix = structure_cache(model)
    rows = dopri.manifold.rows
    key = (*prefix, "ensemble start block", rows, dopri.compiled, width, _start_formulas(system))
    if key not in cache:
        P, T = ca.MX.sym("p", len(model.parameter_vector)), ca.MX.sym("t")
        XG, VG = ca.MX.sym("x_given", model.n_coordinates), ca.MX.sym("v_given", model.n_coordinates)
        x0, v0 = _start_function(model, system)(P, XG, VG)
        x, v, residual = _projector(model, rows)(x0, v0, T, P)
        a, _ = acceleration_function(model, rows, parametric=True)(x, v, T, P)
        start = ca.Function("ensemble_start", [P, T, XG, VG], [x0, x, v, a, residual]).map(width)
        if dopri.compiled:
            start = compiled_evaluation.compile_function(start)
        return _kept(cache, key, FastCall(start), dopri.compiled)
    return cache[key]


def _kept(cache: dict, key, value, compiled: bool):
    """``value``, kept in ``cache`` unless its compilation (``compiled``) was cut by Ctrl-C (the
    uncompiled fallback serves the stopped run; the next run in this process compiles)."""
    if not (compiled and compiled_evaluation.cut_short()):
        cache[key] = value
    return value


def _mapped_acceleration(dopri: Dopri, width: int) -> FastCall:
    """``(x, v, t, p) -> a`` mapped over ``width`` columns (compiled when dopri is)."""
    cache, prefix = structure_cache(dopri.model)
    rows = dopri.manifold.rows
    key = (*prefix, "ensemble acceleration", rows, dopri.compiled, width)
    if key not in cache:
        n3 = dopri.model.n_coordinates
        X, V, T = ca.MX.sym("x", n3), ca.MX.sym("v", n3), ca.MX.sym("t")
        P = ca.MX.sym("p", len(dopri.model.parameter_vector))
        a, _ = acceleration_function(dopri.model, rows, parametric=True)(X, V, T, P)
        accel = ca.Function("ensemble_acceleration", [X, V, T, P], [a]).map(width)
        if dopri.compiled:
            accel = compiled_evaluation.compile_function(accel)
        return _kept(cache, key, FastCall(accel), dopri.compiled)
    return cache[key]


def _blockwise(call: FastCall, width: int, *columns: np.ndarray) -> list[np.ndarray]:
    """``call`` (mapped over ``width`` columns) on (rows, N) arrays, block by block, the last
    block padded with its last column: each output as an (N, rows) array."""
    n = columns[0].shape[1]
    outputs = None
    for start in range(0, n, width):
        stop = min(start + width, n)
        block = [c[:, start:stop] for c in columns]
        if stop - start < width:
            block = [np.hstack([b, np.repeat(b[:, -1:], width - (stop - start), axis=1)]) for b in block]
        results = call(*(b.ravel(order="F") for b in block))
        if outputs is None:
            outputs = [np.empty((n, r.size // width)) for r in results]
        for out, r in zip(outputs, results, strict=True):
            out[start:stop] = r.reshape(width, -1)[:stop - start]
    return outputs


def _mapped_chunk(dopri: Dopri, block: int, threads: int) -> tuple[FastCall, str]:
    """dopri's step folded CHUNK times (compiled when dopri is, once per structure, tableau
    and row set) and mapped over ``block`` columns on ``threads`` threads."""
    cache, prefix = structure_cache(dopri.model)
    key = (*prefix, "ensemble fold", dopri.tableau.name, dopri.compiled, dopri.manifold.rows)
    if key not in cache:
        folded = dopri._step_function(stale_stops=False).fold(CHUNK)  # (no list refresh per column)
        evaluation = "virtual machine"
        if dopri.compiled:
            machine = compiled_evaluation.compile_function(folded)
            if machine.class_name() == "External":
                folded, evaluation = machine, "compiled"
        if not (dopri.compiled and compiled_evaluation.cut_short()):
            cache[key] = (folded, evaluation)
    else:
        folded, evaluation = cache[key]
    mapped_key = (*key, block, threads)
    if mapped_key not in cache:  # the columns shared out over ``threads`` threads
        mapped = folded.map(block, "thread", threads) if threads > 1 else folded.map(block)
        return _kept(cache, mapped_key, (FastCall(mapped), evaluation), key not in cache)
    return cache[mapped_key]


def simulate_many(system, t_end: float, parameters, *, t_eval=None, t_start: float = 0.0,
                  rtol: float = 1e-8, atol: float = 1e-10, model: Model | None = None,
                  compiled="auto", base: str = "DOP853", max_steps: int | None = None,
                  max_initial_correction: float = 1e-3, block: int = BLOCK, threads: int | None = None,
                  progress: Callable[[float], None] | bool | None = None,
                  singular_tol: float | None = SINGULAR_TOL) -> Ensemble:
    """Simulate ``system`` for every row of the ``parameters`` table in one batched run.

    ``parameters``: ``{name: [values, ...]}`` (or a list of ``{name: value}``) over the
    system's [parameters]; the others keep their values. Each variant starts from its
    system's state for those values (projected, see the module) and runs dopri's step loop
    (``base``, ``rtol``, ``atol``, ``compiled`` as for ``simulate(method="dopri")``) to
    ``t_end``, with its own step sizes; outputs at ``t_eval`` (default: t_end only).
    ``block`` columns go to one call, shared out over ``threads`` threads (CasADi's
    thread map; default: the cores this process may use, one thread per MIN_THREAD_COLUMNS
    columns at most — 1.8× on the 2-core machine of docs/performance.md; pass 1 where the
    cores are busy already, e.g. in one Dask worker per core).
    ``progress(fraction)`` is told how far the slowest running variant is (``True``: a tqdm
    bar on stderr). ``singular_tol``: the singular watch's threshold, as ``simulate``'s (None: off).
    """
    require_system(system, "simulate_many")
    _refuse_events(system, model)
    for key, value in (("t_end", t_end), ("t_start", t_start)):
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
            raise InputError(f"{key} must be a finite number of seconds, got {value!r}")
    t_end, t_start = float(t_end), float(t_start)
    if isinstance(max_initial_correction, bool) or not isinstance(max_initial_correction, numbers.Real) \
            or not max_initial_correction >= 0 or not math.isfinite(max_initial_correction):
        raise InputError("max_initial_correction must be a finite number >= 0 (a fraction of the system's "
                         f"size), got {max_initial_correction!r}")
    if t_end <= t_start:
        raise InputError(f"t_end ({t_end:g} s) must be later than t_start ({t_start:g} s)")
    if not (isinstance(block, int) and block > 0):
        raise InputError(f"block must be a positive whole number of variants, got {block!r}")
    if threads is not None and not (isinstance(threads, int) and not isinstance(threads, bool)
                                    and threads > 0):
        raise InputError(f"threads must be a positive whole number (or None: the cores), got {threads!r}")
    started = time.perf_counter()
    model = model or assemble(system)
    names, table = _table(model, parameters)
    n_var = table.shape[0]
    P = np.tile(np.asarray(model.parameter_vector, float), (n_var, 1))
    for j, name in enumerate(names):
        P[:, model.parameter_names.index(name)] = table[:, j]
    targets = np.array([t_end], float) if t_eval is None else np.asarray(list(t_eval), float).ravel()
    if targets.size == 0 or not np.all(np.isfinite(targets)) or np.any(np.diff(targets) <= 0) \
            or targets[0] < t_start or targets[-1] > t_end:
        raise InputError(f"t_eval must be increasing finite times within [{t_start:g}, {t_end:g}]")
    dopri = Dopri(model, rtol=rtol, atol=atol, base=base, compiled=compiled, max_steps=max_steps,
                  singular_tol=singular_tol)  # (which checks singular_tol as simulate does)
    limit = max_steps or DEFAULT_MAX_STEPS  # the single run's budget: no variant crawls on for ever
    n3 = model.n_coordinates
    with one_blas_thread():
        # the starts: formulas of p, projected onto the constraints, their accelerations
        width = min(block, n_var)
        starts = _start_block(model, system, dopri, width)
        given_x = np.repeat(np.asarray(system.positions, float).reshape(-1, 1), n_var, axis=1)
        given_v = np.repeat(np.asarray(system.velocities, float).reshape(-1, 1), n_var, axis=1)
        x0, xs, vs, a0, missed = _blockwise(starts, width, P.T, np.full((1, n_var), float(t_start)),
                                            given_x, given_v)
        # each variant's size and correction as its own run measures them (run.variants.reasons)
        sizes = reasons.start_sizes(x0)
        moved = reasons.particle_moves(x0, xs)
        status = ["completed"] * n_var
        messages = [""] * n_var
        # members refused before running, as their own runs refuse them (run.variants.refusals):
        # a mass that is not positive, a damping coefficient negative somewhere in [t_start, t_end]
        invalid = refusals.before_running(model, system, P, t_start, t_end)
        for k, (why_status, why) in invalid.items():
            status[k], messages[k] = why_status, why
        # (a start the mapped Newton steps did not bring onto the constraints, as a rod of negative
        # length: refused here, it used to run and fail at t = 0 with "projection failed")
        on = missed[:, 0] <= PROJECTION_FAIL * np.maximum(1.0, np.max(np.abs(xs), axis=1))
        refused = np.flatnonzero(~np.isfinite(moved) | (moved > max_initial_correction * sizes)
                                 | ~np.all(np.isfinite(vs), axis=1) | ~on)
        if refused.size:
            start_of = _start_function(model, system)
            accel_of = acceleration_function(model, dopri.manifold.rows, parametric=True)
        for k in (k for k in refused if k not in invalid):
            # the single run's start decides: it projects what it can, else says why not
            xk, vk = (np.asarray(z, float).ravel() for z in start_of(P[k], given_x[:, k], given_v[:, k]))
            x, v, moved[k], why = reasons.single_start(model, P[k], xk, vk, t_start, max_initial_correction,
                                                       float(sizes[k]))
            if why is not None:
                status[k], messages[k] = "inconsistent start", why
                continue
            xs[k], vs[k] = x, v
            a0[k] = np.asarray(accel_of(x, v, t_start, P[k])[0], float).ravel()
        accel = _mapped_acceleration(dopri, width)
        h = _initial_steps(xs, vs, a0, P, t_start, t_end, dopri,
                           lambda x, v, t, p: _blockwise(accel, width, x, v, t, p))
        S = np.empty((dopri._state_size(), n_var))
        S[:n3], S[n3:2 * n3], S[2 * n3:3 * n3] = xs.T, vs.T, a0.T
        scal = {name: 3 * n3 + i for i, name in enumerate(SCALARS)}
        S[scal["t"]], S[scal["h"]] = t_start, h
        S[scal["rejected"]] = S[scal["n_acc"]] = S[scal["n_rej"]] = S[scal["res"]] = 0.0
        S[scal["rtol"]], S[scal["atol"]] = rtol, atol
        S[3 * n3 + len(SCALARS):] = P.T
        threads = threads or max(1, min(available_cores(), width // MIN_THREAD_COLUMNS))
        chunk, evaluation = _mapped_chunk(dopri, width, threads)
        X = np.full((n_var, targets.size, n3), np.nan)
        V = np.full((n_var, targets.size, n3), np.nan)
        running = np.array([s == "completed" for s in status])
        scale = np.maximum(1.0, np.max(np.abs(xs), axis=1))
        report, bar = _progress(progress, n_var)
        watch = MemberWatch(model, P, xs, t_start, t_end)  # (each member's share of the clock)
        replay = Replay(dopri._chunks, scal["res"], CHUNK)
        collapse = MemberCollapse(model, P, t_end)  # (each member's steps, as its own run's)
        singular = MemberSingular(model, P, dopri.rows, singular_tol, t_end, watch.share)
        with interrupt.watch():
            for j, target in enumerate(targets):
                S[scal["t_target"]] = np.where(running, target, S[scal["t"]])
                if target <= t_start:
                    X[running, j], V[running, j] = S[:n3, running].T, S[n3:2 * n3, running].T
                    continue
                while True:
                    active = np.flatnonzero(running & (S[scal["t"]] < target))
                    if active.size == 0:
                        break
                    if interrupt.requested():  # members that reached this output time keep it
                        reached = running & (S[scal["t"]] >= target)
                        X[reached, j], V[reached, j] = S[:n3, reached].T, S[n3:2 * n3, reached].T
                        for k in np.flatnonzero(running):
                            status[k] = "completed" if reached[k] and j == len(targets) - 1 else "interrupted"
                        running[:] = False
                        break
                    for first in range(0, active.size, width):
                        cols = active[first:first + width]
                        padded = np.zeros((S.shape[0], width))
                        padded[:, :cols.size] = S[:, cols]
                        padded[:, cols.size:] = S[:, cols[:1]]  # (filler columns, results dropped)
                        before, tick = S[scal["n_acc"], cols], watch.clock()
                        (out,) = chunk(padded.ravel(order="F"))
                        watch.charge(cols, watch.clock() - tick)
                        judge(out.reshape(width, -1).T[:, :cols.size], S, cols, status, running, scal,
                              scale, limit, replay)
                        held = watch.stops(cols[running[cols]], S[scal["t"]], S[scal["n_acc"]], S[:n3])
                        for k, why in held:
                            status[k], running[k], messages[k] = "stiff", False, why
                        for k, why in singular.stops(cols[running[cols]], before[running[cols]], S, scal, n3):
                            status[k], running[k], messages[k] = "singular configuration", False, why
                        for k, why in collapse.stops(cols[running[cols]], before[running[cols]], S, scal, n3):
                            status[k], running[k], messages[k] = "step size collapsed", False, why
                    if report is not None:
                        report(float((np.min(S[scal["t"], running]) - t_start) / (t_end - t_start))
                               if running.any() else 1.0)
                X[running, j], V[running, j] = S[:n3, running].T, S[n3:2 * n3, running].T
            # (read inside the watch, which forgets it at its end): Ctrl-C in the last chunk,
            # when every variant finished, is reported all the same, and the caller stops
            stopped = interrupt.requested()
        for k, why in singular.last_looks(status, S, scal, n3):  # (a failed step at a singular configuration)
            status[k], messages[k] = "singular configuration", why
        stops = [k for k, s in enumerate(status) if s not in ("completed", "interrupted") and not messages[k]]
        for i, k in enumerate(stops):  # the frozen column holds the last good state
            messages[k] = reasons.stop_reason(
                model, status[k], P[k], S[:n3, k], S[n3:2 * n3, k], float(S[scal["t"], k]),
                float(S[scal["h"], k]), limit, t_end, diagnose=i < reasons.DIAGNOSED_MAX, t0=t_start,
                steps=int(S[scal["n_acc"], k]))
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - started
    shape = (n_var, targets.size, model.n_particles, 3)
    return Ensemble(names, table, targets, X.reshape(shape), V.reshape(shape), tuple(status),
                    S[scal["n_acc"]].astype(int), S[scal["n_rej"]].astype(int), tuple(messages),
                    np.where([st == "inconsistent start" or k in invalid for k, st in enumerate(status)],
                             np.nan, moved),
                    {"wall_time_s": wall, "variants_per_s": n_var / wall if wall > 0 else math.inf,
                     "evaluation": evaluation, "block": width, "threads": threads, "method": "dopri",
                     "tableau": dopri.tableau.name, "rtol": rtol, "atol": atol, "interrupted": stopped})


def _refuse_events(system, model: Model | None) -> None:
    """simulate_many is dopri's step loop without event handling: a system with one-sided
    constraints (contacts, with their impacts) or [[events]] is refused, by name. It used to
    hold a floor as a two-sided plane, so every ball dropped onto it was "an inconsistent start"."""
    one_sided = [getattr(c, "label", None) or getattr(c, "name", None) or type(c).__name__
                 for c in system.constraints if getattr(c, "unilateral", False)]
    events = getattr(system, "events", None) or ()
    if not one_sided and not events:
        return
    what = (f"one-sided constraint(s) {', '.join(repr(str(n)) for n in one_sided)} (contacts and their "
            "impacts)" if one_sided else f"{len(events)} [[events]]")
    raise InputError(f"simulate_many cannot run this system: it has {what}, which need event handling "
                     "per run, and the batched step loop has none; run each variant with "
                     "simulate(..., parameters=...), or use constrained sweep, whose per-run path handles "
                     "them")


def _progress(progress, n_var: int):
    """(report(fraction) or None, the tqdm bar to close or None): ``progress=True`` draws a
    bar over the slowest running variant's simulated time (on stderr)."""
    if progress is True:
        from tqdm import tqdm

        bar = tqdm(total=1000, desc=f"{n_var} variants", unit="‰", leave=False)

        def report(fraction: float) -> None:
            bar.update(max(0, int(1000 * fraction) - bar.n))

        return report, bar
    if progress is None or progress is False:
        return None, None
    if not callable(progress):
        raise InputError(f"progress must be True (a bar) or a function of the fraction done, "
                         f"got {progress!r}")
    return progress, None


def _initial_steps(x, v, a, P, t0: float, t_end: float, dopri: Dopri, accel) -> np.ndarray:
    """Hairer's starting step for every column: dopri's ``_initial_step``, vectorized (kept
    apart: NumPy on one-row arrays would cost a single run ~25 µs)."""
    if dopri.dt is not None:
        return np.full(x.shape[0], min(float(dopri.dt), t_end - t0))
    with np.errstate(all="ignore"):  # a variant that overflows is judged by its first chunk
        return _hairer(x, v, a, P, t0, t_end, dopri, accel)


def _hairer(x, v, a, P, t0: float, t_end: float, dopri: Dopri, accel) -> np.ndarray:
    y0, f0 = np.hstack([x, v]), np.hstack([v, a])
    sc = dopri.atol + np.abs(y0) * dopri.rtol
    d0, d1 = np.linalg.norm(y0 / sc, axis=1), np.linalg.norm(f0 / sc, axis=1)
    h0 = np.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / np.maximum(d1, 1e-300))
    h0 = np.minimum(h0, t_end - t0)
    x1, v1 = x + h0[:, None] * v, v + h0[:, None] * a
    a1 = accel(x1.T, v1.T, (t0 + h0)[None, :], P.T)[0]  # each at its own t0 + h0
    d2 = np.linalg.norm((np.hstack([v1, a1]) - f0) / sc, axis=1) / h0
    order = dopri.tableau.order
    big = np.maximum(d1, d2)
    h1 = np.where(big <= 1e-15, np.maximum(1e-6, h0 * 1e-3),
                  (0.01 / np.maximum(big, 1e-300)) ** (1 / (order + 1)))
    return np.minimum(np.minimum(100 * h0, h1), t_end - t0)
