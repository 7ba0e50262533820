"""Parameter sweeps and ensembles: many runs of one scene, on Dask (or in this process).

``sweep(scene_path, ["parameters.a=lin(0.002, 0.02, 12)", "parameters.nu=[50, 100]"])`` runs
the scene once per point of the design and writes one summary row per run:

- ``DIR/runs/<run_id>.json`` as each run finishes (atomic; ``run_id`` is a hash of the run's
  overrides), ``DIR/runs/<run_id>.npz`` with the full trajectory only when asked;
- ``DIR/summary.csv`` (and ``DIR/summary.parquet`` when pyarrow is installed), rewritten
  periodically and at the end, rows in design order;
- ``DIR/sweep.json``, what the sweep is (scene hash, ``--set`` overrides, summaries): a
  second sweep into the same DIR must agree with it, and then skips every run whose
  ``runs/<run_id>.json`` exists, so an interrupted sweep run again loses nothing;
- ``DIR/sweep.png``: the summary against the parameter (1-D) or a map (2-D).

Specs (the part after ``KEY=``): a TOML value or list (``[1, 2, 3]``, ``0.5``), ``lin(a, b, n)``,
``log(a, b, n)`` (geometric), or a seeded random distribution ``uniform(a, b)``,
``normal(mu, sigma)``, ``loguniform(a, b)`` (these need ``samples``). Several specs make a full
grid (first key slowest); random specs draw ``samples`` points, crossed with the grid of the
others. Specs are read by a regular expression and :mod:`tomllib`, never ``eval``.

Where runs go: ``scheduler=None`` starts a ``distributed.LocalCluster`` (one single-threaded
worker process per core, listening on 127.0.0.1, no dashboard); ``"tcp://host:port"`` uses
an existing Dask cluster; a ``distributed.Client`` is used as it is; ``"sequential"`` runs
everything in this process, without Dask.

What a worker caches (module-level, per process, so per Dask worker): the assembled Model,
keyed by a hash of the scene *structure* (the scene after overrides, without particle
positions and velocities and without the [simulate], [outputs], [expect], [scene] and
[reduced] tables). Runs that only change the initial state or the run settings share one
Model; a run that changes a parameter, a mass, a constraint or an effect assembles its own
(parameters are numbers in the CasADi expressions). The compiled summary formulas are
cached with their Model. The cache holds at most ``MODEL_CACHE_SIZE`` Models.
"""

from __future__ import annotations

import csv
import hashlib
import io
import itertools
import json
import math
import os
import re
import sys
import time
import tomllib
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import expressions
from .errors import ExpressionError, InputError, RunInterrupted
from .scene import SceneError, apply_overrides, build_scene, expect_requirements, parse_override
from .trajectory import atomic_write

__all__ = [
    "Spec",
    "SweepResult",
    "Summary",
    "sweep",
    "parse_spec",
    "parse_vary",
    "parse_summary",
    "design",
    "run_id",
    "cell_edges",
    "boundary_function",
    "MODEL_CACHE_SIZE",
    "MAX_DESIGN_RUNS",
]

#: How many assembled Models one worker process keeps (least recently used dropped).
MODEL_CACHE_SIZE = 64
#: Seconds between rewrites of summary.csv while a sweep runs.
SUMMARY_EVERY_S = 10.0
#: The most runs one design may have (values of one spec, and grid x samples): a larger
#: design is refused before it is built (it would take minutes and gigabytes to list).
MAX_DESIGN_RUNS = 100_000

RANDOM = ("uniform", "normal", "loguniform")
RANGES = ("lin", "log")
REDUCTIONS = ("final", "max", "min", "max_abs", "mean")

# --- specs -----------------------------------------------------------------------------------

_CALL_RE = re.compile(r"\s*([A-Za-z_]\w*)\s*\((.*)\)\s*", re.S)
_NAME_RE = re.compile(r"[A-Za-z_]\w*")


@dataclass(frozen=True)
class Spec:
    """One ``--vary`` spec: ``kind`` is ``values``, ``lin``, ``log`` or a distribution name."""

    key: str
    text: str
    kind: str
    args: tuple = ()
    values: tuple = ()

    @property
    def random(self) -> bool:
        return self.kind in RANDOM

    @property
    def log(self) -> bool:
        return self.kind in ("log", "loguniform")

    def draw(self, rng: np.random.Generator, n: int) -> list[float]:
        a, b = self.args
        if self.kind == "uniform":
            out = rng.uniform(a, b, n)
        elif self.kind == "normal":
            out = rng.normal(a, b, n)
        else:
            out = np.exp(rng.uniform(math.log(a), math.log(b), n))
        return [float(v) for v in out]

    @property
    def name(self) -> str:
        """The last name of the key (``parameters.a`` -> ``a``), for formulas and axis labels."""
        names = _NAME_RE.findall(self.key)
        return names[-1] if names else self.key


#: How to get Dask: the extra from the package index, or from a source checkout.
DASK_INSTALL_HINT = ("pip install 'constrained[dask]' (from a source checkout: pip install '.[dask]' "
                     "in its top folder)")

def parse_spec(key: str, text: str) -> Spec:
    """Read one spec (see the module doc); an InputError says what is wrong."""
    where = f"--vary {key}={text}"
    m = _CALL_RE.fullmatch(text)
    if m:
        fn, inner = m.group(1), m.group(2)
        known = RANGES + RANDOM
        if fn not in known:
            raise InputError(f"unknown spec function '{fn}' (known: {', '.join(f + '(...)' for f in known)}, "
                             "or a list of values like [1, 2, 3])", where=where)
        parts = [p.strip() for p in inner.split(",")]
        want = 3 if fn in RANGES else 2
        if len(parts) != want or not all(parts):
            usage = {"lin": "lin(start, stop, n)", "log": "log(start, stop, n)",
                     "uniform": "uniform(low, high)",
                     "normal": "normal(mean, sigma)", "loguniform": "loguniform(low, high)"}[fn]
            raise InputError(f"'{fn}' takes {want} numbers: {usage}", where=where)
        nums = []
        for p in parts:
            try:
                v = float(p)
            except ValueError:
                raise InputError(f"'{p}' is not a number (spec arguments must be plain numbers)",
                                 where=where) from None
            if not math.isfinite(v):
                raise InputError(f"'{p}' is not finite", where=where)
            nums.append(v)
        if fn in RANGES:
            n = nums[2]
            if n != int(n) or n < 1:
                raise InputError(f"the number of values must be a whole number >= 1, got {parts[2]}",
                                 where=where)
            n = int(n)
            if n > MAX_DESIGN_RUNS:
                raise InputError(f"{n} values is more than the {MAX_DESIGN_RUNS} runs a sweep may have; "
                                 "use fewer values (or several sweeps)", where=where)
            a, b = nums[0], nums[1]
            if fn == "log":
                if a <= 0 or b <= 0:
                    raise InputError("a log range needs positive start and stop", where=where)
                vals = np.geomspace(a, b, n) if n > 1 else np.array([a])
            else:
                vals = np.linspace(a, b, n) if n > 1 else np.array([a])
            return Spec(key, text, fn, (a, b, n), tuple(float(v) for v in vals))
        a, b = nums
        if fn == "normal" and b < 0:
            raise InputError("sigma must be >= 0", where=where)
        if fn in ("uniform", "loguniform") and not a < b:
            raise InputError(f"'{fn}' needs low < high, got {parts[0]} and {parts[1]}", where=where)
        if fn == "loguniform" and a <= 0:
            raise InputError("'loguniform' needs positive bounds", where=where)
        return Spec(key, text, fn, (a, b))
    try:
        value = tomllib.loads(f"value = {text}")["value"]
    except tomllib.TOMLDecodeError:
        raise InputError(
            f"cannot read the spec {text!r}: give a list [1, 2, 3], lin(start, stop, n), "
            "log(start, stop, n), "
            "uniform(low, high), normal(mean, sigma) or loguniform(low, high)", where=where) from None
    values = value if isinstance(value, list) else [value]
    if not values:
        raise InputError("the list of values is empty", where=where)
    return Spec(key, text, "values", (), tuple(values))


def parse_vary(text: str) -> Spec:
    """``"KEY=SPEC"`` -> Spec. KEY uses the ``--set`` syntax."""
    if not isinstance(text, str) or "=" not in text:
        raise InputError(f"--vary {text!r}: expected KEY=SPEC, e.g. parameters.k=lin(1, 10, 5)")
    key, spec = text.split("=", 1)
    key = key.strip()
    try:
        parse_override(f"{key}=0")
    except SceneError:
        raise InputError(f"--vary {text!r}: {key!r} is not a key path (write e.g. parameters.k, "
                         "particles.p1.mass or particles[0].position[1])") from None
    return parse_spec(key, spec.strip())


def design(specs: Sequence[Spec], samples: int | None = None, seed: int = 0) -> list[dict[str, Any]]:
    """The runs: a list of {key: value}. Grid of the fixed specs x ``samples`` random draws."""
    fixed = [s for s in specs if not s.random]
    rand = [s for s in specs if s.random]
    if rand and samples is None:
        raise InputError(f"--vary {rand[0].key}={rand[0].text}: a random spec needs --samples N")
    if samples is not None:
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
            raise InputError(f"--samples must be a whole number >= 1, got {samples!r}")
        if not rand:
            raise InputError("--samples needs at least one random spec (uniform, normal, loguniform)")
    size = math.prod(len(s.values) for s in fixed) * (samples if rand else 1)
    if size > MAX_DESIGN_RUNS:
        counts = " x ".join([str(len(s.values)) for s in fixed] + ([f"{samples} samples"] if rand else []))
        raise InputError(f"the design has {size} runs ({counts}), more than the {MAX_DESIGN_RUNS} a sweep "
                         "may have; use fewer values or samples (or split it into several sweeps)")
    keys = [s.key for s in specs]
    if len(set(keys)) != len(keys):
        dup = next(k for k in keys if keys.count(k) > 1)
        raise InputError(f"--vary {dup}: the key is varied twice")
    draws: list[dict[str, Any]] = [{}]
    if rand:
        rng = np.random.default_rng(seed)
        cols = {s.key: s.draw(rng, samples) for s in rand}
        draws = [{k: cols[k][i] for k in cols} for i in range(samples)]
    runs = []
    for combo in itertools.product(*(s.values for s in fixed)):
        base = dict(zip([s.key for s in fixed], combo, strict=True))
        for d in draws:
            point = {**base, **d}
            runs.append({k: point[k] for k in keys})
    return runs


def toml_value(value) -> str:
    """A value as TOML text that reads back exactly (floats by repr)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        v = float(value)
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        text = repr(v)
        return text if any(c in text for c in ".eE") else text + ".0"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise InputError(f"cannot write {value!r} as a scene value")


def overrides_of(point: dict[str, Any]) -> list[str]:
    return [f"{k}={toml_value(v)}" for k, v in point.items()]


def run_id(point: dict[str, Any]) -> str:
    """A stable id of one run: a hash of its overrides (16 hex digits)."""
    text = "\n".join(overrides_of(point))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


# --- summaries -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Summary:
    """A user-named scalar: ``reduction:NAME=FORMULA`` (reduction ``final`` when left out)."""

    name: str
    formula: str
    reduction: str = "final"

    @property
    def text(self) -> str:
        return f"{self.reduction}:{self.name}={self.formula}"


def parse_summary(text: str) -> Summary:
    """``[REDUCTION:]NAME=FORMULA``; REDUCTION one of final, max, min, max_abs, mean."""
    where = f"--summary {text!r}"
    if not isinstance(text, str) or "=" not in text:
        raise InputError("expected NAME=FORMULA or REDUCTION:NAME=FORMULA, "
                         "e.g. max_abs:theta=atan2(x_bob, -y_bob)",
                         where=where)
    head, formula = text.split("=", 1)
    reduction = "final"
    if ":" in head:
        reduction, head = (p.strip() for p in head.split(":", 1))
        if reduction not in REDUCTIONS:
            raise InputError(f"unknown reduction '{reduction}' (known: {', '.join(REDUCTIONS)})", where=where)
    name = head.strip()
    if not name.isidentifier():
        raise InputError(f"the summary name {name!r} must be a plain identifier", where=where)
    if not formula.strip():
        raise InputError("the formula is empty", where=where)
    return Summary(name, formula.strip(), reduction)


# --- one run (executed on a worker) ----------------------------------------------------------

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


def _cached_model(raw: dict, system):
    from .model import assemble

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


def _summary_function(entry: dict, summary: Summary):
    """``(x, v, t, p) -> value`` of a summary formula, p the model's parameters (one Function
    per structure and formula, for every run's values)."""
    import casadi as ca

    from .symbols import Symbols

    fun = entry["summaries"].get(summary.formula)
    if fun is None:
        s = entry.get("symbols") or entry.setdefault(
            "symbols", Symbols(entry["model"].system, symbolic_parameters=True))
        expr = ca.SX(expressions.parse(summary.formula, s.state_names, where=f"--summary {summary.name}"))
        fun = ca.Function(f"summary_{summary.name}", [s.x, s.v, s.t, s.p], [expr])
        entry["summaries"][summary.formula] = fun
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


def _load_raw(scene_text: str, file: str) -> dict:
    try:
        return tomllib.loads(scene_text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"not valid TOML: {exc}", file=file) from None


def _scene_for(task: dict):
    raw = _load_raw(task["scene_text"], task["file"])
    raw = apply_overrides(raw, list(task["base_overrides"]) + list(task["overrides"]), file=task["file"])
    return raw, build_scene(raw, path=task["file"])


def _settings_kwargs(scene, outputs: set[str]) -> dict:
    """simulate's keywords for one variant, from the one map of settings (run_options).

    Variants share a model's structure, but the Functions the solvers build their step loops
    on hold each variant's parameter values, so a compiled step loop would be compiled again
    for each: "auto" means none here."""
    from .run_options import from_scene

    return from_scene(scene, outputs=outputs, compiled=scene.settings["compiled"] is True).simulate_kwargs()


def _expect_columns(scene, traj, model) -> dict[str, Any]:
    """The scene's [expect] checks as columns: value and pass/fail."""
    from .scene import check_expectations

    if not scene.expectations:
        return {}
    out: dict[str, Any] = {}
    for r in check_expectations(scene, traj, model):
        key = r.key if r.key.startswith("expect.") else f"expect.{r.key}"
        out[key] = float(r.value)
        out[f"{key}.ok"] = bool(r.ok)
    return out


def run_task(task: dict) -> dict:
    """Build the scene with the run's overrides, simulate, summarize. Never raises for a bad run.

    Returns {"run_id", "row" (summary columns), "wall_time_s", "worker", "trajectory" (or None)}.
    """
    from .simulate import simulate

    started = time.perf_counter()
    row: dict[str, Any] = {}
    traj = None
    try:
        raw, scene = _scene_for(task)
        s = scene.settings
        if s["t_end"] is None:
            raise SceneError("no end time: give t_end in [simulate] or vary/set simulate.t_end",
                             file=task["file"], key="simulate.t_end")
        entry = _cached_model(raw, scene.system)
        model = entry["model"].with_parameters(scene.system.parameters)  # nothing rebuilt
        outputs = {"energy", "constraint_residual", "velocity_residual"}
        if scene.expectations:
            outputs |= set(expect_requirements(scene))
        if task["save_trajectory"]:
            outputs |= {q for q in scene.outputs.get("quantities", ())
                        if q in ("multipliers", "constraint_forces")}
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            traj = simulate(scene.system, s["t_end"], model=model, **_settings_kwargs(scene, outputs))
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
                values = _series(_summary_function(entry, summary), traj, model.parameter_values)
                row[summary.name] = _reduce(values, summary.reduction)
            row.update(_expect_columns(scene, traj, model))
        row["steps"] = int(traj.stats.get("steps", 0) or 0)
        status = "ok"
    except RunInterrupted:
        # Ctrl-C stops the sweep, not just this run: it has no result (a rerun computes it)
        raise KeyboardInterrupt from None
    except Exception as exc:  # a failing run is a row with its error; the sweep goes on
        status = _message(exc)
    return {
        "run_id": task["run_id"],
        "status": status,
        "row": row,
        "wall_time_s": time.perf_counter() - started,
        "worker": f"{os.uname().nodename}:{os.getpid()}",
        "trajectory": traj if (task["save_trajectory"] and traj is not None and status == "ok") else None,
    }


def _unfinished(record: dict) -> bool:
    """Whether a result or record is of a run stopped by Ctrl-C (earlier versions recorded
    those as failed runs): it has no result, so it is not kept and a rerun computes it."""
    status = str(record.get("status", ""))
    return (status.startswith("interrupted") or "the run was interrupted" in status
            or "KeyboardInterrupt" in status)


def _message(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if not isinstance(exc, InputError | ExpressionError) and type(exc).__module__ != "constrained.errors":
        text = f"{type(exc).__name__}: {text}"
    return text or type(exc).__name__


# --- the sweep -------------------------------------------------------------------------------


@dataclass
class SweepResult:
    """A finished (or stopped) sweep: the table and what was done.

    ``rows`` (list of dicts, design order, only runs that have a result), ``columns``,
    ``computed`` (runs computed by this call), ``skipped`` (results found in DIR and reused),
    ``failed`` (rows whose status is not ``ok``), ``total`` (runs in the design),
    ``paths`` (files written), ``wall_time_s``, ``specs``, ``design``.
    """

    out_dir: Path
    specs: list[Spec]
    design: list[dict]
    rows: list[dict]
    columns: list[str]
    computed: int
    skipped: int
    wall_time_s: float
    paths: list[Path] = field(default_factory=list)
    workers: int = 1

    @property
    def total(self) -> int:
        return len(self.design)

    @property
    def failed(self) -> int:
        return sum(1 for r in self.rows if r.get("status") != "ok")

    @property
    def complete(self) -> bool:
        return len(self.rows) == len(self.design)

    def column(self, name: str) -> np.ndarray:
        """One column as an array (floats where possible; NaN where a run has no value)."""
        if name not in self.columns:
            raise InputError(f"no column '{name}' in the sweep table (columns: {', '.join(self.columns)})")
        values = [r.get(name) for r in self.rows]
        try:
            return np.array([np.nan if v is None else v for v in values], dtype=float)
        except (TypeError, ValueError):
            return np.array(values, dtype=object)

    def to_pandas(self):
        import pandas as pd

        return pd.DataFrame(self.rows, columns=self.columns)


def sweep(
    scene_path,
    vary: Sequence[str],
    *,
    samples: int | None = None,
    seed: int = 0,
    scheduler=None,
    out_dir=None,
    overrides: Iterable[str] = (),
    summary: Sequence[str] = (),
    save_trajectories: bool = False,
    progress: bool = True,
    limit: int | None = None,
    workers: int | None = None,
    plot: str | None = None,
    boundary: str | None = None,
    figure: bool = True,
) -> SweepResult:
    """Run the scene at every point of the design given by ``vary`` (``KEY=SPEC`` strings).

    ``scheduler``: None (local Dask cluster, ``workers`` processes, default one per core),
    a ``tcp://HOST:PORT`` address, a ``distributed.Client``, or ``"sequential"``.
    ``summary``: ``[REDUCTION:]NAME=FORMULA`` columns (formulas in t, x_NAME, vx_NAME, ...
    and the scene's parameters; reductions final, max, min, max_abs, mean over the samples).
    ``limit``: compute at most this many missing runs, then stop (the rest stay missing).
    ``plot``: the column the figure shows (default: the first summary, else energy_drift);
    ``boundary``: a formula in the varied keys' last names and the parameters whose zero
    contour is drawn on a 2-D map. Bad input raises InputError (SceneError for the scene).
    """
    started = time.perf_counter()
    path = Path(scene_path)
    file = str(scene_path)
    if not path.is_file():
        raise SceneError("no such file" if not path.exists() else "is not a file", file=file)
    scene_bytes = path.read_bytes()
    try:
        scene_text = scene_bytes.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError(f"not UTF-8 text (byte {exc.start})", file=file) from None
    overrides = list(overrides)
    if not vary:
        raise InputError("give at least one --vary KEY=SPEC")
    specs = [parse_vary(v) for v in vary]
    points = design(specs, samples, seed)
    summaries = [parse_summary(s) for s in summary]
    names = [s.name for s in summaries]
    if len(set(names)) != len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise InputError(f"--summary: the name '{twice}' is used twice")
    _validate(scene_text, file, overrides, specs, points[0], summaries)
    out = Path(out_dir) if out_dir is not None else Path("out") / (path.stem + "_sweep")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a directory")
    manifest = {
        "scene": file,
        "scene_sha256": hashlib.sha256(scene_bytes).hexdigest(),
        "overrides": overrides,
        "summaries": [s.text for s in summaries],
        "trajectories": bool(save_trajectories),
    }
    _check_manifest(out, manifest)
    runs_dir = out / "runs"
    ids = [run_id(p) for p in points]
    if len(set(ids)) != len(ids):
        raise InputError("the design has repeated points (the same values twice); remove the duplicates")
    done: dict[str, dict] = {}
    for rid in ids:
        record = _read_record(runs_dir / f"{rid}.json")
        if record is not None and not _unfinished(record) and (
                not save_trajectories or record["status"] != "ok" or (runs_dir / f"{rid}.npz").is_file()):
            done[rid] = record
    todo = [i for i, rid in enumerate(ids) if rid not in done]
    if limit is not None:
        todo = todo[: max(int(limit), 0)]
    skipped = len(done)
    out.mkdir(parents=True, exist_ok=True)
    runs_dir.mkdir(exist_ok=True)
    manifest_full = {**manifest, "vary": [f"{s.key}={s.text}" for s in specs], "samples": samples,
                     "seed": seed}
    _write_json(out / "sweep.json", manifest_full)

    tasks = [
        {
            "run_id": ids[i],
            "index": i,
            "scene_text": scene_text,
            "file": file,
            "base_overrides": overrides,
            "overrides": overrides_of(points[i]),
            "summaries": summaries,
            "save_trajectory": bool(save_trajectories),
        }
        for i in todo
    ]
    index_of = {rid: i for i, rid in enumerate(ids)}
    paths: list[Path] = []
    last_write = [time.monotonic()]

    def record(result: dict) -> None:
        if _unfinished(result):
            return
        rid = result["run_id"]
        i = index_of[rid]
        traj = result.pop("trajectory", None)
        if traj is not None:
            traj.save(runs_dir / f"{rid}.npz")
        rec = {
            "run_id": rid,
            "index": i,
            "values": points[i],
            "overrides": overrides_of(points[i]),
            "status": result["status"],
            "row": result["row"],
            "wall_time_s": result["wall_time_s"],
            "worker": result["worker"],
        }
        _write_json(runs_dir / f"{rid}.json", rec)
        done[rid] = rec
        if time.monotonic() - last_write[0] > SUMMARY_EVERY_S:
            _write_table(out, specs, points, ids, done, parquet=False)
            last_write[0] = time.monotonic()

    try:
        n_workers = _execute(tasks, record, scheduler, progress=progress, workers=workers)
    except BaseException:  # interrupted: the finished runs are in runs/; leave a table of them too
        if done:
            _write_table(out, specs, points, ids, done, parquet=False)
        raise
    rows, columns = _table(specs, points, ids, done)
    paths += _write_table(out, specs, points, ids, done, parquet=True)
    result = SweepResult(out, specs, points, rows, columns, computed=len(tasks), skipped=skipped,
                         wall_time_s=0.0, paths=paths, workers=n_workers)
    if figure and result.rows:
        try:
            fig = save_sweep_figure(result, out / "sweep.png", column=plot, boundary=boundary,
                                    scene_text=scene_text, file=file, overrides=overrides)
        except ImportError:
            fig = None
        if fig is not None:
            paths.append(fig)
    result.wall_time_s = time.perf_counter() - started
    return result


def _validate(scene_text: str, file: str, overrides: list[str], specs: list[Spec], first: dict,
              summaries: list[Summary]) -> None:
    """Apply the first point of the design to the scene and build it: bad keys fail here."""
    raw = _load_raw(scene_text, file)
    base = apply_overrides(raw, overrides, file=file)
    try:
        build_scene(base, path=file)
    except SceneError as exc:
        raise SceneError(f"{exc.reason} (with the --set overrides)", file=file, key=exc.key) from None
    for spec in specs:
        tokens, _ = parse_override(f"{spec.key}=0", file=file)
        params = base.get("parameters", {})
        if tokens and tokens[0] == "parameters" and len(tokens) == 2 and tokens[1] not in params:
            known = ", ".join(params) or "none"
            raise SceneError(f"--vary {spec.key}: the scene has no parameter '{tokens[1]}' "
                             f"(parameters: {known})",
                             file=file, key=spec.key)
        try:
            raw1 = apply_overrides(base, [f"{spec.key}={toml_value(first[spec.key])}"], file=file)
            build_scene(raw1, path=file)
        except SceneError as exc:
            raise SceneError(f"--vary {spec.key}={spec.text}: {exc.reason}", file=file,
                             key=exc.key or spec.key) from None
    try:
        raw1 = apply_overrides(base, overrides_of(first), file=file)
        scene = build_scene(raw1, path=file)
    except SceneError as exc:
        raise SceneError(f"the first run of the sweep ({', '.join(overrides_of(first))}): {exc.reason}",
                         file=file, key=exc.key) from None
    if scene.settings["t_end"] is None:
        raise SceneError("no end time: give t_end in [simulate], or --set simulate.t_end=...",
                         file=file, key="simulate.t_end")
    if summaries:
        from .symbols import Symbols

        names = Symbols(scene.system).state_names
        for s in summaries:
            try:
                expressions.parse(s.formula, names, where=f"--summary {s.name}")
            except ExpressionError as exc:
                raise InputError(f"{exc} (names: t, x_P, y_P, z_P, vx_P, ... of the particles "
                                 f"{', '.join(scene.system.names)}, and the parameters)") from None


def _check_manifest(out: Path, manifest: dict) -> None:
    path = out / "sweep.json"
    if not path.is_file():
        return
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    for key, what in (("scene_sha256", "the scene file"), ("overrides", "the --set overrides"),
                      ("summaries", "the --summary columns")):
        if old.get(key) != manifest[key]:
            raise InputError(
                f"--out {out} holds the results of a different sweep ({what} changed); its runs cannot "
                "be reused. Use another --out directory, or delete this one")


def _read_record(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        rec = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) and "row" in rec and "status" in rec else None


def _write_json(path: Path, data: dict) -> None:
    text = json.dumps(data, indent=1, default=_json_default)
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return repr(value)


def _table(specs, points, ids, done) -> tuple[list[dict], list[str]]:
    keys = [s.key for s in specs]
    rows, metric_cols = [], []
    seen = set()
    for i, rid in enumerate(ids):
        rec = done.get(rid)
        if rec is None:
            continue
        row = {"run": i, "run_id": rid}
        for k in keys:
            row[k] = points[i][k]
        row["status"] = rec["status"]
        for c, v in rec["row"].items():
            if c not in seen:
                seen.add(c)
                metric_cols.append(c)
            row[c] = v
        rows.append(row)
    return rows, ["run", "run_id", *keys, "status", *metric_cols]


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, list | dict):
        return json.dumps(v)
    return str(v)


def _write_table(out: Path, specs, points, ids, done, *, parquet: bool) -> list[Path]:
    rows, columns = _table(specs, points, ids, done)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in columns])
    text = buf.getvalue()
    path = out / "summary.csv"
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))
    written = [path]
    if parquet:
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            return written
        data = {}
        for c in columns:
            vals = [r.get(c) for r in rows]
            if any(isinstance(v, list | dict) for v in vals):
                vals = [None if v is None else json.dumps(v) for v in vals]
            elif any(isinstance(v, float) for v in vals) and all(
                    v is None or (isinstance(v, int | float) and not isinstance(v, bool)) for v in vals):
                vals = [None if v is None else float(v) for v in vals]
            data[c] = vals
        try:
            table = pa.table(data)
        except (pa.ArrowInvalid, pa.ArrowTypeError):
            table = pa.table({c: [None if v is None else _cell(v) for v in vs] for c, vs in data.items()})
        ppath = out / "summary.parquet"
        atomic_write(ppath, lambda f: pq.write_table(table, f))
        written.append(ppath)
    return written


# --- execution -------------------------------------------------------------------------------


def _execute(tasks: list[dict], record, scheduler, *, progress: bool, workers: int | None) -> int:
    """Run the tasks; ``record(result)`` on this process as each finishes. Returns the worker count."""
    if scheduler == "sequential":
        bar = _Progress(len(tasks), progress)
        try:
            for task in tasks:
                record(run_task(task))
                bar.update()
        finally:
            bar.close()
        return 1
    try:
        import distributed
    except ImportError:
        raise InputError(f"Dask is not installed: {DASK_INSTALL_HINT}, or use --scheduler "
                         "sequential") from None
    own_cluster = own_client = None
    if scheduler is None:
        if not tasks:
            return 0
        n = workers or os.cpu_count() or 1
        # no dashboard: dashboard_address=None alone still serves HTTP on :8787 (and warns when
        # that port is taken); a free loopback port, and dashboard=False serves no pages on it
        own_cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                               dashboard_address="127.0.0.1:0", host="127.0.0.1",
                                               scheduler_kwargs={"dashboard": False})
        client = own_client = distributed.Client(own_cluster)
    elif isinstance(scheduler, str):
        if not re.fullmatch(r"(tcp|tls|inproc|ucx)://\S+", scheduler):
            raise InputError(f"--scheduler {scheduler!r}: expected tcp://HOST:PORT, or 'sequential'")
        try:
            client = own_client = distributed.Client(scheduler, timeout=20)
        except (OSError, TimeoutError) as exc:
            raise InputError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})") from None
    else:
        client = scheduler
    try:
        n_workers = len(client.scheduler_info().get("workers", {}))
        if not tasks:
            return n_workers
        futures = [client.submit(run_task, task, pure=False) for task in tasks]
        bar = _Progress(len(tasks), progress)
        try:
            for fut in distributed.as_completed(futures):
                try:
                    result = fut.result()
                except Exception as exc:  # the task itself died (worker lost): record it
                    task = tasks[futures.index(fut)]
                    result = {"run_id": task["run_id"], "status": f"worker failure: {_message(exc)}",
                              "row": {}, "wall_time_s": float("nan"), "worker": "?"}
                record(result)
                fut.release()
                bar.update()
        except BaseException:
            client.cancel(futures)
            raise
        finally:
            bar.close()
        return n_workers
    finally:
        if own_client is not None:
            own_client.close()
        if own_cluster is not None:
            own_cluster.close()


class _Progress:
    """A tqdm bar on stderr when tqdm is installed, else a line every 10 % (off when quiet)."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.n, self.bar = total, 0, None
        self.enabled = enabled and total > 0
        if self.enabled:
            try:
                from tqdm import tqdm

                self.bar = tqdm(total=total, desc="sweep", unit="run", file=sys.stderr)
            except ImportError:
                self.bar = None

    def update(self) -> None:
        self.n += 1
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(1)
        elif self.n == self.total or self.n % max(1, self.total // 10) == 0:
            print(f"sweep: {self.n}/{self.total} runs", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# --- figures ---------------------------------------------------------------------------------


def cell_edges(values: Sequence[float], log: bool = False) -> np.ndarray:
    """Edges of the cells around grid values: midpoints (geometric when ``log``), outer half cells."""
    v = np.asarray(values, float)
    if len(v) == 1:
        return np.array([v[0] * 0.9, v[0] * 1.1]) if log else np.array([v[0] - 0.5, v[0] + 0.5])
    w = np.log(v) if log else v
    mid = 0.5 * (w[1:] + w[:-1])
    edges = np.concatenate([[w[0] - (mid[0] - w[0])], mid, [w[-1] + (w[-1] - mid[-1])]])
    return np.exp(edges) if log else edges


def boundary_function(formula: str, axes: Sequence[str], parameters: dict[str, float]):
    """A vectorized f(*axis arrays) from a formula in the axis names and parameters (no eval)."""
    import casadi as ca

    syms = {n: ca.SX.sym(n) for n in axes}
    names = {**{k: float(v) for k, v in parameters.items()}, **syms}
    expr = ca.SX(expressions.parse(formula, names, where="--boundary"))
    fun = ca.Function("boundary", [syms[n] for n in axes], [expr])

    def f(*arrays):
        shape = np.shape(arrays[0])
        flat = [np.asarray(a, float).ravel()[None, :] for a in arrays]
        return np.asarray(fun.map(flat[0].shape[1])(*flat)).reshape(shape)

    return f


#: units of the scene keys a sweep can vary, by the key's last name (parameters: [scene] units)
KEY_UNITS = {"t_end": "s", "t_start": "s", "dt": "s", "output_dt": "s", "mass": "kg", "position": "m",
             "velocity": "m/s", "length": "m", "rest": "m", "offset": "m", "point": "m", "k": "N/m",
             "coefficient": "N·s/m", "g": "m/s²", "charge": "C"}


def axis_label(key: str, units: dict | None = None) -> str:
    """``"a [m]"`` for ``parameters.a`` with ``units = {a = "m"}``; known keys get their SI unit
    (``particles.p1.mass [kg]``); a summary column is looked up in ``units`` by its name."""
    units = units or {}
    parts = re.split(r"[.\[\]]+", key.strip("."))
    names = [p for p in parts if p and not p.isdigit()]
    last = names[-1] if names else key
    if key.startswith("parameters."):
        unit = units.get(last)
        return f"{last} [{unit}]" if unit else f"{last} (parameter)"
    unit = units.get(key) or (KEY_UNITS.get(last) if "." in key else None)
    return f"{key} [{unit}]" if unit else key


def save_sweep_figure(result: SweepResult, path, *, column: str | None = None, boundary: str | None = None,
                      scene_text: str | None = None, file: str = "scene", overrides=()) -> Path | None:
    """1-D: ``column`` against the parameter; 2-D grid: a map, with the zero contour of ``boundary``."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    specs = [s for s in result.specs if len(set(map(repr, s.values))) > 1 or s.random]
    if column is None:
        metric = [c for c in result.columns[result.columns.index("status") + 1:]]
        user = [c for c in metric if not c.startswith(("x_", "y_", "z_", "vx_", "vy_", "vz_", "min_", "max_"))
                and c not in ("t_final", "energy_drift", "max_constraint_residual", "max_velocity_residual",
                              "steps")]
        column = user[0] if user else ("energy_drift" if "energy_drift" in metric else (metric or [None])[0])
    if column is None or column not in result.columns or len(specs) not in (1, 2):
        return None
    z = result.column(column)
    if z.dtype == object:
        return None
    if any(not all(isinstance(v, int | float) for v in (s.values or (0.0,))) for s in specs):
        return None
    units = {}
    if scene_text is not None:
        scene_table = _load_raw(scene_text, file).get("scene", {})
        units = scene_table.get("units", {}) if isinstance(scene_table, dict) else {}
    fig, ax = plt.subplots(figsize=(6.4, 4.8), constrained_layout=True)
    if len(specs) == 1:
        s = specs[0]
        x = np.array([r[s.key] for r in result.rows], float)
        order = np.argsort(x)
        ax.plot(x[order], z[order], "o-", ms=3)
        ax.set_xlabel(axis_label(s.key, units))
        ax.set_ylabel(axis_label(column, units))
        if s.log:
            ax.set_xscale("log")
        ax.grid(True, alpha=0.3)
    else:
        sx, sy = specs[1], specs[0]  # the second key across, the first up
        if sx.random or sy.random:
            xs = np.array([r[sx.key] for r in result.rows], float)
            ys = np.array([r[sy.key] for r in result.rows], float)
            im = ax.scatter(xs, ys, c=z, cmap="viridis", s=20)
            gx = np.linspace(xs.min(), xs.max(), 200)
            gy = np.linspace(ys.min(), ys.max(), 200)
        else:
            Z = np.full((len(sy.values), len(sx.values)), np.nan)
            jx = {v: j for j, v in enumerate(sx.values)}
            iy = {v: i for i, v in enumerate(sy.values)}
            for r, val in zip(result.rows, z, strict=True):
                Z[iy[r[sy.key]], jx[r[sx.key]]] = val
            ex, ey = cell_edges(sx.values, sx.log), cell_edges(sy.values, sy.log)
            finite = Z[np.isfinite(Z)]
            norm = None
            if finite.size and finite.min() < 0 < finite.max():
                norm = TwoSlopeNorm(0.0, finite.min(), finite.max())
            im = ax.pcolormesh(ex, ey, Z, cmap="RdBu" if norm is not None else "viridis", norm=norm,
                               shading="flat")
            gx = np.geomspace(ex[0], ex[-1], 400) if sx.log else np.linspace(ex[0], ex[-1], 400)
            gy = np.geomspace(ey[0], ey[-1], 400) if sy.log else np.linspace(ey[0], ey[-1], 400)
        fig.colorbar(im, ax=ax, label=axis_label(column, units))
        if boundary:
            params = {}
            if scene_text is not None:
                raw = apply_overrides(_load_raw(scene_text, file), list(overrides), file=file)
                params = {k: v for k, v in raw.get("parameters", {}).items() if isinstance(v, int | float)}
            fb = boundary_function(boundary, [sx.name, sy.name], params)
            GX, GY = np.meshgrid(gx, gy)
            ax.contour(GX, GY, fb(GX, GY), levels=[0.0], colors="k", linewidths=1.5)
            ax.plot([], [], "k-", label=f"{boundary} = 0")
            ax.legend(loc="upper right", fontsize=8)
        ax.set_xlabel(axis_label(sx.key, units))
        ax.set_ylabel(axis_label(sy.key, units))
        if sx.log:
            ax.set_xscale("log")
        if sy.log:
            ax.set_yscale("log")
    ax.set_title(f"sweep: {column} ({len(result.rows)} runs)", fontsize=10)
    path = Path(path)
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=120))
    plt.close(fig)
    return path
