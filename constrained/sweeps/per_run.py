"""The per-run path of a sweep: one scene built, simulated and summarized per variant
(executed in this process or on a Dask worker).

What a worker caches (module-level, per process, so per Dask worker): the assembled Model,
keyed by a hash of the scene *structure* (the scene after overrides, without particle
positions and velocities, without the values of [parameters] and without the [simulate],
[outputs], [expect], [scene] and [reduced] tables). Runs that only change the initial
state, the run settings or parameter values share one Model (``Model.with_parameters``);
a run that changes a mass, a constraint or an effect given as a number assembles its own.
The compiled summary formulas are cached with their Model. The cache holds at most
``MODEL_CACHE_SIZE`` Models.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import warnings
from collections import OrderedDict
from typing import Any

import numpy as np

from ..errors import ExpressionError, InitialStateWarning, InputError, RunInterrupted
from ..model import expressions
from ..scene.load import SceneError, apply_overrides, build_scene, expect_requirements
from .design import Summary, load_raw
from .store import unfinished

#: How many assembled Models one worker process keeps (least recently used dropped).
MODEL_CACHE_SIZE = 64

_MODEL_CACHE: OrderedDict[str, dict] = OrderedDict()
#: Counters of this process: models assembled and reused (read by tests and the report).
CACHE_STATS = {"assembled": 0, "reused": 0}

_STATE_TABLES = ("simulate", "outputs", "expect", "scene", "reduced")


def structure_key(raw: dict) -> str:
    """Hash of what the Model's structure depends on: the scene without initial state, run
    settings and the values of [parameters] (inputs of the Model's Functions: their names
    count, their values do not; ``Model.with_parameters`` gives each run its values)."""
    slim = {k: v for k, v in raw.items() if k not in _STATE_TABLES}
    if isinstance(slim.get("parameters"), dict):
        slim["parameters"] = sorted(slim["parameters"])
    if isinstance(slim.get("particles"), list):
        slim["particles"] = [
            {k: v for k, v in p.items() if k not in ("position", "velocity")} if isinstance(p, dict) else p
            for p in slim["particles"]
        ]
    text = json.dumps(slim, sort_keys=True, default=repr)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def cached_model(raw: dict, system):
    from ..model.structure import assemble

    key = structure_key(raw)
    entry = _MODEL_CACHE.get(key)
    if entry is None:
        entry = {"model": assemble(system), "summaries": {}}
        _MODEL_CACHE[key] = entry
        CACHE_STATS["assembled"] += 1
        while len(_MODEL_CACHE) > MODEL_CACHE_SIZE:
            _MODEL_CACHE.popitem(last=False)
    else:
        _MODEL_CACHE.move_to_end(key)
        CACHE_STATS["reused"] += 1
    return entry


def summary_function(entry: dict, summary: Summary):
    """``(x, v, t, p) -> value`` of a summary formula, p the model's parameters (one Function
    per structure and formula, for every run's values)."""
    return formula_function(entry, summary.formula, f"--summary {summary.name}")


def formula_function(entry: dict, formula, where: str):
    """``(x, v, t, p) -> value`` of a formula in t, x_P, vx_P, ... and the parameters (or a
    number), cached with the entry's Model; p is the Model's ``parameter_vector`` (the plain
    numbers after the parameters: unused here)."""
    import casadi as ca

    from ..model.symbols import Symbols

    fun = entry["summaries"].get(formula)
    if fun is None:
        s = entry.get("symbols") or entry.setdefault(
            "symbols", Symbols(entry["model"].system, symbolic_parameters=True,
                               numbers=entry["model"].structure.n_numbers))
        expr = ca.SX(float(formula)) if isinstance(formula, int | float) else \
            ca.SX(expressions.parse(formula, s.state_names, where=where))
        fun = ca.Function("formula", [s.x, s.v, s.t, s.p], [expr])
        entry["summaries"][formula] = fun
    return fun


def _series(fun, traj, parameters) -> np.ndarray:
    n = len(traj.t)
    x = np.asarray(traj.x, float).reshape(n, -1).T
    v = np.asarray(traj.v, float).reshape(n, -1).T
    return np.asarray(fun.map(n)(x, v, np.asarray(traj.t, float)[None, :], parameters)).ravel()


def _reduce(values: np.ndarray, how: str) -> float:
    if how == "final":
        return float(values[-1])
    if how == "max":
        return float(np.max(values))
    if how == "min":
        return float(np.min(values))
    if how == "max_abs":
        return float(np.max(np.abs(values)))
    return float(np.mean(values))


def scene_for(task: dict, overrides: list[str]):
    """(raw dict, Scene) of the task's scene with the --set overrides and ``overrides``."""
    raw = load_raw(task["scene_text"], task["file"])
    raw = apply_overrides(raw, list(task["base_overrides"]) + list(overrides), file=task["file"])
    return raw, build_scene(raw, path=task["file"])


def solver_columns(options) -> dict[str, Any]:
    """The table's columns saying what ran: ``method`` (with its base tableau, e.g.
    ``dopri(DOP853)``), ``rtol``, ``atol``, ``dt`` (None when the steps are adaptive)."""
    base = options.method_options.get("base")
    return {"method": f"{options.method}({base})" if base else options.method,
            "rtol": float(options.rtol), "atol": float(options.atol),
            "dt": None if options.dt is None else float(options.dt)}


def _settings_kwargs(scene, outputs: set[str]) -> dict:
    """simulate's keywords for one variant, from the one map of settings (run_options).

    Variants share a model's structure, but the Functions the solvers build their step loops
    on hold each variant's parameter values, so a compiled step loop would be compiled again
    for each: "auto" means none here."""
    return options_of(scene, outputs).simulate_kwargs()


def options_of(scene, outputs: set[str]):
    from ..run.options import from_scene

    return from_scene(scene, outputs=outputs, compiled=scene.settings["compiled"] is True)


def _expect_columns(scene, traj, model) -> dict[str, Any]:
    """The scene's [expect] checks as columns: value and pass/fail."""
    from ..scene.load import check_expectations

    if not scene.expectations:
        return {}
    out: dict[str, Any] = {}
    for r in check_expectations(scene, traj, model):
        key = r.key if r.key.startswith("expect.") else f"expect.{r.key}"
        out[key] = float(r.value)
        out[f"{key}.ok"] = bool(r.ok)
    return out


def run_task(task: dict) -> dict:
    """Build the scene with the run's overrides, simulate, summarize. Never raises for a bad run
    (Ctrl-C raises KeyboardInterrupt: the run has no result).

    ``task``: the chunk's scene (``scene_text``, ``file``, ``base_overrides``, ``summaries``,
    ``save_trajectory``) with this run's ``run_id`` and ``overrides``. Returns {"run_id",
    "status", "row" (summary columns), "wall_time_s", "worker", "trajectory" (or None)}.
    """
    from ..run.simulate import simulate

    started = time.perf_counter()
    row: dict[str, Any] = {}
    traj = None
    try:
        raw, scene = scene_for(task, task["overrides"])
        s = scene.settings
        if s["t_end"] is None:
            raise SceneError("no end time: give t_end in [simulate] or vary/set simulate.t_end",
                             file=task["file"], key="simulate.t_end")
        entry = cached_model(raw, scene.system)
        model = entry["model"].with_parameters(scene.system.parameters)  # nothing rebuilt
        outputs = {"energy", "constraint_residual", "velocity_residual"}
        if scene.expectations:
            outputs |= set(expect_requirements(scene))
        if task["save_trajectory"]:
            outputs |= {q for q in scene.outputs.get("quantities", ())
                        if q in ("multipliers", "constraint_forces")}
        options = options_of(scene, outputs)
        # (a corrected start is in the run's info, not a warning per variant)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", InitialStateWarning)
            traj = simulate(scene.system, s["t_end"], model=model, **options.simulate_kwargs())
            row["t_final"] = float(traj.t[-1])
            names = traj.particle_names
            for i, p in enumerate(names):
                for k, axis in enumerate("xyz"):
                    row[f"{axis}_{p}"] = float(traj.x[-1, i, k])
                for k, axis in enumerate("xyz"):
                    row[f"v{axis}_{p}"] = float(traj.v[-1, i, k])
            for i, p in enumerate(names):
                for k, axis in enumerate("xyz"):
                    row[f"min_{axis}_{p}"] = float(np.min(traj.x[:, i, k]))
                    row[f"max_{axis}_{p}"] = float(np.max(traj.x[:, i, k]))
            if traj.energy is not None:
                row["energy_drift"] = float(np.max(np.abs(traj.energy - traj.energy[0])))
            if traj.constraint_residual is not None:
                row["max_constraint_residual"] = float(np.max(traj.constraint_residual))
            if traj.velocity_residual is not None:
                row["max_velocity_residual"] = float(np.max(traj.velocity_residual))
            for summary in task["summaries"]:
                values = _series(summary_function(entry, summary), traj, model.parameter_vector)
                row[summary.name] = _reduce(values, summary.reduction)
            row.update(_expect_columns(scene, traj, model))
        row["steps"] = int(traj.stats.get("steps", 0) or 0)
        row.update(solver_columns(options))
        status = "ok"
    except RunInterrupted:
        # Ctrl-C stops the sweep, not just this run: it has no result (a rerun computes it)
        raise KeyboardInterrupt from None
    except Exception as exc:  # a failing run is a row with its error; the sweep goes on
        status = message(exc)
    return {
        "run_id": task["run_id"],
        "status": status,
        "row": row,
        "wall_time_s": time.perf_counter() - started,
        "worker": worker_name(),
        "trajectory": traj if (task["save_trajectory"] and traj is not None and status == "ok") else None,
    }


def message(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if not isinstance(exc, InputError | ExpressionError) and type(exc).__module__ != "constrained.errors":
        text = f"{type(exc).__name__}: {text}"
    return text or type(exc).__name__


def worker_name() -> str:
    """``host:pid`` of this process (the table of a chunk says where it ran)."""
    return f"{os.uname().nodename}:{os.getpid()}"


def run_variants(task: dict) -> dict:
    """A chunk of variants on the per-run path: ``run_task`` for each of ``task["variants"]``
    ((index, run_id, overrides) triples). Returns {"rows": {run_id: {"status", "row"}},
    "trajectories": {run_id: Trajectory}, "interrupted", "wall_time_s", "worker"}; Ctrl-C
    ends the chunk with the runs finished before it (``interrupted`` True)."""
    started = time.perf_counter()
    rows: dict[str, dict] = {}
    trajectories: dict[str, Any] = {}
    interrupted = False
    for _index, rid, overrides in task["variants"]:
        try:
            result = run_task({**task, "run_id": rid, "overrides": overrides})
        except KeyboardInterrupt:
            interrupted = True
            break
        if unfinished(result):
            continue
        rows[rid] = {"status": result["status"], "row": result["row"]}
        if result.get("trajectory") is not None:
            trajectories[rid] = result["trajectory"]
    return {"rows": rows, "trajectories": trajectories, "interrupted": interrupted,
            "wall_time_s": time.perf_counter() - started, "worker": worker_name()}
