"""How a sweep's variants run: grouped into chunks, in this process or on Dask.

**Groups.** Variants whose overrides differ only in the values of ``parameters.NAME`` (plain
numbers) share one structure: the scene after the other overrides is the same, and
``simulate_many`` takes the parameter values as columns. Such a group runs *batched*
(constrained.sweep_batch) unless its scene cannot (another method, [expect] checks,
one-sided constraints, events, saved trajectories: ``sweep_batch.batch_blocker``); then, and
for variants that change anything else (a mass or position given as a number, a
constraint, the method), each variant runs on its own (the *per-run* path,
constrained.sweep_run).

**Chunks.** A group is cut into chunks (``BATCH_CHUNK`` variants batched, ``RUN_CHUNK`` per
run); a chunk is one task, and its rows are written as one file when it finishes.

**Where.** ``scheduler``: ``"sequential"`` runs every chunk in this process; ``"local"`` a
``distributed.LocalCluster`` (one single-threaded worker process per core, 127.0.0.1, no
dashboard); ``"tcp://HOST:PORT"`` an existing Dask cluster; a ``distributed.Client`` is
used as it is. ``None`` (``"auto"``) decides by the estimated work: the first chunk of each
path runs in this process as a probe, its wall time per variant times the variants left is
the estimate, and only when that exceeds ``DASK_WORTH_S`` and the machine has at least two
idle cores (its core count minus the load average of other processes) does the rest go to a
local cluster, which costs 3–4 s to start and a model build per worker.
"""

from __future__ import annotations

import importlib.util
import math
import os
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from ..extras import install_hint
from ..run.ensemble import BLOCK, MIN_THREAD_COLUMNS
from ..threads import available_cores
from .batch import COMPILE_FROM
from .design import overrides_of

#: Variants per batched chunk (one simulate_many call, one file).
BATCH_CHUNK = 500
#: Variants per per-run chunk on Dask (in this process, with ``scheduler="sequential"``: one,
#: so each run's row is on disk as soon as it finishes).
RUN_CHUNK = 8
#: Estimated seconds of work left above which "auto" starts a local Dask cluster.
DASK_WORTH_S = 20.0
#: How to get Dask: the extra from the package index, or from a source checkout.
DASK_INSTALL_HINT = install_hint("dask")

_PARAMETER_KEY = re.compile(r"parameters\.([A-Za-z_]\w*)")


@dataclass
class Chunk:
    """One task: ``path`` "batched" or "per-run", the design ``indices``, and the task dict."""

    path: str
    indices: list[int]
    task: dict
    reason: str = ""


@dataclass
class Plan:
    chunks: list[Chunk]
    notes: list[str] = field(default_factory=list)

    def count(self, path: str) -> int:
        return sum(len(c.indices) for c in self.chunks if c.path == path)


def _split(point: dict) -> tuple[dict, dict]:
    """(parameter values that can be columns, the other overrides) of one variant."""
    params, other = {}, {}
    for key, value in point.items():
        m = _PARAMETER_KEY.fullmatch(key)
        numeric = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        if m and numeric:
            params[m.group(1)] = float(value)
        else:
            other[key] = value
    return params, other


def plan(base: dict, points: list[dict], ids: list[str], todo: list[int], *, blocker: Callable,
         batch_chunk: int | None = None, run_chunk: int | None = None) -> Plan:
    """Group and cut the variants ``todo`` (design indices) into chunks.

    ``base``: the task fields every chunk shares (scene text, file, --set overrides,
    summaries, save_trajectory); ``blocker(shared_overrides)`` gives (why the scene with those
    overrides cannot run batched, "" when it can; its ``compiled`` setting). With "auto" a
    batched group is compiled when it has at least ``COMPILE_FROM`` variants."""
    batch_chunk = batch_chunk or BATCH_CHUNK
    run_chunk = run_chunk or RUN_CHUNK
    groups: dict[tuple, list[int]] = {}
    shared_of: dict[tuple, list[str]] = {}
    values: dict[int, dict] = {}
    for i in todo:
        params, other = _split(points[i])
        key = (tuple(overrides_of(other)), tuple(params))
        groups.setdefault(key, []).append(i)
        shared_of[key] = list(key[0])
        values[i] = params
    chunks: list[Chunk] = []
    notes: list[str] = []
    for key, members in groups.items():
        shared = shared_of[key]
        reason, compiled = ("the variant changes no [parameters] value", False) if not key[1] \
            else blocker(shared)
        if compiled not in (True, False):
            compiled = len(members) >= COMPILE_FROM
        if reason:
            for start in range(0, len(members), run_chunk):
                part = members[start:start + run_chunk]
                chunks.append(Chunk("per-run", part, {
                    **base, "variants": [(i, ids[i], overrides_of(points[i])) for i in part]}, reason))
            continue
        names = key[1]
        for start in range(0, len(members), batch_chunk):
            part = members[start:start + batch_chunk]
            table = {n: [values[i][n] for i in part] for n in names}
            chunks.append(Chunk("batched", part, {
                **base, "shared": shared, "table": table, "compiled": compiled,
                "variants": [(i, ids[i], None) for i in part]}))
    reasons = sorted({c.reason for c in chunks if c.path == "per-run"})
    if reasons:
        notes.append("per-run path: " + "; ".join(reasons))
    return Plan(chunks, notes)


def run_chunk(task: dict) -> dict:
    """Run one chunk (on a worker or here): batched or per run, by ``task["path"]``."""
    if task.get("path") == "batched":
        from .batch import run_batch

        return run_batch(task)
    from .per_run import run_variants

    return run_variants(task)


# --- where the chunks run --------------------------------------------------------------------


@dataclass
class Where:
    """What ran the chunks: ``mode`` ("in-process", "local cluster", "cluster"), ``workers``
    and ``reason`` (for the output)."""

    mode: str
    workers: int
    reason: str


def execute(chunks: list[Chunk], record: Callable[[Chunk, dict], None], scheduler, *,
            progress: bool, workers: int | None) -> Where:
    """Run the chunks; ``record(chunk, result)`` in this process as each finishes (it raises
    KeyboardInterrupt for a chunk stopped by Ctrl-C, after keeping its finished rows)."""
    total = sum(len(c.indices) for c in chunks)
    bar = _Progress(total, progress)
    try:
        if scheduler == "sequential":
            _in_process(chunks, record, bar)
            return Where("in-process", 1, "--scheduler sequential")
        if scheduler is None or scheduler == "auto":
            return _auto(chunks, record, bar, workers)
        client, close = _client(scheduler, workers)
        try:
            n = len(client.scheduler_info().get("workers", {}))
            _on_dask(client, chunks, record, bar)
            mode = "local cluster" if scheduler == "local" else "cluster"
            return Where(mode, n, "--scheduler local" if scheduler == "local" else "the given scheduler")
        finally:
            close()
    finally:
        bar.close()


def _in_process(chunks, record, bar) -> None:
    for chunk in chunks:
        result = run_chunk({**chunk.task, "path": chunk.path})
        record(chunk, result)
        bar.update(len(chunk.indices))


def _auto(chunks: list[Chunk], record, bar, workers: int | None) -> Where:
    """Probe the first chunk of each path here, then decide where the rest goes."""
    cost: dict[str, float] = {}
    rest = []
    for chunk in chunks:
        if chunk.path in cost:
            rest.append(chunk)
            continue
        started = time.perf_counter()
        result = run_chunk({**chunk.task, "path": chunk.path})
        cost[chunk.path] = (time.perf_counter() - started) / max(1, len(chunk.indices))
        record(chunk, result)
        bar.update(len(chunk.indices))
    left = sum(cost[c.path] * len(c.indices) for c in rest)
    # a batched chunk here shares its columns out over this machine's cores itself
    # (simulate_many's threads): worker processes on the same cores would not run it faster
    spread = sum(cost[c.path] * len(c.indices) for c in rest if not _uses_the_cores(c))
    cores = workers or os.cpu_count() or 1
    idle = _idle_cores()
    per = ", ".join(f"{cost[p] * 1e3:.2f} ms per variant {p}" for p in cost)
    estimate = (f"about {left:.1f} s of work left after the first chunk ({per}, including the model's "
                "assembly and any compile)")
    if not chunks:
        return Where("in-process", 1, "nothing left to compute")
    if not rest:
        return Where("in-process", 1, f"the first chunk of each path held the whole design ({per})")
    if spread <= DASK_WORTH_S or cores < 2 or idle < 2:
        _in_process(rest, record, bar)
        if cores < 2:
            why = f"{estimate}; one worker"
        elif spread < left and spread <= DASK_WORTH_S:
            why = (f"{estimate}: batched chunks share their variants out over this machine's "
                   f"{available_cores()} cores themselves (simulate_many's threads), so worker "
                   "processes would not run them faster")
        elif left <= DASK_WORTH_S:
            why = (f"{estimate}: below {DASK_WORTH_S:.0f} s a local Dask cluster (3-4 s to start, a model "
                   "build per worker) does not pay")
        else:
            why = (f"{estimate}, but other processes keep the machine busy (about {idle:.1f} of "
                   f"{os.cpu_count()} cores idle): more worker processes would not run faster")
        return Where("in-process", 1, why)
    if importlib.util.find_spec("distributed") is None:  # no Dask: go on here, and say how to get it
        _in_process(rest, record, bar)
        return Where("in-process", 1, f"{estimate}, but Dask is not installed: {DASK_INSTALL_HINT}")
    client, close = _client("local", workers)
    try:
        _on_dask(client, rest, record, bar)
        return Where("local cluster", cores, f"{estimate}: above {DASK_WORTH_S:.0f} s")
    finally:
        close()


def _uses_the_cores(chunk: Chunk) -> bool:
    """Whether the chunk's simulate_many call gets a thread per core (its threads: one per
    MIN_THREAD_COLUMNS of its variants in a block, at most the cores)."""
    width = min(len(chunk.indices), BLOCK)
    return chunk.path == "batched" and width // MIN_THREAD_COLUMNS >= available_cores()


def _idle_cores() -> float:
    """Cores not busy with other processes: the core count minus the 1-minute load average,
    plus the one this sweep itself keeps busy (the core count where that is unknown)."""
    n = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):
        return float(n)
    return max(1.0, min(float(n), n - load + 1.0))


def _client(scheduler, workers: int | None):
    """(client, close) for "local", an address or a Client; InputError for a bad address."""
    from ..errors import InputError

    try:
        import distributed
    except ImportError:
        raise InputError(f"Dask is not installed: {DASK_INSTALL_HINT}, or use --scheduler "
                         "sequential") from None
    if scheduler == "local":
        n = workers or os.cpu_count() or 1
        # no dashboard: dashboard_address=None alone still serves HTTP on :8787 (and warns when
        # that port is taken); a free loopback port, and dashboard=False serves no pages on it
        cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                           dashboard_address="127.0.0.1:0", host="127.0.0.1",
                                           scheduler_kwargs={"dashboard": False})
        client = distributed.Client(cluster)

        def close():
            client.close()
            cluster.close()

        return client, close
    if isinstance(scheduler, str):
        if not re.fullmatch(r"(tcp|tls|inproc|ucx)://\S+", scheduler):
            raise InputError(f"--scheduler {scheduler!r}: expected tcp://HOST:PORT, 'local' or 'sequential'")
        try:
            client = distributed.Client(scheduler, timeout=20)
        except (OSError, TimeoutError) as exc:
            raise InputError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({exc})") from None
        return client, client.close
    return scheduler, lambda: None


def _on_dask(client, chunks: list[Chunk], record, bar) -> None:
    import distributed

    if not chunks:
        return
    # one thread per task: a worker per core is the parallelism there (in this process the
    # batched call shares its columns out over the cores itself)
    futures = [client.submit(run_chunk, {**c.task, "path": c.path, "threads": 1}, pure=False) for c in chunks]
    chunk_of = {f.key: c for f, c in zip(futures, chunks, strict=True)}
    try:
        for fut in distributed.as_completed(futures):
            chunk = chunk_of[fut.key]
            try:
                result = fut.result()
            except Exception as exc:  # the task itself died (worker lost): its variants fail
                from .per_run import message

                status = f"worker failure: {message(exc)}"
                failed = {rid: {"status": status, "row": {}} for _, rid, _ in chunk.task["variants"]}
                result = {"rows": failed, "trajectories": {}, "interrupted": False, "wall_time_s": math.nan,
                          "worker": "?"}
            record(chunk, result)
            fut.release()
            bar.update(len(chunk.indices))
    except BaseException:
        client.cancel(futures)
        raise


class _Progress:
    """A tqdm bar on stderr when tqdm is installed, else a line every 10 % (off when quiet)."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.n, self.bar = total, 0, None
        self.enabled = enabled and total > 0
        self.step = 0
        if self.enabled:
            try:
                from tqdm import tqdm

                self.bar = tqdm(total=total, desc="sweep", unit="run", file=sys.stderr)
            except ImportError:
                self.bar = None

    def update(self, n: int = 1) -> None:
        self.n += n
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(n)
        elif self.n == self.total or self.n // max(1, self.total // 10) > self.step:
            self.step = self.n // max(1, self.total // 10)
            print(f"sweep: {self.n}/{self.total} runs", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
