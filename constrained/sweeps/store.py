"""What a sweep leaves in its directory, and how a rerun finds what is done.

- ``DIR/chunks/<chunk_id>.parquet``: the rows of one finished chunk (``run``, ``run_id``,
  ``status``, the metric columns), written atomically (a temporary file renamed into
  place) as the chunk finishes; the schema's metadata ``constrained`` holds the chunk's
  path (batched / per-run), worker and wall time. Without pyarrow: ``<chunk_id>.json``.
- ``DIR/summary.csv`` (and ``summary.parquet``): every finished variant in design order,
  assembled from the chunk files.
- ``DIR/sweep.json``: what the sweep is (scene hash, ``--set`` overrides, summaries); a
  sweep into a DIR made by a different one is refused.

Resume is per variant: a rerun reads every chunk file and skips the variants (run ids)
found in them, whatever chunk they were in. A chunk file that cannot be read (truncated,
not Parquet, wrong columns) is removed and its variants computed again. Records of older
versions (``DIR/runs/<run_id>.json``) count as done too.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..run.trajectory import atomic_write

#: The columns saying what ran (last in the table): method (with its base tableau), tolerances,
#: fixed step (empty when adaptive) and the path (batched / per-run).
SOLVER_COLUMNS = ("method", "rtol", "atol", "dt", "path")
#: The metadata key of a chunk file's schema.
META_KEY = b"constrained"


def have_pyarrow() -> bool:
    try:
        import pyarrow  # noqa: F401
        import pyarrow.parquet  # noqa: F401
    except ImportError:
        return False
    return True


def chunk_id(run_ids: list[str]) -> str:
    """A chunk's file name: a hash of its variants' run ids (16 hex digits)."""
    return hashlib.sha256("\n".join(run_ids).encode("ascii")).hexdigest()[:16]


def check_manifest(out: Path, manifest: dict) -> None:
    """Refuse a DIR whose sweep.json describes another sweep (InputError)."""
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


def write_json(path: Path, data: dict) -> None:
    text = json.dumps(data, indent=1, default=_json_default)
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return repr(value)


# --- chunk files -----------------------------------------------------------------------------


def write_chunk(directory: Path, rows: dict[str, dict], index_of: dict[str, int], meta: dict) -> Path:
    """One chunk's rows ({run_id: {"status", "row"}}) as ``directory/<chunk_id>.parquet``."""
    ids = sorted(rows, key=index_of.__getitem__)
    name = chunk_id(ids)
    records = [{"run": index_of[rid], "run_id": rid, "status": rows[rid]["status"], **rows[rid]["row"]}
               for rid in ids]
    if not have_pyarrow():
        path = directory / f"{name}.json"
        write_json(path, {"meta": meta, "rows": records})
        return path
    import pyarrow.parquet as pq

    table = _arrow_table(records, _columns(records))
    table = table.replace_schema_metadata({META_KEY: json.dumps(meta, default=_json_default).encode()})
    path = directory / f"{name}.parquet"
    atomic_write(path, lambda f: pq.write_table(table, f))
    return path


def read_chunks(directory: Path, wanted: set[str]) -> tuple[dict[str, dict], list[str]]:
    """({run_id: {"status", "row", "meta"}} of the variants in ``wanted`` found in the chunk
    files, [notes on files that could not be read and were removed])."""
    done: dict[str, dict] = {}
    notes: list[str] = []
    if not directory.is_dir():
        return done, notes
    for path in sorted(directory.iterdir()):
        if path.name.startswith(".") or path.suffix not in (".parquet", ".json"):
            continue
        try:
            meta, records = _read_chunk(path)
        except Exception as exc:  # any reader error: the chunk is computed again
            notes.append(f"{path} could not be read ({' '.join(str(exc).split())[:120]}); its variants "
                         "are computed again")
            path.unlink(missing_ok=True)
            continue
        for rec in records:
            rid = rec.pop("run_id")
            status = rec.pop("status")
            rec.pop("run", None)
            if rid in wanted:
                done[rid] = {"status": status, "row": rec,
                             "meta": meta}
    return done, notes


def _read_chunk(path: Path) -> tuple[dict, list[dict]]:
    if path.suffix == ".json":
        data = json.loads(path.read_text())
        meta, records = data["meta"], data["rows"]
    else:
        import pyarrow.parquet as pq

        table = pq.read_table(path)
        raw = (table.schema.metadata or {}).get(META_KEY)
        meta = json.loads(raw) if raw else {}
        records = table.to_pylist()
    if not isinstance(records, list) or not all(
            isinstance(r, dict) and isinstance(r.get("run_id"), str) and isinstance(r.get("status"), str)
            for r in records):
        raise ValueError("no run_id and status columns")
    return meta, records


def read_legacy_records(runs_dir: Path, ids: list[str]) -> dict[str, dict]:
    """Finished runs recorded by older versions as ``runs/<run_id>.json``."""
    done: dict[str, dict] = {}
    if not runs_dir.is_dir():
        return done
    for rid in ids:
        path = runs_dir / f"{rid}.json"
        if not path.is_file():
            continue
        try:
            rec = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(rec, dict) and "row" in rec and "status" in rec and not unfinished(rec):
            done[rid] = {"status": rec["status"], "row": rec["row"], "meta": {"path": "per-run"}}
    return done


def unfinished(record: dict) -> bool:
    """Whether a record is of a run stopped by Ctrl-C (earlier versions recorded those as
    failed runs): it has no result, so it is not kept and a rerun computes it."""
    status = str(record.get("status", ""))
    return (status.startswith("interrupted") or "the run was interrupted" in status
            or "KeyboardInterrupt" in status)


# --- the summary table -----------------------------------------------------------------------


def table(keys: list[str], points: list[dict], ids: list[str], done: dict,
          consume: bool = False) -> tuple[list[dict], list[str]]:
    """(rows in design order of the variants in ``done``, columns); ``consume``: take the
    records out of ``done`` as they go into rows (not both held at once)."""
    rows, metric_cols = [], []
    seen = set()
    for i, rid in enumerate(ids):
        rec = done.pop(rid, None) if consume else done.get(rid)
        if rec is None:
            continue
        row = {"run": i, "run_id": rid}
        for k in keys:
            row[k] = points[i][k]
        row["status"] = rec["status"]
        values = rec["row"]
        for c in values:
            if c not in seen:
                seen.add(c)
                metric_cols.append(c)
        row.update(values)
        rows.append(row)
    last = [c for c in SOLVER_COLUMNS if c in seen]
    metric_cols = [c for c in metric_cols if c not in SOLVER_COLUMNS] + last
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


def _columns(rows: list[dict]) -> list[str]:
    seen: dict[str, None] = {}
    for r in rows:
        for c in r:
            seen.setdefault(c, None)
    return list(seen)


def _arrow_table(rows: list[dict], columns: list[str]):
    """A pyarrow Table: numbers as float64 (int64 when all are whole), text as strings,
    lists as JSON text, missing values as nulls."""
    import pyarrow as pa

    data: dict[str, Any] = {}
    for c in columns:
        vals = [r.get(c) for r in rows]
        present = [v for v in vals if v is not None]
        if any(isinstance(v, list | dict) for v in present):
            vals = [None if v is None else json.dumps(v) for v in vals]
        elif present and all(isinstance(v, int | float) and not isinstance(v, bool) for v in present) \
                and any(isinstance(v, float) for v in present):
            vals = [None if v is None else float(v) for v in vals]
        data[c] = vals
    try:
        return pa.table(data)
    except (pa.ArrowInvalid, pa.ArrowTypeError):
        return pa.table({c: [None if v is None else _cell(v) for v in vs] for c, vs in data.items()})


def write_table(out: Path, keys: list[str], points, ids, done, *, parquet: bool,
                rows_columns: tuple[list[dict], list[str]] | None = None) -> list[Path]:
    """``out/summary.csv`` (and ``summary.parquet``) of the variants in ``done``, atomically
    (``rows_columns``: ``table(...)`` when the caller has it already)."""
    rows, columns = rows_columns or table(keys, points, ids, done)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in columns])
    text = buf.getvalue()
    path = out / "summary.csv"
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))
    written = [path]
    if parquet and have_pyarrow():
        import pyarrow.parquet as pq

        arrow = _arrow_table(rows, columns)
        ppath = out / "summary.parquet"
        atomic_write(ppath, lambda f: pq.write_table(arrow, f))
        written.append(ppath)
    return written
