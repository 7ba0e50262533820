"""Parameter sweeps and ensembles: many runs of one scene, in chunks, here or on Dask.

``sweep(scene_path, ["parameters.a=lin(0.002, 0.02, 12)", "parameters.nu=[50, 100]"])`` runs
the scene once per point of the design and writes one summary row per run:

- ``DIR/chunks/<chunk_id>.parquet`` as each chunk of variants finishes (atomic;
  constrained.sweep_store), ``DIR/runs/<run_id>.npz`` with the full trajectory only when asked;
- ``DIR/summary.csv`` (and ``DIR/summary.parquet`` when pyarrow is installed), assembled
  from the chunk files in design order, rewritten periodically and at the end;
- ``DIR/sweep.json``, what the sweep is (scene hash, ``--set`` overrides, summaries): a
  second sweep into the same DIR must agree with it, and then skips every variant found in
  a chunk file, so an interrupted sweep run again loses nothing;
- ``DIR/sweep.png``: the summary against the parameter (1-D) or a map (2-D).

The design (constrained.sweep_design): ``--vary`` specs (grid x random draws) and/or the
rows of a ``--design`` file. How variants run (constrained.sweep_execute): variants that
differ only in [parameters] values run *batched*, a chunk per ``simulate_many`` call
(constrained.sweep_batch); the others one run each (constrained.sweep_run); chunks run in
this process or on Dask, chosen by the estimated work unless ``scheduler`` says.
"""

from __future__ import annotations

import hashlib
import re
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ExpressionError, InputError
from ..model import expressions
from ..scene.load import SceneError, apply_overrides, build_scene, parse_override
from .batch import BATCH_SAMPLES, batch_blocker
from .design import (
    MAX_DESIGN_RUNS,
    Spec,
    Summary,
    design,
    load_raw,
    overrides_of,
    parse_spec,
    parse_summary,
    parse_vary,
    read_design_file,
    run_id,
    toml_value,
)
from .execute import DASK_INSTALL_HINT, RUN_CHUNK, Chunk, Where, execute, plan
from .per_run import _MODEL_CACHE, CACHE_STATS, MODEL_CACHE_SIZE, _settings_kwargs, run_task, structure_key
from .plot import axis_label, boundary_function, cell_edges, save_sweep_figure
from .store import (
    check_manifest,
    read_done,
    read_legacy_records,
    summary_columns,
    summary_rows,
    write_chunk,
    write_json,
    write_table,
)

__all__ = [
    "Spec",
    "SweepResult",
    "Summary",
    "sweep",
    "parse_spec",
    "parse_vary",
    "parse_summary",
    "design",
    "read_design_file",
    "run_id",
    "cell_edges",
    "boundary_function",
    "axis_label",
    "save_sweep_figure",
    "MODEL_CACHE_SIZE",
    "MAX_DESIGN_RUNS",
    "BATCH_SAMPLES",
    "DASK_INSTALL_HINT",
]

# names older code imported from here
_REEXPORTED = (_MODEL_CACHE, CACHE_STATS, _settings_kwargs, run_task, structure_key, toml_value)

#: Seconds between rewrites of summary.csv while a sweep runs.
SUMMARY_EVERY_S = 10.0


@dataclass
class SweepResult:
    """A finished (or stopped) sweep: the table and what was done.

    ``rows`` (list of dicts, design order, only runs that have a result) and ``columns`` are
    read from the chunk files in DIR when first asked for (a sweep holds no rows while it
    runs: its memory is flat in the number of variants); ``column(name)`` streams one
    column. ``finished`` (runs with a result), ``failed`` (those whose status is not ``ok``),
    ``computed`` (runs computed by this call), ``skipped`` (results found in DIR and reused),
    ``total`` (runs in the design), ``paths`` (files written), ``wall_time_s``, ``specs``,
    ``design``; ``batched`` and ``per_run``: how many of the computed runs took each path;
    ``where``: what ran the chunks and why (``where.mode``, ``where.reason``); ``notes``: why
    variants ran per run; ``warnings``: chunk files found unreadable (their variants were
    computed again).
    """

    out_dir: Path
    specs: list[Spec]
    design: list[dict]
    computed: int
    skipped: int
    wall_time_s: float
    paths: list[Path] = field(default_factory=list)
    workers: int = 1
    batched: int = 0
    per_run: int = 0
    where: Where | None = None
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    finished: int = 0
    failed: int = 0
    #: where the rows are: (varied keys, {chunk file: first design index}, {run id: design index})
    source: tuple = field(default=((), {}, {}), repr=False)
    _rows: list[dict] | None = field(default=None, repr=False)
    _columns: list[str] | None = field(default=None, repr=False)

    @property
    def total(self) -> int:
        return len(self.design)

    @property
    def complete(self) -> bool:
        return self.finished == len(self.design)

    @property
    def rows(self) -> list[dict]:
        if self._rows is None:
            summary = self.out_dir / "summary.parquet"
            if summary in self.paths and summary.is_file():  # the table as written
                import pyarrow.parquet as pq

                table = pq.read_table(summary)
                self._rows, self._columns = table.to_pylist(), table.column_names
            else:
                keys, files, index_of = self.source
                self._rows = list(summary_rows(list(keys), self.design, files, index_of))
        return self._rows

    @property
    def columns(self) -> list[str]:
        if self._columns is None:
            keys, files, _ = self.source
            self._columns = summary_columns(list(keys), files)[0]
        return self._columns

    def column(self, name: str) -> np.ndarray:
        """One column as an array (floats where possible; NaN where a run has no value)."""
        if name not in self.columns:
            raise InputError(f"no column '{name}' in the sweep table (columns: {', '.join(self.columns)})")
        summary = self.out_dir / "summary.parquet"
        if self._rows is not None:
            values = [r.get(name) for r in self._rows]
        elif summary in self.paths and summary.is_file():  # one column of the table as written
            import pyarrow.parquet as pq

            values = pq.read_table(summary, columns=[name]).column(name).to_pylist()
        else:  # streamed: one column in memory, not the table
            keys, files, index_of = self.source
            values = [r.get(name) for r in summary_rows(list(keys), self.design, files, index_of)]
        try:
            return np.array([np.nan if v is None else v for v in values], dtype=float)
        except (TypeError, ValueError):
            return np.array(values, dtype=object)

    def to_pandas(self):
        import pandas as pd

        return pd.DataFrame(self.rows, columns=self.columns)


def sweep(
    scene_path,
    vary: Sequence[str] = (),
    *,
    design_file=None,
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
    batch: bool = True,
    chunk_size: int | None = None,
) -> SweepResult:
    """Run the scene at every point of the design given by ``vary`` (``KEY=SPEC`` strings)
    and/or the rows of ``design_file`` (CSV or Parquet, one column per scene key).

    ``scheduler``: None or "auto" (in this process or a local Dask cluster, by the estimated
    work: see constrained.sweep_execute), "sequential" (this process), "local" (a local Dask
    cluster of ``workers`` processes, default one per core), a ``tcp://HOST:PORT`` address,
    or a ``distributed.Client``.
    ``summary``: ``[REDUCTION:]NAME=FORMULA`` columns (formulas in t, x_NAME, vx_NAME, ...
    and the scene's parameters; reductions final, max, min, max_abs, mean over the samples).
    ``limit``: compute at most this many missing runs, then stop (the rest stay missing).
    ``plot``: the column the figure shows (default: the first summary, else the position
    coordinate that varies most across the runs, see ``plot.default_column``);
    ``boundary``: a formula in the varied keys' last names and the parameters whose zero
    contour is drawn on a 2-D map. ``batch=False`` runs every variant on the per-run path;
    ``chunk_size``: variants per batched chunk (default ``sweep_execute.BATCH_CHUNK``).
    Bad input raises InputError (SceneError for the scene).
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
    for option, value, least in (("--chunk-size", chunk_size, 1), ("--workers", workers, 1),
                                 ("--limit", limit, 0), ("--samples", samples, 1)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < least):
            raise InputError(f"{option} must be a whole number >= {least}, got {value!r}"
                             + (" (0: compute none of the missing runs)" if option == "--limit" else ""))
    if not vary and design_file is None:
        raise InputError("give at least one --vary KEY=SPEC, or --design FILE")
    specs = [parse_vary(v) for v in vary]
    file_specs, file_rows = read_design_file(design_file) if design_file is not None else ([], None)
    points = design(specs, samples, seed, rows=file_rows)
    specs = file_specs + specs
    summaries = [parse_summary(s) for s in summary]
    names = [s.name for s in summaries]
    if len(set(names)) != len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise InputError(f"--summary: the name '{twice}' is used twice")
    _validate(scene_text, file, overrides, specs, points[0], summaries)
    out = Path(out_dir) if out_dir is not None else default_out_dir(path)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a directory")
    manifest = {
        "scene": file,
        "scene_sha256": hashlib.sha256(scene_bytes).hexdigest(),
        "overrides": overrides,
        "summaries": [s.text for s in summaries],
        "trajectories": bool(save_trajectories),
    }
    check_manifest(out, manifest)
    runs_dir, chunks_dir = out / "runs", out / "chunks"
    ids = [run_id(p) for p in points]
    if len(set(ids)) != len(ids):
        raise InputError("the design has repeated points (the same values twice); remove the duplicates")
    index_of = {rid: i for i, rid in enumerate(ids)}
    done, files, warnings = read_done(chunks_dir, index_of)  # {run id: ok}: no rows held
    legacy = read_legacy_records(runs_dir, [i for i in ids if i not in done])
    if legacy:  # an earlier version's records, written once as a chunk file of today's layout
        chunks_dir.mkdir(parents=True, exist_ok=True)
        files[write_chunk(chunks_dir, legacy, index_of, {"path": "per-run"})] = min(map(index_of.get, legacy))
        done.update({rid: rec["status"] == "ok" for rid, rec in legacy.items()})
        del legacy
    if save_trajectories:  # a run without its trajectory file is computed again
        done = {rid: ok for rid, ok in done.items() if not ok or (runs_dir / f"{rid}.npz").is_file()}
    todo = [i for i, rid in enumerate(ids) if rid not in done]
    if limit is not None:
        todo = todo[: max(int(limit), 0)]
    skipped = len(done)
    out.mkdir(parents=True, exist_ok=True)
    chunks_dir.mkdir(exist_ok=True)
    if save_trajectories:
        runs_dir.mkdir(exist_ok=True)
    record_of_sweep = {**manifest, "vary": list(vary), "samples": samples, "seed": seed,
                       "design_file": None if design_file is None else str(design_file)}
    write_json(out / "sweep.json", {**record_of_sweep, **_progress_record(done, len(ids))})
    base_raw = apply_overrides(load_raw(scene_text, file), overrides, file=file)
    keys = [s.key for s in specs]
    work = plan({"scene_text": scene_text, "file": file, "base_overrides": overrides, "summaries": summaries,
                 "save_trajectory": bool(save_trajectories)}, points, ids, todo,
                blocker=lambda shared: _blocker(base_raw, file, shared, save_trajectories, batch),
                batch_chunk=chunk_size, run_chunk=1 if scheduler == "sequential" else RUN_CHUNK)
    last_write = [time.monotonic()]

    def record(chunk: Chunk, result: dict) -> None:
        for rid, traj in result.get("trajectories", {}).items():
            traj.save(runs_dir / f"{rid}.npz")
        rows = result["rows"]
        if rows:
            for rec in rows.values():
                rec["row"]["path"] = chunk.path
            meta = {"path": chunk.path, "worker": result.get("worker"),
                    "wall_time_s": result.get("wall_time_s"), "evaluation": result.get("evaluation")}
            path = write_chunk(chunks_dir, rows, index_of, meta)
            files[path] = min(files.get(path, len(ids)), *(index_of[rid] for rid in rows))
            for rid, rec in rows.items():  # (the rows live in the chunk file from here on)
                done[rid] = rec["status"] == "ok"
        if result.get("interrupted"):
            raise KeyboardInterrupt
        if time.monotonic() - last_write[0] > SUMMARY_EVERY_S:
            write_tables()
            last_write[0] = time.monotonic()

    def write_tables() -> list[Path]:
        paths = write_table(out, keys, points, files, index_of, parquet=True)
        write_json(out / "sweep.json", {**record_of_sweep, **_progress_record(done, len(ids))})
        return paths

    try:
        where = execute(work.chunks, record, scheduler, progress=progress, workers=workers)
    except KeyboardInterrupt:  # the finished chunks are on disk; leave a table of them too, and say so
        if done:
            write_tables()
        raise SweepInterrupted(_interrupted_message(out, len(done), len(ids), bool(done))) from None
    except BaseException:
        if done:
            write_tables()
        raise
    paths = write_tables()
    result = SweepResult(out, specs, points, computed=len(todo), skipped=skipped,
                         wall_time_s=0.0, paths=paths, workers=where.workers, batched=work.count("batched"),
                         per_run=work.count("per-run"), where=where, notes=work.notes,
                         warnings=warnings, finished=len(done), failed=sum(not ok for ok in done.values()),
                         source=(tuple(keys), files, index_of))
    if figure and result.finished:
        try:
            fig = save_sweep_figure(result, out / "sweep.png", column=plot, boundary=boundary,
                                    scene_text=scene_text, file=file, overrides=overrides,
                                    summaries=[s.name for s in summaries])
        except ImportError:
            fig = None
        if fig is not None:
            paths.append(fig)
    result.wall_time_s = time.perf_counter() - started
    return result


class SweepInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped the sweep; the message says how many runs are in the table and how to go
    on. (A KeyboardInterrupt: callers that stop on Ctrl-C still do.)"""


def _progress_record(done: dict, total: int) -> dict:
    """What ``sweep.json`` says of the table beside it: how many runs it holds, of how many, and
    whether the sweep is complete — so a table left by an interrupted (or ``--limit``) call is
    marked as partial in the directory itself, not only in the message of the call."""
    return {"finished": len(done), "failed": sum(not ok for ok in done.values()), "total": total,
            "complete": len(done) == total}


def _interrupted_message(out: Path, finished: int, total: int, table: bool) -> str:
    if not table:
        return (f"sweep interrupted (Ctrl-C) before any of its {total} runs finished; nothing was kept. "
                "Run the same command again to compute them")
    return (f"sweep interrupted (Ctrl-C): {finished} of {total} runs are in {out / 'summary.csv'} "
            "(sweep.json: \"complete\": false); run the same command again to compute the rest")


def default_out_dir(scene_path: Path) -> Path:
    """``out/<scene file stem>_sweep``, without doubling the word: ``kapitza_sweep.toml`` →
    ``out/kapitza_sweep``, ``double_pendulum.toml`` → ``out/double_pendulum_sweep``."""
    stem = Path(scene_path).stem
    return Path("out") / ((re.sub(r"[_-]?sweep$", "", stem, flags=re.IGNORECASE) or stem) + "_sweep")


def _blocker(base_raw: dict, file: str, shared: list[str], save_trajectories: bool,
             batch: bool) -> tuple[str, object]:
    """(why the variants with these shared overrides cannot run batched or "", the scene's
    ``compiled`` setting)."""
    if not batch:
        return "asked for (--per-run)", False
    try:
        scene = build_scene(apply_overrides(base_raw, shared, file=file), path=file)
    except SceneError:
        return "the scene with these overrides does not build (each run reports why)", False
    return batch_blocker(scene, save_trajectories), scene.settings.get("compiled", "auto")


def _validate(scene_text: str, file: str, overrides: list[str], specs: list[Spec], first: dict,
              summaries: list[Summary]) -> None:
    """Apply the first point of the design to the scene and build it: bad keys fail here."""
    raw = load_raw(scene_text, file)
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
            raise SceneError(f"{spec.source}: the scene has no parameter '{tokens[1]}' "
                             f"(parameters: {known})",
                             file=file, key=spec.key)
        try:
            raw1 = apply_overrides(base, [f"{spec.key}={toml_value(first[spec.key])}"], file=file)
            build_scene(raw1, path=file)
        except SceneError as exc:
            raise SceneError(f"{spec.source}: {exc.reason}", file=file,
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
        from ..model.symbols import Symbols

        names = Symbols(scene.system).state_names
        for s in summaries:
            try:
                expressions.parse(s.formula, names, where=f"--summary {s.name}")
            except ExpressionError as exc:
                raise InputError(f"{exc} (names: t, x_P, y_P, z_P, vx_P, ... of the particles "
                                 f"{', '.join(scene.system.names)}, and the parameters)") from None
