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

Memory stays flat in the number of variants: a sweep holds, per variant, its design point
and whether it is done and ok (``read_done``); the rows themselves live in the chunk files
and are streamed from them in design order (``records``: a file is read when the order
reaches its first variant, so only the files whose variants interleave are held at once)
into the summary files and, when asked, into ``SweepResult.rows``.
"""

from __future__ import annotations

import csv
import hashlib
import heapq
import io
import json
from collections.abc import Iterator
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


def chunk_files(directory: Path) -> list[Path]:
    """The chunk files of ``directory`` (not temporaries), sorted."""
    if not directory.is_dir():
        return []
    return [p for p in sorted(directory.iterdir())
            if not p.name.startswith(".") and p.suffix in (".parquet", ".json")]


def read_done(directory: Path, index_of: dict[str, int]
              ) -> tuple[dict[str, bool], dict[Path, int], list[str]]:
    """``(done, files, notes)``: {run_id: its status is ok} of the design's variants (the keys of
    ``index_of``) found in the chunk files, {chunk file: the design index of its first such
    variant}, and notes on files that could not be read (removed: their variants are computed
    again). Only the run_id and status columns are read."""
    done: dict[str, bool] = {}
    files: dict[Path, int] = {}
    notes: list[str] = []
    for path in chunk_files(directory):
        try:
            ids, statuses = _read_ids(path)
        except Exception as exc:  # any reader error: the chunk is computed again
            notes.append(f"{path} could not be read ({' '.join(str(exc).split())[:120]}); its variants "
                         "are computed again")
            path.unlink(missing_ok=True)
            continue
        first = [index_of[rid] for rid in ids if rid in index_of]
        if first:
            files[path] = min(first)
        for rid, status in zip(ids, statuses, strict=True):
            if rid in index_of:
                done[rid] = status == "ok"
    return done, files, notes


def _read_ids(path: Path) -> tuple[list[str], list[str]]:
    if path.suffix == ".json":
        _, records = _read_chunk(path)
        return [r["run_id"] for r in records], [r["status"] for r in records]
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(path, columns=["run_id", "status"])
    if not all(pa.types.is_string(table.schema.field(c).type) or pa.types.is_large_string(
            table.schema.field(c).type) for c in ("run_id", "status")) or table.column("run_id").null_count \
            or table.column("status").null_count:
        raise ValueError("no run_id and status columns")
    return table.column("run_id").to_pylist(), table.column("status").to_pylist()


def records(files: dict[Path, int], index_of: dict[str, int]) -> Iterator[tuple[int, dict]]:
    """``(design index, {"run_id", "status", metric columns...})`` of every variant of the design
    found in ``files`` (from ``read_done``), once each, in design order. Each file's rows are
    in design order (``write_chunk``); the files are merged as a sweep line over their first
    variants, so a file is read when the order reaches it and dropped when it is done."""
    pending = sorted(files.items(), key=lambda item: (item[1], str(item[0])))
    heap: list = []
    k, last, serial = 0, -1, 0
    while k < len(pending) or heap:
        if k < len(pending) and (not heap or pending[k][1] <= heap[0][0]):
            path = pending[k][0]
            k += 1
            try:
                _, rows = _read_chunk(path)
            except Exception:  # noqa: BLE001 - gone or damaged since it was read: its variants are missing
                continue
            ordered = iter(sorted((index_of[r["run_id"]], n, r) for n, r in enumerate(rows)
                                  if r.get("run_id") in index_of))
            serial = _push(heap, ordered, serial)
            continue
        index, _, row, ordered = heapq.heappop(heap)
        serial = _push(heap, ordered, serial)
        if index == last:  # a variant in two files (a chunk written twice): the first one read
            continue
        last = index
        row.pop("run", None)
        yield index, row


def _push(heap: list, ordered, serial: int) -> int:
    item = next(ordered, None)
    if item is not None:
        index, _, row = item
        heapq.heappush(heap, (index, serial, row, ordered))
    return serial + 1


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


def summary_rows(keys: list[str], points: list[dict], files: dict[Path, int],
                 index_of: dict[str, int]) -> Iterator[dict]:
    """The summary's rows in design order, streamed from the chunk files: ``run``, ``run_id``,
    the varied keys, ``status``, then the run's metric columns."""
    for i, rec in records(files, index_of):
        row = {"run": i, "run_id": rec.pop("run_id")}
        for k in keys:
            row[k] = points[i][k]
        row["status"] = rec.pop("status")
        row.update(rec)
        yield row


def summary_columns(keys: list[str], files: dict[Path, int]) -> tuple[list[str], dict[str, str]]:
    """``(columns, kinds)``: the summary's columns (the metrics in order of first appearance over
    the files in design order, the solver's columns last) and each metric's kind ("str",
    "float", "int", "bool" or "null", unified over the files), read from the files' schemas."""
    seen: dict[str, set] = {}
    for path, _ in sorted(files.items(), key=lambda item: (item[1], str(item[0]))):
        try:
            kinds = _file_kinds(path)
        except Exception:  # noqa: BLE001 - damaged since: its rows are not read either
            continue
        for name, kind in kinds.items():
            seen.setdefault(name, set()).add(kind)
    metrics = [c for c in seen if c not in ("run", "run_id", "status", *keys)]
    last = [c for c in SOLVER_COLUMNS if c in seen]
    metrics = [c for c in metrics if c not in SOLVER_COLUMNS] + last
    return ["run", "run_id", *keys, "status", *metrics], {name: _unify(seen[name]) for name in metrics}


def _unify(kinds: set) -> str:
    """One column type for the kinds a column has in several files (ints and floats: float)."""
    kinds = kinds - {"null"}
    if not kinds:
        return "null"
    if kinds <= {"int", "float"}:
        return "float" if "float" in kinds else "int"
    return "bool" if kinds == {"bool"} else "str"


def _file_kinds(path: Path) -> dict[str, str]:
    if path.suffix == ".json":
        _, rows = _read_chunk(path)
        columns = _columns(rows)
        return {c: _kind([r.get(c) for r in rows]) for c in columns}
    import pyarrow as pa
    import pyarrow.parquet as pq

    kinds = {}
    for field_ in pq.read_schema(path):
        t = field_.type
        kinds[field_.name] = ("null" if pa.types.is_null(t) else "bool" if pa.types.is_boolean(t) else
                              "int" if pa.types.is_integer(t) else
                              "float" if pa.types.is_floating(t) else "str")
    return kinds


def _kind(values: list) -> str:
    present = [v for v in values if v is not None]
    if not present:
        return "null"
    if all(isinstance(v, bool) for v in present):
        return "bool"
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in present):
        return "float" if any(isinstance(v, float) for v in present) else "int"
    return "str"


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


#: Rows converted and written at a time (the summary files are written in such batches).
WRITE_BATCH = 256


def write_table(out: Path, keys: list[str], points: list[dict], files: dict[Path, int],
                index_of: dict[str, int], *, parquet: bool) -> list[Path]:
    """``out/summary.csv`` (and ``summary.parquet``) of the variants found in ``files``, in design
    order, each atomically; streamed: WRITE_BATCH rows in memory at a time.

    The files beside it never describe other rows than the new csv: the earlier call's
    ``summary.parquet`` and ``sweep.png`` are removed before the csv is replaced (the parquet is
    written again after it, the figure when the sweep ends). A sweep interrupted after its
    periodic rewrite used to leave a new csv beside the parquet and figure of an earlier call."""
    for stale in (out / "sweep.png", out / "summary.parquet"):
        stale.unlink(missing_ok=True)
    columns, kinds = summary_columns(keys, files)
    for k in keys:
        kinds[k] = _kind([p.get(k) for p in points[:1000]])
    kinds.update(run="int", run_id="str", status="str")
    arrow = parquet and have_pyarrow()
    path, ppath = out / "summary.csv", out / "summary.parquet"
    written = [path] + ([ppath] if arrow else [])

    def write_csv(f) -> None:
        text = io.TextIOWrapper(f, encoding="utf-8", newline="")
        w = csv.writer(text, lineterminator="\n")
        w.writerow(columns)
        for r in summary_rows(keys, points, files, index_of):
            w.writerow([_cell(r.get(c)) for c in columns])
        text.flush()
        text.detach()

    atomic_write(path, write_csv)
    if arrow:
        import pyarrow as pa
        import pyarrow.parquet as pq

        types = {"str": pa.string(), "float": pa.float64(), "int": pa.int64(), "bool": pa.bool_(),
                 "null": pa.null()}
        schema = pa.schema([(c, types[kinds.get(c, "str")]) for c in columns])

        def write_parquet(f) -> None:
            with pq.ParquetWriter(f, schema) as writer:
                batch: list[dict] = []
                for r in summary_rows(keys, points, files, index_of):
                    batch.append(r)
                    if len(batch) == WRITE_BATCH:
                        writer.write_table(_typed_table(batch, schema))
                        batch = []
                if batch or not columns:
                    writer.write_table(_typed_table(batch, schema))

        atomic_write(ppath, write_parquet)
    return written


def _typed_table(rows: list[dict], schema):
    """The rows as a pyarrow Table of ``schema`` (values converted to its column types)."""
    import pyarrow as pa

    data = {}
    for field_ in schema:
        values = [r.get(field_.name) for r in rows]
        t = field_.type
        if pa.types.is_null(t):
            values = [None] * len(rows)
        elif pa.types.is_string(t):
            values = [None if v is None else v if isinstance(v, str) else _cell(v) for v in values]
        elif pa.types.is_floating(t):
            values = [_float_or_none(v) for v in values]
        elif pa.types.is_integer(t):
            values = [None if v is None else int(v) for v in values]
        data[field_.name] = values
    return pa.table(data, schema=schema)


def _float_or_none(v):
    try:
        return None if v is None else float(v)
    except (TypeError, ValueError):
        return None
