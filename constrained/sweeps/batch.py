"""The batched path of a sweep: a chunk of variants that differ only in [parameters] values
runs as ONE ``simulate_many`` call, and its table columns are evaluated from the Ensemble's
arrays in mapped CasADi calls — no Scene, Model or Trajectory per variant.

Which scenes can take it (``batch_blocker``): method ``dopri`` (the default) with adaptive
steps (no ``dt``), no one-sided constraints or [[events]], no [expect] check of a conserved
quantity or of constraint forces (those need each run's Trajectory), no saved trajectories;
every other case runs on the per-run path (constrained.sweep_run).

What "over the run" means here: the samples are the scene's output times (``output_dt`` or
``samples``), else ``BATCH_SAMPLES`` evenly spaced times from t_start to t_end (the per-run
path of a method without output times samples every step). The columns, for variant k with
samples x_kj, v_kj at t_j:

- ``x_P``, ``vx_P``, …: the last sample; ``min_x_P``, ``max_x_P``: over the samples;
- ``energy_drift`` = max_j |E(x_kj, v_kj, t_j; p_k) − E(x_k0, v_k0, t_0; p_k)|;
- ``max_constraint_residual`` = max_j max_i |f_i| / s_i (metres, constrained.residual), and
  ``max_velocity_residual`` likewise with |J_i v + f_t,i| / s_i;
- each ``--summary`` formula at every sample, reduced over j; ``steps``: accepted steps;
- the scene's [expect] checks (``expect.KEY``, ``expect.KEY.ok``) by the measures of
  ``scene.check_expectations``, their formulas (parameters included) evaluated for every
  variant's samples in mapped calls.

With the same output times, every number equals the per-run path's to round-off (the same
step sequence: ``simulate_many`` advances each column exactly as its own run).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from ..scene.expectations import drift, expect_requirements, period  # the [expect] checks' own measures
from .per_run import (
    cached_model,
    formula_function,
    options_of,
    scene_for,
    solver_columns,
    summary_function,
    worker_name,
)

#: Output times of a batched chunk when the scene gives none (t_start and t_end included).
BATCH_SAMPLES = 21
#: With ``compiled = "auto"`` a batched structure is compiled to machine code when it runs at
#: least this many variants in one process (the compile, about a second, is cached on disk).
COMPILE_FROM = 400

#: simulate_many's statuses, as the table's status messages.
STATUS_TEXT = {
    "non-finite": "the solution became non-finite (NaN or inf): check the parameter values",
    "inconsistent start": "inconsistent start: the initial positions miss the constraints by more than "
                          "max_initial_correction; make the positions consistent with the parameters",
    "projection failed": "the projection onto the constraints no longer converged (a singular "
                         "configuration?); try a smaller rtol or other parameter values",
    "step limit": "the step limit was reached before t_end",
    "step size collapsed": "the step size collapsed (stiff or singular motion)",
    "singular configuration": "the constraints became dependent (a singular configuration)",
    "non-positive mass": "a particle's mass (a formula of the parameters) is not a finite positive number "
                         "for these parameter values; give values that make every mass positive",
    "negative damping": "a damping coefficient (a formula of the parameters and t) is negative or not finite "
                        "during the run for these parameter values: an energy source, not dissipation",
}


def batch_blocker(scene, save_trajectories: bool) -> str:
    """Why this scene's variants cannot run batched ("" when they can)."""
    method = scene.settings.get("method") or "dopri"
    if method != "dopri":
        return f"method '{method}' (batched runs use dopri)"
    if scene.settings.get("dt") is not None:
        return "a fixed step dt (batched runs choose their steps)"
    if save_trajectories:
        return "--trajectories needs each run's full trajectory"
    if any(c["kind"] == "conserved" for c in scene.expectations or ()):
        return "the scene's [expect] conserved checks need each run's trajectory"
    if "constraint_forces" in expect_requirements(scene):
        return "the scene's [expect] checks use constraint forces (each run's multipliers)"
    if any(getattr(c, "unilateral", False) for c in scene.system.constraints):
        return "one-sided constraints need event handling per run"
    if getattr(scene.system, "events", None):
        return "[[events]] need event handling per run"
    return ""


def run_batch(task: dict) -> dict:
    """One chunk as one ``simulate_many`` call. ``task``: the chunk's scene (``scene_text``,
    ``file``, ``base_overrides``, ``summaries``), ``shared`` (the overrides every variant of
    the chunk shares), ``variants`` ((index, run_id, None) triples), ``table``
    ({parameter: [values]} in the variants' order), ``compiled``. Returns what
    ``sweep_run.run_variants`` does (no trajectories)."""
    from ..manifold.residual import functions as residual_functions
    from ..run.ensemble import simulate_many

    started = time.perf_counter()
    ids = [rid for _, rid, _ in task["variants"]]
    raw, scene = scene_for(task, task["shared"])
    entry = cached_model(raw, scene.system)
    model = entry["model"].with_parameters(scene.system.parameters)
    options = options_of(scene, set())
    t_eval = options.t_eval
    if t_eval is None:
        t_eval = np.linspace(options.t_start, options.t_end, BATCH_SAMPLES)
    table = {k: np.asarray(v, float) for k, v in task["table"].items()}
    if not table:  # nothing varies in [parameters]: one column per variant all the same
        name = model.parameter_names[0] if model.parameter_names else None
        table = {name: np.full(len(ids), model.parameter_values[0])} if name else {}
    kwargs = {k: options.method_options[k] for k in ("base",) if k in options.method_options}
    if options.max_steps:  # the scene's step budget holds on this path too
        kwargs["max_steps"] = options.max_steps
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        ens = simulate_many(scene.system, options.t_end, table, t_eval=t_eval, t_start=options.t_start,
                            rtol=options.rtol, atol=options.atol, model=model, compiled=task["compiled"],
                            max_initial_correction=options.max_initial_correction,
                            progress=task.get("progress"), threads=task.get("threads"), **kwargs)
        interrupted = "interrupted" in ens.status or ens.stats.get("interrupted", False)
        P = np.tile(np.asarray(model.parameter_vector, float), (len(ids), 1))
        for name, values in table.items():
            P[:, model.parameter_names.index(name)] = values
        columns = _columns(ens, model, P, entry, task["summaries"], residual_functions(model),
                           scene.expectations or ())
    solver = solver_columns(options)
    rows: dict[str, dict] = {}
    for k, rid in enumerate(ids):
        status = ens.status[k]
        if status == "interrupted":
            continue
        if status != "completed":
            why = ens.messages[k] if ens.messages else ""  # its own run's words (run/variants/reasons.py)
            rows[rid] = {"status": " ".join((why or STATUS_TEXT.get(status, status)).split()), "row": {}}
            continue
        row: dict[str, Any] = {name: _plain(values[k]) for name, values in columns.items()}
        row.update(solver)
        rows[rid] = {"status": "ok", "row": row}
    return {"rows": rows, "trajectories": {}, "interrupted": interrupted,
            "wall_time_s": time.perf_counter() - started, "worker": worker_name(),
            "evaluation": ens.stats.get("evaluation")}


def _reduce_rows(values: np.ndarray, how: str) -> np.ndarray:
    """sweep_run._reduce over the samples (axis 1) of every variant at once."""
    if how == "final":
        return values[:, -1]
    if how == "max":
        return np.max(values, axis=1)
    if how == "min":
        return np.min(values, axis=1)
    if how == "max_abs":
        return np.max(np.abs(values), axis=1)
    return np.mean(values, axis=1)


def _plain(value):
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    return float(value)


def _columns(ens, model, P: np.ndarray, entry: dict, summaries, residual,
             expectations=()) -> dict[str, np.ndarray]:
    """The table's metric columns of every variant (arrays over variants), in the per-run
    path's order."""
    n, T = len(ens), len(ens.t)
    names = model.particle_names
    X = ens.x.reshape(n, T, -1)  # (n, T, 3N)
    V = ens.v.reshape(n, T, -1)
    flat_x = X.reshape(n * T, -1).T  # (3N, n T), variant-major
    flat_v = V.reshape(n * T, -1).T
    flat_t = np.tile(ens.t, n)[None, :]
    flat_p = np.repeat(P, T, axis=0).T

    maps = entry.setdefault("maps", {})

    def along(fun, *inputs) -> np.ndarray:  # (n, T), the mapped Function kept per size
        key = (fun.name(), fun.__hash__(), n * T)
        if key not in maps:
            maps[key] = fun.map(n * T)
        return np.asarray(maps[key](*inputs), float).reshape(n, T)

    out: dict[str, np.ndarray] = {"t_final": np.full(n, float(ens.t[-1]))}
    for i, p in enumerate(names):
        for k, axis in enumerate("xyz"):
            out[f"{axis}_{p}"] = ens.x[:, -1, i, k]
        for k, axis in enumerate("xyz"):
            out[f"v{axis}_{p}"] = ens.v[:, -1, i, k]
    for i, p in enumerate(names):
        for k, axis in enumerate("xyz"):
            out[f"min_{axis}_{p}"] = np.min(ens.x[:, :, i, k], axis=1)
            out[f"max_{axis}_{p}"] = np.max(ens.x[:, :, i, k], axis=1)
    energy = along(model.parametric("energy"), flat_x, flat_v, flat_t, flat_p)
    out["energy_drift"] = np.max(np.abs(energy - energy[:, :1]), axis=1)
    if model.n_constraints:
        out["max_constraint_residual"] = np.max(along(residual["position"], flat_x, flat_t, flat_p), axis=1)
        out["max_velocity_residual"] = np.max(
            along(residual["velocity"], flat_x, flat_v, flat_t, flat_p), axis=1)
    else:
        out["max_constraint_residual"] = out["max_velocity_residual"] = np.zeros(n)
    for summary in summaries:
        values = along(summary_function(entry, summary), flat_x, flat_v, flat_t, flat_p)
        out[summary.name] = _reduce_rows(values, summary.reduction)
    series = {"energy_drift": energy, "constraint_residual": None, "velocity_residual": None}
    if model.n_constraints and expectations:
        series["constraint_residual"] = along(residual["position"], flat_x, flat_t, flat_p)
        series["velocity_residual"] = along(residual["velocity"], flat_x, flat_v, flat_t, flat_p)
    for c in expectations:
        lhs = rhs = None
        if "lhs" in c:
            lhs = along(formula_function(entry, c["lhs"], c["key"]), flat_x, flat_v, flat_t, flat_p)
        if "rhs" in c:
            rhs = along(formula_function(entry, c["rhs"], c["key"]), flat_x, flat_v, flat_t, flat_p)
        value, ok = _expect(c, ens.t, lhs, rhs, series.get(c["kind"]), n)
        out[c["key"]] = value
        out[f"{c['key']}.ok"] = ok
    out["steps"] = np.asarray(ens.steps, int)
    return out


def _expect(c: dict, t: np.ndarray, lhs, rhs, data, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(value, ok) of one [expect] check for every variant, by the per-run measures of
    ``scene.check_expectations`` (samples (n, T) of lhs / rhs / the run's quantity)."""
    kind, tol = c["kind"], c.get("tol", 0.0)
    if kind == "energy_drift":
        value = np.array([drift(row)[0] for row in data])
    elif kind in ("constraint_residual", "velocity_residual"):
        value = np.zeros(n) if data is None else np.max(np.abs(data), axis=1)
    elif kind == "final":
        value = np.abs(lhs[:, -1] - rhs[:, -1])
    elif kind == "closed_form":
        value = np.max(np.abs(lhs - rhs), axis=1)
    elif kind == "period":
        found = [period(t, row) for row in lhs]
        value = np.array([np.nan if f is None else abs(f - rhs[k, 0]) for k, f in enumerate(found)])
    else:  # bounds, reaches: counts of samples outside / inside
        inside = (lhs >= c["lo"]) & (lhs <= c["hi"])
        if kind == "bounds":
            return np.count_nonzero(~inside, axis=1).astype(float), np.all(inside, axis=1)
        return np.count_nonzero(inside, axis=1).astype(float), np.any(inside, axis=1)
    return value.astype(float), value <= tol
